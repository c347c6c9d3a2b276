"""Composite view-synthesis models: scene representation + pose vectors -> images (section 3.6).

Two kinds, matching the authors' four settings (the authors' code):

  GQNSynthesis    GQN rooms: the scene code comes from an encoder over context views and their
                  pose vectors (summed over views), decoded with AdaIN for every query pose.
  TableSynthesis  ShapeNet car, Gibson rooms, 7-Scenes: a learned unit-norm vector per scene
                  (and, for Gibson / 7-Scenes, per-scene instance-norm tables in the decoder),
                  concatenated with the pose vectors and decoded.

Both take pose vectors already computed by `camrep.pose` (the pose system is a separate parameter
group, trained with its own optimiser), and return (images in [-1, 1], aux).

Mixed precision (`model.dtype`): `dtype` is the dtype of the encoder's and decoder's
computation (bfloat16 on a GPU); parameters are float32 whatever it is, so the optimiser state is
too, and the images come out in float32, so the losses are float32 sums. Scene codes, AdaIN
tables and pose vectors stay float32.
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from camrep.models.decoder import ResAdaINDecoder, UpConvDecoder
from camrep.models.encoder import SceneEncoder
from camrep.models.layers import SceneTable

Array = jax.Array


class GQNSynthesis(nn.Module):
  """Encoder over context views + residual AdaIN decoder (the authors' code).

  Attributes:
    width: channel multiplier (1.0 = paper width).
    gamma_offset: added to the encoder's AdaIN gammas in the decoder (0 as the authors; see
      `ResAdaINDecoder`).
    dtype: dtype of the computation (None: float32; "bfloat16" with `model.dtype`).
  """

  width: float = 1.0
  gamma_offset: float = 0.0
  dtype: Any = None

  @nn.compact
  def __call__(
    self, context_images: Array, context_vecs: Array, query_vecs: Array
  ) -> tuple[Array, dict]:
    """Synthesises the query views of each scene.

    Args:
      context_images: (S, C, 64, 64, 3) in [-1, 1].
      context_vecs: (S, C, P) pose vectors of the context views.
      query_vecs: (S, Q, P) pose vectors of the query views.

    Returns:
      images (S, Q, 64, 64, 3) in [-1, 1] (float32), and aux with the scene code and decoder
      styles.
    """
    encoder = SceneEncoder(width=self.width, dtype=self.dtype, name="encoder")
    scene, enc_aux = encoder(context_images, context_vecs)
    images, dec_aux = ResAdaINDecoder(
      width=self.width, gamma_offset=self.gamma_offset, dtype=self.dtype, name="decoder"
    )(scene, query_vecs)
    return images, {"scene": scene, "decoder": dec_aux}


class TableSynthesis(nn.Module):
  """Per-scene code u (unit norm) and pose vectors -> image (the authors' code).

  Attributes:
    num_scenes: size of the per-scene tables (training scenes).
    scene_dim: size of u (car 128, Gibson 768, 7-Scenes 96).
    width: channel multiplier of the decoder.
    image_size: 128 (paper) or 64.
    per_scene_norm: per-scene instance-norm tables in the decoder (Gibson, 7-Scenes).
    norm_eps: added to |u| before normalising (7-Scenes: 1e-6).
    gamma_init_one: decoder tables' gamma initialised at 1 instead of ~0 (camrep option).
    dtype: dtype of the decoder's computation (None: float32; "bfloat16" with `model.dtype`).
  """

  num_scenes: int
  scene_dim: int = 128
  width: float = 1.0
  image_size: int = 128
  per_scene_norm: bool = False
  norm_eps: float = 0.0
  gamma_init_one: bool = False
  dtype: Any = None

  @nn.compact
  def __call__(self, scene_ids: Array, vecs: Array) -> tuple[Array, dict]:
    """Synthesises views of the given scenes.

    Args:
      scene_ids: (S,) int scene indices into the tables.
      vecs: (S, V, P) pose vectors.

    Returns:
      images (S, V, H, W, 3) in [-1, 1] (float32), and aux.
    """
    table = SceneTable(self.num_scenes, self.scene_dim, norm_eps=self.norm_eps, name="scene")
    u, _ = table(scene_ids)  # (S, du)
    S, V = vecs.shape[:2]
    z = jnp.concatenate([jnp.broadcast_to(u[:, None], (S, V, u.shape[-1])), vecs], axis=-1)
    decoder = UpConvDecoder(
      width=self.width,
      image_size=self.image_size,
      per_scene_norm=self.per_scene_norm,
      num_scenes=self.num_scenes if self.per_scene_norm else 0,
      gamma_init_one=self.gamma_init_one,
      dtype=self.dtype,
      name="decoder",
    )
    index = jnp.broadcast_to(scene_ids[:, None], (S, V)) if self.per_scene_norm else None
    images, aux = decoder(z, index)
    return images, {"scene": u, "decoder": aux}

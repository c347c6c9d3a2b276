"""Decoders (generators) of the view-synthesis model (the authors' code).

Two architectures, both ending in tanh (images in [-1, 1]) and upsampling by nearest-neighbour x2:

`ResAdaINDecoder` (GQN rooms, 64 x 64, the authors'). Input z = [u (128) || pose vector] per query
view; the scene's u and AdaIN parameters come from `SceneEncoder` and are broadcast over the
scene's query views. Channel counts at width 1.0:

  fc      dense -> 4 x 4 x 256 (no activation)
  res8    h = up(x); main: lrelu -> conv3 256 -> lrelu -> conv3 256 -> AdaIN(gamma8, beta8)
          -> lrelu; skip: conv1 256 on h; sum                                  -> 8 x 8 x 256
  res16   h = up(x); main: conv3 256 -> lrelu -> conv3 256 -> AdaIN(gamma16, beta16) -> lrelu;
          skip: conv1 256; sum                                                 -> 16 x 16 x 256
  res32   h = up(x); main: conv3 128 -> lrelu -> conv3 128 -> lrelu; skip: conv1 128; sum
  res64   h = up(x); main: conv3 64 -> lrelu -> conv3 3; skip: conv1 3; sum; tanh -> 64 x 64 x 3

`UpConvDecoder` (ShapeNet car; Gibson rooms and 7-Scenes; as the authors'). Input
[u || pose vectors]; u comes from a `SceneTable` owned by the training code. At width 1.0:

  fc      dense 4096, lrelu, reshape                                           -> 4 x 4 x 256
  conv8   convT 4x4 s2 256 [-> IN(gamma8, beta8)] -> lrelu                     -> 8 x 8 x 256
  conv16  up; conv4 256 [-> IN(gamma16, beta16)] -> lrelu; + up(x) (residual)  -> 16 x 16 x 256
  conv32  up; conv4 128 [-> IN(gamma32, beta32)] -> lrelu                      -> 32 x 32 x 128
  conv64  up; conv4 64 [-> IN(gamma64, beta64)] -> lrelu                       -> 64 x 64 x 64
  to_rgb  up; conv4 3; tanh                                                    -> 128 x 128 x 3

The bracketed instance norms exist only with `per_scene_norm=True` (Gibson, 7-Scenes), whose
gamma / beta come from per-scene tables looked up by scene index. The authors call them gamma2,
gamma4, gamma6, gamma8 (layer numbers); here they are named by resolution (gamma8 ... gamma64),
like the GQN decoder's. `image_size=64` drops conv64 for quick runs.

The authors' stride-1 `conv2d_transpose` layers are implemented as plain convs (see
`layers.conv`); the stride-2 one is a `ConvTranspose`.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from camrep.models import layers

Array = jax.Array

GQN_STYLE_KEYS = ("gamma8", "beta8", "gamma16", "beta16")


class ResAdaINDecoder(nn.Module):
  """GQN-rooms decoder with AdaIN at 8 x 8 and 16 x 16 (the authors' code).

  Attributes:
    width: channel multiplier (paper: 1.0); the AdaIN parameters must have 256 * width channels.
    gamma_offset: added to the encoder's gamma8 / gamma16 before AdaIN. 0 as the authors (gamma
      starts as a small random head output, so the AdaIN branches start nearly silent); 1 is a
      camrep option (`model.gamma_init_one`): the heads learn gamma - 1, so the normalised
      branches pass signal from the first step.
    dtype: dtype of the computation (e.g. bfloat16, `model.dtype`); None: float32. Parameters
      are float32 either way, and the images come out in float32 (tanh taken in float32).
  """

  width: float = 1.0
  gamma_offset: float = 0.0
  dtype: Any = None

  @nn.compact
  def __call__(self, scene: Mapping[str, Array], poses: Array) -> tuple[Array, dict]:
    """Renders query views of a batch of scenes.

    Args:
      scene: the encoder's output: "u" (scenes, u_dim) and "gamma8", "beta8", "gamma16",
        "beta16" (scenes, 256 * width). Other keys are ignored.
      poses: (scenes, queries, pose_dim) query pose vectors.

    Returns:
      images: (scenes, queries, 64, 64, 3) in [-1, 1], float32 (whatever `dtype`).
      aux: {"style": {name: (scenes, C)} the AdaIN parameters used,
            "rms": {block name: () activation RMS}}.
    """
    if poses.ndim != 3:
      raise ValueError(f"expected poses (scenes, queries, pose_dim), got {poses.shape}")
    s, q = poses.shape[:2]
    c256 = layers.scaled(256, self.width)
    c128 = layers.scaled(128, self.width)
    c64 = layers.scaled(64, self.width)
    u = scene["u"]
    if u.shape[0] != s:
      raise ValueError(f"u has {u.shape[0]} scenes, poses {s}")
    for k in GQN_STYLE_KEYS:
      layers.check_channels(k, scene[k].shape, c256)

    def per_query(a: Array) -> Array:
      """(S, C) -> (S * Q, C): broadcast a scene quantity over the scene's queries."""
      return jnp.broadcast_to(a[:, None, :], (s, q, a.shape[-1])).reshape((s * q, a.shape[-1]))

    z = jnp.concatenate([per_query(u), poses.reshape((s * q, -1)).astype(u.dtype)], axis=-1)
    style = {k: per_query(scene[k]) for k in GQN_STYLE_KEYS}
    if self.gamma_offset:
      style = {k: v + self.gamma_offset if k.startswith("gamma") else v for k, v in style.items()}
    acts = {}

    x = layers.dense(4 * 4 * c256, name="fc", dtype=self.dtype)(z).reshape((s * q, 4, 4, c256))
    acts["fc"] = x

    # Each block upsamples x2 (nearest) before its first conv and its 1x1 skip conv; the convs
    # of upsampled inputs are `layers.UpConv`s (computed at the low resolution).
    up = functools.partial(layers.conv, dtype=self.dtype, kind=layers.UpConv)
    conv = functools.partial(layers.conv, dtype=self.dtype)
    a = up(c256, 3, name="res8_conv_a")(layers.lrelu(x))  # lrelu commutes with upsampling
    a = conv(c256, 3, name="res8_conv_b")(layers.lrelu(a))
    a = layers.lrelu(layers.adain(a, style["gamma8"], style["beta8"]))
    x = a + up(c256, 1, name="res8_skip")(x)
    acts["res8"] = x

    a = up(c256, 3, name="res16_conv_a")(x)
    a = conv(c256, 3, name="res16_conv_b")(layers.lrelu(a))
    a = layers.lrelu(layers.adain(a, style["gamma16"], style["beta16"]))
    x = a + up(c256, 1, name="res16_skip")(x)
    acts["res16"] = x

    a = up(c128, 3, name="res32_conv_a")(x)
    a = layers.lrelu(conv(c128, 3, name="res32_conv_b")(layers.lrelu(a)))
    x = a + up(c128, 1, name="res32_skip")(x)
    acts["res32"] = x

    a = up(c64, 3, name="res64_conv_a")(x)
    a = conv(3, 3, name="res64_conv_b")(layers.lrelu(a))
    x = a + up(3, 1, name="res64_skip")(x)
    acts["res64"] = x

    for k, v in acts.items():
      self.sow("intermediates", f"{k}_out", v)
    images = jnp.tanh(layers.at_least_f32(x)).reshape((s, q, *x.shape[1:]))
    aux = {
      "style": {k: scene[k] for k in GQN_STYLE_KEYS},
      "rms": {k: layers.rms(v) for k, v in acts.items()},
    }
    return images, aux


class UpConvDecoder(nn.Module):
  """Car / Gibson / 7-Scenes decoder (the authors' code), optionally with per-scene AdaIN tables.

  Attributes:
    width: channel multiplier (paper: 1.0).
    image_size: 128 (paper) or 64 (quick runs: drops the 64-channel up-block).
    per_scene_norm: insert instance norms with per-scene gamma / beta tables (Gibson,
      7-Scenes); False for the car model.
    num_scenes: rows of the per-scene tables (Gibson: number of areas, 20 in the paper;
      7-Scenes: 7). Unused without `per_scene_norm`.
    table_init_stddev: the tables are initialised N(0, stddev^2), 0.001 as the authors, so
      gamma is ~0 at the start and every normalised output starts near beta ~ 0 (only the
      16 x 16 residual path carries signal at first).
    gamma_init_one: camrep improvement candidate, off by default for fidelity: initialise the
      gamma tables at 1 + N(0, stddev^2) so that the normalised layers pass signal from the
      first step.
    dtype: dtype of the computation (e.g. bfloat16, `model.dtype`); None: float32. Parameters
      (tables included) are float32 either way; the images come out in float32.
  """

  width: float = 1.0
  image_size: int = 128
  per_scene_norm: bool = False
  num_scenes: int = 0
  table_init_stddev: float = 1e-3
  gamma_init_one: bool = False
  dtype: Any = None

  def _style(self, name: str, channels: int, scene_index: Array) -> tuple[Array, Array]:
    """Per-scene (gamma, beta) rows for one layer: (..., channels) each."""
    normal = nn.initializers.normal(stddev=self.table_init_stddev)
    if self.gamma_init_one:

      def gamma_init(key, shape, dtype=jnp.float32):
        return 1.0 + normal(key, shape, dtype)

    else:
      gamma_init = normal
    gamma = self.param(f"gamma{name}", gamma_init, (self.num_scenes, channels))
    beta = self.param(f"beta{name}", normal, (self.num_scenes, channels))
    return jnp.take(gamma, scene_index, axis=0), jnp.take(beta, scene_index, axis=0)

  @nn.compact
  def __call__(self, z: Array, scene_index: Array | None = None) -> tuple[Array, dict]:
    """Renders images from [u || pose vectors].

    Args:
      z: (..., in_dim) concatenated scene code and pose vectors (car: 128 + 96 + 96 = 320;
        Gibson: 768 + 96 + 96 = 960; 7-Scenes: 96 + 6 * 32 = 288).
      scene_index: (...) integer scene index of each row, required with `per_scene_norm`.

    Returns:
      images: (..., image_size, image_size, 3) in [-1, 1], float32 (whatever `dtype`).
      aux: {"style": {"gamma8": (..., C), "beta8": ..., ...} the looked-up AdaIN parameters
            (empty without `per_scene_norm`), "rms": {layer name: () activation RMS}}.
    """
    if self.image_size not in (64, 128):
      raise ValueError(f"image_size must be 64 or 128, got {self.image_size}")
    if self.per_scene_norm:
      if scene_index is None:
        raise ValueError("per_scene_norm needs scene_index")
      if self.num_scenes < 1:
        raise ValueError("per_scene_norm needs num_scenes >= 1")
      if scene_index.shape != z.shape[:-1]:
        raise ValueError(f"scene_index {scene_index.shape} must match z {z.shape[:-1]}")
    lead = z.shape[:-1]
    z = z.reshape((-1, z.shape[-1]))
    idx = None if scene_index is None else scene_index.reshape((-1,))
    c256 = layers.scaled(256, self.width)
    widths = {"8": c256, "16": c256, "32": layers.scaled(128, self.width)}
    if self.image_size == 128:
      widths["64"] = layers.scaled(64, self.width)
    style, acts = {}, {}

    def norm_act(x: Array, name: str) -> Array:
      if self.per_scene_norm:
        gamma, beta = self._style(name, x.shape[-1], idx)
        style[f"gamma{name}"], style[f"beta{name}"] = gamma, beta
        x = layers.adain(x, gamma, beta)
      return layers.lrelu(x)

    x = layers.lrelu(layers.dense(4 * 4 * c256, name="fc", dtype=self.dtype)(z)).reshape(
      (-1, 4, 4, c256)
    )
    acts["fc"] = x
    x = norm_act(layers.conv_transpose(c256, 4, strides=2, name="conv8", dtype=self.dtype)(x), "8")
    acts["conv8"] = x
    # conv{16,32,64} and to_rgb convolve x upsampled x2 (nearest): `layers.UpConv`s.
    up = functools.partial(layers.conv, dtype=self.dtype, kind=layers.UpConv)
    for name in list(widths)[1:]:
      y = norm_act(up(widths[name], 4, name=f"conv{name}")(x), name)
      x = y + layers.upsample2(x) if name == "16" else y
      acts[f"conv{name}"] = x
    x = up(3, 4, name="to_rgb")(x)
    acts["to_rgb"] = x

    for k, v in acts.items():
      self.sow("intermediates", f"{k}_out", v)
    images = jnp.tanh(layers.at_least_f32(x)).reshape((*lead, *x.shape[1:]))
    aux = {
      "style": {k: v.reshape((*lead, v.shape[-1])) for k, v in style.items()},
      "rms": {k: layers.rms(v) for k, v in acts.items()},
    }
    return images, aux


# Paper-size variants.
GQNDecoder = functools.partial(ResAdaINDecoder, width=1.0)
CarDecoder = functools.partial(UpConvDecoder, width=1.0, image_size=128, per_scene_norm=False)
GibsonDecoder = functools.partial(
  UpConvDecoder, width=1.0, image_size=128, per_scene_norm=True, num_scenes=20
)
SevenScenesDecoder = functools.partial(
  UpConvDecoder, width=1.0, image_size=128, per_scene_norm=True, num_scenes=7
)
CarSceneTable = functools.partial(layers.SceneTable, num_scenes=2151, dim=128)
GibsonSceneTable = functools.partial(layers.SceneTable, num_scenes=20, dim=768)
SevenScenesSceneTable = functools.partial(layers.SceneTable, num_scenes=7, dim=96, norm_eps=1e-6)

# Tiny variants for tests.
GQNDecoderTiny = functools.partial(ResAdaINDecoder, width=1 / 16)
CarDecoderTiny = functools.partial(UpConvDecoder, width=1 / 16, image_size=64, per_scene_norm=False)
GibsonDecoderTiny = functools.partial(
  UpConvDecoder, width=1 / 16, image_size=64, per_scene_norm=True, num_scenes=3
)

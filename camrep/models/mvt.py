"""A small decoder-only multi-view transformer for novel-view synthesis (LVSM-style: Jin et al.,
"LVSM: A Large View Synthesis Model with Minimal 3D Inductive Bias", ICLR 2025).

For every query view of a scene, one token sequence holds the C context views' patch tokens and
the query view's patch tokens:

  context token  Dense([p x p pixels, camera features]) + e_patch
  query token    Dense([camera features]) + e_patch, or a learned constant + e_patch when the
                 conditioning has no token features (relative encodings, the no-camera control)

(e_patch a learned embedding of the patch position, shared by all views). A plain pre-norm
transformer (`Block`: x + Attn(LN x), x + MLP(LN x)) runs full self-attention over the sequence;
relative conditionings act inside every attention layer (`relative_attention`, eqs. R1-R2), each
token carrying its view's camera. The query tokens' outputs are decoded to p x p x 3 pixels
(LN, Dense, tanh) and put back together: images in [-1, 1].

Camera conditioning comes as `camera_conditioning.ViewCodes` computed outside the module, so the
module's parameters are the transformer's only ("model") and a learned pose system stays a
separate pytree ("rep"), as with camrep's other synthesis models. `PosedMVT` ties a module to a
conditioning: init / apply / loss on (context images, context poses, query poses).

Sizes: `MVTQuick` (64 x 64 images, patch 8, width 128, 4 layers, 4 heads: trains on CPU cores in
minutes), `MVTMedium` (width 384, 8 layers, 6 heads: one GPU), `MVTTiny` (tests).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from camrep.models import relative_attention
from camrep.models.camera_conditioning import (
  CameraConditioning,
  PatchGrid,
  ViewCodes,
  patchify,
  unpatchify,
)
from camrep.models.relative_attention import ViewTransform

Array = jax.Array
Params = dict

dense_init = nn.initializers.xavier_uniform()


class Block(nn.Module):
  """Pre-norm transformer block with (optionally relative) multi-head self-attention.

  Attributes:
    width: token width.
    heads: attention heads (width / heads features each).
    mlp_ratio: hidden width of the MLP over `width`.
    rope_base: frequency base of the patch RoPE of relative encodings.
    dtype: dtype of the computation (None: float32).
  """

  width: int
  heads: int
  mlp_ratio: float = 4.0
  rope_base: float = relative_attention.ROPE_BASE
  dtype: Any = None

  @nn.compact
  def __call__(self, x: Array, codes: ViewCodes, grid: PatchGrid) -> Array:
    """x (B, V, N, width) -> (B, V, N, width); codes.transform (B, V, k, b, b) or None."""
    if self.width % self.heads:
      raise ValueError(f"width {self.width} is not a multiple of heads {self.heads}")
    hd = self.width // self.heads
    dense = functools.partial(nn.Dense, kernel_init=dense_init, dtype=self.dtype)
    h = nn.LayerNorm(dtype=self.dtype, name="norm1")(x)
    qkv = dense(3 * self.width, name="qkv")(h).reshape(*x.shape[:-1], 3, self.heads, hd)
    q, k, v = qkv[..., 0, :, :], qkv[..., 1, :, :], qkv[..., 2, :, :]
    if codes.transform is None:
      o = _plain_attention(q, k, v)
    else:
      o = relative_attention.attention(
        q, k, v, codes.transform, grid=grid.shape, base=self.rope_base, values=codes.values
      )
    x = x + dense(self.width, name="proj")(o.reshape(x.shape))
    h = nn.LayerNorm(dtype=self.dtype, name="norm2")(x)
    h = dense(int(self.mlp_ratio * self.width), name="mlp_in")(h)
    return x + dense(self.width, name="mlp_out")(nn.gelu(h))


def _plain_attention(q: Array, k: Array, v: Array) -> Array:
  """Softmax attention over all V N tokens: (B, V, N, heads, h) each."""
  B, V, N, H, hd = q.shape
  qf, kf, vf = (x.reshape(B, V * N, H, hd) for x in (q, k, v))
  logits = jnp.einsum("bthd,bshd->bhts", qf, kf) / jnp.sqrt(jnp.asarray(hd, q.dtype))
  a = jax.nn.softmax(logits.astype(jnp.float32), axis=-1).astype(v.dtype)
  return jnp.einsum("bhts,bshd->bthd", a, vf).reshape(q.shape)


class MultiViewTransformer(nn.Module):
  """Decoder-only multi-view transformer (module docstring).

  Attributes:
    patch: patch side p in pixels.
    width: token width.
    depth: transformer blocks.
    heads: attention heads.
    mlp_ratio: MLP hidden width over `width`.
    rope_base: frequency base of the patch RoPE of relative encodings.
    dtype: dtype of the computation (None: float32); parameters are float32.
  """

  patch: int = 8
  width: int = 128
  depth: int = 4
  heads: int = 4
  mlp_ratio: float = 4.0
  rope_base: float = relative_attention.ROPE_BASE
  dtype: Any = None

  @nn.compact
  def __call__(
    self, context_images: Array, context_codes: ViewCodes, query_codes: ViewCodes
  ) -> tuple[Array, dict]:
    """Synthesises the query views of each scene.

    Args:
      context_images: (S, C, H, W, 3) in [-1, 1].
      context_codes: camera codes of the context views, leading axes (S, C).
      query_codes: camera codes of the query views, leading axes (S, Q); of the same
        conditioning as `context_codes`.

    Returns:
      images (S, Q, H, W, 3) in [-1, 1] (float32), and aux {"query_tokens": (S, Q, N, width)}.
    """
    S, C, H, W, _ = context_images.shape
    grid = PatchGrid(H, W, self.patch)
    Q = _num_views(query_codes)
    if Q is None:
      raise ValueError(
        "query_codes carry neither features nor a transform (a conditioning without camera "
        "information gives zero-width features)"
      )
    dense = functools.partial(nn.Dense, self.width, kernel_init=dense_init, dtype=self.dtype)

    ctx = patchify(context_images, grid)  # (S, C, N, 3 p^2)
    if context_codes.features is not None:
      ctx = jnp.concatenate([ctx, context_codes.features.astype(ctx.dtype)], axis=-1)
    ctx = dense(name="context_embed")(ctx)
    if query_codes.features is not None and query_codes.features.shape[-1]:
      tgt = dense(name="query_embed")(query_codes.features)
    else:
      token = self.param("query_token", nn.initializers.normal(0.02), (self.width,))
      tgt = jnp.broadcast_to(token, (S, Q, grid.n, self.width))
    e_patch = self.param("patch_embed", nn.initializers.normal(0.02), (grid.n, self.width))
    ctx, tgt = ctx + e_patch, tgt + e_patch

    # One sequence per (scene, query view): the C context views then the query view.
    x = jnp.concatenate(
      [jnp.broadcast_to(ctx[:, None], (S, Q, C, grid.n, self.width)), tgt[:, :, None]], axis=2
    ).reshape(S * Q, C + 1, grid.n, self.width)
    codes = ViewCodes(values=query_codes.values)
    if query_codes.transform is not None:
      t = ViewTransform.concat_views(
        [
          jax.tree.map(lambda a: a[:, None], context_codes.transform),
          jax.tree.map(lambda a: a[:, :, None], query_codes.transform),
        ]
      )
      codes = ViewCodes(
        transform=jax.tree.map(lambda a: a.reshape(S * Q, *a.shape[2:]), t),
        values=query_codes.values,
      )
    for i in range(self.depth):
      x = Block(
        self.width, self.heads, self.mlp_ratio, self.rope_base, self.dtype, name=f"block{i}"
      )(x, codes, grid)
    out = nn.LayerNorm(dtype=self.dtype, name="norm_out")(x[:, -1])
    pix = nn.Dense(3 * self.patch**2, kernel_init=dense_init, dtype=self.dtype, name="to_pixels")(
      out
    )
    images = jnp.tanh(pix.astype(jnp.float32))
    images = unpatchify(images, grid).reshape(S, Q, H, W, 3)
    return images, {"query_tokens": out.reshape(S, Q, grid.n, self.width)}


def _num_views(codes: ViewCodes) -> int | None:
  if codes.features is not None:
    return codes.features.shape[1]
  if codes.transform is not None:
    return codes.transform.D.shape[1]
  return None


MVTQuick = functools.partial(MultiViewTransformer, patch=8, width=128, depth=4, heads=4)
MVTMedium = functools.partial(MultiViewTransformer, patch=8, width=384, depth=8, heads=6)
MVTTiny = functools.partial(MultiViewTransformer, patch=4, width=32, depth=1, heads=2)

SIZES = {"tiny": MVTTiny, "quick": MVTQuick, "medium": MVTMedium}
"""The sizes by name (a run's `config.model.size`)."""


@dataclasses.dataclass(frozen=True)
class PosedMVT:
  """A `MultiViewTransformer` fed by a `CameraConditioning`: (context images, context poses,
  query poses) -> query images. Parameters {"model": the module's, "rep": the conditioning's
  ({} for fixed encodings)}.

  Attributes:
    module: the transformer.
    conditioning: the camera conditioning.
  """

  module: MultiViewTransformer
  conditioning: CameraConditioning

  def codes(
    self, params_rep: Params, context_poses: Array, query_poses: Array, grid: PatchGrid
  ) -> tuple[ViewCodes, ViewCodes]:
    """Camera codes of the context (S, C, P) and query (S, Q, P) poses."""
    c = self.conditioning.view_codes(params_rep, context_poses, grid)
    return c, self.conditioning.view_codes(params_rep, query_poses, grid)

  def grid(self, images: Array) -> PatchGrid:
    return PatchGrid(images.shape[-3], images.shape[-2], self.module.patch)

  def init(
    self, key: Array, context_images: Array, context_poses: Array, query_poses: Array
  ) -> Params:
    """Initial {"model", "rep"} shaped from example inputs (see `apply`)."""
    k_model, k_rep = jax.random.split(key)
    rep = self.conditioning.init(k_rep)
    c, q = self.codes(rep, context_poses, query_poses, self.grid(context_images))
    variables = self.module.init(k_model, context_images, c, q)
    return {"model": variables["params"], "rep": rep}

  def apply(
    self, params: Params, context_images: Array, context_poses: Array, query_poses: Array
  ) -> tuple[Array, dict]:
    """Query images (S, Q, H, W, 3) in [-1, 1] and aux.

    Args:
      params: {"model", "rep"}.
      context_images: (S, C, H, W, 3) in [-1, 1].
      context_poses: (S, C, P) pose columns of the setting.
      query_poses: (S, Q, P).
    """
    c, q = self.codes(params["rep"], context_poses, query_poses, self.grid(context_images))
    return self.module.apply({"params": params["model"]}, context_images, c, q)

  def loss(
    self, params: Params, key: Array, batch: Mapping[str, Array]
  ) -> tuple[Array, dict[str, Array]]:
    """L_rec (eq. 9: mean over query images of the sum over pixels of squared errors) plus the
    conditioning's own loss (the rotation loss of the learned encodings, when weighted).

    Args:
      params: {"model", "rep"}.
      key: PRNG key of the rotation loss's pose pairs.
      batch: {"context_image" (S, C, H, W, 3) in [-1, 1], "context_pose" (S, C, P),
        "target_image" (S, Q, H, W, 3), "target_pose" (S, Q, P)} (the held-out batch layout).

    Returns:
      (total, {"rec", "mse", and the conditioning's terms}); "mse" is per pixel and channel.
    """
    pred, _ = self.apply(
      params, batch["context_image"], batch["context_pose"], batch["target_pose"]
    )
    err = (pred - batch["target_image"]) ** 2
    rec = jnp.mean(jnp.sum(err, axis=(-3, -2, -1)))
    pose_loss, terms = self.conditioning.pose_loss(key, params["rep"])
    return rec + pose_loss, {"rec": rec, "mse": jnp.mean(err), **terms}

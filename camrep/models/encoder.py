"""GQN-rooms scene encoder (the authors' code).

Each context image of a scene is encoded together with its pose vector; the per-view head
outputs (the scene vector u and the AdaIN parameters of the decoder) are SUMMED over the context
views of the scene (not averaged, and u is not normalised: the authors' code).

Trunk, for a 64 x 64 x 3 image in [-1, 1] (ReLU everywhere; channel counts at width 1.0):

  conv1   conv 2x2 s2, 256                                    -> 32 x 32 x 256
  block2  [conv 3x3 128 + conv 1x1 128], ReLU                 -> 32 x 32 x 128
  conv3   conv 2x2 s2, 256; concat tiled pose vector          -> 16 x 16 x (256 + pose_dim)
  block4  [conv 3x3 128 + conv 1x1 128], ReLU                 -> 16 x 16 x 128
  conv5   conv 3x3, 256                                       -> 16 x 16 x 256   ("h5")
  conv6   conv 2x2 s2, 256; block7 [3x3 128 + 1x1 128]        -> 8 x 8 x 128     ("h7")
  conv8   conv 2x2 s2, 256; block9 [3x3 128 + 1x1 128]        -> 4 x 4 x 128     ("h9")

Heads (no activation): conv 3x3 on a named trunk feature, then global average pooling. The
generator's heads (`GQN_GENERATOR_HEADS`) are u (128, from h9), gamma8 / beta8 (256, from h7)
and gamma16 / beta16 (256, from h5). The head list is a field so that the pose-regression
encoder of the authors' code (AdaIN parameters only, gamma16 / beta16 of 128 channels) is the same
module with other heads.

Our reading: step 1 lists no activation; "ReLU everywhere unless stated" is applied,
so conv1 is followed by ReLU.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from camrep.models import layers

Array = jax.Array


class Head(NamedTuple):
  """One output head: conv 3x3 + global average pool on a trunk feature.

  Attributes:
    name: output key, also the parameter scope "head_<name>".
    source: trunk feature it reads: "h5" (16 x 16), "h7" (8 x 8) or "h9" (4 x 4).
    channels: output size at width 1.0.
    scaled: whether `channels` follows the width multiplier (True for AdaIN parameters, which
      must match the decoder's channels; False for the scene vector u).
  """

  name: str
  source: str
  channels: int
  scaled: bool


GQN_GENERATOR_HEADS: tuple[Head, ...] = (
  Head("u", "h9", 128, False),
  Head("gamma8", "h7", 256, True),
  Head("beta8", "h7", 256, True),
  Head("gamma16", "h5", 256, True),
  Head("beta16", "h5", 256, True),
)

SOURCES = ("h5", "h7", "h9")


class SceneEncoder(nn.Module):
  """GQN-rooms context encoder with heads summed over context views.

  Attributes:
    width: channel multiplier of the trunk and of the `scaled` heads (paper: 1.0).
    heads: the output heads (default: the generator's u, gamma8, beta8, gamma16, beta16).
    trunk_channels: channels of the strided and h5 convs at width 1.0 (paper 256).
    block_channels: channels of the [3x3 + 1x1] blocks at width 1.0 (paper 128).
    dtype: dtype of the computation (e.g. bfloat16, `model.dtype`); None: float32 (Flax infers
      it from the float32 parameters). Parameters are float32 either way, and the heads' outputs
      are summed over views in float32 and returned in float32.
  """

  width: float = 1.0
  heads: tuple[Head, ...] = GQN_GENERATOR_HEADS
  trunk_channels: int = 256
  block_channels: int = 128
  dtype: Any = None

  def _block(self, x: Array, name: str, tiled: Array | None = None) -> Array:
    """[conv 3x3 + conv 1x1] summed, then ReLU; with `tiled` (N, P), over x concatenated with
    `tiled` broadcast to every pixel (`layers.ConcatConstantConv`)."""
    c = layers.scaled(self.block_channels, self.width)
    kw = dict(dtype=self.dtype)
    if tiled is None:
      a = layers.conv(c, 3, name=f"{name}_conv3", **kw)(x)
      b = layers.conv(c, 1, name=f"{name}_conv1", **kw)(x)
    else:
      kw["kind"] = layers.ConcatConstantConv
      a = layers.conv(c, 3, name=f"{name}_conv3", **kw)(x, tiled)
      b = layers.conv(c, 1, name=f"{name}_conv1", **kw)(x, tiled)
    return nn.relu(a + b)

  @nn.compact
  def __call__(self, images: Array, poses: Array) -> tuple[dict[str, Array], dict]:
    """Encodes the context views of a batch of scenes.

    Args:
      images: (scenes, views, H, W, 3) context images in [-1, 1]; H and W divisible by 16
        (64 in the paper).
      poses: (scenes, views, pose_dim) pose vectors of the context images (the concatenated
        per-DOF vectors, e.g. [v_view (96) || v_loc (96)] = 192 for GQN rooms).

    Returns:
      out: {head.name: (scenes, channels)} summed over views; for the default heads
        u (scenes, 128), gamma8 / beta8 / gamma16 / beta16 (scenes, 256 * width).
      aux: {"per_view": {head.name: (scenes, views, channels)},
            "rms": {feature name: () activation RMS}}.
    """
    if images.ndim != 5 or poses.ndim != 3 or images.shape[:2] != poses.shape[:2]:
      raise ValueError(
        f"expected images (S, V, H, W, 3) and poses (S, V, P), got {images.shape} {poses.shape}"
      )
    s, v = images.shape[:2]
    x = images.reshape((s * v, *images.shape[2:]))
    p = poses.reshape((s * v, poses.shape[-1]))
    tc = layers.scaled(self.trunk_channels, self.width)

    x = nn.relu(layers.conv(tc, 2, strides=2, name="conv1", dtype=self.dtype)(x))
    x = self._block(x, "block2")
    x = nn.relu(layers.conv(tc, 2, strides=2, name="conv3", dtype=self.dtype)(x))
    x = self._block(x, "block4", tiled=p)  # the pose vector tiled over the 16 x 16 map
    h5 = nn.relu(layers.conv(tc, 3, name="conv5", dtype=self.dtype)(x))
    x = nn.relu(layers.conv(tc, 2, strides=2, name="conv6", dtype=self.dtype)(h5))
    h7 = self._block(x, "block7")
    x = nn.relu(layers.conv(tc, 2, strides=2, name="conv8", dtype=self.dtype)(h7))
    h9 = self._block(x, "block9")
    feats = {"h5": h5, "h7": h7, "h9": h9}
    for k, f in feats.items():
      self.sow("intermediates", k, f)

    out, per_view = {}, {}
    for head in self.heads:
      if head.source not in feats:
        raise ValueError(f"head {head.name}: unknown source {head.source!r}, not in {SOURCES}")
      c = layers.scaled(head.channels, self.width) if head.scaled else head.channels
      pooled = layers.conv(c, 3, name=f"head_{head.name}", dtype=self.dtype, kind=layers.ConvMean)
      y = pooled(feats[head.source]).reshape((s, v, c))  # conv 3x3 then the mean over (H, W)
      per_view[head.name] = y
      out[head.name] = jnp.sum(y, axis=1)
    aux = {"per_view": per_view, "rms": {k: layers.rms(f) for k, f in feats.items()}}
    return out, aux


# Size variants.
GQNEncoder = functools.partial(SceneEncoder, width=1.0)
GQNEncoderTiny = functools.partial(SceneEncoder, width=1 / 16)

"""Pose regressors: images -> pose heads (paper section 4.4; the authors' code).

Every regressor ends in `PoseHeads`: an optional extra dense layer (the baselines' parameter-count
equaliser, the authors' code: 196 units for GQN, 256 car, 192 Gibson) and one dense layer per
`HeadSpec`, normalised as the targets are (`normalise_head`: learned
position vectors block-normalised to 1 / n_blocks per block, angle vectors unit length, baselines
raw). All modules share one call signature and return `(heads, aux)`:

  module.apply(variables, images, scene=..., context_images=..., context_poses=..., train=...)

Channel counts below are at width 1.0 (`layers.scaled(c, width)` otherwise).

`GQNRegressor` (the authors' code), 64 x 64 query images, AdaIN parameters from its own context
encoder (`SceneEncoder` with heads gamma16 / beta16 (128, from h5), gamma8 / beta8 (256, h7),
gamma4 / beta4 (256, h9), summed over the scene's context views):

  conv1  conv 4x4 s2 64, lrelu                           -> 32 x 32 x 64
  conv2  conv 4x4 s2 128, AdaIN(gamma16, beta16), lrelu  -> 16 x 16 x 128
  conv3  conv 4x4 s2 256, AdaIN(gamma8, beta8), lrelu    -> 8 x 8 x 256
  conv4  conv 4x4 s2 256, AdaIN(gamma4, beta4), lrelu    -> 4 x 4 x 256; flatten 4096; heads

`CarRegressor` (authors'): conv 4x4 s2 64, 64, 128, 128, 256, each + lrelu; 128 -> 4 x 4 x 256;
flatten; heads.

`GibsonRegressor` (authors'): conv 4x4 s2 64, 128, 256, 256, 256, each followed by a per-area
instance norm with learned tables gamma_k, beta_k (num_scenes, C) initialised N(0, 0.001^2) and
lrelu; flatten; heads.

`ResNetRegressor` (the authors' code, the MapNet-based 7-Scenes model): torchvision ResNet-34 trunk
(basic blocks [3, 4, 6, 3], batch norm), global average pool, fc 512 -> 2048 + ReLU, heads
(six 32-d unit heads for ours, or position / orientation heads); new layers Kaiming-normal with
zero bias. `load_torchvision_resnet34` loads ImageNet weights saved from torchvision.

Layer conventions follow `layers` (TF 'SAME' padding, glorot, lrelu 0.2) for the TF models; the
ResNet follows torchvision (explicit symmetric padding, no conv bias, BN eps 1e-5).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from camrep.models import layers
from camrep.models.encoder import Head, SceneEncoder
from camrep.pose_encodings import GROUPS as GROUPS
from camrep.pose_encodings import HeadSpec as HeadSpec

Array = jax.Array

GQN_REGRESSION_HEADS: tuple[Head, ...] = (
  Head("gamma16", "h5", 128, True),
  Head("beta16", "h5", 128, True),
  Head("gamma8", "h7", 256, True),
  Head("beta8", "h7", 256, True),
  Head("gamma4", "h9", 256, True),
  Head("beta4", "h9", 256, True),
)
"""Encoder heads of the GQN regressor (the authors' code): AdaIN parameters only."""

# torch.nn.init.kaiming_normal_ (fan_in, gain sqrt(2), untruncated normal): MapNet's new layers.
kaiming_normal = nn.initializers.variance_scaling(2.0, "fan_in", "normal")
# torchvision ResNet convs: kaiming_normal_(mode="fan_out", nonlinearity="relu").
_resnet_conv_init = nn.initializers.variance_scaling(2.0, "fan_out", "normal")


class PoseHeads(nn.Module):
  """Optional extra dense layer, then one dense + normalisation per head.

  Attributes:
    heads: the head specs (`camrep.pose_encodings.PoseEncoding.heads`).
    extra_fc: units of the extra layer (followed by lrelu), or None.
    kernel_init: kernel initialiser of the dense layers (glorot for the TF models).
    extra_fc_match: with `extra_fc`, size the extra layer by the feature size F instead: the
      units e that make these heads' parameters (F e + e + e o + o, o the heads' total size)
      equal those of one dense layer from F to `extra_fc_match` outputs (F m + m: the heads of
      "ours"), so that a baseline has as many parameters as ours at any width. None: `extra_fc`
      units as given (the paper's fixed 196 / 256 / 192).
  """

  heads: tuple[HeadSpec, ...]
  extra_fc: int | None = None
  extra_fc_match: int | None = None
  kernel_init: Callable = layers.kernel_init

  @nn.compact
  def __call__(self, x: Array) -> dict[str, Array]:
    """(..., F) features -> {head.name: (..., head.size)}."""
    dense = lambda n, name: nn.Dense(
      n, kernel_init=self.kernel_init, bias_init=layers.bias_init, name=name
    )
    if self.extra_fc:
      units = self.extra_fc
      if self.extra_fc_match:
        f, o, m = x.shape[-1], sum(h.size for h in self.heads), self.extra_fc_match
        units = max(1, round((f * m + m - o) / (f + 1 + o)))
      x = layers.lrelu(dense(units, "extra_fc")(x))
    return {h.name: normalise_head(dense(h.size, f"head_{h.name}")(x), h) for h in self.heads}


def _flatten_images(images: Array) -> tuple[Array, tuple[int, ...]]:
  if images.ndim < 4 or images.shape[-1] != 3:
    raise ValueError(f"images must be (..., H, W, 3), got {images.shape}")
  return layers.flatten_leading(images, 3)


class GQNRegressor(nn.Module):
  """GQN-rooms regressor with AdaIN parameters from a context encoder (the authors' code).

  Attributes:
    heads: output heads.
    width: channel multiplier (paper 1.0).
    extra_fc: baselines' extra dense layer, or None.
    extra_fc_match: size the extra layer to match this head size's parameters (`PoseHeads`).
  """

  heads: tuple[HeadSpec, ...]
  width: float = 1.0
  extra_fc: int | None = None
  extra_fc_match: int | None = None

  @nn.compact
  def __call__(
    self,
    images: Array,
    *,
    scene: Array | None = None,
    context_images: Array | None = None,
    context_poses: Array | None = None,
    train: bool = False,
  ) -> tuple[dict[str, Array], dict]:
    """Regresses the query views of a batch of scenes.

    Args:
      images: (S, Q, H, W, 3) query images in [-1, 1], H = W = 64 in the paper.
      scene: unused.
      context_images: (S, V, H, W, 3) context images of the same scenes.
      context_poses: (S, V, P_c) their pose inputs (ours: [v_xy || v_yaw], 192-d).
      train: unused (no batch norm or dropout).

    Returns:
      heads: {name: (S, Q, size)}.
      aux: {"style": {gamma16, ...: (S, C)}, "rms": {layer: ()}}.
    """
    del scene, train
    if context_images is None or context_poses is None:
      raise ValueError("GQNRegressor needs context_images and context_poses")
    if images.ndim != 5 or images.shape[0] != context_images.shape[0]:
      raise ValueError(
        f"expected images (S, Q, H, W, 3) matching context (S, V, ...), got {images.shape}, "
        f"{context_images.shape}"
      )
    style, _ = SceneEncoder(width=self.width, heads=GQN_REGRESSION_HEADS, name="encoder")(
      context_images, context_poses
    )
    s, q = images.shape[:2]
    x = images.reshape((s * q, *images.shape[2:]))
    c = lambda n: layers.scaled(n, self.width)
    # Per-query AdaIN parameters: the scene's, repeated over its Q queries.
    st = {k: jnp.repeat(v, q, axis=0) for k, v in style.items()}
    x = layers.lrelu(layers.conv(c(64), 4, strides=2, name="conv1")(x))
    rms = {"conv1": layers.rms(x)}
    for name, ch, key in (("conv2", 128, "16"), ("conv3", 256, "8"), ("conv4", 256, "4")):
      x = layers.conv(c(ch), 4, strides=2, name=name)(x)
      x = layers.lrelu(layers.adain(x, st[f"gamma{key}"], st[f"beta{key}"]))
      rms[name] = layers.rms(x)
    x = x.reshape((s, q, -1))
    out = PoseHeads(self.heads, self.extra_fc, extra_fc_match=self.extra_fc_match, name="heads")(x)
    return out, {"style": style, "rms": rms}


class CarRegressor(nn.Module):
  """ShapeNet-car regressor: five strided convs, no normalisation (the authors' code).

  Attributes:
    heads: output heads.
    width: channel multiplier.
    extra_fc: baselines' extra dense layer, or None.
    extra_fc_match: size the extra layer to match this head size's parameters (`PoseHeads`).
    channels: conv channels at width 1.0.
  """

  heads: tuple[HeadSpec, ...]
  width: float = 1.0
  extra_fc: int | None = None
  extra_fc_match: int | None = None
  channels: tuple[int, ...] = (64, 64, 128, 128, 256)

  @nn.compact
  def __call__(
    self,
    images: Array,
    *,
    scene: Array | None = None,
    context_images: Array | None = None,
    context_poses: Array | None = None,
    train: bool = False,
  ) -> tuple[dict[str, Array], dict]:
    """Args: images (..., H, W, 3) in [-1, 1] (128 x 128 in the paper); the rest unused.

    Returns:
      heads {name: (..., size)}, aux {"rms": {layer: ()}}.
    """
    del scene, context_images, context_poses, train
    x, lead = _flatten_images(images)
    rms = {}
    for i, ch in enumerate(self.channels):
      x = layers.lrelu(
        layers.conv(layers.scaled(ch, self.width), 4, strides=2, name=f"conv{i + 1}")(x)
      )
      rms[f"conv{i + 1}"] = layers.rms(x)
    x = x.reshape((*lead, -1))
    heads = PoseHeads(self.heads, self.extra_fc, extra_fc_match=self.extra_fc_match, name="heads")
    return heads(x), {"rms": rms}


class GibsonRegressor(nn.Module):
  """Gibson-rooms regressor: strided convs with per-area instance-norm tables (the authors' code).

  Attributes:
    heads: output heads.
    num_scenes: number of areas (rows of the gamma / beta tables).
    width: channel multiplier.
    extra_fc: baselines' extra dense layer, or None.
    extra_fc_match: size the extra layer to match this head size's parameters (`PoseHeads`).
    channels: conv channels at width 1.0.
    gamma_init_one: initialise gamma tables at 1 + N(0, 0.001^2) instead of the authors'
      N(0, 0.001^2) (which makes every IN output ~ beta ~ 0 at the start).
  """

  heads: tuple[HeadSpec, ...]
  num_scenes: int
  width: float = 1.0
  extra_fc: int | None = None
  extra_fc_match: int | None = None
  channels: tuple[int, ...] = (64, 128, 256, 256, 256)
  gamma_init_one: bool = False

  @nn.compact
  def __call__(
    self,
    images: Array,
    *,
    scene: Array | None = None,
    context_images: Array | None = None,
    context_poses: Array | None = None,
    train: bool = False,
  ) -> tuple[dict[str, Array], dict]:
    """Args: images (..., H, W, 3) in [-1, 1]; scene (...) int area indices; the rest unused.

    Returns:
      heads {name: (..., size)}, aux {"rms": {layer: ()}}.
    """
    del context_images, context_poses, train
    if scene is None:
      raise ValueError("GibsonRegressor needs the scene (area) index of every image")
    x, lead = _flatten_images(images)
    scene = jnp.asarray(scene).reshape(-1)
    small = nn.initializers.normal(1e-3)
    gamma_init = (lambda k, s: 1.0 + small(k, s)) if self.gamma_init_one else small
    rms = {}
    for i, ch in enumerate(self.channels):
      c = layers.scaled(ch, self.width)
      x = layers.conv(c, 4, strides=2, name=f"conv{i + 1}")(x)
      gamma = self.param(f"gamma{i + 1}", gamma_init, (self.num_scenes, c))
      beta = self.param(f"beta{i + 1}", small, (self.num_scenes, c))
      x = layers.lrelu(layers.adain(x, gamma[scene], beta[scene]))
      rms[f"conv{i + 1}"] = layers.rms(x)
    x = x.reshape((*lead, -1))
    heads = PoseHeads(self.heads, self.extra_fc, extra_fc_match=self.extra_fc_match, name="heads")
    return heads(x), {"rms": rms}


# --------------------------------------------------------------------------------------------
# ResNet-34 (torchvision layout) for 7-Scenes.


def _tconv(features: int, kernel: int, strides: int, name: str) -> nn.Conv:
  """torchvision conv: symmetric padding kernel // 2, no bias."""
  p = kernel // 2
  return nn.Conv(
    features,
    (kernel, kernel),
    strides=(strides, strides),
    padding=((p, p), (p, p)),
    use_bias=False,
    kernel_init=_resnet_conv_init,
    name=name,
  )


def _bn(train: bool, name: str) -> nn.BatchNorm:
  """torch BatchNorm2d: eps 1e-5, running-average momentum 0.1 (flax momentum 0.9)."""
  return nn.BatchNorm(use_running_average=not train, momentum=0.9, epsilon=1e-5, name=name)


class BasicBlock(nn.Module):
  """torchvision BasicBlock: conv3-bn-relu-conv3-bn (+ downsample conv1-bn), add, relu."""

  features: int
  strides: int = 1
  downsample: bool = False

  @nn.compact
  def __call__(self, x: Array, train: bool) -> Array:
    y = nn.relu(_bn(train, "bn1")(_tconv(self.features, 3, self.strides, "conv1")(x)))
    y = _bn(train, "bn2")(_tconv(self.features, 3, 1, "conv2")(y))
    if self.downsample:
      x = _bn(train, "downsample_1")(_tconv(self.features, 1, self.strides, "downsample_0")(x))
    return nn.relu(x + y)


RESNET34_STAGES = (3, 4, 6, 3)
RESNET_CHANNELS = (64, 128, 256, 512)


class ResNetRegressor(nn.Module):
  """ResNet-34-style regressor for 7-Scenes-like data (authors'), from scratch or torchvision.

  Parameter names mirror torchvision's state dict: conv1, bn1, layer{i}_{j}/{conv1, bn1, conv2,
  bn2, downsample_0, downsample_1}; then fc (-> fc_dim, ReLU) and heads.

  Attributes:
    heads: output heads.
    width: channel multiplier of the trunk (1.0 for torchvision weights).
    stage_sizes: basic blocks per stage (ResNet-34: 3, 4, 6, 3).
    fc_dim: units of the fc layer after pooling (2048).
    extra_fc: optional extra dense layer before the heads (none in MapNet's baselines).
    extra_fc_match: size the extra layer to match this head size's parameters (`PoseHeads`).
  """

  heads: tuple[HeadSpec, ...]
  width: float = 1.0
  stage_sizes: tuple[int, ...] = RESNET34_STAGES
  fc_dim: int = 2048
  extra_fc: int | None = None
  extra_fc_match: int | None = None

  @nn.compact
  def __call__(
    self,
    images: Array,
    *,
    scene: Array | None = None,
    context_images: Array | None = None,
    context_poses: Array | None = None,
    train: bool = False,
  ) -> tuple[dict[str, Array], dict]:
    """Args: images (..., H, W, 3) (normalised as the caller chooses); train: batch-norm mode.

    Returns:
      heads {name: (..., size)}, aux {"features": (..., fc_dim)}.
    """
    del scene, context_images, context_poses
    x, lead = _flatten_images(images)
    c0 = layers.scaled(RESNET_CHANNELS[0], self.width)
    x = nn.relu(_bn(train, "bn1")(_tconv(c0, 7, 2, "conv1")(x)))
    x = nn.max_pool(x, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)))
    in_ch = c0
    for i, n_blocks in enumerate(self.stage_sizes):
      ch = layers.scaled(RESNET_CHANNELS[i], self.width)
      for j in range(n_blocks):
        strides = 2 if (i > 0 and j == 0) else 1
        x = BasicBlock(ch, strides, strides != 1 or in_ch != ch, name=f"layer{i + 1}_{j}")(x, train)
        in_ch = ch
    x = jnp.mean(x, axis=(1, 2))
    x = nn.relu(
      nn.Dense(self.fc_dim, kernel_init=kaiming_normal, bias_init=layers.bias_init, name="fc")(x)
    )
    x = x.reshape((*lead, self.fc_dim))
    out = PoseHeads(
      self.heads,
      self.extra_fc,
      kernel_init=kaiming_normal,
      extra_fc_match=self.extra_fc_match,
      name="heads",
    )(x)
    return out, {"features": x}


def torchvision_resnet_keys(stage_sizes: Sequence[int] = RESNET34_STAGES) -> dict[str, tuple]:
  """torchvision state-dict keys of a ResNet trunk -> (collection, flax path, kind).

  kind is "conv" (torch (O, I, kh, kw) -> flax (kh, kw, I, O)) or "vector". The fc layer and the
  `num_batches_tracked` counters are not part of the mapping (the regressor replaces fc).
  """
  out = {}

  def conv(tkey, path):
    out[tkey] = ("params", path + ("kernel",), "conv")

  def bn(tkey, path):
    out[f"{tkey}.weight"] = ("params", path + ("scale",), "vector")
    out[f"{tkey}.bias"] = ("params", path + ("bias",), "vector")
    out[f"{tkey}.running_mean"] = ("batch_stats", path + ("mean",), "vector")
    out[f"{tkey}.running_var"] = ("batch_stats", path + ("var",), "vector")

  conv("conv1.weight", ("conv1",))
  bn("bn1", ("bn1",))
  for i, n in enumerate(stage_sizes):
    for j in range(n):
      t, f = f"layer{i + 1}.{j}", (f"layer{i + 1}_{j}",)
      conv(f"{t}.conv1.weight", f + ("conv1",))
      bn(f"{t}.bn1", f + ("bn1",))
      conv(f"{t}.conv2.weight", f + ("conv2",))
      bn(f"{t}.bn2", f + ("bn2",))
      if i > 0 and j == 0:
        conv(f"{t}.downsample.0.weight", f + ("downsample_0",))
        bn(f"{t}.downsample.1", f + ("downsample_1",))
  return out


def _read_state_dict(path: str | os.PathLike) -> dict[str, np.ndarray]:
  path = os.fspath(path)
  if path.endswith(".npz"):
    with np.load(path) as z:
      return {k: np.asarray(z[k]) for k in z.files}
  if path.endswith((".pth", ".pt")):
    try:
      import torch  # optional dependency, absent from camrep's environment
    except ImportError as e:
      raise ImportError(
        f"{path}: reading .pth needs torch; convert it once with "
        "np.savez(out, **{k: v.numpy() for k, v in torch.load(p).items()})"
      ) from e
    sd = torch.load(path, map_location="cpu")
    return {k: v.detach().cpu().numpy() for k, v in sd.items()}
  raise ValueError(f"{path}: expected a .npz (or .pth with torch installed) state dict")


def load_torchvision_resnet34(
  path: str | os.PathLike | Mapping[str, np.ndarray],
  *,
  variables: Mapping[str, Any] | None = None,
  stage_sizes: Sequence[int] = RESNET34_STAGES,
) -> dict[str, Any]:
  """Map a torchvision ResNet state dict onto a `ResNetRegressor`'s variables.

  torch conv weights (O, I, kh, kw) become flax kernels (kh, kw, I, O); batch-norm weight / bias
  become params scale / bias and running_mean / running_var the batch_stats mean / var. The
  ImageNet fc layer and the num_batches_tracked counters are ignored.

  Args:
    path: a .npz with torchvision's key names (`conv1.weight`, `layer1.0.conv1.weight`,
      `bn1.running_mean`, ...), a .pth if torch is installed, or the dict itself.
    variables: the regressor's variables from `init` ({"params", "batch_stats"}); the trunk is
      replaced after checking every shape, fc and heads keep their values. None: return only
      the trunk's variables, to be merged by the caller.
    stage_sizes: blocks per stage of the model.

  Returns:
    {"params": ..., "batch_stats": ...} (float32).

  Raises:
    ValueError: a trunk key is missing from the file, or a tensor's shape does not match the
      model (e.g. weights of a different width).
  """
  sd = dict(path) if isinstance(path, Mapping) else _read_state_dict(path)
  mapping = torchvision_resnet_keys(stage_sizes)
  missing = sorted(set(mapping) - set(sd))
  if missing:
    raise ValueError(f"state dict lacks {len(missing)} ResNet keys, e.g. {missing[:5]}")
  out = flax_unfreeze(variables) if variables is not None else {"params": {}, "batch_stats": {}}
  for tkey, (coll, fpath, kind) in mapping.items():
    value = np.asarray(sd[tkey], np.float32)
    if kind == "conv":
      value = value.transpose(2, 3, 1, 0)
    node = out.setdefault(coll, {})
    for p in fpath[:-1]:
      node = node.setdefault(p, {}) if variables is None else node[p]
    if variables is not None:
      have = node[fpath[-1]].shape
      if tuple(value.shape) != tuple(have):
        raise ValueError(
          f"{tkey}: shape {tuple(sd[tkey].shape)} (as flax {tuple(value.shape)}) does not match "
          f"the model's {coll}/{'/'.join(fpath)} {tuple(have)}"
        )
    node[fpath[-1]] = jnp.asarray(value)
  return out


def flax_unfreeze(tree: Any) -> Any:
  """A mutable nested-dict copy of a (possibly frozen) variables tree."""
  if isinstance(tree, Mapping):
    return {k: flax_unfreeze(v) for k, v in tree.items()}
  return tree


# Size variants.
NETWORKS: dict[str, type[nn.Module]] = {
  "adain_context": GQNRegressor,
  "conv5": CarRegressor,
  "conv5_area_norm": GibsonRegressor,
  "resnet": ResNetRegressor,
}
"""The regressor networks by name (a `camrep.settings.Setting`'s `network`)."""


def make_network(name: str, heads: tuple[HeadSpec, ...], **options: Any) -> nn.Module:
  """The network `name` (a key of `NETWORKS`) with `heads`; of `options` (width, extra_fc,
  extra_fc_match, num_scenes, stage_sizes, fc_dim, ...) it takes the fields the network has.

  Raises:
    ValueError: an unknown name.
  """
  if name not in NETWORKS:
    raise ValueError(f"unknown regressor network {name!r}; choose one of {tuple(NETWORKS)}")
  cls = NETWORKS[name]
  fields = {f.name for f in dataclasses.fields(cls)}
  return cls(heads, **{k: v for k, v in options.items() if k in fields})


ResNet34Regressor = functools.partial(ResNetRegressor, width=1.0, stage_sizes=RESNET34_STAGES)
ResNetRegressorTiny = functools.partial(
  ResNetRegressor, width=1 / 16, stage_sizes=(1, 1, 1, 1), fc_dim=32
)


def normalise_head(v: Array, head: HeadSpec) -> Array:
  """Apply a head's normalisation exactly as `camrep.pose` normalises grid vectors.

  Args:
    v: (..., head.size) raw outputs.

  Returns:
    (..., head.size): unchanged ("none"), v / sqrt(|v|^2 + 1e-12) ("unit"), or each block b of
    size/n_blocks entries v_b / (sqrt(|v_b|^2 + 1e-12) n_blocks) ("block").
  """
  eps = 1e-12
  if head.norm == "none":
    return v
  if head.norm == "block":
    vb = v.reshape(*v.shape[:-1], head.n_blocks, head.size // head.n_blocks)
    nb = jnp.sqrt(jnp.sum(vb * vb, axis=-1, keepdims=True) + eps)
    return (vb / (nb * head.n_blocks)).reshape(v.shape)
  return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True) + eps)

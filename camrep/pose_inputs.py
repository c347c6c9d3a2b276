"""Every pose input a view-synthesis decoder can take (paper sections 3.1-3.3; supplement).

One interface, `PoseInput` (documented once, implemented per kind): `init`, `embed` and
`decode`, each taking explicit arguments. The kinds:

  GridPoseInput    camrep's learned pose system (`camrep.pose`: grid vectors rotated by
                   exp(B delta)), the paper's method;
  LowDimPoseInput  GQN's low-dimensional pose vector (Eslami et al. 2018): raw positions and
                   (sin, cos) of angles, the paper's view-synthesis baseline;
  MlpPoseInput     the supplement's MLP embedding: per DOF a 2-layer MLP (hidden 128, leaky ReLU)
                   of the pose, trained with the decoder (also a regression target,
                   `camrep.regression.targets`).

All map poses (..., P) to per-DOF vectors {name: (..., k)}, so decoders and regressors take any
of them unchanged. `from_config` is the one place that maps a config (`config.rep.kind`) to its
pose input.
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Mapping

import flax.linen as nn
import jax
import jax.numpy as jnp
from typing_extensions import override

from camrep import pose as P
from camrep.data import sources

Array = jax.Array


# The decoder's pose input (config.rep.kind): camrep's learned system (the paper's method), or a
# comparison input for the noise-robustness figure: GQN's low-dimensional pose vector, or the
# supplement's MLP embedding (one 128 -> d MLP per DOF, trained with the decoder).
REP_KINDS = ("grid", "lowdim", "mlp")


class PoseInput(abc.ABC):
  """A decoder's pose input: per-DOF vectors of poses, and back.

  Implementations are frozen dataclasses holding everything they need (the `spec`, constants,
  sizes), so they are hashable static arguments of jitted functions.

  Attributes:
    spec: the pose system: the DOFs, their pose columns and ranges (all kinds use its DOFs).
    learned_grid: True for camrep's learned grid system only: its parameters are a
      `camrep.pose` pytree (rotation losses, Gram maps and grid betas apply), and `embed`
      honours `mode` and `key`.
  """

  spec: P.PoseSystemSpec
  learned_grid = False

  @abc.abstractmethod
  def init(self, key: Array) -> dict:
    """Initial parameters (the "rep" group of the train state; {} when there are none)."""

  @abc.abstractmethod
  def embed(
    self, params, poses: Array, *, mode: str = "nearest", key: Array | None = None
  ) -> dict[str, Array]:
    """Vectors of poses (..., pose_dim): {DOF name: (..., k)}.

    Args:
      params: what `init` returned.
      poses: (..., pose_dim) in the spec's columns (radians, the dataset's length unit).
      mode, key: quantisation of the learned grid ("nearest", "floor", or "random" with a PRNG
        key; `camrep.pose.embed`); the other kinds ignore them.
    """

  @abc.abstractmethod
  def decode(self, params, vectors: Mapping[str, Array], *, mode: str = "nearest") -> Array:
    """Poses (..., pose_dim) from vectors {DOF name: (..., k)}: the inverse of `embed`.

    Args:
      mode: quantisation of the learned grid's candidates; the other kinds ignore it.
    """


@dataclasses.dataclass(frozen=True)
class GridPoseInput(PoseInput):
  """camrep's learned pose system (`camrep.pose`), the paper's method.

  Attributes:
    refine_steps: Gauss-Newton refinement steps of `decode` (0: the authors' plain arg-min).
  """

  spec: P.PoseSystemSpec
  refine_steps: int = 4

  learned_grid = True

  @override
  def init(self, key):
    return P.init(key, self.spec)

  @override
  def embed(self, params, poses, *, mode="nearest", key=None):
    return P.embed(params, self.spec, poses, mode=mode, key=key)

  @override
  def decode(self, params, vectors, *, mode="nearest"):
    return P.decode(params, self.spec, vectors, refine_steps=self.refine_steps, mode=mode)


def gqn_lowdim_constants(family: Mapping) -> tuple[float, float]:
  """(camera height, pitch) of the GQN-rooms procedural family: the constant z and pitch of GQN's
  low-dimensional pose vector, from the family's parameters (`config.data.family`) with the
  renderer's defaults (`procedural.RoomsConfig`) for those it leaves out."""
  from camrep.data import procedural

  rooms = procedural.RoomsConfig()
  return float(family.get("camera_height", rooms.camera_height)), float(
    family.get("pitch", rooms.pitch)
  )


@dataclasses.dataclass(frozen=True)
class LowDimPoseInput(PoseInput):
  """GQN's low-dimensional pose input, split by DOF, no parameters.

  GQN rooms (Eslami et al. 2018; `camera_height` and `pitch` given): (x, y, z, sin yaw, cos yaw,
  sin pitch, cos pitch) with the procedural rooms' constant camera height and pitch: the polar
  DOF "xy" -> (x, y, z), an angle "yaw" -> (sin yaw, cos yaw, sin pitch, cos pitch). Otherwise
  (both None): positions raw, angles (sin, cos).
  """

  spec: P.PoseSystemSpec
  camera_height: float | None = None
  pitch: float | None = None

  def __post_init__(self):
    if (self.camera_height is None) != (self.pitch is None):
      raise ValueError(
        "LowDimPoseInput: give both camera_height and pitch (GQN rooms) or neither, got "
        f"camera_height={self.camera_height!r}, pitch={self.pitch!r}"
      )

  @property
  def gqn(self) -> bool:
    return self.camera_height is not None

  @override
  def init(self, key):
    return {}

  @override
  def embed(self, params, poses, *, mode="nearest", key=None):
    z, pitch = (self.camera_height, self.pitch) if self.gqn else (0.0, 0.0)
    out = {}
    for d in self.spec.dofs:
      cols = poses[..., self.spec.columns(d.name)]
      ones = jnp.ones(cols.shape[:-1] + (1,), cols.dtype)
      if d.is_angle:
        v = jnp.concatenate([jnp.sin(cols), jnp.cos(cols)], -1)
        if self.gqn:
          v = jnp.concatenate([v, math.sin(pitch) * ones, math.cos(pitch) * ones], -1)
      else:
        v = jnp.concatenate([cols, z * ones], -1) if self.gqn and d.width == 2 else cols
      out[d.name] = v
    return out

  @override
  def decode(self, params, vectors, *, mode="nearest"):
    """Positions: their first `width` entries; angles: atan2(sin, cos), in [low, low + 2 pi)."""
    cols = []
    for d in self.spec.dofs:
      v = vectors[d.name]
      if d.is_angle:
        a = jnp.arctan2(v[..., 0], v[..., 1])
        cols.append((d.low + jnp.mod(a - d.low, 2 * math.pi))[..., None])
      else:
        cols.append(v[..., : d.width])
    return jnp.concatenate(cols, axis=-1)


class MlpEmbedding(nn.Module):
  """Supplement baseline: v(l) = normalise(W2 lrelu(W1 l + b1) + b2) for one DOF.

  The input is the DOF value mapped linearly from [low, high] to [-1, 1] (two inputs for a polar
  DOF). The supplement gives no initialisation; here W1, b1 ~ N(0, 1) so that the 128 kinks of
  the leaky ReLU fall across the input range (with zero biases every kink would sit at 0 and the
  normalised output would take only two values), W2 glorot, b2 = 0. The output is unit-normalised
  like the learned system's angle vectors.

  Attributes:
    dim: output size d (96).
    hidden: hidden units (128).
  """

  dim: int = 96
  hidden: int = 128

  @nn.compact
  def __call__(self, x: Array) -> Array:
    """(..., n_in) inputs in [-1, 1] -> (..., dim) unit vectors."""
    normal = nn.initializers.normal(1.0)
    h = nn.Dense(self.hidden, kernel_init=normal, bias_init=normal, name="hidden")(x)
    h = nn.leaky_relu(h, negative_slope=0.2)  # TF slope, as camrep.models.layers.lrelu
    v = nn.Dense(self.dim, kernel_init=nn.initializers.xavier_uniform(), name="out")(h)
    return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True) + 1e-12)


@dataclasses.dataclass(frozen=True)
class MlpPoseInput(PoseInput):
  """The supplement's MLP embedding: one `MlpEmbedding` (spec.dim outputs) per DOF.

  Parameters {DOF name: flax params}. `decode` is the arg-min of eq. 12 over the learned
  system's candidate lists (`camrep.pose.candidates`), without refinement.

  Attributes:
    hidden: hidden units of each MLP (128).
  """

  spec: P.PoseSystemSpec
  hidden: int = 128

  def _module(self) -> MlpEmbedding:
    return MlpEmbedding(self.spec.dim, self.hidden)

  def _input(self, d: P.Dof, cols: Array) -> Array:
    """Pose columns (..., width) mapped from [low, high] to [-1, 1]."""
    return 2.0 * (cols - d.low) / (d.high - d.low) - 1.0

  @override
  def init(self, key):
    out = {}
    for i, d in enumerate(self.spec.dofs):
      x = jnp.zeros((1, d.width), jnp.float32)
      out[d.name] = self._module().init(jax.random.fold_in(key, i), x)["params"]
    return out

  @override
  def embed(self, params, poses, *, mode="nearest", key=None):
    out = {}
    for d in self.spec.dofs:
      cols = poses[..., self.spec.columns(d.name)]
      out[d.name] = self._module().apply({"params": params[d.name]}, self._input(d, cols))
    return out

  @override
  def decode(self, params, vectors, *, mode="nearest"):
    cols = []
    for d in self.spec.dofs:
      cands = d.candidates()
      x = self._input(d, d.columns(cands))
      cvec = self._module().apply({"params": params[d.name]}, x)  # (K, d)
      score = jnp.sum(cvec * cvec, -1) - 2.0 * jnp.einsum("...d,kd->...k", vectors[d.name], cvec)
      cols.append(d.columns(cands[jnp.argmin(score, axis=-1)]))
    return jnp.concatenate(cols, axis=-1)


def rep_kind(config) -> str:
  """The config's pose-input kind (`config.rep.kind`, default "grid"), checked."""
  kind = config.rep.get("kind", "grid")
  if kind not in REP_KINDS:
    raise ValueError(f"unknown rep.kind {kind!r}; choose one of {REP_KINDS}")
  return kind


def from_config(config, spec: P.PoseSystemSpec) -> PoseInput:
  """The pose input of a run: `config.rep.kind` picks the kind; GQN's low-dim vector takes the
  rooms' camera height and pitch from `config.data.family` when the data is GQN's setting."""

  kind = rep_kind(config)
  if kind == "grid":
    return GridPoseInput(spec)
  if kind == "mlp":
    return MlpPoseInput(spec)
  if sources.setting_of(config.data.source) == "gqn":
    z, pitch = gqn_lowdim_constants(config.data.family)
    return LowDimPoseInput(spec, camera_height=z, pitch=pitch)
  return LowDimPoseInput(spec)

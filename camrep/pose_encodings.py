"""Every pose encoding of the paper, behind one interface used by both stages.

A `PoseEncoding` maps poses (..., P) in a setting's columns to vectors and back. View synthesis
feeds a decoder with one (`config.rep.kind`); pose regression predicts one as its targets
(`config.representation`, paper section 4.4, Table 1). The interface, documented once on
`PoseEncoding`: `init`, `embed`, `decode`, `heads` (what a regressor predicts: one head per DOF
for the per-DOF encodings, a position and an orientation head for the hand-designed ones) and
`loss` (the head loss it trains with), and `regulariser`, zero but for the learned grid (its
rotation and direction losses, eqs. 6-9).

  name (regression)  encoding                                                    stages
  grid ("ours")      camrep's learned pose system (`camrep.pose`): grid vectors     both
                     rotated by exp(B delta), the paper's method
  lowdim             GQN's low-dimensional pose vector (Eslami et al. 2018): raw    synthesis
                     positions and (sin, cos) of angles, the view-synthesis baseline
  mlp                the supplement's MLP embedding: per DOF a 2-layer MLP (hidden   both
                     128, leaky ReLU) of the pose, trained with the decoder
  euler              the raw angles                                                 regression
  axis_angle         rotation vector angle * axis                                   regression
  sincos             (sin a, cos a) of each angle                                   regression
  quat               unit quaternion (w, x, y, z), w >= 0                           regression
  logq               log quaternion (MapNet's)                                      regression
  rot6d              first two columns of the rotation matrix (Zhou et al. 2019)    regression
  svd9d              the rotation matrix, SVD-projected (Levinson et al. 2020)      regression
  grid_untrained     control: the learned grid of a view-synthesis run at its        regression
  ("untrained")      random initialisation (what learning added, taken away)
  grid_frozen_gen    control: the learned grid of a run that held its generators B   regression
  ("frozen_gen")     at their initial values (`rep.freeze_generators`)

The hand-designed encodings carry the position raw in a "position" head (none for a setting
without position) and the orientation in an "orientation" head; rot6d and svd9d are continuous
in the rotation, which quaternions with w >= 0 and Euler angles are not; for yaw-only settings
their matrix is a rotation about +z, so 6 or 9 numbers carry one angle. Every head belongs to a
loss group, "position" or "orientation".

`ENCODINGS` is the one registry; `get` looks a name up, `create` builds one for a setting and
pose system (a view-synthesis run's: `synthesis.synthesizers.pose_input`).
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
from typing_extensions import override

from camrep import pose as P
from camrep import rotations
from camrep import settings as settings_lib

Array = jax.Array
Params = Any

GROUPS = ("position", "orientation")
NORMS = ("none", "unit", "block")


@dataclasses.dataclass(frozen=True)
class HeadSpec:
  """One output head of a pose regressor.

  Attributes:
    name: "position" / "orientation" for the hand-designed encodings, the DOF name for the
      per-DOF ones.
    size: output size.
    group: loss group, "position" or "orientation".
    norm: "none"; "unit" (divide by the L2 norm); "block" (each of `n_blocks` blocks scaled to
      norm 1 / n_blocks, camrep.pose's polar block_norm).
    n_blocks: number of blocks for norm="block".
  """

  name: str
  size: int
  group: str
  norm: str = "none"
  n_blocks: int = 1

  def __post_init__(self):
    if self.group not in GROUPS:
      raise ValueError(f"head {self.name}: group must be one of {GROUPS}, got {self.group!r}")
    if self.norm not in NORMS:
      raise ValueError(f"head {self.name}: norm must be one of {NORMS}, got {self.norm!r}")
    if self.norm == "block" and self.size % self.n_blocks:
      raise ValueError(f"head {self.name}: size {self.size} not divisible by {self.n_blocks}")


@dataclasses.dataclass(frozen=True)
class Regularisation:
  """The weights of the learned grid's own loss (a view-synthesis config's `loss` section).

  Attributes:
    rot_weight: lambda_2 = lambda_3, the weight of the rotation losses (eq. 9).
    dir_weight: lambda_4, the weight of L_rot,theta (eq. 9.2; binned polar DOFs); 0: none.
    n_pairs: extra rotation-loss pairs per DOF per step.
    mode: quantisation of the pairs' poses ("random", "nearest", "floor").
  """

  rot_weight: float
  dir_weight: float
  n_pairs: int
  mode: str


class PoseEncoding(abc.ABC):
  """A map from poses (..., P) to vectors {name: (..., k)} and back.

  Implementations are frozen dataclasses holding everything they need (the setting, the pose
  system, sizes), so they are hashable static arguments of jitted functions.

  Attributes:
    name: registry key (`config.rep.kind` in view synthesis).
    regression_name: the name regression configs and records use (`config.representation`,
      Table 1's rows); the `name` unless it differs.
    loss: the head loss a regressor of it trains with (a key of
      `camrep.regression.targets.LOSSES`) unless the config names another.
    title: what it is, in words (messages and records).
    learned: its parameters are learned (by view synthesis), and a regression reads them frozen.
    needs_synthesis: a regression must read its parameters from a view-synthesis run that
      trained it (the learned grid); False for a learned encoding a regression may also
      initialise at random and freeze (the MLP embedding).
    synthesis_input: a view-synthesis decoder can take it (it gives one vector per DOF).
    regression_target: a pose regressor can predict it.
    regularised: its `regulariser` is not zero (the learned grid): the loss options of its
      rotation losses (pairs, weights) apply.
    quantised: `embed` and `decode` honour `mode` (the learned grid), which a regression run
      then must give.
    per_dof: one vector per DOF of a pose system (`spec`); False: a position and an
      orientation vector of the setting's poses.
    setting: the setting whose poses it encodes.
    spec: the pose system of a per-DOF encoding (its DOFs and ranges); None for the others.
  """

  name: ClassVar[str]
  regression_name: ClassVar[str | None] = None
  loss: ClassVar[str]
  title: ClassVar[str]
  learned: ClassVar[bool] = False
  needs_synthesis: ClassVar[bool] = False
  synthesis_input: ClassVar[bool] = False
  regression_target: ClassVar[bool] = True
  regularised: ClassVar[bool] = False
  quantised: ClassVar[bool] = False
  per_dof: ClassVar[bool] = True
  initial_state: ClassVar[bool] = False
  frozen_generators: ClassVar[bool] = False

  setting: settings_lib.Setting
  spec: P.PoseSystemSpec | None

  @classmethod
  def table_name(cls) -> str:
    """`regression_name`, else `name`."""
    return cls.regression_name or cls.name

  @classmethod
  def trained_by(cls) -> type[PoseEncoding]:
    """The view-synthesis pose input (`config.rep.kind`) of a run whose parameters a regression
    of this encoding reads: itself, or the learned grid for its controls."""
    return cls

  @classmethod
  @abc.abstractmethod
  def create(
    cls,
    setting: settings_lib.Setting,
    spec: P.PoseSystemSpec | None,
    *,
    refine_steps: int = 4,
    mlp_hidden: int = 128,
    camera: tuple[float, float] | None = None,
  ) -> PoseEncoding:
    """The encoding of poses of `setting` (and of the pose system `spec`, for the per-DOF ones).

    Args:
      refine_steps: the learned grid's Gauss-Newton refinement steps when decoding (0: the
        authors' plain arg-min).
      mlp_hidden: hidden units of the MLP embedding.
      camera: GQN's low-dim vector: the rooms' constant (camera height, pitch), or None.
    """

  def init(self, key: Array) -> Params:
    """Initial parameters (the "rep" group of a view-synthesis state; {} when there are none)."""
    del key
    return {}

  @abc.abstractmethod
  def embed(
    self, params: Params, poses: Array, *, mode: str = "nearest", key: Array | None = None
  ) -> dict[str, Array]:
    """Vectors of poses (..., P): {head name: (..., size)}, the heads `heads` lists.

    Args:
      params: what `init` returned (or a view-synthesis run's).
      poses: (..., P) in the setting's columns (radians, the dataset's length unit).
      mode, key: quantisation of the learned grid ("nearest", "floor", or "random" with a PRNG
        key; `camrep.pose.embed`); the other encodings ignore them.
    """

  def embed_images(
    self, params: Params, poses: Array, *, mode: str = "nearest", keys: Array | None = None
  ) -> dict[str, Array]:
    """`embed` of poses (E, V, P) with one quantisation key per leading row (keys (E,), needed
    for mode "random" by the learned grid; the other encodings ignore both)."""
    del keys
    return self.embed(params, poses, mode=mode)

  @abc.abstractmethod
  def decode(self, params: Params, vectors: Mapping[str, Array], *, mode: str = "nearest") -> Array:
    """Poses (..., P) from vectors {head name: (..., size)}: the inverse of `embed`; extra
    entries are ignored.

    Args:
      mode: quantisation of the learned grid's candidates; the other encodings ignore it.
    """

  @abc.abstractmethod
  def heads(self) -> tuple[HeadSpec, ...]:
    """The heads a regressor of this encoding predicts, in order."""

  def regulariser(
    self,
    params: Params,
    key: Array,
    *,
    weights: Regularisation,
    pair_poses: Array | None = None,
    scene_keys: Callable[[Array, int], Array] | None = None,
  ) -> tuple[Array, dict[str, Array]]:
    """The encoding's own loss and its named terms, added to a view-synthesis model's loss in
    the objective of the "rep" parameter group. 0 and no terms: only the learned grid has one
    (its generators tie nearby poses together).

    Args:
      params: the encoding's parameters.
      key: the step's key.
      weights: the loss weights and the pairs' quantisation.
      pair_poses: (S, V, P) poses of the batch's views laid out as (anchor, partner) pairs, to
        mix data pairs into the rotation losses; None: extra pairs only.
      scene_keys: (key, S) -> (S,) per-scene keys of the data pairs.
    """
    del params, key, weights, pair_poses, scene_keys
    return jnp.zeros((), jnp.float32), {}

  def gram(self, params: Params, name: str, values: Array) -> Array:
    """Gram matrix V V^T (K, K) of the vectors of DOF (or head) `name` at values (K,) (or (K, 2)
    positions), the other pose columns 0."""
    v = self.embed(params, P.dof_poses(self.spec, name, values))[name]
    return v @ v.T

  def spread(self, params: Params) -> dict[str, Array]:
    """beta per DOF, {name: (d,)}: the std of each element of the DOF's vectors over its grid
    points (the noise test's scale, paper section 4.3)."""
    out = {}
    for d in self.spec.dofs:
      poses = P.dof_poses(self.spec, d.name, P.candidates(self.spec, d.name, d.spacing))
      out[d.name] = jnp.std(self.embed(params, poses)[d.name], axis=0)
    return out


def _dof_group(d: P.Dof) -> str:
  return "orientation" if d.is_angle else "position"


# ----------------------------------------------------------------------------------------------
# Per-DOF encodings: one vector per DOF of the pose system.

_jit_gram = jax.jit(P.gram, static_argnums=(1, 2))


@dataclasses.dataclass(frozen=True)
class GridEncoding(PoseEncoding):
  """camrep's learned pose system (`camrep.pose`), the paper's method.

  Heads: one of spec.dim per DOF (96 at paper size; 7-Scenes 32), block-normalised for a polar
  DOF with block_norm, unit otherwise. Regression targets are the frozen vectors with the run's
  quantisation (eq. 3); decoding is the arg-min over the candidates (eq. 12) plus Gauss-Newton
  refinement.

  Attributes:
    refine_steps: Gauss-Newton refinement steps of `decode` (0: the authors' plain arg-min).
  """

  spec: P.PoseSystemSpec
  refine_steps: int = 4
  setting: settings_lib.Setting | None = None

  name = "grid"
  regression_name = "ours"
  loss = "l2"
  title = "learned pose system"
  learned = True
  needs_synthesis = True
  regularised = True
  quantised = True
  synthesis_input = True

  @override
  @classmethod
  def create(cls, setting, spec, *, refine_steps=4, mlp_hidden=128, camera=None):
    return cls(spec, refine_steps=refine_steps, setting=setting)

  @override
  def init(self, key):
    return P.init(key, self.spec)

  @override
  def embed(self, params, poses, *, mode="nearest", key=None):
    return P.embed(params, self.spec, poses, mode=mode, key=key)

  @override
  def embed_images(self, params, poses, *, mode="nearest", keys=None):
    if mode == "random":
      if keys is None:
        raise ValueError("quantisation 'random' needs per-image keys")
      return jax.vmap(lambda p, k: P.embed(params, self.spec, p, mode=mode, key=k))(poses, keys)
    return P.embed(params, self.spec, poses, mode=mode)

  @override
  def decode(self, params, vectors, *, mode="nearest"):
    return P.decode(params, self.spec, vectors, refine_steps=self.refine_steps, mode=mode)

  @override
  def heads(self):
    out = []
    for d in self.spec.dofs:
      norm, n_blocks = ("block", self.spec.n_blocks) if d.block_norm else ("unit", 1)
      out.append(HeadSpec(d.name, self.spec.dim, _dof_group(d), norm, n_blocks))
    return tuple(out)

  @override
  def regulariser(self, params, key, *, weights, pair_poses=None, scene_keys=None):
    """lambda_2 sum_l L_rot,l + lambda_4 sum L_rot,theta (eqs. 9, 9.2), terms "rot_<dof>" and
    "dir_<dof>".

    Extra pairs use `key` as given (the same on every device of a pmapped step: the term is
    replicated); data pairs use `scene_keys` and are averaged as the caller's batch is. A DOF's
    data-pair term is mixed 0.5 / 0.5 with its extra-pair term (`P.data_rotation_losses`; DOF i
    of scene s draws from fold_in(scene key s, 1000 + i)).
    """
    spec, mode = self.spec, weights.mode
    key_pairs, k_quant = jax.random.split(key)
    data_pairs = data_keys = None
    if pair_poses is not None:
      S, V = pair_poses.shape[:2]
      pairs = pair_poses.reshape(S, V // 2, 2, -1)
      data_pairs = (pairs[:, :, 0], pairs[:, :, 1])
      keys = scene_keys(k_quant, S)
      data_keys = lambda i: jax.vmap(lambda k: jax.random.fold_in(k, 1000 + i))(keys)
    rot = P.data_rotation_losses(
      key_pairs,
      params,
      spec,
      n_pairs=weights.n_pairs,
      mode=mode,
      data_pairs=data_pairs,
      data_keys=data_keys,
    )
    terms = {f"rot_{n}": rot[n] for n in spec.names}
    total = weights.rot_weight * sum(terms.values())
    if weights.dir_weight:
      for d in spec.dofs:
        if d.has_direction_loss:
          terms[f"dir_{d.name}"] = P.direction_loss(params, spec, d.name)
          total = total + weights.dir_weight * terms[f"dir_{d.name}"]
    return total, terms

  @override
  def gram(self, params, name, values):
    return _jit_gram(params, self.spec, name, values=values)

  @override
  def spread(self, params):
    return {n: P.grid_std(params, self.spec, n) for n in self.spec.names}


@dataclasses.dataclass(frozen=True)
class UntrainedGridEncoding(GridEncoding):
  """Control target: the learned grid of a view-synthesis run at its random initialisation
  (grid vectors and generators i.i.d. normal, `camrep.pose.init`), frozen and regressed exactly
  as "ours". Against "ours" it says what view synthesis' learning adds beyond the target's form
  (unit vectors per DOF, arg-min decoding)."""

  name = "grid_untrained"
  regression_name = "untrained"
  title = "learned pose system at its initialisation (control)"
  synthesis_input = False
  initial_state = True

  @override
  @classmethod
  def trained_by(cls):
    return GridEncoding


@dataclasses.dataclass(frozen=True)
class FrozenGeneratorsGridEncoding(GridEncoding):
  """Control target: the learned grid of a view-synthesis run trained with its generators B held
  at their initial values (`rep.freeze_generators`: only the grid vectors and the decoder
  learn), regressed exactly as "ours". Against "ours" it says what learning the pose shift's
  matrix representation (eq. 3) adds."""

  name = "grid_frozen_gen"
  regression_name = "frozen_gen"
  title = "learned pose system with frozen generators (control)"
  synthesis_input = False
  frozen_generators = True

  @override
  @classmethod
  def trained_by(cls):
    return GridEncoding


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
class LowDimEncoding(PoseEncoding):
  """GQN's low-dimensional pose input, split by DOF, no parameters.

  GQN rooms (Eslami et al. 2018; `camera_height` and `pitch` given): (x, y, z, sin yaw, cos yaw,
  sin pitch, cos pitch) with the procedural rooms' constant camera height and pitch: the polar
  DOF "xy" -> (x, y, z), an angle "yaw" -> (sin yaw, cos yaw, sin pitch, cos pitch). Otherwise
  (both None): positions raw, angles (sin, cos).
  """

  spec: P.PoseSystemSpec
  camera_height: float | None = None
  pitch: float | None = None
  setting: settings_lib.Setting | None = None

  name = "lowdim"
  loss = "mse"
  title = "GQN low-dimensional pose vector"
  synthesis_input = True
  regression_target = False

  def __post_init__(self):
    if (self.camera_height is None) != (self.pitch is None):
      raise ValueError(
        "LowDimEncoding: give both camera_height and pitch (GQN rooms) or neither, got "
        f"camera_height={self.camera_height!r}, pitch={self.pitch!r}"
      )

  @override
  @classmethod
  def create(cls, setting, spec, *, refine_steps=4, mlp_hidden=128, camera=None):
    z, pitch = camera if camera is not None else (None, None)
    return cls(spec, camera_height=z, pitch=pitch, setting=setting)

  @property
  def gqn(self) -> bool:
    return self.camera_height is not None

  def _size(self, d: P.Dof) -> int:
    if d.is_angle:
      return 4 if self.gqn else 2
    return d.width + 1 if self.gqn and d.width == 2 else d.width

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

  @override
  def heads(self):
    return tuple(HeadSpec(d.name, self._size(d), _dof_group(d)) for d in self.spec.dofs)


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
class MlpEncoding(PoseEncoding):
  """The supplement's MLP embedding: one `MlpEmbedding` (spec.dim outputs) per DOF.

  Parameters {DOF name: flax params}. `decode` is the arg-min of eq. 12 over the learned
  system's candidate lists (`camrep.pose.candidates`), without refinement. Heads: one unit head
  of spec.dim per DOF.

  Attributes:
    hidden: hidden units of each MLP (128).
  """

  spec: P.PoseSystemSpec
  hidden: int = 128
  setting: settings_lib.Setting | None = None

  name = "mlp"
  loss = "l2"
  title = "MLP embedding"
  learned = True
  synthesis_input = True

  @override
  @classmethod
  def create(cls, setting, spec, *, refine_steps=4, mlp_hidden=128, camera=None):
    return cls(spec, hidden=mlp_hidden, setting=setting)

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

  @override
  def heads(self):
    return tuple(HeadSpec(d.name, self.spec.dim, _dof_group(d), "unit") for d in self.spec.dofs)


# ----------------------------------------------------------------------------------------------
# Hand-designed encodings: the position raw, the orientation in one vector.


@dataclasses.dataclass(frozen=True)
class _HandDesigned(PoseEncoding):
  """A hand-designed encoding: heads "position" (the raw position, absent without one) and
  "orientation" (`size` numbers from the setting's angle columns); decoded angles are wrapped
  into their ranges."""

  setting: settings_lib.Setting
  spec: P.PoseSystemSpec | None = None

  per_dof = False

  @override
  @classmethod
  def create(cls, setting, spec, *, refine_steps=4, mlp_hidden=128, camera=None):
    return cls(settings_lib.get(setting))

  @abc.abstractmethod
  def size(self) -> int:
    """The orientation head's size."""

  @abc.abstractmethod
  def _to_vector(self, angles: Array) -> Array:
    """Angle columns (..., n_angles) -> (..., size)."""

  @abc.abstractmethod
  def _from_vector(self, x: Array) -> Array:
    """(..., size) -> angle columns (..., n_angles) in their ranges."""

  @override
  def embed(self, params, poses, *, mode="nearest", key=None):
    pos, ang = self.setting.split_pose(poses)
    out = {"position": pos} if self.setting.position_dim else {}
    out["orientation"] = self._to_vector(ang)
    return out

  @override
  def decode(self, params, vectors, *, mode="nearest"):
    ang = self._from_vector(vectors["orientation"])
    if self.setting.position_dim:
      return jnp.concatenate([vectors["position"], ang], axis=-1)
    return ang

  @override
  def heads(self):
    out = []
    if self.setting.position_dim:
      out.append(HeadSpec("position", self.setting.position_dim, "position"))
    out.append(HeadSpec("orientation", self.size(), "orientation"))
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class EulerEncoding(_HandDesigned):
  """The raw angles, wrapped (periodic) or clipped to their range when decoded."""

  name = "euler"
  loss = "mse"
  title = "Euler angles"

  @override
  def size(self):
    return len(self.setting.angle_dofs)

  @override
  def _to_vector(self, angles):
    return angles

  @override
  def _from_vector(self, x):
    return self.setting.wrap_angles(x)


@dataclasses.dataclass(frozen=True)
class SinCosEncoding(_HandDesigned):
  """(sin a, cos a) of each angle, interleaved; decoded by atan2."""

  name = "sincos"
  loss = "mse"
  title = "(sin, cos) of the angles"

  @override
  def size(self):
    return 2 * len(self.setting.angle_dofs)

  @override
  def _to_vector(self, angles):
    return jnp.stack([jnp.sin(angles), jnp.cos(angles)], axis=-1).reshape(*angles.shape[:-1], -1)

  @override
  def _from_vector(self, x):
    sc = x.reshape(*x.shape[:-1], -1, 2)
    return self.setting.wrap_angles(jnp.arctan2(sc[..., 0], sc[..., 1]))


@dataclasses.dataclass(frozen=True)
class _ViaQuat(_HandDesigned):
  """An orientation vector computed from the camera's quaternion (`Setting.angles_to_quat`) and
  decoded back through one (`Setting.angles_from_quat`)."""

  @abc.abstractmethod
  def _of_quat(self, q: Array) -> Array:
    """(..., 4) unit quaternions, w >= 0 -> (..., size)."""

  @abc.abstractmethod
  def _to_quat(self, x: Array) -> Array:
    """(..., size) -> (..., 4) quaternions of any norm."""

  @override
  def _to_vector(self, angles):
    return self._of_quat(self.setting.angles_to_quat(angles))

  @override
  def _from_vector(self, x):
    return self.setting.angles_from_quat(self._to_quat(x))


@dataclasses.dataclass(frozen=True)
class AxisAngleEncoding(_ViaQuat):
  """Rotation vector angle * axis, angle in [0, pi]."""

  name = "axis_angle"
  loss = "l1"
  title = "axis-angle"

  @override
  def size(self):
    return 3

  @override
  def _of_quat(self, q):
    return rotations.quat_to_axis_angle(q)

  @override
  def _to_quat(self, x):
    return rotations.axis_angle_to_quat(x)


@dataclasses.dataclass(frozen=True)
class QuatEncoding(_ViaQuat):
  """Unit quaternion (w, x, y, z), w >= 0."""

  name = "quat"
  loss = "l1"
  title = "quaternion"

  @override
  def size(self):
    return 4

  @override
  def _of_quat(self, q):
    return q

  @override
  def _to_quat(self, x):
    return x


@dataclasses.dataclass(frozen=True)
class LogQEncoding(_ViaQuat):
  """Log quaternion arccos(w) v / |v| = axis-angle / 2 (MapNet's)."""

  name = "logq"
  loss = "l1"
  title = "log quaternion"

  @override
  def size(self):
    return 3

  @override
  def _of_quat(self, q):
    return rotations.quat_log(q)

  @override
  def _to_quat(self, x):
    return rotations.quat_exp(x)


@dataclasses.dataclass(frozen=True)
class Rot6dEncoding(_ViaQuat):
  """The first two columns of the rotation matrix (Zhou et al., CVPR 2019), decoded by
  Gram-Schmidt; its loss compares the Gram-Schmidt matrices."""

  name = "rot6d"
  loss = "gram_schmidt_frobenius"
  title = "6-D Gram-Schmidt"

  @override
  def size(self):
    return 6

  @override
  def _of_quat(self, q):
    return rotations.matrix_to_rot6d(rotations.quat_to_matrix(q))

  @override
  def _to_quat(self, x):
    return rotations.matrix_to_quat(rotations.rot6d_to_matrix(x))


@dataclasses.dataclass(frozen=True)
class Svd9dEncoding(_ViaQuat):
  """The 9 entries of the rotation matrix (Levinson et al., NeurIPS 2020), decoded by the SVD
  projection onto SO(3); its loss compares the projection."""

  name = "svd9d"
  loss = "svd_frobenius"
  title = "9-D SVD"

  @override
  def size(self):
    return 9

  @override
  def _of_quat(self, q):
    return rotations.quat_to_matrix(q).reshape(*q.shape[:-1], 9)

  @override
  def _to_quat(self, x):
    return rotations.matrix_to_quat(rotations.orthonormalize(x.reshape(*x.shape[:-1], 3, 3)))


# ----------------------------------------------------------------------------------------------
# The registry.

ENCODINGS: dict[str, type[PoseEncoding]] = {
  cls.name: cls
  for cls in (
    GridEncoding,
    MlpEncoding,
    LowDimEncoding,
    EulerEncoding,
    AxisAngleEncoding,
    SinCosEncoding,
    QuatEncoding,
    LogQEncoding,
    Rot6dEncoding,
    Svd9dEncoding,
    UntrainedGridEncoding,
    FrozenGeneratorsGridEncoding,
  )
}
"""name -> encoding class, every encoding of both stages."""

SYNTHESIS_KINDS = tuple(n for n, c in ENCODINGS.items() if c.synthesis_input)
"""The view-synthesis pose inputs (`config.rep.kind`): grid, mlp, lowdim."""

REPRESENTATIONS = tuple(c.table_name() for c in ENCODINGS.values() if c.regression_target)
"""The regression targets (`config.representation`), as regression configs and records name
them: ours (the learned grid), mlp, the hand-designed ones and the learned grid's controls
(untrained, frozen_gen)."""


def get(name: str) -> type[PoseEncoding]:
  """The encoding class a config or a record names (its `name` or its `regression_name`).

  Raises:
    ValueError: an unknown name.
  """
  for cls in ENCODINGS.values():
    if name in (cls.name, cls.regression_name):
      return cls
  raise ValueError(
    f"unknown pose encoding {name!r}; choose one of {SYNTHESIS_KINDS} (view synthesis) or "
    f"{REPRESENTATIONS} (regression)"
  )


def create(
  name: str,
  setting: settings_lib.Setting | str,
  spec: P.PoseSystemSpec | None = None,
  **options: Any,
) -> PoseEncoding:
  """The encoding `name` of a setting (a name is looked up): a per-DOF encoding on `spec`
  (default: the setting's paper-size pose system), with `options` as `PoseEncoding.create`.

  Raises:
    ValueError: an unknown name or setting, or a spec of other columns than the setting's.
  """
  cls = get(name)
  setting = settings_lib.get(setting)
  if cls.per_dof:
    spec = spec or setting.pose_spec()
    setting.check_spec(spec)
  else:
    spec = None
  return cls.create(setting, spec, **options)

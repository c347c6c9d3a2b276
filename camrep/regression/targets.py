"""Pose representations as regression targets (paper section 4.4, Table 1).

A pose regressor predicts a dict of heads {head name: (..., size)}; this module maps poses in the
dataset's pose columns (`camrep.data.sources`) to those heads and back, and holds the
head losses and their weighting. Each representation is one `Codec` record (head size, loss,
encoder, decoder) in `CODECS`; `encode`, `decode` and `head_specs` look it up. Training
hyper-parameters (which loss weighting, learning rates, ...) live in configs/regression.py.
Everything is a pure, batched function; callers jit.

Settings and pose columns (radians; positions in the dataset's unit):

  gqn           (x, y, yaw)                  position (x, y); orientation: yaw about +z
  car           (azimuth, polar)             no position; orientation: the camera rotation
                                             R = Rz(azimuth - pi/2) Rx(pi - polar) Rz(pi)
                                             (intrinsic Euler "rzxz")
  gibson        (x, y, yaw)                  as gqn
  seven_scenes  (x, y, z, theta, phi, psi)   position (x, y, z); orientation
                                             R = Rz(psi - pi) Ry(phi - pi/2) Rx(theta - pi)
                                             (static Euler "sxyz", shifted; seven_scenes.py)

Representations (`REPRESENTATIONS`, described where `CODECS` is built): the learned "ours" and
"mlp" (one head per DOF, named after the DOF), and the baselines euler, axis_angle, sincos, quat,
logq, rot6d, svd9d (a raw "position" head and an "orientation" head). rot6d and svd9d are
continuous in the rotation, which quaternions with w >= 0 and Euler angles are not; for the
yaw-only settings (gqn, gibson) their matrix is a rotation about +z, so 6 and 9 numbers carry one
angle. Every head belongs to a loss group, "position" or "orientation" (Kendall et al. 2017's
L = e^{-s_x} L_pos + s_x + e^{-s_q} L_ori + s_q weighs the two groups).

Rotation conventions are `camrep.rotations`' (quaternions scalar first, (w, x, y, z)).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp

from camrep import pose as P
from camrep import pose_inputs, rotations
from camrep.data import sources
from camrep.models import pose_regressor

Array = jax.Array

SETTINGS = sources.SETTINGS

TWO_PI = 2.0 * math.pi

POSE_COLUMNS: dict[str, tuple[str, ...]] = {
  "gqn": ("x", "y", "yaw"),
  "car": ("azimuth", "polar"),
  "gibson": ("x", "y", "yaw"),
  "seven_scenes": ("x", "y", "z", "theta", "phi", "psi"),
}
"""Pose columns per setting (the sources' `POSE_NAMES`)."""

POSITION_DIM = {"gqn": 2, "car": 0, "gibson": 2, "seven_scenes": 3}

# Per angle column: True if periodic over [0, 2 pi), False if bounded to [0, pi].
_ANGLE_PERIODIC = {
  "gqn": (True,),
  "car": (True, False),
  "gibson": (True,),
  "seven_scenes": (True, False, True),
}

# Shift between the 7-Scenes pose angles and the sxyz Euler angles (c2w_to_dofs).
_SXYZ_SHIFT = (math.pi, math.pi / 2, math.pi)


def _check_setting(setting: str) -> None:
  if setting not in SETTINGS:
    raise ValueError(f"unknown setting {setting!r}; choose one of {SETTINGS}")


def _check_poses(setting: str, poses: Array) -> Array:
  poses = jnp.asarray(poses)
  n = len(POSE_COLUMNS[setting])
  if poses.ndim < 1 or poses.shape[-1] != n:
    raise ValueError(f"{setting} poses have {n} columns {POSE_COLUMNS[setting]}, got {poses.shape}")
  return poses


# --------------------------------------------------------------------------------------------
# The car setting's camera rotation.


def car_rotation(azimuth: Array, polar: Array) -> Array:
  """Camera rotation of a car view: intrinsic "rzxz" (az - pi/2, pi - polar, pi).

  R = Rz(az - pi/2) Rx(pi - polar) Rz(pi); its third column (the optical axis) is
  -(sin p cos a, sin p sin a, cos p): the camera on the z-up sphere looks at the centre.
  (scipy: `Rotation.from_euler("ZXZ", [az - pi/2, pi - polar, pi])`.)

  Args:
    azimuth, polar: (...) angles in radians.

  Returns:
    (..., 3, 3).
  """
  rz, rx = rotations.rot_z, rotations.rot_x
  return rz(azimuth - math.pi / 2) @ rx(math.pi - polar) @ rz(jnp.full_like(azimuth, math.pi))


def car_angles(R: Array) -> Array:
  """(azimuth, polar) of the camera whose rotation is closest to R in viewing direction.

  Inverse of `car_rotation`, read from the optical axis only, so any predicted rotation decodes
  (its roll is ignored): c = -R[:, 2], azimuth = atan2(c_y, c_x) mod 2 pi,
  polar = atan2(hypot(c_x, c_y), c_z) in [0, pi].

  Args:
    R: (..., 3, 3).

  Returns:
    (..., 2).
  """
  c = -R[..., :, 2]
  azimuth = jnp.mod(jnp.arctan2(c[..., 1], c[..., 0]), TWO_PI)
  polar = jnp.arctan2(jnp.hypot(c[..., 0], c[..., 1]), c[..., 2])
  return jnp.stack([azimuth, polar], axis=-1)


# --------------------------------------------------------------------------------------------
# Poses of a setting: positions, angles, rotations.


def split_pose(setting: str, poses: Array) -> tuple[Array, Array]:
  """(positions (..., POSITION_DIM), angles (..., n_angles)) of poses (..., P)."""
  _check_setting(setting)
  poses = _check_poses(setting, poses)
  k = POSITION_DIM[setting]
  return poses[..., :k], poses[..., k:]


def orientation_quat(setting: str, poses: Array) -> Array:
  """The camera orientation of poses (..., P) as quaternions (..., 4), w >= 0 (`angles_to_quat`
  of their angle columns)."""
  return angles_to_quat(setting, split_pose(setting, poses)[1])


def angles_to_quat(setting: str, angles: Array) -> Array:
  """Quaternions (..., 4), w >= 0, of the setting's angle columns (..., n_angles).

  gqn, gibson: yaw about +z; car: `car_rotation`; seven_scenes: sxyz Euler of the unshifted
  angles.
  """
  _check_setting(setting)
  if setting in ("gqn", "gibson"):
    return rotations.yaw_to_quat(angles[..., 0])
  if setting == "car":
    return rotations.matrix_to_quat(car_rotation(angles[..., 0], angles[..., 1]))
  unshifted = angles - jnp.asarray(_SXYZ_SHIFT, angles.dtype)
  return rotations.matrix_to_quat(rotations.euler_sxyz_to_matrix(unshifted))


def angles_from_quat(setting: str, q: Array) -> Array:
  """Inverse of `angles_to_quat`: the setting's angle columns (..., n_angles) of q (..., 4).

  q is normalised first; a rotation outside the setting's family decodes to the closest member
  (yaw: `quat_to_yaw`; car: `car_angles` by optical axis).
  """
  _check_setting(setting)
  q = rotations.standardise_quat(q)
  if setting in ("gqn", "gibson"):
    return rotations.quat_to_yaw(q)[..., None]
  R = rotations.quat_to_matrix(q)
  if setting == "car":
    return car_angles(R)
  return rotations.matrix_to_euler_sxyz(R) + jnp.asarray(_SXYZ_SHIFT, q.dtype)


def wrap_angles(setting: str, angles: Array) -> Array:
  """Map angle columns into their ranges: periodic mod 2 pi, bounded clipped to [0, pi]."""
  periodic = jnp.asarray(_ANGLE_PERIODIC[setting])
  return jnp.where(periodic, jnp.mod(angles, TWO_PI), jnp.clip(angles, 0.0, math.pi))


# --------------------------------------------------------------------------------------------
# Head specs and the per-setting pose systems.


def default_spec(
  setting: str,
  *,
  n_blocks: int | None = None,
  block_size: int | None = None,
  periodic: bool = True,
  exp_method: str = "taylor2",
  polar_variant: str = "binned",
) -> P.PoseSystemSpec:
  """The paper-size pose system of a setting, as synthesis's `pose_spec` builds it
  from the configs' defaults: gqn polar (x, y) on [-1, 1] at 0.1 + yaw; gibson polar on [0, 2] m
  at 0.05 + yaw; car azimuth + polar angle (0..pi, non-periodic); seven_scenes x, y, z on
  [0, 4] x [0, 1.5] x [0, 3] m at 0.1 + theta, phi (0..pi), psi, with 4 x 8 blocks. Angles at
  10 degrees.
  """
  _check_setting(setting)
  ang = math.pi / 18

  def angle(name, high=TWO_PI, per=periodic):
    return P.AngularDof(name, spacing=ang, high=high, periodic=per)

  if setting == "gqn":
    dofs = (P.PolarDof("xy", -1.0, 1.0, 0.1, variant=polar_variant, pair_radius=2.0), angle("yaw"))
  elif setting == "gibson":
    dofs = (P.PolarDof("xy", 0.0, 2.0, 0.05, variant=polar_variant, pair_radius=2.2), angle("yaw"))
  elif setting == "car":
    dofs = (angle("azimuth"), angle("polar", high=math.pi, per=False))
  else:
    dofs = (
      P.LinearDof("x", 0.0, 4.0, 0.1),
      P.LinearDof("y", 0.0, 1.5, 0.1),
      P.LinearDof("z", 0.0, 3.0, 0.1),
      angle("theta"),
      angle("phi", high=math.pi, per=False),
      angle("psi"),
    )
  nb, bs = (4, 8) if setting == "seven_scenes" else (6, 16)
  return P.PoseSystemSpec(
    dofs=dofs,
    n_blocks=n_blocks or nb,
    block_size=block_size or bs,
    exp_method=exp_method,
  )


def _check_spec(setting: str, spec: P.PoseSystemSpec) -> None:
  cols = []
  for d in spec.dofs:
    cols.extend(d.column_names)
  if len(cols) != len(POSE_COLUMNS[setting]):
    raise ValueError(
      f"spec DOFs {spec.names} do not match {setting} columns {POSE_COLUMNS[setting]}"
    )


# --------------------------------------------------------------------------------------------
# Codecs: one record per representation.


@dataclasses.dataclass(frozen=True)
class TargetSpace:
  """Where a representation's targets live: everything static a codec needs besides the poses.

  Attributes:
    setting: one of `SETTINGS`.
    spec: the pose system of a learned representation (None for the baselines).
    mode: "ours": quantisation of targets and candidates, "floor" or "nearest" (the config's
      `model.quantisation`).
    refine_steps: "ours": Gauss-Newton refinement steps when decoding (0: plain arg-min).
    mlp_hidden: "mlp": hidden units of the MLP embedding.
  """

  setting: str
  spec: P.PoseSystemSpec | None = None
  mode: str | None = None
  refine_steps: int = 4
  mlp_hidden: int = 128


@dataclasses.dataclass(frozen=True)
class Codec:
  """One representation as a regression target: head size, loss, encoder and decoder.

  Learned codecs ("ours", "mlp") have one head per DOF of the pose system, named after the DOF;
  baselines have a "position" head (the raw position; none for car) and an "orientation" head.

  Attributes:
    name: the representation's name (`--config.representation`).
    loss: the head loss it trains with (a key of `LOSSES`) unless the config names another.
    size: space -> the size of each DOF head (learned) or of the orientation head (baselines).
    encode: (space, poses (..., P), rep_params) -> targets {head: (..., size)}.
    decode: (space, heads {head: (..., size)}, rep_params) -> poses (..., P); extra heads are
      ignored.
    learned: the targets are learned pose vectors (need `rep_params` and `space.spec`).
    block_norm: a polar DOF with `block_norm` gets a block-normalised head (as `camrep.pose`
      normalises its vectors); every other learned head is unit-normalised.
  """

  name: str
  loss: str
  size: Callable[[TargetSpace], int]
  encode: Callable[[TargetSpace, Array, Any], dict[str, Array]]
  decode: Callable[[TargetSpace, Mapping[str, Array], Any], Array]
  learned: bool = False
  block_norm: bool = False


def _n_angles(space: TargetSpace) -> int:
  return len(_ANGLE_PERIODIC[space.setting])


def _baseline(
  name: str,
  loss: str,
  size: Callable[[TargetSpace], int],
  to_vector: Callable[[str, Array], Array],
  from_vector: Callable[[str, Array], Array],
) -> Codec:
  """A baseline codec from its orientation maps: to_vector(setting, angles (..., n_angles)) ->
  (..., size) and from_vector(setting, (..., size)) -> angles, wrapped into their ranges."""

  def encode(space: TargetSpace, poses: Array, rep_params: Any) -> dict[str, Array]:
    pos, ang = split_pose(space.setting, poses)
    out = {"position": pos} if POSITION_DIM[space.setting] else {}
    out["orientation"] = to_vector(space.setting, ang)
    return out

  def decode(space: TargetSpace, heads: Mapping[str, Array], rep_params: Any) -> Array:
    ang = from_vector(space.setting, heads["orientation"])
    if POSITION_DIM[space.setting]:
      return jnp.concatenate([heads["position"], ang], axis=-1)
    return ang

  return Codec(name, loss, size, encode, decode)


def _via_quat(
  name: str, loss: str, size: int, of_quat: Callable[[Array], Array], to_quat: Callable
) -> Codec:
  """A baseline codec that goes through the orientation's quaternion (`angles_to_quat`):
  of_quat (..., 4) -> (..., size) and to_quat (..., size) -> (..., 4), any norm."""
  return _baseline(
    name,
    loss,
    lambda space: size,
    lambda setting, ang: of_quat(angles_to_quat(setting, ang)),
    lambda setting, x: angles_from_quat(setting, to_quat(x)),
  )


def _sincos(setting: str, ang: Array) -> Array:
  return jnp.stack([jnp.sin(ang), jnp.cos(ang)], axis=-1).reshape(*ang.shape[:-1], -1)


def _from_sincos(setting: str, x: Array) -> Array:
  sc = x.reshape(*x.shape[:-1], -1, 2)
  return wrap_angles(setting, jnp.arctan2(sc[..., 0], sc[..., 1]))


def _as_matrix(x: Array) -> Array:
  return x.reshape(*x.shape[:-1], 3, 3)


def _encode_ours(space: TargetSpace, poses: Array, rep_params: Any) -> dict[str, Array]:
  if space.mode is None:
    raise ValueError('representation "ours" needs the quantisation mode ("floor" or "nearest")')
  return P.embed(jax.lax.stop_gradient(rep_params), space.spec, poses, mode=space.mode)


def _decode_ours(space: TargetSpace, heads: Mapping[str, Array], rep_params: Any) -> Array:
  if space.mode is None:
    raise ValueError('representation "ours" needs the quantisation mode ("floor" or "nearest")')
  vectors = {n: heads[n] for n in space.spec.names}
  return P.decode(rep_params, space.spec, vectors, refine_steps=space.refine_steps, mode=space.mode)


def _encode_mlp(space: TargetSpace, poses: Array, rep_params: Any) -> dict[str, Array]:
  rp = jax.lax.stop_gradient(rep_params)
  return pose_inputs.MlpPoseInput(space.spec, hidden=space.mlp_hidden).embed(rp, poses)


def _decode_mlp(space: TargetSpace, heads: Mapping[str, Array], rep_params: Any) -> Array:
  return pose_inputs.MlpPoseInput(space.spec, hidden=space.mlp_hidden).decode(rep_params, heads)


def _spec_dim(space: TargetSpace) -> int:
  return space.spec.dim


_CODECS = (
  # The frozen learned pose vectors, one unit (or block-normalised) d-vector per DOF
  # (`camrep.pose.embed`, eq. 3 with the setting's quantisation); decoded by arg-min over the
  # candidates (eq. 12) plus Gauss-Newton refinement (`camrep.pose.decode`).
  Codec("ours", "l2", _spec_dim, _encode_ours, _decode_ours, learned=True, block_norm=True),
  # The supplement's baseline: per DOF a 2-layer MLP of the DOF value (hidden 128, leaky ReLU,
  # output d), unit-normalised; decoded by arg-min over the same candidates.
  Codec("mlp", "l2", _spec_dim, _encode_mlp, _decode_mlp, learned=True),
  # The raw angles, wrapped (periodic) or clipped to [0, pi] when decoded.
  _baseline("euler", "mse", _n_angles, lambda setting, ang: ang, wrap_angles),
  # Rotation vector angle * axis, angle in [0, pi].
  _via_quat("axis_angle", "l1", 3, rotations.quat_to_axis_angle, rotations.axis_angle_to_quat),
  # (sin a, cos a) of each angle, interleaved; decoded by atan2.
  _baseline("sincos", "mse", lambda space: 2 * _n_angles(space), _sincos, _from_sincos),
  # Unit quaternion (w, x, y, z), w >= 0.
  _via_quat("quat", "l1", 4, lambda q: q, lambda x: x),
  # Log quaternion arccos(w) v / |v| = axis-angle / 2 (MapNet's).
  _via_quat("logq", "l1", 3, rotations.quat_log, rotations.quat_exp),
  # The first two columns of the rotation matrix (Zhou et al., CVPR 2019), decoded by
  # Gram-Schmidt; loss on the Gram-Schmidt matrices.
  _via_quat(
    "rot6d",
    "gram_schmidt_frobenius",
    6,
    lambda q: rotations.matrix_to_rot6d(rotations.quat_to_matrix(q)),
    lambda x: rotations.matrix_to_quat(rotations.rot6d_to_matrix(x)),
  ),
  # The 9 entries of the rotation matrix (Levinson et al., NeurIPS 2020), decoded by the SVD
  # projection onto SO(3); loss on the projection.
  _via_quat(
    "svd9d",
    "svd_frobenius",
    9,
    lambda q: rotations.quat_to_matrix(q).reshape(*q.shape[:-1], 9),
    lambda x: rotations.matrix_to_quat(rotations.orthonormalize(_as_matrix(x))),
  ),
)

CODECS: dict[str, Codec] = {c.name: c for c in _CODECS}
"""The representations: name -> `Codec`."""

REPRESENTATIONS = tuple(CODECS)
LEARNED = tuple(c.name for c in _CODECS if c.learned)
BASELINES = tuple(c.name for c in _CODECS if not c.learned)


def codec(representation: str) -> Codec:
  """The `Codec` of a representation.

  Raises:
    ValueError: an unknown representation.
  """
  if representation not in CODECS:
    raise ValueError(f"unknown representation {representation!r}; choose one of {REPRESENTATIONS}")
  return CODECS[representation]


def target_space(
  representation: str, setting: str, *, spec: P.PoseSystemSpec | None = None, **options: Any
) -> TargetSpace:
  """The checked `TargetSpace` of (representation, setting): learned representations get `spec`
  (default `default_spec(setting)`), baselines none; `options` are its other fields."""
  _check_setting(setting)
  if codec(representation).learned:
    spec = spec or default_spec(setting)
    _check_spec(setting, spec)
  else:
    spec = None
  return TargetSpace(setting, spec, **options)


def head_specs(
  representation: str, setting: str, *, spec: P.PoseSystemSpec | None = None
) -> tuple[pose_regressor.HeadSpec, ...]:
  """The heads a regressor for (representation, setting) predicts.

  Learned ("ours", "mlp"): one head of size spec.dim per DOF (96 at paper size; 7-Scenes 32),
  group "position" for polar / linear DOFs and "orientation" for angles; norm "block" for a polar
  DOF with block_norm (ours), "unit" otherwise. Baselines: "position" (2 or 3, none for car) and
  "orientation" (euler 1/2/3, sincos 2/4/6, quat 4, logq 3, axis_angle 3, rot6d 6, svd9d 9), both
  unnormalised.

  Args:
    representation: one of `REPRESENTATIONS`.
    setting: one of `SETTINGS`.
    spec: the pose system (learned representations; default `default_spec(setting)`).
  """
  c = codec(representation)
  space = target_space(representation, setting, spec=spec)
  size = c.size(space)
  if c.learned:
    heads = []
    for d in space.spec.dofs:
      group = "orientation" if d.is_angle else "position"
      block = c.block_norm and d.block_norm
      norm, n_blocks = ("block", space.spec.n_blocks) if block else ("unit", 1)
      heads.append(pose_regressor.HeadSpec(d.name, size, group, norm, n_blocks))
    return tuple(heads)
  heads = []
  if POSITION_DIM[setting]:
    heads.append(pose_regressor.HeadSpec("position", POSITION_DIM[setting], "position"))
  heads.append(pose_regressor.HeadSpec("orientation", size, "orientation"))
  return tuple(heads)


def encode(
  representation: str,
  setting: str,
  poses: Array,
  *,
  spec: P.PoseSystemSpec | None = None,
  rep_params: Any = None,
  mode: str | None = None,
  mlp_hidden: int = 128,
) -> dict[str, Array]:
  """Regression targets of poses: {head name: (..., head size)}, as `head_specs` lists them.

  Args:
    representation: one of `REPRESENTATIONS`.
    setting: one of `SETTINGS`.
    poses: (..., P) poses in the setting's columns (`POSE_COLUMNS`).
    spec: pose system of a learned representation (default `default_spec(setting)`).
    rep_params: "ours": the frozen pose-system params; "mlp": `MlpPoseInput.init` params. Taken
      under stop_gradient.
    mode: quantisation of "ours" ("floor" / "nearest"; required there).
    mlp_hidden: hidden size of the MLP embedding.

  Returns:
    dict of (..., size) float arrays.
  """
  c = codec(representation)
  space = target_space(representation, setting, spec=spec, mode=mode, mlp_hidden=mlp_hidden)
  if c.learned and rep_params is None:
    raise ValueError(f"representation {representation!r} needs rep_params")
  return c.encode(space, _check_poses(setting, poses), rep_params)


def decode(
  representation: str,
  setting: str,
  heads: Mapping[str, Array],
  *,
  spec: P.PoseSystemSpec | None = None,
  rep_params: Any = None,
  mode: str | None = None,
  refine_steps: int = 4,
  mlp_hidden: int = 128,
) -> Array:
  """Poses (..., P) from predicted heads: the inverse of `encode`.

  ours: `camrep.pose.decode` (arg-min over the candidate list, eq. 12, then `refine_steps`
  Gauss-Newton steps; 0 gives the authors' plain arg-min). mlp: arg-min over the same candidate
  lists. Baselines: positions as predicted; euler angles wrapped (periodic) or clipped to
  [0, pi]; sincos via atan2; quat / logq / axis_angle / rot6d (Gram-Schmidt) / svd9d (SVD
  projection) via the quaternion (`angles_from_quat`).

  Args:
    heads: {head name: (..., size)}; extra entries are ignored.
    (others as `encode`.)

  Returns:
    (..., P) poses in the setting's columns.
  """
  c = codec(representation)
  space = target_space(
    representation,
    setting,
    spec=spec,
    mode=mode,
    refine_steps=refine_steps,
    mlp_hidden=mlp_hidden,
  )
  if c.learned and rep_params is None:
    raise ValueError(f"representation {representation!r} needs rep_params")
  return c.decode(space, heads, rep_params)


# --------------------------------------------------------------------------------------------
# Losses and weighting.


def _l2(diff: Array) -> Array:
  return jnp.mean(jnp.sum(diff * diff, axis=-1))


def _gram_schmidt_frobenius(pred: Array, target: Array) -> Array:
  d = rotations.rot6d_to_matrix(pred) - rotations.rot6d_to_matrix(target)
  return jnp.mean(jnp.sum(d * d, axis=(-2, -1)))


def _svd_frobenius(pred: Array, target: Array) -> Array:
  d = rotations.orthonormalize(_as_matrix(pred)) - _as_matrix(target)
  return jnp.mean(jnp.sum(d * d, axis=(-2, -1)))


LOSSES: dict[str, Callable[[Array, Array], Array]] = {
  # Mean over examples of the squared L2 distance, mean_b sum_i (pred - target)^2 (ours).
  "l2": lambda pred, target: _l2(pred - target),
  # Mean over all entries of (pred - target)^2 (Euler, sin/cos; torch's MSELoss).
  "mse": lambda pred, target: jnp.mean((pred - target) * (pred - target)),
  # Mean over all entries of |pred - target| (q, log q, axis-angle; 7-Scenes ours).
  "l1": lambda pred, target: jnp.mean(jnp.abs(pred - target)),
  # Mean over examples of ||GS(pred) - GS(target)||_F^2, 6-D (rot6d, Zhou et al. 2019).
  "gram_schmidt_frobenius": _gram_schmidt_frobenius,
  # Mean over examples of ||SVDO+(pred) - target||_F^2, 9-D (svd9d, Levinson et al. 2020).
  "svd_frobenius": _svd_frobenius,
}
"""Head losses: name -> (pred (..., size), target (..., size)) -> scalar."""

# Losses defined on rotations: a position head of the same run takes the "l2" loss instead.
_ROTATION_LOSSES = ("gram_schmidt_frobenius", "svd_frobenius")


def head_loss(kind: str, pred: Array, target: Array) -> Array:
  """Loss of one head, a scalar: `LOSSES[kind](pred, target)`.

  Args:
    kind: a key of `LOSSES`.
    pred, target: (..., size).

  Raises:
    ValueError: an unknown kind, or shapes that differ.
  """
  if kind not in LOSSES:
    raise ValueError(f"unknown loss {kind!r}; choose one of {tuple(LOSSES)}")
  if pred.shape != target.shape:
    raise ValueError(f"pred {pred.shape} and target {target.shape} differ")
  return LOSSES[kind](pred, target)


def group_losses(
  kind: str,
  pred: Mapping[str, Array],
  target: Mapping[str, Array],
  heads: tuple[pose_regressor.HeadSpec, ...],
) -> dict[str, Array]:
  """Sum of the head losses of each group present: {"position": L_pos, "orientation": L_ori}.

  For 7-Scenes "ours" L_pos = L1_x + L1_y + L1_z; for GQN L_pos = L_loc. The rotation losses of
  rot6d / svd9d are for the orientation; positions take their L2 analogue.
  """
  out = {}
  for h in heads:
    k = "l2" if kind in _ROTATION_LOSSES and h.group == "position" else kind
    val = head_loss(k, pred[h.name], target[h.name])
    out[h.group] = out[h.group] + val if h.group in out else val
  return out


def homoscedastic(loss: Array, s: Array, *, factor: float = 1.0) -> Array:
  """Kendall et al. 2017 learned weighting of one term: e^{-s} loss + factor * s.

  d/ds = factor - e^{-s} loss, so s tends to log(loss / factor). `factor` is 3 for the 7-Scenes
  "ours" loss (three DOF terms per group share one s), else 1.
  """
  return jnp.exp(-s) * loss + factor * s


WEIGHTINGS = ("homoscedastic", "fixed")


def init_log_vars(
  weighting: str, init_s: tuple[float, float], *, learn_s: bool = True
) -> dict[str, Array]:
  """Trainable s per group: {"position": (), "orientation": ()} at `init_s` when the weighting
  is homoscedastic and `learn_s`; {} otherwise (fixed weights, or s held at init_s)."""
  if weighting != "homoscedastic" or not learn_s:
    return {}
  return {
    g: jnp.asarray(s, jnp.float32) for g, s in zip(pose_regressor.GROUPS, init_s, strict=True)
  }


def total_loss(
  groups: Mapping[str, Array],
  *,
  weighting: str,
  init_s: tuple[float, float] = (0.0, 0.0),
  s_factor: float = 1.0,
  weights: tuple[float, float] = (1.0, 1.0),
  log_vars: Mapping[str, Array] | None = None,
) -> Array:
  """The regression objective from the group losses.

  homoscedastic: sum over groups of e^{-s_g} L_g + s_factor s_g, with s_g from `log_vars` (the
  trained values) or, when None or empty, the constants `init_s`; fixed: sum over groups of
  w_g L_g with `weights`. Groups absent from `groups` (car has no position) contribute nothing.

  Args:
    groups: {"position": (), "orientation": ()} group losses (either may be absent).
    weighting: one of `WEIGHTINGS`.
    init_s, s_factor, weights: per group, in the order of `pose_regressor.GROUPS`.
    log_vars: the trained s per group (`init_log_vars`).

  Raises:
    ValueError: an unknown weighting.
  """
  if weighting not in WEIGHTINGS:
    raise ValueError(f"unknown weighting {weighting!r}; choose one of {WEIGHTINGS}")
  total = jnp.zeros((), jnp.float32)
  for i, g in enumerate(pose_regressor.GROUPS):
    if g not in groups:
      continue
    if weighting == "homoscedastic":
      s = log_vars[g] if log_vars else jnp.asarray(init_s[i], jnp.float32)
      total = total + homoscedastic(groups[g], s, factor=s_factor)
    else:
      total = total + weights[i] * groups[g]
  return total

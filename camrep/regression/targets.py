"""Pose representations as regression targets (paper section 4.4, Table 1; digest 4.1-4.5).

A pose regressor predicts a dict of heads {head name: (..., size)}; this module maps poses in the
dataset's pose columns (`camrep.data.records.POSE_NAMES`) to those heads and back, and holds the
losses and the per-setting training defaults. Everything is a pure, batched function; callers jit.

Settings and pose columns (radians; positions in the dataset's unit):

  gqn           (x, y, yaw)                  position (x, y); orientation: yaw about +z
  car           (azimuth, polar)             no position; orientation: the camera rotation
                                             R = Rz(azimuth - pi/2) Rx(pi - polar) Rz(pi)
                                             (intrinsic Euler "rzxz", digest 4.2)
  gibson        (x, y, yaw)                  as gqn
  seven_scenes  (x, y, z, theta, phi, psi)   position (x, y, z); orientation
                                             R = Rz(psi - pi) Ry(phi - pi/2) Rx(theta - pi)
                                             (static Euler "sxyz", shifted; seven_scenes.py)

Representations (`REPRESENTATIONS`):

  ours        the frozen learned pose vectors, one unit (or block-normalised) d-vector per DOF,
              `camrep.pose.embed` under stop_gradient with the setting's quantisation; decoded by
              arg-min over candidates plus Gauss-Newton refinement (`camrep.pose.decode`).
  mlp         the supplement's baseline: per DOF a 2-layer MLP (hidden 128, leaky ReLU, output
              d = 96) of the DOF value, unit-normalised; decoded by arg-min over candidates.
  euler       the raw angles (1 for yaw, 2 for car, 3 for 7-Scenes).
  sincos      (sin a, cos a) of each angle, interleaved.
  quat        unit quaternion (w, x, y, z), sign-normalised to w >= 0.
  logq        log quaternion, 3 numbers: log q = arccos(w) (x, y, z) / |(x, y, z)| = axis-angle / 2.
  axis_angle  rotation vector, 3 numbers: angle * axis, angle in [0, pi].
  rot6d       the first two columns of the rotation matrix, 6 numbers (Zhou et al., CVPR 2019);
              decoded by Gram-Schmidt; loss: squared Frobenius distance of the Gram-Schmidt
              matrix to the true one (their L2 on matrices).
  svd9d       the 9 entries of the rotation matrix (Levinson et al., NeurIPS 2020); decoded by
              the SVD projection onto SO(3), U diag(1, 1, det(U V^T)) V^T; loss: squared
              Frobenius distance of that projection to the true matrix (their loss).
              Both are continuous in the rotation, which quaternions with w >= 0 and Euler angles
              are not. For the yaw-only settings (gqn, gibson) the matrix is a rotation about +z,
              so 6 and 9 numbers carry one angle (4 of the 6 and 5 of the 9 are constant).

Baselines put the position, raw, in a "position" head; learned representations have one head per
DOF, named after the DOF. Every head belongs to a loss group, "position" or "orientation"
(Kendall et al. 2017's L = e^{-s_x} L_pos + s_x + e^{-s_q} L_ori + s_q weighs the two groups).

Quaternions are scalar first (w, x, y, z) as in `camrep.metrics`; scipy's are (x, y, z, w).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp

from camrep import pose as P
from camrep import pose_inputs
from camrep.data import records
from camrep.models import pose_regressor

Array = jax.Array

SETTINGS = records.SETTINGS
REPRESENTATIONS = ("ours", "mlp", "euler", "axis_angle", "sincos", "quat", "logq", "rot6d", "svd9d")
LEARNED = ("ours", "mlp")
BASELINES = ("euler", "axis_angle", "sincos", "quat", "logq", "rot6d", "svd9d")
MATRIX_REPRESENTATIONS = ("rot6d", "svd9d")
LOSSES = ("l2", "mse", "l1", "gram_schmidt_frobenius", "svd_frobenius")
_MATRIX_LOSSES = ("gram_schmidt_frobenius", "svd_frobenius")

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


def _check_representation(representation: str) -> None:
  if representation not in REPRESENTATIONS:
    raise ValueError(f"unknown representation {representation!r}; choose one of {REPRESENTATIONS}")


def _check_poses(setting: str, poses: Array) -> Array:
  poses = jnp.asarray(poses)
  n = len(POSE_COLUMNS[setting])
  if poses.ndim < 1 or poses.shape[-1] != n:
    raise ValueError(f"{setting} poses have {n} columns {POSE_COLUMNS[setting]}, got {poses.shape}")
  return poses


# --------------------------------------------------------------------------------------------
# Rotations: quaternions (w, x, y, z), matrices, rotation vectors, log quaternions, Euler angles.


def _safe_norm(x: Array) -> tuple[Array, Array]:
  """(|x|, |x| > 0) over the last axis, with a zero (not NaN) gradient at x = 0."""
  sq = jnp.sum(x * x, axis=-1)
  pos = sq > 0
  return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0), pos


def standardise_quat(q: Array) -> Array:
  """Unit quaternion with w >= 0: q / |q|, negated where w < 0 (q and -q are one rotation).

  Args:
    q: (..., 4) quaternions (w, x, y, z), any nonzero norm.

  Returns:
    (..., 4).
  """
  n, _ = _safe_norm(q)
  q = q / jnp.maximum(n, jnp.finfo(q.dtype).tiny)[..., None]
  return jnp.where(q[..., :1] < 0, -q, q)


def quat_to_matrix(q: Array) -> Array:
  """Rotation matrices of quaternions (normalised first).

  Args:
    q: (..., 4) quaternions (w, x, y, z).

  Returns:
    (..., 3, 3) R such that R p rotates p (the active convention of scipy's `as_matrix`).
  """
  w, x, y, z = jnp.moveaxis(standardise_quat(q), -1, 0)
  rows = [
    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ]
  return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def matrix_to_quat(R: Array) -> Array:
  """Quaternion of a rotation matrix, w >= 0 (Shepperd's method: well conditioned everywhere).

  Of the four expressions 4 q_i q (i = w, x, y, z) built from R, the one with the largest
  |q_i| is normalised, so there is no cancellation near angle pi.

  Args:
    R: (..., 3, 3) rotation matrices.

  Returns:
    (..., 4) unit quaternions (w, x, y, z) with w >= 0.
  """
  r = lambda i, j: R[..., i, j]
  tr = r(0, 0) + r(1, 1) + r(2, 2)
  cands = jnp.stack(
    [
      jnp.stack([1 + tr, r(2, 1) - r(1, 2), r(0, 2) - r(2, 0), r(1, 0) - r(0, 1)], -1),
      jnp.stack(
        [r(2, 1) - r(1, 2), 1 + r(0, 0) - r(1, 1) - r(2, 2), r(0, 1) + r(1, 0), r(0, 2) + r(2, 0)],
        -1,
      ),
      jnp.stack(
        [r(0, 2) - r(2, 0), r(0, 1) + r(1, 0), 1 - r(0, 0) + r(1, 1) - r(2, 2), r(1, 2) + r(2, 1)],
        -1,
      ),
      jnp.stack(
        [r(1, 0) - r(0, 1), r(0, 2) + r(2, 0), r(1, 2) + r(2, 1), 1 - r(0, 0) - r(1, 1) + r(2, 2)],
        -1,
      ),
    ],
    axis=-2,
  )  # (..., 4 candidates, 4)
  diag = jnp.stack(
    [
      1 + tr,
      1 + r(0, 0) - r(1, 1) - r(2, 2),
      1 - r(0, 0) + r(1, 1) - r(2, 2),
      1 - r(0, 0) - r(1, 1) + r(2, 2),
    ],
    -1,
  )
  best = jnp.argmax(diag, axis=-1)
  q = jnp.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
  return standardise_quat(q)


def quat_to_axis_angle(q: Array) -> Array:
  """Rotation vector angle * axis of a quaternion, angle = 2 atan2(|v|, w) in [0, pi].

  Near the identity the ratio angle / |v| is replaced by its limit 2 / w (relative error
  |v|^2 / 3, below float32 eps where used), so values and gradients stay finite at q = 1.

  Args:
    q: (..., 4) quaternions (w, x, y, z), normalised and sign-standardised first.

  Returns:
    (..., 3).
  """
  q = standardise_quat(q)
  w, v = q[..., 0], q[..., 1:]
  n, _ = _safe_norm(v)
  small = n < math.sqrt(jnp.finfo(q.dtype).eps)
  angle = 2.0 * jnp.arctan2(n, w)
  ratio = jnp.where(small, 2.0 / jnp.maximum(w, 0.5), angle / jnp.where(small, 1.0, n))
  return v * ratio[..., None]


def axis_angle_to_quat(aa: Array) -> Array:
  """Quaternion (cos(a/2), sin(a/2) axis) of rotation vectors aa = a * axis, with w >= 0.

  Args:
    aa: (..., 3) rotation vectors (any angle; angles beyond pi wrap).

  Returns:
    (..., 4) unit quaternions (w, x, y, z).
  """
  a, _ = _safe_norm(aa)
  # sin(a/2) / a = sinc(a / (2 pi)) / 2 with numpy's normalised sinc: finite at 0, with gradient.
  q = jnp.concatenate([jnp.cos(a / 2)[..., None], aa * (0.5 * jnp.sinc(a / TWO_PI))[..., None]], -1)
  return standardise_quat(q)


def quat_log(q: Array) -> Array:
  """Log quaternion arccos(w) v / |v| of a unit quaternion with w >= 0 (MapNet's `qlog`).

  Equals half the rotation vector; 0 at the identity.

  Args:
    q: (..., 4) quaternions (w, x, y, z).

  Returns:
    (..., 3).
  """
  return 0.5 * quat_to_axis_angle(q)


def quat_exp(u: Array) -> Array:
  """Inverse of `quat_log`: (cos|u|, sin|u| u / |u|), standardised to w >= 0.

  Args:
    u: (..., 3) log quaternions.

  Returns:
    (..., 4).
  """
  return axis_angle_to_quat(2.0 * u)


def matrix_to_rot6d(R: Array) -> Array:
  """(..., 3, 3) -> (..., 6): the first two columns (Zhou et al. 2019), column after column."""
  return jnp.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


def rot6d_to_matrix(x: Array) -> Array:
  """(..., 6) -> (..., 3, 3) rotations by Gram-Schmidt (Zhou et al. 2019, eq. 16): b1 = a1 / |a1|,
  b2 = the unit part of a2 orthogonal to b1, b3 = b1 x b2; columns (b1, b2, b3)."""
  a1, a2 = x[..., :3], x[..., 3:]
  b1 = a1 / jnp.maximum(jnp.linalg.norm(a1, axis=-1, keepdims=True), 1e-8)
  a2 = a2 - jnp.sum(b1 * a2, axis=-1, keepdims=True) * b1
  b2 = a2 / jnp.maximum(jnp.linalg.norm(a2, axis=-1, keepdims=True), 1e-8)
  return jnp.stack([b1, b2, jnp.cross(b1, b2)], axis=-1)


def svd_orthogonalise(M: Array) -> Array:
  """(..., 3, 3) -> the nearest rotation in Frobenius norm (Levinson et al. 2020, SVDO+):
  U diag(1, 1, det(U V^T)) V^T of M = U S V^T."""
  U, _, Vt = jnp.linalg.svd(M, full_matrices=False)
  det = jnp.linalg.det(U @ Vt)
  D = jnp.concatenate([jnp.ones_like(U[..., :2, 0]), det[..., None]], axis=-1)
  return (U * D[..., None, :]) @ Vt


def _rz(a: Array) -> Array:
  c, s, o, i = jnp.cos(a), jnp.sin(a), jnp.zeros_like(a), jnp.ones_like(a)
  return jnp.stack(
    [jnp.stack([c, -s, o], -1), jnp.stack([s, c, o], -1), jnp.stack([o, o, i], -1)], -2
  )


def _rx(a: Array) -> Array:
  c, s, o, i = jnp.cos(a), jnp.sin(a), jnp.zeros_like(a), jnp.ones_like(a)
  return jnp.stack(
    [jnp.stack([i, o, o], -1), jnp.stack([o, c, -s], -1), jnp.stack([o, s, c], -1)], -2
  )


def _ry(a: Array) -> Array:
  c, s, o, i = jnp.cos(a), jnp.sin(a), jnp.zeros_like(a), jnp.ones_like(a)
  return jnp.stack(
    [jnp.stack([c, o, s], -1), jnp.stack([o, i, o], -1), jnp.stack([-s, o, c], -1)], -2
  )


def euler_sxyz_to_matrix(angles: Array) -> Array:
  """R = Rz(psi) Ry(phi) Rx(theta) (static xyz; scipy `from_euler("xyz", angles)`).

  Args:
    angles: (..., 3) (theta, phi, psi), radians, unshifted.

  Returns:
    (..., 3, 3).
  """
  return _rz(angles[..., 2]) @ _ry(angles[..., 1]) @ _rx(angles[..., 0])


def matrix_to_euler_sxyz(R: Array) -> Array:
  """Static xyz Euler angles as transforms3d `mat2euler(R, 'sxyz')` (and seven_scenes.py).

  Near gimbal lock (cos phi ~ 0) psi is set to 0, as transforms3d does.

  Args:
    R: (..., 3, 3) rotation matrices.

  Returns:
    (..., 3) (theta, phi, psi): theta, psi in [-pi, pi], phi in [-pi/2, pi/2].
  """
  cy = jnp.hypot(R[..., 0, 0], R[..., 1, 0])
  regular = cy > 4 * jnp.finfo(R.dtype).eps
  theta = jnp.where(
    regular, jnp.arctan2(R[..., 2, 1], R[..., 2, 2]), jnp.arctan2(-R[..., 1, 2], R[..., 1, 1])
  )
  phi = jnp.arctan2(-R[..., 2, 0], cy)
  psi = jnp.where(regular, jnp.arctan2(R[..., 1, 0], R[..., 0, 0]), 0.0)
  return jnp.stack([theta, phi, psi], axis=-1)


def car_rotation(azimuth: Array, polar: Array) -> Array:
  """Camera rotation of a car view (digest 4.2): intrinsic "rzxz" (az - pi/2, pi - polar, pi).

  R = Rz(az - pi/2) Rx(pi - polar) Rz(pi); its third column (the optical axis) is
  -(sin p cos a, sin p sin a, cos p): the camera on the z-up sphere looks at the centre.
  (scipy: `Rotation.from_euler("ZXZ", [az - pi/2, pi - polar, pi])`.)

  Args:
    azimuth, polar: (...) angles in radians.

  Returns:
    (..., 3, 3).
  """
  return _rz(azimuth - math.pi / 2) @ _rx(math.pi - polar) @ _rz(jnp.full_like(azimuth, math.pi))


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


def yaw_to_quat(yaw: Array) -> Array:
  """Quaternion of a rotation by yaw about +z, w >= 0: (..., ) -> (..., 4)."""
  h = 0.5 * yaw
  z = jnp.zeros_like(h)
  return standardise_quat(jnp.stack([jnp.cos(h), z, z, jnp.sin(h)], axis=-1))


def quat_to_yaw(q: Array) -> Array:
  """Yaw of the rotation about +z closest to q: 2 atan2(q_z, q_w) mod 2 pi, (..., 4) -> (...).

  (The z-rotation (cos a, 0, 0, sin a) maximising |<q, .>| has a = atan2(q_z, q_w).)
  """
  return jnp.mod(2.0 * jnp.arctan2(q[..., 3], q[..., 0]), TWO_PI)


# --------------------------------------------------------------------------------------------
# Poses of a setting: positions, angles, rotations.


def split_pose(setting: str, poses: Array) -> tuple[Array, Array]:
  """(positions (..., POSITION_DIM), angles (..., n_angles)) of poses (..., P)."""
  _check_setting(setting)
  poses = _check_poses(setting, poses)
  k = POSITION_DIM[setting]
  return poses[..., :k], poses[..., k:]


def orientation_quat(setting: str, poses: Array) -> Array:
  """The camera orientation of poses (..., P) as quaternions (..., 4), w >= 0.

  gqn, gibson: yaw about +z; car: `car_rotation`; seven_scenes: sxyz Euler of the unshifted
  angles.
  """
  _, ang = split_pose(setting, poses)
  if setting in ("gqn", "gibson"):
    return yaw_to_quat(ang[..., 0])
  if setting == "car":
    return matrix_to_quat(car_rotation(ang[..., 0], ang[..., 1]))
  return matrix_to_quat(euler_sxyz_to_matrix(ang - jnp.asarray(_SXYZ_SHIFT, ang.dtype)))


def angles_from_quat(setting: str, q: Array) -> Array:
  """Inverse of `orientation_quat`: the setting's angle columns (..., n_angles) of q (..., 4).

  q is normalised first; a rotation outside the setting's family decodes to the closest member
  (yaw: `quat_to_yaw`; car: `car_angles` by optical axis).
  """
  _check_setting(setting)
  q = standardise_quat(q)
  if setting in ("gqn", "gibson"):
    return quat_to_yaw(q)[..., None]
  R = quat_to_matrix(q)
  if setting == "car":
    return car_angles(R)
  return matrix_to_euler_sxyz(R) + jnp.asarray(_SXYZ_SHIFT, q.dtype)


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
  """The paper-size pose system of a setting (digest 1.7), as synthesis's `pose_spec` builds it
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


def _orientation_size(setting: str, representation: str) -> int:
  n_angles = len(_ANGLE_PERIODIC[setting])
  sizes = {"euler": n_angles, "sincos": 2 * n_angles, "quat": 4, "logq": 3, "axis_angle": 3}
  return {**sizes, "rot6d": 6, "svd9d": 9}[representation]


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
  _check_setting(setting)
  _check_representation(representation)
  if representation in LEARNED:
    spec = spec or default_spec(setting)
    _check_spec(setting, spec)
    heads = []
    for d in spec.dofs:
      group = "orientation" if d.is_angle else "position"
      block = representation == "ours" and d.block_norm
      heads.append(
        pose_regressor.HeadSpec(
          d.name, spec.dim, group, "block" if block else "unit", spec.n_blocks if block else 1
        )
      )
    return tuple(heads)
  heads = []
  if POSITION_DIM[setting]:
    heads.append(pose_regressor.HeadSpec("position", POSITION_DIM[setting], "position"))
  heads.append(
    pose_regressor.HeadSpec(
      "orientation", _orientation_size(setting, representation), "orientation"
    )
  )
  return tuple(heads)


# --------------------------------------------------------------------------------------------
# Encoding poses as targets, decoding predictions.


def encode(
  representation: str,
  setting: str,
  poses: Array,
  *,
  spec: P.PoseSystemSpec | None = None,
  rep_params: Mapping | None = None,
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
    mode: quantisation of "ours" ("floor" / "nearest"); default the setting's (`defaults`).
    mlp_hidden: hidden size of the MLP embedding.

  Returns:
    dict of (..., size) float arrays.
  """
  _check_setting(setting)
  _check_representation(representation)
  poses = _check_poses(setting, poses)
  if representation in LEARNED:
    if rep_params is None:
      raise ValueError(f"representation {representation!r} needs rep_params")
    spec = spec or default_spec(setting)
    _check_spec(setting, spec)
    rp = jax.lax.stop_gradient(rep_params)
    if representation == "ours":
      mode = mode or defaults(setting, "ours").quantisation
      return P.embed(rp, spec, poses, mode=mode)
    return pose_inputs.MlpPoseInput(spec, hidden=mlp_hidden).embed(rp, poses)
  pos, ang = split_pose(setting, poses)
  if representation == "euler":
    ori = ang
  elif representation == "sincos":
    ori = jnp.stack([jnp.sin(ang), jnp.cos(ang)], axis=-1).reshape(*ang.shape[:-1], -1)
  else:
    q = orientation_quat(setting, poses)
    ori = {
      "quat": lambda: q,
      "logq": lambda: quat_log(q),
      "axis_angle": lambda: quat_to_axis_angle(q),
      "rot6d": lambda: matrix_to_rot6d(quat_to_matrix(q)),
      "svd9d": lambda: quat_to_matrix(q).reshape(*q.shape[:-1], 9),
    }[representation]()
  out = {"position": pos} if POSITION_DIM[setting] else {}
  out["orientation"] = ori
  return out


def decode(
  representation: str,
  setting: str,
  heads: Mapping[str, Array],
  *,
  spec: P.PoseSystemSpec | None = None,
  rep_params: Mapping | None = None,
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
  _check_setting(setting)
  _check_representation(representation)
  if representation in LEARNED:
    if rep_params is None:
      raise ValueError(f"representation {representation!r} needs rep_params")
    spec = spec or default_spec(setting)
    _check_spec(setting, spec)
    if representation == "ours":
      mode = mode or defaults(setting, "ours").quantisation
      vectors = {n: heads[n] for n in spec.names}
      return P.decode(rep_params, spec, vectors, refine_steps=refine_steps, mode=mode)
    return pose_inputs.MlpPoseInput(spec, hidden=mlp_hidden).decode(rep_params, heads)
  ori = heads["orientation"]
  if representation == "euler":
    ang = wrap_angles(setting, ori)
  elif representation == "sincos":
    sc = ori.reshape(*ori.shape[:-1], -1, 2)
    ang = wrap_angles(setting, jnp.arctan2(sc[..., 0], sc[..., 1]))
  else:
    to_q = {
      "quat": lambda x: x,
      "logq": quat_exp,
      "axis_angle": axis_angle_to_quat,
      "rot6d": lambda x: matrix_to_quat(rot6d_to_matrix(x)),
      "svd9d": lambda x: matrix_to_quat(svd_orthogonalise(x.reshape(*x.shape[:-1], 3, 3))),
    }
    ang = angles_from_quat(setting, to_q[representation](ori))
  if POSITION_DIM[setting]:
    return jnp.concatenate([heads["position"], ang], axis=-1)
  return ang


# --------------------------------------------------------------------------------------------
# Losses and weighting.


def head_loss(kind: str, pred: Array, target: Array) -> Array:
  """Loss of one head, a scalar (digest 4.1-4.5).

  "l2": mean over examples of the squared L2 distance, mean_b sum_i (pred - target)^2 (ours);
  "mse": mean over all entries of (pred - target)^2 (Euler, sin/cos; torch MSELoss);
  "l1": mean over all entries of |pred - target| (q, log q, axis-angle; 7-Scenes ours);
  "gram_schmidt_frobenius": mean over examples of ||GS(pred) - GS(target)||_F^2, pred and target
  6-D (rot6d, Zhou et al. 2019);
  "svd_frobenius": mean over examples of ||SVDO+(pred) - target||_F^2, pred and target 9-D
  (svd9d, Levinson et al. 2020).

  Args:
    pred, target: (..., size).
  """
  if pred.shape != target.shape:
    raise ValueError(f"pred {pred.shape} and target {target.shape} differ")
  diff = pred - target
  if kind == "l2":
    return jnp.mean(jnp.sum(diff * diff, axis=-1))
  if kind == "mse":
    return jnp.mean(diff * diff)
  if kind == "l1":
    return jnp.mean(jnp.abs(diff))
  if kind == "gram_schmidt_frobenius":
    d = rot6d_to_matrix(pred) - rot6d_to_matrix(target)
    return jnp.mean(jnp.sum(d * d, axis=(-2, -1)))
  if kind == "svd_frobenius":
    m = lambda x: x.reshape(*x.shape[:-1], 3, 3)
    d = svd_orthogonalise(m(pred)) - m(target)
    return jnp.mean(jnp.sum(d * d, axis=(-2, -1)))
  raise ValueError(f"unknown loss {kind!r}; choose one of {LOSSES}")


def group_losses(
  kind: str,
  pred: Mapping[str, Array],
  target: Mapping[str, Array],
  heads: tuple[pose_regressor.HeadSpec, ...],
) -> dict[str, Array]:
  """Sum of the head losses of each group present: {"position": L_pos, "orientation": L_ori}.

  For 7-Scenes "ours" L_pos = L1_x + L1_y + L1_z (digest 4.4); for GQN L_pos = L_loc.
  """
  out = {}
  for h in heads:
    # The matrix losses of rot6d / svd9d are for the orientation; positions take their L2 analogue.
    k = "l2" if kind in _MATRIX_LOSSES and h.group == "position" else kind
    val = head_loss(k, pred[h.name], target[h.name])
    out[h.group] = out[h.group] + val if h.group in out else val
  return out


def homoscedastic(loss: Array, s: Array, *, factor: float = 1.0) -> Array:
  """Kendall et al. 2017 learned weighting of one term: e^{-s} loss + factor * s.

  d/ds = factor - e^{-s} loss, so s tends to log(loss / factor). `factor` is 3 for the 7-Scenes
  "ours" loss (three DOF terms per group share one s, digest 4.4), else 1.
  """
  return jnp.exp(-s) * loss + factor * s


@dataclasses.dataclass(frozen=True)
class RegressionDefaults:
  """Training defaults of one (setting, representation) pair (digest 4.1-4.5).

  Attributes:
    loss: head loss kind, see `head_loss`.
    weighting: "homoscedastic" (learned or fixed s per group) or "fixed" (constant weights).
    init_s: initial (s_position, s_orientation) of the homoscedastic weighting.
    s_factor: factor of s in `homoscedastic`.
    learn_s: whether s_position, s_orientation are trained.
    weights: fixed (position, orientation) weights of weighting="fixed".
    lr: Adam learning rate.
    weight_decay: coupled L2 added to the gradients before Adam (7-Scenes; also on s).
    extra_fc: units of the extra dense layer before the heads (baselines' parameter-count
      equaliser), or None.
    quantisation: "ours": quantisation of targets and candidates ("floor" or "nearest").
  """

  loss: str
  weighting: str
  init_s: tuple[float, float] = (0.0, 0.0)
  s_factor: float = 1.0
  learn_s: bool = True
  weights: tuple[float, float] = (1.0, 1.0)
  lr: float = 1e-4
  weight_decay: float = 0.0
  extra_fc: int | None = None
  quantisation: str = "floor"


# "ours" per setting (digest 4.1-4.4). Baselines (digest 4.5): MSE for euler / sincos, L1 for
# quat / logq / axis_angle, all with Kendall's weighting from s_pos = 0, s_ori = -3 (learned),
# the setting's learning rate (the paper's tuned values are not given) and the extra FC layer.
_DEFAULTS_OURS: dict[str, RegressionDefaults] = {
  "gqn": RegressionDefaults(
    "l2", "homoscedastic", init_s=(-math.log(20.0), -math.log(5.0)), lr=1e-4, quantisation="floor"
  ),
  "car": RegressionDefaults("l2", "fixed", weights=(1.0, 1.0), lr=1e-3, quantisation="floor"),
  "gibson": RegressionDefaults(
    "l2", "fixed", weights=(20.0, 10.0), lr=1e-3, quantisation="nearest"
  ),
  "seven_scenes": RegressionDefaults(
    "l1",
    "homoscedastic",
    init_s=(-3.0, -3.0),
    s_factor=3.0,
    lr=5e-5,
    weight_decay=5e-4,
    quantisation="floor",
  ),
}
_EXTRA_FC = {"gqn": 196, "car": 256, "gibson": 192, "seven_scenes": None}
_BASELINE_LOSS = {
  "euler": "mse",
  "sincos": "mse",
  "quat": "l1",
  "logq": "l1",
  "axis_angle": "l1",
  "rot6d": "gram_schmidt_frobenius",  # Zhou et al. 2019
  "svd9d": "svd_frobenius",  # Levinson et al. 2020
}

DEFAULTS: dict[tuple[str, str], RegressionDefaults] = {}
"""The table: (setting, representation) -> `RegressionDefaults`."""
for _s in SETTINGS:
  for _r in REPRESENTATIONS:
    if _r in LEARNED:
      DEFAULTS[_s, _r] = _DEFAULTS_OURS[_s]
    else:
      DEFAULTS[_s, _r] = dataclasses.replace(
        _DEFAULTS_OURS[_s],
        loss=_BASELINE_LOSS[_r],
        weighting="homoscedastic",
        init_s=(0.0, -3.0),
        s_factor=1.0,
        learn_s=True,
        extra_fc=_EXTRA_FC[_s],
      )


def defaults(setting: str, representation: str) -> RegressionDefaults:
  """The `DEFAULTS` entry of (setting, representation)."""
  _check_setting(setting)
  _check_representation(representation)
  return DEFAULTS[setting, representation]


def init_log_vars(cfg: RegressionDefaults) -> dict[str, Array]:
  """Trainable s per group: {"position": (), "orientation": ()} at cfg.init_s when the weighting
  is homoscedastic with learn_s; {} otherwise (fixed weights, or s held at cfg.init_s)."""
  if cfg.weighting != "homoscedastic" or not cfg.learn_s:
    return {}
  return {
    g: jnp.asarray(s, jnp.float32) for g, s in zip(pose_regressor.GROUPS, cfg.init_s, strict=True)
  }


def total_loss(
  cfg: RegressionDefaults,
  groups: Mapping[str, Array],
  *,
  log_vars: Mapping[str, Array] | None = None,
) -> Array:
  """The regression objective from the group losses.

  homoscedastic: sum over groups of e^{-s_g} L_g + s_factor s_g, with s_g from `log_vars` (the
  trained values) or, when None, the constants cfg.init_s; fixed: sum over groups of w_g L_g.
  Groups absent from `groups` (car has no position) contribute nothing.
  """
  total = jnp.zeros((), jnp.float32)
  for i, g in enumerate(pose_regressor.GROUPS):
    if g not in groups:
      continue
    if cfg.weighting == "homoscedastic":
      s = log_vars[g] if log_vars else jnp.asarray(cfg.init_s[i], jnp.float32)
      total = total + homoscedastic(groups[g], s, factor=cfg.s_factor)
    elif cfg.weighting == "fixed":
      total = total + cfg.weights[i] * groups[g]
    else:
      raise ValueError(f"unknown weighting {cfg.weighting!r}")
  return total

"""Rotations of 3-space: quaternions, matrices, rotation vectors, 6-D and 9-D forms, Euler angles.

Shared by the data readers (7-Scenes poses, `camrep.data.readers.seven_scenes`) and the regression
targets (`camrep.regression.targets`). Every function is pure and batched over leading axes, and
runs on two backends, chosen by its first argument:

  a JAX array (or a tracer under jit / grad)  computed with jax.numpy in the array's dtype;
  anything else (NumPy arrays, lists)         computed with NumPy in float64, NumPy out: what
                                              the readers need to turn pose files into exact
                                              float64 poses on the host.

Conventions: quaternions are scalar first, (w, x, y, z), as in `camrep.metrics` (scipy's are
(x, y, z, w)); a matrix R acts on column vectors, R p (the active convention of scipy's
`Rotation.as_matrix`); angles are in radians. Functions that return a quaternion standardise
it to w >= 0 (q and -q are one rotation).
"""

from __future__ import annotations

import math
from types import ModuleType

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array

TWO_PI = 2.0 * math.pi


def _backend(x) -> tuple[ModuleType, Array | np.ndarray]:
  """(array namespace, x in it): jax.numpy for JAX arrays and tracers (dtype kept), else NumPy
  in float64."""
  if isinstance(x, jax.Array):
    return jnp, x
  return np, np.asarray(x, dtype=np.float64)


def _safe_norm(xp: ModuleType, x):
  """|x| over the last axis, with a zero (not NaN) gradient at x = 0."""
  sq = xp.sum(x * x, axis=-1)
  pos = sq > 0
  return xp.where(pos, xp.sqrt(xp.where(pos, sq, 1.0)), 0.0)


# --------------------------------------------------------------------------------------------
# Quaternions and matrices.


def standardise_quat(q):
  """Unit quaternion with w >= 0: q / |q|, negated where w < 0 (q and -q are one rotation).

  Args:
    q: (..., 4) quaternions (w, x, y, z), any nonzero norm.

  Returns:
    (..., 4).
  """
  xp, q = _backend(q)
  n = _safe_norm(xp, q)
  q = q / xp.maximum(n, xp.finfo(q.dtype).tiny)[..., None]
  return xp.where(q[..., :1] < 0, -q, q)


def quat_to_matrix(q):
  """Rotation matrices of quaternions (normalised first).

  Args:
    q: (..., 4) quaternions (w, x, y, z), any nonzero norm.

  Returns:
    (..., 3, 3) R such that R p rotates p.
  """
  xp, q = _backend(q)
  w, x, y, z = xp.moveaxis(standardise_quat(q), -1, 0)
  rows = [
    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ]
  return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def matrix_to_quat(R):
  """Quaternion of a rotation matrix, w >= 0 (Shepperd's method: well conditioned everywhere).

  Of the four expressions 4 q_i q (i = w, x, y, z) built from R, the one with the largest
  |q_i| is normalised, so there is no cancellation near angle pi.

  Args:
    R: (..., 3, 3) rotation matrices.

  Returns:
    (..., 4) unit quaternions (w, x, y, z) with w >= 0.
  """
  xp, R = _backend(R)
  r = lambda i, j: R[..., i, j]
  tr = r(0, 0) + r(1, 1) + r(2, 2)
  cands = xp.stack(
    [
      xp.stack([1 + tr, r(2, 1) - r(1, 2), r(0, 2) - r(2, 0), r(1, 0) - r(0, 1)], -1),
      xp.stack(
        [r(2, 1) - r(1, 2), 1 + r(0, 0) - r(1, 1) - r(2, 2), r(0, 1) + r(1, 0), r(0, 2) + r(2, 0)],
        -1,
      ),
      xp.stack(
        [r(0, 2) - r(2, 0), r(0, 1) + r(1, 0), 1 - r(0, 0) + r(1, 1) - r(2, 2), r(1, 2) + r(2, 1)],
        -1,
      ),
      xp.stack(
        [r(1, 0) - r(0, 1), r(0, 2) + r(2, 0), r(1, 2) + r(2, 1), 1 - r(0, 0) - r(1, 1) + r(2, 2)],
        -1,
      ),
    ],
    axis=-2,
  )  # (..., 4 candidates, 4)
  diag = xp.stack(
    [
      1 + tr,
      1 + r(0, 0) - r(1, 1) - r(2, 2),
      1 - r(0, 0) + r(1, 1) - r(2, 2),
      1 - r(0, 0) - r(1, 1) + r(2, 2),
    ],
    -1,
  )
  best = xp.argmax(diag, axis=-1)
  q = xp.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
  return standardise_quat(q)


def orthonormalize(M):
  """The nearest rotation in Frobenius norm: U diag(1, 1, sign det(U V^T)) V^T of M = U S V^T.

  The SVD projection onto SO(3) (Levinson et al., NeurIPS 2020, "SVDO+"); a reflection is
  projected to a proper rotation, not kept. Used on 7-Scenes rotations (not exactly
  orthonormal) and to decode 9-D regression outputs.

  Args:
    M: (..., 3, 3) matrices.

  Returns:
    (..., 3, 3) rotation matrices.
  """
  xp, M = _backend(M)
  U, _, Vt = xp.linalg.svd(M, full_matrices=False)
  det = xp.linalg.det(U @ Vt)
  D = xp.concatenate([xp.ones_like(U[..., :2, 0]), xp.sign(det)[..., None]], axis=-1)
  return (U * D[..., None, :]) @ Vt


# --------------------------------------------------------------------------------------------
# Rotation vectors and log quaternions.


def quat_to_axis_angle(q):
  """Rotation vector angle * axis of a quaternion, angle = 2 atan2(|v|, w) in [0, pi].

  Near the identity the ratio angle / |v| is replaced by its limit 2 / w (relative error
  |v|^2 / 3, below float32 eps where used), so values and gradients stay finite at q = 1.

  Args:
    q: (..., 4) quaternions (w, x, y, z), normalised and sign-standardised first.

  Returns:
    (..., 3).
  """
  xp, q = _backend(q)
  q = standardise_quat(q)
  w, v = q[..., 0], q[..., 1:]
  n = _safe_norm(xp, v)
  small = n < math.sqrt(xp.finfo(q.dtype).eps)
  angle = 2.0 * xp.arctan2(n, w)
  ratio = xp.where(small, 2.0 / xp.maximum(w, 0.5), angle / xp.where(small, 1.0, n))
  return v * ratio[..., None]


def axis_angle_to_quat(aa):
  """Quaternion (cos(a/2), sin(a/2) axis) of rotation vectors aa = a * axis, with w >= 0.

  Args:
    aa: (..., 3) rotation vectors (any angle; angles beyond pi wrap).

  Returns:
    (..., 4) unit quaternions (w, x, y, z).
  """
  xp, aa = _backend(aa)
  a = _safe_norm(xp, aa)
  # sin(a/2) / a = sinc(a / (2 pi)) / 2 with numpy's normalised sinc: finite at 0, with gradient.
  half = (0.5 * xp.sinc(a / TWO_PI))[..., None]
  return standardise_quat(xp.concatenate([xp.cos(a / 2)[..., None], aa * half], -1))


def quat_log(q):
  """Log quaternion arccos(w) v / |v| of a unit quaternion with w >= 0 (MapNet's `qlog`).

  Equals half the rotation vector; 0 at the identity.

  Args:
    q: (..., 4) quaternions (w, x, y, z).

  Returns:
    (..., 3).
  """
  return 0.5 * quat_to_axis_angle(q)


def quat_exp(u):
  """Inverse of `quat_log`: (cos|u|, sin|u| u / |u|), standardised to w >= 0.

  Args:
    u: (..., 3) log quaternions.

  Returns:
    (..., 4).
  """
  return axis_angle_to_quat(2.0 * _backend(u)[1])


# --------------------------------------------------------------------------------------------
# Continuous 6-D representation (Zhou et al., CVPR 2019).


def matrix_to_rot6d(R):
  """(..., 3, 3) -> (..., 6): the first two columns (Zhou et al. 2019), column after column."""
  xp, R = _backend(R)
  return xp.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


def rot6d_to_matrix(x):
  """(..., 6) -> (..., 3, 3) rotations by Gram-Schmidt (Zhou et al. 2019, eq. 16): b1 = a1 / |a1|,
  b2 = the unit part of a2 orthogonal to b1, b3 = b1 x b2; columns (b1, b2, b3)."""
  xp, x = _backend(x)
  a1, a2 = x[..., :3], x[..., 3:]
  b1 = a1 / xp.maximum(xp.linalg.norm(a1, axis=-1, keepdims=True), 1e-8)
  a2 = a2 - xp.sum(b1 * a2, axis=-1, keepdims=True) * b1
  b2 = a2 / xp.maximum(xp.linalg.norm(a2, axis=-1, keepdims=True), 1e-8)
  return xp.stack([b1, b2, xp.cross(b1, b2)], axis=-1)


# --------------------------------------------------------------------------------------------
# Rotations about the axes and Euler angles.


def rot_x(a):
  """(...) angles -> (..., 3, 3) rotations about +x."""
  xp, a = _backend(a)
  c, s, o, i = xp.cos(a), xp.sin(a), xp.zeros_like(a), xp.ones_like(a)
  return xp.stack([xp.stack([i, o, o], -1), xp.stack([o, c, -s], -1), xp.stack([o, s, c], -1)], -2)


def rot_y(a):
  """(...) angles -> (..., 3, 3) rotations about +y."""
  xp, a = _backend(a)
  c, s, o, i = xp.cos(a), xp.sin(a), xp.zeros_like(a), xp.ones_like(a)
  return xp.stack([xp.stack([c, o, s], -1), xp.stack([o, i, o], -1), xp.stack([-s, o, c], -1)], -2)


def rot_z(a):
  """(...) angles -> (..., 3, 3) rotations about +z."""
  xp, a = _backend(a)
  c, s, o, i = xp.cos(a), xp.sin(a), xp.zeros_like(a), xp.ones_like(a)
  return xp.stack([xp.stack([c, -s, o], -1), xp.stack([s, c, o], -1), xp.stack([o, o, i], -1)], -2)


def euler_sxyz_to_matrix(angles):
  """R = Rz(psi) Ry(phi) Rx(theta): static xyz Euler angles (scipy `from_euler("xyz", angles)`).

  Written out entry by entry rather than as the product of `rot_z`, `rot_y`, `rot_x`.

  Args:
    angles: (..., 3) (theta, phi, psi).

  Returns:
    (..., 3, 3).
  """
  xp, a = _backend(angles)
  ct, cp, cs = xp.cos(a[..., 0]), xp.cos(a[..., 1]), xp.cos(a[..., 2])
  st, sp, ss = xp.sin(a[..., 0]), xp.sin(a[..., 1]), xp.sin(a[..., 2])
  rows = [
    [cs * cp, cs * sp * st - ss * ct, cs * sp * ct + ss * st],
    [ss * cp, ss * sp * st + cs * ct, ss * sp * ct - cs * st],
    [-sp, cp * st, cp * ct],
  ]
  return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def matrix_to_euler_sxyz(R):
  """Static xyz Euler angles, exactly as transforms3d `mat2euler(R, 'sxyz')`.

  Inverse of `euler_sxyz_to_matrix` (scipy `as_euler("xyz")`). Near gimbal lock (cos phi ~ 0,
  below 4 eps of the dtype) psi is set to 0 and the whole in-plane angle goes into theta, as
  transforms3d does.

  Args:
    R: (..., 3, 3) rotation matrices.

  Returns:
    (..., 3) (theta, phi, psi): theta, psi in [-pi, pi], phi in [-pi/2, pi/2].
  """
  xp, R = _backend(R)
  cy = xp.hypot(R[..., 0, 0], R[..., 1, 0])
  regular = cy > xp.finfo(R.dtype).eps * 4.0
  theta = xp.where(
    regular, xp.arctan2(R[..., 2, 1], R[..., 2, 2]), xp.arctan2(-R[..., 1, 2], R[..., 1, 1])
  )
  phi = xp.arctan2(-R[..., 2, 0], cy)
  psi = xp.where(regular, xp.arctan2(R[..., 1, 0], R[..., 0, 0]), 0.0)
  return xp.stack([theta, phi, psi], axis=-1)


def yaw_to_quat(yaw):
  """Quaternion of a rotation by yaw about +z, w >= 0: (...) -> (..., 4)."""
  xp, yaw = _backend(yaw)
  h = 0.5 * yaw
  z = xp.zeros_like(h)
  return standardise_quat(xp.stack([xp.cos(h), z, z, xp.sin(h)], axis=-1))


def quat_to_yaw(q):
  """Yaw of the rotation about +z closest to q: 2 atan2(q_z, q_w) mod 2 pi, (..., 4) -> (...).

  (The z-rotation (cos a, 0, 0, sin a) maximising |<q, .>| has a = atan2(q_z, q_w).)
  """
  xp, q = _backend(q)
  return xp.mod(2.0 * xp.arctan2(q[..., 3], q[..., 0]), TWO_PI)


__all__ = [
  "axis_angle_to_quat",
  "euler_sxyz_to_matrix",
  "matrix_to_euler_sxyz",
  "matrix_to_quat",
  "matrix_to_rot6d",
  "orthonormalize",
  "quat_exp",
  "quat_log",
  "quat_to_axis_angle",
  "quat_to_matrix",
  "quat_to_yaw",
  "rot6d_to_matrix",
  "rot_x",
  "rot_y",
  "rot_z",
  "standardise_quat",
  "yaw_to_quat",
]

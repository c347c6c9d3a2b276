"""Tests of camrep.rotations against scipy.spatial.transform.Rotation, on both backends.

Every conversion runs on NumPy (float64 in, NumPy float64 out: the readers' path) and on JAX in
float64 (`x64`); float32 accuracy and gradients are JAX-only. Rotations include random ones,
near-identity ones (1e-9 .. 1e-3 rad) and near-pi ones (pi - 1e-6 .. pi - 1e-2), over several
leading batch shapes.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from camrep import rotations as rot
from tests.utils import BATCH_SHAPES, FAST_BATCH_SHAPE, assert_close, slow_except, x64

# Compilation dominates these small shapes; the numerics are checked to the same tolerances.
pytestmark = pytest.mark.usefixtures("fast_compile")

TWO_PI = 2 * math.pi
BACKENDS = ("numpy", "jax")


@pytest.fixture(params=BACKENDS)
def xp(request):
  """Converts test inputs to the backend under test (JAX: in float64) and checks outputs."""

  class Backend:
    name = request.param

    def __call__(self, x):
      return np.asarray(x, np.float64) if self.name == "numpy" else jnp.asarray(x)

    def check(self, y):
      """The backend's output type: NumPy float64 in, NumPy float64 out; JAX in, JAX out."""
      want = np.ndarray if self.name == "numpy" else jax.Array
      assert isinstance(y, want) and y.dtype == np.float64, (type(y), y.dtype)
      return np.asarray(y)

  with x64():
    yield Backend()


def _wxyz(r: Rotation) -> np.ndarray:
  """scipy (x, y, z, w) -> (w, x, y, z) with w >= 0."""
  q = np.roll(r.as_quat(), 1, axis=-1)
  return np.where(q[..., :1] < 0, -q, q)


def _rotations(n=200, seed=0) -> Rotation:
  """Random rotations plus near-identity and near-pi ones, and the identity."""
  rng = np.random.default_rng(seed)
  axes = rng.normal(size=(20, 3))
  axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
  small = np.geomspace(1e-9, 1e-3, 10).repeat(2)[:, None] * axes
  near_pi = (math.pi - np.geomspace(1e-6, 1e-2, 10).repeat(2))[:, None] * axes
  rand = Rotation.random(n, random_state=seed).as_rotvec()
  return Rotation.from_rotvec(np.concatenate([rand, small, near_pi, np.zeros((1, 3))]))


def _batched(x: np.ndarray, shape: tuple[int, ...], item_ndim: int) -> np.ndarray:
  """The first prod(shape) items of x (items of `item_ndim` trailing axes), as (*shape, item)."""
  n = int(np.prod(shape))
  return x[:n].reshape(*shape, *x.shape[x.ndim - item_ndim :])


def _angle_close(a, b, atol):
  d = np.mod(np.asarray(a) - np.asarray(b) + math.pi, TWO_PI) - math.pi
  assert np.all(np.isfinite(d)) and np.max(np.abs(d)) <= atol, np.max(np.abs(d))


# ---------------------------------------------------------------------------- quaternions


def test_quaternion_matrix_conversions_match_scipy(xp):
  r = _rotations()
  R, q = r.as_matrix(), _wxyz(r)
  assert_close(xp.check(rot.matrix_to_quat(xp(R))), q, atol=1e-12)
  assert_close(xp.check(rot.quat_to_matrix(xp(q))), R, atol=1e-12)
  # Unnormalised and negated quaternions are the same rotation.
  assert_close(xp.check(rot.quat_to_matrix(xp(-3.0 * q))), R, atol=1e-12)
  assert np.all(xp.check(rot.matrix_to_quat(xp(R)))[:, 0] >= 0)
  assert_close(xp.check(rot.standardise_quat(xp(-3.0 * q))), q, atol=1e-12)


@pytest.mark.parametrize("shape", slow_except(BATCH_SHAPES, [FAST_BATCH_SHAPE]))
def test_conversions_broadcast_over_leading_axes(xp, shape):
  r = _rotations(10, seed=4)
  R, q, rv = (
    _batched(x, shape, k) for x, k in ((r.as_matrix(), 2), (_wxyz(r), 1), (r.as_rotvec(), 1))
  )
  for got, want in (
    (rot.quat_to_matrix(xp(q)), R),
    (rot.matrix_to_quat(xp(R)), q),
    (rot.quat_to_axis_angle(xp(q)), rv),
    (rot.axis_angle_to_quat(xp(rv)), q),
    (rot.rot6d_to_matrix(rot.matrix_to_rot6d(xp(R))), R),
    (rot.orthonormalize(xp(R)), R),
    (rot.euler_sxyz_to_matrix(rot.matrix_to_euler_sxyz(xp(R))), R),
  ):
    got = xp.check(got)
    assert got.shape == want.shape
    assert_close(got, want, atol=1e-12)


def test_axis_angle_and_log_quaternion_match_scipy(xp):
  r = _rotations()
  q, rv = _wxyz(r), r.as_rotvec()  # scipy: angle in [0, pi], the sign of q with w >= 0
  assert_close(xp.check(rot.quat_to_axis_angle(xp(q))), rv, atol=1e-12)
  assert_close(xp.check(rot.quat_to_axis_angle(xp(-q))), rv, atol=1e-12)
  assert_close(xp.check(rot.quat_log(xp(q))), rv / 2, atol=1e-12)
  assert_close(xp.check(rot.axis_angle_to_quat(xp(rv))), q, atol=1e-12)
  assert_close(xp.check(rot.quat_exp(xp(rv / 2))), q, atol=1e-12)
  # Angles beyond pi wrap to the same rotation.
  big = rv / np.maximum(np.linalg.norm(rv, axis=-1, keepdims=True), 1e-30) * 4.0
  got = xp.check(rot.quat_to_matrix(rot.axis_angle_to_quat(xp(big))))
  assert_close(got, Rotation.from_rotvec(big).as_matrix(), atol=1e-12)


def test_conversions_float32_accuracy():
  r = _rotations(seed=1)
  q = jnp.asarray(_wxyz(r), jnp.float32)
  got = rot.matrix_to_quat(jnp.asarray(r.as_matrix(), jnp.float32))
  assert got.dtype == jnp.float32
  assert_close(got, q, atol=2e-6)
  assert_close(rot.quat_to_axis_angle(q), r.as_rotvec(), atol=2e-6)
  assert_close(rot.axis_angle_to_quat(jnp.asarray(r.as_rotvec(), jnp.float32)), q, atol=2e-6)


def test_rotation_vector_gradients_finite_at_identity():
  g1 = jax.jit(jax.jacfwd(rot.axis_angle_to_quat))(jnp.zeros(3))
  assert_close(g1, np.concatenate([np.zeros((1, 3)), 0.5 * np.eye(3)]), atol=1e-7)
  g2 = jax.jit(jax.jacrev(rot.quat_to_axis_angle))(jnp.array([1.0, 0.0, 0.0, 0.0]))
  assert np.all(np.isfinite(np.asarray(g2)))
  assert_close(np.asarray(g2)[:, 1:], 2 * np.eye(3), atol=1e-6)


# ---------------------------------------------------------------------------- 6-D and 9-D


def test_rot6d_and_projection_round_trip_and_always_give_rotations(xp):
  R = _rotations().as_matrix()
  assert_close(xp.check(rot.rot6d_to_matrix(rot.matrix_to_rot6d(xp(R)))), R, atol=1e-12)
  assert_close(xp.check(rot.orthonormalize(xp(R))), R, atol=1e-12)
  # Gram-Schmidt of any 6 numbers is a rotation; so is the SVD projection of any 9.
  rng = np.random.default_rng(1)
  for M in (
    rot.rot6d_to_matrix(xp(rng.normal(size=(50, 6)))),
    rot.orthonormalize(xp(rng.normal(size=(50, 3, 3)))),
  ):
    M = xp.check(M)
    assert_close(
      M @ np.swapaxes(M, -1, -2), np.broadcast_to(np.eye(3), M.shape), atol=1e-12, rtol=0
    )
    assert_close(np.linalg.det(M), np.ones(50), atol=1e-12, rtol=0)


def test_projection_is_the_nearest_rotation_as_scipy_finds_it(xp):
  # scipy's from_matrix orthogonalises a non-orthogonal matrix to its nearest rotation
  # (Frobenius norm; Markley 2008), the same as the SVD projection of Levinson et al.
  rng = np.random.default_rng(2)
  R = _rotations(60, seed=3).as_matrix()
  noisy = R + 0.2 * rng.normal(size=R.shape)
  want = Rotation.from_matrix(noisy).as_matrix()
  assert_close(xp.check(rot.orthonormalize(xp(noisy))), want, atol=1e-9, rtol=0)
  # A reflection is projected to a proper rotation, not kept.
  assert np.linalg.det(xp.check(rot.orthonormalize(xp(np.diag([1.0, 1.0, -1.0]))))) > 0


def test_rot6d_is_continuous_where_quaternions_jump():
  # Rotations about a fixed axis through angle pi: the w >= 0 quaternion flips sign there; the
  # 6-D and 9-D representations move by about the angle step.
  angles = np.linspace(math.pi - 0.05, math.pi + 0.05, 101)
  axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
  R = jnp.asarray(Rotation.from_rotvec(angles[:, None] * axis).as_matrix(), jnp.float32)
  step = angles[1] - angles[0]
  jump = lambda x: float(np.max(np.linalg.norm(np.diff(np.asarray(x), axis=0), axis=-1)))
  assert jump(rot.matrix_to_rot6d(R)) < 3 * step
  assert jump(R.reshape(-1, 9)) < 3 * step
  assert jump(rot.matrix_to_quat(R)) > 1.0  # q -> -q at the crossing


def test_projection_gradient_is_finite_at_distinct_singular_values():
  # (Equal singular values, e.g. at a rotation itself, make the SVD's gradient infinite.)
  noise = 0.1 * np.random.default_rng(5).normal(size=(8, 3, 3))
  M = jnp.asarray(Rotation.random(8, random_state=5).as_matrix() + noise, jnp.float32)
  g = jax.grad(lambda m: jnp.sum(rot.orthonormalize(m) ** 2 * jnp.arange(9.0).reshape(3, 3)))(M)
  assert np.all(np.isfinite(np.asarray(g)))


# ---------------------------------------------------------------------------- Euler angles


def test_euler_sxyz_matches_scipy(xp):
  r = _rotations(seed=2)
  e = r.as_euler("xyz")  # extrinsic x, y, z: R = Rz(psi) Ry(phi) Rx(theta)
  assert_close(xp.check(rot.euler_sxyz_to_matrix(xp(e))), r.as_matrix(), atol=1e-12)
  got = xp.check(rot.matrix_to_euler_sxyz(xp(r.as_matrix())))
  assert_close(got, e, atol=1e-10)
  assert_close(xp.check(rot.euler_sxyz_to_matrix(xp(got))), r.as_matrix(), atol=1e-12)
  # Static axes: the product of the single-axis rotations, each as scipy's.
  for f, a in ((rot.rot_x, "x"), (rot.rot_y, "y"), (rot.rot_z, "z")):
    assert_close(xp.check(f(xp(e[:, 0]))), Rotation.from_euler(a, e[:, :1]).as_matrix(), atol=1e-12)
  Rz, Ry, Rx = (
    xp.check(f(xp(e[:, i]))) for f, i in ((rot.rot_z, 2), (rot.rot_y, 1), (rot.rot_x, 0))
  )
  assert_close(Rz @ Ry @ Rx, r.as_matrix(), atol=1e-12)


def test_euler_gimbal_lock_follows_transforms3d(xp):
  # phi = +-pi/2: transforms3d sets psi = 0 and puts the whole in-plane angle into theta.
  for phi in (math.pi / 2, -math.pi / 2):
    R = Rotation.from_euler("xyz", [0.3, phi, 0.5]).as_matrix()
    ang = xp.check(rot.matrix_to_euler_sxyz(xp(R)))
    assert ang[2] == 0.0 and abs(abs(ang[1]) - math.pi / 2) < 1e-7
    assert_close(xp.check(rot.euler_sxyz_to_matrix(xp(ang))), R, atol=1e-7)


def test_yaw_quaternion_matches_scipy(xp):
  yaw = np.linspace(0, TWO_PI, 37)[:-1]
  q = xp.check(rot.yaw_to_quat(xp(yaw)))
  assert_close(q, _wxyz(Rotation.from_euler("z", yaw[:, None])), atol=1e-12)
  _angle_close(xp.check(rot.quat_to_yaw(xp(q))), yaw, 1e-12)
  # A tilted rotation decodes to the closest yaw.
  tilted = Rotation.from_euler("zx", np.stack([yaw, np.full(36, 0.2)], -1))
  _angle_close(xp.check(rot.quat_to_yaw(xp(_wxyz(tilted)))), yaw, 1e-9)


# ---------------------------------------------------------------------------- backends


def test_numpy_inputs_are_computed_in_float64_and_jax_keeps_its_dtype():
  q32 = _wxyz(_rotations(5)).astype(np.float32)
  out = rot.quat_to_matrix(q32)
  assert isinstance(out, np.ndarray) and out.dtype == np.float64
  assert isinstance(rot.quat_to_matrix(q32.tolist()), np.ndarray)  # lists too
  out = jax.jit(rot.quat_to_matrix)(jnp.asarray(q32))
  assert isinstance(out, jax.Array) and out.dtype == jnp.float32


def test_seven_scenes_reader_uses_these_functions():
  from camrep.data.readers import seven_scenes

  for name in ("quat_to_matrix", "orthonormalize", "matrix_to_euler_sxyz", "euler_sxyz_to_matrix"):
    assert getattr(seven_scenes, name) is getattr(rot, name), name

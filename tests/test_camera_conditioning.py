"""Camera conditionings of the multi-view transformer (`camrep.models.camera_conditioning`) and the
relative attention they plug into (`camrep.models.relative_attention`): shapes, agreement with
independent NumPy/SciPy evaluations of the papers' equations, the invariances that hold (and one
that does not), finite gradients, and the drop-in example of the module docstring."""

import doctest
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from camrep import lie
from camrep import pose as P
from camrep.data import procedural
from camrep.data.procedural import render
from camrep.models import camera_conditioning as cc
from camrep.models import relative_attention as ra
from tests.utils import x64

pytestmark = pytest.mark.usefixtures("fast_compile")

ROOMS_SPEC = P.PoseSystemSpec(
  dofs=(P.LinearDof("x", -1.0, 1.0, 0.1), P.LinearDof("y", -1.0, 1.0, 0.1), P.AngularDof("yaw")),
  n_blocks=2,
  block_size=2,
)


def rooms_poses(rng, shape):
  xy = rng.uniform(-0.8, 0.8, size=(*shape, 2))
  return np.concatenate([xy, rng.uniform(0, 2 * np.pi, size=(*shape, 1))], -1)


def random_rigid(rng, shape):
  """Random camera-to-world matrices (*shape, 4, 4), float64."""
  A = rng.normal(size=(*shape, 3, 3))
  Q, R = np.linalg.qr(A)
  Q = Q * np.sign(np.diagonal(R, axis1=-2, axis2=-1))[..., None, :]
  Q = np.where(np.linalg.det(Q)[..., None, None] < 0, -Q, Q)
  T = np.zeros((*shape, 4, 4))
  T[..., :3, :3], T[..., :3, 3], T[..., 3, 3] = Q, rng.normal(size=(*shape, 3)), 1.0
  return T


# --------------------------------------------------------------------------------------------
# NumPy reference of eqs. R1-R2: full per-token matrices, inverted numerically.


def token_matrices(Dcam, grid, h, base=ra.ROPE_BASE):
  """Per-token (V, N, h, h) matrices D_t: [camera blocks tiled | RoPE cols | RoPE rows | I]."""
  V, k, b, _ = Dcam.shape
  rows, cols = grid
  reps = max(1, (h // 2) // (k * b))
  cam = reps * k * b
  rope = 4 * ((h - cam) // 4)
  F = rope // 4
  omega = base ** (-np.arange(F) / max(F, 1))
  out = np.zeros((V, rows * cols, h, h))
  for v in range(V):
    for n in range(rows * cols):
      M = np.eye(h)
      for c in range(reps * k):
        M[c * b : (c + 1) * b, c * b : (c + 1) * b] = Dcam[v, c % k]
      for seg, pos in ((cam, n % cols), (cam + rope // 2, n // cols)):
        for f in range(F):
          a = pos * omega[f]
          i, j = seg + f, seg + F + f
          M[i, i], M[i, j], M[j, i], M[j, j] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
      out[v, n] = M
  return out


def reference_attention(q, k, v, rel):
  """o_i = sum_j softmax_j(q_i^T Rel_ij k_j / sqrt(h)) Rel_ij v_j; q, k, v (T, heads, h),
  rel (T, T, h, h)."""
  h = q.shape[-1]
  s = np.einsum("thd,tsde,she->hts", q, rel, k) / np.sqrt(h)
  a = np.exp(s - s.max(-1, keepdims=True))
  a /= a.sum(-1, keepdims=True)
  return np.einsum("hts,tsde,she->thd", a, rel, v), s


def reference_from_tokens(q, k, v, D):
  """Reference with Rel_ij = D_i D_j^{-1} from per-token matrices D (V, N, h, h)."""
  Df = D.reshape(-1, *D.shape[-2:])
  rel = np.einsum("tab,sbc->tsac", Df, np.linalg.inv(Df))
  flat = lambda x: x.reshape(-1, *x.shape[-2:])
  o, s = reference_attention(flat(q), flat(k), flat(v), rel)
  return o.reshape(q.shape), s


def view_codes(enc, params, poses, grid):
  """enc.view_codes, jitted (one compile instead of one per primitive)."""
  return jax.jit(enc.view_codes, static_argnums=2)(params, jnp.asarray(poses), grid)


@functools.partial(jax.jit, static_argnames=("grid", "values"))
def attention(q, k, v, transform, *, grid, values=True):
  return ra.attention(q, k, v, transform, grid=grid, values=values)


@functools.partial(jax.jit, static_argnames=("grid",))
def scores(q, k, transform, *, grid):
  return ra.scores(q, k, transform, grid=grid)


def qkv(rng, V, N, heads, h):
  return [rng.normal(size=(V, N, heads, h)) for _ in range(3)]


def check_against_reference(codes, Dcam_ref, grid, h, rng):
  q, k, v = qkv(rng, codes.transform.D.shape[0], grid[0] * grid[1], 2, h)
  o_ref, s_ref = reference_from_tokens(q, k, v, token_matrices(Dcam_ref, grid, h))
  o = attention(q, k, v, codes.transform, grid=grid)
  s = scores(q, k, codes.transform, grid=grid)
  np.testing.assert_allclose(np.asarray(s), s_ref, atol=1e-9, rtol=1e-9)
  np.testing.assert_allclose(np.asarray(o), o_ref, atol=1e-9, rtol=1e-9)


# --------------------------------------------------------------------------------------------
# Patches and cameras.


def test_patchify_orders_patches_row_major_and_inverts():
  grid = cc.PatchGrid(8, 12, 4)
  x = np.random.default_rng(0).normal(size=(2, 8, 12, 3)).astype(np.float32)
  p = np.asarray(cc.patchify(x, grid))
  assert p.shape == (2, 6, 48)
  np.testing.assert_array_equal(p[:, 1 * 3 + 2], x[:, 4:8, 8:12].reshape(2, 48))
  np.testing.assert_array_equal(np.asarray(cc.unpatchify(p, grid)), x)
  with pytest.raises(ValueError, match="do not split"):
    cc.PatchGrid(10, 12, 4)


@pytest.mark.parametrize("name", ["rooms", "object"])
def test_pose_cameras_match_the_families_cameras(name):
  family = procedural.make_family(name, preset="small")
  cams = cc.cameras_of_family(family)
  poses = family.poses("train", 0)
  np.testing.assert_allclose(
    np.asarray(cams.T_world_cam(poses)), family.poses_to_c2w(0, poses), atol=1e-5
  )
  grid = cc.PatchGrid(family.image_size, family.image_size, 8)
  K = np.asarray(cams.K(grid))
  np.testing.assert_allclose(K[0, 0], family.camera.focal, rtol=1e-6)


def test_cameras_of_family_refuses_scene_dependent_cameras():
  with pytest.raises(ValueError, match="depend on the scene"):
    cc.cameras_of_family(procedural.make_family("area", preset="small"))


def test_plucker_rays_match_the_renderers_rays():
  cams = cc.RoomsCameras()
  grid = cc.PatchGrid(16, 16, 4)
  pose = np.array([0.3, -0.2, 1.1])
  T = cams.T_world_cam(pose)
  rays = np.asarray(cc.plucker_rays(T, cams.K(grid), grid)).reshape(-1, 6)
  o, d = render.camera_rays(T, render.Camera(16, 16, cams.fov_deg))
  np.testing.assert_allclose(rays[:, :3], np.asarray(d), atol=1e-5)
  np.testing.assert_allclose(rays[:, 3:], np.cross(np.asarray(o), np.asarray(d)), atol=1e-5)


# --------------------------------------------------------------------------------------------
# Codes: shapes.


def conditionings():
  cams = cc.RoomsCameras()
  return {
    "none": cc.NoCamera(),
    "raymap": cc.Raymap(cams),
    "gta": cc.GTA(cams),
    "gta_so3": cc.GTA(cams, group="so3"),
    "prope": cc.PRoPE(cams),
    "learned_abs": cc.LearnedAbsolute(ROOMS_SPEC),
    "learned_rel": cc.LearnedRelative(ROOMS_SPEC),
  }


EXPECTED = {
  "none": ((2, 3, 16, 0), None),
  "raymap": ((2, 3, 16, 6 * 16), None),
  "gta": (None, (2, 3, 1, 4, 4)),
  "gta_so3": (None, (2, 3, 1, 3, 3)),
  "prope": (None, (2, 3, 1, 4, 4)),
  "learned_abs": ((2, 3, 16, 3 * 4), None),
  "learned_rel": (None, (2, 3, 6, 2, 2)),
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_view_codes_shapes(name):
  c = conditionings()[name]
  params = c.init(jax.random.key(0))
  poses = rooms_poses(np.random.default_rng(0), (2, 3))
  codes = view_codes(c, params, jnp.asarray(poses, jnp.float32), cc.PatchGrid(16, 16, 4))
  features, transform = EXPECTED[name]
  assert (None if codes.features is None else codes.features.shape) == features
  assert (None if codes.transform is None else codes.transform.D.shape) == transform
  assert c.relative == (transform is not None)
  assert c.learns == name.startswith("learned")
  if codes.transform is not None:
    eye = np.broadcast_to(np.eye(transform[-1]), transform)
    np.testing.assert_allclose(codes.transform.D @ codes.transform.D_inv, eye, atol=1e-5)


def test_learned_absolute_features_are_the_pose_vectors():
  c = cc.LearnedAbsolute(ROOMS_SPEC)
  params = c.init(jax.random.key(1))
  poses = jnp.asarray(rooms_poses(np.random.default_rng(1), (2, 3)), jnp.float32)
  f = view_codes(c, params, poses, cc.PatchGrid(8, 8, 4)).features
  v = jax.jit(lambda p, x: P.concat(P.embed(p, ROOMS_SPEC, x), ROOMS_SPEC))(params, poses)
  np.testing.assert_array_equal(np.asarray(f), np.broadcast_to(v[:, :, None], f.shape))


# --------------------------------------------------------------------------------------------
# Agreement with the equations, evaluated independently in NumPy / SciPy (float64).


def test_prope_attention_matches_the_relative_projective_equation():
  rng = np.random.default_rng(2)
  grid = cc.PatchGrid(12, 8, 4)  # 3 x 2 patches: rows and columns differ
  V, h = 3, 20  # 8 camera dims (two 4 x 4 copies), 12 RoPE dims
  with x64():
    T = random_rigid(rng, (V,))
    K = np.zeros((V, 3, 3))
    K[:, 0, 0], K[:, 1, 1] = rng.uniform(5, 15, V), rng.uniform(5, 15, V)
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = rng.uniform(2, 6, V), rng.uniform(4, 8, V), 1.0
    codes = cc.PRoPE(cc.RoomsCameras()).codes_from_cameras(jnp.asarray(T), jnp.asarray(K), grid)
    # P = lift(K~) T_cam_world with PRoPE's normalised intrinsics, from the definitions.
    Kn = np.zeros((V, 4, 4))
    Kn[:, 0, 0], Kn[:, 1, 1] = K[:, 0, 0] / 8, K[:, 1, 1] / 12
    Kn[:, 0, 2], Kn[:, 1, 2] = K[:, 0, 2] / 8 - 0.5, K[:, 1, 2] / 12 - 0.5
    Kn[:, 2, 2] = Kn[:, 3, 3] = 1.0
    Pm = Kn @ np.linalg.inv(T)
    check_against_reference(codes, Pm[:, None], grid.shape, h, rng)


@pytest.mark.parametrize("group", ["se3", "so3"])
def test_gta_attention_matches_the_relative_pose_equation(group):
  rng = np.random.default_rng(3)
  grid = cc.PatchGrid(8, 8, 4)
  with x64():
    T = random_rigid(rng, (3,))
    codes = cc.GTA(cc.RoomsCameras(), group=group).codes_from_cameras(jnp.asarray(T))
    T_cam_world = np.linalg.inv(T)
    D = T_cam_world if group == "se3" else T_cam_world[:, :3, :3]
    check_against_reference(codes, D[:, None], grid.shape, 16, rng)


def test_learned_relative_scores_are_exp_of_the_pose_difference():
  """s_ij = q_i^T (diag_l expm(B_l (p_j,l - p_i,l)) (+) RoPE(patch_i - patch_j)) k_j, with the
  exponentials from scipy (the relative form written directly, not through D_i D_j^{-1})."""
  rng = np.random.default_rng(4)
  grid = (2, 2)
  h = 16  # 12 camera dims (3 DOFs x 2 blocks x 2), 4 RoPE dims
  with x64():
    enc = cc.LearnedRelative(ROOMS_SPEC)
    params = jax.tree.map(lambda a: a.astype(jnp.float64), enc.init(jax.random.key(4)))
    poses = rooms_poses(rng, (3,))
    codes = view_codes(enc, params, poses, cc.PatchGrid(8, 8, 4))
    B = {
      d.name: np.asarray(lie.skew(params[d.name][P.GENERATOR], block_size=2))
      for d in ROOMS_SPEC.dofs
    }
    V, N = 3, 4
    rope = token_matrices(np.broadcast_to(np.eye(2), (V, 6, 2, 2)), grid, h)  # RoPE part
    rel = np.zeros((V * N, V * N, h, h))
    for a in range(V * N):
      for b in range(V * N):
        va, vb = a // N, b // N
        M = rope[va, a % N] @ np.linalg.inv(rope[vb, b % N])
        blocks = [
          scipy.linalg.expm(Bl * (poses[vb, col] - poses[va, col]))
          for col, name in enumerate(("x", "y", "yaw"))
          for Bl in B[name]
        ]
        M[:12, :12] = scipy.linalg.block_diag(*blocks)
        rel[a, b] = M
    q, k, v = qkv(rng, V, N, 2, h)
    flat = lambda x: x.reshape(-1, *x.shape[-2:])
    o_ref, s_ref = reference_attention(flat(q), flat(k), flat(v), rel)
    s = scores(q, k, codes.transform, grid=grid)
    o = attention(q, k, v, codes.transform, grid=grid)
    np.testing.assert_allclose(np.asarray(s), s_ref, atol=1e-9)
    np.testing.assert_allclose(np.asarray(o).reshape(o_ref.shape), o_ref, atol=1e-9)


def test_values_false_leaves_values_and_outputs_alone():
  rng = np.random.default_rng(5)
  with x64():
    T = random_rigid(rng, (2,))
    codes = cc.GTA(cc.RoomsCameras()).codes_from_cameras(jnp.asarray(T))
    q, k, v = qkv(rng, 2, 4, 1, 8)
    o = attention(q, k, v, codes.transform, grid=(2, 2), values=False)
    s = np.asarray(scores(q, k, codes.transform, grid=(2, 2)))[0]
    a = np.exp(s - s.max(-1, keepdims=True))
    a /= a.sum(-1, keepdims=True)
    np.testing.assert_allclose(np.asarray(o).reshape(8, 8), a @ v.reshape(8, 8), atol=1e-12)


# --------------------------------------------------------------------------------------------
# Invariances.


def scores_of(enc, params, poses, h=16):
  codes = view_codes(enc, params, jnp.asarray(poses, jnp.float32), cc.PatchGrid(8, 8, 4))
  rng = np.random.default_rng(6)
  q, k, _ = qkv(rng, poses.shape[0], 4, 2, h)
  return np.asarray(
    scores(jnp.asarray(q, jnp.float32), jnp.asarray(k, jnp.float32), codes.transform, grid=(2, 2))
  )


def rigid_rotation_about_z(poses, phi):
  """Rooms poses of the cameras after the world turns by phi about +z (through the origin)."""
  c, s = np.cos(phi), np.sin(phi)
  x, y, yaw = poses[..., 0], poses[..., 1], poses[..., 2]
  return np.stack([c * x - s * y, s * x + c * y, yaw + phi], -1)


@pytest.mark.parametrize("name", ["gta", "gta_so3", "prope"])
def test_fixed_relative_encodings_are_invariant_to_a_rigid_transform_of_the_world(name):
  rng = np.random.default_rng(7)
  enc = conditionings()[name]
  grid = cc.PatchGrid(8, 8, 4)
  with x64():
    T = random_rigid(rng, (4,))
    G = random_rigid(rng, ())
    K = enc.cameras.K(grid)
    q, k, _ = qkv(rng, 4, 4, 2, 16)

    def s(T):
      codes = (
        enc.codes_from_cameras(jnp.asarray(T), K, grid)
        if name == "prope"
        else (enc.codes_from_cameras(jnp.asarray(T)))
      )
      return np.asarray(scores(q, k, codes.transform, grid=grid.shape))

    np.testing.assert_allclose(s(G @ T), s(T), atol=1e-9)
  # Through the rooms poses: the world turned about +z is a rigid transform of every camera.
  poses = rooms_poses(rng, (4,))
  np.testing.assert_allclose(
    scores_of(enc, {}, rigid_rotation_about_z(poses, 0.7)), scores_of(enc, {}, poses), atol=2e-4
  )


def test_prope_is_invariant_to_turning_every_car_camera_in_azimuth():
  enc = cc.PRoPE(cc.ObjectCameras())
  rng = np.random.default_rng(8)
  poses = np.stack([rng.uniform(0, 2 * np.pi, 4), rng.uniform(0.6, 1.5, 4)], -1)
  shifted = poses + np.array([1.3, 0.0])
  np.testing.assert_allclose(scores_of(enc, {}, shifted), scores_of(enc, {}, poses), atol=2e-4)


@pytest.mark.parametrize("dof", [0, 1, 2])
def test_learned_relative_is_invariant_to_a_shift_along_any_dof(dof):
  enc = cc.LearnedRelative(ROOMS_SPEC)
  params = enc.init(jax.random.key(9))
  poses = rooms_poses(np.random.default_rng(9), (4,))
  shift = np.zeros(3)
  shift[dof] = 0.37 if dof < 2 else 2.1  # yaw: unwrapped values, past 2 pi for some cameras
  s0, s1 = scores_of(enc, params, poses), scores_of(enc, params, poses + shift)
  np.testing.assert_allclose(s1, s0, atol=2e-4)
  assert np.ptp(s0) > 0.5  # the scores do vary across the pairs


def test_learned_relative_is_not_invariant_to_a_rigid_rotation_of_the_room():
  """(x, y, yaw) differences are not the relative pose when the world turns: the approximation
  the docstring states (GTA and PRoPE pass this test, above)."""
  enc = cc.LearnedRelative(ROOMS_SPEC)
  params = enc.init(jax.random.key(10))
  poses = rooms_poses(np.random.default_rng(10), (4,))
  s0, s1 = scores_of(enc, params, poses), scores_of(enc, params, rigid_rotation_about_z(poses, 0.7))
  assert np.max(np.abs(s1 - s0)) > 0.05


def test_raymap_is_absolute():
  enc = cc.Raymap(cc.RoomsCameras())
  poses = rooms_poses(np.random.default_rng(11), (2,))
  grid = cc.PatchGrid(8, 8, 4)
  f0 = view_codes(enc, {}, jnp.asarray(poses, jnp.float32), grid).features
  f1 = view_codes(enc, {}, jnp.asarray(poses + np.array([0.1, 0, 0]), jnp.float32), grid).features
  assert np.max(np.abs(np.asarray(f1 - f0))) > 1e-2


# --------------------------------------------------------------------------------------------
# Learned encodings: parameters, gradients, rotation loss, refusals.


def test_learned_relative_init_gives_generators_of_the_requested_scale():
  params = cc.LearnedRelative(ROOMS_SPEC, init_scale=3.0).init(jax.random.key(12))
  coeffs = np.concatenate([np.ravel(params[d.name][P.GENERATOR]) for d in ROOMS_SPEC.dofs])
  assert 1.0 < np.std(coeffs) < 9.0
  assert set(params) == {"x", "y", "yaw"} and set(params["x"]) == {P.GRID, P.GENERATOR}


def test_learned_relative_gradients_are_finite_at_zero_and_random_poses():
  enc = cc.LearnedRelative(ROOMS_SPEC)
  params = enc.init(jax.random.key(13))
  rng = np.random.default_rng(13)
  q, k, _ = (jnp.asarray(x, jnp.float32) for x in qkv(rng, 3, 4, 2, 16))
  for poses in (np.zeros((3, 3)), rooms_poses(rng, (3,))):

    def f(params, poses=poses):
      codes = enc.view_codes(params, jnp.asarray(poses, jnp.float32), cc.PatchGrid(8, 8, 4))
      return jnp.sum(jax.nn.softmax(scores(q, k, codes.transform, grid=(2, 2))) ** 2)

    g = jax.jit(jax.grad(f))(params)
    leaves = jax.tree.leaves(g)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    # At p = 0 every exp(B p) is I whatever B: the generators then get no gradient.
    assert np.any(np.abs(np.asarray(g["yaw"][P.GENERATOR])) > 0) == bool(np.any(poses))


def test_rotation_loss_is_optional_and_the_papers():
  kind = cc.LearnedRelative  # the learned encodings share `pose_loss`
  key = jax.random.key(14)
  params = kind(ROOMS_SPEC).init(key)
  total, terms = kind(ROOMS_SPEC).pose_loss(key, params)
  assert float(total) == 0.0 and terms == {}
  total, terms = jax.jit(kind(ROOMS_SPEC, rotation_weight=0.5, n_pairs=8).pose_loss)(key, params)
  expected = jax.jit(lambda k, p: P.rotation_losses(k, p, ROOMS_SPEC, n_pairs=8))(key, params)
  assert set(terms) == {"rot_x", "rot_y", "rot_yaw"}
  np.testing.assert_allclose(
    float(total), 0.5 * sum(float(v) for v in expected.values()), rtol=1e-6
  )


def test_learned_relative_refuses_the_polar_system():
  spec = P.PoseSystemSpec(dofs=(P.PolarDof(), P.AngularDof("yaw")), n_blocks=1, block_size=2)
  with pytest.raises(ValueError, match="do not commute"):
    cc.LearnedRelative(spec)


def test_learned_relative_refuses_the_truncated_exponential():
  spec = P.PoseSystemSpec(dofs=ROOMS_SPEC.dofs, n_blocks=2, block_size=2, exp_method="taylor2")
  with pytest.raises(ValueError, match="exact exponential"):
    cc.LearnedRelative(spec)


def test_head_layout_and_its_refusal():
  assert ra.HeadLayout.of(32, 1, 4) == ra.HeadLayout(camera=16, reps=4, rope=16)
  assert ra.HeadLayout.of(32, 1, 3) == ra.HeadLayout(camera=15, reps=5, rope=16)
  assert ra.HeadLayout.of(16, 6, 2) == ra.HeadLayout(camera=12, reps=1, rope=4)
  with pytest.raises(ValueError, match="needs 24 dims per head"):
    ra.HeadLayout.of(16, 6, 4)


def test_gta_refuses_an_unknown_group():
  with pytest.raises(ValueError, match="group"):
    cc.GTA(cc.RoomsCameras(), group="se2")


def test_module_docstring_example_runs():
  """The drop-in example: the learned relative encoding around jax.nn.dot_product_attention."""
  result = doctest.testmod(cc, optionflags=doctest.ELLIPSIS)
  assert result.attempted >= 10 and result.failed == 0


def test_intrinsics_focal_from_horizontal_fov():
  K = np.asarray(cc.intrinsics(cc.PatchGrid(32, 64, 8), 90.0))
  np.testing.assert_allclose(K, [[32, 0, 32], [0, 32, 16], [0, 0, 1]], atol=1e-5)
  assert math.isclose(float(K[0, 0]), render.Camera(32, 64, 90.0).focal, rel_tol=1e-6)

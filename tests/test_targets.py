"""Tests of the pose encodings as regression targets (camrep.pose_encodings through
camrep.regression.targets): round trips, head sizes, losses, defaults.

The rotation conversions themselves are tested in tests/test_rotations.py, the settings'
conventions in tests/test_settings.py.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from camrep import lie, pose_encodings, rotations, settings
from camrep import pose as P
from camrep.models import pose_regressor
from camrep.regression import targets as T
from tests.utils import assert_close, regression_hparams, slow_except

TWO_PI = 2 * math.pi


pytestmark = pytest.mark.usefixtures("fast_compile")


def _angle_close(a, b, atol):
  d = np.mod(np.asarray(a) - np.asarray(b) + math.pi, TWO_PI) - math.pi
  assert np.all(np.isfinite(d)) and np.max(np.abs(d)) <= atol, np.max(np.abs(d))


# ---------------------------------------------------------------------------- setting conventions


def test_matrix_losses_are_the_frobenius_distance_of_rotations():
  # Two rotations about z differing by theta: ||R1 - R2||_F^2 = 4 (1 - cos theta).
  theta = 0.7
  R1 = Rotation.from_rotvec([0, 0, 0.2]).as_matrix()
  R2 = Rotation.from_rotvec([0, 0, 0.2 + theta]).as_matrix()
  want = 4 * (1 - math.cos(theta))
  six = lambda R: rotations.matrix_to_rot6d(jnp.asarray(R[None], jnp.float32))
  got6 = T.head_loss("gram_schmidt_frobenius", 2.5 * six(R2), six(R1))  # scale does not matter
  assert float(got6) == pytest.approx(want, rel=1e-5)
  nine = lambda R: jnp.asarray(R.reshape(1, 9), jnp.float32)
  assert float(T.head_loss("svd_frobenius", 3.0 * nine(R2), nine(R1))) == pytest.approx(
    want, rel=1e-5
  )
  # Finite gradients, zero at the target.
  g = jax.grad(lambda x: T.head_loss("svd_frobenius", x, nine(R1)))(nine(R2) + 0.01)
  assert np.all(np.isfinite(np.asarray(g)))
  assert float(T.head_loss("gram_schmidt_frobenius", six(R1), six(R1))) == pytest.approx(
    0, abs=1e-10
  )
  # With a position head (gqn), positions take the L2 loss, the orientation the matrix loss.
  heads = T.head_specs("rot6d", "gqn")
  tgt = T.encode("rot6d", "gqn", jnp.array([[0.1, 0.2, 0.3]]))
  pred = {"position": tgt["position"] + jnp.array([[0.3, 0.4]]), "orientation": tgt["orientation"]}
  g = T.group_losses("gram_schmidt_frobenius", pred, tgt, heads)
  assert float(g["position"]) == pytest.approx(0.25, rel=1e-5)
  assert float(g["orientation"]) == pytest.approx(0, abs=1e-10)


def _poses(setting, n=64, seed=0):
  rng = np.random.default_rng(seed)
  u = lambda lo, hi: rng.uniform(lo, hi, n)
  cols = {
    "gqn": [u(-0.95, 0.95), u(-0.95, 0.95), u(0, TWO_PI)],
    "gibson": [u(0.05, 1.95), u(0.05, 1.95), u(0, TWO_PI)],
    "car": [u(0, TWO_PI), u(0.05, math.pi - 0.05)],
    # Euler phi strictly inside (0, pi): outside gimbal lock the sxyz angles are unique.
    "seven_scenes": [
      u(0.1, 3.9),
      u(0.1, 1.4),
      u(0.1, 2.9),
      u(0, TWO_PI),
      u(0.2, 2.9),
      u(0, TWO_PI),
    ],
  }[setting]
  return np.stack(cols, -1).astype(np.float32)


def _check_poses_close(setting, got, want, *, pos_atol, ang_atol):
  k = settings.get(setting).position_dim
  got, want = np.asarray(got), np.asarray(want)
  assert got.shape == want.shape
  if k:
    assert_close(got[..., :k], want[..., :k], atol=pos_atol, rtol=0)
  _angle_close(got[..., k:], want[..., k:], ang_atol)


@pytest.mark.parametrize("setting", settings.names())
def test_baseline_round_trip(setting):
  poses = _poses(setting)

  @jax.jit
  def round_trip(p):
    enc = {rep: T.encode(rep, setting, p) for rep in T.BASELINES}
    return enc, {rep: T.decode(rep, setting, enc[rep]) for rep in T.BASELINES}

  enc, dec = round_trip(poses)
  for rep in T.BASELINES:
    heads = T.head_specs(rep, setting)
    assert sorted(h.name for h in heads) == sorted(enc[rep])
    for h in heads:
      assert enc[rep][h.name].shape == (64, h.size) and h.norm == "none"
    _check_poses_close(setting, dec[rep], poses, pos_atol=1e-6, ang_atol=2e-3)


def test_baseline_target_values():
  poses = np.array([[0.1, -0.2, 3 * math.pi / 2]], np.float32)
  enc = T.encode("sincos", "gqn", poses)
  assert_close(enc["position"], [[0.1, -0.2]], atol=1e-7)
  assert_close(enc["orientation"], [[-1.0, 0.0]], atol=1e-6)
  # 270 degrees about z: w = cos(135) < 0 is flipped, so q = (sin 45, 0, 0, -cos 45).
  h = math.sqrt(0.5)
  assert_close(T.encode("quat", "gqn", poses)["orientation"], [[h, 0, 0, -h]], atol=1e-6)
  assert_close(
    T.encode("axis_angle", "gqn", poses)["orientation"], [[0, 0, -math.pi / 2]], atol=1e-6
  )
  assert_close(T.encode("logq", "gqn", poses)["orientation"], [[0, 0, -math.pi / 4]], atol=1e-6)
  assert_close(T.encode("euler", "gqn", poses)["orientation"], [[3 * math.pi / 2]], atol=1e-6)
  # Predictions outside the range decode into it.
  dec = T.decode("euler", "car", {"orientation": jnp.array([[-0.5, 4.0]])})
  assert_close(dec, [[TWO_PI - 0.5, math.pi]], atol=1e-6)


def _integer_planes(rng, n_blocks, s, freqs):
  """Q (per block) and per-plane frequencies: blocks Q diag(f_k J) Q^T."""
  Qs = [np.linalg.qr(rng.normal(size=(s, s)))[0] for _ in range(n_blocks)]
  return Qs, freqs


def _skew_from_planes(Qs, f):
  blocks = []
  for b, Q in enumerate(Qs):
    s = Q.shape[0]
    D = np.zeros((s, s))
    for k in range(s // 2):
      D[2 * k, 2 * k + 1], D[2 * k + 1, 2 * k] = -f[b, k], f[b, k]
    blocks.append(Q @ D @ Q.T)
  return np.stack(blocks)


def consistent_params(spec, seed=0):
  """Pose-system params whose grid vectors lie on orbits exp(B (x - low)) v0.

  Angles: integer frequencies (orbits close after 2 pi); bounded ranges: slow enough that the
  orbit does not close. Polar: commuting generators B_x, B_y in shared planes, and the binned
  direction table B_j = cos(theta_j) B_x + sin(theta_j) B_y.
  """
  rng = np.random.default_rng(seed)
  nb, s = spec.n_blocks, spec.block_size
  params = {}
  for d in spec.dofs:
    Qs = [np.linalg.qr(rng.normal(size=(s, s)))[0] for _ in range(nb)]
    v0 = rng.normal(size=(nb, s))
    v0 /= np.linalg.norm(v0, axis=-1, keepdims=True)
    v0 = v0.reshape(-1)
    if d.width == 2:  # polar
      scale = 1.2 / (d.high - d.low)
      fx = rng.uniform(-1, 1, (nb, s // 2)) * scale
      fy = rng.uniform(-1, 1, (nb, s // 2)) * scale
      Bx, By = _skew_from_planes(Qs, fx), _skew_from_planes(Qs, fy)
      ax = d.low + d.spacing * np.arange(d.n_side)
      gx, gy = np.meshgrid(ax - d.low, ax - d.low, indexing="ij")
      gen = gx.reshape(-1, 1, 1, 1) * Bx + gy.reshape(-1, 1, 1, 1) * By
      grid = lie.apply_exp_blocks(
        gen, 1.0, np.broadcast_to(v0, (d.n_grid, spec.dim)), method="expm"
      )
      th = np.arange(d.n_directions) * TWO_PI / d.n_directions
      table = np.cos(th)[:, None, None, None] * Bx + np.sin(th)[:, None, None, None] * By
      params[d.name] = {
        "grid": jnp.asarray(grid, jnp.float32),
        P.GENERATOR: lie.vee(jnp.asarray(table)).astype(jnp.float32),
        P.DIRECTION: jnp.zeros((nb, lie.num_skew_params(s)), jnp.float32),
      }
      continue
    f = rng.integers(1, 3, (nb, s // 2)).astype(float)
    if not d.periodic:
      f = f * (1.2 / (d.high - d.low))
    B = _skew_from_planes(Qs, f)
    k = np.arange(d.n_grid) * d.spacing
    grid = lie.apply_exp_blocks(B, k, np.broadcast_to(v0, (d.n_grid, spec.dim)), method="expm")
    params[d.name] = {
      "grid": jnp.asarray(grid, jnp.float32),
      P.GENERATOR: lie.vee(jnp.asarray(B)).astype(jnp.float32),
    }
  return params


SMALL = dict(n_blocks=2, block_size=4, exp_method="taylor2")


@pytest.mark.parametrize("setting", slow_except(settings.names(), ["car", "gibson"]))
def test_ours_round_trip_refines_below_candidate_spacing(setting):
  spec = settings.get(setting).pose_spec(**SMALL)
  params = consistent_params(spec, seed=1)
  poses = _poses(setting, n=32, seed=5)
  mode = regression_hparams(setting, "ours").quantisation  # gibson "nearest", else "floor"
  kw = dict(spec=spec, rep_params=params, mode=mode)
  enc = jax.jit(lambda p: T.encode("ours", setting, p, **kw))(poses)
  heads = T.head_specs("ours", setting, spec=spec)
  assert sorted(enc) == sorted(spec.names) and [h.name for h in heads] == list(spec.names)
  for h in heads:
    norm = np.asarray(pose_regressor.normalise_head(enc[h.name], h))
    # Targets satisfy the head's normalisation, up to the Taylor exp's norm drift d^4 B^4 / 4.
    assert_close(norm, enc[h.name], atol=2e-3)
  dec = jax.jit(lambda e: T.decode("ours", setting, e, **kw))(enc)
  # Candidates every 0.25 degrees and 0.25 grid units. Refinement gets far below that for
  # typical values; the worst case stays within one candidate step (the Taylor exp is slightly
  # discontinuous at cell boundaries). Polar positions: the binned direction of B(theta) makes the
  # embedding non-smooth (flat in one direction on grid lines), so refinement cannot improve on
  # the arg-min there and only the candidate-step bound is checked.
  k = settings.get(setting).position_dim
  cand = np.array(
    [0.25 * (0.05 if setting == "gibson" else 0.1)] * k
    + [math.radians(0.25)] * (poses.shape[-1] - k)
  )
  err = np.abs(np.asarray(dec) - poses)
  err[:, k:] = np.abs(np.mod(err[:, k:] + math.pi, TWO_PI) - math.pi)
  assert np.all(err <= cand), err.max(0)
  refined = np.median(err, axis=0) <= cand / 100
  assert np.all(refined[k:]) and (setting in ("gqn", "gibson") or np.all(refined)), err


def test_ours_targets_are_frozen_embeddings():
  spec = settings.get("car").pose_spec(**SMALL)
  params = P.init(jax.random.key(0), spec)
  poses = _poses("car", n=8)

  @jax.jit
  def run(p):
    enc = T.encode("ours", "car", poses, spec=spec, rep_params=p, mode="floor")
    ref = P.embed(p, spec, poses, mode="floor")  # car inference: floor quantisation
    total = lambda q: sum(
      jnp.sum(v)
      for v in T.encode("ours", "car", poses, spec=spec, rep_params=q, mode="floor").values()
    )
    return enc, ref, jax.grad(total)(p)

  enc, ref, g = run(params)
  for k in ref:
    assert_close(enc[k], ref[k], atol=0)
  assert all(float(jnp.max(jnp.abs(x))) == 0 for x in jax.tree.leaves(g))  # stop_gradient


def test_mlp_embedding_round_trip():
  spec = settings.get("car").pose_spec()
  mlp = pose_encodings.MlpEncoding(spec).init(jax.random.key(3))
  assert set(mlp) == {"azimuth", "polar"}
  assert mlp["azimuth"]["hidden"]["kernel"].shape == (1, 128)
  assert mlp["azimuth"]["out"]["kernel"].shape == (128, 96)
  poses = _poses("car", n=32, seed=6)
  enc = jax.jit(lambda p: T.encode("mlp", "car", p, spec=spec, rep_params=mlp))(poses)
  assert_close(jnp.linalg.norm(enc["azimuth"], axis=-1), np.ones(32), atol=1e-5)
  dec = jax.jit(lambda e: T.decode("mlp", "car", e, spec=spec, rep_params=mlp))(enc)
  # Arg-min over 0.25-degree candidates, no refinement: a random MLP is poorly conditioned.
  _check_poses_close("car", dec, poses, pos_atol=0, ang_atol=math.radians(0.5))


def test_normalise_head_matches_pose_system():
  spec = settings.get("gqn").pose_spec()
  params = P.init(jax.random.key(1), spec)
  heads = {h.name: h for h in T.head_specs("ours", "gqn", spec=spec)}
  assert heads["xy"].norm == "block" and heads["xy"].n_blocks == 6
  assert heads["yaw"].norm == "unit"
  for name in ("xy", "yaw"):
    raw = params[name]["grid"]
    assert_close(
      pose_regressor.normalise_head(raw, heads[name]), P.grid_vectors(params, spec, name), atol=1e-7
    )


def test_head_sizes():
  sizes = lambda rep, s, spec=None: {h.name: h.size for h in T.head_specs(rep, s, spec=spec)}
  assert sizes("ours", "gqn") == {"xy": 96, "yaw": 96}
  assert sizes("ours", "car") == {"azimuth": 96, "polar": 96}
  assert sizes("ours", "seven_scenes") == dict.fromkeys(("x", "y", "z", "theta", "phi", "psi"), 32)
  assert sizes("euler", "gqn") == {"position": 2, "orientation": 1}
  assert sizes("sincos", "gqn") == {"position": 2, "orientation": 2}
  assert sizes("quat", "gibson") == {"position": 2, "orientation": 4}
  assert sizes("logq", "seven_scenes") == {"position": 3, "orientation": 3}
  assert sizes("axis_angle", "car") == {"orientation": 3}
  assert sizes("sincos", "car") == {"orientation": 4}
  assert sizes("euler", "seven_scenes") == {"position": 3, "orientation": 3}
  assert sizes("rot6d", "seven_scenes") == {"position": 3, "orientation": 6}
  assert sizes("svd9d", "car") == {"orientation": 9}
  groups = {h.name: h.group for h in T.head_specs("ours", "seven_scenes")}
  assert [groups[k] for k in ("x", "y", "z")] == ["position"] * 3
  assert [groups[k] for k in ("theta", "phi", "psi")] == ["orientation"] * 3


def test_invalid_inputs():
  with pytest.raises(ValueError, match="columns"):
    T.encode("quat", "gqn", np.zeros((2, 2)))
  with pytest.raises(ValueError, match="representation"):
    T.encode("rotation6d", "gqn", np.zeros((2, 3)))
  with pytest.raises(ValueError, match="setting"):
    T.head_specs("quat", "kitti")
  with pytest.raises(ValueError, match="rep_params"):
    T.encode("ours", "gqn", np.zeros((2, 3)))
  params = P.init(jax.random.key(0), settings.get("gqn").pose_spec(**SMALL))
  with pytest.raises(ValueError, match="quantisation mode"):
    T.encode(
      "ours",
      "gqn",
      np.zeros((2, 3)),
      spec=settings.get("gqn").pose_spec(**SMALL),
      rep_params=params,
    )
  with pytest.raises(ValueError, match="do not match"):
    T.head_specs("ours", "gqn", spec=settings.get("seven_scenes").pose_spec())


# ---------------------------------------------------------------------------- losses and table


def test_head_losses_hand_computed():
  pred = jnp.array([[1.0, 2.0], [0.0, 0.0]])
  tgt = jnp.array([[0.0, 0.0], [0.0, 3.0]])
  # squared L2 distances 5 and 9: mean 7; MSE (1 + 4 + 0 + 9) / 4; L1 (1 + 2 + 0 + 3) / 4.
  assert float(T.head_loss("l2", pred, tgt)) == pytest.approx(7.0)
  assert float(T.head_loss("mse", pred, tgt)) == pytest.approx(3.5)
  assert float(T.head_loss("l1", pred, tgt)) == pytest.approx(1.5)
  with pytest.raises(ValueError, match="unknown loss"):
    T.head_loss("huber", pred, tgt)
  heads = T.head_specs(
    "ours", "seven_scenes", spec=settings.get("seven_scenes").pose_spec(n_blocks=1, block_size=2)
  )
  p = {h.name: jnp.zeros((1, 2)) for h in heads}
  t = {h.name: jnp.full((1, 2), i + 1.0) for i, h in enumerate(heads)}
  g = T.group_losses("l1", p, t, heads)
  assert float(g["position"]) == pytest.approx(1 + 2 + 3)
  assert float(g["orientation"]) == pytest.approx(4 + 5 + 6)


def _total(h, groups, log_vars=None):
  """`T.total_loss` with the weighting of a `learner.HyperParams`."""
  kw = dict(weighting=h.weighting, init_s=h.init_s, s_factor=h.s_factor, weights=h.weights)
  return T.total_loss(groups, log_vars=log_vars, **kw)


def _log_vars(h):
  return T.init_log_vars(h.weighting, h.init_s, learn_s=h.learn_s)


def test_total_loss_weighting():
  groups = {"position": jnp.asarray(2.0), "orientation": jnp.asarray(0.5)}
  gqn = regression_hparams("gqn", "ours")
  s = _log_vars(gqn)
  assert float(s["position"]) == pytest.approx(-math.log(20)) and float(
    s["orientation"]
  ) == pytest.approx(-math.log(5))
  want = 20 * 2.0 - math.log(20) + 5 * 0.5 - math.log(5)
  assert float(_total(gqn, groups, log_vars=s)) == pytest.approx(want, rel=1e-6)
  assert float(_total(gqn, groups)) == pytest.approx(want, rel=1e-6)  # s held at init_s
  gib = regression_hparams("gibson", "ours")
  assert _log_vars(gib) == {}
  assert float(_total(gib, groups)) == pytest.approx(20 * 2.0 + 10 * 0.5)
  seven = regression_hparams("seven_scenes", "ours")
  s7 = _log_vars(seven)
  want7 = math.exp(3) * 2.0 + 3 * -3.0 + math.exp(3) * 0.5 + 3 * -3.0
  assert float(_total(seven, groups, log_vars=s7)) == pytest.approx(want7, rel=1e-6)
  # Car has no position group; only the orientation term counts.
  car = regression_hparams("car", "quat")
  assert float(_total(car, {"orientation": jnp.asarray(0.5)}, log_vars=_log_vars(car))) == (
    pytest.approx(math.exp(3) * 0.5 - 3, rel=1e-6)
  )
  with pytest.raises(ValueError, match="unknown weighting"):
    T.total_loss(groups, weighting="kendall")


def test_homoscedastic_gradient_wrt_s():
  dl_ds = jax.grad(T.homoscedastic, argnums=1)
  for factor in (1.0, 3.0):
    for s in (-3.0, 0.0, 1.5):
      g = dl_ds(jnp.asarray(0.7), jnp.asarray(s), factor=factor)
      assert float(g) == pytest.approx(factor - math.exp(-s) * 0.7, rel=1e-5)
    # Stationary at s* = log(L / factor).
    s_star = jnp.asarray(math.log(0.7 / factor))
    assert float(dl_ds(jnp.asarray(0.7), s_star, factor=factor)) == pytest.approx(0.0, abs=1e-6)
  # Through total_loss: the gradient reaches each group's s.
  h = regression_hparams("gqn", "quat")
  groups = {"position": jnp.asarray(2.0), "orientation": jnp.asarray(0.5)}
  g = jax.grad(lambda lv: _total(h, groups, log_vars=lv))(_log_vars(h))
  assert float(g["position"]) == pytest.approx(1 - 2.0, rel=1e-6)
  assert float(g["orientation"]) == pytest.approx(1 - math.exp(3) * 0.5, rel=1e-6)


# ---------------------------------------------------------------------------- the registry


def test_one_encoding_class_per_representation():
  assert T.REPRESENTATIONS == (
    "ours", "mlp", "euler", "axis_angle", "sincos", "quat", "logq", "rot6d", "svd9d",
    "untrained", "frozen_gen",
  )  # fmt: skip
  learned = {"ours", "mlp", "untrained", "frozen_gen"}
  assert set(T.LEARNED) == learned and set(T.BASELINES) == set(T.REPRESENTATIONS) - learned
  for name in T.REPRESENTATIONS:
    cls = pose_encodings.get(name)
    assert cls.table_name() == name and cls.loss in T.LOSSES and cls.regression_target
    assert pose_encodings.ENCODINGS[cls.name] is cls
  assert pose_encodings.get("ours") is pose_encodings.get("grid") is pose_encodings.GridEncoding
  with pytest.raises(ValueError, match="unknown pose encoding 'rotation6d'"):
    pose_encodings.get("rotation6d")
  with pytest.raises(ValueError, match="unknown representation 'lowdim'"):
    T.encoding("lowdim", "gqn")  # a view-synthesis input only
  enc = T.encoding("quat", "car")
  with pytest.raises(dataclasses.FrozenInstanceError):
    enc.setting = settings.GQN  # type: ignore[misc]
  # Learned encodings take a pose system, the hand-designed ones nothing but the setting.
  euler = T.encoding("euler", "car", spec=settings.CAR.pose_spec())
  assert euler.spec is None and euler.size() == 2 and euler.setting is settings.CAR
  assert T.encoding("ours", "car").spec == settings.CAR.pose_spec()

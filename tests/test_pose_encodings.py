"""Tests of camrep.pose_encodings: one interface and one registry for both stages' pose encodings,
the view-synthesis factory, GQN's low-dimensional vector, and the learned grid's regulariser.

Regression round trips of every encoding are in tests/test_targets.py; the numbers of the grid,
low-dim and MLP encodings against a stored reference in tests/test_pose.py.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from camrep import pose as P
from camrep import pose_encodings as E
from camrep import settings
from camrep.configs import gqn
from camrep.runtime.runconfig import ConfigError
from camrep.synthesis import components, synthesizers
from tests.utils import assert_close

pytestmark = pytest.mark.usefixtures("fast_compile")

GQN_SMALL = P.PoseSystemSpec(
  dofs=(P.BinnedPolarDof(spacing=0.25, n_directions=12), P.AngularDof("yaw", spacing=math.pi / 6)),
  n_blocks=2,
  block_size=4,
  exp_method="taylor2",
)
POSES = jnp.asarray([[0.1, -0.2, 1.0], [0.5, 0.3, 5.9]], jnp.float32)


def _input(kind, source="rooms", family=None):
  """The pose input of a view-synthesis run on GQN_SMALL (`synthesizers.pose_input`)."""
  c = gqn.get_config("smoke")
  c.rep.kind, c.data.source, c.data.family = kind, source, family or {}
  return synthesizers.pose_input(components.resolve(c), GQN_SMALL)


def test_one_registry_of_every_encoding():
  assert tuple(E.ENCODINGS) == (
    "grid", "mlp", "lowdim", "euler", "axis_angle", "sincos", "quat", "logq", "rot6d", "svd9d",
    "grid_untrained", "grid_frozen_gen",
  )  # fmt: skip
  assert E.SYNTHESIS_KINDS == ("grid", "mlp", "lowdim")
  for name, cls in E.ENCODINGS.items():
    assert issubclass(cls, E.PoseEncoding) and cls.name == name and E.get(name) is cls
    assert cls.title and (cls.synthesis_input or cls.regression_target)
  # "ours" and "mlp" exist once: the regression's names resolve to the synthesis classes.
  assert E.get("ours") is E.GridEncoding and E.get("mlp") is E.MlpEncoding
  with pytest.raises(ValueError, match="unknown pose encoding 'spline'"):
    E.get("spline")
  # Only the learned grid has a loss of its own (its generators tie nearby poses together); its
  # controls are the same grid, regressed from other states of a view-synthesis run.
  regularised = [n for n, c in E.ENCODINGS.items() if c.regularised]
  assert regularised == ["grid", "grid_untrained", "grid_frozen_gen"]
  assert all(issubclass(E.ENCODINGS[n], E.GridEncoding) for n in regularised)


@pytest.mark.parametrize("name", list(E.ENCODINGS))
def test_every_encoding_through_one_interface(name):
  """create, init, embed -> heads, decode, regulariser (zero but for the grid): one code path
  for every encoding, as both stages call them."""
  enc = E.create(name, settings.GQN, GQN_SMALL)
  hash(enc)  # a static jit argument
  params = enc.init(jax.random.key(0))
  v = jax.jit(lambda p, x: enc.embed(p, x))(params, POSES)
  heads = enc.heads()
  assert sorted(h.name for h in heads) == sorted(v)
  for h in heads:
    assert v[h.name].shape == (2, h.size)
  back = jax.jit(lambda p, v: enc.decode(p, v))(params, v)
  assert back.shape == POSES.shape
  if not enc.learned:  # the learned ones decode on their candidates, to a grid step here
    d = np.abs(np.asarray(back) - np.asarray(POSES))
    d[:, 2] = np.abs(np.mod(d[:, 2] + math.pi, 2 * math.pi) - math.pi)
    assert d.max() < 1e-5
  weights = E.Regularisation(rot_weight=100.0, dir_weight=0.8, n_pairs=8, mode="nearest")
  total, terms = enc.regulariser(params, jax.random.key(1), weights=weights)
  if enc.regularised:
    assert set(terms) == {"rot_xy", "rot_yaw", "dir_xy"} and float(total) > 0
  else:
    assert float(total) == 0.0 and terms == {}


def test_the_grid_regulariser_is_the_rotation_and_direction_losses():
  """What `Synthesizer.pose_loss` computed before it moved into the encoding: lambda_2 sum_l
  L_rot,l over extra pairs (eqs. 9) plus lambda_4 L_rot,theta (eq. 9.2), the same keys."""
  grid = E.GridEncoding(GQN_SMALL)
  params = grid.init(jax.random.key(2))
  key = jax.random.key(3)
  weights = E.Regularisation(rot_weight=100.0, dir_weight=0.8, n_pairs=16, mode="random")
  total, terms = grid.regulariser(params, key, weights=weights)
  key_pairs, _ = jax.random.split(key)
  extra = P.rotation_losses(key_pairs, params, GQN_SMALL, n_pairs=16, mode="random")
  direction = P.direction_loss(params, GQN_SMALL, "xy")
  assert_close(terms["rot_xy"], extra["xy"], atol=0)
  assert_close(terms["dir_xy"], direction, atol=0)
  want = 100.0 * (extra["xy"] + extra["yaw"]) + 0.8 * direction
  assert_close(total, want, atol=0, rtol=1e-6)
  # With data pairs: per DOF 0.5 extra + 0.5 the mean over scenes of the pairs' losses.
  pairs = jnp.asarray(
    [[[0.1, 0.2, 1.0], [0.15, 0.2, 1.1], [0.5, 0.5, 2.0], [0.5, 0.45, 2.2]]], jnp.float32
  )

  def scene_keys(k, n):
    return jax.vmap(lambda i: jax.random.fold_in(k, i))(jnp.arange(n))

  _, terms = grid.regulariser(params, key, weights=weights, pair_poses=pairs, scene_keys=scene_keys)
  assert not np.isclose(float(terms["rot_yaw"]), float(extra["yaw"]))


def test_embed_images_quantises_per_image():
  grid = E.GridEncoding(GQN_SMALL)
  params = grid.init(jax.random.key(4))
  poses = jnp.broadcast_to(POSES[None], (3, 2, 3))
  keys = jax.random.split(jax.random.key(5), 3)
  v = grid.embed_images(params, poses, mode="random", keys=keys)
  for e in range(3):
    one = P.embed(params, GQN_SMALL, poses[e], mode="random", key=keys[e])
    assert_close(v["yaw"][e], one["yaw"], atol=0)
  with pytest.raises(ValueError, match="per-image keys"):
    grid.embed_images(params, poses, mode="random")
  # Other encodings ignore quantisation and keys.
  mlp = E.MlpEncoding(GQN_SMALL)
  mp = mlp.init(jax.random.key(6))
  assert_close(
    mlp.embed_images(mp, poses, mode="random", keys=keys)["xy"], mlp.embed(mp, poses)["xy"], atol=0
  )


def test_gram_and_spread_of_the_grid_and_of_the_others():
  grid = E.GridEncoding(GQN_SMALL)
  params = grid.init(jax.random.key(7))
  values = jnp.linspace(0.0, 6.0, 7)
  want = P.gram(params, GQN_SMALL, "yaw", values=values)
  assert_close(grid.gram(params, "yaw", values), want, atol=1e-6)  # jitted vs eager
  assert_close(grid.spread(params)["yaw"], P.grid_std(params, GQN_SMALL, "yaw"), atol=0)
  low = E.LowDimEncoding(GQN_SMALL)
  g = np.asarray(low.gram({}, "yaw", values))
  assert_close(g, np.cos(values[:, None] - values[None, :]), atol=1e-6)  # (sin, cos) vectors
  assert low.spread({})["yaw"].shape == (2,)


@pytest.mark.slow  # ~10 s of compiles; the fast tier keeps the factory's lowdim test below
def test_the_view_synthesis_factory():
  kinds = {"grid": E.GridEncoding, "lowdim": E.LowDimEncoding, "mlp": E.MlpEncoding}
  for kind, cls in kinds.items():
    enc = _input(kind)
    assert type(enc) is cls and isinstance(enc, E.PoseEncoding)
    assert enc.setting is settings.GQN and enc.spec == GQN_SMALL
    params = enc.init(jax.random.key(0))
    v = jax.jit(lambda p, x, enc=enc: enc.embed(p, x))(params, POSES)
    assert set(v) == {"xy", "yaw"}
    assert jax.jit(lambda p, v, enc=enc: enc.decode(p, v))(params, v).shape == POSES.shape
  with pytest.raises(ConfigError, match="rep.kind"):
    _input("spline")
  with pytest.raises(ConfigError, match="rep.kind"):
    _input("quat")  # a regression target only
  grid = E.GridEncoding(GQN_SMALL, refine_steps=0)
  params = grid.init(jax.random.key(1))
  v = grid.embed(params, POSES)
  want = jax.jit(P.decode, static_argnums=1, static_argnames="refine_steps")
  assert_close(jax.jit(grid.decode)(params, v), want(params, GQN_SMALL, v, refine_steps=0), atol=0)


def test_lowdim_takes_explicit_constants_and_inverts():
  gqn = E.LowDimEncoding(GQN_SMALL, camera_height=0.3, pitch=-0.2)
  v = gqn.embed({}, POSES)
  assert_close(v["xy"][:, 2], [0.3, 0.3], atol=1e-7)
  assert_close(v["yaw"][:, 2:], [[np.sin(-0.2), np.cos(-0.2)]] * 2, atol=1e-7)
  assert_close(gqn.decode({}, v), POSES, atol=1e-6)
  assert [h.size for h in gqn.heads()] == [3, 4]
  plain = E.LowDimEncoding(GQN_SMALL)
  assert plain.embed({}, POSES)["xy"].shape == (2, 2) and [h.size for h in plain.heads()] == [2, 2]
  assert_close(plain.decode({}, plain.embed({}, POSES)), POSES, atol=1e-6)
  with pytest.raises(ValueError, match="camera_height"):
    E.LowDimEncoding(GQN_SMALL, camera_height=0.3)
  # The factory reads the rooms' constants from the family given, the renderer's defaults else,
  # for a setting whose low-dim input is GQN's 7-D vector.
  enc = _input("lowdim", family={"camera_height": 0.7})
  assert enc.camera_height == 0.7 and enc.pitch == E.gqn_lowdim_constants({})[1]
  assert settings.GQN.gqn_pose_vector and not settings.CAR.gqn_pose_vector
  assert _input("lowdim", source="object").camera_height is None

"""The multi-view transformer (`camrep.models.mvt`): shapes, parameter tree, one optimisation step
with every camera conditioning, the invariances of the whole model under its relative
conditionings, and independence of query views."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from camrep import pose as P
from camrep.models import camera_conditioning as cc
from camrep.models import mvt
from camrep.models.layers import param_count

pytestmark = pytest.mark.usefixtures("fast_compile")

SPEC = P.PoseSystemSpec(
  dofs=(P.LinearDof("x", -1.0, 1.0, 0.1), P.LinearDof("y", -1.0, 1.0, 0.1), P.AngularDof("yaw")),
  n_blocks=2,
  block_size=2,
)
CAMS = cc.RoomsCameras()
CONDITIONINGS = {
  "none": cc.NoCamera(),
  "raymap": cc.Raymap(CAMS),
  "gta": cc.GTA(CAMS),
  "gta_so3": cc.GTA(CAMS, group="so3"),
  "prope": cc.PRoPE(CAMS),
  "learned_abs": cc.LearnedAbsolute(SPEC),
  "learned_rel": cc.LearnedRelative(SPEC, rotation_weight=1.0, n_pairs=4),
}


def rooms_poses(rng, shape):
  xy = rng.uniform(-0.8, 0.8, size=(*shape, 2))
  return np.concatenate([xy, rng.uniform(0, 2 * np.pi, size=(*shape, 1))], -1).astype(np.float32)


def batch(seed=0, S=1, C=2, Q=1, size=8):
  rng = np.random.default_rng(seed)
  img = lambda n: rng.uniform(-1, 1, size=(S, n, size, size, 3)).astype(np.float32)
  return {
    "context_image": img(C),
    "context_pose": rooms_poses(rng, (S, C)),
    "target_image": img(Q),
    "target_pose": rooms_poses(rng, (S, Q)),
  }


def model(name, **kw):
  return mvt.PosedMVT(mvt.MVTTiny(**kw), CONDITIONINGS[name])


def init(m, b, seed=0):
  args = (b["context_image"], b["context_pose"], b["target_pose"])
  return jax.jit(m.init)(jax.random.key(seed), *args)


@functools.partial(jax.jit, static_argnums=0)
def apply(m, params, b):
  return m.apply(params, b["context_image"], b["context_pose"], b["target_pose"])[0]


def test_shapes_and_parameter_tree():
  m = model("raymap")
  b = batch(S=2, C=3, Q=2)
  params = init(m, b)
  assert params["rep"] == {}
  assert set(params["model"]) == {
    "context_embed",
    "query_embed",
    "patch_embed",
    "block0",
    "norm_out",
    "to_pixels",
  }
  assert set(params["model"]["block0"]) == {"norm1", "qkv", "proj", "norm2", "mlp_in", "mlp_out"}
  assert params["model"]["context_embed"]["kernel"].shape == (4 * 4 * 3 + 4 * 4 * 6, 32)
  out = apply(m, params, b)
  assert out.shape == (2, 2, 8, 8, 3)
  assert np.all(np.abs(np.asarray(out)) <= 1.0)


def test_relative_conditioning_gives_query_tokens_a_learned_constant():
  m = model("prope")
  params = init(m, batch())
  assert "query_token" in params["model"] and "query_embed" not in params["model"]


def test_quick_and_medium_sizes():
  b = batch(C=2, size=64)
  sizes = {}
  for name, module in (("quick", mvt.MVTQuick()), ("medium", mvt.MVTMedium())):
    m = mvt.PosedMVT(module, CONDITIONINGS["raymap"])
    shapes = jax.eval_shape(lambda m=m: init(m, b))
    sizes[name] = param_count(shapes["model"])
  assert 0.7e6 < sizes["quick"] < 1.0e6  # ~0.86 M
  assert 13e6 < sizes["medium"] < 16e6  # ~14.5 M


@pytest.mark.parametrize("name", sorted(CONDITIONINGS))
def test_one_optimisation_step_is_finite(name):
  m = model(name)
  b = batch(seed=1)
  params = init(m, b)
  tx = optax.adam(1e-3)

  @jax.jit
  def step(params, opt_state, key):
    (loss, terms), grads = jax.value_and_grad(m.loss, has_aux=True)(params, key, b)
    updates, opt_state = tx.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss, terms, grads

  new, _, loss, terms, grads = step(params, tx.init(params), jax.random.key(2))
  assert np.isfinite(float(loss)) and float(terms["rec"]) > 0
  for leaf in jax.tree.leaves(grads):
    assert np.all(np.isfinite(np.asarray(leaf)))
  moved = jax.tree.map(lambda a, b: float(jnp.max(jnp.abs(a - b))), params["model"], new["model"])
  assert max(jax.tree.leaves(moved)) > 0
  if name == "learned_rel":  # the one with the rotation loss on
    assert {"rot_x", "rot_y", "rot_yaw"} <= set(terms)
  if CONDITIONINGS[name].learns:
    g = jax.tree.leaves(grads["rep"])
    assert any(float(jnp.max(jnp.abs(x))) > 0 for x in g)


def shifted(b, shift):
  return {**b, "context_pose": b["context_pose"] + shift, "target_pose": b["target_pose"] + shift}


@pytest.mark.parametrize("dof", [0, 2])
def test_learned_relative_model_is_invariant_to_a_global_shift_along_a_dof(dof):
  """The whole transformer's prediction, not only the scores: every camera moved along x (or
  yaw, unwrapped) gives the same query image."""
  m = model("learned_rel")
  b = batch(seed=3, C=3, Q=2)
  params = init(m, b)
  shift = np.zeros(3, np.float32)
  shift[dof] = 0.3 if dof == 0 else 1.7
  out0, out1 = apply(m, params, b), apply(m, params, shifted(b, shift))
  np.testing.assert_allclose(np.asarray(out1), np.asarray(out0), atol=2e-4)


def test_prope_model_is_invariant_to_a_rigid_turn_of_the_room():
  m = model("prope")
  b = batch(seed=4, C=3, Q=2)
  params = init(m, b)

  def turn(p, phi=0.9):
    c, s = np.cos(phi), np.sin(phi)
    x, y, yaw = p[..., 0], p[..., 1], p[..., 2]
    return np.stack([c * x - s * y, s * x + c * y, yaw + phi], -1).astype(np.float32)

  b1 = {**b, "context_pose": turn(b["context_pose"]), "target_pose": turn(b["target_pose"])}
  np.testing.assert_allclose(
    np.asarray(apply(m, params, b1)), np.asarray(apply(m, params, b)), atol=2e-4
  )


def test_raymap_model_sees_absolute_position():
  m = model("raymap")
  b = batch(seed=5)
  params = init(m, b)
  out0, out1 = apply(m, params, b), apply(m, params, shifted(b, np.array([0.3, 0, 0], np.float32)))
  assert float(jnp.max(jnp.abs(out1 - out0))) > 1e-3


@pytest.mark.parametrize("name", ["raymap", "learned_rel"])
def test_query_views_are_synthesised_independently_and_context_order_does_not_matter(name):
  m = model(name)
  b = batch(seed=6, C=3, Q=2)
  params = init(m, b)
  both = np.asarray(apply(m, params, b))
  first = {**b, "target_pose": b["target_pose"][:, :1], "target_image": b["target_image"][:, :1]}
  np.testing.assert_allclose(np.asarray(apply(m, params, first))[:, 0], both[:, 0], atol=1e-5)
  perm = [2, 0, 1]
  swapped = {
    **b,
    "context_image": b["context_image"][:, perm],
    "context_pose": b["context_pose"][:, perm],
  }
  np.testing.assert_allclose(np.asarray(apply(m, params, swapped)), both, atol=1e-5)


def test_training_fits_a_fixed_batch():
  m = model("raymap")
  b = batch(seed=7)
  params = init(m, b)
  tx = optax.adam(3e-3)

  @jax.jit
  def step(params, opt_state):
    (loss, _), grads = jax.value_and_grad(m.loss, has_aux=True)(params, jax.random.key(0), b)
    updates, opt_state = tx.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss

  opt_state = tx.init(params)
  losses = []
  for _ in range(30):
    params, opt_state, loss = step(params, opt_state)
    losses.append(float(loss))
  assert losses[-1] < 0.5 * losses[0]


def test_a_conditioning_without_codes_is_refused():
  m = mvt.MVTTiny()
  img = jnp.zeros((1, 2, 8, 8, 3))
  with pytest.raises(ValueError, match="neither features nor a transform"):
    m.init(jax.random.key(0), img, cc.ViewCodes(), cc.ViewCodes())

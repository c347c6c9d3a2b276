"""camrep.synthesis.step.train_step's update order, on a toy model with a closed-form oracle."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from camrep.synthesis import step as step_lib

W, LR_MODEL, LR_REP = 0.5, 0.1, 0.05


class _Toy:
  """A synthesizer's interface (`loss`, `pose_loss`, `loss_weight`) over two small groups:
  loss = |a * v - t|^2 couples the model's `a` and the rep's `v`; pose loss = |v|^2 / 2."""

  loss_weight = W

  def loss(self, params, batch, key, step):
    r = params["model"]["a"] * params["rep"]["v"] - batch["t"]
    return jnp.sum(r**2), {"rec": jnp.sum(r**2)}

  def pose_loss(self, rep, batch, key):
    value = 0.5 * jnp.sum(rep["v"] ** 2)
    return value, {"rot": value}


def _reference(params, t, pose_steps):
  """The documented order, unrolled: `pose_steps` SGD steps of the rep on W * loss + pose loss,
  each from the last one's rep, then one model step on the loss at the final rep."""
  toy, batch = _Toy(), {"t": t}
  a, v = params["model"]["a"], params["rep"]["v"]
  loss = lambda a_, v_: toy.loss({"model": {"a": a_}, "rep": {"v": v_}}, batch, None, 0)[0]
  pose = lambda v_: toy.pose_loss({"v": v_}, batch, None)[0]
  for _ in range(pose_steps):
    last_pose = pose(v)
    v = v - LR_REP * jax.grad(lambda v_: W * loss(a, v_) + pose(v_))(v)
  a = a - LR_MODEL * jax.grad(loss)(a, v)
  return a, v, last_pose


@pytest.mark.parametrize("pose_steps", [1, 3])
def test_pose_steps_update_the_pose_input_then_the_model_once(pose_steps):
  params = {"model": {"a": jnp.array([1.5, -0.5])}, "rep": {"v": jnp.array([0.3, 2.0])}}
  tx = step_lib.Optimizers(model=optax.sgd(LR_MODEL), rep=optax.sgd(LR_REP))
  state = step_lib.TrainState(
    step=jnp.zeros((), jnp.int32),
    params=params,
    opt_model=tx.model.init(params["model"]),
    opt_rep=tx.rep.init(params["rep"]),
  )
  t = jnp.array([1.0, 0.5])
  p_step = step_lib.make_p_train_step(_Toy(), tx, pose_steps=pose_steps)
  new, metrics = p_step(step_lib.replicate(state, 1), {"t": t[None]}, jax.random.key(0))
  a, v, last_pose = _reference(params, t, pose_steps)
  np.testing.assert_allclose(np.asarray(new.params["rep"]["v"])[0], v, rtol=1e-6)
  np.testing.assert_allclose(np.asarray(new.params["model"]["a"])[0], a, rtol=1e-6)
  # The pose terms logged are the last pose step's (before its update).
  np.testing.assert_allclose(np.asarray(metrics["train/rot"])[0], last_pose, rtol=1e-6)
  assert int(np.asarray(new.step)[0]) == 1

"""One view-synthesis training step over any `synthesizers.Synthesizer` (paper sections
3.3-3.4): the model's loss and the pose input's rotation losses (eqs. 6-9), pmapped over the
local devices; plus the train state, its optimisers and its placement on the devices.

Parameter groups: "model" (decoder, encoder, per-scene tables) minimises the model's loss with
its own Adam; "rep" (grid vectors and generators) minimises lambda_1 loss + lambda_2 sum_l
L_rot,l + lambda_4 L_rot,theta with another Adam. `pose_steps` 0 (GQN) takes one simultaneous
step of both groups from the same forward pass; otherwise `pose_steps` pose-input steps on the same
batch, then one model step.

A step whose loss or gradients are non-finite skips its updates and says so in its metrics
("train/finite" 0); the run frame's loop reads that flag at its log and save steps
(`camrep.runtime.frame.fit`). `make_p_train_chunk` scans the step over K batches per dispatch.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import flax
import flax.serialization
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from camrep.data.feed import batches
from camrep.runtime import frame as frame_lib
from camrep.synthesis import synthesizers

Array = jax.Array

AXIS = synthesizers.AXIS


@flax.struct.dataclass
class TrainState:
  """Everything a step changes: step counter, both parameter groups, both optimiser states."""

  step: Array
  params: dict  # {"model": flax params, "rep": pose-input params}
  opt_model: Any
  opt_rep: Any


class Optimizers(NamedTuple):
  """One optimiser per parameter group."""

  model: optax.GradientTransformation
  rep: optax.GradientTransformation


def learning_rate(config, lr: float):
  """The config's schedule of one group's learning rate: "constant" (the paper), "cosine"
  (decay to 1% of `lr` over `total_steps`, a camrep option for short runs) or "linear" (GQN,
  Eslami et al. 2018: max(lr_f + (lr - lr_f)(1 - n / anneal_steps), lr_f), lr_f = final_scale lr;
  5e-4 -> 5e-5 over 1.6M steps)."""
  o = config.optax
  schedule = o.get("schedule", "constant")
  if schedule == "constant":
    return lr
  if schedule == "cosine":
    return optax.cosine_decay_schedule(lr, max(int(config.total_steps), 1), alpha=0.01)
  if schedule == "linear":
    return optax.linear_schedule(lr, lr * o.final_scale, max(int(o.anneal_steps), 1))
  raise ValueError(f"unknown optax.schedule {schedule!r}; choose 'constant', 'cosine' or 'linear'")


def make_optimizers(config) -> Optimizers:
  """Separate Adams per group (TF defaults eps 1e-8, b1 0.9, b2 0.999, as the authors). With
  `rep.freeze_generators` the rep group's generators ("*_coeffs" leaves: B, B0, C) get zero
  updates (`optax.set_to_zero`), so they keep their initial values; the grid vectors learn."""
  o = config.optax
  adam = lambda lr: optax.adam(learning_rate(config, lr), b1=0.9, b2=0.999, eps=1e-8)
  rep = adam(o.lr_rep)
  if config.rep.get("freeze_generators", False):
    rep = optax.multi_transform({"learned": rep, "frozen": optax.set_to_zero()}, _generator_labels)
  return Optimizers(model=adam(o.lr_model), rep=rep)


def _generator_labels(params):
  """ "frozen" for the generators' leaves (keys ending in "_coeffs", `camrep.dofs`), else
  "learned"."""
  return jax.tree_util.tree_map_with_path(
    lambda path, _: "frozen" if str(path[-1].key).endswith("_coeffs") else "learned", params
  )


def create_train_state(
  key: Array, model: synthesizers.Synthesizer, tx: Optimizers, batch: Mapping[str, Any]
) -> TrainState:
  """A fresh state, the parameters shaped from device 0's slice of a (D, S, ...) batch."""
  params = model.init(key, {k: batch[k][0] for k in ("image", "pose", "scene")})
  return TrainState(
    step=jnp.zeros((), jnp.int32),
    params=params,
    opt_model=tx.model.init(params["model"]),
    opt_rep=tx.rep.init(params["rep"]),
  )


def root_keys(config) -> tuple[Array, Array]:
  """(init_key, loop_key): the run's one root key from `config.seed`, split once."""
  init_key, loop_key = jax.random.split(jax.random.key(config.seed))
  return init_key, loop_key


def init_batch(config) -> dict[str, Any]:
  """The batch whose shapes a fresh state takes: the training layout's (D, S, ...) zeros from the
  config alone (`batches.dummy_batch`: no data is read or rendered; the parameters equal those
  initialised from the first real batch, tests/test_restore.py)."""
  dummy = batches.dummy_batch(config, num_devices=jax.local_device_count())
  return {k: dummy[k] for k in ("image", "pose", "scene")}


def init_fn(config, model, tx: Optimizers) -> Callable[[], TrainState]:
  """The run's fresh state as a function of nothing (`root_keys`' init key, `init_batch`'s
  shapes), jitted: eager init of the pose input and model costs seconds of op dispatch. A
  checkpoint restore traces it for its template (`restore_state`)."""
  init = jax.jit(lambda k, b: create_train_state(k, model, tx, b))
  return functools.partial(init, root_keys(config)[0], init_batch(config))


def train_step(
  state: TrainState,
  batch: Mapping[str, Array],
  key: Array,
  *,
  model: synthesizers.Synthesizer,
  tx: Optimizers,
  pose_steps: int,
) -> tuple[TrainState, dict[str, Array]]:
  """One step on one device's share of the batch; pmapped with axis name "batch".

  Args:
    state: the replicated TrainState.
    batch: this device's slice: image uint8 (S, V, H, W, 3), pose (S, V, P), scene (S,).
    key: the loop key (the same on every device); the step folds in `state.step`.

  Returns:
    (new state, metrics): train/loss (the rep group's objective), train/<term> of the model's
    and the pose input's losses, and norms. Updates are skipped (state kept) when any of them is
    not finite, and metrics["train/finite"] is 0 then.
  """
  params, w = state.params, model.loss_weight
  step_key = jax.random.fold_in(key, state.step)
  learns_rep = bool(jax.tree.leaves(params["rep"]))

  def loss_fn(pm, pr):
    return model.loss({"model": pm, "rep": pr}, batch, step_key, state.step)

  def pose_fn(pr):
    return model.pose_loss(pr, batch, step_key)

  if pose_steps == 0 or not learns_rep:
    # One step of both groups from the same forward pass.
    (total, terms), (g_model, g_rep_loss) = jax.value_and_grad(
      loss_fn, argnums=(0, 1), has_aux=True
    )(params["model"], params["rep"])
    (pose_total, pose_terms), g_rep_pose = jax.value_and_grad(pose_fn, has_aux=True)(params["rep"])
    g_rep = jax.tree.map(lambda a, b: w * a + b, g_rep_loss, g_rep_pose)
    g_model, g_rep = jax.lax.pmean((g_model, g_rep), AXIS)
    rep, opt_rep = params["rep"], state.opt_rep
    if learns_rep:
      up_r, opt_rep = tx.rep.update(g_rep, state.opt_rep, rep)
      rep = optax.apply_updates(rep, up_r)
  else:
    # pose_steps pose-input steps on the same batch (same draws), then one model step.
    rep, opt_rep = params["rep"], state.opt_rep

    def rep_objective(pr):
      total_, terms_ = loss_fn(params["model"], pr)
      pose_total_, pose_terms_ = pose_fn(pr)
      return w * total_ + pose_total_, (pose_total_, pose_terms_)

    def pose_step(carry, _):
      rep_, opt_rep_ = carry
      (_, aux), g = jax.value_and_grad(rep_objective, has_aux=True)(rep_)
      g = jax.lax.pmean(g, AXIS)
      up_r, opt_rep_ = tx.rep.update(g, opt_rep_, rep_)
      return (optax.apply_updates(rep_, up_r), opt_rep_), (aux, g)

    # Scanned, not unrolled: the objective is traced and compiled once, whatever pose_steps
    # (the 7-Scenes, car and Gibson smoke steps, pose_steps 2: 38-41% fewer jaxpr equations).
    (rep, opt_rep), last = jax.lax.scan(pose_step, (rep, opt_rep), length=pose_steps)
    (pose_total, pose_terms), g_rep = jax.tree.map(lambda a: a[-1], last)
    (total, terms), g_model = jax.value_and_grad(loss_fn, has_aux=True)(params["model"], rep)
    g_model = jax.lax.pmean(g_model, AXIS)
  up_m, opt_model = tx.model.update(g_model, state.opt_model, params["model"])
  new_params = {"model": optax.apply_updates(params["model"], up_m), "rep": rep}
  out = {
    "train/loss": w * total + pose_total,
    **{f"train/{k}": v for k, v in {**terms, **pose_terms}.items()},
  }
  return _finish(state, out, new_params, {"model": g_model, "rep": g_rep}, opt_model, opt_rep)


def _finish(state, out, new_params, grads, opt_model, opt_rep):
  """Device-averaged metrics, norms, and the finite guard: a step with a non-finite value keeps
  the old state (the loop stops at its next log step, naming the step)."""
  params = state.params
  out = jax.lax.pmean(out, AXIS)
  out["train/grad_norm_model"] = optax.tree.norm(grads["model"])
  out["train/grad_norm_rep"] = optax.tree.norm(grads["rep"])
  out["train/param_norm_model"] = optax.tree.norm(new_params["model"])
  out["train/param_norm_rep"] = optax.tree.norm(new_params["rep"])
  finite = jnp.array(True)
  for v in out.values():
    finite &= jnp.isfinite(v)
  out["train/finite"] = finite.astype(jnp.float32)
  keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, old)
  new_state = TrainState(
    step=state.step + 1,
    params=keep(new_params, params),
    opt_model=keep(opt_model, state.opt_model),
    opt_rep=keep(opt_rep, state.opt_rep),
  )
  return new_state, out


def make_p_train_step(model: synthesizers.Synthesizer, tx: Optimizers, *, pose_steps: int):
  """The pmapped `train_step`: p_step(replicated state, (D, ...) batch, key) with the loop key
  unreplicated (broadcast to every device) and the state donated."""
  fn = functools.partial(train_step, model=model, tx=tx, pose_steps=pose_steps)
  return jax.pmap(fn, axis_name=AXIS, in_axes=(0, 0, None), donate_argnums=(0,))


def make_p_train_chunk(model: synthesizers.Synthesizer, tx: Optimizers, *, pose_steps: int):
  """`train_step` scanned over K steps (`lax.scan`), pmapped: p_chunk(replicated state, (K, D,
  ...) batches (`BatchPipeline.batches`' layout, mapped over their device axis 1), key) ->
  (state, metrics stacked (D, K), ok (D,)), `ok` 1.0 when every step of the K was finite (the
  finite check reduced on the device). The state is donated."""
  fn = functools.partial(train_step, model=model, tx=tx, pose_steps=pose_steps)

  def chunk(state, batches_, key):
    state, metrics = jax.lax.scan(lambda s, b: fn(s, b, key), state, batches_)
    return state, metrics, jnp.min(metrics["train/finite"])

  return jax.pmap(chunk, axis_name=AXIS, in_axes=(0, 1, None), donate_argnums=(0,))


def state_dict(state: TrainState) -> dict:
  """The state as nested dicts of arrays (what the checkpointer saves)."""
  return flax.serialization.to_state_dict(state)


def from_state_dict(init: Callable[[], TrainState], state_d: dict) -> TrainState:
  """A saved state dict back into a TrainState shaped like `init()`'s (traced, not run)."""
  template = jax.eval_shape(init)
  return jax.tree.map(jnp.asarray, flax.serialization.from_state_dict(template, state_d))


def restore_state(checkpointer, init: Callable[[], TrainState], *, step: int | None = None):
  """(state, step) of a checkpoint (the newest readable one, or `step`), shaped like `init()`.

  Raises:
    CheckpointError: no such checkpoint, none readable, or none matches the template.
  """
  template = jax.tree.map(lambda x: np.zeros(x.shape, x.dtype), jax.eval_shape(init))
  state_d, _, restored = checkpointer.restore(state_dict(template), step=step)
  return from_state_dict(init, state_d), restored


# --------------------------------------------------------------------------------------------
# Device placement.


def replicate(tree, n: int):
  """Stacks n copies on a leading device axis, placed as the pmapped step returns its state
  (sharded over the local devices), so the step is traced once, not again on its 2nd call."""
  devices = jax.local_devices()[:n]
  sharding = jax.sharding.NamedSharding(
    jax.sharding.Mesh(np.asarray(devices), (AXIS,)), jax.sharding.PartitionSpec(AXIS)
  )

  def put(x):  # broadcast on the host: an eager jnp op would compile a program per leaf shape
    x = np.asarray(x)
    return jax.device_put(np.broadcast_to(x[None], (n, *x.shape)), sharding)

  return jax.tree.map(put, tree)


def unreplicate(tree):
  """The first local device's copy (the copies are equal), as NumPy arrays; read from its shard,
  not by indexing (an eager op, compiled once per leaf shape in every process)."""
  return jax.tree.map(lambda x: np.asarray(x.addressable_shards[0].data)[0, ...], tree)


def to_host(metrics: Mapping[str, Array]) -> dict[str, float]:
  """Device 0's scalar metrics as floats (they are device-averaged)."""
  return {k: float(np.asarray(v)[0]) for k, v in metrics.items()}


def restored_from(restored: Mapping | None) -> str:
  """How a run began, for the non-finite stop's message (`runtime.frame.restored_from`)."""
  return frame_lib.restored_from(restored)

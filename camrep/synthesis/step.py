"""One view-synthesis training step (paper sections 3.3-3.4, digest 3): the reconstruction loss
L_rec (eq. 9) and the rotation losses L_rot (eqs. 6-8) combined in a single pmapped step.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import flax
import flax.serialization
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from camrep import pose as P
from camrep import pose_inputs
from camrep.models import convdraw
from camrep.synthesis import components

Array = jax.Array


AXIS = "batch"


@flax.struct.dataclass
class TrainState:
  """Everything a step changes: step counter, both parameter groups, both optimiser states."""

  step: Array
  params: dict  # {"model": flax params, "rep": pose-system params}
  opt_model: Any
  opt_rep: Any


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


def make_optimizers(config) -> tuple[optax.GradientTransformation, optax.GradientTransformation]:
  """Separate Adams per group (digest 3; TF defaults eps 1e-8, b1 0.9, b2 0.999)."""
  o = config.optax
  return optax.adam(learning_rate(config, o.lr_model), b1=0.9, b2=0.999, eps=1e-8), optax.adam(
    learning_rate(config, o.lr_rep), b1=0.9, b2=0.999, eps=1e-8
  )


def init_params(
  key: Array, config, model, spec: P.PoseSystemSpec, batch: Mapping[str, np.ndarray]
) -> dict:
  """Initial parameters of both groups, shaped from one device's slice of a batch."""
  k_model, k_rep = jax.random.split(key)
  pose_input = pose_inputs.from_config(config, spec)
  rep = pose_input.init(k_rep)
  images = components.to_float_images(jnp.asarray(batch["image"][0]))
  vecs = P.concat(pose_input.embed(rep, jnp.asarray(batch["pose"][0])), spec)
  if components.model_kind(config) == "convdraw":
    c = config.data.n_context
    keys = jax.random.split(k_model, images.shape[0])
    init = jax.jit(model.init)
    variables = init(k_model, images[:, :c], vecs[:, :c], vecs[:, c:], images[:, c:], keys)
  elif config.task == "gqn":
    c = config.data.n_context
    variables = jax.jit(model.init)(k_model, images[:, :c], vecs[:, :c], vecs[:, c:])
  else:
    variables = jax.jit(model.init)(k_model, jnp.asarray(batch["scene"][0]), vecs)
  return {"model": variables["params"], "rep": rep}


def create_train_state(key: Array, config, model, spec, batch) -> TrainState:
  params = init_params(key, config, model, spec, batch)
  tx_model, tx_rep = make_optimizers(config)
  return TrainState(
    step=jnp.zeros((), jnp.int32),
    params=params,
    opt_model=tx_model.init(params["model"]),
    opt_rep=tx_rep.init(params["rep"]),
  )


def _scene_keys(key: Array, num_scenes: int) -> Array:
  """Per-scene keys from the scene's position in the GLOBAL batch (device-count independent)."""
  start = jax.lax.axis_index(AXIS) * num_scenes
  return jax.vmap(lambda i: jax.random.fold_in(key, i))(start + jnp.arange(num_scenes))


def _pose_vectors(config, rep, spec, poses, keys, mode):
  """(S, V, P) poses -> (S, V, n_dofs * d) with one key per scene."""
  pose_input = pose_inputs.from_config(config, spec)
  if mode == "random" and pose_input.learned_grid:
    f = lambda p, k: P.concat(pose_input.embed(rep, p, mode=mode, key=k), spec)
    return jax.vmap(f)(poses, keys)
  return P.concat(pose_input.embed(rep, poses, mode=mode), spec)


def reconstruction(model, config, spec, params_model, params_rep, batch, keys, mode):
  """L_rec = mean over target images of sum over pixels of (x_hat - x)^2 (digest 3).

  Returns:
    (loss, (prediction, target)); images in [-1, 1].
  """
  images = components.to_float_images(batch["image"])
  vecs = _pose_vectors(config, params_rep, spec, batch["pose"], keys, mode)
  if config.task == "gqn":
    c = config.data.n_context
    pred, _ = model.apply({"params": params_model}, images[:, :c], vecs[:, :c], vecs[:, c:])
    target = images[:, c:]
  else:
    pred, _ = model.apply({"params": params_model}, batch["scene"], vecs)
    target = images
  per_image = jnp.sum((pred - target) ** 2, axis=(-3, -2, -1))
  return jnp.mean(per_image), (pred, target)


def elbo(model, config, spec, params_model, batch, keys, step):
  """GQN's loss (model.kind "convdraw"): the negative ELBO per query image, averaged, with the
  pixel std annealed by `step` (`convdraw.pixel_sigma`, config.loss.sigma_*).

  Returns:
    (loss, terms {"elbo", "nll", "kl", "rec", "sigma", "kl_weight"}): loss = nll + beta kl, beta
    `convdraw.kl_weight` (config.loss.kl_*; 1: loss = elbo); "rec" is L_rec of the posterior mean
    image (sum of squared errors per image, comparable with the decoder's train/rec).
  """
  L = config.loss
  images = components.to_float_images(batch["image"])
  vecs = P.concat(pose_inputs.from_config(config, spec).embed(None, batch["pose"]), spec)
  c = config.data.n_context
  target = images[:, c:]
  mean, aux = model.apply(
    {"params": params_model}, images[:, :c], vecs[:, :c], vecs[:, c:], target, keys
  )
  sigma = convdraw.pixel_sigma(
    step, initial=L.sigma_initial, final=L.sigma_final, anneal_steps=L.sigma_anneal_steps
  )
  beta = convdraw.kl_weight(
    step,
    initial=L.get("kl_weight_initial", 1.0),
    anneal_steps=L.get("kl_anneal_steps", 0),
  )
  loss, terms = convdraw.negative_elbo(mean, target, aux["kl"], sigma, beta)
  rec = jnp.mean(jnp.sum((mean - target) ** 2, axis=(-3, -2, -1)))
  return loss, {**terms, "rec": rec, "sigma": sigma, "kl_weight": beta}


def rotation_objective(config, spec, params_rep, batch, key_pairs, keys):
  """lambda_2 sum_l L_rot,l + lambda_4 sum L_rot,theta, and the terms (eqs. 9, 9.2).

  Extra pairs use the same key on every device (the term is replicated); data pairs (the
  batch's image pairs) use per-scene keys and are averaged over devices by the caller's pmean.
  """
  L = config.loss
  if not pose_inputs.from_config(config, spec).learned_grid:  # no generators: nothing to tie
    return jnp.zeros((), jnp.float32), {}
  mode = config.rep.quantisation
  extra = P.rotation_losses(key_pairs, params_rep, spec, n_pairs=L.n_pairs, mode=mode)
  terms = {}
  for i, d in enumerate(spec.dofs):
    loss = extra[d.name]
    if L.data_pairs:
      poses = batch["pose"]  # (S, V, P), views laid out as (anchor, partner) pairs
      S, V = poses.shape[:2]
      pairs = poses.reshape(S, V // 2, 2, -1)[..., spec.columns(d.name)]
      x0, x1 = d.values(pairs[:, :, 0]), d.values(pairs[:, :, 1])
      kd = jax.vmap(lambda k, i=i: jax.random.fold_in(k, 1000 + i))(keys)
      per_scene = jax.vmap(
        lambda a, b, k, n=d.name: P.dof_rotation_loss(
          params_rep, spec, n, a, b, mode=mode, key=k if mode == "random" else None
        )
      )(x0, x1, kd)
      loss = 0.5 * loss + 0.5 * jnp.mean(per_scene)
    terms[f"rot_{d.name}"] = loss
  total = L.rot_weight * sum(terms.values())
  if L.dir_weight:
    for d in spec.dofs:
      if d.has_direction_loss:
        terms[f"dir_{d.name}"] = P.direction_loss(params_rep, spec, d.name)
        total = total + L.dir_weight * terms[f"dir_{d.name}"]
  return total, terms


def _global_norm(tree) -> Array:
  return optax.tree.norm(tree)


def train_step(state: TrainState, batch: Mapping[str, Array], key: Array, *, model, config, spec):
  """One step on one device's share of the batch; pmapped with axis name "batch".

  Args:
    state: the replicated TrainState.
    batch: this device's slice: image uint8 (S, V, H, W, 3), pose (S, V, P), scene (S,).
    key: the loop key (replicated); the step folds in `state.step`.

  Returns:
    (new state, metrics); updates are skipped (state kept) when any loss or gradient is not
    finite, and metrics["train/finite"] is 0 then.
  """
  if components.model_kind(config) == "convdraw":
    return elbo_train_step(state, batch, key, model=model, config=config, spec=spec)
  tx_model, tx_rep = make_optimizers(config)
  L = config.loss
  mode = config.rep.quantisation
  step_key = jax.random.fold_in(key, state.step)
  k_pairs, k_quant = jax.random.split(step_key)
  keys = _scene_keys(k_quant, batch["pose"].shape[0])
  params = state.params

  def rec_fn(pm, pr):
    return reconstruction(model, config, spec, pm, pr, batch, keys, mode)

  def rot_fn(pr):
    return rotation_objective(config, spec, pr, batch, k_pairs, keys)

  if config.optax.pose_steps == 0:
    # One simultaneous step from the same forward pass (GQN rooms).
    (rec, _), (g_model, g_rep_rec) = jax.value_and_grad(rec_fn, argnums=(0, 1), has_aux=True)(
      params["model"], params["rep"]
    )
    (rot_total, terms), g_rep_rot = jax.value_and_grad(rot_fn, has_aux=True)(params["rep"])
    g_rep = jax.tree.map(lambda a, b: L.rec_weight * a + b, g_rep_rec, g_rep_rot)
    g_model, g_rep = jax.lax.pmean((g_model, g_rep), AXIS)
    up_m, opt_model = tx_model.update(g_model, state.opt_model, params["model"])
    up_r, opt_rep = tx_rep.update(g_rep, state.opt_rep, params["rep"])
    new_params = {
      "model": optax.apply_updates(params["model"], up_m),
      "rep": optax.apply_updates(params["rep"], up_r),
    }
    grads = {"model": g_model, "rep": g_rep}
  else:
    # pose_steps pose-system steps on the same batch (same draws), then one decoder step.
    rep, opt_rep = params["rep"], state.opt_rep

    def pose_obj(pr):
      rec_, _ = rec_fn(params["model"], pr)
      rot_total_, terms_ = rot_fn(pr)
      return L.rec_weight * rec_ + rot_total_, (rec_, rot_total_, terms_)

    for _ in range(config.optax.pose_steps):
      (_, (rec, rot_total, terms)), g_rep = jax.value_and_grad(pose_obj, has_aux=True)(rep)
      g_rep = jax.lax.pmean(g_rep, AXIS)
      up_r, opt_rep = tx_rep.update(g_rep, opt_rep, rep)
      rep = optax.apply_updates(rep, up_r)
    (rec, _), g_model = jax.value_and_grad(rec_fn, has_aux=True)(params["model"], rep)
    g_model = jax.lax.pmean(g_model, AXIS)
    up_m, opt_model = tx_model.update(g_model, state.opt_model, params["model"])
    new_params = {"model": optax.apply_updates(params["model"], up_m), "rep": rep}
    grads = {"model": g_model, "rep": g_rep}

  loss = L.rec_weight * rec + rot_total
  out = {"train/loss": loss, "train/rec": rec, **{f"train/{k}": v for k, v in terms.items()}}
  return _finish(state, out, new_params, grads, opt_model, opt_rep)


def _finish(state, out, new_params, grads, opt_model, opt_rep):
  """Device-averaged metrics, norms and the finite guard shared by both steps."""
  params = state.params
  out = jax.lax.pmean(out, AXIS)
  out["train/grad_norm_model"] = _global_norm(grads["model"])
  out["train/grad_norm_rep"] = _global_norm(grads["rep"])
  out["train/param_norm_model"] = _global_norm(new_params["model"])
  out["train/param_norm_rep"] = _global_norm(new_params["rep"])
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


def elbo_train_step(state: TrainState, batch, key: Array, *, model, config, spec):
  """`train_step` of GQN's generator (model.kind "convdraw"): one Adam step of the model group
  on the negative ELBO (`elbo`); the pose-input group ("lowdim": no parameters) is left as is.

  Metrics: train/elbo (negative ELBO per query image, nats) = train/nll + train/kl, train/loss =
  train/nll + train/kl_weight train/kl (= train/elbo unless a KL weight schedule is set), train/rec
  (L_rec of the posterior mean), train/sigma (pixel std of this step), and the norms.
  """
  tx_model, _ = make_optimizers(config)
  params = state.params
  keys = _scene_keys(jax.random.fold_in(key, state.step), batch["pose"].shape[0])

  def loss_fn(pm):
    return elbo(model, config, spec, pm, batch, keys, state.step)

  (loss, terms), g_model = jax.value_and_grad(loss_fn, has_aux=True)(params["model"])
  g_model = jax.lax.pmean(g_model, AXIS)
  up_m, opt_model = tx_model.update(g_model, state.opt_model, params["model"])
  new_params = {"model": optax.apply_updates(params["model"], up_m), "rep": params["rep"]}
  grads = {"model": g_model, "rep": jax.tree.map(jnp.zeros_like, params["rep"])}
  out = {"train/loss": loss, **{f"train/{k}": v for k, v in terms.items()}}
  return _finish(state, out, new_params, grads, opt_model, state.opt_rep)


def make_p_train_step(config, model, spec):
  """The pmapped step (state donated)."""
  fn = functools.partial(train_step, model=model, config=config, spec=spec)
  return jax.pmap(fn, axis_name=AXIS, donate_argnums=(0,))


def state_dict(state: TrainState) -> dict:
  """The state as nested dicts of arrays (what the checkpointer saves)."""
  return flax.serialization.to_state_dict(state)

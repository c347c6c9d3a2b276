"""Learning the pose representation by view synthesis (paper section 4.1).

`train_and_evaluate(config, workdir)` runs the whole job; its parts are plain functions:

  pose_spec(config)              the pose system of the config's setting (paper section 3)
  make_model(config, n_scenes)   GQNSynthesis or TableSynthesis (digest section 2)
  make_pipeline(config, split)   batches (devices, scenes, views, ...) from the data
  create_train_state(...)        parameters of both groups and their optimiser states
  train_step(...)                ONE step for one device; pmapped over local devices
  evaluate(...)                  held-out-view PSNR / SSIM and a trivial baseline

Parameter groups (digest 3): "model" (decoder, encoder, per-scene tables) minimises L_rec with
its own Adam; "rep" (grid vectors and generators) minimises
lambda_1 L_rec + lambda_2 sum_l L_rot,l + lambda_4 L_rot,theta with another Adam. GQN takes one
simultaneous step of both groups from the same forward pass; the other settings take
`pose_steps` pose-system steps on the same batch, then one decoder step.

Randomness: one root key from `config.seed`, split once into init and loop keys; the step folds in
its step number, then splits by purpose. Per-scene draws (random neighbour quantisation) fold in
the scene's position in the global batch, so 1 device and 2 devices draw the same numbers.
"""

from __future__ import annotations

import functools
import json
import math
import os
import tempfile
import time
from collections.abc import Mapping
from typing import Any

import flax
import flax.struct
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax

from camrep import metrics as metrics_lib
from camrep import pose as P
from camrep.data import pipeline as pipeline_lib
from camrep.data.errors import DataError
from camrep.models.composite import GQNSynthesis, TableSynthesis

Array = jax.Array
AXIS = "batch"

PROCEDURAL = ("rooms", "object", "area", "scene6dof")
SETTING_OF_SOURCE = {
  "rooms": "gqn",
  "gqn": "gqn",
  "object": "car",
  "srn_cars": "car",
  "area": "gibson",
  "gibson": "gibson",
  "scene6dof": "seven_scenes",
  "seven_scenes": "seven_scenes",
}


# --------------------------------------------------------------------------------------------
# Pose system and model from the config.


def setting(config) -> str:
  """The paper's setting of the config's data source: gqn, car, gibson or seven_scenes."""
  try:
    return SETTING_OF_SOURCE[config.data.source]
  except KeyError:
    raise ValueError(
      f"unknown data.source {config.data.source!r}; choose one of {sorted(SETTING_OF_SOURCE)}"
    ) from None


class ConfigError(ValueError):
  """A config whose parts do not fit together (raised before any data or model is built)."""


def check_config(config) -> None:
  """Raises ConfigError on combinations the train step cannot run (e.g. GQN layouts without
  query views, or data-pair rotation losses on a batch that holds no pairs)."""
  d, L = config.data, config.loss
  try:
    setting(config)
    kind = rep_kind(config)
  except ValueError as e:  # unknown data.source or rep.kind
    raise ConfigError(str(e)) from None
  if config.total_steps < 1:
    raise ConfigError(f"total_steps must be >= 1, got {config.total_steps}")
  if config.task == "gqn" and not 1 <= d.n_context < d.views_per_scene:
    raise ConfigError(
      f"data.n_context must be in [1, views_per_scene) so that each scene has query views, "
      f"got n_context={d.n_context}, views_per_scene={d.views_per_scene}"
    )
  if L.data_pairs and kind == "grid" and d.mode != "pairs":
    raise ConfigError(
      "loss.data_pairs reads the batch's views as (anchor, partner) pairs: it needs "
      f"data.mode='pairs', got {d.mode!r} (GQN rooms: leave data_pairs off)"
    )


def pose_spec(config) -> P.PoseSystemSpec:
  """The pose system of the config's setting (digest 1.7), with camrep's options from config.rep."""
  r = config.rep
  ang = math.radians(r.angle_spacing_deg)

  def angle(name, low=0.0, high=2 * math.pi, periodic=None):
    return P.AngularDof(
      name, spacing=ang, low=low, high=high, periodic=r.periodic if periodic is None else periodic
    )

  def polar(low, high):
    return P.PolarDof(
      "xy",
      low=low,
      high=high,
      spacing=r.position_spacing,
      n_directions=r.n_directions,
      variant=r.polar_variant,
      block_norm=r.block_norm,
      pair_radius=r.pair_radius,
    )

  s = setting(config)
  if s == "gqn":
    dofs = (polar(-1.0, 1.0), angle("yaw"))
  elif s == "gibson":
    dofs = (polar(0.0, 2.0), angle("yaw"))
  elif s == "car":
    dofs = (angle("azimuth"), angle("polar", high=math.pi, periodic=False))
  else:
    sp = r.position_spacing
    dofs = (
      P.LinearDof("x", 0.0, 4.0, sp),
      P.LinearDof("y", 0.0, 1.5, sp),
      P.LinearDof("z", 0.0, 3.0, sp),
      angle("theta"),
      angle("phi", high=math.pi, periodic=False),
      angle("psi"),
    )
  return P.PoseSystemSpec(
    dofs=dofs,
    n_blocks=r.n_blocks,
    block_size=r.block_size,
    exp_method=r.exp_method,
    n_steps=r.n_steps,
  )


# The decoder's pose input (config.rep.kind): camrep's learned system (the paper's method), or a
# comparison input for the noise-robustness figure (issue 5): GQN's low-dimensional pose vector,
# or the supplement's MLP embedding (one 128 -> d MLP per DOF, trained with the decoder).
REP_KINDS = ("grid", "lowdim", "mlp")


def rep_kind(config) -> str:
  kind = config.rep.get("kind", "grid")
  if kind not in REP_KINDS:
    raise ValueError(f"unknown rep.kind {kind!r}; choose one of {REP_KINDS}")
  return kind


def lowdim_constants(config) -> tuple[float, float]:
  """(camera height, pitch) of the GQN-rooms procedural family: the constant z and pitch of GQN's
  low-dimensional pose vector."""
  from camrep.data import procedural

  rooms = procedural.RoomsConfig()
  fam = config.data.family
  return float(fam.get("camera_height", rooms.camera_height)), float(fam.get("pitch", rooms.pitch))


def lowdim_vectors(config, spec: P.PoseSystemSpec, poses: Array) -> dict[str, Array]:
  """GQN's low-dimensional pose input, split by DOF: {name: (..., k)}.

  GQN rooms (Eslami et al. 2018): (x, y, z, sin yaw, cos yaw, sin pitch, cos pitch), with the
  procedural rooms' constant camera height and pitch: "xy" -> (x, y, z), "yaw" -> (sin yaw,
  cos yaw, sin pitch, cos pitch). Other settings: polar / linear DOFs raw, angles (sin, cos).
  """
  gqn = setting(config) == "gqn"
  z, pitch = lowdim_constants(config) if gqn else (0.0, 0.0)
  out = {}
  for d in spec.dofs:
    cols = poses[..., spec.columns(d.name)]
    ones = jnp.ones(cols.shape[:-1] + (1,), cols.dtype)
    if isinstance(d, P.AngularDof):
      v = jnp.concatenate([jnp.sin(cols), jnp.cos(cols)], -1)
      if gqn:
        v = jnp.concatenate([v, math.sin(pitch) * ones, math.cos(pitch) * ones], -1)
    else:
      v = jnp.concatenate([cols, z * ones], -1) if gqn and isinstance(d, P.PolarDof) else cols
    out[d.name] = v
  return out


def init_rep(key: Array, config, spec: P.PoseSystemSpec) -> dict:
  """Parameters of the pose-input group ("rep"): the learned system, the MLPs, or none."""
  kind = rep_kind(config)
  if kind == "grid":
    return P.init(key, spec)
  if kind == "mlp":
    from camrep.regression import targets

    return targets.init_mlp(key, spec)
  return {}


def pose_vectors(
  config, spec: P.PoseSystemSpec, rep, poses: Array, *, mode: str = "nearest", key=None
) -> dict[str, Array]:
  """Per-DOF decoder inputs of poses (..., P) for the config's `rep.kind`: {name: (..., k)}.

  `mode` and `key` (quantisation of the learned system) are ignored by the other kinds.
  """
  kind = rep_kind(config)
  if kind == "grid":
    return P.embed(rep, spec, poses, mode=mode, key=key)
  if kind == "mlp":
    from camrep.regression import targets

    return targets.mlp_embed(rep, spec, poses)
  return lowdim_vectors(config, spec, poses)


def make_model(config, num_scenes: int):
  """The view-synthesis model of the config's setting."""
  m = config.model
  if config.task == "gqn":
    return GQNSynthesis(width=m.width, gamma_offset=1.0 if m.gamma_init_one else 0.0)
  return TableSynthesis(
    num_scenes=num_scenes,
    scene_dim=m.scene_dim,
    width=m.width,
    image_size=m.image_size,
    per_scene_norm=m.per_scene_norm,
    norm_eps=m.norm_eps,
    gamma_init_one=m.gamma_init_one,
  )


# --------------------------------------------------------------------------------------------
# Data.


def make_source(config, split_hint: str = "train"):
  """The procedural family of the config (for in-memory / rendered data)."""
  from camrep.data import procedural

  del split_hint
  overrides = dict(config.data.family.to_dict()) if config.data.family else {}
  return procedural.make_family(config.data.source, preset=config.data.preset, **overrides)


def make_pipeline(
  config,
  split: str,
  *,
  num_devices: int,
  process_index: int = 0,
  process_count: int = 1,
  for_eval: bool = False,
):
  """Batches of `split` laid out for the pmapped step (see camrep.data.pipeline).

  Data comes from `config.data.dir` (a prepared tfds directory) when set; otherwise from the
  procedural family, held in memory (`data.in_memory`) or rendered batch by batch. With
  `for_eval` the pipeline only serves `scene_views` (a one-scene, one-view layout).
  """
  d = config.data
  pcfg = pipeline_lib.PipelineConfig(
    num_devices=num_devices,
    scenes_per_device=1 if for_eval else d.scenes_per_device,
    views_per_scene=1 if for_eval else d.views_per_scene,
    mode="random" if for_eval else d.mode,
    seed=config.seed,
    num_threads=d.num_threads,
    prefetch=d.prefetch,
  )
  kw = dict(process_index=process_index, process_count=process_count)
  if d.dir:
    dataset_config = d.preset if d.preset != "default" else None
    return pipeline_lib.tfds_pipeline(
      d.dir, d.source, split, pcfg, dataset_config=dataset_config, **kw
    )
  if d.source not in PROCEDURAL:
    raise DataError(
      None,
      f"data.source {d.source!r} is a real dataset: prepare it with "
      f"`python -m camrep.data.prepare --source {d.source} --input PATH --data_dir DIR` "
      "and pass --config.data.dir=DIR",
    )
  family = make_source(config)
  if d.in_memory:
    return pipeline_lib.memory_pipeline(family, split, pcfg, **kw)
  return pipeline_lib.render_pipeline(family, split, pcfg, **kw)


def num_train_scenes(pipe) -> int:
  """Size of the per-scene tables: one past the largest training scene id."""
  return int(pipe.all_scene_ids.max()) + 1


def to_float_images(images: Array) -> Array:
  """uint8 [0, 255] -> float32 [-1, 1] (digest 6.1)."""
  return images.astype(jnp.float32) * (2.0 / 255.0) - 1.0


# --------------------------------------------------------------------------------------------
# Train state.


@flax.struct.dataclass
class TrainState:
  """Everything a step changes: step counter, both parameter groups, both optimiser states."""

  step: Array
  params: dict  # {"model": flax params, "rep": pose-system params}
  opt_model: Any
  opt_rep: Any


def learning_rate(config, lr: float):
  """The config's schedule of one group's learning rate: "constant" (the paper) or "cosine"
  (decay to 1% of `lr` over `total_steps`, a camrep option for short runs)."""
  schedule = config.optax.get("schedule", "constant")
  if schedule == "constant":
    return lr
  if schedule == "cosine":
    return optax.cosine_decay_schedule(lr, max(int(config.total_steps), 1), alpha=0.01)
  raise ValueError(f"unknown optax.schedule {schedule!r}; choose 'constant' or 'cosine'")


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
  rep = init_rep(k_rep, config, spec)
  images = to_float_images(jnp.asarray(batch["image"][0]))
  vecs = P.concat(pose_vectors(config, spec, rep, jnp.asarray(batch["pose"][0])), spec)
  if config.task == "gqn":
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


# --------------------------------------------------------------------------------------------
# The train step.


def _scene_keys(key: Array, num_scenes: int) -> Array:
  """Per-scene keys from the scene's position in the GLOBAL batch (device-count independent)."""
  start = jax.lax.axis_index(AXIS) * num_scenes
  return jax.vmap(lambda i: jax.random.fold_in(key, i))(start + jnp.arange(num_scenes))


def _pose_vectors(config, rep, spec, poses, keys, mode):
  """(S, V, P) poses -> (S, V, n_dofs * d) with one key per scene."""
  if mode == "random" and rep_kind(config) == "grid":
    f = lambda p, k: P.concat(P.embed(rep, spec, p, mode=mode, key=k), spec)
    return jax.vmap(f)(poses, keys)
  return P.concat(pose_vectors(config, spec, rep, poses, mode=mode), spec)


def reconstruction(model, config, spec, params_model, params_rep, batch, keys, mode):
  """L_rec = mean over target images of sum over pixels of (x_hat - x)^2 (digest 3).

  Returns:
    (loss, (prediction, target)); images in [-1, 1].
  """
  images = to_float_images(batch["image"])
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


def rotation_objective(config, spec, params_rep, batch, key_pairs, keys):
  """lambda_2 sum_l L_rot,l + lambda_4 sum L_rot,theta, and the terms (eqs. 9, 9.2).

  Extra pairs use the same key on every device (the term is replicated); data pairs (the
  batch's image pairs) use per-scene keys and are averaged over devices by the caller's pmean.
  """
  L = config.loss
  if rep_kind(config) != "grid":  # no generators: nothing to tie nearby poses together
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
      x0, x1 = pairs[:, :, 0], pairs[:, :, 1]
      if not isinstance(d, P.PolarDof):
        x0, x1 = x0[..., 0], x1[..., 0]
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
      if isinstance(d, P.PolarDof) and d.variant == "binned":
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


def make_p_train_step(config, model, spec):
  """The pmapped step (state donated)."""
  fn = functools.partial(train_step, model=model, config=config, spec=spec)
  return jax.pmap(fn, axis_name=AXIS, donate_argnums=(0,))


# --------------------------------------------------------------------------------------------
# Evaluation on held-out views.


def eval_batches(config, train_pipe, test_pipe) -> list[dict[str, np.ndarray]]:
  """Held-out-view evaluation set: per scene, the first test view as target and the first
  training views as context (GQN: the encoder's n_context views; other settings: up to
  evals.baseline_views views whose mean image is the baseline)."""
  ev = config.evals
  test_ids = np.intersect1d(test_pipe.all_scene_ids, train_pipe.all_scene_ids)
  if len(test_ids) == 0:
    raise DataError(None, "no scene has both training and held-out views to evaluate on")
  ids = test_ids[: ev.num_scenes]
  if config.task == "gqn":
    c = config.data.n_context
  else:  # baseline only: the mean of (up to baseline_views of) the scene's training views
    c = min(ev.baseline_views, min(train_pipe.num_scene_views(s) for s in ids))
  out = []
  for start in range(0, len(ids), ev.batch_scenes):
    chunk = ids[start : start + ev.batch_scenes]
    ctx = [train_pipe.scene_views(s, c) for s in chunk]
    tgt = [test_pipe.scene_views(s, 1) for s in chunk]
    out.append(
      {
        "context_image": np.stack([x[0] for x in ctx]),
        "context_pose": np.stack([x[1] for x in ctx]),
        "target_image": np.stack([x[0] for x in tgt]),
        "target_pose": np.stack([x[1] for x in tgt]),
        "scene": chunk.astype(np.int32),
      }
    )
  return out


def make_predict(config, model, spec):
  """jit(params, batch) -> (prediction, baseline), images (E, 1, H, W, 3) in [-1, 1]."""

  def predict(params, b):
    vec = lambda p: P.concat(pose_vectors(config, spec, params["rep"], p, mode="nearest"), spec)
    ctx = to_float_images(b["context_image"])
    if config.task == "gqn":
      pred, _ = model.apply(
        {"params": params["model"]}, ctx, vec(b["context_pose"]), vec(b["target_pose"])
      )
    else:
      pred, _ = model.apply({"params": params["model"]}, b["scene"], vec(b["target_pose"]))
    baseline = jnp.broadcast_to(jnp.mean(ctx, axis=1, keepdims=True), pred.shape)
    return pred, baseline

  return jax.jit(predict)


def evaluate(predict, params, batches) -> tuple[dict[str, float], dict[str, np.ndarray]]:
  """PSNR as the paper (mean of per-image PSNR on [0, 1]), SSIM, and the baseline's PSNR.

  Returns:
    (scalars {"eval/psnr", "eval/ssim", "eval/psnr_baseline", "eval/ssim_baseline"},
     arrays of the first batch for image grids and per-example values).
  """
  psnr, ssim, psnr_b, ssim_b = [], [], [], []
  first = None
  for b in batches:
    pred, base = predict(params, {k: jnp.asarray(v) for k, v in b.items()})
    tgt = to_float_images(jnp.asarray(b["target_image"]))
    psnr.append(np.asarray(metrics_lib.psnr(pred, tgt)).ravel())
    ssim.append(np.asarray(metrics_lib.ssim(pred, tgt)).ravel())
    psnr_b.append(np.asarray(metrics_lib.psnr(base, tgt)).ravel())
    ssim_b.append(np.asarray(metrics_lib.ssim(base, tgt)).ravel())
    if first is None:
      first = {
        "context": b["context_image"],
        "target": b["target_image"],
        "prediction": np.asarray(pred),
      }
  psnr, ssim, psnr_b, ssim_b = (np.concatenate(x) for x in (psnr, ssim, psnr_b, ssim_b))
  scalars = {
    "eval/psnr": float(np.mean(psnr)),
    "eval/ssim": float(np.mean(ssim)),
    "eval/psnr_baseline": float(np.mean(psnr_b)),
    "eval/ssim_baseline": float(np.mean(ssim_b)),
  }
  first.update(psnr=psnr, ssim=ssim, psnr_baseline=psnr_b)
  return scalars, first


# --------------------------------------------------------------------------------------------
# The loop.


class WorkdirError(RuntimeError):
  """The workdir cannot be created or written to."""


def check_workdir(workdir: str) -> None:
  """Creates `workdir` and writes / removes a probe file there, so that a bad workdir fails at
  once with a message naming it, not after minutes of data loading and compilation.

  Raises:
    WorkdirError: the directory cannot be created or written (permissions, a file in the way,
      a read-only or full file system).
  """
  try:
    os.makedirs(workdir, exist_ok=True)
    fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=workdir)
    os.close(fd)
    os.remove(probe)
  except OSError as e:
    raise WorkdirError(f"workdir {workdir} cannot be written: {e.strerror or e}") from e


def _replicate(tree, n: int):
  """Stacks n copies on a leading device axis, placed as the pmapped step returns its state
  (sharded over the local devices), so the step is traced once, not again on its 2nd call."""
  devices = jax.local_devices()[:n]
  sharding = jax.sharding.NamedSharding(
    jax.sharding.Mesh(np.asarray(devices), (AXIS,)), jax.sharding.PartitionSpec(AXIS)
  )

  def put(x):
    x = jnp.asarray(x)
    return jax.device_put(jnp.broadcast_to(x[None], (n, *x.shape)), sharding)

  return jax.tree.map(put, tree)


def _unreplicate(tree):
  return jax.tree.map(lambda x: np.asarray(x[0]), tree)


def _to_host(metrics: Mapping[str, Array]) -> dict[str, float]:
  return {k: float(np.asarray(v)[0]) for k, v in metrics.items()}


def state_dict(state: TrainState) -> dict:
  return flax.serialization.to_state_dict(state)


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str) -> dict[str, float]:
  """Trains and evaluates as the config says; resumes from the workdir's latest checkpoint.

  Writes to `workdir`: config.json, metrics.jsonl, checkpoints/, images/, tensorboard/.

  Several processes (jax.distributed): each runs this with the same config and workdir; each
  reads its own shard of the scenes, the pmapped step averages gradients over every device of
  every process, checkpoints are saved collectively (Orbax), and only process 0 logs, evaluates
  and writes metrics, images and final_metrics.json.

  Returns:
    The last logged scalars (train and eval).

  Raises:
    FloatingPointError: a loss or gradient became non-finite (the last good checkpoint is kept).
    WorkdirError: the workdir cannot be written.
  """
  from camrep.runtime import checkpoint as ckpt_lib
  from camrep.runtime import writers

  check_config(config)
  pidx, pcount = jax.process_index(), jax.process_count()
  lead = pidx == 0  # several processes: only process 0 logs, evaluates and prints
  check_workdir(workdir)
  writer = writers.MetricWriter(workdir) if lead else writers.NullWriter()
  writer.write_config(config)
  n_dev = jax.local_device_count()
  train_pipe = make_pipeline(
    config, "train", num_devices=n_dev, process_index=pidx, process_count=pcount
  )
  test_pipe = make_pipeline(config, "test", num_devices=1, for_eval=True)
  spec = pose_spec(config)
  model = make_model(config, num_train_scenes(train_pipe))
  init_key, loop_key = jax.random.split(jax.random.key(config.seed))

  checkpointer = ckpt_lib.Checkpointer(workdir, max_to_keep=config.max_to_keep)

  # Jitted: eager init of the pose system and model costs seconds of op dispatch.
  init_fn = jax.jit(lambda k, b: create_train_state(k, config, model, spec, b))
  first = train_pipe.batch(0)
  batch0 = {k: first[k] for k in ("image", "pose", "scene")}
  latest = checkpointer.latest_step()
  if latest is None:
    state, start = init_fn(init_key, batch0), 0
    writer.truncate_after(0)  # what a run killed before its first checkpoint logged
  else:
    template = jax.eval_shape(init_fn, init_key, batch0)
    state_d, _, start = checkpointer.restore(state_dict(jax.tree.map(_zeros, template)))
    state = flax.serialization.from_state_dict(template, state_d)
    state = jax.tree.map(jnp.asarray, state)
    writer.truncate_after(start)
    if lead:
      print(f"resumed from step {start} in {workdir}", flush=True)
  p_step = make_p_train_step(config, model, spec)
  predict = make_predict(config, model, spec)
  ebatches = eval_batches(config, train_pipe, test_pipe) if lead else []
  pstate = _replicate(state, n_dev)
  loop_keys = _replicate(jax.random.key_data(loop_key), n_dev)
  loop_keys = jax.vmap(jax.random.wrap_key_data)(jnp.asarray(loop_keys))

  total = config.total_steps
  progress = writers.Progress(total, start_step=start)
  signals = ckpt_lib.install_signal_handlers()
  last: dict[str, float] = {}
  it = train_pipe.iterator(start_step=start, num_steps=max(total - start, 0))
  t_last, steps_since = time.perf_counter(), 0

  def save(step):
    checkpointer.save(step, state_dict(_unreplicate(pstate)), extra={"step": step}, force=True)

  def stop_requested() -> bool:
    # Saves are collective: every process must agree to save and stop (any one was signalled).
    if pcount == 1:
      return signals.requested
    from jax.experimental import multihost_utils

    flags = multihost_utils.process_allgather(np.asarray(signals.requested, np.int32))
    return bool(np.any(flags))

  try:
    step = start
    for step in range(start + 1, total + 1):
      batch = next(it)
      pstate, m = p_step(pstate, {k: batch[k] for k in ("image", "pose", "scene")}, loop_keys)
      steps_since += 1
      finite = float(np.asarray(m["train/finite"])[0])
      if finite < 1:
        host = _to_host(m)
        bad = [k for k, v in host.items() if not math.isfinite(v)]
        writer.write_scalars(step, host)
        raise FloatingPointError(
          f"non-finite training values at step {step} ({', '.join(bad) or 'gradients'}); "
          f"updates of this step were skipped and the last good checkpoint is kept in {workdir}"
        )
      if writers.itstime(step, config.log_every_steps, total):
        now = time.perf_counter()
        host = _to_host(m)
        host["train/steps_per_sec"] = steps_since / max(now - t_last, 1e-9)
        t_last, steps_since = now, 0
        writer.write_scalars(step, host)
        last.update(host)
      status = progress.update(step)
      if status and lead:
        print(status, f"loss={float(np.asarray(m['train/loss'])[0]):.4f}", flush=True)
      if lead and writers.itstime(step, config.eval_every_steps, total):
        scalars, first = evaluate(predict, _unreplicate(pstate.params), ebatches)
        writer.write_scalars(step, scalars)
        g = config.evals.grid_scenes
        grid = writers.view_synthesis_grid(
          first["context"][:g], first["target"][:g], first["prediction"][:g]
        )
        writer.write_images(step, {"eval/grid": grid})
        last.update(scalars)
        print(f"step {step}: " + " ".join(f"{k}={v:.3f}" for k, v in scalars.items()), flush=True)
      stop = stop_requested()
      if writers.itstime(step, config.ckpt_every_steps, total) or stop:
        save(step)
      if stop:
        print(f"stopping at step {step} on a signal; checkpoint saved", flush=True)
        break
  finally:
    signals.uninstall()
    checkpointer.close()
    writer.close()
  if lead:
    with open(os.path.join(workdir, "final_metrics.json"), "w") as f:
      json.dump({"step": int(step), **last}, f, indent=1)
  return last


def _zeros(x):
  return np.zeros(x.shape, x.dtype)

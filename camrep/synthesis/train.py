"""The view-synthesis training loop (paper section 4.1): `train_and_evaluate(config, workdir)`.

The loop reads as the algorithm: build the run's parts from the config (`components`: pose
system, model, pipelines), start or resume the state (`step.create_train_state`, the workdir's
latest checkpoint), then repeat one pmapped step (`step.train_step`: the reconstruction and
rotation losses, paper eqs. 6-9), logging, evaluating on held-out views (`heldout`) and saving
checkpoints on their schedules, until `total_steps` or a stop signal.

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

import dataclasses
import json
import math
import os
import time
from collections.abc import Mapping
from typing import Any

import flax
import flax.struct
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from camrep import pose as P
from camrep.data import batches
from camrep.data import pipeline as pipeline_lib
from camrep.runtime import grids, runconfig
from camrep.runtime import progress as progress_lib
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import components, heldout
from camrep.synthesis import step as step_lib

Array = jax.Array


# --------------------------------------------------------------------------------------------
# Device placement.


def _replicate(tree, n: int):
  """Stacks n copies on a leading device axis, placed as the pmapped step returns its state
  (sharded over the local devices), so the step is traced once, not again on its 2nd call."""
  devices = jax.local_devices()[:n]
  sharding = jax.sharding.NamedSharding(
    jax.sharding.Mesh(np.asarray(devices), (step_lib.AXIS,)),
    jax.sharding.PartitionSpec(step_lib.AXIS),
  )

  def put(x):
    x = jnp.asarray(x)
    return jax.device_put(jnp.broadcast_to(x[None], (n, *x.shape)), sharding)

  return jax.tree.map(put, tree)


def _unreplicate(tree):
  return jax.tree.map(lambda x: np.asarray(x[0]), tree)


def _to_host(metrics: Mapping[str, Array]) -> dict[str, float]:
  return {k: float(np.asarray(v)[0]) for k, v in metrics.items()}


def _zeros(x):
  return np.zeros(x.shape, x.dtype)


# --------------------------------------------------------------------------------------------
# The job's parts.


@dataclasses.dataclass
class Job:
  """Everything one training job holds besides its state: what `train_and_evaluate` builds
  once from the config before the first step.

  Attributes:
    config, workdir: as given.
    lead: whether this process logs, evaluates and writes (process 0).
    checkpointer: the workdir's checkpoints.
    train_pipe, test_pipe: training batches of this process's shard; held-out views.
    spec, model: the pose system and the view-synthesis model.
    lock: the workdir lock (lead process only).
    changes: {field: (old, new)} between the workdir's stored config and this one.
    writer: metrics / images writer (a NullWriter off the lead process), set by `commit_start`.
  """

  config: ml_collections.ConfigDict
  workdir: str
  lead: bool
  checkpointer: Any
  train_pipe: Any
  test_pipe: Any
  spec: P.PoseSystemSpec
  model: Any
  lock: workdir_lib.WorkdirLock | None
  changes: dict[str, tuple[Any, Any]]
  writer: Any = None


def _has_checkpoints(workdir: str) -> bool:
  from camrep.runtime import checkpoint as ckpt_lib

  d = os.path.join(workdir, ckpt_lib.CHECKPOINT_SUBDIR)
  return os.path.isdir(d) and any(name.isdigit() for name in os.listdir(d))


def _topology(config) -> dict[str, int]:
  return workdir_lib.topology(
    processes=jax.process_count(),
    devices=jax.device_count(),
    scenes_per_device=config.data.scenes_per_device,
  )


def build_job(config: ml_collections.ConfigDict, workdir: str) -> Job:
  """Checks the config, the workdir (its stored config, its lock), then builds the data, pose
  system and model. Writes nothing into the workdir but the lock (released on failure).

  Raises:
    ConfigError: the config is inconsistent, or differs from the workdir's stored config in a
      field that may not change (or was not named in `allow_changes`).
    WorkdirError: the workdir cannot be written or another process is writing it.
  """
  from camrep.runtime import checkpoint as ckpt_lib

  components.check_config(config)
  lead = jax.process_index() == 0  # several processes: only process 0 logs, evaluates, writes
  existed = os.path.isdir(workdir)
  workdir_lib.check_workdir(workdir)
  stored = workdir_lib.read_stored_config(workdir)
  changes = {}
  if stored is not None and _has_checkpoints(workdir):
    changes = runconfig.check_changes(
      stored, config, resumable=runconfig.SYNTHESIS_RESUMABLE, workdir=workdir
    )
  if _has_checkpoints(workdir):  # another device count changes the global batch: refused
    allowed = workdir_lib.GLOBAL_BATCH in runconfig.parse_allow_changes(config.allow_changes)
    changes.update(workdir_lib.check_topology(workdir, _topology(config), allowed=allowed))
  lock = workdir_lib.WorkdirLock(workdir) if lead else None
  if lock is not None:
    lock.acquire()
  try:
    pidx, pcount = jax.process_index(), jax.process_count()
    train_pipe = components.make_pipeline(
      config,
      "train",
      num_devices=jax.local_device_count(),
      process_index=pidx,
      process_count=pcount,
    )
    test_pipe = components.make_pipeline(config, "test", num_devices=1, for_eval=True)
    return Job(
      config=config,
      workdir=workdir,
      lead=lead,
      checkpointer=ckpt_lib.Checkpointer(workdir, max_to_keep=config.max_to_keep),
      train_pipe=train_pipe,
      test_pipe=test_pipe,
      spec=components.pose_spec(config),
      model=components.make_model(config, components.num_train_scenes(train_pipe)),
      lock=lock,
      changes=changes,
    )
  except BaseException:
    abandon_start(workdir, lock, existed=existed)
    raise


def abandon_start(workdir: str, lock: workdir_lib.WorkdirLock | None, *, existed: bool) -> None:
  """Undoes a start that failed before `commit_start`: the lock, an empty checkpoints/ directory,
  and the workdir itself when this start created it and it is empty."""
  from camrep.runtime import checkpoint as ckpt_lib

  if lock is not None:
    lock.release()
  for d in (os.path.join(workdir, ckpt_lib.CHECKPOINT_SUBDIR), *([] if existed else [workdir])):
    try:
      os.rmdir(d)  # only when empty
    except OSError:
      pass


def restore_or_init(job: Job, init_key: Array) -> tuple[step_lib.TrainState, int]:
  """The state to start from and its step: the workdir's latest checkpoint, else a fresh init.

  Raises:
    CheckpointError: checkpoints exist but none fits the config (e.g. other shapes).
  """
  # Jitted: eager init of the pose system and model costs seconds of op dispatch.
  init_fn = jax.jit(lambda k, b: step_lib.create_train_state(k, job.config, job.model, job.spec, b))
  # Shapes only (the init reads no pixel): the same template for a fresh start and a restore.
  batch0 = batches.dummy_batch(job.config, num_devices=jax.local_device_count())
  if job.checkpointer.latest_step() is None:
    return init_fn(init_key, batch0), 0
  template = jax.eval_shape(init_fn, init_key, batch0)
  state_d, _, start = job.checkpointer.restore(step_lib.state_dict(jax.tree.map(_zeros, template)))
  state = jax.tree.map(jnp.asarray, flax.serialization.from_state_dict(template, state_d))
  if job.lead:
    print(f"resumed from step {start} in {job.workdir}", flush=True)
  return state, start


def commit_start(job: Job, start: int) -> None:
  """The first writes of an accepted start: metrics logged after `start` by an interrupted run
  are dropped, config.json becomes this config, config_history.jsonl records the start (and any
  config change, with its step), and a resume with changes is marked in the metrics."""
  from camrep.runtime import writers

  if not job.lead:
    job.writer = writers.NullWriter()
    return
  job.writer = writers.MetricWriter(job.workdir)
  job.writer.truncate_after(start)
  job.writer.write_config(job.config)
  event = "resume" if start > 0 else "start"
  workdir_lib.append_history(
    job.workdir, start, job.changes, what=event, topology=_topology(job.config)
  )
  if start > 0 and job.changes:
    job.writer.write_scalars(start, {"resume/config_changes": len(job.changes)})
    changed = ", ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in job.changes.items())
    print(f"config changed at step {start}: {changed}", flush=True)


def raise_if_not_finite(job: Job, step: int, metrics: Mapping[str, Array]) -> None:
  """Logs the step's values and raises FloatingPointError when the step flagged non-finite
  losses or gradients (the step already skipped its updates)."""
  if float(np.asarray(metrics["train/finite"])[0]) >= 1:
    return
  host = _to_host(metrics)
  bad = [k for k, v in host.items() if not math.isfinite(v)]
  job.writer.write_scalars(step, host)
  raise FloatingPointError(
    f"non-finite training values at step {step} ({', '.join(bad) or 'gradients'}); "
    f"updates of this step were skipped and the last good checkpoint is kept in {job.workdir}"
  )


class StepRate:
  """Training steps per second since the last call of `rate`."""

  def __init__(self):
    self._t, self._n = time.perf_counter(), 0

  def tick(self) -> None:
    self._n += 1

  def rate(self) -> float:
    now = time.perf_counter()
    r = self._n / max(now - self._t, 1e-9)
    self._t, self._n = now, 0
    return r


def evaluate_and_log(job: Job, predict, params, batches, step: int) -> dict[str, float]:
  """Held-out-view PSNR / SSIM of `params` written as eval/* scalars plus the eval/grid image."""
  scalars, first = heldout.evaluate(predict, params, batches)
  job.writer.write_scalars(step, scalars)
  g = job.config.evals.grid_scenes
  grid = grids.view_synthesis_grid(
    first["context"][:g], first["target"][:g], first["prediction"][:g]
  )
  job.writer.write_images(step, {"eval/grid": grid})
  print(f"step {step}: " + " ".join(f"{k}={v:.3f}" for k, v in scalars.items()), flush=True)
  return scalars


def stop_requested(signals) -> bool:
  """Whether any process was signalled to stop (saves are collective: all must agree)."""
  if jax.process_count() == 1:
    return signals.requested
  from jax.experimental import multihost_utils

  flags = multihost_utils.process_allgather(np.asarray(signals.requested, np.int32))
  return bool(np.any(flags))


def write_final_metrics(job: Job, step: int, last: Mapping[str, float]) -> None:
  """final_metrics.json: the last logged scalars, and the config changes of the run's history."""
  history = workdir_lib.read_history(job.workdir)
  changes = [{"step": h["step"], "changes": h["changes"]} for h in history if h["changes"]]
  with open(os.path.join(job.workdir, "final_metrics.json"), "w") as f:
    json.dump({"step": int(step), **last, "config_changes": changes}, f, indent=1)


# --------------------------------------------------------------------------------------------
# The loop.


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

  existed = os.path.isdir(workdir)
  job = build_job(config, workdir)
  init_key, loop_key = jax.random.split(jax.random.key(config.seed))
  try:
    state, start = restore_or_init(job, init_key)
    commit_start(job, start)
  except BaseException:
    job.checkpointer.close()
    abandon_start(workdir, job.lock, existed=existed)
    raise

  n_dev = jax.local_device_count()
  p_step = step_lib.make_p_train_step(config, job.model, job.spec)
  predict = heldout.make_predict(config, job.model, job.spec)
  eval_set = heldout.eval_batches(config, job.train_pipe, job.test_pipe) if job.lead else []
  pstate = _replicate(state, n_dev)
  loop_keys = jax.vmap(jax.random.wrap_key_data)(
    jnp.asarray(_replicate(jax.random.key_data(loop_key), n_dev))
  )

  total = config.total_steps
  progress = progress_lib.Progress(total, start_step=start)
  rate = StepRate()
  signals = ckpt_lib.install_signal_handlers()
  host_batches = job.train_pipe.iterator(start_step=start, num_steps=max(total - start, 0))
  # The next batches are copied to the devices while the step runs (data.device_prefetch).
  n_ahead = int(config.data.get("device_prefetch", 2))
  batches = (
    pipeline_lib.prefetch_to_device(host_batches, n_ahead, devices=jax.local_devices())
    if n_ahead > 0
    else host_batches
  )
  last: dict[str, float] = {}
  step = start
  try:
    for step in range(start + 1, total + 1):
      batch = next(batches)
      pstate, m = p_step(pstate, {k: batch[k] for k in ("image", "pose", "scene")}, loop_keys)
      rate.tick()
      raise_if_not_finite(job, step, m)
      if progress_lib.itstime(step, config.log_every_steps, total):
        host = {**_to_host(m), "train/steps_per_sec": rate.rate()}
        job.writer.write_scalars(step, host)
        last.update(host)
      status = progress.update(step)
      if status and job.lead:
        print(status, f"loss={float(np.asarray(m['train/loss'])[0]):.4f}", flush=True)
      if job.lead and progress_lib.itstime(step, config.eval_every_steps, total):
        last.update(evaluate_and_log(job, predict, _unreplicate(pstate.params), eval_set, step))
      stop = stop_requested(signals)
      if progress_lib.itstime(step, config.ckpt_every_steps, total) or stop:
        state_d = step_lib.state_dict(_unreplicate(pstate))
        job.checkpointer.save(step, state_d, extra={"step": step}, force=True)
      if stop:
        print(f"stopping at step {step} on a signal; checkpoint saved", flush=True)
        break
    if job.lead:
      write_final_metrics(job, step, last)
  finally:
    signals.uninstall()
    if hasattr(host_batches, "close"):  # stops grain's worker processes, if any
      host_batches.close()
    job.checkpointer.close()
    job.writer.close()
    if job.lock is not None:
      job.lock.release()
  return last

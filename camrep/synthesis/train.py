"""The view-synthesis training loop (paper section 4.1): `train_and_evaluate(config, workdir)`.

Build the run's parts from the config (`components`: data pipelines, pose system and model),
restore the workdir's latest checkpoint or initialise, then run the pmapped step
(`step.train_step`: the model's loss and the rotation losses, eqs. 6-9; K =
`steps_per_dispatch` of them scanned per dispatch) in the run frame's fit loop
(`runtime.frame`: lock, records, metrics, checkpoints, signals, the finite policy), which logs,
evaluates on held-out views (`heldout`) and saves checkpoints on their schedules, until
`total_steps`, a stop signal, or the plateau rule (`runtime.stopping`) on the held-out
evaluations (score: the held-out-view MSE 10^(-eval/psnr / 10)).

Randomness: one root key from `config.seed`, split once into init and loop keys; the step folds in
its step number, then splits by purpose. Per-scene draws (random neighbour quantisation) fold in
the scene's position in the global batch, so 1 device and 2 devices draw the same numbers.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator

import jax
import ml_collections
import numpy as np
from typing_extensions import override

from camrep.data.feed import pipeline as pipeline_lib
from camrep.models import layers
from camrep.runtime import frame as frame_lib
from camrep.runtime import session as session_lib
from camrep.runtime import stopping
from camrep.synthesis import components, config_schema, heldout, restore
from camrep.synthesis import step as step_lib

# What the plateau rule's curve holds (final_metrics.json "stopping").
SCORE = "10^(-eval/psnr / 10): held-out-view MSE (geometric mean over the evaluated views)"
KEYS = ("image", "pose", "scene")


def _print(line: str) -> None:
  print(line, flush=True)


class SynthesisStage(frame_lib.Stage):
  """View synthesis's part of the fit loop (`runtime.frame.Stage`): the replicated train state,
  the pmapped step (scanned over K batches when K > 1), the training batches on the devices,
  the held-out evaluation (lead only) and its plateau score."""

  def __init__(self, config, model, tx, train_pipe, test_pipe, writer, *, lead: bool, log):
    self.config, self.model, self.tx, self.train_pipe = config, model, tx, train_pipe
    self.loop_key = step_lib.root_keys(config)[1]
    self._evaluate = (
      heldout.make_evaluate(model, train_pipe, test_pipe, writer, log=log) if lead else None
    )

  @override
  def dispatch(self, n):
    pose_steps = self.config.optax.pose_steps
    if n == 1:
      p_step = step_lib.make_p_train_step(self.model, self.tx, pose_steps=pose_steps)

      def one(state, batch):
        state, metrics = p_step(state, batch, self.loop_key)
        return state, metrics, metrics["train/finite"]

      return one
    p_chunk = step_lib.make_p_train_chunk(self.model, self.tx, pose_steps=pose_steps)
    return lambda state, batches_: p_chunk(state, batches_, self.loop_key)

  @override
  def chunks(self, spans):
    spans = iter(spans)
    first = next(spans, None)
    if first is None:
      return iter(())
    start = first[0] - 1
    if frame_lib.steps_per_dispatch(self.config) == 1:
      return components.device_batches(self.config, self.train_pipe, start)
    return _stacked_device_batches(self.config, self.train_pipe, itertools.chain([first], spans))

  @override
  def rows(self, metrics, n):
    host = {k: np.asarray(v)[0] for k, v in metrics.items()}  # device 0's (device-averaged)
    if n == 1:
      return [{k: float(v) for k, v in host.items()}]
    return [{k: float(v[i]) for k, v in host.items()} for i in range(n)]

  @override
  def saved(self, state):
    return step_lib.state_dict(step_lib.unreplicate(state))

  @override
  def evaluate(self, state, step):
    return self._evaluate(step_lib.unreplicate(state.params), step)

  @override
  def score(self, row):
    return stopping.psnr_score(row["eval/psnr"]) if "eval/psnr" in row else None


def _stacked_device_batches(config, pipe, spans) -> Iterator[dict]:
  """The training batches of each span (first step, n), read in one go per span
  (`BatchPipeline.batches`, the batch of step s being `batch(s - 1)`): (K, D, ...) arrays,
  copied to the devices `data.device_prefetch` dispatches ahead; (D, ...) for a span of one
  step (the single-step program's layout)."""
  spans = [(first - 1, n) for first, n in spans]
  host = pipe.iterator(spans=spans)
  n_ahead = int(config.data.get("device_prefetch", 2))
  try:
    it = (
      pipeline_lib.prefetch_to_device(host, n_ahead, devices=jax.local_devices(), device_axis=1)
      if n_ahead > 0
      else host
    )
    for (_, n), b in zip(spans, it, strict=False):
      yield {k: b[k][0] for k in KEYS} if n == 1 else {k: b[k] for k in KEYS}
  finally:
    if hasattr(host, "close"):
      host.close()


def train_and_evaluate(
  config: ml_collections.ConfigDict, workdir: str, *, log: Callable[[str], None] = _print
) -> dict[str, float]:
  """Trains and evaluates as the config says; resumes from the workdir's latest checkpoint.

  Writes to `workdir`: config.json, record.json (`components.run_record`, checked at resume),
  config_history.jsonl, metrics.jsonl, checkpoints/, images/, tensorboard/, and once the run
  is complete its final pose system (pose_system.npz, `restore.save_pose_file`; a model that
  reads the setting's pose vectors) and final_metrics.json ({"complete": true, "step":
  total_steps, "num_params": {group: n}, ...}).
  The same command on a complete workdir changes nothing; with a larger `total_steps` (named in
  `allow_changes`) it extends the run. With the plateau rule on (`config.stop.min_improvement >
  0`) the run may complete before `total_steps`, and final_metrics.json records why
  ("stopping": `runtime.stopping.stopping_record`). SIGTERM or Ctrl-C saves a checkpoint and
  stops; the same command resumes.

  Several processes (jax.distributed): each runs this with the same config and workdir; each
  reads its own shard of the scenes, the pmapped step averages gradients over every device of
  every process, checkpoints are saved collectively (Orbax), and only process 0 logs, evaluates
  and writes metrics, images and final_metrics.json.

  Args:
    config: the run's config (checked first: `config_schema.validate`).
    workdir: the run's directory.
    log: called with each progress line (default: print, flushed).

  Returns:
    The last logged scalars (train and eval).

  Raises:
    ConfigError: a bad config, one the workdir's does not allow, or `total_steps` below the
      latest checkpoint's step.
    FloatingPointError: a loss or gradient became non-finite (the last checkpoint is kept).
    WorkdirError: the workdir cannot be written.
  """
  run = config_schema.validate(config)  # before anything is written
  lead = jax.process_index() == 0  # several processes: only process 0 logs, evaluates, writes
  record = components.run_record(run)  # the data and pose system, library defaults included
  rule = frame_lib.stopping_rule(config)
  # What the steps depend on besides the config (recorded per start, checked at resume).
  topology = frame_lib.topology(
    processes=jax.process_count(),
    devices=jax.device_count(),
    scenes_per_device=config.data.scenes_per_device,
  )
  with frame_lib.Frame(
    workdir,
    config,
    schema=config_schema.SCHEMA,
    record=record,
    lead=lead,
    log=log,
    topology=topology,
  ) as frame:
    done = frame.already_complete(rule)
    if done is not None:
      return done

    # Build the data and the model; restore the latest checkpoint or initialise.
    train_pipe, test_pipe = components.make_pipelines(config)
    model = components.make_model(run, components.num_train_scenes(train_pipe))
    tx = step_lib.make_optimizers(config)
    init = step_lib.init_fn(config, model, tx)
    state, start = frame.restore_or_init(
      init, saved=step_lib.state_dict, restored=lambda d: step_lib.from_state_dict(init, d)
    )
    frame.begin(start)
    # Only the lead evaluates (its evaluation set is built here, once).
    stage = SynthesisStage(
      config, model, tx, train_pipe, test_pipe, frame.writer, lead=lead, log=log
    )
    pstate = step_lib.replicate(state, jax.local_device_count())
    fit = frame_lib.fit(frame, stage, pstate, start, rule=rule)

    # The run is complete (at total_steps or at its plateau): final_metrics.json.
    last = fit.last
    if fit.complete:
      last = last if fit.step > start else session_lib.last_logged(workdir)
      record = dict(last)
      # Parameters per optimiser group (the comparisons state them beside their scores).
      record["num_params"] = {g: layers.param_count(p) for g, p in state.params.items()}
      if rule.active:
        record["stopping"] = fit.stopping_record(rule, config.total_steps, score=SCORE)
      if lead and model.reads_pose_vectors and not model.own_pose_system:
        # The regression targets' pose system, as the final checkpoint holds it.
        rep = step_lib.unreplicate(fit.state.params["rep"])
        restore.save_pose_file(workdir, rep, fit.step)
      frame.finish(fit.step, record)
  return last

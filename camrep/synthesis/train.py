"""The view-synthesis training loop (paper section 4.1): `train_and_evaluate(config, workdir)`.

Build the run's parts from the config (`components`: data pipelines, pose system and model),
restore the workdir's latest checkpoint or initialise, then repeat one pmapped step
(`step.train_step`: the model's loss and the rotation losses, eqs. 6-9), logging, evaluating on
held-out views (`heldout`) and saving checkpoints on their schedules, until `total_steps`, a
stop signal (`runtime.preemption`), or the plateau rule (`plateau`) on the held-out evaluations.
The workdir's lock, records and writer are a `runtime.session.Session`.

Randomness: one root key from `config.seed`, split once into init and loop keys; the step folds in
its step number, then splits by purpose. Per-scene draws (random neighbour quantisation) fold in
the scene's position in the global batch, so 1 device and 2 devices draw the same numbers.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable

import jax
import ml_collections
import numpy as np

from camrep.runtime import checkpoint as ckpt_lib
from camrep.runtime import preemption, runconfig, stopping
from camrep.runtime import progress as progress_lib
from camrep.runtime import session as session_lib
from camrep.synthesis import components, heldout, plateau
from camrep.synthesis import step as step_lib


def _print(line: str) -> None:
  print(line, flush=True)


def train_and_evaluate(
  config: ml_collections.ConfigDict, workdir: str, *, log: Callable[[str], None] = _print
) -> dict[str, float]:
  """Trains and evaluates as the config says; resumes from the workdir's latest checkpoint.

  Writes to `workdir`: config.json, record.json (`components.run_record`, checked at resume),
  config_history.jsonl, metrics.jsonl, checkpoints/, images/, tensorboard/, and
  final_metrics.json ({"complete": true, "step": total_steps, ...}) once the run is complete.
  The same command on a complete workdir changes nothing; with a larger `total_steps` (named in
  `allow_changes`) it extends the run. With the plateau rule on (`config.stop.min_improvement >
  0`) the run may complete before `total_steps`, and final_metrics.json records why
  ("stopping": see `plateau`).

  Several processes (jax.distributed): each runs this with the same config and workdir; each
  reads its own shard of the scenes, the pmapped step averages gradients over every device of
  every process, checkpoints are saved collectively (Orbax), and only process 0 logs, evaluates
  and writes metrics, images and final_metrics.json.

  Args:
    config: the run's config.
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
  components.check_config(config)
  lead = jax.process_index() == 0  # several processes: only process 0 logs, evaluates, writes
  record = components.run_record(config)  # the data and pose system, library defaults included
  rule = components.stopping_rule(config)
  with (
    session_lib.Session(
      workdir, config, resumable=runconfig.SYNTHESIS_RESUMABLE, record=record, lead=lead, log=log
    ) as session,
    ckpt_lib.Checkpointer(workdir, max_to_keep=config.max_to_keep) as ckpt,
  ):
    done = plateau.already_complete(config, workdir, ckpt.latest_step(), log, rule=rule)
    if done is not None:
      return done

    # Build the data and the model; restore the latest checkpoint or initialise.
    train_pipe, test_pipe = components.make_pipelines(config)
    model = components.make_model(config, components.num_train_scenes(train_pipe))
    tx = step_lib.make_optimizers(config)
    init = step_lib.init_fn(config, model, tx)
    state_d, _, restored = ckpt.restore_or_init(lambda: step_lib.state_dict(init()))
    state, start = step_lib.from_state_dict(init, state_d), restored or 0
    if restored is not None:
      log(f"resumed from step {start} in {workdir}")
    origin = step_lib.restored_from(ckpt.restored if restored is not None else None)
    session.begin(start)
    curve = plateau.recorded_curve(workdir, start) if lead and rule.active else []
    p_step = step_lib.make_p_train_step(model, tx, pose_steps=config.optax.pose_steps)
    if lead:  # only the lead evaluates (its evaluation set is built here, once)
      evaluate = heldout.make_evaluate(model, train_pipe, test_pipe, session.writer, log=log)
    pstate = step_lib.replicate(state, jax.local_device_count())
    loop_key = step_lib.root_keys(config)[1]
    total = config.total_steps
    progress = progress_lib.Progress(total, start_step=start)
    last, pending, step, stopped = {}, [], start, False
    # A resumed run whose curve ends at its start (another rule now): the rule decides at once.
    at_start = bool(curve) and curve[-1][0] == start
    ended, reason = plateau.agree(rule, curve, lead, check_now=at_start)

    # Train: one step; at log and save steps the non-finite check and the train scalars; the
    # held-out evaluation and the plateau rule; the checkpoint.
    with (
      preemption.install_signal_handlers() as signals,
      contextlib.closing(components.device_batches(config, train_pipe, start)) as batches,
    ):
      todo = range(start + 1, total + 1) if not ended else range(0)
      for step, batch in zip(todo, batches, strict=False):
        pstate, metrics = p_step(pstate, batch, loop_key)
        pending.append((step, metrics))
        stopped = preemption.stop_requested(signals)
        save = progress_lib.itstime(step, config.ckpt_every_steps, total) or stopped
        logs = progress_lib.itstime(step, config.log_every_steps, total)
        if logs or save:  # the host reads the steps' metrics only here: the device runs ahead
          step_lib.raise_if_not_finite(session.writer, pending, workdir, origin)
          pending = []
        if logs:
          last.update(_write_train_scalars(session.writer, step, metrics, progress))
        status = progress.update(step)
        if status and lead:
          log(f"{status} loss={float(np.asarray(metrics['train/loss'])[0]):.4f}")
        evaluated = progress_lib.itstime(step, config.eval_every_steps, total)
        if lead and evaluated:
          last.update(evaluate(step_lib.unreplicate(pstate.params), step))
          if rule.active:
            curve.append((step, stopping.psnr_score(last["eval/psnr"])))
        if evaluated and rule.active:
          ended, reason = plateau.agree(rule, curve, lead)
          if ended:
            step_lib.raise_if_not_finite(session.writer, pending, workdir, origin)
            pending, save = [], True
            if lead:
              log(f"stopping at step {step}: {reason}")
        if save:
          state_d = step_lib.state_dict(step_lib.unreplicate(pstate))
          ckpt.save(step, state_d, extra={"step": step}, force=True)
        if ended:
          break
        if stopped:
          log(f"stopping at step {step} on a signal; checkpoint saved")
          break

    # The run is complete (at total_steps or at its plateau): final_metrics.json.
    if ended or (not stopped and step == total):
      ckpt.wait_until_finished()  # final_metrics.json only once its checkpoint exists
      last = last if step > start else session_lib.last_logged(workdir)
      record = dict(last)
      if rule.active:
        why = reason if ended else "reached total_steps"
        record["stopping"] = plateau.stopping_record(rule, curve, step, total, ended, why)
      session.finish(step, record)
  return last


def _write_train_scalars(writer, step: int, metrics, progress) -> dict[str, float]:
  """Writes a log step's train scalars (device 0's, device-averaged) and steps/s; returns them."""
  host = step_lib.to_host(metrics)
  if math.isfinite(progress.steps_per_second):
    host["train/steps_per_sec"] = progress.steps_per_second
  writer.write_scalars(step, host)
  return host

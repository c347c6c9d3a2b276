"""The view-synthesis training loop (paper section 4.1): `train_and_evaluate(config, workdir)`.

Build the run's parts from the config (`components`: data pipelines, pose system and model),
restore the workdir's latest checkpoint or initialise, then repeat one pmapped step
(`step.train_step`: the model's loss and the rotation losses, eqs. 6-9), logging, evaluating on
held-out views (`heldout`) and saving checkpoints on their schedules, until `total_steps`, a
stop signal, or the plateau rule (`config.stop`, `runtime.stopping`) on the held-out evaluations.
The workdir's lock, records and writer are a `runtime.session.Session`.

Randomness: one root key from `config.seed`, split once into init and loop keys; the step folds in
its step number, then splits by purpose. Per-scene draws (random neighbour quantisation) fold in
the scene's position in the global batch, so 1 device and 2 devices draw the same numbers.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
from collections.abc import Callable, Iterator, Mapping

import jax
import ml_collections
import numpy as np

from camrep.data import pipeline as pipeline_lib
from camrep.runtime import checkpoint as ckpt_lib
from camrep.runtime import preemption, runconfig, stopping, writers
from camrep.runtime import progress as progress_lib
from camrep.runtime import session as session_lib
from camrep.synthesis import components, heldout
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
  `allow_changes`) it extends the run.

  With the plateau rule on (`config.stop.min_improvement > 0`), each held-out evaluation adds
  (step, 10^(-eval/psnr / 10)) to the validation curve (the curve of a resumed run is read back
  from metrics.jsonl), and when `stopping.check` says the curve has plateaued the run saves its
  checkpoint at that step and completes there: final_metrics.json's "step" is that step and its
  "stopping" record = {rule, score, stopped_early, steps, total_steps, reason, curve [[step,
  score], ...]} (written whenever the rule is on, also when the run reaches the cap). Rerunning an
  early-stopped run with the same rule changes nothing; with another rule (`stop` named in
  `allow_changes`) or the rule off it resumes from that step, and the rule is checked at once on
  the recorded curve.

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
  resumable = runconfig.SYNTHESIS_RESUMABLE
  record = components.run_record(config)  # the data and pose system, library defaults included
  with (
    session_lib.Session(
      workdir, config, resumable=resumable, record=record, lead=lead, log=log
    ) as session,
    ckpt_lib.Checkpointer(workdir, max_to_keep=config.max_to_keep) as ckpt,
  ):
    rule = components.stopping_rule(config)
    done = already_complete(config, workdir, ckpt.latest_step(), log, rule=rule)
    if done is not None:
      return done
    train_pipe, test_pipe = components.make_pipelines(config)
    model = components.make_model(config, components.num_train_scenes(train_pipe))
    tx = step_lib.make_optimizers(config)
    init = step_lib.init_fn(config, model, tx)
    state_d, _, restored = ckpt.restore_or_init(lambda: step_lib.state_dict(init()))
    state, start = step_lib.from_state_dict(init, state_d), restored or 0
    if restored is not None:
      log(f"resumed from step {start} in {workdir}")
    origin = restored_from(ckpt.restored if restored is not None else None)
    session.begin(start)
    curve = recorded_curve(workdir, start) if lead and rule.active else []

    p_step = step_lib.make_p_train_step(model, tx, pose_steps=config.optax.pose_steps)
    eval_set = heldout.eval_batches(model, train_pipe, test_pipe) if lead else []
    evaluate = functools.partial(
      heldout.evaluate_and_log,
      session.writer,
      heldout.make_predict(model),
      eval_set,
      grid_scenes=config.evals.grid_scenes,
      log=log,
    )
    pstate = step_lib.replicate(state, jax.local_device_count())
    loop_key = step_lib.root_keys(config)[1]
    total = config.total_steps
    progress = progress_lib.Progress(total, start_step=start)
    last, pending, step, stopped = {}, [], start, False
    # A resumed run whose curve ends at its start (another rule now): the rule decides at once.
    plateau, reason = agree(rule, curve, lead, check_now=bool(curve) and curve[-1][0] == start)
    with (
      preemption.install_signal_handlers() as signals,
      contextlib.closing(device_batches(config, train_pipe, start)) as batches,
    ):
      todo = range(start + 1, total + 1) if not plateau else range(0)
      for step, batch in zip(todo, batches, strict=False):
        pstate, metrics = p_step(pstate, batch, loop_key)
        pending.append((step, metrics))
        stopped = preemption.stop_requested(signals)
        save = progress_lib.itstime(step, config.ckpt_every_steps, total) or stopped
        if progress_lib.itstime(step, config.log_every_steps, total) or save:
          raise_if_not_finite(session.writer, pending, workdir, origin)  # host reads only here
          pending = []
        if progress_lib.itstime(step, config.log_every_steps, total):
          host = step_lib.to_host(metrics)
          if math.isfinite(progress.steps_per_second):
            host["train/steps_per_sec"] = progress.steps_per_second
          session.writer.write_scalars(step, host)
          last.update(host)
        status = progress.update(step)
        if status and lead:
          log(f"{status} loss={float(np.asarray(metrics['train/loss'])[0]):.4f}")
        evaluated = progress_lib.itstime(step, config.eval_every_steps, total)
        if lead and evaluated:
          last.update(evaluate(step_lib.unreplicate(pstate.params), step))
          if rule.active:
            curve.append((step, stopping.psnr_score(last["eval/psnr"])))
        if evaluated and rule.active:
          plateau, reason = agree(rule, curve, lead)
          if plateau:
            raise_if_not_finite(session.writer, pending, workdir)
            pending, save = [], True
            if lead:
              log(f"stopping at step {step}: {reason}")
        if save:
          state_d = step_lib.state_dict(step_lib.unreplicate(pstate))
          ckpt.save(step, state_d, extra={"step": step}, force=True)
        if plateau:
          break
        if stopped:
          log(f"stopping at step {step} on a signal; checkpoint saved")
          break
    if plateau or (not stopped and step == total):
      ckpt.wait_until_finished()  # final_metrics.json only once its checkpoint exists
      last = last if step > start else session_lib.last_logged(workdir)
      record = dict(last)
      if rule.active:
        why = reason if plateau else "reached total_steps"
        record["stopping"] = stopping_record(rule, curve, step, total, plateau, why)
      session.finish(step, record)
  return last


def device_batches(config, pipe, start: int) -> Iterator[dict]:
  """The training batches from `start` on, copied to the devices `data.device_prefetch` steps
  ahead while the step runs; closing it stops the pipeline's worker processes, if any."""
  host = pipe.iterator(start_step=start, num_steps=max(config.total_steps - start, 0))
  n_ahead = int(config.data.get("device_prefetch", 2))
  try:
    it = (
      pipeline_lib.prefetch_to_device(host, n_ahead, devices=jax.local_devices())
      if n_ahead > 0
      else host
    )
    for b in it:
      yield {k: b[k] for k in ("image", "pose", "scene")}
  finally:
    if hasattr(host, "close"):
      host.close()


def already_complete(
  config, workdir: str, latest: int | None, log, *, rule: stopping.Rule | None = None
) -> dict[str, float] | None:
  """final_metrics.json's scalars when the workdir holds this run complete (nothing is written):
  at `total_steps`, or stopped early at its latest checkpoint by the same plateau `rule`. None
  when there is training (or the final record) left to do.

  Raises:
    ConfigError: `total_steps` is below the latest checkpoint's step.
  """
  total = config.total_steps
  if latest is not None and latest > total:
    raise runconfig.ConfigError(
      f"total_steps={total} is below the step {latest} of the latest checkpoint in {workdir}: "
      "the run is already past it; raise total_steps or use another --workdir (nothing changed)"
    )
  if latest is None or not session_lib.is_complete(workdir, latest):
    return None
  final = session_lib.read_final(workdir)
  if latest == total:
    log(f"{workdir} is complete at step {total} (final_metrics.json); nothing to do")
  elif stopped_early_by(final, rule):
    log(
      f"{workdir} is complete at step {latest}, stopped by the plateau rule "
      f"({final['stopping']['reason']}); nothing to do"
    )
  else:
    return None
  return {k: v for k, v in final.items() if "/" in k}


def stopped_early_by(final: Mapping | None, rule: stopping.Rule | None) -> bool:
  """Whether a final_metrics.json record says its run stopped early under this active `rule`."""
  s = (final or {}).get("stopping")
  if rule is None or not rule.active or not isinstance(s, Mapping):
    return False
  return s.get("stopped_early") is True and s.get("rule") == dataclasses.asdict(rule)


def recorded_curve(workdir: str, start: int) -> list[tuple[int, float]]:
  """The plateau rule's curve up to `start` from metrics.jsonl: (step, 10^(-eval/psnr / 10)) of
  each held-out evaluation logged (a resumed run goes on with the curve it had)."""
  return [
    (int(r["step"]), stopping.psnr_score(r["eval/psnr"]))
    for r in writers.read_metrics(workdir)
    if "eval/psnr" in r and int(r["step"]) <= start
  ]


def agree(rule: stopping.Rule, curve, lead: bool, *, check_now: bool = True) -> tuple[bool, str]:
  """The lead's `stopping.check` of the curve (only the lead evaluates), shared with every
  process (saves are collective: all must stop at the same step). Call on every process."""
  stop, why = stopping.check(rule, curve) if lead and check_now else (False, "")
  if jax.process_count() > 1 and rule.active:
    from jax.experimental import multihost_utils

    flags = multihost_utils.process_allgather(np.asarray(stop, np.int32))
    stop = bool(np.any(flags))
  return stop, why


def stopping_record(rule, curve, step: int, total: int, stopped_early: bool, reason: str) -> dict:
  """final_metrics.json's "stopping": the rule, its score, where and why the run ended, and
  the validation curve [[step, score], ...]."""
  return {
    "rule": dataclasses.asdict(rule),
    "score": "10^(-eval/psnr / 10): held-out-view MSE (geometric mean over the evaluated views)",
    "stopped_early": bool(stopped_early),
    "steps": int(step),
    "total_steps": int(total),
    "reason": reason,
    "curve": [[int(t), float(v)] for t, v in curve],
  }


def restored_from(restored: Mapping | None) -> str:
  """How a run began, for the non-finite stop's message: `Checkpointer.restored` or None."""
  if restored is None:
    return "this run started from step 0 (no checkpoint restored)"
  how = (
    "checksum verified"
    if restored.get("verified")
    else "not verified (written before checkpoints had checksums)"
  )
  return f"this run restored from step {restored['step']}, {how}"


def raise_if_not_finite(
  writer, pending: list[tuple[int, Mapping]], workdir: str, origin: str = ""
) -> None:
  """Raises FloatingPointError naming the first of the `pending` (step, metrics) that flagged
  non-finite losses or gradients (the step skipped its updates), after logging its values;
  `origin` (`restored_from`) says which checkpoint the run began from and whether it was
  verified."""
  for step, metrics in pending:
    if float(np.asarray(metrics["train/finite"])[0]) >= 1:
      continue
    host = step_lib.to_host(metrics)
    bad = [k for k, v in host.items() if not math.isfinite(v)]
    writer.write_scalars(step, host)
    raise FloatingPointError(
      f"non-finite training values at step {step} ({', '.join(bad) or 'gradients'}); "
      f"updates of this step were skipped; {origin + '; ' if origin else ''}the last checkpoint "
      f"is kept in {workdir} and a resume verifies its checksums before using it"
    )


"""One run frame and one fit loop for every training stage (view synthesis, pose regression).

  with Frame(workdir, config, schema=SCHEMA, record=record) as frame:
    done = frame.already_complete(rule)      # complete already: its final scalars, nothing written
    state, start = frame.restore_or_init(init, saved=..., restored=...)
    frame.begin(start)                       # first writes; frame.writer is open from here
    result = fit(frame, stage, state, start, rule=rule)
    if result.complete:
      frame.finish(result.step, record)      # final_metrics.json, {"complete": true, ...}

The frame (`Frame`, a context manager) is a run's hold on its workdir:

  on entry          the workdir checked (writable; one that holds checkpoints but no config.json
                    is refused, never resumed unchecked), the config against the stored one
                    (`runconfig.check_changes` with the stage's declarations), what decides the
                    data and pose system against record.json (`workdir.check_record`; none
                    there: one warning, and `begin` writes it), the device topology
                    (`workdir.check_topology`), and the workdir's lock taken;
  restore_or_init   the latest readable checkpoint (`checkpoint.Checkpointer`), or a fresh state;
  begin             the first writes of an accepted start: final_metrics.json (if any) marked
                    incomplete, metrics logged after the restored step by an interrupted run
                    dropped, config.json made this config, record.json, config_history.jsonl
                    told of the start (and of any config change, with its step);
  finish            final_metrics.json: the last logged scalars, the config changes of the run's
                    history, the machine, {"complete": true, "step": step}; written atomically
                    once what it describes is on disk;
  on exit           the checkpointer and the metric writer closed and the lock released whatever
                    happened (a full disk while logging included: no stale lock is left); a stop
                    on non-finite values recorded in final_metrics.json ({"complete": false,
                    "stopped": "non-finite", "reason"}); a start that failed before `begin`
                    leaves the workdir as it found it.

A stage that starts over instead of resuming a changed run (`restart=True`, regression) compares
the stored config whenever there is one, and a change of a FIXED field named in `allow_changes`
(or of its record.json) makes the run start again from step 0: `begin` removes the old
checkpoints, final_metrics.json and the stage's outputs (`outputs`).

The fit loop (`fit`) runs a `Stage` (its state, step, batches, evaluation and plateau score) from
the restored step to `total_steps`:

  * K = `steps_per_dispatch` steps per dispatch: the stage's step scanned over K batches
    (`lax.scan`), the metrics stacked and the finite check reduced on the device. Dispatches end
    at every multiple of K, at every evaluation and checkpoint step and at `total_steps`
    (`spans`), so where a run (re)starts does not change them and a resume stays exact; K = 1
    dispatches the plain step, each step as it is;
  * logging at `itstime(step, log_every_steps, total)`, from the stacked metrics of every step;
  * the finite policy: the step flags non-finite values and skips its update; the host reads
    the flags at log and checkpoint steps only (the device runs ahead) and stops with
    FloatingPointError naming the first bad step (its values logged; the last checkpoint kept);
  * evaluation at `eval_every_steps` (the lead process only) and the plateau rule
    (`stopping.check`) on the stage's score of each evaluation, decided by the lead and shared
    with every process (`agree`);
  * checkpoints at `ckpt_every_steps`, where the rule stops the run, and on a stop signal;
  * signals (`preemption`): SIGTERM or Ctrl-C saves a checkpoint at the end of the dispatch and
    stops, with one line saying how to resume (exit status 0); the same command resumes.

Several processes (jax.distributed): every process runs the frame and the loop with the same
workdir; only the lead (process 0) takes the lock, writes and evaluates (the others get a
`writers.NullWriter`); checkpoints are saved collectively, and stop signals and plateau
decisions are combined over every process so that all stop at the same step.
"""

from __future__ import annotations

import abc
import dataclasses
import itertools
import json
import os
import shutil
import signal
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any

import jax
import numpy as np

from camrep.runtime import checkpoint as ckpt_lib
from camrep.runtime import preemption, runconfig, stopping, writers
from camrep.runtime import progress as progress_lib
from camrep.runtime import session as session_lib
from camrep.runtime import validate as V
from camrep.runtime import workdir as workdir_lib
from camrep.runtime.runconfig import ConfigError

_F = V.Field

# The fields every training loop reads, declared once (each stage's schema includes them).
FIELDS: dict[str, V.Field] = {
  "total_steps": _F(V.count(1), resume=V.MAY_CHANGE),
  "log_every_steps": _F(V.count(0), resume=V.MAY_CHANGE),  # 0: never
  "eval_every_steps": _F(V.count(0), resume=V.MAY_CHANGE),  # 0: never (regression: at the end)
  # Retention that keeps no checkpoint would lose the run: refused.
  "ckpt_every_steps": _F(V.count(1), resume=V.MAY_CHANGE),
  "max_to_keep": _F(V.POSITIVE, resume=V.MAY_CHANGE),
  # K: steps per dispatch (results equal K = 1's up to float round-off).
  "steps_per_dispatch": _F(V.count(1), resume=V.MAY_CHANGE),
  "allow_changes": _F(V.ANY, resume=V.FREE),
  # The plateau stopping rule (`stopping`; the ranges `rule_from_config` accepts).
  "stop.min_improvement": _F(V.NONNEG, resume=V.MAY_CHANGE),  # 0: off
  "stop.window": _F(V.Rule("fraction"), resume=V.MAY_CHANGE),
  "stop.min_steps": _F(V.count(0), resume=V.MAY_CHANGE),
}


def stopping_rule(config) -> stopping.Rule:
  """The plateau rule of `config.stop` (off when the config has no such section: a workdir
  written before it existed).

  Raises:
    ConfigError: a value out of range (min_improvement < 0, window outside (0, 1), ...).
  """
  try:
    return stopping.rule_from_config(config.get("stop"))
  except ValueError as e:
    raise ConfigError(str(e)) from None


def check_config(config) -> None:
  """The frame's cross-field checks: a usable stopping rule, checked at evaluations.

  Raises:
    ConfigError: as above.
  """
  rule = stopping_rule(config)
  if rule.active and config.eval_every_steps <= 0:
    raise ConfigError(
      f"--config.stop.min_improvement={rule.min_improvement:g}: the plateau rule is checked at "
      "each evaluation; set --config.eval_every_steps > 0"
    )


def steps_per_dispatch(config) -> int:
  """K of the config (1 for a config written before the field existed)."""
  return int(config.get("steps_per_dispatch", 1) or 1)


def topology(*, processes: int, devices: int, scenes_per_device: int) -> dict[str, int]:
  """What a run's steps depend on besides its config: {"processes", "devices", "global_batch"}
  (scenes per step over all devices of all processes), the `Frame`'s `topology`."""
  return {
    "processes": int(processes),
    "devices": int(devices),
    "global_batch": int(devices) * int(scenes_per_device),
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


def _write_json(path: str, record: Mapping[str, Any]) -> None:
  """Writes `record` atomically: a reader sees the old file or the whole new one."""
  writers.write_text_atomic(path, json.dumps(record, indent=1))


class Frame:
  """A run's hold on its workdir (see the module docstring).

  Attributes:
    workdir, config: as given.
    lead: whether this process writes (process 0).
    record: what this start records in record.json (None: nothing recorded or checked).
    changes: {field: (old, new)} between the workdir's stored config and this one.
    restart: whether this start begins again from step 0 (a `restart` stage's FIXED change).
    writer: the metric writer (after `begin`; None before).
    origin: how the state began (`restored_from`), after `restore_or_init`.
    extra: the restored checkpoint's JSON extra ({} on a fresh start).
  """

  def __init__(
    self,
    workdir: str,
    config: Any,
    *,
    schema: V.Schema,
    record: Mapping[str, Any] | None = None,
    lead: bool = True,
    log: Callable[[str], None] = print,
    topology: Mapping[str, int] | None = None,
    restart: bool = False,
    outputs: Callable[[str], None] | None = None,
  ):
    """Sets the frame up (nothing is read or written before `__enter__`).

    Args:
      workdir: the run's directory.
      config: the requested config.
      schema: the stage's declarations (`validate.Field`s): what may change on resume.
      record: what decides the run's data and pose system (record.json), or None; may also be
        given later, before `begin` (`check_record`).
      lead: whether this process writes (process 0).
      log: progress printer.
      topology: what the steps depend on besides the config (`topology`), recorded per
        start and checked at resume; None: nothing.
      restart: start over (from step 0) on an allowed change of a FIXED field or of the record,
        instead of refusing it (see the module docstring).
      outputs: removes the stage's outputs from the workdir (called by `begin` when the run
        starts over).
    """
    self.workdir, self.config, self.lead, self.log = workdir, config, lead, log
    self.schema = schema
    self.record = None if record is None else dict(record)
    self.topology = None if topology is None else dict(topology)
    self._restart_policy, self._outputs = restart, outputs
    self.restart = False
    self.changes: dict[str, Any] = {}
    self.writer: Any = None
    self.origin = restored_from(None)
    self.extra: dict[str, Any] = {}
    self._lock: workdir_lib.WorkdirLock | None = None
    self._ckpt: ckpt_lib.Checkpointer | None = None
    self._existed = os.path.isdir(workdir)
    self._held = False  # this start took the workdir's lock (what it may undo)
    self._stored: dict[str, Any] | None = None
    self._resuming = False

  # -- entry and exit ------------------------------------------------------------------------

  def __enter__(self) -> Frame:
    """Checks the workdir and the config against it, and takes its lock.

    Raises:
      ConfigError: the config differs from the workdir's in a field that may not change, or
        the data or pose system differ from its record.json (`workdir.check_record`).
      WorkdirError: the workdir cannot be written, another process is writing it, or it holds
        checkpoints without a config.json.
    """
    workdir_lib.check_workdir(self.workdir)
    try:
      self._enter()
    except BaseException:
      self._abandon()
      raise
    return self

  def _enter(self) -> None:
    self._stored = stored = workdir_lib.read_stored_config(self.workdir)
    self._resuming = resuming = session_lib.has_checkpoints(self.workdir)
    if resuming and stored is None:
      raise workdir_lib.WorkdirError(
        f"cannot resume in {self.workdir}: it holds checkpoints but no "
        f"{writers.CONFIG_FILE}, so nothing can check this config against the one that trained "
        f"them. Put its {writers.CONFIG_FILE} back, use a new --workdir, or remove "
        f"{os.path.join(self.workdir, ckpt_lib.CHECKPOINT_SUBDIR)} to start over (nothing "
        "changed)"
      )
    if stored is not None and (resuming or self._restart_policy):
      what = "rerun" if self._restart_policy else "resume"
      self.changes = runconfig.check_changes(
        stored,
        self.config,
        schema=self.schema,
        workdir=self.workdir,
        what=what,
        restart=self._restart_policy,
      )
      if self._restart_policy and runconfig.fixed_changes(stored, self.config, schema=self.schema):
        self.restart = True
    try:  # a metrics.jsonl that cannot be read back is refused before anything is written
      writers.read_metrics(self.workdir)
    except writers.MetricsFileError as e:
      raise workdir_lib.WorkdirError(str(e)) from None
    if self.record is not None:
      self.check_record(self.record)
    if resuming and self.topology is not None and not self.restart:
      # another device count changes the global batch: refused unless allowed
      allowed = workdir_lib.GLOBAL_BATCH in runconfig.parse_allow_changes(
        self.config.get("allow_changes", "")
      )
      self.changes.update(workdir_lib.check_topology(self.workdir, self.topology, allowed=allowed))
    if self.lead:
      self._lock = workdir_lib.WorkdirLock(self.workdir)
      self._lock.acquire()
      self._held = True

  def check_record(self, record: Mapping[str, Any]) -> None:
    """Checks (and keeps, for `begin`) what decides this start's data and pose system against
    the workdir's record.json; call before `begin`.

    Raises:
      ConfigError: it differs from the record of the workdir's checkpoints (a stage that starts
        over records the difference and starts over instead).
    """
    self.record = dict(record)
    if self._stored is None or not (self._resuming or self._restart_policy):
      return
    if self._restart_policy:
      old = workdir_lib.read_record(self.workdir)
      if old is not None:  # a changed record is recorded, and the run starts over
        refused, accepted = workdir_lib.record_differences(old, self.record)
        self.changes.update({f"record.{k}": v for k, v in {**refused, **accepted}.items()})
        self.restart = self.restart or bool(refused)
      return
    record_changes = workdir_lib.check_record(self.workdir, self.record)
    if record_changes is None and self.lead:
      self.log(
        f"warning: {self.workdir} has no {workdir_lib.RECORD_FILE} (written by a camrep "
        "that kept none): its data and pose system cannot be checked against this start's; "
        f"resuming, and recording them in {workdir_lib.RECORD_FILE} from now on"
      )
    elif record_changes:
      self.changes.update(record_changes)

  def __exit__(self, exc_type, exc, tb) -> None:
    """Closes the checkpointer and the writer and releases the lock, whatever happened; records
    a non-finite stop; undoes a start that failed before `begin`."""
    errors: list[BaseException] = []
    if exc_type is not None and issubclass(exc_type, FloatingPointError):
      self._record_non_finite(exc)
    for close in (self._close_checkpointer, self._close_writer):
      try:
        close()
      except Exception as e:  # a full disk: the lock must still go
        errors.append(e)
    if self._lock is not None:
      self._lock.release()
    if exc_type is not None and self.writer is None:
      self._abandon()
    if errors and exc_type is None:
      raise errors[0]

  def _close_checkpointer(self) -> None:
    if self._ckpt is not None:
      ckpt, self._ckpt = self._ckpt, None
      ckpt.close()

  def _close_writer(self) -> None:
    if self.writer is not None:
      self.writer.close()

  def _record_non_finite(self, exc: BaseException) -> None:
    """final_metrics.json says the run stopped on non-finite values (what a regression that
    would read its pose system checks)."""
    if not self.lead or self.writer is None:
      return
    try:
      final = session_lib.read_final(self.workdir) or {}
      record = {**final, "complete": False, "stopped": "non-finite", "reason": str(exc)}
      _write_json(os.path.join(self.workdir, session_lib.FINAL_FILE), record)
    except OSError:
      pass  # the error itself says what happened

  def _abandon(self) -> None:
    """Undoes a start that failed before `begin`: an empty checkpoints/ directory (only when this
    start held the lock: a start refused by another run's lock touches nothing of that run), and
    the workdir itself when this start created it and it is empty."""
    dirs = [os.path.join(self.workdir, ckpt_lib.CHECKPOINT_SUBDIR)] if self._held else []
    for d in dirs + ([] if self._existed else [self.workdir]):
      try:
        os.rmdir(d)  # only when empty
      except OSError:
        pass

  # -- checkpoints ---------------------------------------------------------------------------

  @property
  def checkpointer(self) -> ckpt_lib.Checkpointer:
    """The workdir's `Checkpointer` (opened on first use)."""
    if self._ckpt is None:
      self._ckpt = ckpt_lib.Checkpointer(
        self.workdir, max_to_keep=int(self.config.get("max_to_keep", 3))
      )
    return self._ckpt

  def latest_step(self) -> int | None:
    """The latest checkpoint's step (None: none, or the run starts over)."""
    if self.restart or not self._resuming:
      return None
    return self.checkpointer.latest_step()

  def already_complete(self, rule: stopping.Rule | None = None) -> dict[str, float] | None:
    """final_metrics.json's scalars when the workdir holds this run complete (nothing is
    written): at `total_steps`, or stopped early at its latest checkpoint by the same plateau
    `rule`. None when there is training (or the final record) left to do.

    Raises:
      ConfigError: `total_steps` is below the latest checkpoint's step.
    """
    total = self.config.total_steps
    latest = self.latest_step()
    if latest is not None and latest > total:
      raise ConfigError(
        f"total_steps={total} is below the step {latest} of the latest checkpoint in "
        f"{self.workdir}: the run is already past it; raise total_steps or use another "
        "--workdir (nothing changed)"
      )
    if latest is None or not session_lib.is_complete(self.workdir, latest):
      return None
    final = session_lib.read_final(self.workdir)
    if latest == total:
      self.log(f"{self.workdir} is complete at step {total} (final_metrics.json); nothing to do")
    elif stopping.stopped_early_by(final, rule):
      self.log(
        f"{self.workdir} is complete at step {latest}, stopped by the plateau rule "
        f"({final['stopping']['reason']}); nothing to do"
      )
    else:
      return None
    return {k: v for k, v in final.items() if "/" in k}

  def restore_or_init(
    self,
    init: Callable[[], Any],
    *,
    saved: Callable[[Any], Any],
    restored: Callable[[Any], Any],
  ) -> tuple[Any, int]:
    """(state, step) of the latest readable checkpoint, or (init(), 0).

    Args:
      init: the fresh state (also the template a checkpoint is restored into).
      saved: state -> the pytree a checkpoint holds (host arrays).
      restored: that pytree -> state.

    Raises:
      CheckpointError: checkpoints exist but none is readable or matches the template.
    """
    if self.restart:  # the old checkpoints go in `begin`
      return init(), 0
    checkpointer = self.checkpointer  # opened now: an unwritable directory fails before training
    if not self._resuming:
      return init(), 0
    state_d, extra, step = checkpointer.restore_or_init(lambda: saved(init()))
    if step is None:
      return restored(state_d), 0
    self.extra = dict(extra)
    self.origin = restored_from(self.checkpointer.restored)
    self.log(f"resumed from step {step} in {self.workdir}")
    return restored(state_d), int(step)

  def save(self, step: int, state_d: Any, extra: Mapping[str, Any] | None = None) -> None:
    """Saves checkpoint `step` (collective: every process calls it)."""
    self.checkpointer.save(step, state_d, extra={"step": int(step), **(extra or {})}, force=True)

  # -- records -------------------------------------------------------------------------------

  def begin(self, start: int) -> None:
    """The first writes of an accepted start (see the module docstring).

    Raises:
      WorkdirError: metrics.jsonl holds a line that cannot be read back (`writers`).
    """
    if self.restart:
      if self.lead:
        self._start_over()
      self.checkpointer  # noqa: B018 - opened again: an unwritable directory fails now
    elif start == 0 and self.lead and self._outputs is not None:
      self._outputs(self.workdir)  # a stale output would mark this unfinished run as done
    if not self.lead:
      self.writer = writers.NullWriter()
      return
    final = session_lib.read_final(self.workdir)
    if final is not None and final.get("complete") is not False:
      _write_json(os.path.join(self.workdir, session_lib.FINAL_FILE), {**final, "complete": False})
    self.writer = writers.MetricWriter(self.workdir)
    try:
      self.writer.truncate_after(start)
    except writers.MetricsFileError as e:
      raise workdir_lib.WorkdirError(str(e)) from None
    self.writer.write_config(self.config)
    if self.record is not None:
      workdir_lib.write_record(self.workdir, self.record)
    if start > 0:
      what = "resume"
    else:
      what = "rerun" if self._restart_policy and self._stored is not None else "start"
    workdir_lib.append_history(self.workdir, start, self.changes, what=what, topology=self.topology)
    if start > 0 and self.changes:
      self.writer.write_scalars(start, {"resume/config_changes": len(self.changes)})
      changed = ", ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in self.changes.items())
      self.log(f"config changed at step {start}: {changed}")

  def _start_over(self) -> None:
    """Removes what the run being replaced wrote: its checkpoints, final_metrics.json and the
    stage's outputs (metrics.jsonl is truncated by `begin`)."""
    self._close_checkpointer()
    shutil.rmtree(os.path.join(self.workdir, ckpt_lib.CHECKPOINT_SUBDIR), ignore_errors=True)
    final = os.path.join(self.workdir, session_lib.FINAL_FILE)
    if os.path.exists(final):
      os.remove(final)
    if self._outputs is not None:
      self._outputs(self.workdir)
    self._resuming = False

  def recorded_curve(
    self, score: Callable[[Mapping[str, Any]], float | None], start: int
  ) -> list[tuple[int, float]]:
    """The plateau rule's curve up to `start` from metrics.jsonl: (step, score(row)) of every
    logged row the stage scores (a resumed run goes on with the curve it had)."""
    curve = []
    for row in writers.read_metrics(self.workdir):
      s = score(row)
      if s is not None and int(row["step"]) <= start:
        curve.append((int(row["step"]), s))
    return curve

  def wait(self) -> None:
    """Blocks until the checkpoint being saved is on disk."""
    if self._ckpt is not None:
      self._ckpt.wait_until_finished()

  def finish(self, step: int, last: Mapping[str, Any]) -> None:
    """final_metrics.json: the last logged scalars (and whatever else `last` holds), the config
    changes of the run's history, the machine that finished it (`workdir.machine`), and
    {"complete": true, "step": step}. Call once what it describes is on disk (the last
    checkpoint saved, the metrics flushed, the stage's outputs written)."""
    if not self.lead:
      return
    self.wait()
    self.writer.flush()
    history = workdir_lib.read_history(self.workdir)
    changes = [{"step": h["step"], "changes": h["changes"]} for h in history if h["changes"]]
    record = {"step": int(step), **last, "config_changes": changes, "complete": True}
    record["machine"] = workdir_lib.machine()
    _write_json(os.path.join(self.workdir, session_lib.FINAL_FILE), record)


# ---------------------------------------------------------------------------------------------
# The fit loop.


class Stage(abc.ABC):
  """What a training stage gives the fit loop; each stage (view synthesis, regression)
  implements it. State and metrics are the stage's own pytrees; the loop only moves them.

  Attributes:
    eval_at_end: whether the periodic evaluation also runs at `total_steps` (regression scores
      every split there on its own instead).
    log_rate: whether the log rows carry train/steps_per_sec.
    unlogged: keys of `rows` kept out of metrics.jsonl.
  """

  eval_at_end: bool = True
  log_rate: bool = True
  unlogged: tuple[str, ...] = ()

  @abc.abstractmethod
  def dispatch(self, n: int) -> Callable[[Any, Any], tuple[Any, Any, Any]]:
    """The step over `n` steps: fn(state, chunk) -> (state, metrics, ok), where `chunk` is what
    `chunks` yields for a span of `n` steps, `metrics` the steps' metrics (stacked over the `n`
    steps when n > 1: `lax.scan`), and `ok` the finite flags reduced on the device (read at log
    and checkpoint steps only). Called once per distinct `n`; the loop reports its compile."""

  @abc.abstractmethod
  def chunks(self, spans: Iterator[tuple[int, int]]) -> Iterator[Any]:
    """The training batches of each span (first step, n) in order, laid out for `dispatch(n)`
    (n > 1: stacked on a steps axis). Closing the iterator stops any worker."""

  @abc.abstractmethod
  def rows(self, metrics: Any, n: int) -> list[dict[str, float]]:
    """The host scalars of each of the `n` steps of a dispatch's metrics, with "train/finite"
    (1.0 where the step's values were finite)."""

  @abc.abstractmethod
  def saved(self, state: Any) -> Any:
    """The state as the pytree a checkpoint holds (host arrays)."""

  def evaluate(self, state: Any, step: int) -> dict[str, float]:
    """Evaluates at `step` (lead process only), writes its metrics; returns its scalars."""
    del state, step
    return {}

  def score(self, row: Mapping[str, Any]) -> float | None:
    """The plateau score (lower is better) of an evaluation's scalars or a logged metrics row;
    None when the row holds no evaluation."""
    del row
    return None

  def extra(self, step: int) -> dict[str, Any]:
    """JSON values saved with checkpoint `step` beside {"step": step}."""
    del step
    return {}


def spans(
  start: int, total: int, k: int, boundaries: Iterable[int] = ()
) -> Iterator[tuple[int, int]]:
  """The dispatches of steps start+1 .. total as (first step, number of steps): each ends at the
  next multiple of `k`, of each positive period in `boundaries` (evaluations, checkpoints), or
  at `total`, whichever comes first; a pure function of the step grid, so a run restarted at
  any dispatch end takes the same dispatches as one left alone."""
  periods = [int(b) for b in boundaries if b and b > 0] + [max(int(k), 1)]
  step = int(start)
  while step < total:
    end = min([total] + [(step // p + 1) * p for p in periods])
    yield step + 1, end - step
    step = end


def agree(rule: stopping.Rule, curve, lead: bool, *, check_now: bool = True) -> tuple[bool, str]:
  """The lead's `stopping.check` of the curve (only the lead evaluates), shared with every
  process (saves are collective: all must stop at the same step). Call on every process."""
  stop, why = stopping.check(rule, curve) if lead and check_now else (False, "")
  if jax.process_count() > 1 and rule.active:
    from jax.experimental import multihost_utils

    flags = multihost_utils.process_allgather(np.asarray(stop, np.int32))
    stop = bool(np.any(flags))
  return stop, why


@dataclasses.dataclass
class FitResult:
  """Where `fit` left the run.

  Attributes:
    state: the stage's state after the last step.
    step: the last step trained (the start when none was).
    last: the last logged train scalars and evaluation scalars.
    curve: the plateau rule's curve [(step, score)].
    ended: the plateau rule stopped the run.
    reason: why the run ended ("reached total_steps" or the rule's reason).
    stopped: a signal stopped the run (a checkpoint was saved; it is not complete).
  """

  state: Any
  step: int
  last: dict[str, float]
  curve: list[tuple[int, float]]
  ended: bool
  reason: str
  stopped: bool

  @property
  def complete(self) -> bool:
    """Whether the run is complete (at total_steps or at its plateau)."""
    return self.ended or not self.stopped

  def stopping_record(self, rule: stopping.Rule, total: int, *, score: str | None = None) -> dict:
    """`stopping.stopping_record` of this run."""
    return stopping.stopping_record(
      rule, self.curve, self.step, total, self.ended, self.reason, score=score
    )


def _signal_name(handler) -> str:
  return signal.Signals(handler.signum).name if handler.signum else "a stop signal"


def _is_finite(ok) -> bool:
  return bool(np.all(np.asarray(ok) >= 1))


def fit(
  frame: Frame,
  stage: Stage,
  state: Any,
  start: int,
  *,
  rule: stopping.Rule,
  progress_every: float = 30.0,
) -> FitResult:
  """Trains `stage` from step `start` on (see the module docstring).

  Args:
    frame: the entered frame, after `begin`.
    stage: the stage.
    state: the stage's state at `start` (placed for its step).
    start: the step the run starts or resumes from.
    rule: the plateau stopping rule.
    progress_every: seconds between status lines.

  Returns:
    A `FitResult`.

  Raises:
    FloatingPointError: a step's values were not finite (its update skipped; the last
      checkpoint kept).
  """
  config, lead, log, workdir = frame.config, frame.lead, frame.log, frame.workdir
  total = int(config.total_steps)
  log_every, eval_every = int(config.log_every_steps), int(config.eval_every_steps)
  ckpt_every, k = int(config.ckpt_every_steps), steps_per_dispatch(config)
  # The curve of every evaluation's score (the rule reads it when active; the records keep it).
  curve = frame.recorded_curve(stage.score, start) if lead else []
  last: dict[str, float] = {}
  progress = progress_lib.Progress(total, start_step=start, every_seconds=progress_every)
  # A resumed run whose curve ends at its start (another rule now): the rule decides at once.
  at_start = rule.active and bool(curve) and curve[-1][0] == start
  ended, reason = agree(rule, curve, lead, check_now=at_start)
  if ended and lead:
    log(f"stopping at step {start}: {reason}")
  step, stopped, pending = start, False, []
  compiled: dict[int, Callable] = {}
  todo = spans(start, total, k, (eval_every, ckpt_every)) if not ended else iter(())
  plan, ahead = itertools.tee(todo)  # the batches are read ahead of the loop
  with preemption.install_signal_handlers() as signals:
    batches = stage.chunks(ahead)
    try:
      for (first, n), chunk in zip(plan, batches, strict=False):
        fn = compiled.get(n)
        if fn is None:
          if lead:
            log(f"compiling the train step ({n} step{'s' if n > 1 else ''} per dispatch) ...")
          t0 = time.perf_counter()
          fn = compiled[n] = stage.dispatch(n)
          state, metrics, ok = fn(state, chunk)
          if lead:
            log(f"compiled the train step in {time.perf_counter() - t0:.1f} s")
        else:
          state, metrics, ok = fn(state, chunk)
        step = first + n - 1
        pending.append((first, n, metrics, ok))
        stopped = preemption.stop_requested(signals)
        save = progress_lib.itstime(step, ckpt_every, total) or stopped
        logged = [s for s in range(first, step + 1) if progress_lib.itstime(s, log_every, total)]
        if logged or save:  # the host reads the steps' flags only here: the device runs ahead
          _raise_if_not_finite(frame, stage, pending)
          pending = []
        status = progress.update(step)
        if logged:
          rows = stage.rows(metrics, n)
          for s in logged:
            row = {key: v for key, v in rows[s - first].items() if key not in stage.unlogged}
            if stage.log_rate and np.isfinite(progress.steps_per_second):
              row["train/steps_per_sec"] = progress.steps_per_second
            frame.writer.write_scalars(s, row)
            last.update(row)
        if status and lead:
          loss = stage.rows(metrics, n)[-1].get("train/loss", float("nan"))
          log(f"{status} loss={loss:.4f}")
        evaluated = progress_lib.itstime(step, eval_every, total) and (
          stage.eval_at_end or step < total
        )
        if lead and evaluated:
          scalars = stage.evaluate(state, step)
          last.update(scalars)
          s = stage.score(scalars)
          if s is not None:
            curve.append((step, s))
        if evaluated and rule.active:
          ended, reason = agree(rule, curve, lead)
          if ended:
            _raise_if_not_finite(frame, stage, pending)
            pending, save = [], True
            if lead:
              log(f"stopping at step {step}: {reason}")
        if save:
          frame.save(step, stage.saved(state), stage.extra(step))
        if ended:
          break
        if stopped:  # every process says it (each was stopped, by its signal or another's)
          log(
            f"stopping at step {step} on {_signal_name(signals)}; checkpoint saved in "
            f"{workdir}: run the same command to resume"
          )
          break
    finally:
      if hasattr(batches, "close"):
        batches.close()
  if not ended:
    reason = "reached total_steps"
  return FitResult(state, step, last, curve, ended, reason, stopped and not ended)


def _raise_if_not_finite(frame: Frame, stage: Stage, pending) -> None:
  """Raises FloatingPointError naming the first step of the pending dispatches whose values
  were not finite (that step skipped its update), after logging its values."""
  for first, n, metrics, ok in pending:
    if _is_finite(ok):
      continue
    for i, row in enumerate(stage.rows(metrics, n)):
      if row.get("train/finite", 1.0) >= 1:
        continue
      step = first + i
      bad = [k for k, v in row.items() if not np.isfinite(v)]
      frame.writer.write_scalars(step, row)
      raise FloatingPointError(
        f"non-finite training values at step {step} ({', '.join(bad) or 'gradients'}); "
        f"updates of this step were skipped; {frame.origin}; the last checkpoint is kept in "
        f"{frame.workdir} and a resume verifies its checksums before using it"
      )

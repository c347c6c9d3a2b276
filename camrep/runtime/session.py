"""A training run's hold on its workdir, as one context manager: the checks and the lock on
entry, the start's records (config.json, config history, metrics truncated to the restored step)
and the metric writer once training begins, `final_metrics.json` when it completes, and on exit
the writer closed and the lock released (a start that failed before `begin` leaves the workdir as
it found it).

  with Session(workdir, config, resumable=runconfig.SYNTHESIS_RESUMABLE) as session:
    ...                             # build data and model, restore or init the state
    session.begin(start)            # first writes; session.writer is open from here
    ...                             # train, session.writer.write_scalars(...)
    session.finish(step, last)      # final_metrics.json, {"complete": true, "step": step, ...}

final_metrics.json is written atomically, and `begin` marks an existing one `"complete": false`
before an extended run writes anything else, so a killed run never leaves a record that says it
completed; `read_final` / `is_complete` read it back.

The checks on entry, when the workdir holds checkpoints: a config.json must be there (a workdir
without one is refused, never resumed unchecked); the config against it
(`runconfig.check_changes`); the caller's `record` (what decides the data and the pose system,
library defaults included) against the workdir's record.json (`workdir.check_record`; none
there: one warning, and `begin` writes it); the topology (`workdir.check_topology`).

Several processes: every process enters the session with the same workdir; only the lead
(process 0) takes the lock and writes (the others get a `writers.NullWriter`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import jax

from camrep.runtime import runconfig, writers
from camrep.runtime import workdir as workdir_lib
from camrep.runtime.checkpoint import CHECKPOINT_SUBDIR

FINAL_FILE = "final_metrics.json"


def has_checkpoints(workdir: str) -> bool:
  d = os.path.join(workdir, CHECKPOINT_SUBDIR)
  return os.path.isdir(d) and any(name.isdigit() for name in os.listdir(d))


def read_final(workdir: str) -> dict[str, Any] | None:
  """workdir/final_metrics.json, or None when there is none or it cannot be read."""
  try:
    with open(os.path.join(workdir, FINAL_FILE), encoding="utf-8") as f:
      final = json.load(f)
  except (OSError, json.JSONDecodeError):
    return None
  return final if isinstance(final, dict) else None


def is_complete(workdir: str, total_steps: int | None = None) -> bool:
  """Whether final_metrics.json records a completed run (at `total_steps`, when given)."""
  final = read_final(workdir)
  if not final or final.get("complete") is not True:
    return False
  return total_steps is None or final.get("step") == int(total_steps)


def last_logged(workdir: str) -> dict[str, float]:
  """The latest value of every train/ and eval/ scalar in metrics.jsonl."""
  last = {}
  for row in writers.read_metrics(workdir):
    last.update({k: v for k, v in row.items() if k.startswith(("train/", "eval/"))})
  return last


def _write_json(path: str, record: Mapping[str, Any]) -> None:
  """Writes `record` atomically: a reader sees the old file or the whole new one."""
  writers.write_text_atomic(path, json.dumps(record, indent=1))


class Session:
  """The workdir of one start (see the module docstring).

  Attributes:
    workdir, config: as given.
    lead: whether this process writes (process 0).
    record: what this start records in record.json (None: nothing recorded or checked).
    changes: {field: (old, new)} between the workdir's stored config and this one.
    writer: the metric writer (after `begin`; None before).
  """

  def __init__(
    self,
    workdir: str,
    config: Any,
    *,
    resumable: Iterable[str] | None,
    record: Mapping[str, Any] | None = None,
    lead: bool = True,
    log: Callable[[str], None] = print,
  ):
    self.workdir, self.config, self.lead, self.log = workdir, config, lead, log
    self.record = None if record is None else dict(record)
    self._resumable = resumable
    self.changes: dict[str, tuple[Any, Any]] = {}
    self.writer: Any = None
    self._lock: workdir_lib.WorkdirLock | None = None
    self._existed = os.path.isdir(workdir)
    # What the steps depend on besides the config (recorded per start, checked at resume).
    self.topology = workdir_lib.topology(
      processes=jax.process_count(),
      devices=jax.device_count(),
      scenes_per_device=config.data.scenes_per_device,
    )

  def __enter__(self) -> Session:
    """Checks the workdir (writable; its stored config and record against this one's) and
    takes its lock.

    Raises:
      ConfigError: the config differs from the workdir's in a field that may not change, or
        the data or pose system differ from its record.json (`workdir.check_record`).
      WorkdirError: the workdir cannot be written, another process is writing it, or it holds
        checkpoints without a config.json.
    """
    workdir_lib.check_workdir(self.workdir)
    stored = workdir_lib.read_stored_config(self.workdir)
    resuming = has_checkpoints(self.workdir)
    if resuming and stored is None:
      raise workdir_lib.WorkdirError(
        f"cannot resume in {self.workdir}: it holds checkpoints but no "
        f"{writers.CONFIG_FILE}, so nothing can check this config against the one that trained "
        f"them. Put its {writers.CONFIG_FILE} back, use a new --workdir, or remove "
        f"{os.path.join(self.workdir, CHECKPOINT_SUBDIR)} to start over (nothing changed)"
      )
    if resuming:
      self.changes = runconfig.check_changes(
        stored, self.config, resumable=self._resumable, workdir=self.workdir
      )
    if resuming and self.record is not None:  # library defaults, the data itself
      record_changes = workdir_lib.check_record(self.workdir, self.record)
      if record_changes is None and self.lead:
        self.log(
          f"warning: {self.workdir} has no {workdir_lib.RECORD_FILE} (written by a camrep "
          "that kept none): its data and pose system cannot be checked against this start's; "
          f"resuming, and recording them in {workdir_lib.RECORD_FILE} from now on"
        )
      elif record_changes:
        self.changes.update(record_changes)
    if resuming:  # another device count changes the global batch: refused
      allowed = workdir_lib.GLOBAL_BATCH in runconfig.parse_allow_changes(
        self.config.get("allow_changes", "")
      )
      self.changes.update(workdir_lib.check_topology(self.workdir, self.topology, allowed=allowed))
    if self.lead:
      self._lock = workdir_lib.WorkdirLock(self.workdir)
      self._lock.acquire()
    return self

  def begin(self, start: int) -> None:
    """The first writes of an accepted start: final_metrics.json (if any) marked incomplete,
    metrics logged after `start` by an interrupted run dropped, config.json made this config,
    and config_history.jsonl told of the start (and any config change, with its step)."""
    if not self.lead:
      self.writer = writers.NullWriter()
      return
    final = read_final(self.workdir)
    if final is not None and final.get("complete") is not False:
      _write_json(os.path.join(self.workdir, FINAL_FILE), {**final, "complete": False})
    self.writer = writers.MetricWriter(self.workdir)
    self.writer.truncate_after(start)
    self.writer.write_config(self.config)
    if self.record is not None:
      workdir_lib.write_record(self.workdir, self.record)
    workdir_lib.append_history(
      self.workdir,
      start,
      self.changes,
      what="resume" if start > 0 else "start",
      topology=self.topology,
    )
    if start > 0 and self.changes:
      self.writer.write_scalars(start, {"resume/config_changes": len(self.changes)})
      changed = ", ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in self.changes.items())
      self.log(f"config changed at step {start}: {changed}")

  def finish(self, step: int, last: Mapping[str, float]) -> None:
    """final_metrics.json: the last logged scalars, the config changes of the run's history, the
    machine that finished it (`workdir.machine`), and {"complete": true, "step": step}. Call
    once what it describes is on disk (the last checkpoint saved, the metrics flushed)."""
    if not self.lead:
      return
    self.writer.flush()
    history = workdir_lib.read_history(self.workdir)
    changes = [{"step": h["step"], "changes": h["changes"]} for h in history if h["changes"]]
    record = {"step": int(step), **last, "config_changes": changes, "complete": True}
    record["machine"] = workdir_lib.machine()
    _write_json(os.path.join(self.workdir, FINAL_FILE), record)

  def __exit__(self, exc_type, exc, tb) -> None:
    if self.writer is not None:
      self.writer.close()
    if self._lock is not None:
      self._lock.release()
    if exc_type is not None and self.writer is None:
      self._abandon()

  def _abandon(self) -> None:
    """Undoes a start that failed before `begin`: an empty checkpoints/ directory, and the
    workdir itself when this start created it and it is empty."""
    dirs = [os.path.join(self.workdir, CHECKPOINT_SUBDIR)]
    for d in dirs + ([] if self._existed else [self.workdir]):
      try:
        os.rmdir(d)  # only when empty
      except OSError:
        pass

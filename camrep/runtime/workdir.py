"""The workdir of a run: checked before any work starts, held by one writer at a time, and its
config and config history read back.

Files this module owns in a workdir:

  .camrep.lock          {"pid", "host", "started", "argv"} of the process writing the workdir;
                        removed when it ends. A lock whose process is gone (same host, PID not
                        running) is stale and is taken over with a warning.
  config_history.jsonl  one line per start: {"step", "time", "host", "pid", "changes":
                        {field: [old, new]}}; `changes` is empty for a fresh start.
  record.json           what decides the run's data and model beyond config.json (which stays
                        the user's config): written at each start by the caller's record
                        (view synthesis: `synthesis.components.run_record`, the family's
                        resolved parameters, the pose spec, the data fingerprint), checked at
                        resume by `check_record`. A workdir written before camrep kept one
                        resumes unchecked, with a warning, and gains it.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import socket
import sys
import tempfile
import time
import warnings
from collections.abc import Mapping
from typing import Any

import ml_collections

from camrep.runtime import writers

LOCK_FILE = ".camrep.lock"
# An unreadable lock older than this is taken over (a run that died while writing it).
UNREADABLE_LOCK_GRACE_S = 10.0
HISTORY_FILE = "config_history.jsonl"


class WorkdirError(RuntimeError):
  """The workdir cannot be created or written to, or another process is writing it."""


class StaleLockWarning(UserWarning):
  """A workdir lock left by a process that no longer runs was taken over."""


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


def read_config(workdir: str) -> ml_collections.ConfigDict:
  """workdir/config.json (written by `writers.MetricWriter.write_config`) as a ConfigDict.

  Raises:
    FileNotFoundError: no such workdir, or it has no config.json.
  """
  if not os.path.isdir(workdir):
    raise FileNotFoundError(f"workdir {workdir!r} does not exist")
  path = os.path.join(workdir, writers.CONFIG_FILE)
  if not os.path.exists(path):
    raise FileNotFoundError(
      f"{path} not found: {workdir!r} is not a camrep training workdir "
      "(`python -m camrep.main --config=... --workdir=DIR` writes it)"
    )
  with open(path, encoding="utf-8") as f:
    return ml_collections.ConfigDict(json.load(f))


def read_stored_config(workdir: str) -> dict[str, Any] | None:
  """workdir/config.json as plain JSON values, or None when the workdir holds none.

  Raises:
    WorkdirError: the file exists but is not JSON.
  """
  path = os.path.join(workdir, writers.CONFIG_FILE)
  if not os.path.exists(path):
    return None
  try:
    with open(path, encoding="utf-8") as f:
      return json.load(f)
  except (OSError, json.JSONDecodeError) as e:
    raise WorkdirError(f"{path} cannot be read as JSON: {e}") from e


def _now() -> str:
  return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _pid_running(pid: int) -> bool:
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:  # exists, owned by someone else
    return True
  return True


class WorkdirLock:
  """One writer per workdir: `.camrep.lock`, created atomically, removed by `release`.

  Usage:
    lock = WorkdirLock(workdir)
    lock.acquire()      # WorkdirError if a live process holds it
    try: ... finally: lock.release()
  """

  def __init__(self, workdir: str):
    self.workdir = workdir
    self.path = os.path.join(workdir, LOCK_FILE)
    self.held = False

  def holder(self) -> dict[str, Any] | None:
    """The lock's content, or None when there is no lock file ({} when it is unreadable)."""
    try:
      with open(self.path, encoding="utf-8") as f:
        return json.load(f)
    except FileNotFoundError:
      return None
    except (OSError, json.JSONDecodeError):
      return {}

  def live_holder(self) -> dict[str, Any] | None:
    """The lock's content when a live process holds it (or one on another host, which cannot be
    checked), else None (no lock, or a stale one)."""
    h = self.holder()
    if not h:
      return None
    host, pid = h.get("host"), h.get("pid")
    if host == socket.gethostname() and isinstance(pid, int) and not _pid_running(pid):
      return None
    return h

  def _create(self) -> bool:
    """Creates the lock with this process's record; False when a lock exists.

    Raises:
      WorkdirError: the lock cannot be written (a full disk, a read-only file system); no empty
        or partial lock is left behind (it would refuse every later start).
    """
    me = {"pid": os.getpid(), "host": socket.gethostname(), "started": _now(), "argv": sys.argv}
    try:
      fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
      return False
    except OSError as e:
      raise WorkdirError(f"cannot create the lock {self.path}: {e.strerror or e}") from e
    try:
      with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(json.dumps(me))
        f.flush()
        os.fsync(f.fileno())
    except OSError as e:
      try:
        os.remove(self.path)
      except OSError:
        pass
      raise WorkdirError(
        f"cannot write the lock {self.path}: {e.strerror or e} (nothing was left behind)"
      ) from e
    return True

  def _abandoned(self) -> bool:
    """Whether an unreadable (empty or cut) lock is old enough to be a dead process's: a live
    one writes its record within microseconds of creating the file."""
    try:
      return time.time() - os.path.getmtime(self.path) > UNREADABLE_LOCK_GRACE_S
    except OSError:
      return False

  def acquire(self, *, wait: float = 0.0, log=None, poll: float = 0.5) -> None:
    """Takes the lock, taking over a stale one (with a `StaleLockWarning`).

    Args:
      wait: seconds to wait for a live holder to let go (0: refuse at once; math.inf: until it
        does), saying once through `log` whom it waits for.
      log: progress printer for the wait (default: stderr).
      poll: seconds between looks while waiting.

    Raises:
      WorkdirError: a live process (or one on another host) holds the lock (after `wait`); the
        message names it.
    """
    deadline, said = time.monotonic() + wait, False
    while True:
      try:
        return self._acquire()
      except WorkdirError:
        if time.monotonic() + poll > deadline:
          raise
        h = self.live_holder()
        if h is None:  # let go, died or not yet written since the attempt: look again
          time.sleep(poll)
          continue
        if not said:
          line = (
            f"waiting for PID {h.get('pid')} on {h.get('host')} (started "
            f"{h.get('started', '?')}) to release {self.workdir} (Ctrl-C to give up)"
          )
          (log or (lambda m: print(m, file=sys.stderr, flush=True)))(line)
          said = True
        time.sleep(poll)

  def _acquire(self) -> None:
    for _ in range(2):
      if self._create():
        self.held = True
        return
      h = self.holder()
      if h is None:  # released between our two looks
        continue
      host, pid = h.get("host"), h.get("pid")
      dead = host == socket.gethostname() and isinstance(pid, int) and not _pid_running(pid)
      if dead or (not h and self._abandoned()):
        msg = (
          f"taking over the stale lock of {self.workdir}: PID {pid} on {host} "
          f"(started {h.get('started', '?')}) no longer runs"
          if h
          else f"taking over the unreadable (empty or cut) lock {self.path} left by a dead run"
        )
        warnings.warn(msg, StaleLockWarning, stacklevel=2)
        print(f"warning: {msg}", file=sys.stderr, flush=True)
        os.remove(self.path)
        continue
      who = f"PID {pid} on {host}, started {h.get('started', '?')}" if h else "an unreadable lock"
      raise WorkdirError(
        f"workdir {self.workdir} is in use by another run ({who}; {self.path}). Wait for it to "
        "finish, or use another --workdir; if that process is gone (another host, a crashed "
        "machine), delete the lock file."
      )
    raise WorkdirError(f"could not take the lock {self.path} (it keeps changing hands)")

  def release(self) -> None:
    """Removes the lock if this object holds it."""
    if self.held:
      self.held = False
      h = self.holder()
      if h and h.get("pid") == os.getpid():
        os.remove(self.path)


def append_history(
  workdir: str,
  step: int,
  changes: Mapping[str, tuple[Any, Any]],
  *,
  what: str = "start",
  topology: Mapping[str, int] | None = None,
) -> None:
  """Appends one line to config_history.jsonl: the step at which `changes` took effect, and the
  `topology` (processes, devices, global batch) the run goes on with."""
  row = {
    "step": int(step),
    "event": what,
    "time": _now(),
    "host": socket.gethostname(),
    "pid": os.getpid(),
    "changes": {k: list(v) for k, v in changes.items()},
  }
  if topology is not None:
    row["topology"] = {k: int(v) for k, v in topology.items()}
  path = os.path.join(workdir, HISTORY_FILE)
  text = json.dumps(row, default=str) + "\n"
  with open(path, "a+b") as f:  # appends whatever the position
    if f.seek(0, os.SEEK_END) > 0:
      f.seek(-1, os.SEEK_END)
      if f.read(1) != b"\n":  # a line cut short by a killed run: end it, do not glue onto it
        text = "\n" + text
    f.write(text.encode("utf-8"))


def read_history(workdir: str) -> list[dict[str, Any]]:
  """config_history.jsonl back (an empty list when there is none), without lines cut short by
  a killed run."""
  path = os.path.join(workdir, HISTORY_FILE)
  if not os.path.exists(path):
    return []
  rows = []
  with open(path, encoding="utf-8") as f:
    for line in f:
      try:
        rows.append(json.loads(line))
      except json.JSONDecodeError:  # blank, or cut short
        continue
  return [r for r in rows if isinstance(r, dict)]


# `allow_changes` name that lets a resume change the global batch (another device count).
GLOBAL_BATCH = "global_batch"


def machine() -> dict[str, Any]:
  """What ran a run, for its records (final_metrics.json, results.json): JAX's backend, the kind
  and count of its devices, the host's CPU model and the jax version. Runs of one table may come
  from several machines (a GPU machine beside the CPU), whose results differ in round-off."""
  import jax  # here: the rest of this module is read by tools that never import JAX

  cpu = platform.processor() or platform.machine()
  try:
    with open("/proc/cpuinfo", encoding="utf-8") as f:
      cpu = next(
        (line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu
      )
  except OSError:
    pass
  devices = jax.devices()
  return {
    "backend": jax.default_backend(),
    "device_kind": devices[0].device_kind,
    "devices": len(devices),
    "cpu": cpu,
    "cpu_count": os.cpu_count(),
    "jax": jax.__version__,
  }


def recorded_topology(workdir: str) -> dict[str, int] | None:
  """The topology of the workdir's latest start (config_history.jsonl), or None when no start
  recorded one (a workdir written before camrep recorded it)."""
  for row in reversed(read_history(workdir)):
    if "topology" in row:
      return row["topology"]
  return None


def check_topology(workdir: str, now: Mapping[str, int], *, allowed: bool) -> dict[str, Any]:
  """Refuses a resume whose global batch differs from the workdir's last start (another number
  of devices or scenes per device) unless `allowed`.

  Returns:
    {"topology": [old, new]} when the topology changed (a change to record), else {}.

  Raises:
    ConfigError: the global batch changed and `allowed` is False; the message says how to
      allow it.
  """
  from camrep.runtime.runconfig import ConfigError

  old = recorded_topology(workdir)
  if old is None or dict(old) == dict(now):
    return {}
  if old.get("global_batch") != now["global_batch"] and not allowed:
    raise ConfigError(
      f"cannot resume in {workdir}: its run took {old.get('global_batch')} scenes per step on "
      f"{old.get('devices')} device(s) in {old.get('processes')} process(es); this start would "
      f"take {now['global_batch']} on {now['devices']} device(s) in {now['processes']} "
      "process(es), which changes every later step. Use the same devices, a new --workdir, or "
      f"--config.allow_changes={GLOBAL_BATCH} to record the change in config_history.jsonl"
    )
  return {"topology": [dict(old), dict(now)]}


# What decides a run's data and model beyond its config.json (library defaults): written at each
# start, checked at resume (`check_record`).
RECORD_FILE = "record.json"
# Record fields that may differ at resume: the record's format version, where a prepared
# dataset lies (a moved copy keeps its fingerprint) and the "world" fingerprint (derived from
# the fields compared one by one).
_RECORD_FREE = ("version", "data.dataset", "data.world")


def read_record(workdir: str) -> dict[str, Any] | None:
  """workdir/record.json, or None when the workdir has none (written before camrep kept one).

  Raises:
    WorkdirError: the file exists but is not a JSON object.
  """
  path = os.path.join(workdir, RECORD_FILE)
  if not os.path.exists(path):
    return None
  try:
    with open(path, encoding="utf-8") as f:
      record = json.load(f)
  except (OSError, json.JSONDecodeError) as e:
    raise WorkdirError(f"{path} cannot be read as JSON: {e}") from e
  if not isinstance(record, dict):
    raise WorkdirError(f"{path} holds no JSON object")
  return record


def write_record(workdir: str, record: Mapping[str, Any]) -> None:
  """Writes workdir/record.json atomically."""
  text = json.dumps(record, indent=1, sort_keys=True, default=str)
  writers.write_text_atomic(os.path.join(workdir, RECORD_FILE), text)


def flatten_record(tree: Any, prefix: str = "") -> dict[str, Any]:
  """{"a": {"b": 1}, "c": [{"d": 2}]} -> {"a.b": 1, "c.0.d": 2} (lists of scalars stay whole)."""
  if isinstance(tree, Mapping) and tree:
    items = tree.items()
  elif isinstance(tree, list | tuple) and tree and all(isinstance(x, Mapping) for x in tree):
    items = ((str(i), x) for i, x in enumerate(tree))
  else:
    return {prefix[:-1]: tree} if prefix else {}
  out = {}
  for k, v in items:
    out.update(flatten_record(v, f"{prefix}{k}."))
  return out


def record_differences(
  old: Mapping[str, Any], new: Mapping[str, Any], *, free: tuple[str, ...] = _RECORD_FREE
) -> tuple[dict[str, tuple[Any, Any]], dict[str, tuple[Any, Any]]]:
  """(refused, accepted) differences {field: (old, new)} between two records.

  Accepted: the `free` fields, and fields the old record lacks (camrep gained them after it was
  written; their defaults keep the old behaviour, as `runconfig.check_changes` treats config
  fields). A procedural "data.fingerprint" is compared through the fields it hashes (named one
  by one, and a gained field does not refuse the resume); a prepared dataset's is compared as is.
  """
  a, b = flatten_record(dict(old)), flatten_record(dict(new))
  procedural = a.get("data.kind") == b.get("data.kind") == "procedural"
  refused, accepted = {}, {}
  for k in sorted(set(a) | set(b)):
    if a.get(k) == b.get(k) or (procedural and k == "data.fingerprint"):
      continue
    if k in free or k not in a:
      accepted[k] = (a.get(k), b.get(k))
    else:
      refused[k] = (a.get(k), b.get(k))
  return refused, accepted


def check_record(
  workdir: str, now: Mapping[str, Any], *, what: str = "resume in"
) -> dict[str, Any] | None:
  """Refuses a resume whose data or pose system differ from the workdir's record.json, where
  config.json may show no difference (a library default changed, a prepared dataset replaced).

  Args:
    workdir: the workdir (its record.json).
    now: the record of this start (`synthesis.components.run_record`).
    what: the message's verb ("resume in", "restore").

  Returns:
    None when the workdir has no record (written before camrep kept one: the caller warns and
    writes it); else {"record.FIELD": [old, new]} of the accepted differences (a moved dataset,
    a field camrep gained), to record in config_history.jsonl.

  Raises:
    ConfigError: a field differs; the first line names the first one (old -> new), the next
      lines every one and the way out.
  """
  from camrep.runtime.runconfig import ConfigError

  old = read_record(workdir)
  if old is None:
    return None
  refused, accepted = record_differences(old, now)
  if refused:
    (field, (a, b)), n = next(iter(refused.items())), len(refused)
    more = f" (and {n - 1} more)" if n > 1 else ""
    lines = [
      f"cannot {what} {workdir}: {field}: {a!r} -> {b!r}{more}: what decides its data or "
      f"pose system differs from its {RECORD_FILE}, though config.json may not show it (a "
      "library default or the data itself changed)"
    ]
    lines += [f"  {k}: {x!r} -> {y!r}" for k, (x, y) in refused.items()]
    if "data.fingerprint" in refused and now.get("data", {}).get("kind") == "prepared":
      lines.append(
        f"the prepared dataset {now['data'].get('dataset')} is not the one this workdir was "
        f"trained on ({old.get('data', {}).get('dataset')}): only a moved copy of the same "
        "dataset may replace it"
      )
    lines.append(
      "resume with the camrep version and data that wrote the workdir, or use a new --workdir"
    )
    raise ConfigError("\n".join(lines))
  return {f"record.{k}": [a, b] for k, (a, b) in accepted.items()}

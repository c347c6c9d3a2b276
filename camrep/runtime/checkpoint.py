"""Checkpointing for the training loop: Orbax `CheckpointManager` plus fault handling.

A checkpoint holds the train state (any pytree of jax/numpy arrays and Python scalars, e.g. a
flax `TrainState` with the parameter groups, the optax states and the step counter) and a small
JSON-able `extra` dict (e.g. `{"data_step": 1200, "rng_seed": 0}`). Each step is one Orbax
composite checkpoint `workdir/checkpoints/<step>/{state,extra}`.

Typical use in the train loop (resume order: latest readable checkpoint in the workdir, else a
fresh `init_fn()`):

  ckpt = Checkpointer(workdir, max_to_keep=3)
  state, extra, step = ckpt.restore_or_init(lambda: create_train_state(init_key, config))
  start_step = 0 if step is None else step
  for step in range(start_step + 1, total_steps + 1):
    state, metrics = p_train_step(state, batch, loop_key)
    if itstime(step, ckpt_every_steps, total_steps):
      ckpt.save(step, state, extra={"data_step": step})
  ckpt.close()

(`preemption` adds the save and stop on SIGTERM/SIGINT.)

Faults and what happens:

* A save is atomic: Orbax writes `<step>.orbax-checkpoint-tmp*` and renames it when complete.
  A killed save leaves only that tmp directory; it is never listed, and it is removed when the
  next `Checkpointer` opens the directory, or right after a failed save.
* `restore()` without `step` tries the newest checkpoint first; if it cannot be read (a file
  truncated or deleted, a sub-item missing) it emits a `CorruptCheckpointWarning` naming the
  bad step and tries the previous one, and raises `CheckpointError` if none is usable. The next
  `save()` deletes the steps found bad, so that the resumed run can write them again.
* Integrity: once a save is complete on disk (after Orbax's rename; for an async save at the
  next `save`, `wait_until_finished` or `close`), process 0 writes `<step>/camrep_checksums.json`
  (`checksums`: crc32c and size of every file of the step, written atomically). `restore()`
  checks it before reading a step: a file whose size or checksum differs (bit rot, a flipped
  byte that Orbax would read without complaint) makes that step bad exactly like an unreadable one
  (`CorruptCheckpointWarning` "checksum mismatch in FILE", fallback, deleted at the next save).
  So a step that restores is verified. A step without a manifest (written by an older camrep,
  or an async save killed after its rename and before its manifest) restores unverified, with
  one log line. The cost is one read of the step's files per save, once it is finished.
* A template that does not match the checkpoint (missing/extra leaves, other shapes) raises
  `CheckpointError` at once, without falling back: older checkpoints would not match either.
  Dtypes are cast to the template's.
* An unwritable directory, or an `OSError` during a save (e.g. ENOSPC, disk full), raises
  `CheckpointError` naming the directory; earlier checkpoints are untouched and the partial
  one is cleaned up.

Several processes (multi-host): every process must construct the `Checkpointer` and call
`save`/`restore` with the same steps, because Orbax's saves are collective. Orbax handles
`jax.process_index()`: each process writes its own array shards, the `extra` JSON, step
metadata and directory renames/deletions happen only on the primary process (0), and it places
the barriers. This module writes only the checksum manifest, on process 0 (the writability probe
is a per-process uniquely named temporary file, removed at once); every process verifies it at
restore (same files, same verdict, so all fall back alike). `extra` must be identical on all
processes. With several processes, combine a stop request across processes
(`preemption.stop_requested`) before deciding to save, since a save that only some processes
enter would hang. Only one writer may use a directory at a time;
readers (evaluation jobs) should pass `read_only=True`, which neither cleans up tmp
directories nor saves.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import sys
import tempfile
import threading
import time
import types
import warnings
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from camrep.runtime.checksums import (
  MANIFEST_NAME,
  _ChecksumMismatch,
  _short,
  verify_manifest,
  write_manifest,
)

__all__ = [
  "CheckpointError",
  "Checkpointer",
  "CorruptCheckpointWarning",
]

PyTree = Any

_STATE = "state"
_EXTRA = "extra"
CHECKPOINT_SUBDIR = "checkpoints"
_TMP_SUFFIX = ".orbax-checkpoint-tmp"


class CheckpointError(RuntimeError):
  """A checkpoint could not be written or no usable checkpoint could be read."""


class CorruptCheckpointWarning(UserWarning):
  """The newest checkpoint is unreadable and an older one is used instead."""


def _os_error_in_chain(exc: BaseException) -> OSError | None:
  """Returns the first `OSError` in the cause/context chain of `exc`, or None."""
  seen = set()
  while exc is not None and id(exc) not in seen:
    seen.add(id(exc))
    if isinstance(exc, OSError):
      return exc
    exc = exc.__cause__ or exc.__context__
  return None


def _is_disk_full(exc: BaseException) -> bool:
  err = _os_error_in_chain(exc)
  if err is not None and err.errno in (errno.ENOSPC, errno.EDQUOT):
    return True
  # Tensorstore reports I/O failures as ValueError carrying the strerror text.
  return "No space left on device" in str(exc)


# Tensorstore status codes/strerror texts of I/O failures (it raises ValueError, not OSError).
_TENSORSTORE_IO_ERRORS = ("PERMISSION_DENIED", "RESOURCE_EXHAUSTED", "Read-only file system")


def _is_io_error(exc: BaseException) -> bool:
  if _os_error_in_chain(exc) is not None or _is_disk_full(exc):
    return True
  return any(code in str(exc) for code in _TENSORSTORE_IO_ERRORS)


class _HeldStderr:
  """Holds what is written to file descriptor 2 (Python's stderr, absl logging, C++ code) while
  a save runs, through a pipe drained by a thread (no disk needed: the disk may be full).
  `release()` writes it out; `drop()` discards it. A failed Orbax save is followed by dozens of
  "Event loop is closed" tracebacks from its writer threads that would bury the one error that
  matters; a save that succeeds shows whatever it wrote, unchanged."""

  def __init__(self) -> None:
    self._chunks: list[bytes] = []
    self._saved_fd: int | None = None
    self._thread: threading.Thread | None = None
    try:
      sys.stderr.flush()
      read_fd, write_fd = os.pipe()
      self._saved_fd = os.dup(2)
      os.dup2(write_fd, 2)
      os.close(write_fd)
    except (OSError, ValueError, AttributeError):  # no fd 2 (embedded interpreter): hold nothing
      self._saved_fd = None
      return
    self._read_fd = read_fd
    self._thread = threading.Thread(target=self._drain, name="held_stderr", daemon=True)
    self._thread.start()

  def _drain(self) -> None:
    while chunk := os.read(self._read_fd, 65536):
      self._chunks.append(chunk)
    os.close(self._read_fd)

  def _restore(self) -> bytes:
    if self._saved_fd is None:
      return b""
    try:
      sys.stderr.flush()
    except (OSError, ValueError):
      pass
    os.dup2(self._saved_fd, 2)  # closes the pipe's last write end: the drain thread ends
    os.close(self._saved_fd)
    self._saved_fd = None
    if self._thread is not None:
      self._thread.join(timeout=5.0)
    return b"".join(self._chunks)

  def release(self) -> None:
    held = self._restore()
    if held:
      os.write(2, held)

  def drop(self) -> int:
    """Discards what was held; returns its number of lines."""
    return self._restore().count(b"\n")


SAVE_WRITERS_TIMEOUT_S = 30.0
"""How long a failed save waits, at most, for the writer threads it started to end."""


def _join_threads_since(running: set[threading.Thread], timeout_s: float) -> list[str]:
  """Waits, `timeout_s` at most in all, for every thread not in `running` (those started since:
  the failed save's writers, including any a writer starts while others are joined) to end,
  releasing those that wait for its signals (`_release_if_waiting_for_signals`); returns the
  names of those still alive. One save at a time per process (the checkpointing of a run or a
  grid's members is serial): a thread started since belongs to the failed save.

  Joins with `threading.Thread.join` itself: Orbax's writer threads override `join` to re-raise
  the thread's own error, which after a failed save is the aftermath (a file of the removed tmp
  directory not found), not the error the save reports. Threads Python made for foreign (C++)
  threads that called into it are skipped: they cannot be joined."""
  deadline = time.monotonic() + timeout_s
  me = threading.current_thread()
  while True:
    alive = [
      t
      for t in threading.enumerate()
      if t not in running
      and t is not me
      and not isinstance(t, threading._DummyThread)
      and t.is_alive()
    ]
    if not alive or time.monotonic() >= deadline:
      return [t.name for t in alive]
    for t in alive:
      _release_if_waiting_for_signals(t)
    for t in alive:
      threading.Thread.join(t, max(0.0, deadline - time.monotonic()))


def _release_if_waiting_for_signals(thread: threading.Thread) -> None:
  """Ends an Orbax writer thread that waits for a signal its failed save will never send.

  An item's writer (the JSON `extra`'s, the commit thread) waits for the step directory to be
  created before writing; when another item's write fails first, that signal never comes and the
  thread would wait Orbax's coordination timeout (300 s), and the process as long at exit.
  Marking it cancelled and sending the signals it waits for makes it return without writing. A
  writer already past its wait is not interrupted (Orbax's `cancel` would stop its event loop
  under its pending file writes, each of which then prints a traceback); the mark only names its
  end. Threads without Orbax's signalling attributes are left alone, and so are all threads of
  a multi-process save: its signals are shared by every process (only the primary creates the
  step directory), and those of the other processes' writers must not be sent from here."""
  receive = getattr(thread, "_receive_signals", None)
  operation_id = getattr(thread, "_operation_id", None)
  if not receive or operation_id is None or not hasattr(thread, "_cancelled"):
    return
  if jax.process_count() > 1:
    return
  try:
    from orbax.checkpoint._src.futures import future as ocp_future

    thread._cancelled = True
    ocp_future.set_signals(receive, operation_id=operation_id)
  except Exception as e:  # Orbax's internals moved: the thread ends at its own timeout.
    logging.info("Could not release the failed save's writer %s: %s", thread.name, _short(e))


class _AbandonedSaveTasks(logging.Filter):
  """Drops asyncio's "Task exception was never retrieved" records. After a failed save, Orbax's
  other write tasks of that save fail too (their directory is gone) and are garbage-collected
  unread, sometimes after the held stderr was dropped and the save's one error printed; each
  would print a traceback under that error, which already says what happened."""

  def filter(self, record: logging.LogRecord) -> bool:
    return not record.getMessage().startswith("Task exception was never retrieved")


_ABANDONED_SAVE_TASKS = _AbandonedSaveTasks()


def _is_late_write_completion(value: BaseException, tb: types.TracebackType | None) -> bool:
  """Whether an uncaught error is an abandoned save's array write completing after Orbax closed
  the event loop that awaited it: TensorStore, from C++, calls the loop's `call_soon_threadsafe`
  and prints the RuntimeError (one traceback per pending write, under the save's one error)."""
  return (
    isinstance(value, RuntimeError)
    and str(value) == "Event loop is closed"
    and tb is not None
    and tb.tb_frame.f_code.co_name == "call_soon_threadsafe"
  )


def _without_late_write_completions(hook: Callable[..., Any]) -> Callable[..., Any]:
  """`sys.excepthook` that drops `_is_late_write_completion` errors and passes on the rest."""

  def excepthook(kind, value, tb):
    if not _is_late_write_completion(value, tb):
      hook(kind, value, tb)

  excepthook.camrep_drops_late_writes = True
  return excepthook


def _quiet_abandoned_save_tasks() -> None:
  """Installs `_AbandonedSaveTasks` on the asyncio logger, and drops the abandoned writes' late
  completions from `sys.excepthook`, for the rest of the process."""
  log = logging.getLogger("asyncio")
  if _ABANDONED_SAVE_TASKS not in log.filters:
    log.addFilter(_ABANDONED_SAVE_TASKS)
  if not getattr(sys.excepthook, "camrep_drops_late_writes", False):
    sys.excepthook = _without_late_write_completions(sys.excepthook)


def _to_abstract(x: Any) -> Any:
  """Maps a template leaf to what `StandardRestore` expects (shape/dtype/sharding)."""
  if isinstance(x, jax.ShapeDtypeStruct):
    return x
  if isinstance(x, jax.Array):
    return ocp.utils.to_shape_dtype_struct(x)
  if isinstance(x, np.ndarray | np.generic):
    return jax.ShapeDtypeStruct(np.shape(x), np.asarray(x).dtype)
  return x  # Python scalars are restored as such.


def _like_template(restored: Any, template: Any) -> Any:
  """Casts one restored leaf to the container type of its template leaf."""
  if isinstance(template, np.generic):
    return template.dtype.type(np.asarray(restored))
  if isinstance(template, np.ndarray):
    return np.asarray(restored, dtype=template.dtype)
  if isinstance(template, jax.Array | jax.ShapeDtypeStruct) and not isinstance(restored, jax.Array):
    return jnp.asarray(restored, dtype=template.dtype)
  return restored


def _shape_mismatch(restored: PyTree, template: PyTree, limit: int = 4) -> str:
  """'path: saved shape -> template shape' for the first `limit` leaves whose shapes differ."""
  out = []
  flat_r = jax.tree_util.tree_leaves_with_path(restored)
  flat_t = jax.tree_util.tree_leaves(template)
  for (path, a), b in zip(flat_r, flat_t, strict=True):
    sa, sb = tuple(np.shape(a)), tuple(getattr(b, "shape", np.shape(b)))
    if sa != sb:
      out.append(f"{jax.tree_util.keystr(path)}: {sa} -> {sb}")
  more = f" and {len(out) - limit} more" if len(out) > limit else ""
  return "; ".join(out[:limit]) + more


class Checkpointer:
  """Saves and restores `(state, extra)` under `workdir/checkpoints` with Orbax.

  Attributes:
    directory: the checkpoint directory, `workdir/checkpoints`.
    restored: the last successful `restore`, {"step": int, "verified": bool (its checksum
      manifest matched; False: a step written before camrep kept manifests)}; None before.
  """

  def __init__(
    self,
    workdir: str | os.PathLike[str],
    *,
    max_to_keep: int | None = 3,
    async_save: bool = False,
    read_only: bool = False,
  ) -> None:
    """Opens (and unless `read_only` creates) `workdir/checkpoints`.

    Args:
      workdir: the experiment's work directory.
      max_to_keep: number of most recent checkpoints kept; None keeps all.
      async_save: if True, `save` returns once the arrays are copied to host memory and the
        files are written in a background thread; errors then surface on the next `save`,
        `wait_until_finished` or `close`.
      read_only: open for reading only (evaluation jobs): no directory creation, no tmp
        directory cleanup, `save` raises.

    Raises:
      CheckpointError: if the directory cannot be created or written to.
    """
    if max_to_keep is not None and max_to_keep < 1:
      # Orbax would keep no checkpoint at all: a finished run could not be resumed or evaluated.
      raise CheckpointError(f"max_to_keep={max_to_keep} would keep no checkpoint; use >= 1")
    self.directory = os.path.abspath(os.path.join(os.fspath(workdir), CHECKPOINT_SUBDIR))
    self._max_to_keep = max_to_keep
    self._async_save = async_save
    self._read_only = read_only
    self._bad_steps: set[int] = set()
    self._pending_step: int | None = None
    self._unhashed_step: int | None = None  # saved (maybe still in flight), no manifest yet
    self._noted_unverified = False
    # The last successful `restore`: {"step", "verified" (against its checksum manifest)}.
    self.restored: dict[str, Any] | None = None
    if read_only:
      if not os.path.isdir(self.directory):
        raise CheckpointError(f"Checkpoint directory {self.directory} does not exist.")
    else:
      self._check_writable()
      # `<step>.orbax-checkpoint-tmp*` left by a killed save: never listed, but a leftover of
      # the same step would make the next save of that step fail.
      self._remove_tmp_dirs()
    self._manager = self._new_manager()

  def _check_writable(self) -> None:
    """Creates the directory and writes/removes a probe file, so failures come early."""
    try:
      os.makedirs(self.directory, exist_ok=True)
      fd, probe = tempfile.mkstemp(
        prefix=f".write-probe-{jax.process_index()}-", dir=self.directory
      )
      os.close(fd)
      os.remove(probe)
    except OSError as e:
      raise CheckpointError(
        f"Checkpoint directory {self.directory} is not writable ({_short(e)})."
      ) from e

  def _new_manager(self) -> ocp.CheckpointManager:
    options = ocp.CheckpointManagerOptions(
      max_to_keep=self._max_to_keep,
      create=not self._read_only,
      read_only=self._read_only,
      # We remove tmp dirs ourselves (`_remove_tmp_dirs`), synchronously and with retries.
      cleanup_tmp_directories=False,
      enable_async_checkpointing=self._async_save,
    )
    try:
      return ocp.CheckpointManager(
        self.directory,
        options=options,
        item_handlers={
          _STATE: ocp.StandardCheckpointHandler(),
          _EXTRA: ocp.JsonCheckpointHandler(),
        },
      )
    except OSError as e:
      raise CheckpointError(
        f"Cannot open checkpoint directory {self.directory} ({_short(e)})."
      ) from e

  # Listing.

  def all_steps(self) -> list[int]:
    """Returns the finalized checkpoint steps, ascending (tmp directories are ignored)."""
    if self._read_only:  # Another process writes: re-read the directory.
      self._manager.reload()
    return sorted(self._manager.all_steps())

  def latest_step(self) -> int | None:
    """Returns the newest finalized step, or None. It may still prove unreadable."""
    steps = self.all_steps()
    return steps[-1] if steps else None

  # Saving.

  def save(
    self,
    step: int,
    state: PyTree,
    *,
    extra: Mapping[str, Any] | None = None,
    force: bool = False,
  ) -> bool:
    """Saves `state` and `extra` as checkpoint `step`.

    Without `async_save` this returns only once the checkpoint is complete on disk.

    Args:
      step: the step number (the directory name).
      state: pytree of jax/numpy arrays and Python scalars.
      extra: JSON-serialisable dict, e.g. `{"data_step": ..., "rng_seed": ...}`.
      force: overwrite an existing checkpoint at `step` and save even if `step` is not
        newer than the latest checkpoint. Without it such a save is skipped (returns False).

    Returns:
      Whether a checkpoint was written (started, with `async_save`).

    Raises:
      CheckpointError: on an `OSError` while writing (disk full, permission denied, ...).
        The partial checkpoint is removed and earlier checkpoints stay loadable.
      TypeError: if `extra` is not JSON-serialisable.
    """
    if self._read_only:
      raise CheckpointError(f"Checkpointer for {self.directory} is read-only.")
    extra = dict(extra or {})
    json.dumps(extra)  # Fail before touching the disk.
    step = int(step)
    held = _HeldStderr()
    running = set(threading.enumerate())  # the threads before this save (and the drain)
    try:
      # Surface errors of a previous async save before deleting anything.
      self._manager.wait_until_finished()
      self._write_pending_manifest()
      self._delete_bad_steps()
      self._remove_tmp_dirs(step)
      if force and step in self._manager.all_steps():
        self._manager.delete(step)
      if not force and (latest := self._manager.latest_step()) is not None and step <= latest:
        held.release()  # (every path out of this method gives fd 2 back)
        logging.info("Checkpoint step %d not saved: not newer than step %d.", step, latest)
        return False
      self._pending_step = step
      self._unhashed_step = step
      saved = self._manager.save(
        step,
        args=ocp.args.Composite(
          **{_STATE: ocp.args.StandardSave(state), _EXTRA: ocp.args.JsonSave(extra)}
        ),
        force=force,
      )
      if not self._async_save:
        self._manager.wait_until_finished()
        self._write_pending_manifest()
    except Exception as e:
      try:
        self._raise_save_error(e, step)
      except CheckpointError:
        # The failed save's writer threads end meanwhile (printing their tracebacks into the
        # held stderr, sometimes recreating the tmp directory): wait for them, then remove it
        # again. (A fixed pause once did, until a loaded machine's writers outlived it.)
        left = _join_threads_since(running, SAVE_WRITERS_TIMEOUT_S)
        self._remove_tmp_dirs()
        held.drop()
        if left:
          logging.warning("The failed save's writer threads %s are still running.", left)
        raise
      finally:
        held.release()  # an unexpected error: its context stays visible
    held.release()
    return bool(saved)

  def _write_pending_manifest(self) -> None:
    """Writes the manifest of the last save, which must be complete (after Orbax's
    `wait_until_finished`). Process 0 only."""
    step, self._unhashed_step = self._unhashed_step, None
    if step is None or jax.process_index() != 0:
      return
    step_dir = os.path.join(self.directory, str(step))
    if not os.path.isdir(step_dir):  # not saved (skipped), or already removed by retention
      return
    t0 = time.perf_counter()
    write_manifest(step_dir)
    logging.info("Checksummed checkpoint step %d in %.3f s.", step, time.perf_counter() - t0)

  def _delete_bad_steps(self) -> None:
    for bad in sorted(self._bad_steps & set(self._manager.all_steps())):
      logging.warning("Deleting unreadable checkpoint step %d in %s.", bad, self.directory)
      self._manager.delete(bad)
    self._bad_steps.clear()

  def _raise_save_error(self, exc: Exception, step: int | None) -> None:
    """Cleans up after a failed save and re-raises, as CheckpointError for I/O errors. Called
    where the failure surfaces: in `save`, or in `wait_until_finished` for an async save."""
    _quiet_abandoned_save_tasks()
    self._unhashed_step = None
    self._recover()
    if _is_disk_full(exc):
      raise CheckpointError(
        f"Disk full while saving checkpoint step {step} in {self.directory}; the partial "
        f"checkpoint was removed and earlier ones are intact ({_short(exc)})."
      ) from exc
    if _is_io_error(exc):
      raise CheckpointError(
        f"Could not write checkpoint step {step} in {self.directory}; earlier checkpoints "
        f"are intact ({_short(exc)})."
      ) from exc
    raise exc

  def _recover(self) -> None:
    """Removes the failed save's tmp directory and replaces the (possibly broken) manager."""
    try:
      self._manager.close()
    except Exception as e:  # The failed save may re-raise here; it is already handled.
      logging.info("Ignoring error while closing checkpoint manager: %s", _short(e))
    self._remove_tmp_dirs()
    self._manager = self._new_manager()

  def _remove_tmp_dirs(self, step: int | None = None) -> None:
    """Removes unfinalized `<step>.orbax-checkpoint-tmp*` directories (all if step is None).

    Only called when none of our saves is in flight (single writer per directory), and only
    on the primary process, before any process starts the next collective save.
    """
    if jax.process_index() != 0:
      return
    prefix = "" if step is None else f"{step}{_TMP_SUFFIX}"
    for name in os.listdir(self.directory):
      if _TMP_SUFFIX not in name or not name.startswith(prefix):
        continue
      path = os.path.join(self.directory, name)
      # After a failed save, the other items' writer threads may still be adding files for
      # a moment, so rmtree can fail or race; retry until the directory is gone.
      deadline = time.monotonic() + 10.0
      while os.path.lexists(path):
        shutil.rmtree(path, ignore_errors=True)
        if not os.path.lexists(path):
          break
        if time.monotonic() > deadline:
          logging.warning("Could not remove unfinalized checkpoint %s.", path)
          break
        time.sleep(0.05)

  def wait_until_finished(self) -> None:
    """Blocks until a pending async save is complete.

    Raises:
      CheckpointError: if that save failed with an I/O error.
    """
    try:
      self._manager.wait_until_finished()
    except Exception as e:
      self._raise_save_error(e, self._pending_step)
    try:
      self._write_pending_manifest()
    except OSError as e:
      raise CheckpointError(
        f"Could not write the checksum manifest of step {self._pending_step} in "
        f"{self.directory} ({_short(e)})."
      ) from e

  def close(self) -> None:
    """Waits for pending saves and releases Orbax's resources."""
    try:
      self.wait_until_finished()
    finally:
      self._manager.close()

  def __enter__(self) -> Checkpointer:
    return self

  def __exit__(self, *exc_info: object) -> None:
    self.close()

  # Restoring.

  def restore(self, state_template: PyTree, *, step: int | None = None) -> tuple[PyTree, dict, int]:
    """Restores a checkpoint into the structure, shapes and dtypes of `state_template`.

    Args:
      state_template: a pytree like the saved state; leaves may be arrays or
        `jax.ShapeDtypeStruct`s (e.g. from `jax.eval_shape`). Non-array pytree fields (a
        `TrainState`'s `apply_fn`, `tx`) are taken from the template. Leaves come back as
        the template's type (numpy for numpy, jax.Array for jax), cast to its dtype.
      step: the step to restore; None means the newest readable one, falling back to older
        checkpoints (with a `CorruptCheckpointWarning`) when newer ones are unreadable.

    Returns:
      `(state, extra, step)`.

    Raises:
      CheckpointError: if there is no checkpoint, the requested step is missing or
        unreadable, no checkpoint is readable, or the template does not match.
    """
    steps = self.all_steps()
    if not steps:
      raise CheckpointError(f"No checkpoint in {self.directory}.")
    if step is not None:
      if step not in steps:
        raise CheckpointError(
          f"No checkpoint for step {step} in {self.directory}; available: {steps}."
        )
      candidates = [int(step)]
    else:
      candidates = steps[::-1]
    abstract = jax.tree.map(_to_abstract, state_template)
    failures = []
    for s in candidates:
      try:
        verified = self._verify(s)
        restored = self._manager.restore(
          s,
          args=ocp.args.Composite(
            **{_STATE: ocp.args.StandardRestore(abstract), _EXTRA: ocp.args.JsonRestore()}
          ),
        )
        state = jax.tree.map(_like_template, restored[_STATE], state_template)
        extra = restored[_EXTRA]
        if not isinstance(extra, dict):
          raise ValueError(f"'extra' is {type(extra).__name__}, not a dict")
      except Exception as e:
        mismatch = (
          None if isinstance(e, _ChecksumMismatch) else self._template_mismatch(s, abstract)
        )
        if mismatch:
          raise CheckpointError(
            f"Checkpoint step {s} in {self.directory} does not match the state template: {mismatch}"
          ) from e
        if step is not None:
          raise CheckpointError(
            f"Checkpoint step {s} in {self.directory} is unreadable (corrupted or partial): "
            f"{_short(e)}"
          ) from e
        self._bad_steps.add(s)
        failures.append(f"step {s}: {_short(e, 200)}")
        msg = (
          f"Checkpoint step {s} in {self.directory} is unreadable (corrupted or partial), "
          f"skipping it: {_short(e, 200)}"
        )
        warnings.warn(msg, CorruptCheckpointWarning, stacklevel=2)
        logging.warning(msg)
        continue
      shapes = _shape_mismatch(state, state_template)
      if shapes:
        raise CheckpointError(
          f"Checkpoint step {s} in {self.directory} holds arrays of other shapes than the "
          f"config builds ({shapes}): the config differs from the one that saved it"
        )
      if s != candidates[0]:
        logging.warning("Restored checkpoint step %d from %s (fallback).", s, self.directory)
      self.restored = {"step": s, "verified": verified}
      return state, extra, s
    raise CheckpointError(
      f"No usable checkpoint in {self.directory}: all of steps {steps} are unreadable. "
      + "; ".join(failures)
    )

  def _verify(self, step: int) -> bool:
    """Checks step `step` against its checksum manifest (raises `_ChecksumMismatch`); False
    when the step has no manifest (restored unverified)."""
    if verify_manifest(os.path.join(self.directory, str(step))):
      return True
    if not self._noted_unverified:
      self._noted_unverified = True
      logging.info(
        "Checkpoint step %d in %s has no %s (written by an older camrep): restored "
        "without checksum verification.",
        step,
        self.directory,
        MANIFEST_NAME,
      )
    return False

  def _template_mismatch(self, step: int, abstract: PyTree) -> str | None:
    """Describes how `abstract` differs from checkpoint `step`'s metadata.

    Returns None when the metadata itself is unreadable (a corrupt checkpoint) or matches.
    """
    try:
      tree = self._manager.item_metadata(step)[_STATE].tree
      saved = {m.name: tuple(m.shape) for m in jax.tree.leaves(tree)}
    except Exception:
      return None
    names = jax.tree.leaves(ocp.tree.get_param_names(abstract, include_empty_nodes=False))
    wanted = {n: tuple(np.shape(x)) for n, x in zip(names, jax.tree.leaves(abstract), strict=True)}
    problems = []
    if missing := sorted(set(wanted) - set(saved)):
      problems.append(f"not in checkpoint: {missing[:10]}")
    if unexpected := sorted(set(saved) - set(wanted)):
      problems.append(f"not in template: {unexpected[:10]}")
    shapes = [
      f"{n} {saved[n]} vs {wanted[n]}"
      for n in sorted(wanted)
      if saved.get(n, wanted[n]) != wanted[n]
    ]
    if shapes:
      problems.append(f"shape (checkpoint vs template): {shapes[:10]}")
    return "; ".join(problems) or None

  def restore_or_init(self, init_fn: Callable[[], PyTree]) -> tuple[PyTree, dict, int | None]:
    """Restores the newest readable checkpoint, or calls `init_fn()` if there is none.

    Args:
      init_fn: builds the initial state; on resume its result is the restore template
        (called for real, not traced, so numpy leaves and static fields are kept).

    Returns:
      `(state, extra, step)`, with `({}, None)` for extra and step on a fresh start.

    Raises:
      CheckpointError: if checkpoints exist but none is usable (rather than silently
        restarting from scratch).
    """
    if not self.all_steps():
      logging.info("No checkpoint in %s: initialising.", self.directory)
      return init_fn(), {}, None
    state, extra, step = self.restore(init_fn())
    logging.info("Resumed from checkpoint step %d in %s.", step, self.directory)
    return state, extra, step

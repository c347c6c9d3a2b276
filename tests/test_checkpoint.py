"""Tests for camrep.runtime.checkpoint (and its checksums and preemption): round trips, retention,
resume, and fault handling."""

from __future__ import annotations

import asyncio
import errno
import json
import logging
import os
import signal
import sys
import threading
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
import pytest
from flax.training import train_state

from camrep.runtime import checkpoint as ckpt_lib
from camrep.runtime import checksums, preemption

# When a read or write fails, Orbax/tensorstore leave asyncio futures whose exceptions are
# reported after their event loop closed; that is Orbax-internal noise, not our error.
_ignore_orbax_async_noise = pytest.mark.filterwarnings(
  "ignore::pytest.PytestUnraisableExceptionWarning"
)


def _make_state(seed: int = 0) -> dict:
  """A TrainState-like pytree: two param groups, two optax states, a step, numpy leaves."""
  rng = np.random.default_rng(seed)
  # 64x64 float32 so the data lives in separate OCDBT files, not inlined in the index.
  params = {
    "encoder": {"w": jnp.asarray(rng.normal(size=(64, 64)), jnp.float32)},
    "rep": {"B": jnp.asarray(rng.normal(size=(2, 8, 8)), jnp.float32)},
  }
  adam = optax.adam(1e-3)
  sgd = optax.sgd(1e-2, momentum=0.9)
  opt_enc = adam.init(params["encoder"])
  opt_rep = sgd.init(params["rep"])
  # One Adam step so mu/nu/count are not trivial.
  grads = jax.tree.map(jnp.ones_like, params["encoder"])
  _, opt_enc = adam.update(grads, opt_enc, params["encoder"])
  return {
    "params": params,
    "opt_state": {"encoder": opt_enc, "rep": opt_rep},
    "step": jnp.asarray(seed, jnp.int32),
    "nested": {"a": {"b": jnp.arange(6, dtype=jnp.int32).reshape(2, 3)}},
    "np_counts": np.arange(5, dtype=np.int32) + seed,
  }


def _assert_bit_exact(a, b) -> None:
  assert jax.tree.structure(a) == jax.tree.structure(b)
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
    assert type(x) is type(y) or (isinstance(x, jax.Array) and isinstance(y, jax.Array))
    x, y = np.asarray(x), np.asarray(y)
    assert x.dtype == y.dtype and x.shape == y.shape
    np.testing.assert_array_equal(x, y)


def _data_files(step_dir: str) -> list[str]:
  """Array data files of a step, largest first."""
  files = []
  for root, _, names in os.walk(os.path.join(step_dir, "state")):
    files += [os.path.join(root, n) for n in names if os.sep + "d" + os.sep in root + os.sep]
  return sorted(files, key=os.path.getsize, reverse=True)


@pytest.fixture
def ckpt(tmp_path):
  c = ckpt_lib.Checkpointer(tmp_path, max_to_keep=3)
  yield c
  c.close()


def test_round_trip_bit_exact(ckpt):
  state = _make_state(1)
  assert ckpt.save(7, state, extra={"data_step": 700, "rng_seed": 3})
  assert ckpt.all_steps() == [7] and ckpt.latest_step() == 7
  restored, extra, step = ckpt.restore(_make_state(2))
  _assert_bit_exact(restored, state)
  assert isinstance(restored["np_counts"], np.ndarray)
  assert isinstance(restored["params"]["encoder"]["w"], jax.Array)
  assert extra == {"data_step": 700, "rng_seed": 3}
  assert step == 7


def test_round_trip_abstract_template_and_train_state(ckpt):
  params = {"encoder": {"w": jnp.ones((3, 4))}, "rep": {"B": jnp.zeros((2, 2))}}
  tx = optax.multi_transform(
    {"fast": optax.adam(1e-2), "slow": optax.adam(1e-3)}, {"encoder": "fast", "rep": "slow"}
  )
  ts = train_state.TrainState.create(apply_fn=lambda x: x, params=params, tx=tx)
  ts = ts.apply_gradients(grads=jax.tree.map(jnp.ones_like, params))
  ckpt.save(1, ts)
  template = jax.eval_shape(lambda: ts)
  restored, extra, _ = ckpt.restore(template)
  assert isinstance(restored, train_state.TrainState) and restored.apply_fn is ts.apply_fn
  _assert_bit_exact(restored.params, ts.params)
  _assert_bit_exact(restored.opt_state, ts.opt_state)
  assert int(restored.step) == 1 and extra == {}


def test_restore_casts_to_template_dtype(ckpt):
  ckpt.save(1, {"w": jnp.full((2,), 1.5, jnp.float32)})
  restored, _, _ = ckpt.restore({"w": jax.ShapeDtypeStruct((2,), jnp.bfloat16)})
  assert restored["w"].dtype == jnp.bfloat16


def test_template_mismatch_is_an_error_without_fallback(ckpt):
  ckpt.save(1, _make_state(1))
  ckpt.save(2, _make_state(2))
  wrong = _make_state(0)
  wrong["params"]["encoder"]["w"] = jnp.zeros((3, 3))
  del wrong["nested"]
  with warnings.catch_warnings():
    warnings.simplefilter("error", ckpt_lib.CorruptCheckpointWarning)
    with pytest.raises(ckpt_lib.CheckpointError, match="does not match the state template"):
      ckpt.restore(wrong)


def test_max_to_keep(tmp_path):
  with ckpt_lib.Checkpointer(tmp_path, max_to_keep=2) as c:
    for s in range(1, 5):
      c.save(s, {"x": jnp.asarray(s)}, extra={"data_step": s})
    assert c.all_steps() == [3, 4]
    _, extra, step = c.restore({"x": jnp.asarray(0)}, step=3)
    assert (extra, step) == ({"data_step": 3}, 3)


def test_save_not_newer_is_skipped_unless_forced(ckpt):
  stderr_before = os.fstat(2)
  assert ckpt.save(5, {"x": jnp.asarray(1)})
  assert not ckpt.save(5, {"x": jnp.asarray(2)})
  assert not ckpt.save(4, {"x": jnp.asarray(2)})
  # A skipped save gives stderr back (it held fd 2 in a pipe for the rest of the process, so a
  # later crash's message was lost).
  after = os.fstat(2)
  assert (after.st_dev, after.st_ino) == (stderr_before.st_dev, stderr_before.st_ino)
  assert not [t for t in threading.enumerate() if t.name == "held_stderr"]
  assert ckpt.save(5, {"x": jnp.asarray(3)}, force=True)
  restored, _, _ = ckpt.restore({"x": jnp.asarray(0)})
  assert int(restored["x"]) == 3 and ckpt.all_steps() == [5]


def test_async_save(tmp_path):
  state = _make_state(4)
  with ckpt_lib.Checkpointer(tmp_path, async_save=True) as c:
    c.save(1, state, extra={"data_step": 1})
    c.save(2, state, extra={"data_step": 2})
    c.wait_until_finished()
    restored, extra, step = c.restore(state)
  _assert_bit_exact(restored, state)
  assert (extra, step) == ({"data_step": 2}, 2)


def test_restore_or_init_empty_dir_calls_init(ckpt):
  calls = []

  def init_fn():
    calls.append(1)
    return {"x": jnp.zeros((2,))}

  state, extra, step = ckpt.restore_or_init(init_fn)
  assert calls == [1] and step is None and extra == {}
  np.testing.assert_array_equal(state["x"], np.zeros(2))


def test_restore_or_init_resumes(tmp_path):
  state = _make_state(3)
  with ckpt_lib.Checkpointer(tmp_path) as c:
    c.save(3, state, extra={"data_step": 30})
  # A new Checkpointer, as after a restart.
  with ckpt_lib.Checkpointer(tmp_path) as c:
    restored, extra, step = c.restore_or_init(lambda: _make_state(0))
  _assert_bit_exact(restored, state)
  assert (extra, step) == ({"data_step": 30}, 3)


def test_restore_empty_dir_is_an_error(ckpt):
  with pytest.raises(ckpt_lib.CheckpointError, match="No checkpoint in"):
    ckpt.restore({"x": jnp.zeros(())})
  ckpt.save(1, {"x": jnp.zeros(())})
  with pytest.raises(ckpt_lib.CheckpointError, match="No checkpoint for step 9"):
    ckpt.restore({"x": jnp.zeros(())}, step=9)


@_ignore_orbax_async_noise
@pytest.mark.parametrize("fault", ["truncate_data", "delete_data", "delete_extra", "rm_state"])
def test_corrupted_latest_falls_back_with_warning(ckpt, fault):
  good, bad = _make_state(1), _make_state(2)
  ckpt.save(1, good, extra={"data_step": 1})
  ckpt.save(2, bad, extra={"data_step": 2})
  step_dir = os.path.join(ckpt.directory, "2")
  if fault == "truncate_data":
    for f in _data_files(step_dir):
      with open(f, "r+b") as fh:
        fh.truncate(os.path.getsize(f) // 2)
  elif fault == "delete_data":
    for f in _data_files(step_dir):
      os.remove(f)
  elif fault == "delete_extra":
    os.remove(os.path.join(step_dir, "extra", "metadata"))
  else:
    import shutil

    shutil.rmtree(os.path.join(step_dir, "state"))
  with pytest.warns(ckpt_lib.CorruptCheckpointWarning, match=r"step 2 .*unreadable"):
    restored, extra, step = ckpt.restore(_make_state(0))
  _assert_bit_exact(restored, good)
  assert (extra, step) == ({"data_step": 1}, 1)
  # Asking for the bad step explicitly is an error, not a silent fallback.
  with pytest.raises(ckpt_lib.CheckpointError, match="step 2 .*unreadable"):
    ckpt.restore(_make_state(0), step=2)
  # The resumed run can write step 2 again: the bad one is replaced.
  assert ckpt.save(2, bad, extra={"data_step": 2})
  restored, extra, step = ckpt.restore(_make_state(0))
  _assert_bit_exact(restored, bad)
  assert step == 2


@_ignore_orbax_async_noise
def test_no_usable_checkpoint_is_a_clear_error(ckpt):
  ckpt.save(1, _make_state(1))
  ckpt.save(2, _make_state(2))
  for s in ("1", "2"):
    os.remove(os.path.join(ckpt.directory, s, "extra", "metadata"))
  with pytest.warns(ckpt_lib.CorruptCheckpointWarning):
    with pytest.raises(ckpt_lib.CheckpointError, match="No usable checkpoint"):
      ckpt.restore(_make_state(0))
  with pytest.warns(ckpt_lib.CorruptCheckpointWarning):
    with pytest.raises(ckpt_lib.CheckpointError, match="No usable checkpoint"):
      ckpt.restore_or_init(lambda: _make_state(0))


def test_leftover_tmp_dir_is_ignored_and_cleaned(tmp_path):
  state = _make_state(1)
  with ckpt_lib.Checkpointer(tmp_path) as c:
    c.save(1, state, extra={"data_step": 1})
    ckpt_dir = c.directory
  # As left by a kill during the save of step 2 (half-written copy of a step).
  import shutil

  tmp = os.path.join(ckpt_dir, "2.orbax-checkpoint-tmp")
  shutil.copytree(os.path.join(ckpt_dir, "1"), tmp)
  os.remove(os.path.join(tmp, "extra", "metadata"))
  os.makedirs(os.path.join(ckpt_dir, "3.orbax-checkpoint-tmp-1234567", "state"))
  with ckpt_lib.Checkpointer(tmp_path) as c:
    assert c.all_steps() == [1] and c.latest_step() == 1
    _, extra, step = c.restore(state)
    assert (extra, step) == ({"data_step": 1}, 1)
    assert c.save(2, state, extra={"data_step": 2})
    assert c.save(3, state, extra={"data_step": 3})
    assert c.all_steps() == [1, 2, 3]
  assert sorted(os.listdir(ckpt_dir)) == ["1", "2", "3"]


def _deny_writes_under(monkeypatch, root) -> None:
  """Makes Python-level directory/file creation under `root` fail with EACCES."""
  root = os.fspath(root)
  real_mkdir, real_open = os.mkdir, os.open

  def under(path) -> bool:
    return os.path.abspath(os.fspath(path)).startswith(root)

  def mkdir(path, *args, **kwargs):
    if under(path):
      raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))
    return real_mkdir(path, *args, **kwargs)

  def open_(path, flags, *args, **kwargs):
    if under(path) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
      raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))
    return real_open(path, flags, *args, **kwargs)

  monkeypatch.setattr(os, "mkdir", mkdir)
  monkeypatch.setattr(os, "open", open_)


@pytest.mark.skipif(
  hasattr(os, "geteuid") and os.geteuid() == 0, reason="root ignores directory permissions"
)
def test_unwritable_workdir_chmod(tmp_path):
  workdir = tmp_path / "ro"
  workdir.mkdir()
  workdir.chmod(0o500)
  try:
    with pytest.raises(ckpt_lib.CheckpointError, match=str(workdir)):
      ckpt_lib.Checkpointer(workdir)
  finally:
    workdir.chmod(0o700)


@pytest.mark.parametrize("precreate", [False, True])
def test_unwritable_workdir_monkeypatched(tmp_path, monkeypatch, precreate):
  workdir = tmp_path / "ro"
  if precreate:  # Directory exists but files cannot be created in it.
    (workdir / ckpt_lib.CHECKPOINT_SUBDIR).mkdir(parents=True)
  _deny_writes_under(monkeypatch, workdir)
  with pytest.raises(ckpt_lib.CheckpointError, match="not writable") as info:
    ckpt_lib.Checkpointer(workdir)
  assert str(workdir / ckpt_lib.CHECKPOINT_SUBDIR) in str(info.value)


@_ignore_orbax_async_noise
@pytest.mark.parametrize("async_save", [False, True])
@pytest.mark.parametrize("where", ["array_handler", "json_write"])
def test_disk_full_during_save(tmp_path, monkeypatch, where, async_save):
  asyncio_log = logging.getLogger("asyncio")  # as in a fresh process: no failed save yet
  quiet = [f for f in asyncio_log.filters if f is not ckpt_lib._ABANDONED_SAVE_TASKS]
  monkeypatch.setattr(asyncio_log, "filters", quiet)
  uncaught = []
  monkeypatch.setattr(sys, "excepthook", lambda kind, value, tb: uncaught.append(value))
  good = _make_state(1)
  c = ckpt_lib.Checkpointer(tmp_path, async_save=async_save)
  c.save(1, good, extra={"data_step": 1})
  c.wait_until_finished()

  async def disk_full(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

  if where == "array_handler":
    target = (ocp.StandardCheckpointHandler, "async_save")
  else:  # The Python-level file write of the JSON item, in the commit thread.
    target = (ocp.handlers.JsonCheckpointHandler, "_save_fn")
  with monkeypatch.context() as m:
    m.setattr(*target, disk_full)
    with pytest.raises(ckpt_lib.CheckpointError, match="Disk full") as info:
      c.save(2, _make_state(2), extra={"data_step": 2})
      c.wait_until_finished()  # Async: the error surfaces here.
    assert c.directory in str(info.value)
  # The abandoned save's tasks, collected later, print no traceback under the error (asyncio's
  # log of their exceptions); asyncio's other records still pass.
  never_retrieved = "Task exception was never retrieved\nfuture: <Task finished ...>"
  assert not asyncio_log.filter(logging.makeLogRecord({"msg": never_retrieved}))
  assert asyncio_log.filter(logging.makeLogRecord({"msg": "Executing <Task> took 0.2 seconds"}))
  # Nor do its array writes that complete after their event loop was closed: TensorStore calls
  # `call_soon_threadsafe` from C++ and prints the error through `sys.excepthook`.
  loop = asyncio.new_event_loop()
  loop.close()
  try:
    loop.call_soon_threadsafe(print)
  except RuntimeError as e:
    closed, from_c = e, e.__traceback__.tb_next  # the frames below this test's: as from C++
  sys.excepthook(RuntimeError, closed, from_c)
  other = RuntimeError("Event loop is closed")
  sys.excepthook(RuntimeError, other, closed.__traceback__)  # raised in Python code: shown
  assert uncaught == [other]
  assert c.all_steps() == [1]
  restored, extra, step = c.restore(_make_state(0))
  _assert_bit_exact(restored, good)
  assert (extra, step) == ({"data_step": 1}, 1)
  # Space freed: the same step saves fine and no tmp directory is left behind.
  assert c.save(2, _make_state(2), extra={"data_step": 2})
  c.close()
  assert sorted(os.listdir(c.directory)) == ["1", "2"]


class _RaisingOnJoin(threading.Thread):
  """Like Orbax's writer threads: `join` re-raises the error the thread ended with."""

  error: BaseException | None = None

  def run(self):
    try:
      super().run()
    except BaseException as e:
      self.error = e

  def join(self, timeout=None):
    super().join(timeout)
    if self.error is not None:
      raise self.error


def test_failed_save_waits_for_every_writer_and_raises_none_of_their_errors():
  running = set(threading.enumerate())
  late_done = threading.Event()

  def late_writer():
    late_done.wait(0.3)  # still running when the first writers have ended
    late_done.set()

  def writer():
    threading.Thread(target=late_writer, name="late").start()  # started while joined
    raise FileNotFoundError("tmp/state/_METADATA")  # its directory was removed under it

  first = _RaisingOnJoin(target=writer, name="writer")
  first.start()
  assert ckpt_lib._join_threads_since(running, 10.0) == []
  assert late_done.is_set() and not first.is_alive()
  assert isinstance(first.error, FileNotFoundError)
  # A writer that outlives the deadline is named, not waited for.
  release = threading.Event()
  stuck = threading.Thread(target=release.wait, name="stuck")
  stuck.start()
  try:
    assert ckpt_lib._join_threads_since(running, 0.05) == ["stuck"]
  finally:
    release.set()
    stuck.join()


def test_a_writer_waiting_for_a_signal_the_failed_save_never_sends_is_released():
  # An item's writer waits for the step directory's creation; when another item's write fails
  # first, that signal never comes, and it would wait Orbax's coordination timeout (300 s).
  from orbax.checkpoint._src.futures import future, synchronization

  running = set(threading.enumerate())
  wrote = threading.Event()
  writer = future._SignalingThread(
    target=wrote.set,
    send_signals=[],
    receive_signals=[synchronization.HandlerAwaitableSignal.STEP_DIRECTORY_CREATION],
    operation_id="camrep-test-released",
    name="json_ch_save",
  )
  writer.start()
  assert ckpt_lib._join_threads_since(running, 10.0) == []
  assert not writer.is_alive() and not wrote.is_set()  # returned without writing


def test_extra_must_be_json(ckpt):
  with pytest.raises(TypeError):
    ckpt.save(1, {"x": jnp.zeros(())}, extra={"bad": object()})
  assert ckpt.all_steps() == []


def test_read_only(tmp_path):
  with pytest.raises(ckpt_lib.CheckpointError, match="does not exist"):
    ckpt_lib.Checkpointer(tmp_path, read_only=True)
  with ckpt_lib.Checkpointer(tmp_path) as c:
    c.save(1, {"x": jnp.ones(())})
  with ckpt_lib.Checkpointer(tmp_path, read_only=True) as r:
    assert r.latest_step() == 1
    with pytest.raises(ckpt_lib.CheckpointError, match="read-only"):
      r.save(2, {"x": jnp.ones(())})


def test_signal_handler_sets_requested_and_restores():
  before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
  with preemption.install_signal_handlers() as preempt:
    assert not preempt.requested
    os.kill(os.getpid(), signal.SIGTERM)
    assert preempt.requested and preempt.signum == signal.SIGTERM
    os.kill(os.getpid(), signal.SIGTERM)  # A second SIGTERM is only logged.
    with pytest.raises(KeyboardInterrupt):
      os.kill(os.getpid(), signal.SIGINT)  # A second signal that is SIGINT aborts.
  assert {s: signal.getsignal(s) for s in before} == before
  preempt.uninstall()  # Idempotent.
  assert {s: signal.getsignal(s) for s in before} == before


def test_signal_handler_first_sigint_only_requests():
  # Whatever was installed before comes back (Python's default handler in a terminal; SIG_IGN
  # for a job started in the background by a non-interactive shell, as CI may do).
  before = signal.getsignal(signal.SIGINT)
  handler = preemption.install_signal_handlers()
  try:
    os.kill(os.getpid(), signal.SIGINT)
    assert handler.requested and handler.signum == signal.SIGINT
  finally:
    handler.uninstall()
  assert signal.getsignal(signal.SIGINT) is before


def _manifest(step_dir: str) -> str:
  return os.path.join(step_dir, checksums.MANIFEST_NAME)


@pytest.mark.parametrize("async_save", [False, True])
def test_manifest_written_for_each_save(tmp_path, async_save):
  with ckpt_lib.Checkpointer(tmp_path, max_to_keep=2, async_save=async_save) as c:
    for s in (1, 2, 3):
      c.save(s, _make_state(s), extra={"data_step": s})
    c.wait_until_finished()
    assert c.all_steps() == [2, 3]
    for s in (2, 3):
      step_dir = os.path.join(c.directory, str(s))
      assert os.path.isfile(_manifest(step_dir))
      assert checksums.verify_manifest(step_dir)
      with open(_manifest(step_dir)) as fh:
        files = json.load(fh)["files"]
      # Every file of the step is covered, the array data included.
      on_disk = {
        os.path.relpath(os.path.join(r, n), step_dir)
        for r, _, names in os.walk(step_dir)
        for n in names
        if n != checksums.MANIFEST_NAME
      }
      assert set(files) == on_disk
      assert any(os.path.join(step_dir, f) in _data_files(step_dir) for f in files)
    # No manifest temp file is left behind.
    left = [n for r, _, ns in os.walk(c.directory) for n in ns if ".tmp" in n]
    assert left == []


@_ignore_orbax_async_noise
def test_flipped_bytes_fail_verification_and_fall_back(ckpt):
  good, bad = _make_state(1), _make_state(2)
  ckpt.save(1, good, extra={"data_step": 1})
  ckpt.save(2, bad, extra={"data_step": 2})
  step_dir = os.path.join(ckpt.directory, "2")
  target = _data_files(step_dir)[0]
  size = os.path.getsize(target)
  with open(target, "r+b") as fh:  # 64 bytes in the middle, size unchanged
    fh.seek(size // 2)
    chunk = fh.read(64)
    fh.seek(size // 2)
    fh.write(bytes(b ^ 0xFF for b in chunk))
  assert os.path.getsize(target) == size
  rel = os.path.relpath(target, step_dir)
  with pytest.warns(
    ckpt_lib.CorruptCheckpointWarning, match=rf"step 2 .*checksum mismatch in {rel}"
  ):
    restored, extra, step = ckpt.restore(_make_state(0))
  _assert_bit_exact(restored, good)
  assert (extra, step) == ({"data_step": 1}, 1)
  with pytest.raises(ckpt_lib.CheckpointError, match="checksum mismatch"):
    ckpt.restore(_make_state(0), step=2)
  # The bad step is deleted at the next save and written again, verified.
  assert ckpt.save(2, bad, extra={"data_step": 2})
  with warnings.catch_warnings():
    warnings.simplefilter("error", ckpt_lib.CorruptCheckpointWarning)
    restored, _, step = ckpt.restore(_make_state(0))
  _assert_bit_exact(restored, bad)
  assert step == 2


def test_checkpoint_without_manifest_restores(tmp_path, caplog):
  state = _make_state(3)
  with ckpt_lib.Checkpointer(tmp_path) as c:
    c.save(1, state, extra={"data_step": 1})
    c.save(2, state, extra={"data_step": 2})
    for s in (1, 2):  # as written by an older camrep
      os.remove(_manifest(os.path.join(c.directory, str(s))))
  with ckpt_lib.Checkpointer(tmp_path) as c:
    with warnings.catch_warnings():
      warnings.simplefilter("error")
      with caplog.at_level("INFO"):
        restored, extra, step = c.restore(_make_state(0))
        assert c.restored == {"step": 2, "verified": False}  # the non-finite stop says so
        c.restore(_make_state(0), step=1)
  _assert_bit_exact(restored, state)
  assert (extra, step) == ({"data_step": 2}, 2)
  notes = [r for r in caplog.records if checksums.MANIFEST_NAME in r.getMessage()]
  assert len(notes) == 1  # at most one note, no warning
  with ckpt_lib.Checkpointer(tmp_path) as c:
    c.save(3, state, extra={"data_step": 3})
    c.wait_until_finished()
    c.restore(_make_state(0))
    assert c.restored == {"step": 3, "verified": True}

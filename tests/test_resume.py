"""Deterministic resume: a run killed while it saves a checkpoint, then killed part-way, then
stopped by SIGTERM, each time started again with the same command, ends bit-identical to a run
left alone: the same parameters and the same logged metrics at every step. While the run left
alone runs, a second start on its workdir is refused.

Each run is a separate process (`python -m camrep.main`, through tests/resume_script.py to inject
the kill-during-save fault), as a user would run it. The faults are one chain in one workdir (a
process each), made once for the module's tests, each of which checks its own link.
"""

from __future__ import annotations

import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from camrep.configs import gqn
from camrep.runtime import workdir as workdir_lib
from camrep.runtime import writers
from camrep.synthesis import restore, train
from tests.utils import one_device_env

# One xdist worker runs the module, so the reference run is made once.
pytestmark = [pytest.mark.xdist_group("resume"), pytest.mark.slow]

ROOT = pathlib.Path(__file__).resolve().parents[1]
# Run as a module from ROOT, where camrep and tests import (`python -m tests.resume_script`).
SCRIPT = "tests.resume_script"
TOTAL, EVERY, EVAL = 36, 6, 12
# Wall-clock figures differ between any two runs; everything else must be equal.
TIMING_KEYS = ("train/steps_per_sec",)


def _flags(workdir) -> list[str]:
  return [
    "--config=configs/gqn.py:smoke",
    f"--config.total_steps={TOTAL}",
    f"--config.ckpt_every_steps={EVERY}",
    f"--config.eval_every_steps={EVAL}",
    f"--workdir={workdir}",
  ]


def _run(workdir, kill_in_save: int = 0) -> subprocess.CompletedProcess:
  return subprocess.run(
    [sys.executable, "-m", SCRIPT, str(kill_in_save), *_flags(workdir)],
    cwd=ROOT,
    env=one_device_env(),
    capture_output=True,
    text=True,
    timeout=600,
  )


def _start(workdir) -> subprocess.Popen:
  return subprocess.Popen(
    [sys.executable, "-m", SCRIPT, "0", *_flags(workdir)],
    cwd=ROOT,
    env=one_device_env(),
    stdout=subprocess.PIPE,
    stderr=subprocess.STDOUT,
    text=True,
  )


def _wait_for_step(proc: subprocess.Popen, workdir, step: int) -> None:
  """Waits until metrics.jsonl has logged `step` (the run is then past checkpoint step // EVERY)."""
  path = os.path.join(workdir, "metrics.jsonl")
  deadline = time.monotonic() + 600
  while time.monotonic() < deadline:
    assert proc.poll() is None, f"run ended early:\n{proc.stdout.read()}"
    if os.path.exists(path):
      with open(path) as f:
        steps = [json.loads(x)["step"] for x in f if x.strip().endswith("}")]
      if steps and max(steps) >= step:
        return
    time.sleep(0.05)
  raise TimeoutError(f"step {step} not logged in {workdir}")


def _rows(workdir) -> list[dict]:
  return [
    {k: v for k, v in r.items() if k not in TIMING_KEYS} for r in writers.read_metrics(workdir)
  ]


def _params(workdir):
  run = restore.load_run(str(workdir))
  assert run.step == TOTAL
  return run.params


# Session scope: xdist interleaves other modules' tests on this worker, which tears module-scoped
# fixtures down between this module's tests.
@pytest.fixture(scope="session")
def reference(tmp_path_factory):
  """The run left alone, and what a second start on its workdir, tried while it runs, did:
  (workdir, the second start's error, the PID of the run, names of its files before and after)."""
  workdir = tmp_path_factory.mktemp("reference")
  proc = _start(workdir)
  _wait_for_step(proc, workdir, 2)
  # The second start in this process: refused within milliseconds, while the first still runs
  # (a second process would need seconds to import JAX; tests/test_workdir.py checks the
  # command line's exit status 2 on a held workdir).
  config = gqn.get_config("smoke")
  config.total_steps, config.ckpt_every_steps, config.eval_every_steps = TOTAL, EVERY, EVAL
  before = {p.name for p in workdir.iterdir()}
  try:
    train.train_and_evaluate(config, str(workdir))
    error = None
  except workdir_lib.WorkdirError as e:
    error = e
  running = proc.poll() is None
  after = {p.name for p in workdir.iterdir()}
  out, _ = proc.communicate(timeout=600)
  assert proc.returncode == 0, out[-3000:]
  return {
    "workdir": workdir,
    "error": error,
    "running": running,
    "pid": proc.pid,
    "before": before,
    "after": after,
  }


def _lock_pid(workdir) -> int:
  with open(workdir / workdir_lib.LOCK_FILE) as f:
    return int(json.load(f)["pid"])


@pytest.fixture(scope="session")
def chain(tmp_path_factory):
  """One workdir through every fault, each link a process: killed while committing checkpoint
  18; started again and killed (SIGKILL) at step 20 or later; started again and stopped by
  SIGTERM at step 26 or later; started again to the end. {link: (exit status, output, PID or
  None)}, the workdir's checkpoint names after the first link, and the workdir."""
  workdir = tmp_path_factory.mktemp("chain")
  links = {}
  r = _run(workdir, kill_in_save=18)
  links["save"] = (r.returncode, r.stdout + r.stderr, _lock_pid(workdir))
  names = os.listdir(workdir / "checkpoints")
  for name, sig, step in (("kill", signal.SIGKILL, 20), ("term", signal.SIGTERM, 26)):
    proc = _start(workdir)
    _wait_for_step(proc, workdir, step)
    proc.send_signal(sig)
    out, _ = proc.communicate(timeout=300)
    links[name] = (proc.returncode, out, proc.pid)
    if sig == signal.SIGKILL:
      assert proc.returncode == -signal.SIGKILL, out[-3000:]
      assert os.path.exists(workdir / workdir_lib.LOCK_FILE)  # left by the killed process
  r = _run(workdir)
  links["end"] = (r.returncode, r.stdout + r.stderr, None)
  return {"workdir": workdir, "links": links, "names_after_save": names}


def _assert_identical(workdir, reference):
  got, want = _rows(workdir), _rows(reference)
  assert [r["step"] for r in got] == [r["step"] for r in want]
  assert got == want  # every logged value, bit for bit (JSON floats round-trip exactly)
  final = [r for r in got if "train/loss" in r][-1]
  assert final["step"] == TOTAL
  a, b = _params(workdir), _params(reference)
  assert jax.tree.structure(a) == jax.tree.structure(b)
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_killed_during_checkpoint_save_resumes_from_the_last_complete_one(chain):
  code, out, _ = chain["links"]["save"]
  assert code == -signal.SIGKILL, out[-3000:]
  names = chain["names_after_save"]
  assert any(n.startswith("18.orbax-checkpoint-tmp") for n in names), names  # the partial save
  assert "18" not in names and "12" in names
  code, out, _ = chain["links"]["kill"]
  assert "resumed from step 12" in out, out[-3000:]


def test_killed_part_way_the_next_start_takes_over_the_lock_and_resumes(chain):
  for before, after in (("save", "kill"), ("kill", "term")):  # each start after a SIGKILL
    pid = chain["links"][before][2]
    out = chain["links"][after][1]
    assert f"taking over the stale lock of {chain['workdir']}: PID {pid}" in out, out[-3000:]
    assert "resumed from step" in out


def test_sigterm_saves_a_checkpoint_exits_0_and_the_same_command_finishes(chain):
  code, out, _ = chain["links"]["term"]
  assert code == 0, out[-3000:]
  assert "checkpoint saved" in out
  code, out, _ = chain["links"]["end"]
  assert code == 0, out[-3000:]
  assert "resumed from step" in out
  assert not os.path.exists(chain["workdir"] / workdir_lib.LOCK_FILE)


def test_the_run_through_every_fault_is_bit_identical_to_the_run_left_alone(chain, reference):
  _assert_identical(chain["workdir"], reference["workdir"])


def test_second_start_on_a_live_workdir_is_refused(reference):
  """While a run holds its workdir, a second start is refused (naming the holder) and writes
  nothing; the first finishes as the run left alone (bit-identical to the run through every
  fault: the test above)."""
  error = reference["error"]
  assert isinstance(error, workdir_lib.WorkdirError), error
  assert f"in use by another run (PID {reference['pid']} on" in str(error)
  assert reference["running"], "the first run ended before the second start was tried"
  assert reference["before"] <= reference["after"]

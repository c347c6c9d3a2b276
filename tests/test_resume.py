"""Deterministic resume: a run killed part-way, or stopped by SIGTERM, or killed while
it saves a checkpoint, and started again with the same command ends bit-identical to a run left
alone: the same parameters and the same logged metrics at every step.

Each run is a separate process (`python -m camrep.main`, through tests/resume_script.py to inject
the kill-during-save fault), as a user would run it.
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
# fixtures down between this module's tests (it was built three times).
@pytest.fixture(scope="session")
def reference(tmp_path_factory):
  """The uninterrupted run."""
  workdir = tmp_path_factory.mktemp("reference")
  r = _run(workdir)
  assert r.returncode == 0, r.stderr[-3000:]
  return workdir


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


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
def test_killed_and_restarted_run_is_bit_identical(sig, reference, tmp_path):
  workdir = tmp_path / "w"
  proc = _start(workdir)
  _wait_for_step(proc, workdir, 16)  # between checkpoints 12 and 18
  proc.send_signal(sig)
  out, _ = proc.communicate(timeout=300)
  if sig == signal.SIGTERM:
    assert proc.returncode == 0, out[-3000:]
    assert "checkpoint saved" in out
  else:
    assert proc.returncode == -signal.SIGKILL
    assert os.path.exists(workdir / ".camrep.lock")  # left by the killed process
  r = _run(workdir)
  assert r.returncode == 0, r.stderr[-3000:]
  assert "resumed from step" in r.stdout
  if sig == signal.SIGKILL:  # the dead process's lock is taken over, with a warning
    assert f"taking over the stale lock of {workdir}: PID {proc.pid}" in r.stderr
  assert not os.path.exists(workdir / ".camrep.lock")
  _assert_identical(workdir, reference)


def test_second_start_on_a_live_workdir_is_refused(reference, tmp_path):
  """While a run holds its workdir, a second start is refused (exit 2, naming the
  holder) and writes nothing; the first finishes bit-identical to a run alone."""
  workdir = tmp_path / "w"
  proc = _start(workdir)
  _wait_for_step(proc, workdir, 2)
  # The second start in this process: refused within milliseconds, while the first still runs
  # (a second process would need seconds to import JAX; tests/test_workdir.py checks the
  # command line's exit status 2 on a held workdir).
  config = gqn.get_config("smoke")
  config.total_steps, config.ckpt_every_steps, config.eval_every_steps = TOTAL, EVERY, EVAL
  before = {p.name: p.stat().st_size for p in workdir.iterdir()}
  with pytest.raises(workdir_lib.WorkdirError, match=f"in use by another run \\(PID {proc.pid} on"):
    train.train_and_evaluate(config, str(workdir))
  assert proc.poll() is None, "the first run ended before the second start was tried"
  assert set(before) <= {p.name for p in workdir.iterdir()}
  out, _ = proc.communicate(timeout=600)
  assert proc.returncode == 0, out[-3000:]
  _assert_identical(workdir, reference)


def test_killed_during_checkpoint_save_is_bit_identical(reference, tmp_path):
  workdir = tmp_path / "w"
  r = _run(workdir, kill_in_save=18)
  assert r.returncode == -signal.SIGKILL, r.stderr[-3000:]
  ckpt_dir = workdir / "checkpoints"
  names = os.listdir(ckpt_dir)
  assert any(n.startswith("18.orbax-checkpoint-tmp") for n in names), names  # the partial save
  assert "18" not in names and "12" in names
  r = _run(workdir)
  assert r.returncode == 0, r.stderr[-3000:]
  assert "resumed from step 12" in r.stdout
  _assert_identical(workdir, reference)

"""A pose-regression run killed (SIGKILL) or stopped (SIGTERM, or Ctrl-C's SIGINT) part-way and
started again with the same command ends as a run left alone: the same results.json (apart from
its timings and machine) and the same logged metrics at every step. A stop saves a checkpoint,
says how to resume, exits 0 and leaves no lock; a killed run's lock is taken over.

Each run is a separate process (`python -m camrep.regression` through
tests/regression_resume_script.py, which slows its steps so that the signal lands between two
checkpoints), as a user would run it.
"""

from __future__ import annotations

import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest

from camrep.runtime import workdir as workdir_lib
from camrep.runtime import writers
from tests.utils import one_device_env

pytestmark = [pytest.mark.xdist_group("regression_resume"), pytest.mark.slow]

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCRIPT = "tests.regression_resume_script"
TOTAL, EVERY = 60, 10
# Wall-clock figures and the machine differ between any two runs; everything else must be equal.
TIMINGS = ("train_seconds", "steps_per_sec", "eval_seconds", "machine")


def _flags(workdir, cache) -> list[str]:
  return [
    "--config=configs/regression.py:car,smoke",
    "--config.representation=euler",
    f"--config.total_steps={TOTAL}",
    f"--config.ckpt_every_steps={EVERY}",
    "--config.eval_every_steps=20",  # periodic validation: its curve goes on across the resume
    f"--config.data.cache_dir={cache}",
    f"--workdir={workdir}",
  ]


def _start(workdir, cache) -> subprocess.Popen:
  return subprocess.Popen(
    [sys.executable, "-m", SCRIPT, *_flags(workdir, cache)],
    cwd=ROOT,
    env=one_device_env(),
    stdout=subprocess.PIPE,
    stderr=subprocess.PIPE,
    text=True,
  )


def _run(workdir, cache) -> subprocess.CompletedProcess:
  return subprocess.run(
    [sys.executable, "-m", SCRIPT, *_flags(workdir, cache)],
    cwd=ROOT,
    env={**one_device_env(), "SLOW_STEP_S": "0"},
    capture_output=True,
    text=True,
    timeout=600,
  )


def _wait_for_step(proc: subprocess.Popen, workdir, step: int) -> None:
  path = os.path.join(workdir, "metrics.jsonl")
  deadline = time.monotonic() + 600
  while time.monotonic() < deadline:
    assert proc.poll() is None, f"run ended early:\n{proc.communicate()}"
    if os.path.exists(path):
      with open(path) as f:
        steps = [json.loads(x)["step"] for x in f if x.strip().endswith("}")]
      if steps and max(steps) >= step:
        return
    time.sleep(0.02)
  raise TimeoutError(f"step {step} not logged in {workdir}")


def _results(workdir) -> dict:
  with open(os.path.join(workdir, "results.json")) as f:
    return {k: v for k, v in json.load(f).items() if k not in TIMINGS}


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
  return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def reference(tmp_path_factory, cache):
  """The uninterrupted run (it also renders the data into the cache the others read)."""
  workdir = tmp_path_factory.mktemp("reference")
  r = _run(workdir, cache)
  assert r.returncode == 0, r.stderr[-3000:]
  return workdir


@pytest.mark.parametrize(
  "sig", [signal.SIGKILL, signal.SIGTERM, signal.SIGINT], ids=["SIGKILL", "SIGTERM", "SIGINT"]
)
def test_a_regression_killed_or_stopped_resumes_to_the_same_results(
  sig, reference, cache, tmp_path
):
  workdir = tmp_path / "w"
  proc = _start(workdir, cache)
  _wait_for_step(proc, workdir, 26)  # past checkpoint 20
  proc.send_signal(sig)
  out, err = proc.communicate(timeout=300)
  if sig != signal.SIGKILL:  # SIGTERM, or Ctrl-C (SIGINT): saved and stopped alike
    assert proc.returncode == 0, err[-3000:]
    line = [x for x in out.splitlines() if f"on {sig.name}" in x]
    assert line and "checkpoint saved" in line[0] and "run the same command to resume" in line[0]
    assert not (workdir / workdir_lib.LOCK_FILE).exists()
    assert not (workdir / "results.json").exists()
  else:
    assert proc.returncode == -signal.SIGKILL
    assert (workdir / workdir_lib.LOCK_FILE).exists()  # left by the killed process
  steps = sorted(int(n) for n in os.listdir(workdir / "checkpoints") if n.isdigit())
  assert steps and 20 <= steps[-1] < TOTAL
  r = _run(workdir, cache)
  assert r.returncode == 0, r.stderr[-3000:]
  assert f"resumed from step {steps[-1]}" in r.stdout
  if sig == signal.SIGKILL:
    assert f"taking over the stale lock of {workdir}: PID {proc.pid}" in r.stderr
  assert not (workdir / workdir_lib.LOCK_FILE).exists()
  assert _results(workdir) == _results(reference)
  rows = lambda w: writers.read_metrics(str(w))  # noqa: E731
  assert rows(workdir) == rows(reference)  # every logged value, bit for bit
  history = workdir_lib.read_history(str(workdir))
  assert [h["event"] for h in history] == ["start", "resume"]

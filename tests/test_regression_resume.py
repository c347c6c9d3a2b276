"""A pose-regression run killed (SIGKILL), then stopped by SIGTERM, then by Ctrl-C's SIGINT
part-way, each time started again with the same command, ends as a run left alone: the same
results.json (apart from its timings and machine) and the same logged metrics at every step. A
stop saves a checkpoint, says how to resume, exits 0 and leaves no lock; a killed run's lock is
taken over.

Each run is a separate process (`python -m camrep.regression` through
tests/regression_resume_script.py, which slows its steps so that the signal lands between two
checkpoints), as a user would run it; the signals are one chain in one workdir, made once for
the module's tests, each of which checks its own link.
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


def _checkpoints(workdir) -> list[int]:
  return sorted(int(n) for n in os.listdir(workdir / "checkpoints") if n.isdigit())


@pytest.fixture(scope="module")
def chain(tmp_path_factory, cache):
  """One workdir through every signal, each link a process: killed (SIGKILL) at step 26 or
  later, started again and stopped by SIGTERM at 36 or later, again and stopped by SIGINT at 46
  or later, again to the end. {link: {"code", "out", "err", "pid", "locked" (its lock file left),
  "checkpoints" after it}} and the workdir."""
  workdir = tmp_path_factory.mktemp("chain") / "w"
  links = {}
  for sig, step in ((signal.SIGKILL, 26), (signal.SIGTERM, 36), (signal.SIGINT, 46)):
    proc = _start(workdir, cache)
    _wait_for_step(proc, workdir, step)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=300)
    links[sig.name] = dict(
      code=proc.returncode,
      out=out,
      err=err,
      pid=proc.pid,
      locked=(workdir / workdir_lib.LOCK_FILE).exists(),
      checkpoints=_checkpoints(workdir),
    )
  r = _run(workdir, cache)
  links["end"] = dict(code=r.returncode, out=r.stdout, err=r.stderr, pid=None)
  return {"workdir": workdir, "links": links}


def test_a_killed_regression_leaves_its_lock_and_the_next_start_takes_it_over(chain):
  kill, after = chain["links"]["SIGKILL"], chain["links"]["SIGTERM"]
  assert kill["code"] == -signal.SIGKILL, kill["err"][-3000:]
  assert kill["locked"]  # left by the killed process
  assert kill["checkpoints"] and 20 <= kill["checkpoints"][-1] < TOTAL
  assert f"taking over the stale lock of {chain['workdir']}: PID {kill['pid']}" in after["err"]
  assert f"resumed from step {kill['checkpoints'][-1]}" in after["out"]


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_stopped_regression_saves_says_how_to_resume_and_the_same_command_resumes(chain, sig):
  """SIGTERM, or Ctrl-C (SIGINT): saved and stopped alike, exit 0, no lock, no results.json."""
  names = list(chain["links"])
  link, after = chain["links"][sig], chain["links"][names[names.index(sig) + 1]]
  assert link["code"] == 0, link["err"][-3000:]
  line = [x for x in link["out"].splitlines() if f"on {sig}" in x]
  assert line and "checkpoint saved" in line[0] and "run the same command to resume" in line[0]
  assert not link["locked"]
  stop = link["checkpoints"][-1]
  assert f"stopping at step {stop} on {sig}" in line[0] and stop < TOTAL
  assert f"resumed from step {stop}" in after["out"]


def test_the_regression_through_every_signal_ends_as_the_run_left_alone(chain, reference):
  workdir = chain["workdir"]
  end = chain["links"]["end"]
  assert end["code"] == 0, end["err"][-3000:]
  assert not (workdir / workdir_lib.LOCK_FILE).exists()
  assert _results(workdir) == _results(reference)
  rows = lambda w: writers.read_metrics(str(w))  # noqa: E731
  assert rows(workdir) == rows(reference)  # every logged value, bit for bit
  history = workdir_lib.read_history(str(workdir))
  assert [h["event"] for h in history] == ["start", "resume", "resume", "resume"]

"""Faults at the run frame (camrep.runtime.frame) and the tools around it: each ends in exit 2
with one `error:` line, decided before anything is written (or leaving a workdir the next start
accepts), and never leaves a stale lock. A step count beyond what the train state counts; a
metrics.jsonl line without "step"; a disk that fills while logging; two evaluations of one
workdir at once (the second waits for the first); the coordinator wait, which says how long it
has waited; a regression from a view-synthesis run that is not complete.
"""

from __future__ import annotations

import errno
import json
import os
import pathlib
import shutil
import socket
import subprocess
import sys
import time

import pytest
from absl import flags

from camrep.configs import gqn
from camrep.configs import regression as regression_config
from camrep.regression import driver
from camrep.runtime import cli, runconfig, session, writers
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import train
from tests.utils import snapshot

ROOT = pathlib.Path(__file__).resolve().parents[1]

# Refusals, locks and errors, not numbers: compile as the subprocesses (`_env`) and the shared
# smoke run do, so that the persistent cache serves their programs to each other.
pytestmark = pytest.mark.usefixtures("fast_compile")


def _assert_one_error(err: str, *fragments: str) -> str:
  assert "Traceback" not in err, err[-3000:]
  lines = [line for line in err.splitlines() if line.startswith("error: ")]
  assert len(lines) == 1, err[-3000:]
  for f in fragments:
    assert f in lines[0], (f, lines[0])
  return lines[0]


def _env():
  return {**os.environ, "JAX_DISABLE_MOST_OPTIMIZATIONS": "1"}


def _train_tool(config):
  def define(fv, argv):
    flags.DEFINE_string("workdir", None, "", flag_values=fv)

  def body(fv):
    train.train_and_evaluate(config, fv.workdir, log=lambda s: None)
    return 0

  return define, body


# --------------------------------------------------------------------------------------------
# Step counts.


def test_a_step_count_beyond_the_train_state_is_refused_before_anything_is_written(tmp_path):
  c = gqn.get_config("smoke")
  c.total_steps = 10**20
  with pytest.raises(runconfig.ConfigError, match=r"total_steps=100000000000000000000: must be an"):
    train.train_and_evaluate(c, str(tmp_path / "w"))
  assert not (tmp_path / "w").exists()
  r = regression_config.get_config("smoke")
  r.total_steps = 2**31
  with pytest.raises(runconfig.ConfigError, match=r"2147483648: must be an integer from 1"):
    driver.run(r, str(tmp_path / "r"))
  assert not (tmp_path / "r").exists()


@pytest.mark.slow
@pytest.mark.parametrize(
  "module,config", [("camrep.main", "gqn"), ("camrep.regression", "regression")]
)
def test_command_line_step_count_beyond_the_train_state(module, config, tmp_path):
  for value in ("100000000000000000000", "10**20"):
    r = subprocess.run(
      [
        sys.executable,
        "-m",
        module,
        f"--config={config}:smoke",
        f"--workdir={tmp_path}/w",
        f"--config.total_steps={value}",
      ],  # fmt: skip
      capture_output=True,
      text=True,
      cwd=ROOT,
      env=_env(),
      timeout=300,
    )
    assert r.returncode == 2, r.stderr[-2000:]
    _assert_one_error(r.stderr, f"--config.total_steps={value}")
    assert not (tmp_path / "w").exists()


# --------------------------------------------------------------------------------------------
# Records.


@pytest.mark.slow
def test_a_metrics_line_without_step_is_refused_by_name_and_changes_nothing(
  gqn_smoke_run, tmp_path, capsys
):
  wd = tmp_path / "w"
  shutil.copytree(gqn_smoke_run, wd)
  path = wd / writers.METRICS_FILE
  lines = path.read_text().splitlines()
  lines.insert(1, '{"train/loss": 1.0}')  # hand-edited, or written by another tool
  path.write_text("\n".join(lines) + "\n")
  before = snapshot(wd)
  c = gqn.get_config("smoke")
  c.total_steps, c.allow_changes = 6, "total_steps"
  assert cli.call(*_train_tool(c), [f"--workdir={wd}"]) == 2
  line = _assert_one_error(capsys.readouterr().err, f"{path}:2:", 'without an integer "step"')
  assert "Remove that line" in line and "nothing was changed" in line
  assert snapshot(wd) == before
  with pytest.raises(writers.MetricsFileError, match=":2: a line without"):
    writers.read_metrics(str(wd))


@pytest.mark.slow
def test_a_full_disk_while_logging_leaves_no_stale_lock(tmp_path, monkeypatch, capsys):
  """A disk that fills while metrics are logged: the write fails, and so does every later
  flush (the writer's close included). One error line, the lock released, no partial
  checkpoint; the next start (with space again) runs."""

  full = []

  def enospc(*args, **kwargs):
    full.append(True)
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

  def once_full(method):  # works until the disk is full, then fails as the write did
    return lambda self, *a, **k: enospc() if full else method(self, *a, **k)

  c = gqn.get_config("smoke")
  c.total_steps = 2
  with monkeypatch.context() as m:
    m.setattr(writers.MetricWriter, "write_scalars", enospc)
    m.setattr(writers.MetricWriter, "flush", once_full(writers.MetricWriter.flush))
    m.setattr(writers.MetricWriter, "close", once_full(writers.MetricWriter.close))
    assert cli.call(*_train_tool(c), [f"--workdir={tmp_path}"]) == 2
  assert full  # the disk filled while logging (the first train scalars)
  _assert_one_error(capsys.readouterr().err, "disk full", "nothing half-written")
  assert not (tmp_path / workdir_lib.LOCK_FILE).exists()
  ckpts = tmp_path / "checkpoints"
  assert not ckpts.exists() or not [n for n in os.listdir(ckpts) if "tmp" in n]
  assert cli.call(*_train_tool(c), [f"--workdir={tmp_path}"]) == 0
  assert session.is_complete(str(tmp_path), 2)


# --------------------------------------------------------------------------------------------
# Concurrent evaluations.


@pytest.mark.slow
def test_two_evaluations_of_one_workdir_run_one_after_the_other(gqn_smoke_run, tmp_path):
  """While one evaluation holds the output directory's lock, a second waits (saying whom for)
  and writes nothing; once the first lets go, the second runs and exits 0."""
  wd = tmp_path / "w"
  shutil.copytree(gqn_smoke_run, wd)
  shutil.rmtree(wd / "eval", ignore_errors=True)
  (wd / "eval").mkdir()
  first = workdir_lib.WorkdirLock(str(wd / "eval"))
  first.acquire()  # the first evaluation, in this process
  proc = subprocess.Popen(
    [sys.executable, "-m", "camrep.synthesis.evaluate", f"--workdir={wd}", "--what=gram"],
    cwd=ROOT,
    env=_env(),
    stdout=subprocess.PIPE,
    stderr=subprocess.STDOUT,
    text=True,
  )
  try:
    seen, deadline = "", time.monotonic() + 300
    while f"waiting for PID {os.getpid()}" not in seen:
      assert proc.poll() is None, proc.stdout.read()
      assert time.monotonic() < deadline, seen
      seen += proc.stdout.readline()
    time.sleep(1.0)
    assert proc.poll() is None  # still waiting
    assert sorted(os.listdir(wd / "eval")) == [workdir_lib.LOCK_FILE]
  finally:
    first.release()
  out, _ = proc.communicate(timeout=600)
  assert proc.returncode == 0, out[-3000:]
  assert (wd / "eval" / "gram.npz").exists() and not (wd / "eval" / workdir_lib.LOCK_FILE).exists()


# --------------------------------------------------------------------------------------------
# The coordinator wait.


@pytest.mark.slow
def test_the_coordinator_wait_says_how_long_it_has_waited(tmp_path):
  with socket.socket() as s:  # a port nothing listens on
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
  r = subprocess.run(
    [
      sys.executable,
      "-m",
      "camrep.main",
      "--config=configs/gqn.py:smoke",
      f"--workdir={tmp_path}/w",
      f"--coordinator_address=127.0.0.1:{port}",
      "--num_processes=2",
      "--process_id=1",
      "--coordinator_timeout=4",
    ],  # fmt: skip
    capture_output=True,
    text=True,
    cwd=ROOT,
    env=_env(),
    timeout=120,
  )
  assert r.returncode == 2, r.stderr[-2000:]
  _assert_one_error(r.stderr, f"could not join the jax.distributed job at 127.0.0.1:{port}")
  where = f"the jax.distributed job at 127.0.0.1:{port} (process 1 of 2)"
  assert f"joining {where.replace(' (process', ' as process').rstrip(')')}" in r.stdout
  waits = [x for x in r.stdout.splitlines() if x.startswith(f"waiting for {where}")]
  assert len(waits) >= 2 and waits[0].endswith("of --coordinator_timeout=4 s"), r.stdout
  assert not (tmp_path / "w").exists()


# --------------------------------------------------------------------------------------------
# Regression from a view-synthesis run that is not complete.


def _regression(syn_workdir, **kw):
  c = regression_config.get_config("gqn,smoke")
  c.representation, c.synthesis_workdir = "ours", str(syn_workdir)
  for k, v in kw.items():
    c[k] = v
  return c


@pytest.mark.slow
def test_regression_refuses_a_synthesis_run_that_is_not_complete(gqn_smoke_run, tmp_path):
  cases = {}
  for name in ("running", "non_finite", "incomplete", "no_final"):
    wd = tmp_path / name
    shutil.copytree(gqn_smoke_run, wd)
    cases[name] = wd
  final = session.read_final(gqn_smoke_run)
  (cases["running"] / workdir_lib.LOCK_FILE).write_text(
    json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "started": "now"})
  )
  (cases["non_finite"] / session.FINAL_FILE).write_text(
    json.dumps({**final, "complete": False, "stopped": "non-finite", "reason": "NaN at step 3"})
  )
  (cases["incomplete"] / session.FINAL_FILE).write_text(json.dumps({**final, "complete": False}))
  os.remove(cases["no_final"] / session.FINAL_FILE)
  expect = {
    "running": f"is still training (PID {os.getpid()}",
    "non_finite": "is stopped on non-finite values (NaN at step 3)",
    "incomplete": '"complete": false',
    "no_final": "has no final_metrics.json",
  }
  for name, wd in cases.items():
    out = tmp_path / f"reg_{name}"
    with pytest.raises(runconfig.ConfigError, match="allow_incomplete_synthesis=True") as e:
      driver.run(_regression(wd), str(out), log=lambda s: None)
    assert expect[name] in str(e.value), str(e.value)
    assert not out.exists()  # refused before anything was written
  # Allowed: used, and recorded in results.json.
  lines = []
  results = driver.run(
    _regression(cases["non_finite"], allow_incomplete_synthesis=True),
    str(tmp_path / "allowed"),
    log=lines.append,
  )
  info = results["representation_params"]
  assert info["synthesis_incomplete"] == "stopped on non-finite values (NaN at step 3)"
  assert any(x.startswith("warning: synthesis_workdir") for x in lines)

"""Multi-process training with jax.distributed: 2 processes on localhost, CPU
collectives (gloo), each reading its own shard of the scenes, train exactly as 1 process that
holds the same global batch on 2 devices (tests/multiprocess_reference.py): the same logged
losses and the same parameters in the final checkpoint, which the 2 processes saved together.
"""

from __future__ import annotations

import json
import os
import pathlib
import signal
import socket
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from camrep.runtime import writers
from camrep.synthesis import restore

pytestmark = pytest.mark.slow

ROOT = pathlib.Path(__file__).resolve().parents[1]
STEPS = 6


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("localhost", 0))
    return s.getsockname()[1]


def _env():
  env = dict(os.environ)
  env.pop("XLA_FLAGS", None)
  env["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"
  return env


def _start_two(workdir, *overrides) -> list[subprocess.Popen]:
  port = _free_port()
  flags = [
    "--config=configs/gqn.py:smoke",
    *overrides,
    f"--workdir={workdir}",
    f"--coordinator_address=localhost:{port}",
    "--num_processes=2",
  ]
  return [
    subprocess.Popen(
      [sys.executable, "-m", "camrep.main", *flags, f"--process_id={i}"],
      cwd=ROOT,
      env=_env(),
      stdout=subprocess.PIPE,
      stderr=subprocess.STDOUT,
      text=True,
    )
    for i in range(2)
  ]


def test_two_processes_train_as_one(tmp_path):
  workdir = tmp_path / "run"
  procs = _start_two(
    workdir,
    f"--config.total_steps={STEPS}",
    "--config.ckpt_every_steps=3",
    "--config.log_every_steps=1",
  )
  ref = tmp_path / "ref.npz"
  r = subprocess.run(
    [sys.executable, "-m", "tests.multiprocess_reference", str(STEPS), str(ref)],
    cwd=ROOT,
    env=_env(),
    capture_output=True,
    text=True,
    timeout=600,
  )
  outs = [p.communicate(timeout=600)[0] for p in procs]
  for p, out in zip(procs, outs, strict=True):
    assert p.returncode == 0, out[-3000:]
  assert r.returncode == 0, r.stderr[-3000:]
  assert "process 0/2" in outs[0] and "process 1/2" in outs[1]

  want = np.load(ref)
  rows = [x for x in writers.read_metrics(str(workdir)) if "train/loss" in x]
  assert [x["step"] for x in rows] == list(range(1, STEPS + 1))  # one writer: process 0
  for row in rows:
    for key in ("train/loss", "train/rec", "train/rot_xy", "train/grad_norm_model"):
      assert row[key] == float(want[f"metric/{row['step']}/{key}"]), (row["step"], key)
  assert sorted(os.listdir(workdir / "checkpoints")) == ["3", "6"]
  run = restore.load_run(str(workdir))
  assert run.step == STEPS
  flat = jax.tree_util.tree_flatten_with_path(run.params)[0]
  for path, value in flat:
    np.testing.assert_array_equal(np.asarray(value), want["param/" + jax.tree_util.keystr(path)])


def test_sigterm_to_one_process_stops_both_with_a_checkpoint(tmp_path):
  workdir = tmp_path / "run"
  procs = _start_two(
    workdir,
    "--config.total_steps=100000",
    "--config.ckpt_every_steps=100000",
    "--config.eval_every_steps=100000",
    "--config.log_every_steps=1",
  )
  path = workdir / "metrics.jsonl"
  deadline = time.monotonic() + 300
  while not (path.exists() and any('"train/loss"' in x for x in path.read_text().splitlines())):
    assert time.monotonic() < deadline and all(p.poll() is None for p in procs)
    time.sleep(0.1)
  procs[1].send_signal(signal.SIGTERM)  # the other process is not signalled
  outs = [p.communicate(timeout=300)[0] for p in procs]
  for p, out in zip(procs, outs, strict=True):
    assert p.returncode == 0, out[-3000:]
    assert "checkpoint saved" in out
  steps = os.listdir(workdir / "checkpoints")
  assert len(steps) == 1 and int(steps[0]) < 100000
  last = max(json.loads(x)["step"] for x in path.read_text().splitlines())
  assert int(steps[0]) == last

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
from tests.utils import one_device_env

pytestmark = pytest.mark.slow

ROOT = pathlib.Path(__file__).resolve().parents[1]
STEPS = 6


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("localhost", 0))
    return s.getsockname()[1]


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
      env=one_device_env(),
      stdout=subprocess.PIPE,
      stderr=subprocess.STDOUT,
      text=True,
    )
    for i in range(2)
  ]


def test_two_processes_train_as_one_and_sigterm_to_one_stops_both_with_a_checkpoint(tmp_path):
  """One 2-process run (checkpoints every 3 steps, evaluation at step 4) against the 1-process
  reference for its first STEPS steps; once it has logged them, SIGTERM to process 1 alone stops
  both, each saving the last step's checkpoint and exiting 0."""
  workdir = tmp_path / "run"
  procs = _start_two(
    workdir,
    "--config.total_steps=100000",
    "--config.ckpt_every_steps=3",
    "--config.max_to_keep=100000",
    "--config.log_every_steps=1",
  )
  ref = tmp_path / "ref.npz"
  reference = subprocess.Popen(
    [sys.executable, "-m", "tests.multiprocess_reference", str(STEPS), str(ref)],
    cwd=ROOT,
    env=one_device_env(),
    stdout=subprocess.PIPE,
    stderr=subprocess.STDOUT,
    text=True,
  )
  path = workdir / "metrics.jsonl"

  def logged_steps() -> list[int]:
    if not path.exists():
      return []
    return [json.loads(x)["step"] for x in path.read_text().splitlines() if '"train/loss"' in x]

  deadline = time.monotonic() + 600
  while max(logged_steps(), default=0) < STEPS:
    alive = all(p.poll() is None for p in procs)
    assert time.monotonic() < deadline and alive, [p.communicate()[0][-3000:] for p in procs]
    time.sleep(0.1)
  procs[1].send_signal(signal.SIGTERM)  # the other process is not signalled
  outs = [p.communicate(timeout=300)[0] for p in procs]
  for p, out in zip(procs, outs, strict=True):
    assert p.returncode == 0, out[-3000:]
    assert "checkpoint saved" in out
  assert "process 0/2" in outs[0] and "process 1/2" in outs[1]
  out = reference.communicate(timeout=600)[0]
  assert reference.returncode == 0, out[-3000:]

  # Stopped by the signal, not by the step count; the stop step's checkpoint is the last one.
  rows = [x for x in writers.read_metrics(str(workdir)) if "train/loss" in x]
  last = rows[-1]["step"]
  assert f"stopping at step {last} on " in outs[0]
  assert [x["step"] for x in rows] == list(range(1, last + 1))  # one writer: process 0
  assert STEPS <= last < 100000
  evals = [x["step"] for x in writers.read_metrics(str(workdir)) if "eval/psnr" in x]
  assert evals and evals[0] == 4, evals  # the 2 processes evaluate together, without a hang
  saved = sorted(int(s) for s in os.listdir(workdir / "checkpoints"))
  assert saved == sorted({*range(3, last + 1, 3), last})

  want = np.load(ref)
  for row in rows[:STEPS]:
    for key in ("train/loss", "train/rec", "train/rot_xy", "train/grad_norm_model"):
      assert row[key] == float(want[f"metric/{row['step']}/{key}"]), (row["step"], key)
  run = restore.load_run(str(workdir), step=STEPS)  # saved by the 2 processes together
  assert run.step == STEPS
  flat = jax.tree_util.tree_flatten_with_path(run.params)[0]
  for path_, value in flat:
    np.testing.assert_array_equal(np.asarray(value), want["param/" + jax.tree_util.keystr(path_)])

"""A workdir tells the truth about the run in it: resume compares the config with the
stored one, a refused start writes nothing, allowed changes are recorded with their step, and one
writer holds a workdir at a time (stale locks are taken over). Concurrent starts of real
processes: tests/test_resume.py::test_second_start_on_a_live_workdir_is_refused."""

from __future__ import annotations

import json
import math
import os
import pathlib
import shutil
import socket
import subprocess
import sys

import jax
import pytest

from camrep.configs import gqn, regression, shapenet_car
from camrep.regression import config_schema as regression_schema
from camrep.runtime import runconfig, writers
from camrep.runtime import workdir as workdir_lib
from camrep.runtime.checkpoint import CheckpointError
from camrep.synthesis import config_schema as synthesis_schema
from camrep.synthesis import evaluate as ev
from camrep.synthesis import train
from tests.utils import snapshot

pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]

ROOT = pathlib.Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------------------
# Config changes (no training)


def test_check_changes_names_refused_and_unflagged_fields():
  old = gqn.get_config("smoke")
  new = gqn.get_config("smoke")
  new.model.width = 0.0625
  new.optax.lr_model = 0.5
  with pytest.raises(runconfig.ConfigError) as e:
    runconfig.check_changes(old, new, schema=synthesis_schema.SCHEMA, workdir="W")
  msg = str(e.value)
  assert "model.width: 0.03125 -> 0.0625" in msg and "never allowed" in msg
  assert "optax.lr_model: 0.0001 -> 0.5" in msg and "new --workdir" in msg


def test_check_changes_allows_named_resumable_fields():
  old = gqn.get_config("smoke")
  new = gqn.get_config("smoke")
  new.optax.lr_model, new.total_steps, new.evals.num_scenes = 0.5, 8, 3
  new.data.num_threads = 3  # free: speed only
  with pytest.raises(runconfig.ConfigError, match="allow_changes=evals.num_scenes,optax.lr_model"):
    runconfig.check_changes(old, new, schema=synthesis_schema.SCHEMA, workdir="W")
  new.allow_changes = "optax.lr_model, total_steps,evals"  # a section allows its fields
  got = runconfig.check_changes(old, new, schema=synthesis_schema.SCHEMA, workdir="W")
  assert got == {
    "data.num_threads": (0, 3),
    "evals.num_scenes": (4, 3),
    "optax.lr_model": (0.0001, 0.5),
    "total_steps": (4, 8),
  }
  # Naming a shape-affecting field does not make it resumable.
  new.model.width, new.allow_changes = 0.0625, "model.width"
  with pytest.raises(runconfig.ConfigError, match="model.width"):
    runconfig.check_changes(old, new, schema=synthesis_schema.SCHEMA, workdir="W")
  # A field the stored config lacks (camrep gained it later) is recorded, not refused.
  older = gqn.get_config("smoke")
  del older.model["gamma_init_one"]
  got = runconfig.check_changes(older, gqn.get_config("smoke"), schema={}, workdir="W")
  assert got == {"model.gamma_init_one": (None, False)}
  # A stage that starts over (regression) may change anything it names: a FIXED field then
  # starts the run over (`fixed_changes`), a MAY_CHANGE one resumes.
  r_old, r_new = regression.get_config("smoke"), regression.get_config("smoke")
  r_new.representation, r_new.allow_changes = "euler", "representation"
  schema = regression_schema.SCHEMA
  got = runconfig.check_changes(r_old, r_new, schema=schema, workdir="W", restart=True)
  assert got == {"representation": ("quat", "euler")}
  assert runconfig.fixed_changes(r_old, r_new, schema=schema) == ["representation"]
  r_new.allow_changes = ""
  with pytest.raises(runconfig.ConfigError, match="the run then starts over from step 0"):
    runconfig.check_changes(r_old, r_new, schema=schema, workdir="W", restart=True)
  r_new = regression.get_config("smoke")
  r_new.total_steps, r_new.allow_changes = 9, "total_steps"
  runconfig.check_changes(r_old, r_new, schema=schema, workdir="W", restart=True)
  assert runconfig.fixed_changes(r_old, r_new, schema=schema) == []


# ---------------------------------------------------------------------------------------------
# The lock


def test_lock_refuses_a_live_holder_and_names_it(tmp_path):
  first = workdir_lib.WorkdirLock(str(tmp_path))
  first.acquire()
  held = json.loads((tmp_path / workdir_lib.LOCK_FILE).read_text())
  assert held["pid"] == os.getpid() and held["host"] == socket.gethostname()
  with pytest.raises(workdir_lib.WorkdirError, match=f"PID {os.getpid()} on"):
    workdir_lib.WorkdirLock(str(tmp_path)).acquire()
  first.release()
  assert not (tmp_path / workdir_lib.LOCK_FILE).exists()
  # Another host's lock cannot be checked: refused, with the way out.
  other = {"pid": 1, "host": "elsewhere", "started": "then"}
  (tmp_path / workdir_lib.LOCK_FILE).write_text(json.dumps(other))
  with pytest.raises(workdir_lib.WorkdirError, match="PID 1 on elsewhere.*delete the lock file"):
    workdir_lib.WorkdirLock(str(tmp_path)).acquire()


def test_a_waiter_takes_a_lock_let_go_between_its_attempt_and_its_look(tmp_path):
  """A waiter whose attempt fails, but whose holder lets go before it looks who holds the lock,
  takes the lock (it once gave up with "in use by another run": seen under load, when an
  evaluation waited for another); without a wait it still refuses at once."""
  first = workdir_lib.WorkdirLock(str(tmp_path))
  first.acquire()
  waiter = workdir_lib.WorkdirLock(str(tmp_path))
  look = waiter.live_holder

  def released_before_the_look():
    first.release()
    return look()

  waiter.live_holder = released_before_the_look
  lines = []
  waiter.acquire(wait=math.inf, log=lines.append, poll=0.01)
  assert waiter.held and lines == []
  assert json.loads((tmp_path / workdir_lib.LOCK_FILE).read_text())["pid"] == os.getpid()
  waiter.release()
  first.acquire()
  with pytest.raises(workdir_lib.WorkdirError, match="in use by another run"):
    workdir_lib.WorkdirLock(str(tmp_path)).acquire(wait=0.0)
  first.release()


def test_stale_lock_is_taken_over_with_a_warning(tmp_path):
  gone = subprocess.Popen([sys.executable, "-c", "pass"])
  gone.wait()
  stale = {"pid": gone.pid, "host": socket.gethostname(), "started": "earlier"}
  (tmp_path / workdir_lib.LOCK_FILE).write_text(json.dumps(stale))
  lock = workdir_lib.WorkdirLock(str(tmp_path))
  with pytest.warns(workdir_lib.StaleLockWarning, match=f"PID {gone.pid}.*no longer runs"):
    lock.acquire()
  assert json.loads((tmp_path / workdir_lib.LOCK_FILE).read_text())["pid"] == os.getpid()
  lock.release()


# ---------------------------------------------------------------------------------------------
# A real workdir


@pytest.fixture(scope="module")
def trained(tmp_path_factory, gqn_smoke_run):
  """A finished 4-step GQN :smoke run: this module's copy of the session's shared one."""
  wd = str(tmp_path_factory.mktemp("trained") / "w")
  shutil.copytree(gqn_smoke_run, wd)
  return wd


def test_fresh_start_is_recorded_and_releases_its_lock(trained):
  assert not os.path.exists(os.path.join(trained, workdir_lib.LOCK_FILE))
  (start,) = workdir_lib.read_history(trained)
  assert start["step"] == 0 and start["event"] == "start" and start["changes"] == {}


def test_shape_change_is_refused_and_writes_nothing(trained):
  """(a) at the library level; the command line's exit status is tested below."""
  before = snapshot(trained)
  c = gqn.get_config("smoke")
  c.model.width = 0.0625
  with pytest.raises(runconfig.ConfigError, match=r"model\.width: 0\.03125 -> 0\.0625"):
    train.train_and_evaluate(c, trained)
  assert snapshot(trained) == before


def test_another_config_file_is_refused_and_writes_nothing(trained):
  """(c) a car config into a GQN workdir: refused before config.json is touched."""
  before = snapshot(trained)
  with pytest.raises(runconfig.ConfigError, match=r"data\.source: 'rooms' -> 'object'"):
    train.train_and_evaluate(shapenet_car.get_config("smoke"), trained)
  assert snapshot(trained) == before


def test_command_line_refusal_is_exit_2_without_traceback(trained):
  before = snapshot(trained)
  r = subprocess.run(
    [
      sys.executable,
      "-m",
      "camrep.main",
      "--config=configs/gqn.py:smoke",
      f"--workdir={trained}",
      "--config.model.width=0.0625",
    ],
    cwd=ROOT,
    capture_output=True,
    text=True,
    timeout=300,
  )
  assert r.returncode == 2, r.stderr[-2000:]
  assert "model.width" in r.stderr and "Traceback" not in r.stderr
  assert snapshot(trained) == before


def test_allowed_change_is_recorded_with_its_step(trained, tmp_path):
  """(b) lr and total_steps changed at step 4 with allow_changes: history, metrics, final."""
  wd = str(tmp_path / "w")
  shutil.copytree(trained, wd)
  c = gqn.get_config("smoke")
  c.optax.lr_model, c.total_steps = 5e-4, 6
  with pytest.raises(runconfig.ConfigError, match="allow_changes=optax.lr_model,total_steps"):
    train.train_and_evaluate(c, wd)
  c.allow_changes = "optax.lr_model,total_steps"
  train.train_and_evaluate(c, wd)
  start, resume = workdir_lib.read_history(wd)
  assert resume["step"] == 4 and resume["event"] == "resume"
  assert resume["changes"] == {"optax.lr_model": [0.0001, 0.0005], "total_steps": [4, 6]}
  marks = [r for r in writers.read_metrics(wd) if "resume/config_changes" in r]
  assert marks == [{"step": 4, "resume/config_changes": 2.0}]
  with open(os.path.join(wd, "final_metrics.json")) as f:
    final = json.load(f)
  assert final["step"] == 6 and final["config_changes"] == [
    {"step": 4, "changes": resume["changes"]}
  ]
  assert json.loads(open(os.path.join(wd, "config.json")).read())["optax"]["lr_model"] == 5e-4


def test_a_workdir_written_with_the_retired_fields_resumes(trained, tmp_path):
  """A GQN workdir whose config.json still has the ConvDRAW fields of the old base config
  resumes with today's config (which lacks them); the history records them (old -> None) and
  config.json becomes today's config."""
  wd = tmp_path / "w"
  shutil.copytree(trained, wd)
  stored = json.loads((wd / "config.json").read_text())
  assert "draw_steps" not in stored["model"]
  for field, value in synthesis_schema.RETIRED.items():
    section, name = field.split(".")
    stored[section][name] = value
  (wd / "config.json").write_text(json.dumps(stored, indent=2))
  c = gqn.get_config("smoke")
  c.total_steps, c.allow_changes = 6, "total_steps"
  train.train_and_evaluate(c, str(wd))
  start, resume = workdir_lib.read_history(str(wd))
  assert resume["step"] == 4 and resume["event"] == "resume"
  assert resume["changes"] == {
    "total_steps": [4, 6],
    **{f: [v, None] for f, v in synthesis_schema.RETIRED.items()},
  }
  assert json.loads((wd / "final_metrics.json").read_text())["step"] == 6
  assert "draw_steps" not in json.loads((wd / "config.json").read_text())["model"]


def test_failed_start_in_a_new_workdir_leaves_nothing(tmp_path):
  c = gqn.get_config("smoke")
  c.data.in_memory, c.data.dir = False, str(tmp_path / "no_such_data")
  wd = tmp_path / "w"
  with pytest.raises(Exception):  # noqa: B017 - whatever the data error is, nothing is left
    train.train_and_evaluate(c, str(wd))
  assert not wd.exists()


def test_evaluate_refuses_a_config_that_does_not_fit_the_checkpoints(trained, tmp_path, capsys):
  wd = tmp_path / "w"
  shutil.copytree(trained, wd)
  cfg = json.loads((wd / "config.json").read_text())
  cfg["model"]["width"] = 0.0625  # config.json edited by hand
  (wd / "config.json").write_text(json.dumps(cfg))
  assert ev.main(["--workdir", str(wd), "--what", "gram"]) == 2
  err = capsys.readouterr().err
  assert "other shapes than the config builds" in err and "Traceback" not in err
  with pytest.raises(CheckpointError):
    from camrep.synthesis import restore

    restore.load_run(str(wd))


def test_command_line_on_a_held_workdir_is_exit_2_naming_the_holder(trained):
  """The lock names this (live) test process: `camrep.main` refuses, writes nothing."""
  holder = {"pid": os.getpid(), "host": socket.gethostname(), "started": "now", "argv": []}
  lock = pathlib.Path(trained) / workdir_lib.LOCK_FILE
  lock.write_text(json.dumps(holder))
  try:
    before = snapshot(trained)
    r = subprocess.run(
      [
        sys.executable,
        "-m",
        "camrep.main",
        "--config=configs/gqn.py:smoke",
        f"--workdir={trained}",
      ],
      cwd=ROOT,
      capture_output=True,
      text=True,
      timeout=300,
    )
    assert r.returncode == 2, r.stderr[-2000:]
    assert f"in use by another run (PID {os.getpid()} on" in r.stderr
    assert "Traceback" not in r.stderr
    assert snapshot(trained) == before
  finally:
    lock.unlink()


def test_machine_names_the_backend_the_devices_and_the_cpu():
  """A run's records say what ran it: runs of one table may come from a GPU machine and this CPU."""
  m = workdir_lib.machine()
  assert m["backend"] == jax.default_backend() and m["devices"] == len(jax.devices())
  assert m["device_kind"] == jax.devices()[0].device_kind and m["jax"] == jax.__version__
  assert isinstance(m["cpu"], str) and m["cpu"] and m["cpu_count"] >= 1
  json.dumps(m)  # recorded in JSON files

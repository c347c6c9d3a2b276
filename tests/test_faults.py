"""Red-team faults of the command lines: each
user mistake or resource fault ends in exit 2 with one `error:` line and no traceback, and leaves
the workdir or dataset as it was (or in a state the next start accepts).

The sweep over every `--config.` field of configs/gqn.py:smoke, configs/gqn_convdraw.py:smoke and
configs/regression.py:smoke runs in this process through `camrep.runtime.cli.call` (the same flag
parsing, validation and exit codes as `python -m`); a handful of real subprocesses check that the
command lines behave alike.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import pathlib
import shutil
import socket
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest
from absl import flags
from ml_collections import config_flags

from camrep.configs import gqn, shapenet_car
from camrep.data import prepare
from camrep.regression import config_schema as regression_schema
from camrep.runtime import checkpoint as ckpt_lib
from camrep.runtime import cli, runconfig
from camrep.runtime import frame as frame_lib
from camrep.runtime import validate as V
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import config_schema as synthesis_schema
from camrep.synthesis import evaluate as ev
from camrep.synthesis import train

ROOT = pathlib.Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]


# --------------------------------------------------------------------------------------------
# Helpers.


def _snapshot(path) -> dict[str, str] | None:
  """{relative path: sha256} of every file under `path` (None: no such directory)."""
  path = pathlib.Path(path)
  if not path.exists():
    return None
  return {
    str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
    for p in sorted(path.rglob("*"))
    if p.is_file()
  }


def _assert_one_error(err: str, *fragments: str) -> str:
  """The output holds exactly one `error:` line, which contains every fragment; no traceback."""
  assert "Traceback" not in err, err[-3000:]
  lines = [line for line in err.splitlines() if line.startswith("error: ")]
  assert len(lines) == 1, err[-3000:]
  for f in fragments:
    assert f in lines[0], (f, lines[0])
  return lines[0]


def _run(*args: str, timeout: int = 300, env: dict | None = None) -> subprocess.CompletedProcess:
  return subprocess.run(
    [sys.executable, *args],
    capture_output=True,
    text=True,
    cwd=ROOT,
    timeout=timeout,
    env={**os.environ, "JAX_DISABLE_MOST_OPTIMIZATIONS": "1", **(env or {})},
  )


def _config_tool(schema):
  """A command line that only loads `--config` (with its overrides) and validates it, as
  camrep.main / camrep.regression do before anything else."""

  def define(fv, argv):
    config_flags.DEFINE_config_file(
      "config", None, "config", flag_values=fv, lock_config=True, sys_argv=list(argv)
    )

  def body(fv):
    schema.validate(fv.config, overridden=cli.overridden(fv))
    return 0

  return define, body


def _flag_text(value) -> str:
  if isinstance(value, tuple):
    return ",".join(str(v) for v in value)
  return str(value)


def _sweep_cases(config, schema, free_text):
  """(path, value) pairs that must be refused, generated from the config itself: a wrong type
  for every non-string field, and the values its rule refuses (a wrong enum, a non-positive or
  out-of-range number, a missing path)."""
  cases = []
  assert V.unchecked(config, schema) == [], "fields without a rule"
  for path, value in V.leaves(config).items():
    field = V.field_of(schema, path)
    if isinstance(value, dict):  # a section (family overrides), checked by the family
      assert field.rule.kind == "section", path
      continue
    if value is None or isinstance(value, (bool, int, float, tuple)):
      cases.append((path, "abc"))  # no int, float, bool; a tuple of one string
    if isinstance(value, (int, float)) and not isinstance(value, bool):
      assert field.rule.bad_values(), f"{path}: a number without a range rule"
    if isinstance(value, str) and field.rule.kind == "any":
      assert path in free_text, f"{path}: a string without an enum or path rule"
    cases += [(path, _flag_text(v)) for v in field.rule.bad_values()]
  return cases


# --------------------------------------------------------------------------------------------
# The sweep (in this process).

_SWEEPS = {
  "gqn": ("configs/gqn.py:smoke", synthesis_schema, {"allow_changes", "data.preset"}),
  "gqn_convdraw": (
    "configs/gqn_convdraw.py:smoke",
    synthesis_schema,
    {"allow_changes", "data.preset"},
  ),
  "lvsm": ("configs/lvsm.py:smoke", synthesis_schema, {"allow_changes", "data.preset"}),
  "regression": (
    "configs/regression.py:smoke",
    regression_schema,
    {"allow_changes", "data.preset", "data.cache_dir", "data.dataset_config", "evals.extra_splits"},
  ),
}


@pytest.mark.parametrize("name", sorted(_SWEEPS))
def test_every_config_field_refuses_a_wrong_value_with_exit_2(name, capsys):
  config_arg, schema, free_text = _SWEEPS[name]
  define, body = _config_tool(schema)
  assert cli.call(define, body, [f"--config={config_arg}"]) == 0  # the config itself is fine
  config = _config_from(config_arg)
  cases = _sweep_cases(config, schema.SCHEMA, free_text)
  assert len(cases) > 60
  for path, value in cases:
    flag = f"--config.{path}={value}"
    assert cli.call(define, body, [f"--config={config_arg}", flag]) == 2, flag
    _assert_one_error(capsys.readouterr().err, f"--config.{path}=")


def _config_from(config_arg: str):
  fv = flags.FlagValues()
  config_flags.DEFINE_config_file("config", None, "", flag_values=fv, sys_argv=["p"])
  fv(["p", f"--config={config_arg}"])
  return fv.config


def test_fields_the_run_does_not_use_are_refused_when_set(capsys):
  define, body = _config_tool(synthesis_schema)
  argv = ["--config=configs/gqn.py:smoke", "--config.model.image_size=128"]
  assert cli.call(define, body, argv) == 2
  _assert_one_error(capsys.readouterr().err, "this run does not use config.model.image_size")
  # GQN's generator's fields are configs/gqn_convdraw.py's only: on the decoder's config the
  # flag names an unknown field.
  argv = ["--config=configs/gqn.py:smoke", "--config.model.draw_steps=3"]
  assert cli.call(define, body, argv) == 2
  _assert_one_error(capsys.readouterr().err, "--config.model.draw_steps=3", "no field")
  assert cli.call(define, body, ["--config=configs/gqn_convdraw.py:smoke", argv[1]]) == 0
  # The same value from a config file (not the command line) is the config's business.
  config = gqn.get_config("smoke")
  config.model.draw_steps = 3  # a user's file that adds it: the GQN decoder ignores it
  synthesis_schema.validate(config)
  with pytest.raises(runconfig.ConfigError, match="model.kind='convdraw'"):
    synthesis_schema.validate(config, overridden={"model.draw_steps"})
  define, body = _config_tool(regression_schema)
  # A regression config holds one setting's fields: another setting's is an unknown field, and
  # the setting itself is the config argument's.
  argv = ["--config=configs/regression.py:smoke", "--config.data.n_context=3"]
  assert cli.call(define, body, argv) == 2
  _assert_one_error(capsys.readouterr().err, "--config.data.n_context=3", "no field")
  argv = ["--config=configs/regression.py:smoke", "--config.setting=gqn"]
  assert cli.call(define, body, argv) == 2
  _assert_one_error(capsys.readouterr().err, "--config=configs/regression.py:gqn")


def _fake_prepared(root: pathlib.Path, name: str, config: str, shape, poses=None) -> None:
  from camrep.data import sources

  d = root / name / config / "1.0.0"
  d.mkdir(parents=True)
  (d / "dataset_info.json").write_text("{}")
  meta = {"image_shape": list(shape), "pose_names": list(poses or sources.get(name).pose_names)}
  (d / "camrep_source.json").write_text(json.dumps(meta))


def test_model_image_size_is_checked_against_the_data_before_anything_runs(tmp_path):
  # The procedural family's own size.
  config = shapenet_car.get_config("smoke")
  config.model.image_size = 128
  with pytest.raises(runconfig.ConfigError, match="'object' family .* has 64x64 images"):
    synthesis_schema.validate(config)
  # A prepared dataset's record (camrep_source.json), read without touching its records.
  _fake_prepared(tmp_path, "rooms", "small", (32, 32))
  config = gqn.get_config("smoke")
  config.data.dir = str(tmp_path)
  with pytest.raises(runconfig.ConfigError, match="renders 64x64 images, but the prepared"):
    synthesis_schema.validate(config)
  _fake_prepared(tmp_path, "object", "small", (128, 128))
  config = shapenet_car.get_config("smoke")
  config.data.dir = str(tmp_path)
  with pytest.raises(runconfig.ConfigError, match=r"set --config.model.image_size=128"):
    synthesis_schema.validate(config)
  # Pose dimensions: a dataset of another source's poses under this source's name.
  _fake_prepared(tmp_path, "area", "small", (64, 64), poses=("x", "y", "z"))
  config = gqn.get_config("smoke")
  config.data.source, config.data.dir, config.task = "area", str(tmp_path), "table"
  with pytest.raises(runconfig.ConfigError, match=r"holds poses \['x', 'y', 'z'\]"):
    synthesis_schema.validate(config)


# --------------------------------------------------------------------------------------------
# Real command lines (a handful of subprocesses).

_USER_ERRORS = {
  "missing_config_file": (
    ["-m", "camrep.main", "--config=configs/no_such.py"],
    "config file configs/no_such.py does not exist",
  ),
  "unknown_key": (
    ["-m", "camrep.main", "--config=configs/gqn.py:smoke", "--config.no_such_key=1"],
    "--config.no_such_key=1: the config has no field 'no_such_key'",
  ),
  "scenes_per_device_0": (
    ["-m", "camrep.main", "--config=configs/gqn.py:smoke", "--config.data.scenes_per_device=0"],
    "--config.data.scenes_per_device=0: must be a number > 0",
  ),
  "unsupported_image_size": (
    ["-m", "camrep.main", "--config=configs/shapenet_car.py:smoke", "--config.model.image_size=96"],
    "--config.model.image_size=96: must be one of [64, 128]",
  ),
  "process_id_without_coordinator": (
    ["-m", "camrep.main", "--config=configs/gqn.py:smoke", "--num_processes=2", "--process_id=5"],
    "--num_processes, --process_id given without --coordinator_address",
  ),
  "regression_negative_seed": (
    ["-m", "camrep.regression", "--config=configs/regression.py:smoke", "--config.seed=-1"],
    "--config.seed=-1: must be a number >= 0",
  ),
}


@pytest.mark.parametrize("case", sorted(_USER_ERRORS))
def test_command_line_user_errors(case, tmp_path):
  args, message = _USER_ERRORS[case]
  r = _run(*args, f"--workdir={tmp_path}/w", timeout=120)
  assert r.returncode == 2, r.stderr[-2000:]
  _assert_one_error(r.stderr, message)
  assert not (tmp_path / "w").exists()  # refused before the workdir was made


def test_unreachable_coordinator_is_reported_within_the_timeout(tmp_path):
  with socket.socket() as s:  # a port nothing listens on
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
  t0 = time.monotonic()
  r = _run(
    "-m",
    "camrep.main",
    "--config=configs/gqn.py:smoke",
    f"--workdir={tmp_path}/w",
    f"--coordinator_address=127.0.0.1:{port}",
    "--num_processes=2",
    "--process_id=1",
    "--coordinator_timeout=3",
    timeout=120,
  )
  assert r.returncode == 2, r.stderr[-2000:]
  _assert_one_error(r.stderr, f"could not join the jax.distributed job at 127.0.0.1:{port}")
  assert time.monotonic() - t0 < 60  # jax alone waits 5 minutes, then aborts (exit 134)
  assert not (tmp_path / "w").exists()


def test_inconsistent_process_flags_are_refused():
  from camrep import main  # defines the flags on absl's FLAGS: this process parses none

  cases = {
    ("h:1", 2, 2): "--process_id=2: must be < --num_processes=2",
    ("h:1", 0, 0): "--num_processes=0: must be >= 1",
    ("h:1", 2, -1): "--process_id=-1: must be >= 0",
    ("nohost", 2, 0): "--coordinator_address=nohost: expected host:port",
    ("h:1", None, 0): "given without --num_processes",
  }
  for (address, n, i), message in cases.items():
    with pytest.raises(cli.UsageError, match=message):
      main.check_process_flags(address, n, i)
  main.check_process_flags(None, None, None)
  main.check_process_flags("h:1", 2, 1)
  main.check_process_flags(None, 2, None, distributed=True)  # cluster detection fills the rest


def test_disk_full_during_checkpoint_save_ends_with_one_error_and_the_next_start_resumes(tmp_path):
  wd = tmp_path / "w"
  flags_ = ["camrep.main", "--config=configs/gqn.py:smoke", f"--workdir={wd}"]
  r = _run("tests/faults_script.py", "enospc_checkpoint:4", *flags_)
  assert r.returncode == 2, r.stderr[-3000:]
  line = _assert_one_error(r.stderr, "Disk full while saving checkpoint step 4")
  # The output ends with it, with no traceback of the failed save's writer threads, which the
  # fault slows as a loaded machine does (they once outlived a fixed pause and printed after it).
  assert r.stderr.rstrip().endswith(line), r.stderr[-3000:]
  assert "Traceback" not in r.stderr and "Event loop is closed" not in r.stderr, r.stderr[-3000:]
  assert sorted(os.listdir(wd / "checkpoints")) == ["2"]  # no partial step 4
  assert not (wd / workdir_lib.LOCK_FILE).exists()
  r = _run("-m", *flags_)
  assert r.returncode == 0, r.stderr[-3000:]
  assert "resumed from step 2" in r.stdout
  assert sorted(os.listdir(wd / "checkpoints")) == ["2", "4"]


# --------------------------------------------------------------------------------------------
# Resources (in this process).


def _enospc(*args, **kwargs):
  raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_disk_full_at_lock_creation_leaves_no_lock(tmp_path, monkeypatch):
  lock = workdir_lib.WorkdirLock(str(tmp_path))
  with monkeypatch.context() as m:
    m.setattr(workdir_lib.os, "fsync", _enospc)
    with pytest.raises(workdir_lib.WorkdirError, match="No space left on device"):
      lock.acquire()
  assert os.listdir(tmp_path) == []  # an empty lock would refuse every later start
  lock.acquire()
  assert lock.held
  lock.release()


def test_an_old_empty_lock_is_taken_over_and_a_fresh_one_refused(tmp_path):
  path = tmp_path / workdir_lib.LOCK_FILE
  path.write_text("")  # left by a start that died while writing it (camrep before this fix)
  with pytest.raises(workdir_lib.WorkdirError, match="unreadable lock"):
    workdir_lib.WorkdirLock(str(tmp_path)).acquire()  # a live start may be writing it now
  old = time.time() - 2 * workdir_lib.UNREADABLE_LOCK_GRACE_S
  os.utime(path, (old, old))
  lock = workdir_lib.WorkdirLock(str(tmp_path))
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    lock.acquire()
  assert lock.held and any(issubclass(w.category, workdir_lib.StaleLockWarning) for w in caught)
  lock.release()


def _train_tool(config):
  def define(fv, argv):
    flags.DEFINE_string("workdir", None, "", flag_values=fv)

  def body(fv):
    train.train_and_evaluate(config, fv.workdir)
    return 0

  return define, body


def test_resume_on_another_device_count_is_refused_unless_allowed(gqn_smoke_run, tmp_path):
  wd = tmp_path / "w"
  shutil.copytree(gqn_smoke_run, wd)
  history = workdir_lib.read_history(str(wd))
  assert history[-1]["topology"] == {"processes": 1, "devices": 1, "global_batch": 2}
  # As if it had run on 2 devices: this 1-device resume halves the global batch.
  two = {"processes": 1, "devices": 2, "global_batch": 4}
  with open(wd / workdir_lib.HISTORY_FILE, "a") as f:
    f.write(json.dumps({**history[-1], "topology": two}) + "\n")
  before = _snapshot(wd)
  config = gqn.get_config("smoke")
  config.total_steps, config.allow_changes = 6, "total_steps"
  with pytest.raises(runconfig.ConfigError, match="took 4 scenes per step on 2 device"):
    train.train_and_evaluate(config, str(wd), log=lambda s: None)
  assert _snapshot(wd) == before
  now = frame_lib.topology(processes=1, devices=1, scenes_per_device=2)
  change = workdir_lib.check_topology(str(wd), now, allowed=True)
  assert change == {"topology": [two, now]}  # recorded in config_history.jsonl when allowed


def test_evaluate_disk_full_and_read_only_leave_the_workdir_unchanged(
  gqn_smoke_run, tmp_path, monkeypatch, capsys
):
  wd = tmp_path / "w"
  shutil.copytree(gqn_smoke_run, wd)
  shutil.rmtree(wd / ev.EVAL_SUBDIR, ignore_errors=True)
  before = _snapshot(wd)
  with monkeypatch.context() as m:
    m.setattr(workdir_lib.tempfile, "mkstemp", lambda *a, **k: _enospc_erofs())
    assert ev.main([f"--workdir={wd}", "--what=gram"]) == 2
  _assert_one_error(capsys.readouterr().err, "cannot be written: Read-only file system")
  assert _snapshot(wd) == before
  with monkeypatch.context() as m:
    m.setattr(ev.gram_lib.np, "savez", _enospc)
    assert ev.main([f"--workdir={wd}", "--what=gram"]) == 2
  _assert_one_error(capsys.readouterr().err, "disk full")
  assert _snapshot(wd) == before  # no eval/ directory, no staged file


def _enospc_erofs():
  raise OSError(errno.EROFS, os.strerror(errno.EROFS))


def test_prepare_disk_full_leaves_a_dataset_the_next_run_finishes(tmp_path, monkeypatch, capsys):
  args = ["--source=rooms", "--preset=small", f"--data_dir={tmp_path}", "--no_progress"]
  args += ["--config.num_train_scenes=1", "--config.num_test_scenes=1", "--config.image_size=16"]
  with monkeypatch.context() as m:
    m.setattr(os, "fsync", _enospc)  # the metadata, written last, marks a finished dataset
    assert prepare.main(args) == 2
  _assert_one_error(capsys.readouterr().err, "disk full")
  assert not list(tmp_path.rglob("camrep_source.json*"))
  assert prepare.main(args) == 0
  assert "wrote" in capsys.readouterr().out and list(tmp_path.rglob("camrep_source.json"))


def test_retention_that_keeps_no_checkpoint_is_refused(tmp_path):
  with pytest.raises(ckpt_lib.CheckpointError, match="keep no checkpoint"):
    ckpt_lib.Checkpointer(tmp_path, max_to_keep=0)
  assert not (tmp_path / "checkpoints").exists()
  config = gqn.get_config("smoke")
  config.max_to_keep = 0
  with pytest.raises(runconfig.ConfigError, match="max_to_keep=0: must be a number > 0"):
    synthesis_schema.validate(config)


# --------------------------------------------------------------------------------------------
# Prepared data and the command lines around it: each of these printed a Python traceback.


def _capture(tmp_path, **top):
  """A small NeRF capture (transforms.json, 8 views) written by the captures tests' helper."""
  from tests.test_captures import rig, write_nerf

  return write_nerf(tmp_path / "cap", rig(8)[0], rng=np.random.default_rng(0), **top)


def _prepare_args(root, data_dir, *extra):
  return ["--source=nerf", f"--input={root}", f"--data_dir={data_dir}", "--no_progress",
          "--config.image_size=8", *extra]  # fmt: skip


def test_nerf_camera_angle_x_zero_is_refused(tmp_path, capsys):
  root = _capture(tmp_path, camera_angle_x=0)
  assert prepare.main(_prepare_args(root, tmp_path / "d")) == 2
  _assert_one_error(capsys.readouterr().err, "frame 0: camera_angle_x=0 is not a field of view")
  assert not (tmp_path / "d").exists()


def test_prepare_disk_full_while_writing_records_keeps_the_complete_dataset(
  tmp_path, monkeypatch, capsys
):
  import tensorflow_datasets as tfds

  root = _capture(tmp_path)
  args = _prepare_args(root, tmp_path / "d")
  assert prepare.main(args) == 0
  before = _snapshot(tmp_path / "d")

  def full(*a, **k):  # what array_record raises when the disk fills (no errno, only text)
    raise RuntimeError(
      'Failed to finalize writing of split "train": write() failed: No space left on device; '
      "writing .../nerf-train.array_record-00000-of-00001; at byte 307200"
    )

  with monkeypatch.context() as m:
    m.setattr(tfds.core.file_adapters.ArrayRecordFileAdapter, "write_examples", full)
    assert prepare.main([*args, "--overwrite"]) == 2  # overwriting: the old one must survive
    _assert_one_error(capsys.readouterr().err, "disk full writing", "No space left on device")
    assert _snapshot(tmp_path / "d") == before  # the complete dataset, nothing half-written
    shutil.rmtree(tmp_path / "d")
    assert prepare.main(args) == 2
    _assert_one_error(capsys.readouterr().err, "disk full")
  assert not list((tmp_path / "d").rglob("*.array_record*"))
  assert prepare.main(args) == 0


def test_a_second_prepare_of_one_dataset_is_refused_by_name(tmp_path, capsys):
  root = _capture(tmp_path)
  parent = tmp_path / "d" / "nerf"
  parent.mkdir(parents=True)
  me = {"pid": os.getpid(), "host": socket.gethostname(), "started": "now", "argv": []}
  (parent / workdir_lib.LOCK_FILE).write_text(json.dumps(me))  # a live writer holds it
  assert prepare.main(_prepare_args(root, tmp_path / "d")) == 2
  _assert_one_error(capsys.readouterr().err, "another process is preparing this dataset", "PID")
  assert sorted(os.listdir(parent)) == [workdir_lib.LOCK_FILE]  # nothing written
  (parent / workdir_lib.LOCK_FILE).unlink()
  assert prepare.main(_prepare_args(root, tmp_path / "d")) == 0
  assert not (parent / workdir_lib.LOCK_FILE).exists()  # released


def test_a_missing_flagfile_is_one_error(tmp_path, capsys):
  missing = tmp_path / "no_such_flags"
  for module in ("camrep.main", "camrep.regression"):  # the --config flag reads flagfiles
    r = _run("-m", module, f"--flagfile={missing}", timeout=120)
    assert r.returncode == 2, r.stderr[-2000:]
    _assert_one_error(r.stderr, "Unable to open flagfile: [Errno 2] No such file", str(missing))
  assert prepare.main([f"--flagfile={missing}"]) == 2
  _assert_one_error(capsys.readouterr().err, "Unable to open flagfile")


def test_data_dir_and_cache_dir_naming_a_file(tmp_path, capsys):
  afile = tmp_path / "afile"
  afile.write_text("")
  assert prepare.main(_prepare_args(_capture(tmp_path), afile)) == 2
  _assert_one_error(capsys.readouterr().err, f"{afile}: --data_dir names a file, not a directory")
  r = _run("-m", "camrep.regression", "--config=configs/regression.py:smoke",
           f"--workdir={tmp_path}/w", f"--config.data.cache_dir={afile}", timeout=300)  # fmt: skip
  assert r.returncode == 2, r.stderr[-2000:]
  _assert_one_error(r.stderr, f"{afile}: already exists and is not a directory")
  assert not (tmp_path / "w").exists()


def test_a_cut_noise_json_is_one_error(tmp_path, capsys):
  from experiments import noise_figure

  wd = tmp_path / "w"
  (wd / ev.EVAL_SUBDIR).mkdir(parents=True)
  (wd / "config.json").write_text("{}")
  (wd / ev.EVAL_SUBDIR / "noise.json").write_text('{"setting": "gqn", "alphas": [0.0, 0.')
  argv = ["--runs", str(wd), "--png", str(tmp_path / "n.png"), "--md", str(tmp_path / "n.md")]
  assert noise_figure.main(argv) == 2
  _assert_one_error(capsys.readouterr().err, "noise.json is not valid JSON", "--what=noise")


def test_a_non_utf8_data_dir_is_refused_before_writing(tmp_path, capsys):
  # Under a non-UTF-8 locale, Python keeps a non-ASCII name's bytes as surrogates ("dé" in
  # UTF-8 -> "d\udcc3\udca9"), which the ArrayRecord writer refuses with a TypeError.
  root = _capture(tmp_path)
  odd = os.path.join(str(tmp_path), "d\udcc3\udca9")
  assert prepare.main(_prepare_args(root, odd)) == 2
  _assert_one_error(capsys.readouterr().err, "not valid in this locale's file-system encoding")
  assert sorted(os.listdir(tmp_path)) == ["cap"]
  env = {"LC_ALL": "C", "LANG": "C", "PYTHONCOERCECLOCALE": "0", "PYTHONUTF8": "0"}
  argv = _prepare_args(root, os.fsencode(odd).decode("utf-8"))  # the name's real UTF-8 bytes
  r = subprocess.run(
    [sys.executable, "-m", "camrep.data.prepare", *argv],
    capture_output=True, text=True, cwd=ROOT, timeout=300, env={**os.environ, **env},
  )  # fmt: skip
  assert r.returncode == 2, r.stderr[-2000:]
  _assert_one_error(r.stderr, "file-system encoding (ascii)")
  assert sorted(os.listdir(tmp_path)) == ["cap"]


@pytest.mark.skipif(shutil.which("nvidia-smi") is not None, reason="this machine has a GPU")
def test_jax_platforms_gpu_without_one_is_one_error(tmp_path):
  r = _run("-m", "camrep.main", "--config=configs/gqn.py:smoke", f"--workdir={tmp_path}/w",
           env={"JAX_PLATFORMS": "gpu"}, timeout=120)  # fmt: skip
  assert r.returncode == 2, r.stderr[-2000:]
  _assert_one_error(r.stderr, "JAX_PLATFORMS='gpu': JAX cannot start that platform", "cpu")
  assert not (tmp_path / "w").exists()
  r = _run("-m", "camrep.data.prepare", "--source=rooms", "--preset=small",
           f"--data_dir={tmp_path}/d", env={"JAX_PLATFORMS": "gpu"}, timeout=120)  # fmt: skip
  assert r.returncode == 2, r.stderr[-2000:]
  _assert_one_error(r.stderr, "JAX_PLATFORMS='gpu'")
  assert not (tmp_path / "d").exists()  # refused before anything was written


def test_prepare_refuses_a_negative_image_size(tmp_path, capsys):
  root = _capture(tmp_path)
  for argv in (
    ["--source=rooms", "--preset=small", f"--data_dir={tmp_path / 'd'}", "--config.image_size=-5"],
    [*_prepare_args(root, tmp_path / "d"), "--config.image_size=-5"],
  ):
    assert prepare.main(argv) == 2
    _assert_one_error(capsys.readouterr().err, "--config.image_size=-5: must be a positive integer")
  assert not (tmp_path / "d").exists()


def test_help_lists_config_its_variants_and_every_source():
  """`--help` exits 0 in absl's format (a "flags:" section) and lists --config, its variants and,
  for prepare, every source with its layout."""
  from camrep.data import sources

  for module in ("camrep.main", "camrep.regression"):
    r = _run("-m", module, "--help", timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "flags:" in r.stdout and "Traceback" not in r.stderr, module
    text = " ".join(r.stdout.split())
    assert " --config: " in text, module  # a flag line, not only the docstring
    assert "shapenet_car[:quick|:medium|:smoke" in text and "--config.FIELD=VALUE" in text
    assert "quick: minutes on 2 CPU cores" in text
  r = _run("-m", "camrep.data.prepare", "--help", timeout=120)
  assert r.returncode == 0, r.stderr[-2000:]
  assert "flags:" in r.stdout and "Traceback" not in r.stderr
  head = r.stdout.split("flags:")[0]
  listed = head.split("Sources (")[1].split("The capture sources")[0]
  for name in sources.SOURCES:  # each with its layout
    assert name in listed, name
  for layout in ("transforms_{train,val,test}.json", "poses_bounds.npy", "sparse/0/"):
    assert layout in listed
  assert " --config: --config.FIELD=VALUE" in " ".join(r.stdout.split("flags:")[1].split())


def test_a_family_count_below_one_is_refused_before_anything_is_written(tmp_path, capsys):
  # A split without views (tfds: "No examples were yielded"), a rendering without samples
  # (supersample=0 wrote a dataset), more objects at least than at most (numpy's "low >= high").
  base = ["--source=rooms", "--preset=small", "--no_progress", "--config.image_size=16"]
  for flags_ in (
    ["--config.test_views=0"],
    ["--config.num_test_scenes=0"],
    ["--config.train_views=-1"],
    ["--config.supersample=0"],
    ["--config.min_objects=5", "--config.max_objects=2"],
  ):
    assert prepare.main([*base, f"--data_dir={tmp_path / 'd'}", *flags_]) == 2, flags_
    field = flags_[0].removeprefix("--config.")
    _assert_one_error(capsys.readouterr().err, field, "must")
    assert not (tmp_path / "d").exists()
  config = gqn.get_config("smoke")
  config.data.family.test_views = 0
  with pytest.raises(runconfig.ConfigError, match="test_views=0: must be an integer >= 1"):
    synthesis_schema.validate(config)


def test_a_seen_capture_without_a_training_view_is_refused(tmp_path, capsys):
  # holdout_every=1 holds every view out: the dataset was written without a train split, exit 0.
  root = _capture(tmp_path)
  assert prepare.main(_prepare_args(root, tmp_path / "d", "--config.holdout_every=1")) == 2
  _assert_one_error(capsys.readouterr().err, "cap has no view left to train on", "holdout_every")
  assert not (tmp_path / "d").exists()
  assert prepare.main(_prepare_args(root, tmp_path / "d", "--config.holdout_every=2")) == 0

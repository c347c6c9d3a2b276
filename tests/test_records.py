"""A workdir's record is complete and checked (and the stop message).

record.json holds what decides the data and the pose system beyond config.json (the procedural
family's resolved parameters, the pose spec, the data fingerprint): a changed library default or
a swapped prepared dataset is refused at resume like a changed flag; a workdir with checkpoints
and no config.json is refused; the regression's "ours" check compares the data fingerprint; an
old workdir without a record resumes with one warning and gains it; a non-finite stop says
whether the checkpoint it began from was verified.
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
import shutil

import pytest
from absl import flags

from camrep.configs import gqn, regression
from camrep.data import prepare, procedural
from camrep.data.feed import fingerprint
from camrep.regression import config_schema, pose_system
from camrep.regression import driver as R
from camrep.runtime import cli, runconfig, writers
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import components, train
from camrep.synthesis import step as step_lib

pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]


def _snapshot(path) -> dict[str, str]:
  """{relative path: sha256} of every file under `path`."""
  path = pathlib.Path(path)
  return {
    str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
    for p in sorted(path.rglob("*"))
    if p.is_file()
  }


def _error_line(err: str) -> str:
  """The one `error:` line of a tool's output (no traceback)."""
  assert "Traceback" not in err, err[-3000:]
  lines = [line for line in err.splitlines() if line.startswith("error: ")]
  assert len(lines) == 1, err[-3000:]
  return lines[0]


def _train_tool(config):
  def define(fv, argv):
    flags.DEFINE_string("workdir", None, "", flag_values=fv)

  def body(fv):
    train.train_and_evaluate(config, fv.workdir, log=lambda s: None)
    return 0

  return define, body


def _resume_config(total_steps: int = 6):
  config = gqn.get_config("smoke")
  config.total_steps, config.allow_changes = total_steps, "total_steps"
  return config


@pytest.fixture
def run_copy(gqn_smoke_run, tmp_path):
  wd = tmp_path / "w"
  shutil.copytree(gqn_smoke_run, wd)
  return wd


def test_the_record_holds_the_resolved_family_spec_and_fingerprint(gqn_smoke_run):
  config = gqn.get_config("smoke")
  assert workdir_lib.read_stored_config(gqn_smoke_run)["data"]["family"] == {}  # the user's
  record = workdir_lib.read_record(gqn_smoke_run)
  assert record == json.loads(json.dumps(components.run_record(components.resolve(config))))
  data = record["data"]
  assert data["kind"] == "procedural" and data["family"]["wall_style"] == "tinted"
  assert data["family"]["num_train_scenes"] == 4  # the small preset's
  assert [d["kind"] for d in record["pose_spec"]["dofs"]] == ["PolarDof", "AngularDof"]
  # The "world" leaves out how many scenes and views: a larger config of the same rooms.
  bigger = gqn.get_config("smoke")
  bigger.data.family.num_train_scenes = 40
  other = fingerprint.data_record(bigger.data)
  assert other["world"] == data["world"] and other["fingerprint"] != data["fingerprint"]


def test_a_changed_library_default_at_resume_is_refused_and_changes_nothing(
  run_copy, monkeypatch, capsys
):
  before = _snapshot(run_copy)
  # The small preset's rooms now have distinct walls: config.json (data.family: {}) is the same.
  small = {**procedural.SMALL_OVERRIDES["rooms"], "wall_style": "distinct"}
  monkeypatch.setitem(procedural.SMALL_OVERRIDES, "rooms", small)
  assert cli.call(*_train_tool(_resume_config()), [f"--workdir={run_copy}"]) == 2
  line = _error_line(capsys.readouterr().err)
  assert f"cannot resume in {run_copy}: data.family.wall_style: 'tinted' -> 'distinct'" in line
  assert _snapshot(run_copy) == before
  monkeypatch.undo()
  # A pose-system default (simulated by editing the stored record).
  record = workdir_lib.read_record(str(run_copy))
  record["pose_spec"]["dofs"][1]["spacing"] = 0.5
  workdir_lib.write_record(str(run_copy), record)
  before = _snapshot(run_copy)
  with pytest.raises(runconfig.ConfigError, match=r"pose_spec\.dofs\.1\.spacing: 0\.5 -> 0\.17"):
    train.train_and_evaluate(_resume_config(), str(run_copy), log=lambda s: None)
  assert _snapshot(run_copy) == before


def test_a_restore_for_evaluation_refuses_a_changed_library_default(run_copy, monkeypatch):
  from camrep.synthesis import evaluate, restore

  small = {**procedural.SMALL_OVERRIDES["rooms"], "wall_style": "distinct"}
  monkeypatch.setitem(procedural.SMALL_OVERRIDES, "rooms", small)
  with pytest.raises(runconfig.ConfigError, match="data.family.wall_style: 'tinted' -> 'distinct'"):
    restore.load_run(str(run_copy))
  before = _snapshot(run_copy)
  assert evaluate.main([f"--workdir={run_copy}", "--what=gram"]) == 2
  assert _snapshot(run_copy) == before


def test_checkpoints_without_config_json_are_refused(run_copy, capsys):
  os.remove(run_copy / writers.CONFIG_FILE)
  before = _snapshot(run_copy)
  config = _resume_config()
  config.seed, config.optax.lr_model = 7, 1e-2  # unchecked, they would be claimed for every step
  assert cli.call(*_train_tool(config), [f"--workdir={run_copy}"]) == 2
  line = _error_line(capsys.readouterr().err)
  assert "holds checkpoints but no config.json" in line and "Put its config.json back" in line
  assert _snapshot(run_copy) == before


def test_an_old_workdir_without_a_record_resumes_with_a_warning_and_gains_one(run_copy):
  os.remove(run_copy / workdir_lib.RECORD_FILE)
  lines = []
  config = _resume_config()
  train.train_and_evaluate(config, str(run_copy), log=lines.append)
  warnings = [x for x in lines if x.startswith("warning:")]
  assert len(warnings) == 1 and f"has no {workdir_lib.RECORD_FILE}" in warnings[0]
  assert workdir_lib.read_record(str(run_copy)) == json.loads(
    json.dumps(components.run_record(components.resolve(config)))
  )
  assert workdir_lib.read_history(str(run_copy))[-1]["changes"] == {"total_steps": [4, 6]}


def _prepare_rooms(data_dir, seed: int) -> pathlib.Path:
  args = ["--source=rooms", "--preset=small", f"--data_dir={data_dir}", "--no_progress"]
  args += ["--config.num_train_scenes=1", "--config.num_test_scenes=1"]
  args += ["--config.image_size=16", f"--config.seed={seed}"]
  assert prepare.main(args) == 0
  return next(pathlib.Path(data_dir).rglob("camrep_source.json")).parent


def test_a_moved_prepared_dataset_keeps_its_fingerprint_a_swapped_one_is_refused(tmp_path):
  path = _prepare_rooms(tmp_path / "a", seed=0)
  moved = tmp_path / "moved"
  shutil.copytree(tmp_path / "a", moved)
  old = {"data": fingerprint.prepared_record(path)}
  now = {"data": fingerprint.prepared_record(next(moved.rglob("camrep_source.json")).parent)}
  assert now["data"]["fingerprint"] == old["data"]["fingerprint"]
  workdir_lib.write_record(str(tmp_path), old)
  assert workdir_lib.check_record(str(tmp_path), now) == {
    "record.data.dataset": [old["data"]["dataset"], now["data"]["dataset"]]
  }
  # Another dataset under the same name and settings (here: another seed) in the moved place.
  swapped = _prepare_rooms(tmp_path / "b", seed=1)
  now = {"data": fingerprint.prepared_record(swapped)}
  with pytest.raises(runconfig.ConfigError, match="only a moved copy of the same dataset"):
    workdir_lib.check_record(str(tmp_path), now)
  # The sidecar's content, not its file (np.savez stamps the time into the zip).
  a = fingerprint.prepared_record(_prepare_rooms(tmp_path / "c", seed=0))
  assert a["fingerprint"] == old["data"]["fingerprint"]


def _regression(workdir, **family):
  config = regression.get_config("gqn,smoke")
  config.representation = "ours"
  config.synthesis_workdir = str(workdir)
  for k, v in family.items():
    config.data.family[k] = v
  return config_schema.check(config)


def test_regression_ours_refuses_a_pose_system_learned_on_other_rooms(gqn_smoke_run, tmp_path):
  # The same rooms: accepted (restore_pose_system restores only the checkpoint).
  run = _regression(gqn_smoke_run)
  assert pose_system.restore_pose_system(gqn_smoke_run, run.setting, run)["step"] == 4
  # Rooms of another wall style: the source and the directory are the same, the rooms are not.
  other = _regression(gqn_smoke_run, wall_style="distinct")
  wd = tmp_path / "reg"
  with pytest.raises(runconfig.ConfigError, match="other data") as e:
    R.run(other.config, str(wd), log=lambda s: None)
  assert "data.family.wall_style: 'tinted' -> 'distinct'" in str(e.value)
  assert not wd.exists()
  # Another light and seed: each named.
  with pytest.raises(runconfig.ConfigError, match="data.family.light_azimuth_deg: None -> 30"):
    run = _regression(gqn_smoke_run, light_azimuth_deg=30.0, seed=3)
    pose_system.restore_pose_system(gqn_smoke_run, run.setting, run)


def test_non_finite_stop_says_whether_the_restored_checkpoint_was_verified():
  # End to end (a resumed run stopping on NaN: "restored from step 4, checksum verified"):
  # tests/test_train.py::test_non_finite_stops_and_keeps_last_good_checkpoint; the Checkpointer's
  # `restored` of a step without a manifest: tests/test_checkpoint.py.
  assert step_lib.restored_from({"step": 4, "verified": True}) == (
    "this run restored from step 4, checksum verified"
  )
  assert step_lib.restored_from({"step": 2, "verified": False}) == (
    "this run restored from step 2, not verified (written before checkpoints had checksums)"
  )
  assert step_lib.restored_from(None) == "this run started from step 0 (no checkpoint restored)"


def test_record_differences_accept_gained_fields_and_name_changed_ones():
  old = components.run_record(components.resolve(gqn.get_config("smoke")))
  new = json.loads(json.dumps(old))
  new["data"]["family"]["fog"] = 0.0  # a parameter camrep gained: its default keeps the images
  new["data"]["fingerprint"] = new["data"]["world"] = "sha256:other"  # follows from it
  new["version"] = 2
  refused, accepted = workdir_lib.record_differences(old, new)
  assert refused == {} and set(accepted) == {"data.family.fog", "data.world", "version"}
  new["data"]["family"]["pitch"] = -0.2
  refused, _ = workdir_lib.record_differences(old, new)
  assert refused == {"data.family.pitch": (-0.3, -0.2)}

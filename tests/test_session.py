"""A workdir's records stay true across reruns (camrep.runtime.session, the trainer's end):
rerunning a complete run changes no byte, lowering total_steps is refused, final_metrics.json
says "complete" only for a completed run, a cut config-history line is survived, and the
experiments scripts tell finished runs from unfinished ones and name what they skip."""

from __future__ import annotations

import hashlib
import json
import os
import shutil

import pytest

from camrep.comparison import launch
from camrep.configs import gqn
from camrep.runtime import runconfig, session, writers
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import step as step_lib
from camrep.synthesis import train
from experiments import table1

pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]


def hashes(workdir) -> dict[str, str]:
  """relative path -> sha256 of every file under workdir."""
  out = {}
  for root, _, files in os.walk(workdir):
    for f in files:
      p = os.path.join(root, f)
      with open(p, "rb") as fh:
        out[os.path.relpath(p, workdir)] = hashlib.sha256(fh.read()).hexdigest()
  return out


@pytest.fixture
def run(tmp_path, gqn_smoke_run):
  """A copy of the session's complete 4-step run."""
  wd = str(tmp_path / "w")
  shutil.copytree(gqn_smoke_run, wd)
  return wd


def test_a_complete_run_records_it(run):
  final = session.read_final(run)
  assert final["complete"] is True and final["step"] == 4
  assert session.is_complete(run) and session.is_complete(run, 4)
  assert not session.is_complete(run, 6)
  assert final["machine"] == workdir_lib.machine()  # what ran it (this CPU here)
  rows = writers.read_metrics(run)
  assert final["eval/psnr"] == [r for r in rows if "eval/psnr" in r][-1]["eval/psnr"]
  assert not [f for f in os.listdir(run) if ".tmp" in f]  # written by os.replace


def test_rerunning_a_complete_run_changes_no_file(run):
  before = hashes(run)
  lines = []
  last = train.train_and_evaluate(gqn.get_config("smoke"), run, log=lines.append)
  assert hashes(run) == before
  assert lines == [f"{run} is complete at step 4 (final_metrics.json); nothing to do"]
  assert last["eval/psnr"] == session.read_final(run)["eval/psnr"]


def test_lowering_total_steps_is_refused_and_changes_nothing(run):
  before = hashes(run)
  c = gqn.get_config("smoke")
  c.total_steps, c.allow_changes = 2, "total_steps"
  with pytest.raises(runconfig.ConfigError, match="total_steps=2 is below the step 4"):
    train.train_and_evaluate(c, run)
  assert hashes(run) == before


def test_killed_extension_leaves_the_record_incomplete(run, monkeypatch):
  """An extended run that dies before it completes leaves final_metrics.json marked incomplete
  (its values kept); the next start finishes it and marks it complete at the new step."""

  def dies(*args, **kw):
    raise KeyboardInterrupt

  c = gqn.get_config("smoke")
  c.total_steps, c.allow_changes = 6, "total_steps"
  with monkeypatch.context() as m:
    m.setattr(step_lib, "make_p_train_step", dies)
    with pytest.raises(KeyboardInterrupt):
      train.train_and_evaluate(c, run, log=lambda line: None)
  final = session.read_final(run)
  assert final["complete"] is False and final["step"] == 4 and "eval/psnr" in final
  assert not session.is_complete(run)
  assert not os.path.exists(os.path.join(run, workdir_lib.LOCK_FILE))
  train.train_and_evaluate(c, run, log=lambda line: None)
  assert session.is_complete(run, 6)


def test_missing_final_record_is_written_from_the_logged_metrics(run):
  """Killed after its last checkpoint, before final_metrics.json: the rerun trains no step and
  writes the record from metrics.jsonl."""
  want = session.read_final(run)
  os.remove(os.path.join(run, session.FINAL_FILE))
  train.train_and_evaluate(gqn.get_config("smoke"), run, log=lambda line: None)
  got = session.read_final(run)
  assert got["complete"] is True and got["step"] == 4
  for k in ("eval/psnr", "eval/ssim", "train/loss", "train/rec"):
    assert got[k] == want[k], k
  assert [r["step"] for r in writers.read_metrics(run) if "train/loss" in r] == [2, 4]


def test_a_cut_history_line_is_survived_and_not_glued_onto(run):
  path = os.path.join(run, workdir_lib.HISTORY_FILE)
  with open(path, "a", encoding="utf-8") as f:
    f.write('{"step": 4, "event": "res')  # a killed run's half line, no newline
  c = gqn.get_config("smoke")
  c.total_steps, c.allow_changes = 6, "total_steps"
  train.train_and_evaluate(c, run, log=lambda line: None)
  rows = workdir_lib.read_history(run)
  assert [(r["step"], r["event"]) for r in rows] == [(0, "start"), (4, "resume")]
  with open(path, encoding="utf-8") as f:
    lines = f.read().splitlines()
  assert lines[-2] == '{"step": 4, "event": "res' and json.loads(lines[-1])["event"] == "resume"
  assert session.read_final(run)["config_changes"] == [
    {"step": 4, "changes": {"total_steps": [4, 6]}}
  ]


def test_run_comparison_and_table1_tell_unfinished_runs(run, tmp_path, capsys):
  job = launch.Job("synthesis_gqn", ["true"], run, 1, "synthesis")
  assert job.done()
  assert launch.run_jobs([job], str(tmp_path / "logs"), at_once=1, label="") == []
  assert "[skipped] synthesis_gqn: done" in capsys.readouterr().out
  final = session.read_final(run)
  with open(os.path.join(run, session.FINAL_FILE), "w") as f:
    json.dump({**final, "complete": False}, f)  # what an extension killed mid-way leaves
  assert not job.done()
  with open(os.path.join(run, session.FINAL_FILE), "w") as f:
    json.dump({k: v for k, v in final.items() if k != "complete"}, f)  # an older record
  assert not job.done()
  runs = tmp_path / "regression"
  (runs / "car" / "quat" / "lr0.001_seed0").mkdir(parents=True)
  assert table1.unfinished([str(runs / "*" / "*" / "*")]) == [
    str(runs / "car" / "quat" / "lr0.001_seed0")
  ]
  assert table1.main(["--runs", str(runs / "*" / "*" / "*"), "--out", str(tmp_path / "t.md")]) == 2
  err = capsys.readouterr().err
  assert f"skipped {runs}/car/quat/lr0.001_seed0: no results.json (unfinished run)" in err

"""The comparison launcher's archive (`--archive DIR`), its seed-by-seed order, and its safety on
a shared folder (one launch per DIR, damaged records, stops).

A converge launch is hours of 2-core CPU time, longer than a machine is kept: the archive holds
each finished run's compact record (no checkpoints) in the repository, and a launch on a new
machine restores them and trains only what is missing. The runs here are fabricated by a stand-in
for `run_job` (no JAX): it writes the files a real run writes and the launcher reads.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import time

import numpy as np
import pytest

from camrep.comparison import archive as archive_lib
from camrep.comparison import command, launch
from camrep.comparison import plan as plan_lib
from camrep.regression import runs


class _Launcher:
  """The launcher's modules under the names these tests use."""

  def __init__(self):
    self.launch, self.command = launch, command

  def __getattr__(self, name):
    return getattr(launch, name)

  def main(self, argv):
    return command.main(argv)

  def parse(self, argv):
    return command.parse_args(argv)

  def make(self, argv):
    return command.make_launch(command.parse_args(argv))


@pytest.fixture
def rc():
  return _Launcher()


def _args(out, archive, *extra):
  return [
    "--no_vectorise",  # seed by seed, one process per run (test_a_vectorised_launch: the grids)
    "--size",
    "converge",
    "--settings",
    "car",
    "--representations",
    "ours,quat",
    "--skip_figures",
    "--out",
    str(out),
    "--archive",
    str(archive),
    *extra,
  ]


def _flag(argv, name):
  return next(a.split("=", 1)[1] for a in argv if a.startswith(f"--config.{name}="))


def _summary(err):
  return {"all": {"rotation_error_deg": {"mean": err, "median": err / 2}}}


def fake_run_job(rc, ran, score=lambda lr: 1.0 + abs(np.log10(lr) + 3), pose_bytes=0):
  """A `run_job` that writes what a finished run leaves, and records the order of the runs.
  Regression: validation error `score(lr)`, by default lowest at lr 1e-3 (inside the grid: no
  extension). View synthesis: with `pose_bytes`, a final pose system file of that size."""

  def run_job(job, logs, *, index, env=None):
    if job.kind in ("table", "evaluate"):  # tables and curves: scripts over the runs, not runs
      return True
    ran.append(job.name)
    wd = job.workdir
    os.makedirs(wd, exist_ok=True)
    with open(os.path.join(wd, "config.json"), "w") as f:
      json.dump({"argv": job.argv}, f)
    with open(os.path.join(wd, "metrics.jsonl"), "w") as f:
      f.write('{"step": 1, "eval/psnr": 15.0}\n')
    if job.name.startswith("synthesis_"):
      step = int(_flag(job.argv, "total_steps"))  # complete at its cap
      os.makedirs(os.path.join(wd, "checkpoints", str(step)), exist_ok=True)
      os.makedirs(os.path.join(wd, "tensorboard"), exist_ok=True)
      open(os.path.join(wd, "tensorboard", "events.out"), "w").close()
      with open(os.path.join(wd, "final_metrics.json"), "w") as f:
        json.dump({"complete": True, "step": step}, f)
      if pose_bytes:
        with open(os.path.join(wd, "pose_system.npz"), "wb") as f:
          f.write(os.urandom(pose_bytes))
      return True
    if job.members:  # a grid: each member's workdir as its own run writes it
      lrs = [float(x) for x in launch.flag_value(job.argv, "--lrs").split(",")]
      seeds = [int(x) for x in launch.flag_value(job.argv, "--seeds").split(",")]
      members = [(lr, k) for lr in lrs for k in seeds]
      assert [os.path.basename(w) for w in job.members] == [runs.run_name(*m) for m in members]
    else:
      members = [(float(_flag(job.argv, "optax.lr")), int(_flag(job.argv, "seed")))]
    for w, (lr, seed) in zip(job.members or [wd], members, strict=True):
      os.makedirs(w, exist_ok=True)
      with open(os.path.join(w, "metrics.jsonl"), "w") as f:
        f.write('{"step": 1, "eval/psnr": 15.0}\n')
      val = score(lr)
      r = dict(setting="car", representation=_flag(job.argv, "representation"), lr=lr, seed=seed)
      r.update(steps=10, variant="quick", validation=_summary(val), test=_summary(2 * val))
      with open(os.path.join(w, "results.json"), "w") as f:
        json.dump(r, f)
      np.savez(os.path.join(w, "errors_test.npz"), rotation_error_deg=np.full(4, val))
    return True

  return run_job


def test_a_launch_goes_seed_by_seed_and_archives_each_run(rc, tmp_path, monkeypatch):
  """Seed k's synthesis runs come just before its regressions, and every finished run's records
  (never checkpoints or TensorBoard files) are in the archive as soon as it ends."""
  ran = []
  monkeypatch.setattr(launch, "run_job", fake_run_job(rc, ran))
  out, archive = tmp_path / "out", tmp_path / "archive"
  the_launch = rc.make(_args(out, archive))
  copies = []
  real_sync = archive_lib.sync
  monkeypatch.setattr(archive_lib, "sync", lambda o, a: copies.append(len(ran)) or real_sync(o, a))
  assert rc.execute(the_launch) == []
  syn = [n for n in ran if n.startswith("synthesis_")]
  assert syn == ["synthesis_car_seed0", "synthesis_car_seed1", "synthesis_car_seed2"]
  pos = {n: i for i, n in enumerate(ran)}
  phase1 = [n for n in ran if n.endswith("_seed0") and n.startswith("regression_")]
  assert len(phase1) == 2 * 3 and max(pos[n] for n in phase1) < pos["synthesis_car_seed1"]
  for k in (1, 2):
    mine = [n for n in ran if n.startswith("regression_") and n.endswith(f"_seed{k}")]
    assert mine and all(pos[f"synthesis_car_seed{k}"] < pos[n] for n in mine)
    assert all(n.startswith("regression_car_") and "lr1e-3" in n for n in mine)
  assert copies[: len(ran)] == list(range(1, len(ran) + 1))  # after every run, at once
  assert len(copies) > len(ran)  # and after the tables and curves
  kept = sorted(
    os.path.relpath(os.path.join(d, f), archive) for d, _, fs in os.walk(archive) for f in fs
  )
  assert "synthesis/car_seed1/run.json" in kept
  assert "regression/car/ours/lr1e-3_seed2/run.json" in kept
  # One compact record per run; beside a view-synthesis run's, its config (what its initial
  # pose system is made from: test_the_untrained_control_needs_only_the_archived_config).
  assert {os.path.basename(p) for p in kept if not p.startswith("synthesis/")} == {"run.json"}
  assert {os.path.basename(p) for p in kept if p.startswith("synthesis/")} == {
    "run.json",
    "config.json",
  }
  record = runs.load(str(archive / "regression" / "car" / "ours" / "lr1e-3_seed2"))
  np.testing.assert_array_equal(record.view_errors()["rotation_error_deg"], np.full(4, 1.0))
  assert record.curves == {"eval/psnr": {1: 15.0}}
  assert archive_lib.sync(str(out), str(archive)) == 0  # nothing changed: nothing written


def test_a_vectorised_launch_trains_each_group_as_one_program(rc, tmp_path, monkeypatch):
  """converge (vectorised): phase 1 is one program per representation over its lrs with seed 0,
  then every later seed's synthesis, then phase 2 one program over seeds 1 and 2 at the chosen
  lr; every member's run is archived as its own, and a second launch trains nothing."""
  ran = []
  monkeypatch.setattr(launch, "run_job", fake_run_job(rc, ran))
  out, archive = tmp_path / "out", tmp_path / "archive"
  args = _args(out, archive)[1:]  # without --no_vectorise
  assert rc.execute(rc.make(args)) == []
  grid = "lr3e-4-lr1e-3-lr3e-3"
  assert [n for n in ran if not n.startswith("synthesis_")] == [
    f"regression_car_ours_{grid}_seed0",
    f"regression_car_quat_{grid}_seed0",
    "regression_car_ours_lr1e-3_seed1-2",
    "regression_car_quat_lr1e-3_seed1-2",
  ]
  pos = {n: i for i, n in enumerate(ran)}
  assert pos["synthesis_car_seed0"] < pos[f"regression_car_ours_{grid}_seed0"]
  assert pos["synthesis_car_seed2"] < pos["regression_car_ours_lr1e-3_seed1-2"]
  for rep in ("ours", "quat"):
    for name in [f"{t}_seed0" for t in ("lr3e-4", "lr1e-3", "lr3e-3")] + [
      "lr1e-3_seed1",
      "lr1e-3_seed2",
    ]:
      assert (archive / "regression" / "car" / rep / name / "run.json").exists()
  ran.clear()
  assert rc.execute(rc.make(args)) == []
  assert ran == []


@pytest.mark.parametrize("vectorise", [True, False])
def test_a_full_grid_launch_trains_every_seeds_synthesis_before_phase_1(
  rc, tmp_path, monkeypatch, vectorise
):
  """--full_grid (as the protocol size) has no phase 2: phase 1 reads every seed's view
  synthesis, so every seed's synthesis is trained first and no regression starts without the
  pose system it reads."""
  ran, missing = [], []
  fake = fake_run_job(rc, ran)

  def run_job(job, logs, **kw):
    if job.name.startswith("regression_"):
      done = lambda w: os.path.exists(os.path.join(w, "final_metrics.json"))
      missing.extend(w for w in launch.synthesis_reads(job) if not done(w))
    return fake(job, logs, **kw)

  monkeypatch.setattr(launch, "run_job", run_job)
  args = _args(tmp_path / "out", tmp_path / "archive", "--full_grid")
  the_launch = rc.make(args if not vectorise else args[1:])
  assert not the_launch.later
  assert rc.execute(the_launch) == []
  assert missing == []
  syn = [i for i, n in enumerate(ran) if n.startswith("synthesis_")]
  reg = [i for i, n in enumerate(ran) if n.startswith("regression_")]
  assert len(syn) == 3 and max(syn) < min(reg)
  assert len(reg) == (2 if vectorise else 2 * 3 * 3)  # ours and quat, 3 lrs x 3 seeds each


def test_a_new_machine_restores_the_archive_and_trains_only_what_is_missing(
  rc, tmp_path, monkeypatch, capsys
):
  """On another machine (an empty DIR) the archived runs are restored and skipped; a
  view-synthesis run whose record came from the archive is trained again only while a run that
  reads its checkpoints is missing, and a partial run in DIR resumes from its own checkpoints."""
  ran = []
  monkeypatch.setattr(launch, "run_job", fake_run_job(rc, ran))
  first, archive = tmp_path / "first", tmp_path / "archive"
  assert rc.execute(rc.make(_args(first, archive))) == []
  # Lose seed 2's phase-2 ours run: it must be trained again, and so must its pose system.
  lost = archive / "regression" / "car" / "ours" / "lr1e-3_seed2"
  for f in os.listdir(lost):
    os.remove(lost / f)
  os.rmdir(lost)
  ran.clear()
  out = tmp_path / "second"
  os.makedirs(out / "synthesis" / "car_seed1" / "checkpoints" / "4")  # a partial run here
  assert rc.main(_args(out, archive)) == 0
  # The partial seed-1 run resumes from its own checkpoints (restoring never overwrites it).
  assert ran == [
    "synthesis_car_seed1",
    "synthesis_car_seed2",
    "regression_car_ours_lr1e-3_seed2",
  ]
  text = capsys.readouterr().out
  assert "restored" in text and "archived, nothing left needs it" in text
  assert "synthesis_car_seed0: archived" in text
  assert (out / "synthesis" / "car_seed1" / "checkpoints" / "4").is_dir()
  assert (archive / "regression" / "car" / "ours" / "lr1e-3_seed2" / "run.json").exists()
  # The archived synthesis record of seed 0 came back without checkpoints and stays so.
  assert rc.archived_only(str(out / "synthesis" / "car_seed0"))
  assert rc.has_checkpoint(str(out / "synthesis" / "car_seed2"))
  # A third launch finds nothing to do, and its dry run says so (phase 2 at the chosen lr).
  ran.clear()
  capsys.readouterr()
  assert rc.main(_args(tmp_path / "third", archive)) == 0
  assert ran == []
  assert rc.main(_args(tmp_path / "third", archive, "--dry_run")) == 0
  plan = capsys.readouterr().out
  assert "plus up to 0 phase-1 runs" in plan and "phase 2] " in plan
  assert plan.count("[done, phase 2]") == 4 and "<LR>" not in plan.split("(phase 2:")[0]
  # A dry run on a DIR the archive has not been restored into says that its runs show as to do.
  assert rc.main(_args(tmp_path / "fourth", archive, "--dry_run")) == 0
  first = capsys.readouterr().out.splitlines()[0]
  n = len(list(archive.glob("synthesis/*")) + list(archive.glob("regression/*/*/*")))
  assert first.startswith(f"--archive {archive}: its {n} runs are restored when the launch")
  assert not (tmp_path / "fourth").exists()


def test_the_untrained_control_needs_only_the_archived_config_of_its_synthesis_runs(
  rc, tmp_path, monkeypatch
):
  """ "untrained" regresses a view-synthesis run's initial pose system, which its config.json and
  record.json make (`restore.load_model`): the archive keeps them beside the run's record, so on
  a new machine the control runs without training those runs again; from an archive that lacks
  them they are trained again, as for "ours"."""
  ran = []
  monkeypatch.setattr(launch, "run_job", fake_run_job(rc, ran))
  archive = tmp_path / "archive"

  def args(out):
    return [
      *("--size", "protocol", "--settings", "car", "--representations", "untrained"),
      *("--skip_figures", "--out", str(out), "--archive", str(archive)),
    ]

  def forget_the_regressions():
    for d in archive.glob("regression/car/untrained/*"):
      (d / "run.json").unlink()
      d.rmdir()

  assert rc.execute(rc.make(args(tmp_path / "first"))) == []
  syn = sorted(n for n in ran if n.startswith("synthesis_"))
  seeds = plan_lib.plans()["protocol"].seeds_for("car")
  assert syn == sorted(f"synthesis_car_seed{k}" for k in seeds)
  assert ran[-1].startswith("regression_car_untrained_")
  config = archive / "synthesis" / "car_seed3" / "config.json"
  trained = tmp_path / "first" / "synthesis" / "car_seed3" / "config.json"
  assert config.read_text() == trained.read_text()
  forget_the_regressions()
  ran.clear()
  assert rc.main(args(tmp_path / "second")) == 0
  grid = "lr1e-4-lr3e-4-lr1e-3-lr3e-3-lr1e-2"
  assert [n.rsplit("_", 1)[0] for n in ran] == [f"regression_car_untrained_{grid}"]
  second = tmp_path / "second" / "synthesis" / "car_seed3"
  assert rc.archived_only(str(second))
  assert (second / "config.json").read_text() == config.read_text()
  # An archive without the configs (kept before they were): the runs are trained again.
  forget_the_regressions()
  for path in archive.glob("synthesis/*/config.json"):
    path.unlink()
  ran.clear()
  assert rc.main(args(tmp_path / "third")) == 0
  assert sorted(n for n in ran if n.startswith("synthesis_")) == syn


@pytest.mark.parametrize("pose_bytes", [28_278, 1_081_462])  # the car's, the area's (quick)
def test_a_small_final_pose_system_is_archived_and_read_without_training_its_run_again(
  rc, tmp_path, monkeypatch, pose_bytes
):
  """A view-synthesis run's final pose system (pose_system.npz) up to POSE_FILE_LIMIT bytes is
  kept in the archive with its config: on a new machine "ours" regresses it without the run
  being trained again. A larger one stays out of the archive (committed to git), and its run is
  trained again while a regression still reads it."""
  ran = []
  monkeypatch.setattr(launch, "run_job", fake_run_job(rc, ran, pose_bytes=pose_bytes))
  archive = tmp_path / "archive"
  assert rc.execute(rc.make(_args(tmp_path / "first", archive))) == []
  small = pose_bytes <= archive_lib.POSE_FILE_LIMIT
  assert (archive / "synthesis" / "car_seed2" / "pose_system.npz").exists() == small
  shutil.rmtree(archive / "regression" / "car" / "ours" / "lr1e-3_seed2")
  ran.clear()
  assert rc.main(_args(tmp_path / "second", archive)) == 0
  again = [] if small else ["synthesis_car_seed2"]
  assert ran == [*again, "regression_car_ours_lr1e-3_seed2"]
  second = tmp_path / "second" / "synthesis" / "car_seed2"
  if small:
    pose = (second / "pose_system.npz").read_bytes()
    assert pose == (archive / "synthesis" / "car_seed2" / "pose_system.npz").read_bytes()


def test_the_archives_figures_are_restored_over_older_ones_in_dir(tmp_path):
  """A figure remade in the archive (or brought by a checkout) replaces DIR's older copy when a
  launch restores, so that the sync after each run does not copy DIR's old one back over it; a
  figure only DIR has is kept, and synced into the archive."""
  archive, out = tmp_path / "archive", tmp_path / "out"
  os.makedirs(archive)
  os.makedirs(out)
  (archive / "noise_gibson.md").write_text("every pose input\n")
  (out / "noise_gibson.md").write_text("a launch's own runs only\n")
  (out / "curve_gibson.md").write_text("only in DIR\n")
  assert archive_lib.restore(str(archive), str(out)) == 0  # no runs: the figures only
  assert (out / "noise_gibson.md").read_text() == "every pose input\n"
  archive_lib.sync(str(out), str(archive))
  assert (archive / "noise_gibson.md").read_text() == "every pose input\n"
  assert (archive / "curve_gibson.md").read_text() == "only in DIR\n"


def test_an_archived_table_names_the_archived_runs_not_dirs(tmp_path, monkeypatch):
  """A table the launch wrote in DIR names DIR's runs by their absolute paths; its archived copy
  names the same runs in the archive, by the archive's path from the working directory (the
  repository root), so that it is the table the archived records give. Figures are copied as
  they are."""
  monkeypatch.chdir(tmp_path)
  out = tmp_path / "runs" / "protocol"
  os.makedirs(out)
  table = f"Runs: gibson_seed0: `{out}/synthesis/gibson_seed0`; `{out}/synthesis/gibson_seed1`\n"
  (out / "curve_synthesis_gibson.md").write_text(table)
  (out / "curve_synthesis_gibson.png").write_bytes(str(out).encode())
  assert archive_lib.sync(str(out), os.path.join("results", "protocol")) == 2
  archived = tmp_path / "results" / "protocol"
  assert (archived / "curve_synthesis_gibson.md").read_text() == (
    "Runs: gibson_seed0: `results/protocol/synthesis/gibson_seed0`; "
    "`results/protocol/synthesis/gibson_seed1`\n"
  )
  assert (archived / "curve_synthesis_gibson.png").read_bytes() == str(out).encode()
  assert archive_lib.sync(str(out), os.path.join("results", "protocol")) == 0  # unchanged
  # An archive outside the working directory is named by its absolute path.
  elsewhere = tmp_path.parent / f"{tmp_path.name}_archive"
  archive_lib.sync(str(out), str(elsewhere))
  assert (
    f"`{elsewhere}/synthesis/gibson_seed0`" in (elsewhere / "curve_synthesis_gibson.md").read_text()
  )


def test_a_raised_cap_resumes_a_synthesis_run_that_reached_the_old_one(rc, tmp_path):
  wd = tmp_path / "syn"
  wd.mkdir()
  argv = ["python", "-m", "camrep.main", "--config.total_steps=4800"]
  job = rc.Job("synthesis_x", argv, str(wd), 1, "synthesis")

  def final(step, stopped_early):
    with open(wd / "final_metrics.json", "w") as f:
      json.dump({"complete": True, "step": step, "stopping": {"stopped_early": stopped_early}}, f)

  final(2400, False)  # reached the old cap of 2,400
  assert not job.done()
  assert rc.synthesis_done(rc.read_final(str(wd)), argv[:3])  # no cap asked: complete is done
  final(4800, False)
  assert job.done()
  final(1200, True)  # stopped by its plateau rule before the cap
  assert job.done()
  (wd / "config.json").write_text(json.dumps({"total_steps": 2400}))
  assert not job.done()  # stopped under another cap: stale (its rule followed that cap)
  (wd / "config.json").write_text(json.dumps({"total_steps": 4800}))
  assert job.done()
  os.remove(wd / "final_metrics.json")
  assert not job.done()


def test_a_synthesis_run_that_trains_on_loses_its_old_evaluation(rc, tmp_path, monkeypatch):
  """A run resumed past its old cap is evaluated again: its old eval/noise.json is removed
  before it trains (the evaluation job is then not done and runs after it)."""
  ran = []
  monkeypatch.setattr(launch, "run_job", lambda job, logs, **kw: ran.append(job.name) or True)
  the_launch = rc.make(_args(tmp_path / "out", tmp_path / "archive")[:-2])
  the_launch.figures = rc.figure_jobs(
    the_launch.out, the_launch.plan, the_launch.synth, the_launch.python
  )
  wd = tmp_path / "out" / "synthesis" / "car_seed0"
  os.makedirs(wd / "eval")
  os.makedirs(wd / "checkpoints" / "2400")
  with open(wd / "final_metrics.json", "w") as f:
    json.dump({"complete": True, "step": 2400, "stopping": {"stopped_early": False}}, f)
  open(wd / "eval" / "noise.json", "w").close()
  jobs = rc.synthesis_of_seed(the_launch, 0)
  assert rc.run_synthesis(the_launch, jobs, str(tmp_path / "logs"), dict(at_once=1)) == []
  assert not (wd / "eval" / "noise.json").exists()
  assert ran == ["synthesis_car_seed0", "evaluate_car_seed0"]


def test_a_convdraw_run_of_another_length_is_trained_again_from_scratch(
  rc, tmp_path, monkeypatch, capsys
):
  """GQN's ConvDRAW at converge size trains 4x its quick length with its schedules stretched to
  it. A run complete at the quick length cannot resume (its schedules were fractions of 2,000
  steps): the launcher removes it, says so, and trains it again; a plateau run at an old cap
  resumes instead (`--config.allow_changes` names total_steps)."""
  ran = []
  monkeypatch.setattr(launch, "run_job", lambda job, logs, **kw: ran.append(job.name) or True)
  args = _args(tmp_path / "out", tmp_path / "archive")[:-2]
  args[args.index("car")] = "gqn"
  the_launch = rc.make([*args, "--noise_runs", "--noise_kinds", "convdraw"])
  job = next(j for j in the_launch.synth if j.name == "synthesis_gqn_convdraw_seed0")
  assert _flag(job.argv, "total_steps") == str(the_launch.plan.convdraw_steps) == "8000"
  assert _flag(job.argv, "loss.sigma_anneal_steps") == "800"
  assert _flag(job.argv, "optax.anneal_steps") == "6400"
  assert _flag(job.argv, "loss.kl_anneal_steps") == "4000"
  assert not rc.resumable(job.argv) and "--config.stop.window=0.25" not in job.argv
  plateau = next(j for j in the_launch.synth if j.name == "synthesis_gqn_seed0")
  assert rc.resumable(plateau.argv)
  wd = tmp_path / "out" / "synthesis" / "gqn_convdraw_seed0"
  os.makedirs(wd / "checkpoints" / "2000")
  with open(wd / "final_metrics.json", "w") as f:
    json.dump({"complete": True, "step": 2000}, f)
  assert rc.run_synthesis(the_launch, [job], str(tmp_path / "logs"), dict(at_once=1)) == []
  assert ran == ["synthesis_gqn_convdraw_seed0"] and not wd.exists()  # removed, then trained
  assert "complete at step 2000, not at the 8000 steps asked" in capsys.readouterr().out


@pytest.mark.parametrize("how", ["ctrl-c", "sigterm"])
def test_an_interrupted_launch_says_how_to_resume_instead_of_a_traceback(
  rc, tmp_path, monkeypatch, capsys, how
):
  """Ctrl-C or SIGTERM (`kill`, `timeout` around a chunk) ends the launch with exit status 130
  and one line on what was kept and how to go on; the runs finished before it stay archived, and
  the process's own SIGTERM handling is given back."""
  ran = []
  fake = fake_run_job(rc, ran)
  before = signal.getsignal(signal.SIGTERM)

  def run_job(job, logs, *, index, env=None):
    if len(ran) == 2:
      if how == "sigterm":
        os.kill(os.getpid(), signal.SIGTERM)
      raise KeyboardInterrupt
    return fake(job, logs, index=index, env=env)

  monkeypatch.setattr(launch, "run_job", run_job)
  out, archive = tmp_path / "out", tmp_path / "archive"
  assert rc.main(_args(out, archive)) == 130
  err = capsys.readouterr().err
  assert "interrupted after" in err and f"archived in {archive}" in err and "Traceback" not in err
  assert (archive / "synthesis" / "car_seed0" / "run.json").exists()
  assert signal.getsignal(signal.SIGTERM) == before


@pytest.mark.parametrize("extend", [None, 3])
def test_extend_grid_sets_how_far_phase_1_follows_a_choice_at_the_edge(
  rc, tmp_path, monkeypatch, extend
):
  """A choice that stays at the grid's top gets the plan's 2 extensions, or `--extend_grid N`;
  a rerun with a larger N resumes: only the new lr for seed 0, then the later seeds at it."""
  ran = []
  monkeypatch.setattr(launch, "run_job", fake_run_job(rc, ran, score=lambda lr: 1.0 / lr))
  out, archive = tmp_path / "out", tmp_path / "archive"
  flags = [] if extend is None else ["--extend_grid", str(extend)]
  assert rc.main(_args(out, archive, "--representations", "quat", *flags)) == 0
  seed0 = sorted(n for n in ran if n.startswith("regression_car_quat_") and n.endswith("_seed0"))
  assert len(seed0) == 3 + (2 if extend is None else extend)
  top = "lr3e-2" if extend is None else "lr1e-1"  # the car grid (3e-4, 1e-3, 3e-3), then x3 steps
  assert [n for n in ran if n.endswith(("_seed1", "_seed2")) and "regression" in n] == [
    f"regression_car_quat_{top}_seed1",
    f"regression_car_quat_{top}_seed2",
  ]
  if extend is None:  # resumed with one more extension: seed 0 at 1e-1, then seeds 1, 2 there
    ran.clear()
    assert rc.main(_args(out, archive, "--representations", "quat", "--extend_grid", "3")) == 0
    assert [n for n in ran if n.startswith("regression_")] == [
      "regression_car_quat_lr1e-1_seed0",
      "regression_car_quat_lr1e-1_seed1",
      "regression_car_quat_lr1e-1_seed2",
    ]
  with pytest.raises(SystemExit):
    rc.parse(["--size", "quick", "--out", str(out), "--extend_grid", "1"])


def test_a_launch_of_one_setting_keeps_the_other_columns_of_table1(rc, tmp_path):
  """table1.md is rewritten by every launch that has a Table 1 setting; it reads all three
  settings' runs in DIR, so a car-only chunk does not drop the rooms and area columns."""
  (table1,) = [j for j in rc.table_jobs(str(tmp_path), "py", ["car"]) if j.name == "table1"]
  runs = table1.argv[table1.argv.index("--runs") + 1 : table1.argv.index("--out")]
  assert runs == [str(tmp_path / "regression" / s / "*" / "*") for s in ("car", "gqn", "gibson")]
  assert not [j for j in rc.table_jobs(str(tmp_path), "py", ["seven_scenes"]) if j.name == "table1"]


def test_a_launch_of_one_noise_kind_draws_the_pose_inputs_trained_before(
  rc, tmp_path, monkeypatch, capsys
):
  """A launch of `--noise_kinds convdraw` on a column whose low-dimensional runs an earlier launch
  trained (or the archive restored) draws its noise figure and synthesis curves from all of them,
  in the order a full launch names them, not from its own runs alone: the archive's figures would
  lose the other pose inputs. Another column's runs stay out of it."""
  out, archive = tmp_path / "out", tmp_path / "archive"
  for name in ("gibson_lowdim_seed0", "gibson_lowdim_seed1", "gibson_lowdim_seed2", "gqn_seed0"):
    wd = out / "synthesis" / name
    os.makedirs(wd / "eval")
    (wd / "config.json").write_text(json.dumps({"argv": []}))
    (wd / "metrics.jsonl").write_text('{"step": 1, "eval/psnr": 15.0}\n')
    (wd / "final_metrics.json").write_text(json.dumps({"complete": True, "step": 2400}))
    (wd / "eval" / "noise.json").write_text(json.dumps({"alphas": [0.0], "psnr": [15.0]}))
  unevaluated = out / "synthesis" / "gibson_mlp_seed0"  # complete, no noise test: curves only
  os.makedirs(unevaluated)
  (unevaluated / "config.json").write_text(json.dumps({"argv": []}))
  (unevaluated / "final_metrics.json").write_text(json.dumps({"complete": True, "step": 2400}))
  ran, argv = [], {}
  fake = fake_run_job(rc, ran)

  def run_job(job, logs, **kw):
    argv[job.name] = job.argv
    return fake(job, logs, **kw)

  monkeypatch.setattr(launch, "run_job", run_job)
  monkeypatch.setattr(launch, "chosen_lr", lambda *a: 1e-3)  # phase 1's choice (car's scores)
  args = _args(out, archive, "--noise_runs", "--noise_kinds", "convdraw")
  args[args.index("car")] = "gibson"
  args[args.index("ours,quat")] = "ours"
  args.remove("--skip_figures")
  assert rc.main(args) == 0
  # A dry run lists an evaluation whose noise curve is recorded as done (the stand-in above
  # evaluates nothing: seed 0's curve is written here).
  (out / "synthesis" / "gibson_seed0" / "eval").mkdir()
  (out / "synthesis" / "gibson_seed0" / "eval" / "noise.json").write_text('{"alphas": [0.0]}')
  capsys.readouterr()
  assert rc.main([*args, "--dry_run"]) == 0
  plan = [line for line in capsys.readouterr().out.splitlines() if ".evaluate " in line]
  state = {os.path.basename(line.split()[-1]): line.split("]")[0] + "]" for line in plan}
  assert state["gibson_seed0"] == "[done]" and state["gibson_seed1"] == "[~2m00s]"
  noise = argv["noise_figure_gibson"]
  drawn = [os.path.basename(a) for a in noise[noise.index("--runs") + 1 : noise.index("--png")]]
  seeds = ("seed0", "seed1", "seed2")
  assert drawn == [f"gibson{k}_{s}" for k in ("", "_lowdim", "_convdraw") for s in seeds]
  curve = argv["curve_synthesis_gibson"]
  drawn = [os.path.basename(a) for a in curve[curve.index("--runs") + 1 : curve.index("--title")]]
  kinds = ("", "_lowdim", "_mlp", "_convdraw")  # gibson regresses no MLP: NOISE_INPUTS order
  assert drawn == [f"gibson{k}_{s}" for k in kinds for s in seeds if k != "_mlp" or s == "seed0"]
  assert not [n for n in argv if n.endswith("_gqn")]
  # The rooms' run is in DIR, evaluated, and still no rooms figure was drawn above.
  assert [n for n in launch.finished_synthesis(str(out), evaluated=True) if "gqn" in n] == [
    "gqn_seed0"
  ]


# ------------------------------------------------------------------------ a shared folder


def test_a_second_launch_on_one_dir_is_refused_naming_the_first(rc, tmp_path, capsys):
  """One launch per DIR: the second refuses before it writes anything, naming the first's PID,
  host and start time; a dry run (read only) is not refused."""
  from camrep.runtime import workdir as workdir_lib

  out = tmp_path / "out"
  first = workdir_lib.WorkdirLock(str(out.mkdir() or out))
  first.acquire()
  try:
    assert rc.main(_args(out, tmp_path / "archive")) == 2
    err = capsys.readouterr().err
    h = first.holder()
    assert err.startswith("error: --out") and "in use by another launch" in err
    assert f"PID {h['pid']} on {h['host']}, started {h['started']}" in err
    assert sorted(os.listdir(out)) == [".camrep.lock"]  # nothing restored or started
    assert rc.main([*_args(out, tmp_path / "archive"), "--dry_run"]) == 0
  finally:
    first.release()


def test_an_archive_or_out_that_is_a_file_is_an_error_line(rc, tmp_path, capsys):
  f = tmp_path / "file"
  f.write_text("x")
  for args in (_args(tmp_path / "out", f), _args(f, tmp_path / "archive")):
    with pytest.raises(SystemExit) as e:
      rc.main(args)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "error:" in err and f"{f} is a file, not a directory" in err and "Traceback" not in err


def test_a_representation_the_sizes_columns_lack_is_an_error_line_not_an_empty_launch(
  rc, tmp_path, capsys
):
  """A misspelt --representations, or a control at a size without controls, would plan no run
  and exit 0: it is refused, naming what the columns offer."""
  for wrong in ("qaut", "untrained"):
    args = _args(tmp_path / "out", tmp_path / "archive")
    args[args.index("ours,quat")] = f"ours,{wrong}"
    with pytest.raises(SystemExit) as e:
      rc.main(args)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert f"--representations: ['{wrong}'] not in the converge size's columns ['car']" in err
    assert "choose from ['axis_angle', 'euler'," in err and "Traceback" not in err
  assert not (tmp_path / "out").exists()
  args = _args(tmp_path / "out", tmp_path / "archive", "--dry_run")
  args[args.index("converge")] = "protocol"
  args[args.index("ours,quat")] = "untrained"
  assert rc.main(args) == 0  # the protocol size's controls are its columns'


def test_a_cut_record_in_the_archive_is_trained_again_not_taken_as_finished(
  rc, tmp_path, monkeypatch, capsys
):
  """A truncated results.json (an archive of whole run files) or run.json in the archive is
  named and not restored: the run trains again and its archived record is rewritten whole."""
  ran = []
  monkeypatch.setattr(launch, "run_job", fake_run_job(rc, ran))
  archive = tmp_path / "archive"
  assert rc.execute(rc.make(_args(tmp_path / "first", archive))) == []
  cut = archive / "regression" / "car" / "quat" / "lr3e-3_seed0" / "run.json"
  cut.write_text(cut.read_text()[:50])
  old = archive / "regression" / "car" / "quat" / "lr3e-4_seed0"  # an old-style archived run
  (old / "run.json").unlink()
  (old / "results.json").write_text('{"setting": "car", "representation": "qu')
  ran.clear()
  assert rc.main(_args(tmp_path / "second", archive)) == 0
  captured = capsys.readouterr()
  for path in (cut, old / "results.json"):
    assert f"the archived run {path.parent} cannot be read ({path}" in captured.out
  assert sorted(ran) == ["regression_car_quat_lr3e-3_seed0", "regression_car_quat_lr3e-4_seed0"]
  assert runs.load(str(cut.parent)).results["lr"] == 3e-3  # rewritten whole


@pytest.mark.parametrize("damaged", ["results.json", "errors_test.npz"])
def test_a_damaged_run_in_dir_is_named_set_aside_and_trained_again(
  rc, tmp_path, monkeypatch, capsys, damaged
):
  """A finished-looking run whose results.json is cut or whose errors_test.npz is damaged is not
  finished: the launch names the file, keeps it as <name>.damaged and trains the run again."""
  ran = []
  monkeypatch.setattr(launch, "run_job", fake_run_job(rc, ran))
  out = tmp_path / "out"
  args = [a for a in _args(out, tmp_path / "archive") if a != "--archive"][:-1]
  assert rc.main(args) == 0
  wd = out / "regression" / "car" / "ours" / "lr1e-3_seed1"
  path = wd / damaged
  path.write_bytes(path.read_bytes()[:30])
  ran.clear()
  assert rc.main(args) == 0
  text = capsys.readouterr().out
  assert ran == ["regression_car_ours_lr1e-3_seed1"]
  assert f"warning: {path} cannot be read" in text and f"kept as {path}.damaged" in text
  assert (wd / f"{damaged}.damaged").exists() and runs.damage(str(wd)) is None


@pytest.mark.parametrize("resumes", [False, True])
def test_the_stop_message_says_what_becomes_of_the_runs_in_flight(
  rc, tmp_path, monkeypatch, capsys, resumes
):
  """Stopped mid-launch, the message says that view-synthesis runs resume from their last
  checkpoint, and that regression runs start over, or resume where the regression stage keeps
  checkpoints (its config has a checkpoint period)."""

  def run_job(job, logs, *, index, env=None):
    raise KeyboardInterrupt

  monkeypatch.setattr(launch, "run_job", run_job)
  monkeypatch.setattr(command, "regression_resumes", lambda: resumes)
  assert rc.main(_args(tmp_path / "out", tmp_path / "archive")) == 130
  err = capsys.readouterr().err
  assert "view-synthesis runs resume from their last checkpoint" in err
  want = "regression runs resume from their last checkpoint" if resumes else "start over"
  assert want in err and "resume from their last checkpoints when" not in err
  assert not (tmp_path / "out" / ".camrep.lock").exists()  # the lock is given back


def test_the_stop_message_of_this_checkout_says_regression_runs_resume():
  """The unpatched message: regression runs keep checkpoints (their config has a period, read by
  the run frame), so a stopped one resumes (tests/test_regression_resume.py runs it)."""
  from camrep.configs import regression
  from camrep.regression import config_schema

  assert command.regression_resumes()
  assert regression.get_config("quick").ckpt_every_steps > 0
  assert "ckpt_every_steps" in config_schema.SCHEMA
  message = command.interrupted_message("1 s", "")
  assert message.endswith("regression runs resume from their last checkpoint too")


def test_a_stopped_launch_lets_its_run_save_before_it_ends(rc, tmp_path, monkeypatch):
  """Ctrl-C while a run is in flight: the run gets SIGTERM (a training run saves a checkpoint
  and exits) and the launcher waits for it, instead of killing it at once."""
  import sys

  saved = tmp_path / "saved"
  code = (
    "import signal, sys, time\n"
    f"signal.signal(signal.SIGTERM, lambda *a: (open({str(saved)!r}, 'w').close(), sys.exit(0)))\n"
    "print('ready', flush=True)\n"
    "time.sleep(30)\n"
  )
  job = launch.Job("slow", [sys.executable, "-c", code], "", 1)
  log = tmp_path / "logs" / "slow.log"
  real_wait = launch._wait

  # Ctrl-C arrives once the run says it has set up its handler (a loaded machine can take
  # seconds to start Python).
  def wait(proc, timeout):
    rc = real_wait(proc, timeout)
    if rc is None and "ready" in log.read_text().splitlines():
      raise KeyboardInterrupt
    return rc

  monkeypatch.setattr(launch, "_wait", wait)
  with pytest.raises(KeyboardInterrupt):
    launch.run_job(job, str(tmp_path / "logs"), index="1/1")
  assert saved.exists()


def test_a_stop_with_several_jobs_at_once_starts_no_other_job(rc, tmp_path, monkeypatch):
  started = []

  def run_job(job, logs, *, index, env=None):
    started.append(job.name)
    if job.name == "a":
      raise KeyboardInterrupt
    time.sleep(0.3)  # a run in flight when the stop comes
    return True

  monkeypatch.setattr(launch, "run_job", run_job)
  jobs = [launch.Job(n, ["true"], "", 1) for n in ("a", "b", "c", "d", "e")]
  with pytest.raises(KeyboardInterrupt):
    launch.run_jobs(jobs, str(tmp_path / "logs"), at_once=2, label="")
  assert "a" in started and len(started) <= 2


def test_a_run_stopped_at_its_plateau_under_another_cap_is_stale_with_its_readers(
  rc, tmp_path, monkeypatch, capsys
):
  """A view-synthesis run that stopped at its plateau under an older cap (its rule's window and
  evaluations follow the cap) is not done, nor are the regressions that read its pose system:
  the dry run names them, a launch moves them (in DIR and the archive) to stale/<path>.stale-<cap>
  and trains them again; runs under the plan's cap and baselines stay."""
  ran = []
  monkeypatch.setattr(launch, "run_job", fake_run_job(rc, ran))
  out, archive = tmp_path / "out", tmp_path / "archive"
  args = [a if a != "ours,quat" else "mlp,quat" for a in _args(out, archive)]
  assert rc.main(args) == 0
  cap = int(_flag(rc.make(args).synth[0].argv, "total_steps"))

  def stopped(name, trained):
    wd = out / "synthesis" / name
    config = json.loads((wd / "config.json").read_text())
    (wd / "config.json").write_text(json.dumps({**config, "total_steps": trained}))
    final = {"complete": True, "step": trained // 2, "stopping": {"stopped_early": True}}
    (wd / "final_metrics.json").write_text(json.dumps(final))

  stopped("car_mlp_seed0", cap // 2)  # stopped under an older cap: stale
  stopped("car_mlp_seed1", cap)  # stopped under the plan's cap: done
  archive_lib.sync(str(out), str(archive))
  readers = sorted(p.name for p in (out / "regression" / "car" / "mlp").glob("*_seed0"))
  assert len(readers) == 3  # phase 1: seed 0 at every lr
  ran.clear()
  assert rc.main([*args, "--dry_run"]) == 0
  text = capsys.readouterr().out
  stale = [line for line in text.splitlines() if line.startswith("  stale: ")]
  assert len(stale) == 2 * (1 + len(readers))  # DIR and the archive alike
  for root in (out, archive):
    aside = f"{root}/stale/synthesis/car_mlp_seed0.stale-{cap // 2}"
    assert f"  stale: {root}/synthesis/car_mlp_seed0: stopped at its plateau under " \
           f"--config.total_steps={cap // 2}, the plan's cap is {cap}; the launch moves it to " \
           f"{aside} and trains it again" in text  # fmt: skip
    for r in readers:
      assert f"  stale: {root}/regression/car/mlp/{r}: reads synthesis/car_mlp_seed0" in text
  assert "car_mlp_seed1" not in "".join(stale) and "/quat/" not in "".join(stale)
  assert ran == []
  # The launch: moved aside (never deleted), then trained again; nothing else.
  assert rc.main(args) == 0
  assert ran[0] == "synthesis_car_mlp_seed0"
  assert sorted(ran[1:]) == [f"regression_car_mlp_{r}" for r in readers]
  for root in (out, archive):
    aside = root / "stale" / "synthesis" / f"car_mlp_seed0.stale-{cap // 2}"
    assert runs.load(str(aside)).config["total_steps"] == cap // 2
    for r in readers:
      assert (root / "stale" / "regression" / "car" / "mlp" / f"{r}.stale-{cap // 2}").is_dir()
    assert runs.load(str(root / "synthesis" / "car_mlp_seed0")).final["step"] == cap
  assert capsys.readouterr().out.count("; moved to ") == len(stale)
  assert rc.main([*args, "--dry_run"]) == 0
  assert "stale:" not in capsys.readouterr().out

"""The comparison launcher (`python -m camrep.comparison`): its plans, commands, estimates and
job order, on dry runs and fabricated runs (no training)."""

from __future__ import annotations

import dataclasses
import importlib
import os
import subprocess
import sys

import pytest

from camrep.comparison import command, launch, plan
from camrep.runtime import frame as frame_lib
from camrep.runtime import xla_cpu
from camrep.synthesis import config_schema
from tests.test_tables import _summary, _write

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_dry_run(tmp_path, capsys):
  assert command.main(["--size", "quick", "--out", str(tmp_path), "--dry_run"]) == 0
  text = capsys.readouterr().out
  first = text.splitlines()[0]
  assert "regression runs" in first and "estimated" in first and "2 CPU cores" in first
  assert (
    "--config=configs/gqn.py:quick" in text and "--config=configs/seven_scenes.py:quick" in text
  )
  assert "--config.representation=axis_angle" in text and "experiments/table2.py" in text
  assert f"--config.synthesis_workdir={tmp_path}/synthesis/car\n" in text
  assert "--config.optax.lr=<LR>" in text  # phase 2: other seeds at the chosen lr
  # Phase 2 reads the lr that seed 0's validation chose.
  quick = plan.plans()["quick"]
  reg = os.path.join(str(tmp_path), "regression")
  _write(reg, "car", "quat", 1e-3, 0, _summary("car", 3.0), _summary("car", 1.0))
  _write(reg, "car", "quat", 3e-3, 0, _summary("car", 2.0), _summary("car", 9.0))
  assert launch.chosen_lr(str(tmp_path), "car", "quat", quick) == 3e-3
  # A full grid chooses on the validation mean over the seeds (as the tables do), not seed 0's:
  # seeds 1 and 2 prefer 1e-3 by far.
  for seed in (1, 2):
    _write(reg, "car", "quat", 1e-3, seed, _summary("car", 1.0), _summary("car", 1.0))
    _write(reg, "car", "quat", 3e-3, seed, _summary("car", 9.0), _summary("car", 1.0))
  protocol = plan.plans()["protocol"]
  assert protocol.full_grid and launch.chosen_lr(str(tmp_path), "car", "quat", protocol) == 1e-3
  assert launch.chosen_lr(str(tmp_path), "car", "quat", quick) == 3e-3  # seed 0's choice
  # --full_grid with a plan of two phases: the launch's plan says so, for its choices.
  L = launch.make_launch(quick, str(tmp_path), settings=["car"], full_grid=True)
  assert L.plan.full_grid and not L.later
  assert (
    command.main(["--size", "paper", "--out", str(tmp_path), "--dry_run", "--settings", "car"]) == 0
  )
  assert "--config=configs/regression.py:car " in capsys.readouterr().out
  args = ["--size", "medium", "--out", str(tmp_path), "--dry_run", "--jobs", "4"]
  assert command.main(args) == 0
  text = capsys.readouterr().out
  assert "4 jobs at a time" in text.splitlines()[0] and "derived, not measured" in text
  assert "--config=configs/gqn.py:medium" in text
  assert "--config=configs/regression.py:car,medium" in text
  # --noise_runs: the GQN noise figure's other pose inputs and GQN's own generator (not medium).
  noise = ["--out", str(tmp_path), "--dry_run", "--settings", "gqn", "--noise_runs"]
  assert command.main(["--size", "quick", *noise]) == 0
  text = capsys.readouterr().out
  for name in ("gqn_lowdim", "gqn_mlp", "gqn_convdraw"):
    assert f"--workdir={tmp_path}/synthesis/{name}" in text
  assert "--config=configs/gqn_convdraw.py:quick" in text and "noise_figure.py" in text
  assert command.main(["--size", "medium", *noise, "--noise_kinds", "lowdim,convdraw"]) == 0
  text = capsys.readouterr().out
  assert "synthesis/gqn_lowdim" in text and "gqn_mlp" not in text and "convdraw" not in text


def test_jobs_run_at_once(tmp_path, monkeypatch):
  """--jobs N: N subprocesses at a time, each told its share of GPU memory and to run XLA:CPU on
  one thread (beside the XLA flags it has; a flag of its own wins), a regression grid its share of
  the cores as host devices; failures named."""
  monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION", raising=False)
  monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
  assert launch.job_env(1) is None
  env = launch.job_env(3)
  assert env["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.300"
  assert env["XLA_FLAGS"] == "--xla_dump_to=/tmp/x --xla_cpu_multi_thread_eigen=false"
  monkeypatch.setenv("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.2")
  monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true")
  env = launch.job_env(2)
  assert env["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.2"
  assert env["XLA_FLAGS"] == "--xla_cpu_multi_thread_eigen=true"
  # A regression grid beside others: its share of the cores as host devices (at least 1).
  grid = launch.Job("g", ["python", "-m", "camrep.regression"], "g", 1, "regression", ("g/a",))
  monkeypatch.setattr(xla_cpu, "usable_cores", lambda: 16)
  assert launch.sharing_cores(grid, 4).argv[-1] == "--host_devices=4"
  assert launch.sharing_cores(grid, 3).argv[-1] == "--host_devices=5"
  assert launch.sharing_cores(grid, 32).argv[-1] == "--host_devices=1"
  assert launch.sharing_cores(grid, 1) is grid  # alone: every core (the command's default)
  one = launch.Job("r", ["python", "-m", "camrep.regression"], "r", 1, "regression")
  assert launch.sharing_cores(one, 4) is one
  mine = dataclasses.replace(grid, argv=[*grid.argv, "--host_devices=2"])
  assert launch.sharing_cores(mine, 4) is mine
  monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION")
  monkeypatch.delenv("XLA_FLAGS")
  marks = tmp_path / "marks"
  marks.mkdir()
  # Each job waits (up to 20 s) until the other has started: only passes if both run at once.
  code = (
    "import os, sys, time; m, me, other, frac = sys.argv[1:5]; open(os.path.join(m, me), 'w');"
    "t = time.time()\nwhile not os.path.exists(os.path.join(m, other)) and time.time() - t < 20:"
    " time.sleep(0.05)\nassert os.path.exists(os.path.join(m, other));"
    "assert os.environ['XLA_PYTHON_CLIENT_MEM_FRACTION'] == frac;"
    "assert os.environ['XLA_FLAGS'] == '--xla_cpu_multi_thread_eigen=false';"
    "assert sys.argv[5:] == (['--host_devices=1'] if me == 'b' else [])"
  )
  monkeypatch.setattr(xla_cpu, "usable_cores", lambda: 2)
  jobs = [
    launch.Job(me, [sys.executable, "-c", code, str(marks), me, other, "0.450"], "", 1)
    for me, other in (("a", "b"), ("b", "a"))
  ]
  # "b" as a regression grid: its share of the 2 cores beside "a", one host device.
  jobs[1] = dataclasses.replace(jobs[1], members=(str(tmp_path / "b_member"),))
  fail = launch.Job("fails", [sys.executable, "-c", "raise SystemExit(3)"], "", 1)
  assert launch.run_jobs(jobs + [fail], str(tmp_path / "logs"), at_once=2, label="") == ["fails"]
  assert sorted(os.listdir(marks)) == ["a", "b"]


def test_converge_plan(tmp_path, capsys):
  """--size converge: >= 3 seeds per cell, the stopping rule on every regression, one
  synthesis run per seed paired with ours' regression seed, capture columns, an estimate; the
  lr grid extends while a choice is at its edge; --max_hours starts nothing after the deadline."""
  cap = tmp_path / "chair"
  cap.mkdir()
  out = str(tmp_path / "cmp")
  args = ["--size", "converge", "--out", out, "--dry_run", "--data", f"car_chair=nerf:{cap}"]
  assert command.main(args) == 0
  text = capsys.readouterr().out
  first = text.splitlines()[0]
  assert first.startswith("converge comparison") and "estimated" in first
  assert "phase-1 runs" in first and "edge" in first
  the_launch = command.make_launch(command.parse_args(args))
  converge = the_launch.plan
  assert len(converge.seeds) >= 3 and all(len(g) >= 3 for g in converge.lrs.values())
  cells = {}
  for j in the_launch.first:  # one program per column and representation (vectorised)
    assert j.members and launch.flag_value(j.argv, "--seeds") == "0"
    cells.setdefault(launch._group(j), set()).update(w.rpartition("_")[2] for w in j.members)
  for col, rep, seed in the_launch.later:
    cells[col, rep].add(f"seed{seed}")
  assert ("car_chair", "ours") in cells and ("seven_scenes", "ours") in cells
  assert all(len(seeds) >= 3 for seeds in cells.values())
  for j in the_launch.first:
    assert "--config.stop.min_improvement=0.02" in j.argv and "--config.eval_every_steps=" in (
      " ".join(j.argv)
    )
  ours = [j for j in the_launch.first if "--config.representation=ours" in j.argv]
  for j in ours:  # each member reads the synthesis run of its seed
    assert launch.flag_value(j.argv, "--config.synthesis_workdir").endswith("_seed{seed}")
    assert {os.path.basename(w) for w in launch.synthesis_reads(j)} == {
      f"{launch._group(j)[0]}_seed0"
    }
  syn = {j.name for j in the_launch.synth}
  assert {f"synthesis_car_chair_seed{k}" for k in range(3)} <= syn
  chair = next(j for j in the_launch.synth if j.name == "synthesis_car_chair_seed1")
  assert f"--config.data.dir={cap}" in chair.argv and "--config.seed=1" in chair.argv
  assert any("table1_car_chair.md" in " ".join(j.argv) for j in the_launch.tables)
  # The capture's MLP embedding has its own synthesis runs, which its mlp regressions read.
  mlp = next(j for j in the_launch.synth if j.name == "synthesis_car_chair_mlp_seed2")
  assert "--config.rep.kind=mlp" in mlp.argv and f"--config.data.dir={cap}" in mlp.argv
  assert "--config.data.scenes_per_device=1" in mlp.argv
  assert mlp.estimate_s == converge.synthesis_s["capture"] < converge.synthesis_s["car"]
  mlp_reg = [j for j in the_launch.first if j.name.startswith("regression_car_chair_mlp_")]
  wd = os.path.join(out, "synthesis", "car_chair_mlp_seed0")
  assert mlp_reg and all(launch.synthesis_reads(j) == {wd} for j in mlp_reg)
  assert launch.synthesis_column("car_chair_mlp_seed0", the_launch.data) == "car_chair"
  assert launch.synthesis_column("car_mlp_seed0", the_launch.data) == "car"
  noise = next(j for j in the_launch.figures if j.name == "noise_figure_car_chair")
  assert os.path.join(out, "synthesis", "car_chair_mlp_seed1") in noise.argv
  assert noise.argv[noise.argv.index("--column") + 1] == "chair, car setting"  # not "(car)"
  # The grid extends: car quat chose the highest lr of (3e-4, 1e-3, 3e-3) -> 1e-2 next.
  reg = os.path.join(out, "regression")

  def write(lr, val):  # named as the launcher names its workdirs (lr3e-3_seed0)
    _write(reg, "car", "quat", lr, 0, _summary("car", val), _summary("car", 1.0))
    wd = os.path.join(reg, "car", "quat", f"lr{lr:g}_seed0")
    os.rename(wd, os.path.join(reg, "car", "quat", f"{launch.lr_tag(lr)}_seed0"))

  for lr, val in ((3e-4, 3.0), (1e-3, 2.0), (3e-3, 1.0)):
    write(lr, val)
  assert launch.extension_lr(out, "car", "quat", converge) == 1e-2
  write(1e-2, 2.0)
  assert launch.extension_lr(out, "car", "quat", converge) is None  # 3e-3 now inside the grid
  assert launch.chosen_lr(out, "car", "quat", converge) == 3e-3
  curves = [j for j in launch.curve_jobs(the_launch) if j.name == "curve_car"]
  assert len(curves) == 1 and "--bands" in curves[0].argv
  title = curves[0].argv[curves[0].argv.index("--title") + 1]  # says what the score is
  assert title.startswith("car: validation score = rotation_error_deg mean / 2.85")
  assert os.path.join(reg, "car", "quat", "lr3e-3_seed0") in curves[0].argv
  assert os.path.join(reg, "car", "quat", "lr1e-3_seed0") not in curves[0].argv
  # A launch of one representation draws the column's other representations DIR holds too.
  _write(reg, "car", "euler", 1e-3, 0, _summary("car", 1.0), _summary("car", 1.0))
  euler = os.path.join(reg, "car", "euler", "lr1e-3_seed0")
  os.rename(os.path.join(reg, "car", "euler", "lr0.001_seed0"), euler)
  one = command.make_launch(command.parse_args([*args, "--representations", "quat"]))
  (curve,) = [j for j in launch.curve_jobs(one) if j.name == "curve_car"]
  runs = curve.argv[curve.argv.index("--runs") + 1 : curve.argv.index("--title")]
  assert runs == [euler, os.path.join(reg, "car", "quat", "lr3e-3_seed0")], runs
  # A workdir at the chosen lr that holds no finished run (a launch cut short, a plan with more
  # seeds) logged no curve: it is left out, not drawn as an error.
  os.makedirs(os.path.join(reg, "car", "quat", "lr3e-3_seed5", "checkpoints"))
  (curve,) = [j for j in launch.curve_jobs(one) if j.name == "curve_car"]
  assert curve.argv[curve.argv.index("--runs") + 1 : curve.argv.index("--title")] == runs
  assert [launch.half_decade(x, up=u) for x, u in ((1e-3, True), (3e-4, False), (1e-4, False))] == [
    3e-3,
    1e-4,
    3e-5,
  ]
  # --max_hours: past the deadline nothing starts, and that is not a failure.
  job = launch.Job("never", [sys.executable, "-c", "raise SystemExit(3)"], "", 1)
  assert launch.run_jobs([job], str(tmp_path / "logs"), at_once=1, label="", deadline=0.0) == []
  assert "not started (--max_hours)" in capsys.readouterr().out
  assert not os.path.exists(tmp_path / "logs" / "never.log")


def _synthesis_quick(setting):
  module = plan.settings()[setting]["synthesis_config"].removeprefix("configs/").removesuffix(".py")
  return importlib.import_module(f"camrep.configs.{module}").get_config("quick")


def test_converge_synthesis_to_its_plateau(tmp_path, capsys):
  """--size converge: every view-synthesis run but GQN's ConvDRAW gets a cap
  of 4x its quick steps and the plateau rule, flags its config accepts (ConvDRAW: 4x its quick
  length with its schedules stretched, no rule); the held-out PSNR
  curves of each column's synthesis runs are drawn with bands over seeds."""
  out = str(tmp_path / "cmp")
  args = ["--size", "converge", "--out", out, "--dry_run", "--noise_runs"]
  assert command.main(args) == 0
  assert "curve_synthesis_<column>" in capsys.readouterr().out
  the_launch = command.make_launch(command.parse_args(args))
  flags = {j.name: {a.split("=")[0]: a.split("=")[1] for a in j.argv[4:]} for j in the_launch.synth}
  assert flags["synthesis_car_seed2"]["--config.total_steps"] == "4800"
  assert flags["synthesis_car_mlp_seed0"]["--config.stop.min_steps"] == "1200"
  g = flags["synthesis_gqn_lowdim_seed1"]
  assert g["--config.total_steps"] == "8000" and g["--config.eval_every_steps"] == "400"
  assert g["--config.stop.min_improvement"] == "0.02" and g["--config.seed"] == "1"
  # GQN's generator: 4x its quick length, its schedules stretched to it, no plateau rule.
  draw = flags["synthesis_gqn_convdraw_seed0"]
  assert draw["--config.total_steps"] == "8000" and draw["--config.optax.anneal_steps"] == "6400"
  assert "--config.stop.window" not in draw
  # On the car: the same, on the car's family (the config's `:object` variant).
  car = next(j for j in the_launch.synth if j.name == "synthesis_car_convdraw_seed1")
  assert "--config=configs/gqn_convdraw.py:object" in car.argv
  assert flags["synthesis_car_convdraw_seed1"]["--config.total_steps"] == "8000"
  assert "--config.stop.window" not in flags["synthesis_car_convdraw_seed1"]
  assert car.estimate_s == the_launch.plan.synthesis_s["gqn_convdraw"]
  quick = importlib.import_module("camrep.configs.gqn_convdraw").get_config("quick")
  assert quick.optax.anneal_steps == 2000 * 8 // 10  # the fractions the stretch keeps
  # The flags fit the configs they go with: caps 4x their quick steps (the car 8x), the rule
  # and the permission to raise a cap accepted.
  for name in plan.SETTINGS:
    c = _synthesis_quick(name)
    caps = the_launch.plan.synthesis_caps
    assert caps[name] == (8 if name == "car" else 4) * c.total_steps
    plateau = dict(
      a.removeprefix("--config.").split("=") for a in plan.synthesis_flags(the_launch.plan, name)
    )
    for k, v in plateau.items():
      section, _, field = k.rpartition(".")
      node = c[section] if section else c
      kind = type(node[field])
      node[field] = v if kind is str else float(v) if kind is float else int(v)
    config_schema.validate(c, overridden=set(plateau))
    assert frame_lib.stopping_rule(c).active
  # Curves: one job per column over its synthesis workdirs that exist.
  for name in ("car_seed0", "car_seed1", "car_mlp_seed0", "gqn_seed0"):
    os.makedirs(os.path.join(out, "synthesis", name))
  jobs = {j.name: j.argv for j in launch.curve_jobs(the_launch)}
  car = jobs["curve_synthesis_car"]
  assert "eval/psnr" in car and "--bands" in car
  assert sum(a.startswith(os.path.join(out, "synthesis", "car")) for a in car) == 3
  assert "curve_synthesis_gqn" in jobs and "curve_synthesis_gibson" not in jobs


def test_crossed_seeds(tmp_path, capsys):
  """--crossed COLUMN: every regression seed of ours on every other synthesis
  seed, outside regression/ (never tabled), then experiments/seed_spread.py; off by default."""
  out = str(tmp_path / "cmp")
  args = ["--size", "converge", "--out", out, "--dry_run", "--settings", "car,gqn"]
  assert command.main([*args, "--crossed", "car"]) == 0
  text = capsys.readouterr().out
  assert "crossed seeds of car's ours: 6 more regression runs" in text
  the_launch = command.make_launch(command.parse_args([*args, "--crossed", "car"]))
  jobs = launch.crossed_jobs(the_launch, 1e-3)
  assert len(jobs) == 6 and len({j.name for j in jobs}) == 6
  job = next(j for j in jobs if j.name == "crossed_car_lr1e-3_seed0_syn2")
  assert f"--workdir={os.path.join(out, 'crossed', 'car', 'lr1e-3_seed0_syn2')}" in job.argv
  assert f"--config.synthesis_workdir={os.path.join(out, 'synthesis', 'car_seed2')}" in job.argv
  assert "--config.seed=0" in job.argv and "--config.representation=ours" in job.argv
  assert "--config.optax.lr=0.001" in job.argv and "--config.stop.min_improvement=0.02" in job.argv
  spread = launch.seed_spread_job(the_launch, 1e-3)
  assert "experiments/seed_spread.py" in spread.argv and "--decode" in spread.argv
  assert os.path.join(out, "regression", "car", "ours", "lr1e-3_seed*") in spread.argv
  # Off by default; refused where the sizes do not pair seeds or the column is not launched.
  assert launch.crossed_jobs(command.make_launch(command.parse_args(args)), 1e-3) == []
  for bad in (["--size", "quick", "--crossed", "car"], [*args, "--crossed", "gibson"]):
    with pytest.raises(SystemExit) as e:
      command.parse_args([*bad, "--out", out] if bad[1] == "quick" else bad)
    assert e.value.code == 2


def test_vectorised_regressions(tmp_path, capsys):
  """converge and medium train each column's and representation's regressions as one program
  (`python -m camrep.regression --lrs --seeds`): phase 1 over the lrs with seed 0, phase 2 over
  the later seeds at the lr seed 0's validation chose; the members are the runs' own workdirs
  (done when every one is); the estimate says what it saves. quick and paper run one process
  per run."""
  out = str(tmp_path / "cmp")
  args = ["--size", "converge", "--out", out, "--dry_run", "--settings", "car"]
  assert command.main(args) == 0
  text = capsys.readouterr().out
  assert "vectorised regressions" in text and "saves ~" in text
  assert f"--workdir={out}/regression/car/quat --lrs=0.0003,0.001,0.003 --seeds=0 " in text
  regressions = [x for x in text.splitlines() if "camrep.regression " in x]
  assert regressions and not any(
    "--config.seed=" in x or "--config.optax.lr=" in x for x in regressions
  )
  assert f"--workdir={out}/regression/car/quat '--lrs=<LR>' --seeds=1,2 " in text
  the_launch = command.make_launch(command.parse_args(args))
  converge = the_launch.plan
  assert converge.vectorise["startup_s"] > 0
  quat = next(j for j in the_launch.first if launch._group(j) == ("car", "quat"))
  reg = os.path.join(out, "regression")
  assert quat.workdir == os.path.join(reg, "car", "quat") and quat.members == tuple(
    os.path.join(reg, "car", "quat", f"{t}_seed0") for t in ("lr3e-4", "lr1e-3", "lr3e-3")
  )
  alone = 3 * converge.regression_s["car"]
  assert quat.estimate_s == plan.group_s(converge, "car", 3) < alone
  startup, speedup = converge.vectorise["startup_s"], converge.vectorise["step_speedup"]
  one = converge.regression_s["car"]
  assert quat.estimate_s == pytest.approx(startup + 3 * (one - startup) / speedup)
  ours = next(j for j in the_launch.first if launch._group(j) == ("car", "ours"))
  assert launch.flag_value(ours.argv, "--config.synthesis_workdir") == os.path.join(
    out, "synthesis", "car_seed{seed}"
  )
  # Phase 1 done for quat (3e-3 chosen): phase 2 is one program over seeds 1 and 2 at 3e-3.
  assert not quat.done()
  for lr, val in ((3e-4, 3.0), (1e-3, 2.0), (3e-3, 1.0)):
    _write(reg, "car", "quat", lr, 0, _summary("car", val), _summary("car", 1.0))
    os.rename(
      os.path.join(reg, "car", "quat", f"lr{lr:g}_seed0"),
      os.path.join(reg, "car", "quat", f"{launch.lr_tag(lr)}_seed0"),
    )
  assert quat.done()
  later = next(
    j for j in launch.phase2_grid_jobs(the_launch) if launch._group(j) == ("car", "quat")
  )
  assert launch.flag_value(later.argv, "--lrs") == "0.003"
  assert launch.flag_value(later.argv, "--seeds") == "1,2"
  assert [os.path.basename(w) for w in later.members] == ["lr3e-3_seed1", "lr3e-3_seed2"]
  ours2 = next(
    j for j in launch.phase2_grid_jobs(the_launch) if launch._group(j) == ("car", "ours")
  )
  assert launch.synthesis_reads(ours2) == {
    os.path.join(out, "synthesis", f"car_seed{k}") for k in (1, 2)
  }
  # --full_grid: one program over every lr and seed.
  full = command.make_launch(command.parse_args([*args, "--full_grid"]))
  quat = next(j for j in full.first if launch._group(j) == ("car", "quat"))
  assert len(quat.members) == 9 and launch.flag_value(quat.argv, "--seeds") == "0,1,2"
  assert not full.later
  # medium is vectorised too; quick and paper start one process per run.
  assert plan.plans()["medium"].vectorise
  for size in ("quick", "paper"):
    assert not plan.plans()[size].vectorise
    small = command.make_launch(command.parse_args(["--size", size, "--out", out, "--dry_run"]))
    assert all(not j.members and "--config.seed=0" in j.argv for j in small.first)


def _parsed_config(argv, monkeypatch):
  """The config a `python -m camrep.main` command line gives (its --config flags parsed here)."""
  from absl import flags
  from ml_collections import config_flags

  monkeypatch.chdir(ROOT)
  fv = flags.FlagValues()
  argv = ["camrep", *[a for a in argv if a.startswith("--config")]]
  config_flags.DEFINE_config_file("config", None, flag_values=fv, sys_argv=argv)
  fv(argv)
  return fv.config


def test_protocol_plan_capture_columns_hold_out_the_regressions_validation_views(
  tmp_path, monkeypatch
):
  """A capture column's view-synthesis runs evaluate (and stop) on the validation views carved
  from the capture's training views at the car regression's k; the same plan's converge size,
  which made results/converge, passes nothing (its runs resume as they were)."""
  import numpy as np

  from camrep.configs import regression as regression_config
  from camrep.data import prepare
  from camrep.synthesis import components
  from tests.test_captures import rig, write_llff

  root = write_llff(tmp_path / "obj", rig(16)[0], rng=np.random.default_rng(5))
  data = tmp_path / "data"
  prepare.prepare_source("llff", data, input_path=str(root), preset="small", progress=False)
  args = ["--out", str(tmp_path / "cmp"), "--dry_run", "--settings", "car"]
  args += ["--data", f"car_obj=llff:{data}"]
  syn = command.make_launch(command.parse_args(["--size", "protocol", *args])).synth
  capture = [j for j in syn if j.name.startswith("synthesis_car_obj")]
  car = [j for j in syn if j not in capture]
  assert capture and car
  fraction = regression_config.get_config("car,quick").data.validation_fraction
  for j in capture:
    assert "--config.evals.split=validation" in j.argv
    assert f"--config.data.validation_fraction={fraction:g}" in j.argv
  assert all("--config.data.validation_fraction" not in " ".join(j.argv) for j in car)
  c = _parsed_config(capture[0].argv, monkeypatch)
  config_schema.validate(c)  # every flag is a field the run uses, the split can be carved
  assert components.carved_validation(c) == 10 == round(1 / fraction)
  converge = command.make_launch(command.parse_args(["--size", "converge", *args])).synth
  assert all("--config.evals.split" not in " ".join(j.argv) for j in converge)


def test_protocol_plan(tmp_path, capsys, monkeypatch):
  """--size protocol: 10 seeds a cell on the area, 5 on the other settings (`seed_counts`), and
  each column's view-synthesis runs at its own seeds; every seed at every lr, the same lrs for every
  representation of a column and no extension, the control targets in every column (capture
  columns too) reading the right view-synthesis runs, 7-Scenes synthesis over all seven scenes,
  every view-synthesis run evaluated on at least 32 held-out targets."""
  cap = tmp_path / "chair"
  cap.mkdir()
  out = str(tmp_path / "cmp")
  args = ["--size", "protocol", "--out", out, "--dry_run", "--data", f"car_chair=nerf:{cap}"]
  assert command.main(args) == 0
  text = capsys.readouterr().out
  assert text.startswith("protocol comparison") and "estimated" in text.splitlines()[0]
  assert "after every seed's view synthesis, no phase 2" in text and "<LR>" not in text
  the_launch = command.make_launch(command.parse_args(args))
  p = the_launch.plan
  assert len(p.seeds) >= 10 and p.full_grid and p.extend_grid == 0 and not the_launch.later
  counts = {s: len(p.seeds_for(s)) for s in plan.SETTINGS}
  assert counts == {"gqn": 5, "car": 5, "gibson": 10, "seven_scenes": 5}
  cells, seeds_of = {}, {}
  for j in the_launch.first:  # the full grid: every seed at every lr, one program a group
    col, rep = launch._group(j)
    seeds_of[col] = p.seeds_for(launch.setting_of(col))
    lrs = tuple(float(x) for x in launch.flag_value(j.argv, "--lrs").split(","))
    assert lrs == p.lrs[launch.setting_of(col)]
    assert launch.flag_value(j.argv, "--seeds") == ",".join(map(str, seeds_of[col]))
    cells.setdefault(col, set()).add(rep)
  for col, reps in cells.items():
    assert {"ours", "untrained", "frozen_gen"} <= reps, col
  syn = {j.name.removeprefix("synthesis_"): j for j in the_launch.synth}
  for j in the_launch.first:
    col, rep = launch._group(j)
    reads = {os.path.basename(w) for w in launch.synthesis_reads(j)}
    if rep in ("ours", "untrained"):
      assert reads == {f"{col}_seed{k}" for k in seeds_of[col]}
    elif rep == "frozen_gen":
      assert reads == {f"{col}_frozen_gen_seed{k}" for k in seeds_of[col]}
    assert reads <= set(syn)
  # No view-synthesis run beyond its column's seeds: the car trains seeds 0-4 of its three kinds.
  assert sorted(n for n in syn if n.startswith("car_") and not n.startswith("car_chair")) == sorted(
    f"car{kind}_seed{k}" for kind in ("", "_mlp", "_frozen_gen") for k in range(5)
  )
  for col in cells:
    frozen = syn[f"{col}_frozen_gen_seed3"].argv
    assert "--config.rep.freeze_generators=True" in frozen and "--config.seed=3" in frozen
    assert "--config.rep.freeze_generators=True" not in syn[f"{col}_seed3"].argv
  # Each column's noise figure sets the control beside ours, seed by seed.
  noise = {j.name: j.argv for j in the_launch.figures if j.name.startswith("noise_figure_")}
  for col in cells:
    drawn = [os.path.basename(a) for a in noise[f"noise_figure_{col}"] if "_seed" in a]
    n = len(seeds_of[col])
    assert drawn[:n] == [f"{col}_seed{k}" for k in seeds_of[col]], col
    assert drawn[-n:] == [f"{col}_frozen_gen_seed{k}" for k in seeds_of[col]], col
  seven = syn["seven_scenes_seed0"].argv
  assert any(a.startswith("--config.data.family.scenes=") and "stairs" in a for a in seven)
  assert "--config.data.scenes_per_device=7" in seven and "--config.evals.split=validation" in seven
  # Where a family has fewer scenes than evals.num_scenes, each gives more views (heldout.py): the
  # area's and 7-Scenes' :quick (4 and 2 targets) are raised here.
  for col in ("gqn", "car", "gibson", "seven_scenes", "car_chair"):
    assert _parsed_config(syn[f"{col}_seed0"].argv, monkeypatch).evals.num_scenes >= 32, col
  # The command line parses (every field exists) up to the config's checks: a bad value added
  # last is the first error.
  bad = subprocess.run(
    [*seven, "--config.evals.split=bogus"], cwd=ROOT, capture_output=True, text=True, timeout=300
  )
  assert bad.returncode == 2 and "--config.evals.split='bogus'" in bad.stderr, bad.stderr
  # The same lr grid size for every representation in every size of the plans.
  for size in plan.plans().values():
    assert all(len(v) >= 2 for v in size.lrs.values())
  # The noise figures' other pose inputs: the area (gibson) and the car's low-dim vector too.
  noise = ["--size", "protocol", "--out", out, "--dry_run", "--noise_runs"]
  assert command.main([*noise, "--settings", "gibson,car"]) == 0
  text = capsys.readouterr().out
  names = ("gibson_lowdim", "gibson_mlp", "gibson_convdraw", "car_lowdim", "car_convdraw")
  for name in names:
    assert f"--workdir={out}/synthesis/{name}_seed0 " in text
  assert "noise_gibson" in text
  for variant in ("object", "area"):
    assert f"--config=configs/gqn_convdraw.py:{variant} " in text


def test_plan_refuses_convdraw_where_there_is_no_context(monkeypatch):
  data = {
    "settings": {
      s: {**v, "representations": list(v["representations"])}
      for s, v in plan._read()["settings"].items()
    }
  }
  data["settings"]["gibson"]["noise_inputs"] = ["lowdim", "convdraw"]
  del data["settings"]["gibson"]["convdraw_variant"]
  monkeypatch.setattr(plan, "_read", lambda: data)
  plan.settings.cache_clear()
  try:
    with pytest.raises(ValueError, match="convdraw.*reads context views.*no convdraw_variant"):
      plan.settings()
    data["settings"]["gibson"]["convdraw_variant"] = "bogus"  # not a variant of the config
    with pytest.raises(ValueError, match="unknown config variant 'bogus'"):
      plan.settings()
  finally:
    plan.settings.cache_clear()


def test_plan_seed_counts_are_checked():
  """A size's `seed_counts` names a setting and a count within its seeds; a setting not named
  runs them all."""
  p = plan.plans()["protocol"]
  assert p.seeds_for("gibson") == p.seeds and p.seeds_for("car") == p.seeds[:5]
  assert dataclasses.replace(p, seed_counts={"car": 1}).seeds_for("car") == p.seeds[:1]
  for bad in ({"car": 0}, {"car": len(p.seeds) + 1}, {"chair": 2}):
    with pytest.raises(ValueError, match="seed_counts"):
      dataclasses.replace(p, seed_counts=bad)

"""The transformer comparison's plan (`python -m camrep.comparison --size lvsm_quick`) and its
reader (experiments/lvsm_table.py) on synthetic run records."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from camrep.comparison import command, transformer
from camrep.comparison import launch as launch_lib
from camrep.regression import stats
from camrep.synthesis import conditionings
from experiments import lvsm_table

ALPHAS = [0.0, 0.1, 0.2, 0.3]


def _run(root, column, camera, seed, psnr, *, drop=1.0, source="rooms", data_dir="", noise=True):
  wd = root / column / f"{camera}_seed{seed}"
  (wd / "eval").mkdir(parents=True)
  config = {
    "task": "mvt",
    "seed": seed,
    "model": {"camera": camera},
    "data": {"source": source, "dir": data_dir, "n_context": 2},
  }
  (wd / "config.json").write_text(json.dumps(config))
  final = {
    "step": 100,
    "complete": True,
    "eval/psnr": psnr,
    "eval/ssim": 0.5,
    "eval/psnr_context1": psnr - 1.0,
    "eval/psnr_context4": psnr + 0.5,
    "train/steps_per_sec": 4.0,
    "num_params": {"model": 1000 + (50 if camera == "raymap" else 0), "rep": 0},
  }
  (wd / "final_metrics.json").write_text(json.dumps(final))
  (wd / "metrics.jsonl").write_text(json.dumps({"step": 100, "eval/psnr": psnr}) + "\n")
  if noise:
    curve = [psnr - drop * a / ALPHAS[-1] for a in ALPHAS]
    (wd / "eval" / "noise.json").write_text(
      json.dumps({"alphas": ALPHAS, "psnr": curve, "ssim": [0.5] * 4, "noise_on": "pose"})
    )
  return wd


def _rows(md: str, column: str) -> dict[str, list[str]]:
  section = md.split(f"## {column}")[1].split("\n## ")[0]
  rows = [line for line in section.splitlines() if line.startswith("|")][2:]
  return {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[1:-1]] for r in rows}


def test_the_reader_builds_the_table_and_figure_with_verdicts_against_raymap(tmp_path, capsys):
  jitter = [0.0, 0.1, -0.1]
  for s, j in enumerate(jitter):
    _run(tmp_path, "rooms", "raymap", s, 18.0 + j, drop=2.0)
    _run(tmp_path, "rooms", "prope", s, 19.0 + j + 0.05 * s, drop=1.0)  # better, smaller drop
    _run(tmp_path, "rooms", "none", s, 17.0 + j, drop=0.0)
    _run(tmp_path, "rooms", "gta", s, 18.0 + (0.3, -0.3, 0.0)[s], drop=2.0)  # a tie
    _run(tmp_path, "car", "raymap", s, 20.0, source="object")
    _run(tmp_path, "car", "prope", s, 20.0 + j, source="object", noise=False)
  _run(tmp_path, "rooms", "learned_rel", 0, 25.0)  # one seed: no verdict
  _run(tmp_path, "cap", "raymap", 0, 15.0, source="llff", data_dir="/data/chair/")
  md_path, png = tmp_path / "t.md", tmp_path / "f.png"
  rc = lvsm_table.main(["--runs", str(tmp_path), "--out", str(md_path), "--png", str(png)])
  assert rc == 0, capsys.readouterr().err
  md = md_path.read_text()
  assert png.exists() and png.with_suffix(".pdf").exists()
  rooms = _rows(md, "rooms")
  assert list(rooms)[0] == "raymap"  # the baseline first
  header = [c.strip() for c in md.split("## rooms")[1].splitlines()[2].split("|")[1:-1]]
  col = {h: i for i, h in enumerate(header)}
  assert "ctx 2 (trained)" in col and "ctx 1" in col and "ctx 4" in col
  # Values: the paired differences' seed-level interval, computed the same way here.
  diff = [1.0 + 0.05 * s for s in range(3)]
  m, lo, hi, _ = stats.seed_t_interval(np.asarray(diff))
  iv = stats.Interval(m, lo, hi, 3, 1)
  assert rooms["prope"][col["PSNR - raymap"]] == f"{iv.value:+.2f} [{iv.lo:+.2f}, {iv.hi:+.2f}]"
  assert rooms["prope"][col["PSNR - raymap"] + 1] == "better"
  assert rooms["none"][col["PSNR - raymap"] + 1] == "worse"
  assert rooms["gta"][col["PSNR - raymap"] + 1] == "tie"
  assert rooms["learned_rel"][col["PSNR - raymap"] + 1] == "-"
  assert rooms["learned_rel"][col["seeds"]] == "1"
  # The noise drop: smaller is better (prope 1 dB, raymap 2 dB, none 0 dB).
  assert rooms["prope"][col["noise drop"]].startswith("1.00")
  assert rooms["prope"][-2] == "better" and rooms["none"][-2] == "better"
  assert rooms["gta"][-2] == "tie"
  assert (
    rooms["prope"][col["ctx 1"]]
    == f"{np.mean([19.0 + j + 0.05 * s - 1 for s, j in enumerate(jitter)]):.2f}"
  )
  assert (
    rooms["raymap"][col["params"]] == "1,050" and rooms["prope"][col["params"]] == "1,000 (-50)"
  )
  assert rooms["prope"][col["s / step"]] == "0.250"
  # The car column has no noise tests for prope; the capture column is named by its data.
  car = _rows(md, "car")
  assert car["prope"][col["noise drop"]] == "-"
  assert "## llff:chair" in md


def test_the_reader_refuses_two_runs_of_one_cell(tmp_path, capsys):
  _run(tmp_path / "a", "rooms", "raymap", 0, 18.0)
  _run(tmp_path / "b", "rooms", "raymap", 0, 18.0)
  assert lvsm_table.main(["--runs", str(tmp_path)]) == 2
  assert "two runs of rooms/raymap seed 0" in capsys.readouterr().err


def test_the_plan_lists_every_conditioning_seed_and_column_with_estimates(tmp_path, capsys):
  plan = transformer.plans()["lvsm_quick"]
  assert set(plan.cameras) == set(conditionings.CONDITIONINGS) and len(plan.seeds) >= 3
  capture = tmp_path / "chair_prepared"
  capture.mkdir()
  out = tmp_path / "cmp"
  argv = ["--size", "lvsm_quick", "--out", str(out), "--dry_run"]
  rc = command.main([*argv, "--data", f"car_chair=nerf:{capture}"])
  text = capsys.readouterr().out
  assert rc == 0
  n = len(plan.cameras) * len(plan.seeds) * 3
  assert f"= {n} view-synthesis runs, {n} noise tests" in text
  lines = [line for line in text.splitlines() if line.startswith("[~")]
  runs = [line for line in lines if "camrep.main" in line]
  assert len(runs) == n
  for camera in plan.cameras:
    assert f"    {camera} " in text  # its parameter count
    for column, cfg in (("rooms", "lvsm.py:quick"), ("car", "lvsm.py:object")):
      wd = os.path.join(out, "lvsm", column, f"{camera}_seed2")
      assert any(f"--config=configs/{cfg}" in r and f"--workdir={wd} " in r for r in runs)
  assert sum("--config.data.source=nerf" in r for r in runs) == n // 3
  noise = [line for line in lines if "--what=noise --noise_on=pose" in line]
  assert len(noise) == n
  assert any("experiments/lvsm_table.py" in line and "--baseline raymap" in line for line in lines)
  # Without a capture, the plan names the one it expects.
  assert command.main(argv) == 0
  assert "no capture column: add --data car_chair=nerf:" in capsys.readouterr().out


@pytest.mark.parametrize("column", ["rooms", "car"])
def test_parameter_counts_share_the_trunk(column):
  counts = transformer.parameter_counts(transformer.plans()["lvsm_quick"], column)
  trunk = counts["prope"]["model"]
  for camera in ("none", "gta", "gta_so3", "prope", "learned_rel"):
    assert counts[camera]["model"] == trunk, camera
  assert counts["raymap"]["model"] > trunk and counts["learned_abs"]["model"] > trunk
  assert counts["learned_rel"]["rep"] > 0 and counts["prope"]["rep"] == 0


def _fake_run_job(ran):
  """A `launch.run_job` that writes what a finished run (or its noise test) leaves, in order; the
  table job is the real reader (without its figure)."""

  def run_job(job, logs, *, index, env=None):
    ran.append(job.name)
    if job.kind == "table":
      assert job.argv[-2] == "--png"
      return lvsm_table.main(job.argv[2:-2]) == 0
    wd = pathlib.Path(job.workdir)
    camera, seed = wd.name.rsplit("_seed", 1)
    psnr = 18.0 + sorted(conditionings.CONDITIONINGS).index(camera) / 4
    if job.kind == "synthesis":
      source = {"rooms": "rooms", "car": "object"}[wd.parent.name]
      _run(wd.parent.parent, wd.parent.name, camera, int(seed), psnr, source=source, noise=False)
      (wd / "checkpoints" / "100").mkdir(parents=True)
    else:
      noise = {"alphas": ALPHAS, "psnr": [psnr - a for a in ALPHAS], "noise_on": "pose"}
      (wd / "eval" / "noise.json").write_text(json.dumps({**noise, "ssim": [0.5] * 4}))
    return True

  return run_job


@pytest.fixture
def fake_launcher(monkeypatch):
  """The launcher with `_fake_run_job` and parameter counts not built from models: (the names of
  the jobs it runs, in order; the lvsm_quick plan)."""
  ran = []
  monkeypatch.setattr(launch_lib, "run_job", _fake_run_job(ran))
  plan = transformer.plans()["lvsm_quick"]
  counts = {c: {"model": 1000, "rep": 0} for c in plan.cameras}
  monkeypatch.setattr(transformer, "parameter_counts", lambda plan, column="rooms": counts)
  return ran, plan


def test_a_launch_archives_each_run_with_its_noise_test_and_resumes_from_the_archive(
  tmp_path, fake_launcher, capsys
):
  """`--archive`: each run's noise test follows it at once, every record is in the archive with
  its noise curve, and so is the table of those records, made again after each; a launch on an
  empty DIR restores them and trains nothing, and a restored run whose noise test is missing
  (archived before it ran) is trained again with it."""
  ran, plan = fake_launcher
  archive = tmp_path / "archive"

  def launch(out):
    ran.clear()
    return command.main(["--size", "lvsm_quick", "--out", str(out), "--archive", str(archive)])

  def table_is_the_records():
    made = tmp_path / "from_records.md"
    assert lvsm_table.main(["--runs", str(archive / "lvsm"), "--out", str(made)]) == 0
    assert (archive / "lvsm_table.md").read_text() == made.read_text()

  assert launch(tmp_path / "first") == 0
  n = len(plan.cameras) * len(plan.seeds) * len(plan.columns)
  cells = [name.removeprefix("lvsm_") for name in ran[::4][:-1]]
  assert len(cells) == n and len(ran) == 4 * n + 1
  table = "lvsm_table"
  assert ran == [x for c in cells for x in (f"lvsm_{c}", table, f"noise_{c}", table)] + [table]
  kept = [p.name for p in archive.glob("lvsm/*/*/*")]  # one compact record per run, nothing else
  assert kept == ["run.json"] * n
  first = json.loads((archive / "lvsm" / "rooms" / "none_seed0" / "run.json").read_text())
  assert first["kind"] == "synthesis" and first["noise"]["noise_on"] == "pose"
  table_is_the_records()

  assert launch(tmp_path / "second") == 0
  assert ran == [table] and f"restored {n} finished runs" in capsys.readouterr().out
  assert launch_lib.archived_only(str(tmp_path / "second" / "lvsm" / "car" / "prope_seed1"))

  # A run finished in DIR before its noise test ran: the test runs first, and is archived.
  out = tmp_path / "fourth"
  wd = _run(out / "lvsm", "rooms", "gta", 1, 18.0, noise=False)
  (wd / "checkpoints" / "100").mkdir(parents=True)
  assert launch(out) == 0
  assert ran == ["noise_rooms_gta_seed1", table, table]
  table_is_the_records()

  cut = archive / "lvsm" / "car" / "gta_seed2" / "run.json"
  record = json.loads(cut.read_text())
  del record["noise"]
  cut.write_text(json.dumps(record))
  assert launch(tmp_path / "third") == 0
  assert ran == ["lvsm_car_gta_seed2", table, "noise_car_gta_seed2", table, table]
  assert "lvsm_car_gta_seed2: its record is from the archive" in capsys.readouterr().out
  assert "noise" in json.loads(cut.read_text())
  table_is_the_records()


def test_settings_and_representations_narrow_a_launch_and_a_dry_run_counts_the_archive(
  tmp_path, fake_launcher, capsys
):
  """`--settings gqn` keeps the rooms column only (no car, no capture column), `--representations`
  the named cameras in the plan's order; a dry run on an empty DIR with that archive counts its
  runs done (they are restored at launch) and writes nothing."""
  ran, plan = fake_launcher
  capture = tmp_path / "chair_prepared"
  capture.mkdir()
  archive = tmp_path / "archive"
  argv = ["--size", "lvsm_quick", "--archive", str(archive), "--data", f"car_chair=nerf:{capture}"]
  narrow = ["--settings", "gqn", "--representations", "learned_rel,raymap"]
  assert command.main([*argv, "--out", str(tmp_path / "first"), *narrow]) == 0
  cameras = ("raymap", "learned_rel")
  assert [r for r in ran if r.startswith("lvsm_") and r != "lvsm_table"] == [
    f"lvsm_rooms_{c}_seed{s}" for s in plan.seeds for c in cameras
  ]
  capsys.readouterr()

  fresh = tmp_path / "fresh"
  assert command.main([*argv, "--out", str(fresh), "--dry_run"]) == 0
  text = capsys.readouterr().out
  assert not fresh.exists()
  runs = [line for line in text.splitlines() if "camrep.main" in line]
  done = {line.split("--workdir=")[1].split()[0] for line in runs if line.startswith("[done]")}
  assert done == {
    str(fresh / "lvsm" / "rooms" / f"{c}_seed{s}") for s in plan.seeds for c in cameras
  }
  assert len(runs) == len(plan.cameras) * len(plan.seeds) * 3
  noise = [line for line in text.splitlines() if "--what=noise" in line]
  assert sum(line.startswith("[done]") for line in noise) == len(done)
  assert "no capture column" not in text
  # An archived run without its noise test is trained again at launch: not done in a dry run.
  cut = archive / "lvsm" / "rooms" / "raymap_seed1" / "run.json"
  record = json.loads(cut.read_text())
  del record["noise"]
  cut.write_text(json.dumps(record))
  assert command.main([*argv, "--out", str(fresh), "--dry_run"]) == 0
  lines = capsys.readouterr().out.splitlines()
  raymap1 = [line for line in lines if f"{fresh}/lvsm/rooms/raymap_seed1" in line]
  assert len(raymap1) == 2 and not any(line.startswith("[done]") for line in raymap1)


def test_a_transformer_launch_past_its_max_hours_starts_nothing_and_says_how_to_resume(
  tmp_path, fake_launcher, capsys
):
  ran, _ = fake_launcher
  argv = ["--size", "lvsm_quick", "--out", str(tmp_path / "cmp"), "--max_hours", "1e-9"]
  assert command.main(argv) == 0
  out = capsys.readouterr().out
  assert ran == [] and "not started (--max_hours)" in out
  assert "--max_hours 1e-09 reached after" in out and "run the same command again" in out


def test_a_stopped_transformer_launch_says_its_runs_resume_and_names_no_regression(
  tmp_path, fake_launcher, monkeypatch, capsys
):
  """Ctrl-C (or SIGTERM) during a transformer launch: exit 130 and the line on what is kept and
  how its view-synthesis runs resume; the plan has no regression runs, so the line names none."""
  ran, _ = fake_launcher
  finished = launch_lib.run_job

  def run_job(job, logs, *, index, env=None):
    if len(ran) == 2:  # the first run and its table done, the stop during its noise test
      raise KeyboardInterrupt
    return finished(job, logs, index=index, env=env)

  monkeypatch.setattr(launch_lib, "run_job", run_job)
  archive = tmp_path / "archive"
  argv = ["--size", "lvsm_quick", "--out", str(tmp_path / "cmp"), "--archive", str(archive)]
  assert command.main(argv) == 130
  err = capsys.readouterr().err
  assert "interrupted after" in err and f"archived in {archive}" in err, err
  assert "view-synthesis runs resume from their last checkpoint" in err
  assert "regression" not in err and "Traceback" not in err
  assert not (tmp_path / "cmp" / ".camrep.lock").exists()  # the lock is given back


@pytest.mark.parametrize("size", ["lvsm_quick", "quick"])
def test_a_dry_run_whose_reader_has_gone_ends_without_a_traceback(tmp_path, size):
  """`--dry_run | head -1`: a reader that has closed the pipe; the launcher exits 0 without a
  BrokenPipeError traceback, for a transformer plan as for a regression plan (the pipe's read
  end is closed before the launcher starts, so its first line already meets a closed pipe)."""
  root = pathlib.Path(__file__).resolve().parents[1]
  argv = [sys.executable, "-m", "camrep.comparison", "--size", size, "--out", str(tmp_path)]
  read, write = os.pipe()
  os.close(read)
  try:
    p = subprocess.run(
      [*argv, "--dry_run"], cwd=root, stdout=write, stderr=subprocess.PIPE, timeout=300
    )
  finally:
    os.close(write)
  err = p.stderr.decode()
  assert p.returncode == 0 and "Traceback" not in err, err


@pytest.mark.parametrize(
  "extra, says",
  [
    (["--settings", "gibson"], "--settings gibson: --size lvsm_quick has no column of it"),
    (["--representations", "quat"], "--representations quat: not a conditioning"),
    (["--full_grid", "--crossed", "car"], "--full_grid, --crossed: flags of the regression plans"),
    (["--noise_runs"], "--noise_runs: flags of the regression plans"),
    (["--data", "gqn={dir}"], "--data gqn=DIR: --size lvsm_quick trains on its procedural"),
  ],
)
def test_a_transformer_launch_refuses_what_it_would_ignore(tmp_path, capsys, extra, says):
  extra = [x.format(dir=tmp_path) for x in extra]
  argv = ["--size", "lvsm_quick", "--out", str(tmp_path / "cmp"), "--dry_run", *extra]
  with pytest.raises(SystemExit) as e:
    command.main(argv)
  assert e.value.code == 2 and says in capsys.readouterr().err


def test_the_committed_lvsm_table_is_that_of_its_records(tmp_path):
  """results/lvsm, the comparison's archive: one compact record per finished run and the table
  made from them, byte for byte (the launch remakes it after every run)."""
  root = pathlib.Path(__file__).resolve().parent.parent / "results" / "lvsm"
  files = {p.name for p in (root / "lvsm").rglob("*") if p.is_file()}
  assert files == {"run.json"}
  made = tmp_path / "table.md"
  argv = ["--runs", str(root / "lvsm"), "--baseline", "raymap", "--out", str(made)]
  assert lvsm_table.main(argv) == 0
  assert made.read_text() == (root / "lvsm_table.md").read_text()

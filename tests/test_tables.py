"""The table readers (experiments/table1.py, table2.py) over fabricated results, their refusals
(damaged records, two runs of one cell), and the committed tables regenerated from the committed
run records."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from camrep.regression import tables as C
from experiments import table1, table2

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _summary(setting, scale, scenes=("0",)):
  errs = {
    "car": ("rotation_error_deg",),
    "gqn": ("x_error", "y_error", "yaw_error_deg"),
    "gibson": ("x_error", "y_error", "yaw_error_deg"),
    "seven_scenes": ("position_error", "rotation_error_deg"),
  }[setting]
  one = lambda s: {e: {"mean": s * (1 + i), "median": s * (0.5 + i)} for i, e in enumerate(errs)}
  out = {"all": one(scale)}
  for k, sc in enumerate(scenes):
    out[sc] = one(scale * (k + 1))
  return out


def _write(root, setting, rep, lr, seed, val, test, **extra):
  wd = os.path.join(root, setting, rep, f"lr{lr:g}_seed{seed}")
  os.makedirs(wd)
  r = dict(setting=setting, representation=rep, lr=lr, seed=seed, steps=10, params=5)
  r.update(variant="quick", validation=val, test=test, **extra)
  with open(os.path.join(wd, "results.json"), "w") as f:
    json.dump(r, f)


def test_table1_selects_lr_on_validation(tmp_path):
  root = str(tmp_path / "runs")
  # car ours: lr 1e-3 has the lower validation error on both seeds, the worse test error.
  for seed, test in ((0, 2.0), (1, 4.0)):
    _write(root, "car", "ours", 1e-3, seed, _summary("car", 1.0), _summary("car", test))
    _write(root, "car", "ours", 3e-3, seed, _summary("car", 2.0), _summary("car", 0.5))
  # car quat: lr 3e-3 is better on seed 0 (the only seed both lrs have), worse on seed 1.
  _write(root, "car", "quat", 1e-3, 0, _summary("car", 5.0), _summary("car", 9.0))
  _write(root, "car", "quat", 3e-3, 0, _summary("car", 4.0), _summary("car", 7.0))
  _write(root, "car", "quat", 3e-3, 1, _summary("car", 40.0), _summary("car", 8.0))
  _write(root, "gqn", "euler", 1e-4, 0, _summary("gqn", 0.1), _summary("gqn", 0.2))
  sel = C.select(C.load_results([os.path.join(root, "*", "*", "*")]))
  assert sel["car", "ours"].lr == 1e-3 and sel["car", "ours"].seeds == (0, 1)
  assert sel["car", "quat"].lr == 3e-3 and sel["car", "quat"].scores[1e-3][1] == (0,)
  assert C.seed_stats(sel["car", "ours"].runs, "rotation_error_deg") == (3.0, np.sqrt(2), 2)

  out = str(tmp_path / "results" / "table1.md")
  assert table1.main(["--runs", os.path.join(root, "*", "*", "*"), "--out", out]) == 0
  text = open(out).read()
  assert "| ours | 3.00 ± 1.41 | – | – | – |" in text  # the columns with runs only
  assert "| (x, y, q) | 7.50 ± 0.71 |" in text
  # gqn euler (one seed): x = 0.2, y = 0.4, yaw = 0.6; the paper's Table 1 is labelled as such.
  assert "| (x, y, α) Euler | – | 0.200 | 0.400 | 0.600 |\n" in text
  assert "Paper's Table 1" in text and "| ours | 2.85 | 0.053 | 0.053 | 4.07 |" in text
  assert "| car | ours | 1e-3: 0.351 (seeds 0,1), 3e-3: 0.702 (seeds 0,1) | 1e-3 |" in text


def test_table2_medians_per_scene(tmp_path):
  root = str(tmp_path / "runs")
  names = {"0": "chess", "1": "stairs"}
  for rep, scale in (("ours", 0.1), ("quat", 0.2)):
    for seed in (0, 1):
      test = _summary("seven_scenes", scale * (1 + 2 * seed), scenes=("0", "1"))
      val = _summary("seven_scenes", scale)
      _write(root, "seven_scenes", rep, 1e-3, seed, val, test, data={"scene_names": names})
  out = str(tmp_path / "table2.md")
  assert table2.main(["--runs", os.path.join(root, "*", "*", "*"), "--out", out]) == 0
  text = open(out).read()
  # ours, chess: position medians 0.05 / 0.15, rotation medians 0.15 / 0.45 over the seeds.
  assert "| chess | 0.10 ± 0.07 m, 0.3 ± 0.2° | 0.20 ± 0.14 m, 0.6 ± 0.4° | 0.12 m, 4.83° |" in text
  assert "| stairs | 0.20 ± 0.14 m, 0.6 ± 0.4° |" in text
  assert "| average | 0.15 ± 0.11 m, 0.5 ± 0.3° |" in text and "0.21 m, 7.92° (7 scenes)" in text
  assert "real 7-Scenes" in text


# ------------------------------------------------------------------ refusals and labels


def test_a_damaged_record_is_refused_by_name_or_skipped_when_asked(tmp_path, capsys):
  """A cut results.json or a damaged errors file is named and refused (exit 2, no traceback);
  --skip_damaged skips it with a warning naming it; never counted, never a crash."""
  root = str(tmp_path / "runs")
  for seed in (0, 1):
    _write(root, "car", "ours", 1e-3, seed, _summary("car", 1.0), _summary("car", 2.0))
  good = os.path.join(root, "car", "ours", "lr0.001_seed0")
  np.savez(os.path.join(good, "errors_test.npz"), rotation_error_deg=np.ones(4), scene=np.zeros(4))
  cut = os.path.join(root, "car", "ours", "lr0.001_seed1", "results.json")
  with open(cut, "r+") as f:
    f.truncate(40)
  with open(os.path.join(good, "errors_test.npz"), "r+b") as f:
    f.truncate(30)
  runs = [os.path.join(root, "*", "*", "*")]
  out = str(tmp_path / "t.md")
  assert table1.main(["--runs", *runs, "--out", out]) == 2
  err = capsys.readouterr().err
  assert err.startswith("error: damaged runs") and cut in err and "errors_test.npz" in err
  assert "Traceback" not in err and not os.path.exists(out)
  assert table1.main(["--runs", *runs, "--out", out]) == 2  # nothing else to table
  capsys.readouterr()
  _write(root, "car", "quat", 1e-3, 0, _summary("car", 1.0), _summary("car", 3.0))
  assert table1.main(["--runs", *runs, "--out", out, "--skip_damaged"]) == 0
  err = capsys.readouterr().err
  assert f"warning: skipped {cut}" in err and "1 runs read" in open(out).read()


def test_two_runs_of_one_cell_are_refused_naming_both(tmp_path, capsys):
  """Two workdirs with the same setting, representation, lr and seed: refused by name (one was
  silently dropped before)."""
  root = str(tmp_path / "runs")
  _write(root, "car", "ours", 1e-3, 0, _summary("car", 1.0), _summary("car", 2.0))
  _write(root, "car_chair", "ours", 1e-3, 0, _summary("car", 1.0), _summary("car", 5.0))
  with open(os.path.join(root, "car_chair", "ours", "lr0.001_seed0", "results.json")) as f:
    r = json.load(f)
  r["setting"] = "car"  # a capture column's runs are of the car setting
  with open(os.path.join(root, "car_chair", "ours", "lr0.001_seed0", "results.json"), "w") as f:
    json.dump(r, f)
  out = str(tmp_path / "t.md")
  assert table1.main(["--runs", os.path.join(root, "*", "*", "*"), "--out", out]) == 2
  err = capsys.readouterr().err
  assert "two runs of car/ours at lr 0.001, seed 0" in err
  assert "car/ours/lr0.001_seed0" in err and "car_chair/ours/lr0.001_seed0" in err
  with pytest.raises(C.DuplicateRuns):
    C.select(C.load_results([os.path.join(root, "*", "*", "*")]))


def test_a_car_only_table_shows_its_column_in_its_own_pose_terms(tmp_path):
  """Captures and car-only launches: only the car column, rows named by the encoding of the
  setting's pose columns ("q of (azimuth, polar)"), not the rooms' "(x, y, q)"; a table with
  the rooms keeps the paper's labels."""
  root = str(tmp_path / "runs")
  for rep in ("ours", "quat", "sincos"):
    _write(root, "car", rep, 1e-3, 0, _summary("car", 1.0), _summary("car", 2.0))
  text = table1.build(C.load_results([os.path.join(root, "*", "*", "*")]))
  assert "| representation | car rotation (deg) |\n|---|---|\n" in text
  assert "| q of (azimuth, polar) |" in text and "| sin, cos of (azimuth, polar) |" in text
  assert "(x, y, q)" not in text and "rooms x" not in text
  assert C.pose_columns("car") == ("azimuth", "polar")
  _write(root, "gqn", "quat", 1e-3, 0, _summary("gqn", 0.1), _summary("gqn", 0.2))
  text = table1.build(C.load_results([os.path.join(root, "*", "*", "*")]))
  assert "| (x, y, q) |" in text and "| rooms x |" in text and "area x" not in text


def test_the_committed_tables_regenerate_byte_identical_from_the_committed_records():
  """results/converge keeps one compact record per run (run.json): Table 1 and the lead table
  made from them are the committed files, byte for byte, and so is the claims table (which
  also reads the view-synthesis records)."""
  conv = os.path.join(ROOT, "results", "converge")
  reg = os.path.join(conv, "regression")
  assert not [f for _, _, fs in os.walk(reg) for f in fs if f != "run.json"]
  results = C.load_results([os.path.join(reg, s, "*", "*") for s in ("car", "gqn", "gibson")])
  with open(os.path.join(conv, "table1.md"), encoding="utf-8") as f:
    assert table1.build(results) == f.read()
  from experiments import lead_table

  with open(os.path.join(conv, "lead_table.md"), encoding="utf-8") as f:
    assert lead_table.build(reg) + "\n" == f.read()
  from experiments import claims_table

  with open(os.path.join(conv, "claims.md"), encoding="utf-8") as f:
    assert claims_table.build(conv) + "\n" == f.read()


def test_the_protocol_figures_regenerate_from_its_records(tmp_path, monkeypatch, capsys):
  """results/protocol keeps one compact record per finished run of the protocol size (and a
  view-synthesis run's config.json and record.json); the tables of its figures are the
  launcher's own figure jobs over that directory (paths relative to the repository), byte for
  byte. (Its tables: `test_the_launchers_table_jobs_run_as_commands`.)"""
  from camrep.comparison import command, launch
  from experiments import learning_curve, noise_figure

  proto = os.path.join(ROOT, "results", "protocol")
  kept = {"run.json", "config.json", "record.json"}  # with a view-synthesis run's config
  synthesis = os.path.join(proto, "synthesis")
  assert not [f for _, _, fs in os.walk(synthesis) for f in fs if f not in kept]
  monkeypatch.chdir(ROOT)
  args = ["--size", "protocol", "--out", "results/protocol", "--dry_run"]
  the_launch = command.make_launch(command.parse_args(args))
  jobs = [j for j in the_launch.figures if j.kind != "evaluate"] + launch.curve_jobs(the_launch)
  scripts = {
    "experiments/noise_figure.py": noise_figure,
    "experiments/learning_curve.py": learning_curve,
  }
  drawn = set()
  for job in jobs:
    argv = [os.path.relpath(a, ROOT) if a.startswith(proto) else a for a in job.argv[2:]]
    md = argv[argv.index("--md") + 1]
    if not os.path.isfile(md):
      continue  # a figure the launch will draw once its runs exist
    argv[argv.index("--md") + 1] = str(tmp_path / "figure.md")
    argv[argv.index("--png") + 1] = str(tmp_path / "figure.png")
    assert scripts[job.argv[1]].main(argv) == 0, job.name
    with open(md, encoding="utf-8") as f:
      assert (tmp_path / "figure.md").read_text() == f.read(), md
    drawn.add(os.path.basename(md))
  assert {"noise_gibson.md", "curve_synthesis_gibson.md"} <= drawn
  capsys.readouterr()


def test_every_committed_curve_table_regenerates_from_the_records_it_names(tmp_path, capsys):
  """Each curve_*.md of the record archives, results/converge and results/protocol
  (experiments/learning_curve.py --bands), names its runs, which are records in the repository:
  its title, metrics and runs give it back byte for byte. (results/quick's snapshot was drawn
  from workdirs that are not kept.)"""
  import glob
  import re

  from experiments import learning_curve

  tables = sorted(
    p
    for archive in ("converge", "protocol")
    for p in glob.glob(os.path.join(ROOT, "results", archive, "curve_*.md"))
  )
  assert len(tables) >= 15
  for path in tables:
    with open(path, encoding="utf-8") as f:
      text = f.read()
    title = text.split("\n\n")[0].removeprefix("# ")
    metrics = [line.strip("`").split("`")[0] for line in text.splitlines() if line.startswith("`")]
    named = re.findall(r"`([^`]+)`", next(x for x in text.splitlines() if x.startswith("Runs: ")))
    assert not [r for r in named if os.path.isabs(r)], f"{path} names paths outside the repository"
    runs = [os.path.join(ROOT, r) for r in named]
    md = tmp_path / "curve.md"
    argv = ["--bands", "--metrics", ",".join(metrics), "--runs", *runs, "--title", title]
    assert learning_curve.main([*argv, "--md", str(md)]) == 0, path
    assert md.read_text().replace(ROOT + os.sep, "") == text, path
  capsys.readouterr()


def test_the_launchers_table_jobs_run_as_commands(tmp_path, monkeypatch, capsys):
  """Each table job of a protocol launch runs as the command the launcher starts (from the
  repository, over a copy of results/protocol) and exits 0; every table it writes that
  results/protocol has is the committed one, byte for byte (the claims table today)."""
  import shutil

  from camrep.comparison import command, launch

  out = tmp_path / "protocol"
  shutil.copytree(os.path.join(ROOT, "results", "protocol"), out)
  for name in ("claims.md", "lead_table.md", "table1.md", "table2.md"):
    (out / name).unlink(missing_ok=True)
  monkeypatch.chdir(ROOT)
  args = ["--size", "protocol", "--out", str(out), "--settings", "gibson,seven_scenes", "--dry_run"]
  tables = command.make_launch(command.parse_args(args)).tables
  assert {"lead_table", "claims"} <= {j.name for j in tables}
  failed = launch.run_jobs(tables, str(tmp_path / "logs"), at_once=2, label="")
  logs = {j.name: (tmp_path / "logs" / f"{j.name}.log").read_text() for j in tables}
  assert failed == [], {n: logs[n] for n in failed}
  assert all((out / f).is_file() for f in ("lead_table.md", "table1.md", "table2.md"))
  compared = set()
  for name in ("claims.md", "lead_table.md", "table1.md", "table2.md"):
    committed = os.path.join(ROOT, "results", "protocol", name)
    if os.path.isfile(committed):
      with open(committed, encoding="utf-8") as f:
        assert (out / name).read_text() == f.read(), name
      compared.add(name)
  assert "claims.md" in compared
  capsys.readouterr()


def test_the_results_readme_leads_with_the_claims_table_as_its_records_give_it():
  """results/README.md's "The claims" section is results/converge/claims.md (table and note) as
  committed, so the front page cannot drift from the table the records regenerate."""
  with open(os.path.join(ROOT, "results", "README.md"), encoding="utf-8") as f:
    section = f.read().split("## The claims\n\n", 1)[1]
  with open(os.path.join(ROOT, "results", "converge", "claims.md"), encoding="utf-8") as f:
    table, note = f.read().strip().split("\n\n")
  assert section.startswith(table + "\n\n" + note + "\n")

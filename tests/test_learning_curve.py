"""experiments/learning_curve.py on fabricated workdirs: tables, figure, labels and refusals."""

from __future__ import annotations

import json

import cv2
import numpy as np

from experiments import learning_curve


def _workdir(tmp_path, name, representation, rows):
  wd = tmp_path / name
  wd.mkdir()
  config = {"representation": representation, "optax": {"lr": 1e-3}}
  (wd / "config.json").write_text(json.dumps(config))
  (wd / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
  return str(wd)


def test_tables_and_figure_from_metrics(tmp_path, capsys):
  lc = learning_curve
  key = "eval/test_scenes/yaw_error_deg_mean"
  a = _workdir(
    tmp_path,
    "a",
    "ours",
    [{"step": 50, "train/loss": 1.0}, {"step": 100, key: 80.0}, {"step": 200, key: 20.5}],
  )
  b = _workdir(tmp_path, "b", "quat", [{"step": 100, key: 85.0}, {"step": 300, key: "NaN"}])
  png, md = tmp_path / "out" / "c.png", tmp_path / "out" / "c.md"
  assert lc.main(["--runs", a, b, "--metrics", key, "--png", str(png), "--md", str(md)]) == 0
  text = md.read_text()
  assert "| step | ours (lr 0.001) | quat (lr 0.001) |" in text
  assert "| 100 | 80 | 85 |" in text and "| 200 | 20.5 |  |" in text
  assert "| 300 |  | nan |" in text  # logged non-finite values stay visible
  assert "train/loss" not in text
  img = cv2.imread(str(png))
  assert img is not None and img.shape[0] > 100
  assert (tmp_path / "out" / "c.pdf").read_bytes().startswith(b"%PDF")
  # The tables give the curves back (how results/quick/curve_rooms.png is redrawn).
  labels, metrics, curves = lc.from_markdown(text)
  assert labels == ["ours (lr 0.001)", "quat (lr 0.001)"] and metrics == [key]
  assert curves[0][0] == {100: 80.0, 200: 20.5} and curves[0][1][100] == 85.0
  assert lc.main(["--from_md", str(md), "--png", str(tmp_path / "re.png")]) == 0
  assert cv2.imread(str(tmp_path / "re.png")).shape == img.shape
  capsys.readouterr()


def test_runs_with_one_label_are_seeds_of_one_curve(tmp_path):
  lc = learning_curve
  key = "eval/psnr"
  a = _workdir(tmp_path, "s0", "ours", [{"step": 1, key: 10.0}, {"step": 2, key: 12.0}])
  b = _workdir(tmp_path, "s1", "ours", [{"step": 1, key: 14.0}, {"step": 2, key: 16.0}])
  labels = [lc.label_of(a), lc.label_of(b)]
  fig = lc.figure(labels, [key], [[lc.curve(a, key), lc.curve(b, key)]])
  (ax,) = fig.axes
  (line,) = ax.get_lines()  # one curve: the mean of the two seeds
  np.testing.assert_allclose(line.get_ydata(), [12.0, 14.0])
  assert "2 seeds" in line.get_label() and len(ax.collections) == 1  # and its band


def test_refusals(tmp_path, capsys):
  lc = learning_curve
  a = _workdir(tmp_path, "a", "ours", [{"step": 1, "eval/psnr": 20.0}])
  assert lc.main(["--runs", a, "--metrics", "eval/ssim"]) == 2
  assert "eval/ssim is not logged" in capsys.readouterr().err
  assert lc.main(["--runs", str(tmp_path / "nope"), "--metrics", "eval/psnr"]) == 2
  assert "has no metrics.jsonl" in capsys.readouterr().err
  assert lc.main(["--runs", a, "--metrics", "eval/psnr", "--labels", "x,y"]) == 2
  assert lc.main(["--runs", a, "--metrics", "eval/psnr", "--labels", "mine"]) == 0
  assert "| step | mine |" in capsys.readouterr().out


def test_bands_over_seeds_per_representation(tmp_path, capsys):
  lc = learning_curve
  key = "eval/validation/score"
  runs = [
    _workdir(tmp_path, f"{rep}{seed}", rep, [{"step": 100, key: v}, {"step": 200, key: v / 2}])
    for rep, seed, v in (("ours", 0, 1.0), ("ours", 1, 3.0), ("ours", 2, 2.0), ("quat", 0, 4.0))
  ]
  png, md = tmp_path / "b.png", tmp_path / "b.md"
  args = ["--bands", "--runs", *runs, "--metrics", key, "--png", str(png), "--md", str(md)]
  assert lc.main([*args, "--title", "car: the score"]) == 0
  text = md.read_text()
  assert text.startswith("# car: the score\n")
  assert "| step | ours (3 runs) | quat (1 run) |" in text
  assert "| 100 | 2 [1, 3] | 4 [4, 4] |" in text and "| 200 | 1 [0.5, 1.5] | 2 [2, 2] |" in text
  assert cv2.imread(str(png)) is not None
  # A run that stopped early: the later steps say how many runs their cells are over.
  runs.append(_workdir(tmp_path, "ours3", "ours", [{"step": 100, key: 6.0}]))
  args = ["--bands", "--runs", *runs, "--metrics", key, "--png", str(png), "--md", str(md)]
  assert lc.main(args) == 0
  text = md.read_text()
  assert "| step | ours (4 runs) | quat (1 run) |" in text
  assert "| 100 | 3 [1, 6] | 4 [4, 4] |" in text
  assert "| 200 | 1 [0.5, 1.5] (3 runs) | 2 [2, 2] |" in text
  capsys.readouterr()


def test_bands_group_view_synthesis_runs_by_pose_input(tmp_path, capsys):
  """Synthesis workdirs (no representation) are grouped by rep.kind; GQN's ConvDRAW (whose
  rep.kind is lowdim) by its model.kind, not with the low-dim decoder; the grid with frozen
  generators as the control, not with ours."""
  lc = learning_curve
  runs = []
  for name, rep, model, psnr in (
    ("car_seed0", "grid", "decoder", 20.0),
    ("car_seed1", "grid", "decoder", 22.0),
    ("car_lowdim_seed0", "lowdim", "decoder", 18.0),
    ("car_convdraw_seed0", "lowdim", "convdraw", 19.0),
    ("car_frozen_gen_seed0", "grid", "decoder", 17.0),
  ):
    wd = tmp_path / name
    wd.mkdir()
    frozen = name.startswith("car_frozen_gen")
    config = {"rep": {"kind": rep, "freeze_generators": frozen}, "model": {"kind": model}}
    (wd / "config.json").write_text(json.dumps(config))
    (wd / "metrics.jsonl").write_text(json.dumps({"step": 120, "eval/psnr": psnr}) + "\n")
    runs.append(str(wd))
  md = tmp_path / "s.md"
  args = ["--bands", "--runs", *runs, "--metrics", "eval/psnr", "--png", str(tmp_path / "s.png")]
  assert lc.main([*args, "--md", str(md)]) == 0
  text = md.read_text()
  heads = "| step | grid (2 runs) | lowdim (1 run) | convdraw (1 run) | frozen_gen (1 run) |"
  assert heads in text
  assert "| 120 | 21 [20, 22] | 18 [18, 18] | 19 [19, 19] | 17 [17, 17] |" in text
  capsys.readouterr()


def test_a_compact_record_gives_the_same_curves_and_groups(tmp_path):
  """A finished run's record (run.json: its eval/ curves and config essentials) is read like its
  workdir: the same tables under --bands."""
  from camrep.regression import runs

  key = "eval/validation/score"
  rows = [{"step": 50, "train/loss": 1.0}, {"step": 100, key: 0.5}, {"step": 200, key: 0.25}]
  wd = _workdir(tmp_path, "full", "ours", rows)
  (tmp_path / "full" / "results.json").write_text(
    json.dumps({"setting": "car", "representation": "ours", "lr": 1e-3, "seed": 0})
  )
  rec = tmp_path / "rec"
  runs.write_record(runs.compact(runs.load(wd)), str(rec / runs.RECORD_FILE))
  md = {}
  for name, run in (("full", wd), ("rec", str(rec))):
    md[name] = tmp_path / f"{name}.md"
    args = ["--bands", "--runs", run, "--metrics", key, "--md", str(md[name])]
    assert learning_curve.main(args) == 0
  text = md["rec"].read_text()
  assert "| 200 | 0.25 [0.25, 0.25] |" in text and "ours (1 run)" in text
  assert text.replace(str(rec), "X") == md["full"].read_text().replace(wd, "X")
  assert learning_curve.curve(str(rec), "train/loss") == {}  # records keep eval/ metrics only

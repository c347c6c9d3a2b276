"""experiments/seed_spread.py: the crossed synthesis-seed x regression-seed
table, its variance split, and the decoding error of a pose system, on fabricated run directories
(and, for the decoding error, a one-step car view-synthesis run)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from camrep.configs import shapenet_car
from camrep.regression import stats
from camrep.synthesis import train
from experiments import seed_spread

A = {0: 0.0, 1: 1.0, 2: 2.0}  # synthesis-seed effects
B = {0: 0.0, 1: 0.5, 2: -0.5}  # regression-seed effects
N = 6  # test views


def _runs(tmp_path, cells, lr=1e-3, representation="ours"):
  """Regression run dirs of (synthesis seed, regression seed) cells, errors 3 + A[j] + B[k] on
  every view; the synthesis workdirs say their seed in config.json only (not in their name)."""
  out = []
  for j, k in cells:
    syn = tmp_path / f"syn_{'abc'[j]}"
    syn.mkdir(exist_ok=True)
    (syn / "config.json").write_text(json.dumps({"seed": j}))
    wd = tmp_path / "crossed" / f"lr_seed{k}_syn{j}"
    wd.mkdir(parents=True)
    results = {
      "setting": "car",
      "representation": representation,
      "seed": k,
      "lr": lr,
      "data": {"test_split": "test"},
      "representation_params": {"workdir": str(syn)},
    }
    (wd / "results.json").write_text(json.dumps(results))
    poses = np.stack([np.linspace(0, 1, N), np.full(N, 1.0)], axis=1)
    errs = np.full(N, 3.0 + A[j] + B[k])
    np.savez(wd / "errors_test.npz", rotation_error_deg=errs, scene=np.zeros(N), pose=poses)
    out.append(str(wd))
  return out


def test_two_way_anova_of_a_crossed_table(tmp_path, capsys):
  ss = seed_spread
  full = [(j, k) for j in range(3) for k in range(3)]
  _runs(tmp_path, full)
  runs = ss.load_runs([str(tmp_path / "crossed" / "*")])
  syn, reg, y = ss.grid(runs)
  assert syn == [0, 1, 2] and reg == [0, 1, 2]
  np.testing.assert_allclose(y, 3.0 + np.array(list(A.values()))[:, None] + list(B.values()))
  split = stats.two_way_anova(y)
  # Additive effects: the rows carry 6 of the 7.5 of the total sum of squares, the columns 1.5,
  # no residual; the components are the effects' sample variances (1 and 0.25).
  assert split["synthesis"]["ss"] == pytest.approx(6.0) and split["total"]["ss"] == pytest.approx(
    7.5
  )
  assert split["synthesis"]["share"] == pytest.approx(0.8)
  assert split["synthesis"]["component"] == pytest.approx(1.0)
  assert split["regression"]["component"] == pytest.approx(0.25)
  assert split["residual"]["ss"] == pytest.approx(0.0, abs=1e-12)
  # The sums of squares add up for any table, and an interaction lands in the residual.
  rng = np.random.default_rng(0)
  y2 = rng.normal(size=(3, 4))
  s2 = stats.two_way_anova(y2)
  parts = sum(s2[k]["ss"] for k in ("synthesis", "regression", "residual"))
  assert parts == pytest.approx(s2["total"]["ss"]) and s2["residual"]["df"] == 6
  y3 = y.copy()
  y3[0, 0] += 1.0
  assert stats.two_way_anova(y3)["residual"]["ss"] > 0.1

  md = tmp_path / "out" / "spread.md"
  decoded = {0: 1.0, 1: 2.0, 2: 3.0}
  args = ["--runs", str(tmp_path / "crossed" / "*"), "--md", str(md), "--decode"]
  assert ss.main(args, decode=lambda runs: decoded) == 0
  text = md.read_text()
  assert "| synthesis seed \\ regression seed | 0 | 1 | 2 | row mean | decoding error |" in text
  assert "| 1 | 4.00 | 4.50 | 3.50 | 4.00 | 2.00 |" in text
  assert "| between synthesis seeds | 2 | 6.00 (80%) | 1.00 | 1.00 |" in text
  assert "| between regression seeds | 2 | 1.50 (20%) | 0.250 | 0.500 |" in text
  assert "averages 2.00 against a regression error of 4.00 (50% of it)" in text
  assert "Pearson correlation with the row mean is 1.00 (3 points)" in text
  capsys.readouterr()


def test_refusals(tmp_path, capsys):
  ss = seed_spread
  _runs(tmp_path, [(0, 0), (0, 1), (1, 0)])  # (1, 1) missing
  md = str(tmp_path / "x.md")
  assert ss.main(["--runs", str(tmp_path / "crossed" / "*"), "--md", md]) == 2
  err = capsys.readouterr().err
  assert "not fully crossed" in err and "(1, 1)" in err
  other = tmp_path / "quat"
  other.mkdir()
  _runs(other, [(0, 0)], representation="quat")
  assert ss.main(["--runs", str(other / "crossed" / "*"), "--md", md]) == 2
  assert "not 'ours'" in capsys.readouterr().err
  lrs = tmp_path / "lrs"
  lrs.mkdir()
  _runs(lrs, [(0, 0)], lr=1e-3)
  (lrs / "crossed" / "lr_seed0_syn0").rename(lrs / "crossed" / "first")
  _runs(lrs, [(0, 1)], lr=3e-3)
  assert ss.main(["--runs", str(lrs / "crossed" / "*"), "--md", md]) == 2
  assert "several learning rates" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.usefixtures("fast_compile")
def test_decoding_error_of_a_pose_system(tmp_path):
  """The decoding error is the error of the true poses encoded and decoded with the workdir's
  own pose system, quantisation and refinement (what the regression's own codec gives), within
  a grid cell (10 degrees) for a system of one training step."""
  import jax.numpy as jnp

  from camrep.regression import pose_system, scoring
  from camrep.regression import targets as T

  ss = seed_spread
  config = shapenet_car.get_config("smoke")
  config.total_steps, config.evals.num_scenes = 1, 1
  wd = str(tmp_path / "car")
  train.train_and_evaluate(config, wd, log=lambda s: None)
  azimuth = np.radians(np.arange(0, 360, 30, dtype=np.float64))
  poses = np.stack([azimuth, np.full_like(azimuth, math.radians(60))], axis=1)
  got = {}
  for mode in ("nearest", "floor"):
    kw = dict(error="azimuth_error_deg", quantisation=mode, refine_steps=0)
    got[mode] = ss.decoding_error(wd, "car", poses, **kw)
    system = pose_system.load_pose_system(wd, "car")
    codec = dict(spec=system["spec"], rep_params=system["rep"], mode=mode)
    true = jnp.asarray(poses, jnp.float32)
    back = T.decode("ours", "car", T.encode("ours", "car", true, **codec), refine_steps=0, **codec)
    want = float(np.mean(scoring.pose_errors("car", back, true)["azimuth_error_deg"]))
    assert got[mode] == pytest.approx(want, rel=1e-6)
    assert 0.0 <= got[mode] < 10.0
  assert got["nearest"] != got["floor"]  # the quantisation is passed through

"""Bootstrap intervals and paired comparisons (camrep/regression/stats.py) on synthetic per-view
errors with known answers, and Table 1 built from run directories with errors_test.npz."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from camrep.regression import stats, tables
from experiments import table1, table2


def _errors(seed, shape=(3, 200), scale=1.0):
  return np.random.default_rng(seed).gamma(2.0, scale, shape)


def test_interval_covers_the_mean_and_shrinks_with_more_views():
  e = _errors(0)
  iv = stats.interval(e)
  assert iv.value == pytest.approx(e.mean()) and iv.lo < iv.value < iv.hi
  assert (iv.n_seeds, iv.n_views) == (3, 200)
  assert stats.interval(e) == iv  # fixed bootstrap seed: reproducible
  wide = stats.interval(_errors(0, (3, 20)))
  assert (wide.hi - wide.lo) > 2 * (iv.hi - iv.lo)
  # A seed offset (one seed's errors all larger) widens the interval: seeds are resampled.
  shifted = e + np.array([[0.0], [0.0], [3.0]])
  s = stats.interval(shifted)
  assert (s.hi - s.lo) > 3 * (iv.hi - iv.lo)
  # Constant errors: a point interval.
  c = stats.interval(np.full((3, 10), 2.0))
  assert (c.value, c.lo, c.hi) == (2.0, 2.0, 2.0)


def test_medians_per_scene_averaged():
  e = np.array([[1.0, 2.0, 3.0, 10.0, 20.0, 30.0], [1.0, 2.0, 3.0, 10.0, 20.0, 30.0]])
  scenes = np.array([0, 0, 0, 1, 1, 1])
  assert stats.statistic(e, scenes, "median") == pytest.approx((2.0 + 20.0) / 2)
  assert stats.statistic(e, None, "median") == pytest.approx(6.5)
  iv = stats.interval(e, scenes, "median")
  assert iv.lo >= 1.0 * 0 + (1 + 10) / 2 and iv.hi <= (3 + 30) / 2


def test_paired_verdicts():
  base = _errors(1)
  same = stats.paired_ratio(base, base.copy(), baseline="quat")
  assert same.verdict == "tie" and (same.ratio.value, same.ratio.lo, same.ratio.hi) == (1, 1, 1)
  better = stats.paired_ratio(0.6 * base * (1 + 0.1 * _errors(2)), base, baseline="quat")
  assert better.verdict == "better" and better.ratio.hi < 1 and better.baseline == "quat"
  worse = stats.paired_ratio(1.5 * base, base)
  assert worse.verdict == "worse" and worse.ratio.value == pytest.approx(1.5)
  # Unpaired noise of the same size: a tie, and the interval contains the point ratio.
  noisy = stats.paired_ratio(_errors(3), _errors(4))
  assert noisy.verdict == "tie" and noisy.ratio.lo < noisy.ratio.value < noisy.ratio.hi
  # Pairing matters: a per-view difficulty shared by both makes a 10% gain detectable.
  hard = np.exp(np.random.default_rng(5).normal(0, 1.5, (3, 200)))
  assert stats.paired_ratio(0.9 * hard, hard).verdict == "better"
  assert [stats.verdict(*x) for x in ((0.5, 0.9), (0.9, 1.1), (1.01, 2.0))] == [
    "better",
    "tie",
    "worse",
  ]
  with pytest.raises(ValueError, match="equal"):
    stats.paired_ratio(base[:2], base)


def _write_run(root, rep, seed, errors, *, lr=1e-3, poses=None, setting="car"):
  wd = os.path.join(root, setting, rep, f"lr{lr:g}_seed{seed}")
  os.makedirs(wd)
  n = len(errors)
  poses = np.tile(np.arange(n, dtype=np.float32)[:, None], (1, 2)) if poses is None else poses
  np.savez(
    os.path.join(wd, "errors_test.npz"),
    rotation_error_deg=np.asarray(errors, np.float32),
    scene=np.zeros(n, np.int32),
    pose=poses,
  )
  summ = {"all": {"rotation_error_deg": {"mean": float(np.mean(errors)), "median": 0.0}}}
  r = dict(setting=setting, representation=rep, seed=seed, lr=lr, steps=10, variant="quick")
  r.update(validation=summ, test=summ, data={"test_split": "test"})
  with open(os.path.join(wd, "results.json"), "w") as f:
    json.dump(r, f)


def test_table1_intervals_and_verdicts_from_run_directories(tmp_path):
  root = str(tmp_path / "runs")
  for seed in range(3):
    base = _errors(10 + seed, (100,))
    _write_run(root, "quat", seed, base)
    _write_run(root, "sincos", seed, 1.3 * base)
    _write_run(root, "ours", seed, 0.5 * base)
  C = table1
  results = C.C.load_results([os.path.join(root, "*", "*", "*")])
  sel = C.C.select(results)
  comp = stats.compare_runs(sel["car", "ours"].runs, sel["car", "quat"].runs, "rotation_error_deg")
  assert comp.verdict == "better" and comp.ratio.value == pytest.approx(0.5, rel=1e-5)
  text = C.build(results)
  iv = stats.cell_interval(sel["car", "ours"].runs, "rotation_error_deg")
  assert f"| ours | {stats.fmt_interval(iv, digits=C.C.digits_for(iv.value))} |" in text
  assert "| ours / best hand-designed | 0.50 [0.50, 0.50] better (vs quat; 3 seeds) |" in text
  # Other test views (other true poses) cannot be paired: named, not silently compared.
  _write_run(root, "logq", 0, _errors(9, (100,)), poses=np.ones((100, 2), np.float32))
  _write_run(root, "logq", 1, _errors(8, (100,)))
  with pytest.raises(ValueError, match="other test views"):
    stats.seed_matrix(
      C.C.select(C.C.load_results([os.path.join(root, "*", "*", "*")]))["car", "logq"].runs,
      "rotation_error_deg",
    )


def test_table2_average_intervals_and_verdicts(tmp_path):
  root = str(tmp_path / "runs")
  scenes = np.repeat(np.arange(2, dtype=np.int32), 50)
  for seed in range(3):
    pos, rot = _errors(20 + seed, (100,)), _errors(30 + seed, (100,))
    for rep, f_pos, f_rot in (("quat", 1.0, 1.0), ("logq", 1.2, 1.2), ("ours", 0.5, 1.0)):
      wd = os.path.join(root, "seven_scenes", rep, f"lr1e-3_seed{seed}")
      os.makedirs(wd)
      e = {"position_error": f_pos * pos, "rotation_error_deg": f_rot * rot}
      np.savez(os.path.join(wd, "errors_test.npz"), scene=scenes, **e)
      summ = {
        str(k) if k != "all" else k: {
          n: {"mean": 0.0, "median": float(np.median(v if k == "all" else v[scenes == k]))}
          for n, v in e.items()
        }
        for k in ("all", 0, 1)
      }
      r = dict(setting="seven_scenes", representation=rep, seed=seed, lr=1e-3, variant="quick")
      r.update(validation=summ, test=summ)
      r["data"] = {"test_split": "test", "scene_names": {"0": "chess", "1": "stairs"}}
      with open(os.path.join(wd, "results.json"), "w") as f:
        json.dump(r, f)
  text = table2.build(tables.load_results([os.path.join(root, "*", "*", "*")]))
  row = next(x for x in text.splitlines() if x.startswith("| ours / best hand-designed"))
  # ours halves quat's position errors view by view and equals its rotation errors.
  assert "position 0.50 [0.50, 0.50] better (vs quat; 3 seeds)" in row
  assert "rotation 1.00 [1.00, 1.00] tie (vs quat; 3 seeds)" in row
  assert "95% bootstrap interval" in text
  # Each scene's cell: the mean over seeds of the scene's median, with its own interval.
  runs = tables.select(tables.load_results([os.path.join(root, "*", "*", "*")]))
  ours = runs["seven_scenes", "ours"].runs
  pos = stats.seed_matrix(ours, "position_error")[0][:, scenes == 1]
  rot = stats.seed_matrix(ours, "rotation_error_deg")[0][:, scenes == 1]
  iv_pos, iv_rot = stats.interval(pos, None, "median"), stats.interval(rot, None, "median")
  stairs = next(x for x in text.splitlines() if x.startswith("| stairs |"))
  cell = f"{stats.fmt_interval(iv_pos, digits=2)} m, {stats.fmt_interval(iv_rot, digits=1)}°"
  assert stairs.split("|")[ours_column(text)].strip() == cell
  assert iv_pos.lo < iv_pos.value < iv_pos.hi
  assert abs(iv_pos.value - np.median(pos, axis=1).mean()) < 1e-12


def ours_column(text: str) -> int:
  """The index (in a `|`-split row) of Table 2's "ours" column."""
  header = next(x for x in text.splitlines() if x.startswith("| scene |"))
  return [c.strip() for c in header.split("|")].index("ours")


# ---------------------------------------------------------------- seed-level intervals and Holm


def test_holm_matches_a_hand_computed_example():
  """p = (0.01, 0.04, 0.03, 0.005), m = 4: sorted 0.005, 0.01, 0.03, 0.04 times 4, 3, 2, 1 give
  0.02, 0.03, 0.06, 0.04, made monotone 0.02, 0.03, 0.06, 0.06; NaN is left out of m."""
  adj = stats.holm([0.01, 0.04, float("nan"), 0.03, 0.005])
  np.testing.assert_allclose(adj[[0, 1, 3, 4]], [0.03, 0.06, 0.06, 0.02])
  assert np.isnan(adj[2])
  assert stats.holm([0.5, 0.9]).tolist() == [1.0, 1.0]  # capped at 1
  assert stats.holm([0.01]).tolist() == [0.01]  # one test: unchanged


def test_t_quantiles_and_interval_against_closed_forms():
  """t quantiles: 1 df tan(pi (q - 1/2)); 2 df (2q - 1) sqrt(2 / (4 q (1 - q))); the 2-df two-sided
  p of t is 1 - t / sqrt(2 + t^2)."""
  for q in (0.9, 0.975, 0.995):
    assert stats.t_quantile(q, 1) == pytest.approx(np.tan(np.pi * (q - 0.5)), rel=1e-9)
    assert stats.t_quantile(q, 2) == pytest.approx((2 * q - 1) * np.sqrt(2 / (4 * q * (1 - q))))
  assert stats.t_quantile(0.975, 9) == pytest.approx(2.262157, abs=1e-6)
  m, lo, hi, p = stats.seed_t_interval([1.0, 2.0, 3.0])  # mean 2, sd 1
  half = stats.t_quantile(0.975, 2) / np.sqrt(3)
  assert (m, lo, hi) == pytest.approx((2.0, 2 - half, 2 + half))
  t = 2 * np.sqrt(3)
  assert p == pytest.approx(1 - t / np.sqrt(2 + t * t))
  assert all(np.isnan(x) for x in stats.seed_t_interval([1.0])[1:])  # one seed: no interval
  assert stats.seed_t_interval([0.5, 0.5])[1:] == (0.5, 0.5, 0.0)  # no spread


def test_seed_ratio_is_the_t_interval_of_per_seed_log_ratios():
  """Per-seed ratios 1.2, 1.25, 1.3 (ours = c_s x base, per seed): the geometric mean and the t
  interval of their logs; swapping the two gives the reciprocal interval and the same p; a common
  scale changes nothing."""
  base = _errors(0, (3, 50))
  c = np.array([1.2, 1.25, 1.3])
  r = stats.seed_ratio(c[:, None] * base, base, baseline="quat", population=False)
  m, lo, hi, p = stats.seed_t_interval(np.log(c))
  assert r.per_seed == pytest.approx(tuple(c))
  assert (r.ratio.value, r.ratio.lo, r.ratio.hi) == pytest.approx(tuple(np.exp([m, lo, hi])))
  assert r.p == pytest.approx(p) and r.verdict() == "worse" and r.population is None
  swapped = stats.seed_ratio(base, c[:, None] * base, population=False)
  assert swapped.ratio.lo == pytest.approx(1 / r.ratio.hi) and swapped.p == pytest.approx(r.p)
  assert swapped.verdict() == "better" and swapped.verdict(p_adjusted=0.2) == "tie"
  scaled = stats.seed_ratio(7 * c[:, None] * base, 7 * base, population=False)
  assert scaled.ratio.hi == pytest.approx(r.ratio.hi)
  one = stats.seed_ratio(base[:1], base[:1])
  assert one.verdict() == "–" and np.isnan(one.population.lo)


def test_corrected_bootstrap_is_wider_than_the_percentile_bootstrap_at_three_seeds():
  """The corrected hierarchical bootstrap (sqrt(S / (S - 1)) and t_{S-1} quantiles) holds the
  ratio of the statistics and is wider than the percentile interval of the same replicates."""
  ours, base = _errors(1), _errors(2)
  c = stats.corrected_bootstrap_ratio(ours, base)
  plain = stats.paired_ratio(ours, base).ratio
  assert c.value == pytest.approx(plain.value)
  assert c.lo < plain.lo < plain.value < plain.hi < c.hi


def test_variance_components_recover_known_variances():
  """errors = 5 + seed (sd 2) + view (sd 1) + noise (sd 0.5) over 400 seeds and 400 views: the
  method of moments gives back 4, 1 and 0.25 (unlike the sums of squares' shares)."""
  rng = np.random.default_rng(0)
  s, n = 400, 400
  e = 5 + 2 * rng.standard_normal((s, 1)) + rng.standard_normal((1, n))
  e = e + 0.5 * rng.standard_normal((s, n))
  c = stats.variance_components(e)
  assert (c.mean, c.seed, c.view, c.noise) == pytest.approx((5, 4, 1, 0.25), rel=0.15)
  assert sum(c.shares()) == pytest.approx(1.0)
  with pytest.raises(ValueError, match=">= 2 seeds"):
    stats.variance_components(e[:1])


def test_seed_view_ratio_adds_the_views_variance_to_the_seed_level_interval():
  """The population interval shares the seed-level centre; where the views barely change the
  ratio (ours = c_s x base, view by view) it is the seed-level t interval up to 1%; where every
  seed gives the same ratio on every view draw it has no width; where the views do change the
  ratio (10 seeds, 30 views) it is wider than the seed-level interval; NaN for one seed."""
  base = _errors(0, (3, 50))
  c = np.array([1.2, 1.25, 1.3])
  r = stats.seed_ratio(c[:, None] * base, base)
  assert r.population.value == pytest.approx(r.ratio.value)
  assert (r.population.lo, r.population.hi) == pytest.approx((r.ratio.lo, r.ratio.hi), rel=1e-2)
  flat = stats.seed_view_ratio(2 * base, base)
  assert (flat.lo, flat.value, flat.hi) == pytest.approx((2.0, 2.0, 2.0))
  ours, other = _errors(1, (10, 30)), _errors(2, (10, 30))
  seed_only = stats.seed_ratio(ours, other, population=False).ratio
  both = stats.seed_view_ratio(ours, other)
  assert both.lo < seed_only.lo and seed_only.hi < both.hi
  assert np.isnan(stats.seed_view_ratio(ours[:1], other[:1]).lo)

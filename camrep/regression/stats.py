"""Intervals over seeds and test views, and the paired comparison of two representations
(results that carry a conclusion). Pure NumPy, for the table readers (experiments/table1.py, ...).

A table cell is the errors of one representation in one column: a (S, N) matrix E of per-view
test errors, S seeds (runs at the chosen learning rate) by N test views (the same views in every
run: the test split does not depend on the seed). Its statistic is

  stat(E) = mean over seeds of reduce(E[s, views of each scene]) averaged over scenes

with reduce the mean (Table 1: then stat is the mean of E) or the median (Table 2: per-scene
medians averaged over scenes, as the paper's "average"); without scenes, one group of all views.

Interval: a two-level bootstrap, `B` replicates with a fixed NumPy seed: each replicate draws S
seeds with replacement and, independently, N views with replacement (within each scene when
there are scenes, so every scene keeps its count), the same view draw for every drawn seed, and
recomputes the statistic; the 95% interval is the 2.5 and 97.5 percentiles of the replicates.

Paired comparison ("ours" against a baseline in one column): both matrices on the same seeds
(the seeds both have, matched by seed number) and the same views (checked: the true poses are
equal). Two intervals of the ratio stat(E_ours) / stat(E_base):

  - seed-level t interval (`seed_ratio`, the verdict's): per seed s the ratio
    r_s = stat(E_ours[s]) / stat(E_base[s]) on the shared test views; with l_s = log r_s,
    l̄ and sd over the S seeds, the interval is exp(l̄ ± t_{S-1, 0.975} sd / sqrt(S)) around the
    geometric mean exp(l̄), and p the two-sided one-sample t test of mean log ratio 0 (S - 1
    degrees of freedom; S >= 2). The seeds are the independent units: with 3 seeds this is
    wide (t_{2, 0.975} = 4.30), as it must be. The test views are shared by every seed, so
    their sampling is not in this interval: it is an interval for this test set;
  - seed-level t widened by the views (`seed_view_ratio`, beside it): the same centre, the
    variance of l̄ plus the variance of the log ratio when only the test views are resampled
    (every seed kept), t quantiles with Welch-Satterthwaite degrees of freedom: an interval for
    the population of views, not only this test set;
  - hierarchical bootstrap with a small-sample correction (`corrected_bootstrap_ratio`): the
    two-level bootstrap above applied to both matrices with one draw per replicate, its
    standard error of the log ratio inflated by sqrt(S / (S - 1)) (a bootstrap of S seeds
    underestimates the seed variance by (S - 1) / S) and t quantiles in place of the
    percentiles: log ratio ± t_{S-1, 0.975} se. It covers about 100% in the records' regimes
    (too wide to decide anything) and is kept for the coverage check only.

`paired_ratio` keeps the plain percentile bootstrap (2.5 and 97.5 percentiles of the replicated
ratio), which undercovers where the seeds dominate a cell's variance (`regression.coverage`).

Verdicts over a table: each comparison's p value, Holm-adjusted over the table's comparisons
(`holm`); "better" / "worse" when the adjusted p is below 0.05 (the direction from l̄), else
"tie"; unadjusted, p < 0.05 is the t interval excluding 1.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy import stats as sp_stats

from camrep.regression import runs as runs_lib

B = 2000  # bootstrap replicates
SEED = 0  # of the bootstrap's random generator: tables are reproducible
HAND_DESIGNED = ("euler", "axis_angle", "sincos", "quat", "logq", "rot6d", "svd9d")
LEVEL = 0.95  # of every interval
ALPHA = 0.05  # family-wise error rate of a table's verdicts (Holm)


@dataclasses.dataclass(frozen=True)
class Interval:
  """A statistic and its 95% bootstrap interval (lo, hi), from `n_seeds` x `n_views`."""

  value: float
  lo: float
  hi: float
  n_seeds: int
  n_views: int


@dataclasses.dataclass(frozen=True)
class Comparison:
  """Paired ratio stat(ours) / stat(baseline) with its interval and verdict."""

  ratio: Interval
  baseline: str
  verdict: str  # "better", "tie" or "worse" (for ours)


def _groups(scenes: np.ndarray | None, n: int) -> list[np.ndarray]:
  if scenes is None:
    return [np.arange(n)]
  scenes = np.asarray(scenes)
  return [np.flatnonzero(scenes == s) for s in np.unique(scenes)]


def statistic(errors: np.ndarray, scenes: np.ndarray | None = None, reduce: str = "mean") -> float:
  """stat(E) of the module docstring.

  Args:
    errors: (S, N) per-seed, per-view errors.
    scenes: (N,) scene id of each view, or None (one group).
    reduce: "mean" or "median" over a scene's views.
  """
  fn = {"mean": np.mean, "median": np.median}[reduce]
  errors = np.asarray(errors, np.float64)
  per = [fn(errors[:, g], axis=1) for g in _groups(scenes, errors.shape[1])]
  return float(np.mean(np.mean(per, axis=0)))


def _draws(rng, n_seeds: int, groups: Sequence[np.ndarray]):
  seeds = rng.integers(0, n_seeds, n_seeds)
  views = np.concatenate([g[rng.integers(0, len(g), len(g))] for g in groups])
  return seeds, views


def _resampled_stats(mats, scenes, reduce, b, seed, chunk: int = 250) -> np.ndarray:
  """(b, len(mats)) statistics of the matrices under shared seed and view draws.

  The draws come one replicate at a time, in `_draws`' order (the intervals depend on it); the
  statistics of `chunk` replicates are computed at once. Each replicate's views are drawn group
  by group, keeping each group's count, so its groups are the same blocks of columns in every
  replicate: per block, `reduce` over the block (the (S, n_g) rows, as `statistic` reduces
  them), the mean over blocks, then over seeds: the values `statistic` gives, bit for bit.
  """
  rng = np.random.default_rng(seed)
  n_seeds, n = mats[0].shape
  groups = _groups(scenes, n)
  draws = [_draws(rng, n_seeds, groups) for _ in range(b)]
  seeds = np.stack([d[0] for d in draws])  # (b, S)
  views = np.stack([d[1] for d in draws])  # (b, N), group by group
  bounds = np.cumsum([0, *(len(g) for g in groups)])
  fn = {"mean": np.mean, "median": np.median}[reduce]
  out = np.empty((b, len(mats)))
  for lo in range(0, b, chunk):
    s, v = seeds[lo : lo + chunk], views[lo : lo + chunk]
    for j, m in enumerate(mats):
      m = np.asarray(m, np.float64)
      sub = m[s[:, :, None], v[:, None, :]]  # (c, S, N)
      per = np.stack(
        [fn(sub[:, :, a:z], axis=2) for a, z in zip(bounds[:-1], bounds[1:], strict=True)]
      )
      out[lo : lo + chunk, j] = np.mean(np.mean(per, axis=0), axis=1)
  return out


def interval(
  errors: np.ndarray,
  scenes: np.ndarray | None = None,
  reduce: str = "mean",
  *,
  b: int = B,
  seed: int = SEED,
) -> Interval:
  """The statistic of (S, N) errors with its 95% bootstrap interval (module docstring)."""
  errors = np.asarray(errors, np.float64)
  if errors.ndim != 2 or errors.size == 0:
    raise ValueError(f"errors must be a non-empty (seeds, views) matrix, got {errors.shape}")
  reps = _resampled_stats([errors], scenes, reduce, b, seed)[:, 0]
  lo, hi = np.percentile(reps, [2.5, 97.5])
  value = statistic(errors, scenes, reduce)
  return Interval(value, float(lo), float(hi), errors.shape[0], errors.shape[1])


def seed_interval(
  errors: np.ndarray, scenes: np.ndarray | None = None, reduce: str = "mean", level: float = LEVEL
) -> Interval:
  """The statistic of (S, N) errors with the t interval of its S per-seed statistics (S - 1
  degrees of freedom; NaN bounds for one seed): an interval over seeds for this test set."""
  errors = np.asarray(errors, np.float64)
  if errors.ndim != 2 or errors.size == 0:
    raise ValueError(f"errors must be a non-empty (seeds, views) matrix, got {errors.shape}")
  m, lo, hi, _ = seed_t_interval(per_seed_statistics(errors, scenes, reduce), level)
  return Interval(m, lo, hi, errors.shape[0], errors.shape[1])


def verdict(lo: float, hi: float) -> str:
  """ "better" (interval of ours / baseline below 1), "worse" (above 1) or "tie"."""
  if hi < 1:
    return "better"
  if lo > 1:
    return "worse"
  return "tie"


def paired_ratio(
  ours: np.ndarray,
  base: np.ndarray,
  scenes: np.ndarray | None = None,
  reduce: str = "mean",
  *,
  baseline: str = "",
  b: int = B,
  seed: int = SEED,
) -> Comparison:
  """stat(ours) / stat(base) of two (S, N) matrices paired by row (seed) and column (view)."""
  ours, base = np.asarray(ours, np.float64), np.asarray(base, np.float64)
  if ours.shape != base.shape or ours.ndim != 2 or ours.size == 0:
    raise ValueError(
      f"paired errors need equal (seeds, views) shapes, got {ours.shape}, {base.shape}"
    )
  reps = _resampled_stats([ours, base], scenes, reduce, b, seed)
  with np.errstate(divide="ignore", invalid="ignore"):
    ratios = reps[:, 0] / reps[:, 1]
  lo, hi = np.percentile(ratios, [2.5, 97.5])
  value = statistic(ours, scenes, reduce) / statistic(base, scenes, reduce)
  r = Interval(float(value), float(lo), float(hi), ours.shape[0], ours.shape[1])
  return Comparison(r, baseline, verdict(r.lo, r.hi))


def t_quantile(q: float, df: float) -> float:
  """The q quantile of Student's t with df degrees of freedom."""
  return float(sp_stats.t.ppf(q, df))


@dataclasses.dataclass(frozen=True)
class SeedComparison:
  """Seed-level paired comparison of ours against a baseline (module docstring).

  Attributes:
    ratio: the geometric mean of the per-seed ratios with its seed-level t interval (NaN bounds
      for one seed).
    per_seed: (S,) ratios r_s, in seed order.
    p: two-sided p value of mean log ratio 0 (NaN for one seed, 0 when every r_s is equal and
      not 1).
    population: the same geometric mean with the interval widened by the test views' sampling
      (`seed_view_ratio`), or None when not computed.
    baseline: the baseline's name.
  """

  ratio: Interval
  per_seed: tuple[float, ...]
  p: float
  population: Interval | None
  baseline: str

  @property
  def direction(self) -> str:
    """ "better" (geometric mean ratio below 1) or "worse" (at or above 1)."""
    return "better" if self.ratio.value < 1 else "worse"

  def verdict(self, p_adjusted: float | None = None, alpha: float = ALPHA) -> str:
    """ "better" / "worse" when p (or the Holm-adjusted p) is below alpha, else "tie"; "–"
    without a p value (one seed)."""
    p = self.p if p_adjusted is None else p_adjusted
    if not math.isfinite(p):
      return "–"
    return self.direction if p < alpha else "tie"


def seed_t_interval(values: np.ndarray, level: float = LEVEL) -> tuple[float, float, float, float]:
  """(mean, lo, hi, p) of a one-sample t interval and the two-sided test of mean 0.

  Args:
    values: (S,) independent values (per-seed log ratios).
    level: the interval's coverage.

  Returns NaN bounds and p for S < 2; for S >= 2 with zero spread, the mean as both bounds and p
  0 (or 1 when the mean is 0).
  """
  x = np.asarray(values, np.float64)
  n, m = len(x), float(np.mean(x))
  if n < 2:
    return m, math.nan, math.nan, math.nan
  se = float(np.std(x, ddof=1)) / math.sqrt(n)
  if se == 0:
    return m, m, m, (1.0 if m == 0 else 0.0)
  half = t_quantile(0.5 + level / 2, n - 1) * se
  p = float(2 * sp_stats.t.sf(abs(m) / se, n - 1))
  return m, m - half, m + half, p


def welch_interval(
  a: np.ndarray, b: np.ndarray, level: float = LEVEL
) -> tuple[float, float, float]:
  """(mean(a) - mean(b), lo, hi): Welch's t interval of a difference of means of two
  independent samples (Welch-Satterthwaite degrees of freedom); NaN bounds when a sample has
  one value."""
  a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
  d = float(a.mean() - b.mean())
  if len(a) < 2 or len(b) < 2:
    return d, math.nan, math.nan
  va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
  se = math.sqrt(va + vb)
  if se == 0:
    return d, d, d
  df = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))
  half = t_quantile(0.5 + level / 2, df) * se
  return d, d - half, d + half


def per_seed_statistics(
  errors: np.ndarray, scenes: np.ndarray | None = None, reduce: str = "mean"
) -> np.ndarray:
  """(S,) stat of each seed's row of (S, N) errors (`statistic` of one seed)."""
  errors = np.asarray(errors, np.float64)
  return np.array([statistic(row[None], scenes, reduce) for row in errors])


def corrected_bootstrap_ratio(
  ours: np.ndarray,
  base: np.ndarray,
  scenes: np.ndarray | None = None,
  reduce: str = "mean",
  *,
  level: float = LEVEL,
  b: int = B,
  seed: int = SEED,
) -> Interval:
  """stat(ours) / stat(base) with the corrected hierarchical bootstrap interval (module
  docstring); NaN bounds for one seed."""
  ours, base = np.asarray(ours, np.float64), np.asarray(base, np.float64)
  s, n = ours.shape
  value = statistic(ours, scenes, reduce) / statistic(base, scenes, reduce)
  if s < 2:
    return Interval(float(value), math.nan, math.nan, s, n)
  reps = _resampled_stats([ours, base], scenes, reduce, b, seed)
  with np.errstate(divide="ignore", invalid="ignore"):
    logs = np.log(reps[:, 0] / reps[:, 1])
  logs = logs[np.isfinite(logs)]
  se = float(np.std(logs, ddof=1)) * math.sqrt(s / (s - 1))
  half = t_quantile(0.5 + level / 2, s - 1) * se
  c = math.log(value)
  return Interval(float(value), math.exp(c - half), math.exp(c + half), s, n)


def seed_view_ratio(
  ours: np.ndarray,
  base: np.ndarray,
  scenes: np.ndarray | None = None,
  reduce: str = "mean",
  *,
  level: float = LEVEL,
  b: int = B,
  seed: int = SEED,
) -> Interval:
  """The seed-level t interval widened by the test views' sampling: with l_s the per-seed log
  ratios (S of them) and v the variance of log(stat(ours) / stat(base)) when only the views are
  resampled (`b` replicates, every seed kept, within each scene), the interval is
  exp(l̄ ± t_df sqrt(sd(l)^2 / S + v)) with Welch-Satterthwaite's
  df = (sd^2 / S + v)^2 / ((sd^2 / S)^2 / (S - 1) + v^2 / (N - 1)): t_{S-1} where the seeds
  dominate, near normal where the views do. An interval for the population of views, not only
  this test set; NaN bounds for one seed."""
  ours, base = np.asarray(ours, np.float64), np.asarray(base, np.float64)
  s, n = ours.shape
  with np.errstate(divide="ignore", invalid="ignore"):
    logs = np.log(
      per_seed_statistics(ours, scenes, reduce) / per_seed_statistics(base, scenes, reduce)
    )
  m = float(np.mean(logs))
  if s < 2:
    return Interval(math.exp(m), math.nan, math.nan, s, n)
  rng = np.random.default_rng(seed)
  groups = _groups(scenes, n)
  views = np.stack(
    [np.concatenate([g[rng.integers(0, len(g), len(g))] for g in groups]) for _ in range(b)]
  )
  sub_scenes = None if scenes is None else np.asarray(scenes)[np.concatenate(groups)]
  reps = np.empty(b)
  for i, v in enumerate(views):
    with np.errstate(divide="ignore", invalid="ignore"):
      reps[i] = np.log(
        statistic(ours[:, v], sub_scenes, reduce) / statistic(base[:, v], sub_scenes, reduce)
      )
  var_v = float(np.nanvar(reps, ddof=1))
  var_s = float(np.var(logs, ddof=1)) / s
  total = var_s + var_v
  if total == 0:
    return Interval(math.exp(m), math.exp(m), math.exp(m), s, n)
  df = total**2 / (var_s**2 / (s - 1) + var_v**2 / max(n - 1, 1))
  half = t_quantile(0.5 + level / 2, df) * math.sqrt(total)
  return Interval(math.exp(m), math.exp(m - half), math.exp(m + half), s, n)


def seed_ratio(
  ours: np.ndarray,
  base: np.ndarray,
  scenes: np.ndarray | None = None,
  reduce: str = "mean",
  *,
  baseline: str = "",
  level: float = LEVEL,
  population: bool = True,
  b: int = B,
  seed: int = SEED,
) -> SeedComparison:
  """Seed-level comparison of two (S, N) matrices paired by row (seed) and column (view),
  with the interval for the population of views beside it (`population`: `seed_view_ratio`)."""
  ours, base = np.asarray(ours, np.float64), np.asarray(base, np.float64)
  if ours.shape != base.shape or ours.ndim != 2 or ours.size == 0:
    raise ValueError(
      f"paired errors need equal (seeds, views) shapes, got {ours.shape}, {base.shape}"
    )
  with np.errstate(divide="ignore", invalid="ignore"):
    r = per_seed_statistics(ours, scenes, reduce) / per_seed_statistics(base, scenes, reduce)
    m, lo, hi, p = seed_t_interval(np.log(r), level)
  iv = Interval(math.exp(m), math.exp(lo), math.exp(hi), ours.shape[0], ours.shape[1])
  pop = (
    seed_view_ratio(ours, base, scenes, reduce, level=level, b=b, seed=seed) if population else None
  )
  return SeedComparison(iv, tuple(float(x) for x in r), p, pop, baseline)


def holm(pvalues: Sequence[float]) -> np.ndarray:
  """Holm's step-down adjusted p values (same order as `pvalues`; NaN stays NaN and is not
  counted): the k-th smallest of m p values becomes max over j <= k of min(1, (m - j + 1) p_(j)).
  Rejecting where the adjusted p is below alpha keeps the family-wise error rate at alpha."""
  p = np.asarray(pvalues, np.float64)
  out = np.full(p.shape, np.nan)
  ok = np.flatnonzero(np.isfinite(p))
  m = len(ok)
  if not m:
    return out
  order = ok[np.argsort(p[ok], kind="stable")]
  adj = np.minimum(1.0, (m - np.arange(m)) * p[order])
  out[order] = np.maximum.accumulate(adj)
  return out


def values_interval(values: Sequence[float]) -> tuple[Interval, float]:
  """The mean of (S,) per-seed values with its 95% t interval over seeds, and the two-sided p of
  mean 0 (the one interval call; NaN bounds and p for one seed)."""
  x = np.asarray(values, np.float64)
  m, lo, hi, p = seed_t_interval(x)
  return Interval(m, lo, hi, len(x), 1), p


def paired_seed_difference(ours: Mapping[int, float], base: Mapping[int, float]):
  """(interval of the mean paired difference ours - base, its p) over the seeds both have;
  (None, NaN) with fewer than 2."""
  seeds = sorted(set(ours) & set(base))
  if len(seeds) < 2:
    return None, math.nan
  return values_interval([ours[s] - base[s] for s in seeds])


def holm_verdicts(results, *, higher_is_better: bool) -> list[str]:
  """Verdicts of one family of `paired_seed_difference` results, Holm-adjusted (family-wise 5%):
  "better"/"worse" by the sign of the mean difference, "tie" otherwise, "-" without a result."""
  adjusted = holm([p for _, p in results])
  out = []
  for (iv, _), p in zip(results, adjusted, strict=True):
    if iv is None:
      out.append("-")
    elif not p < 0.05 or iv.value == 0:
      out.append("tie")
    else:
      out.append("better" if (iv.value > 0) == higher_is_better else "worse")
  return out


# ------------------------------------------------------------------------------ from the runs


def errors_file(run: Mapping[str, Any]) -> str:
  """Where a loaded run's per-view errors come from: the errors_<test split>.npz beside its
  results.json, or its run.json ("" if it has no path)."""
  path = run.get("_path", "")
  if not path or path.endswith(runs_lib.RECORD_FILE):
    return path
  return runs_lib.errors_file(os.path.dirname(path), run)


def view_errors(run: Mapping[str, Any], error: str) -> dict[str, np.ndarray] | None:
  """{"errors": (N,), "scene": (N,), "pose": (N, P)} of one run's test split, or None when it
  has no per-view errors or none named `error`."""
  if "_run" in run:
    z = run["_run"].view_errors()
  else:
    path = errors_file(run)
    z = runs_lib.read_errors(path) if path.endswith(".npz") and os.path.isfile(path) else None
  if z is None or error not in z:
    return None
  out = {"errors": np.asarray(z[error], np.float64), "scene": np.asarray(z["scene"])}
  out["pose"] = np.asarray(z["pose"]) if "pose" in z else None
  return out


def seed_matrix(
  runs: Sequence[Mapping[str, Any]], error: str, seeds: Sequence[int] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
  """((S, N) errors, (N,) scenes, (N, P) poses) of runs (one per seed; only `seeds`, in that
  order, when given), or None when a run has no per-view errors.

  Raises:
    ValueError: the runs' test views differ (another count or other true poses).
  """
  by_seed = {int(r["seed"]): r for r in runs}
  order = list(seeds) if seeds is not None else sorted(by_seed)
  rows, scenes, poses = [], None, None
  for s in order:
    v = view_errors(by_seed[s], error)
    if v is None:
      return None
    if scenes is None:
      scenes, poses = v["scene"], v["pose"]
    elif len(v["errors"]) != len(scenes) or not _same_views(poses, v["pose"]):
      raise ValueError(
        f"runs {by_seed[order[0]].get('_path')} and {by_seed[s].get('_path')} have other test "
        "views: their errors cannot be paired"
      )
    rows.append(v["errors"])
  if not rows:
    return None
  return np.stack(rows), scenes, poses


def _same_views(a, b) -> bool:
  if a is None or b is None:
    return True
  return a.shape == b.shape and np.allclose(a, b, atol=1e-5)


def cell_interval(
  runs: Sequence[Mapping[str, Any]],
  error: str,
  reduce: str = "mean",
  *,
  by_scene: bool = False,
  method: str = "bootstrap",
) -> Interval | None:
  """The interval of one table cell from its runs' per-view errors (None without them):
  `interval` (method "bootstrap") or `seed_interval` ("seed_t")."""
  m = seed_matrix(runs, error)
  if m is None:
    return None
  errors, scenes, _ = m
  fn = {"bootstrap": interval, "seed_t": seed_interval}[method]
  return fn(errors, scenes if by_scene else None, reduce)


def _paired_errors(ours, base, error: str, baseline: str):
  """(ours' (S, N) errors, the baseline's, the views' scenes (N,)) on the S seeds both groups of
  runs have; None without a common seed or per-view errors.

  Raises:
    ValueError: the two groups' test views differ.
  """
  common = sorted({int(r["seed"]) for r in ours} & {int(r["seed"]) for r in base})
  if not common:
    return None
  a, b_ = seed_matrix(ours, error, common), seed_matrix(base, error, common)
  if a is None or b_ is None:
    return None
  if a[0].shape != b_[0].shape or not _same_views(a[2], b_[2]):
    raise ValueError(
      f"ours and {baseline or 'the baseline'} were tested on other views: cannot pair them"
    )
  return a[0], b_[0], a[1]


def compare_runs(
  ours: Sequence[Mapping[str, Any]],
  base: Sequence[Mapping[str, Any]],
  error: str,
  reduce: str = "mean",
  *,
  baseline: str = "",
  by_scene: bool = False,
) -> Comparison | None:
  """Paired comparison on the seeds both groups have (None: no common seed or no per-view
  errors).

  Raises:
    ValueError: the two groups' test views differ.
  """
  pair = _paired_errors(ours, base, error, baseline)
  if pair is None:
    return None
  a, b_, scenes = pair
  return paired_ratio(a, b_, scenes if by_scene else None, reduce, baseline=baseline)


def seed_compare_runs(
  ours: Sequence[Mapping[str, Any]],
  base: Sequence[Mapping[str, Any]],
  error: str,
  reduce: str = "mean",
  *,
  baseline: str = "",
  by_scene: bool = False,
  population: bool = True,
) -> SeedComparison | None:
  """`seed_ratio` of two groups of runs on the seeds both have (None: no common seed or no
  per-view errors).

  Raises:
    ValueError: the two groups' test views differ.
  """
  pair = _paired_errors(ours, base, error, baseline)
  if pair is None:
    return None
  a, b_, scenes = pair
  scenes = scenes if by_scene else None
  return seed_ratio(a, b_, scenes, reduce, baseline=baseline, population=population)


def best_hand_designed(
  cells: Mapping[str, float],
) -> str | None:
  """The hand-designed representation with the lowest finite value among `cells`
  ({representation: value}), or None."""
  cands = [(v, r) for r, v in cells.items() if r in HAND_DESIGNED and math.isfinite(v)]
  return min(cands)[1] if cands else None


def fmt_interval(iv: Interval | None, *, digits: int) -> str:
  """ "1.23 [1.10, 1.41]" ("–" for None)."""
  if iv is None or not math.isfinite(iv.value):
    return "–"
  return f"{iv.value:.{digits}f} [{iv.lo:.{digits}f}, {iv.hi:.{digits}f}]"


def fmt_comparison(c: Comparison | None) -> str:
  """ "0.81 [0.70, 0.93] better (vs quat)" ("–" for None)."""
  if c is None:
    return "–"
  r = c.ratio
  return f"{r.value:.2f} [{r.lo:.2f}, {r.hi:.2f}] {c.verdict} (vs {c.baseline})"


def fmt_seed_comparison(c: SeedComparison | None) -> str:
  """ "0.81 [0.70, 0.93] better (vs quat; 3 seeds)": the seed-level t interval and its
  unadjusted verdict ("–" for None)."""
  if c is None:
    return "–"
  r = c.ratio
  return (
    f"{r.value:.2f} [{r.lo:.2f}, {r.hi:.2f}] {c.verdict()} (vs {c.baseline}; {r.n_seeds} seeds)"
  )


@dataclasses.dataclass(frozen=True)
class Components:
  """Variance components of a (S, N) error matrix under errors = mu + seed + view + noise
  (two-way random effects without replication, method of moments; a negative estimate is
  clipped to 0). Unlike sums of squares, these are the variances of the effects themselves."""

  mean: float
  seed: float
  view: float
  noise: float

  def shares(self) -> tuple[float, float, float]:
    """(seed, view, noise) as fractions of their sum."""
    t = self.seed + self.view + self.noise
    return (self.seed / t, self.view / t, self.noise / t) if t > 0 else (0.0, 0.0, 0.0)


def variance_components(errors: np.ndarray) -> Components:
  """`Components` of (S, N) errors, S, N >= 2: with the mean squares
  MS_seed = N sum_s (m_s - m)^2 / (S - 1), MS_view = S sum_v (m_v - m)^2 / (N - 1) and
  MS_res = sum (e_sv - m_s - m_v + m)^2 / ((S - 1)(N - 1)),
  seed = (MS_seed - MS_res) / N, view = (MS_view - MS_res) / S, noise = MS_res
  (`two_way_anova` with seeds as rows and views as columns)."""
  e = np.asarray(errors, np.float64)
  s, n = e.shape
  if s < 2 or n < 2:
    raise ValueError(f"variance components need >= 2 seeds and views, got {e.shape}")
  a = two_way_anova(e, names=("seed", "view"))
  return Components(
    float(e.mean()), a["seed"]["component"], a["view"]["component"], a["residual"]["component"]
  )


def two_way_anova(
  y: np.ndarray, names: tuple[str, str] = ("synthesis", "regression")
) -> dict[str, dict[str, float]]:
  """Two-way ANOVA without replication of a (J, K) table, random effects (rows: by default
  synthesis seeds, columns regression seeds, as experiments/seed_spread.py crosses them): per
  source (the two `names`, "residual", "total") its df, sum of squares, share of the total sum of
  squares, and (not "total") the variance component by the method of moments, sigma^2_rows =
  max(0, (MS_rows - MS_res) / K), sigma^2_cols = max(0, (MS_cols - MS_res) / J), sigma^2_res =
  MS_res, and its square root.

  Raises:
    ValueError: fewer than 2 rows or 2 columns.
  """
  r, c = names
  y = np.asarray(y, np.float64)
  J, K = y.shape
  if J < 2 or K < 2:
    raise ValueError(f"need >= 2 {r} seeds and >= 2 {c} seeds, got {J} x {K}")
  m = y.mean()
  rows, cols = y.mean(axis=1), y.mean(axis=0)
  ss = {
    r: K * float(np.sum((rows - m) ** 2)),
    c: J * float(np.sum((cols - m) ** 2)),
    "residual": float(np.sum((y - rows[:, None] - cols[None, :] + m) ** 2)),
    "total": float(np.sum((y - m) ** 2)),
  }
  df = {r: J - 1, c: K - 1, "residual": (J - 1) * (K - 1), "total": J * K - 1}
  ms = {k: ss[k] / df[k] for k in (r, c, "residual")}
  comp = {
    r: max(0.0, (ms[r] - ms["residual"]) / K),
    c: max(0.0, (ms[c] - ms["residual"]) / J),
    "residual": ms["residual"],
  }
  out = {}
  for k in (r, c, "residual", "total"):
    share = ss[k] / ss["total"] if ss["total"] > 0 else float("nan")
    out[k] = {"df": df[k], "ss": ss[k], "share": share}
    if k in comp:
      out[k].update(component=comp[k], std=math.sqrt(comp[k]))
  return out

"""Coverage of the comparison's 95% intervals, simulated in a regime fitted to recorded errors.

A row of the lead table compares two (S, N) test-error matrices (seeds x views), ours and the
baseline's. `fit` splits each into errors = mean + seed effect + view effect + noise
(`stats.variance_components`); `simulate` draws new matrices from that model:

  - seed effects: normal with the estimated seed variance, independent for ours and the baseline
    (their seeds are separate runs);
  - view effects: the records' own centred per-view means, drawn with replacement as (ours,
    baseline) pairs within each scene, so a view hard for one stays hard for the other and the
    skewed, heavy-tailed spread of real view errors is kept;
  - noise: the records' two-way residuals (rescaled to unbiased variance), drawn with
    replacement;

and counts how often each 95% interval of ours / baseline (`METHODS`) holds the true ratio:

  - seed t, of the test set's value: the seed-level t interval (`stats.seed_ratio`, the
    verdict's) against the ratio of the expected statistics on the replicate's own test views
    (what the interval claims: a new seed on the same test set);
  - seed t, of the population value: the same interval against the ratio over the whole
    population of views (the records' views, infinitely resampled);
  - seed t widened by the views (`stats.seed_view_ratio`): the seed-level t interval with the
    views' resampling variance added (Welch-Satterthwaite df), against the population value;
  - corrected bootstrap: the hierarchical bootstrap with sqrt(S / (S - 1)) and t quantiles
    (`stats.corrected_bootstrap_ratio`), against the population value;
  - percentile bootstrap: the former method (`stats.paired_ratio`), against the population value.

The reader over archived records, its table and figure: experiments/coverage.py.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from camrep.regression import stats

TARGET = (0.90, 0.97)  # the coverage a 95% interval must reach at the seed counts used
METHODS = (
  ("t_test_set", "seed t, of the test set's value"),
  ("t_population", "seed t, of the population value"),
  ("seed_view", "seed t widened by the views, of the population value"),
  ("boot_corrected", "corrected bootstrap, of the population value"),
  ("boot_percentile", "percentile bootstrap (former), of the population value"),
)


@dataclasses.dataclass(frozen=True)
class Model:
  """errors = mean + seed + view + noise of ours (index 0) and the baseline (index 1).

  Attributes:
    label: the lead-table row.
    reduce: "mean" or "median" over a scene's views.
    scenes: (N,) scene of each recorded view, or None (one group).
    mean: (2,) grand means.
    seed_sd: (2,) standard deviations of the seed effects.
    views: (N, 2) centred per-view means (the view effects), recorded order.
    noise: two (M,) pools of residuals (unbiased scale).
    components: the two `stats.Components`.
  """

  label: str
  reduce: str
  scenes: np.ndarray | None
  mean: np.ndarray
  seed_sd: np.ndarray
  views: np.ndarray
  noise: tuple[np.ndarray, np.ndarray]
  components: tuple[stats.Components, stats.Components]


def fit(label: str, ours: np.ndarray, base: np.ndarray, scenes, reduce: str) -> Model:
  """The `Model` of a row's two (S, N) matrices."""
  comps, views, noise = [], [], []
  for e in (np.asarray(ours, np.float64), np.asarray(base, np.float64)):
    s, n = e.shape
    c = stats.variance_components(e)
    comps.append(c)
    mv = e.mean(axis=0)
    views.append(mv - mv.mean())
    res = e - e.mean(axis=1, keepdims=True) - mv[None] + e.mean()
    noise.append(res.ravel() * math.sqrt(s * n / ((s - 1) * (n - 1))))
  return Model(
    label,
    reduce,
    None if scenes is None else np.asarray(scenes),
    np.array([c.mean for c in comps]),
    np.sqrt([c.seed for c in comps]),
    np.stack(views, axis=1),
    (noise[0], noise[1]),
    (comps[0], comps[1]),
  )


def _view_draw(rng, groups) -> np.ndarray:
  return np.concatenate([g[rng.integers(0, len(g), len(g))] for g in groups])


def _matrices(model: Model, rng, idx: np.ndarray, n_seeds: int, seeds: bool = True):
  """(ours, base) (S, N) errors on the views `idx` (rows of model.views)."""
  out = []
  for k in range(2):
    a = rng.standard_normal(n_seeds) * model.seed_sd[k] if seeds else np.zeros(n_seeds)
    pool = model.noise[k]
    e = pool[rng.integers(0, len(pool), (n_seeds, len(idx)))]
    out.append(model.mean[k] + a[:, None] + model.views[idx, k][None] + e)
  return out


def _expected_ratio(model: Model, rng, idx, scenes, draws: int) -> float:
  """E[stat(ours)] / E[stat(base)] over the noise on views `idx` (the seed effects, mean 0,
  move both statistics' expectations by nothing): exact for the mean (the noise pools have
  mean 0), by `draws` noise draws for the median."""
  if model.reduce == "mean":
    o, b = (model.mean[k] + model.views[idx, k][None] for k in range(2))
    return stats.statistic(o, scenes) / stats.statistic(b, scenes)
  o, b = _matrices(model, rng, idx, draws, seeds=False)
  return stats.statistic(o, scenes, model.reduce) / stats.statistic(b, scenes, model.reduce)


def simulate(
  model: Model, n_seeds: int, sims: int, *, b: int, seed: int = 0, draws: int = 64
) -> dict[str, float]:
  """{method: coverage} of `METHODS` over `sims` simulated tables of `n_seeds` seeds."""
  rng = np.random.default_rng(seed)
  n = len(model.views)
  groups = stats._groups(model.scenes, n)
  scene_of = (lambda idx: None) if model.scenes is None else (lambda idx: model.scenes[idx])
  pop = np.concatenate([np.tile(g, max(1, 4000 // n)) for g in groups])
  population = _expected_ratio(model, rng, pop, scene_of(pop), 8)
  hits = {k: 0 for k, _ in METHODS}
  q = stats.t_quantile(0.975, n_seeds - 1)
  for i in range(sims):
    idx = _view_draw(rng, groups)
    scenes = scene_of(idx)
    ours, base = _matrices(model, rng, idx, n_seeds)
    test_set = _expected_ratio(model, rng, idx, scenes, draws)
    c = stats.seed_ratio(ours, base, scenes, model.reduce, population=False)
    reps = stats._resampled_stats([ours, base], scenes, model.reduce, b, 1000 + i)
    with np.errstate(divide="ignore", invalid="ignore"):
      logs = np.log(reps[:, 0] / reps[:, 1])
      value = stats.statistic(ours, scenes, model.reduce) / stats.statistic(
        base, scenes, model.reduce
      )
    lo_p, hi_p = np.exp(np.nanpercentile(logs, [2.5, 97.5]))
    se = np.nanstd(logs, ddof=1) * math.sqrt(n_seeds / (n_seeds - 1))
    with np.errstate(invalid="ignore"):
      lo_c, hi_c = value * math.exp(-q * se), value * math.exp(q * se)
    inside = lambda lo, hi, t: bool(lo <= t <= hi)
    sv = stats.seed_view_ratio(ours, base, scenes, model.reduce, b=b, seed=2000 + i)
    hits["seed_view"] += inside(sv.lo, sv.hi, population)
    hits["t_test_set"] += inside(c.ratio.lo, c.ratio.hi, test_set)
    hits["t_population"] += inside(c.ratio.lo, c.ratio.hi, population)
    hits["boot_corrected"] += inside(lo_c, hi_c, population)
    hits["boot_percentile"] += inside(lo_p, hi_p, population)
  return {k: v / sims for k, v in hits.items()}


def seed_share(c: stats.Components, n_seeds: int, n_views: int) -> float:
  """The share of the seeds in the variance of a cell's mean over S seeds and N shared views:
  (seed + noise / N) / S against view / N (a seed's mean error varies by seed + noise / N)."""
  per_seed = (c.seed + c.noise / n_views) / n_seeds
  total = per_seed + c.view / n_views
  return per_seed / total if total > 0 else 0.0

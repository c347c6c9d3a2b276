"""Coverage of the lead table's intervals, by simulation in the regimes of the archived records.

  python -m experiments.coverage --runs results/converge/regression \
      --md results/converge/coverage.md --png results/converge/coverage.png

Per lead-table row (`experiments/lead_table.py`: ours against the best hand-designed
representation chosen on validation), the two (S, N) test-error matrices are split into
errors = mean + seed effect + view effect + noise (`camrep.regression.stats.variance_components`,
one split per representation). The simulation draws new error matrices from that model:

  - seed effects: normal with the estimated seed variance, independent for ours and the baseline
    (their seeds are separate runs);
  - view effects: the records' own centred per-view means, drawn with replacement as (ours,
    baseline) pairs within each scene, so a view hard for one stays hard for the other and the
    skewed, heavy-tailed spread of real view errors is kept;
  - noise: the records' two-way residuals (rescaled to unbiased variance), drawn with
    replacement.

At each seed count S of --seeds (3 as in the records; 5 and 10 planned) it makes --sims tables
of S seeds, and counts how often each 95% interval of ours / baseline holds the true ratio:

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

Writes a Markdown table (per row: variance components as shares of their sum, and the coverages
at each S with their Monte Carlo standard error) and a figure (coverage against S, one panel per
method, one line per row, the 90-97% target band shaded), PNG and PDF twins. The bootstrap uses
--b replicates per simulated table (400: the intervals' ends move by about 1% from 2,000).
--sims 150 --b 100 takes about 10 minutes on one free core; `--sims 20 --seeds 3 --b 50`
seconds. Progress (each row's coverages) goes to stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
from collections.abc import Sequence

import numpy as np

from camrep.regression import stats
from camrep.regression import tables as C
from camrep.runtime import plots
from experiments import lead_table

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


def models(runs: str) -> list[Model]:
  """The `Model` of each lead-table row RUNS has (ours and controls against the best
  hand-designed representation, chosen on validation) with >= 2 common seeds."""
  out = []
  for column in lead_table.COLUMNS + lead_table.capture_columns(runs):
    results = C.load_results([os.path.join(runs, column.directory, "*", "*")])
    if not results:
      continue
    by_rep = {rep: sel for (_, rep), sel in C.select(results).items()}
    best = C.best_on_validation(by_rep, column.error, column.reduce)
    if best is None:
      continue
    for rep in [r for r in by_rep if r not in lead_table.NOT_CONTROLS or r == "ours"]:
      common = sorted(
        {r["seed"] for r in by_rep[rep].runs} & {r["seed"] for r in by_rep[best].runs}
      )
      if len(common) < 2:
        continue
      a = stats.seed_matrix(by_rep[rep].runs, column.error, common)
      z = stats.seed_matrix(by_rep[best].runs, column.error, common)
      if a is None or z is None:
        continue
      label = column.label if rep == "ours" else f"{column.label}: {rep}"
      scenes = a[1] if column.by_scene else None
      out.append(fit(f"{label} (vs {best})", a[0], z[0], scenes, column.reduce))
  return out


def seed_share(c: stats.Components, n_seeds: int, n_views: int) -> float:
  """The share of the seeds in the variance of a cell's mean over S seeds and N shared views:
  (seed + noise / N) / S against view / N (a seed's mean error varies by seed + noise / N)."""
  per_seed = (c.seed + c.noise / n_views) / n_seeds
  total = per_seed + c.view / n_views
  return per_seed / total if total > 0 else 0.0


def report(rows: Sequence[Model], seeds: Sequence[int], cover: dict, sims: int, b: int) -> str:
  """The Markdown table of the coverages."""
  se = lambda p: math.sqrt(max(p * (1 - p), 1e-9) / sims)
  header = [
    "row",
    "ours: seed / view / noise",
    "baseline: seed / view / noise",
    "seeds' share of a cell mean's variance (ours, baseline)",
    "seeds",
  ]
  header += [label for _, label in METHODS]
  lines = []
  for m in rows:
    shares = [" / ".join(f"{100 * x:.0f}%" for x in c.shares()) for c in m.components]
    for s in seeds:
      cov = cover[m.label, s]
      cell = ", ".join(f"{100 * seed_share(c, s, len(m.views)):.0f}%" for c in m.components)
      lines.append(
        [m.label, *shares, cell, str(s)]
        + [f"{100 * cov[k]:.0f}% ± {100 * se(cov[k]):.0f}" for k, _ in METHODS]
      )
  summary = []
  for s in seeds:
    for k, label in METHODS:
      vals = [cover[m.label, s][k] for m in rows]
      n_in = sum(TARGET[0] <= v <= TARGET[1] for v in vals)
      summary.append(
        f"- {s} seeds, {label}: {100 * min(vals):.0f}-{100 * max(vals):.0f}% "
        f"(median {100 * float(np.median(vals)):.0f}%), {n_in} of {len(vals)} rows within "
        f"{100 * TARGET[0]:.0f}-{100 * TARGET[1]:.0f}%"
      )
  note = (
    f"Coverage of nominal 95% intervals of ours / baseline in {sims} simulated tables per row "
    f"and seed count (± its Monte Carlo standard error), bootstrap {b} replicates; variance "
    "components (shares of seed + view + noise variance, method of moments) estimated per "
    "representation from the records (`experiments/coverage.py`)."
  )
  return "\n".join([note, "", *summary, "", C.markdown_table(header, lines)])


def figure(rows: Sequence[Model], seeds: Sequence[int], cover: dict):
  """Coverage against seeds, one panel per method, one line per row; the target band."""
  x = np.asarray(seeds, np.float64)
  panels = [
    plots.Panel(
      label,
      "coverage of the 95% interval",
      {m.label: np.array([cover[m.label, s][k] for s in seeds]) for m in rows},
      xlabel="seeds",
    )
    for k, label in METHODS
  ]
  fig = plots.curves_figure(x, panels, suptitle="Coverage in the records' variance regimes")
  for ax in fig.axes:
    if ax.get_title():
      ax.axhspan(*TARGET, color="0.85", zorder=0)
      ax.axhline(0.95, color="0.4", lw=0.8, ls="--")
      ax.set_ylim(0.4, 1.0)
  return fig


def main(argv: Sequence[str] | None = None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--runs", required=True, help="RUNS: <column>/<representation>/<run> dirs")
  p.add_argument("--seeds", default="3,5,10", help="seed counts to simulate")
  p.add_argument("--sims", type=int, default=300, help="simulated tables per row and seed count")
  p.add_argument("--b", type=int, default=400, help="bootstrap replicates per simulated table")
  p.add_argument("--md", default="", help="Markdown file to write")
  p.add_argument("--png", default="", help="figure to write (and its .pdf twin)")
  args = p.parse_args(argv)
  try:
    seeds = [int(s) for s in args.seeds.split(",")]
  except ValueError:
    print(
      f"error: --seeds must be integers separated by commas, got {args.seeds!r}", file=sys.stderr
    )
    return 2
  if min(seeds) < 2 or args.sims < 1 or args.b < 2:
    print("error: --seeds >= 2, --sims >= 1 and --b >= 2 are needed", file=sys.stderr)
    return 2
  try:
    rows = models(args.runs)
  except C.TableError as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  if not rows:
    print(f"error: no lead-table row with >= 2 seeds under {args.runs}", file=sys.stderr)
    return 2
  cover = {}
  for j, m in enumerate(rows):
    for s in seeds:
      cover[m.label, s] = simulate(m, s, args.sims, b=args.b, seed=j)
      print(f"{m.label}, {s} seeds: {cover[m.label, s]}", file=sys.stderr, flush=True)
  text = report(rows, seeds, cover, args.sims, args.b)
  print(text)
  if args.md:
    with open(args.md, "w", encoding="utf-8") as f:
      f.write(text + "\n")
  if args.png:
    plots.save(figure(rows, seeds, cover), os.path.splitext(args.png)[0])
  return 0


if __name__ == "__main__":
  sys.exit(main())

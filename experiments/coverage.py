"""Coverage of the lead table's intervals, by simulation in the regimes of the archived records.

  python -m experiments.coverage --runs results/converge/regression \
      --md results/converge/coverage.md --png results/converge/coverage.png

Per lead-table row (`experiments/lead_table.py`: ours against the best hand-designed
representation chosen on validation), the two (S, N) test-error matrices are fitted and simulated
by `camrep.regression.coverage` (the model and the interval methods are described there). At each
seed count S of --seeds (3 as in the records; 5 and 10 planned) it makes --sims tables of S seeds.

Writes a Markdown table (per row: variance components as shares of their sum, and the coverages
at each S with their Monte Carlo standard error) and a figure (coverage against S, one panel per
method, one line per row, the 90-97% target band shaded), PNG and PDF twins. The bootstrap uses
--b replicates per simulated table (400: the intervals' ends move by about 1% from 2,000).
--sims 150 --b 100 takes about 10 minutes on one free core; `--sims 20 --seeds 3 --b 50`
seconds. Progress (each row's coverages) goes to stderr.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Sequence

import numpy as np

from camrep.regression import lead, stats
from camrep.regression import tables as C
from camrep.regression.coverage import METHODS, TARGET, Model, fit, seed_share, simulate
from camrep.runtime import plots


def models(runs: str) -> list[Model]:
  """The `Model` of each lead-table row RUNS has (ours and controls against the best
  hand-designed representation, chosen on validation) with >= 2 common seeds."""
  out = []
  for column in lead.COLUMNS + lead.capture_columns(runs):
    results = C.load_results([os.path.join(runs, column.directory, "*", "*")])
    if not results:
      continue
    by_rep = {rep: sel for (_, rep), sel in C.select(results).items()}
    best = C.best_on_validation(by_rep, column.error, column.reduce)
    if best is None:
      continue
    for rep in [r for r in by_rep if r not in lead.NOT_CONTROLS or r == "ours"]:
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

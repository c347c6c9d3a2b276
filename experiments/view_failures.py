"""Where a column's mean error comes from: typical views against gross failures.

  python experiments/view_failures.py --runs results/converge/regression \
      --columns car_chair,car_ethiopianHead,car_moldGoldCape --out results/converge/view_failures.md

Reads the regression runs under RUNS/<column>/<representation>/<lr>_seed<k>/ (as
`python -m camrep.comparison` lays them out), takes each representation at the learning rate
chosen on the validation split (`camrep.regression.tables.select`, as the tables do) and prints,
per column, one row per representation:

  - the mean test error over seeds and views (the tables' cell);
  - the mean over seeds of each seed's median over views;
  - how many test views each seed's run gets more than THRESHOLD wrong (a gross failure: on an
    object seen from all sides, typically a pose taken for its mirror image);

and the test views that every run of every representation fails. With few test views (the LLFF
captures hold out 9 and 15), one or two such views move every mean by several units, which is
why the lead table gives the captures a median row too. Runs in a few seconds.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

import numpy as np

from camrep.regression import stats
from camrep.regression import tables as C


def column_report(runs: str, column: str, error: str, threshold: float) -> str:
  """The Markdown section of one column (RUNS/<column>).

  Raises:
    FileNotFoundError: no runs of `column`, or none with per-view errors.
  """
  results = C.load_results([os.path.join(runs, column, "*", "*")])
  if not results:
    raise FileNotFoundError(f"no regression runs with results.json under {runs}/{column}")
  mats = {}
  for (_, rep), sel in sorted(C.select(results).items()):
    m = stats.seed_matrix(sel.runs, error)
    if m is not None:
      mats[rep] = (sel, m[0])
  if not mats:
    raise FileNotFoundError(f"no per-view errors (errors_test.npz) under {runs}/{column}")
  n_views = {e.shape[1] for _, e in mats.values()}
  if len(n_views) != 1:
    raise ValueError(f"{column}: representations were tested on different views: {n_views}")
  rows = []
  for rep, (sel, e) in mats.items():
    rows.append(
      [
        C.row_label(rep, [sel.setting]),
        C.fmt_lr(sel.lr),
        f"{e.mean():.3g}",
        f"{np.median(e, axis=1).mean():.3g}",
        ", ".join(str(int(k)) for k in (e > threshold).sum(axis=1)),
      ]
    )
  everyone = np.all(np.stack([(e > threshold).all(axis=0) for _, e in mats.values()]), axis=0)
  header = (
    "representation",
    "lr",
    "mean",
    "median (mean over seeds)",
    f"views > {threshold:g} per run",
  )
  failed = np.flatnonzero(everyone).tolist()
  return "\n".join(
    [
      f"## {column}: {error}, {n_views.pop()} test views",
      "",
      C.markdown_table(header, rows),
      "",
      f"Test views that every run of every representation gets more than {threshold:g} wrong: "
      + (", ".join(map(str, failed)) if failed else "none"),
    ]
  )


def main(argv: Sequence[str] | None = None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--runs", required=True, help="RUNS: <column>/<representation>/<run> dirs")
  p.add_argument("--columns", required=True, help="comma-separated columns (directories of RUNS)")
  p.add_argument("--error", default="rotation_error_deg", help="the per-view error to read")
  p.add_argument("--threshold", type=float, default=45.0, help="a gross failure: error above this")
  p.add_argument("--out", default="", help="Markdown file to write (default: print only)")
  args = p.parse_args(argv)
  try:
    sections = [
      column_report(args.runs, c, args.error, args.threshold) for c in args.columns.split(",") if c
    ]
  except (FileNotFoundError, ValueError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  text = "# Typical views and gross failures per representation\n\n" + "\n\n".join(sections)
  print(text)
  if args.out:
    with open(args.out, "w", encoding="utf-8") as f:
      f.write(text + "\n")
    print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

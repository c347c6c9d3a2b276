"""Table 1 of the paper: pose regression with each representation on three settings (mean errors).

Columns come from procedural families or from prepared real datasets (SRN cars, GQN, Gibson), as
the runs' results.json record it; the data of each column is stated under the table. Reads the
results of `camrep.regression` runs (results.json and errors_<split>.npz, or their compact
records run.json; nothing else), groups them by (setting, representation), picks each group's
learning rate on the validation errors (`camrep.regression.tables`: mean of error /
paper-ours-error over the setting's columns, averaged over the seeds every lr has), and writes a
Markdown file with

  1. the measured table in the paper's layout: car mean rotation error (deg); rooms (GQN) mean
     |x|, |y| errors (scene units) and yaw error (deg); area (Gibson) mean |x|, |y| (m) and yaw
     (deg); each cell, when every run of it saved its per-view errors (errors_test.npz), the
     mean over seeds and test views with its 95% bootstrap interval, "mean [lo, hi]"
     (`camrep.regression.stats`: seeds and views resampled), else the mean ± sample std over
     seeds of the test means, at the chosen lr; a last row per column: ours / the best
     hand-designed representation of the column (lowest mean validation error), the geometric
     mean of the per-seed ratios on the same test views with its seed-level t interval and a
     verdict (better: the interval is below 1; tie: it contains 1; worse: above 1; not adjusted
     for multiple comparisons: experiments/lead_table.py is);
  2. the paper's Table 1 (real data, paper-size training) in the same layout, for reference;
  3. the learning-rate selection (grid, scores, chosen lr, seeds, steps, parameter counts).

  python experiments/table1.py --runs 'DIR/regression/*/*/*' --out results/table1.md

Runs in a second; prints the Markdown too.
"""

from __future__ import annotations

import argparse
import glob
import os
import sys
from collections.abc import Sequence

from camrep.regression import runs, stats
from camrep.regression import tables as C

SETTINGS = ("car", "gqn", "gibson")
PROCEDURAL_COLUMNS = {
  "car": "car = `object` family (held-out views of the training cars)",
  "gqn": "rooms = `rooms` family like GQN (held-out rooms; scene units, room [-1, 1]^2)",
  "gibson": "area = `area` family like Gibson (held-out views; metres)",
}
"""What each setting's column holds when its runs read camrep's procedural family."""


def procedural_note(selections) -> str:
  """The sentence describing the columns filled from procedural families ("" when none is)."""
  procedural = [
    s
    for s in SETTINGS
    if any(not C.is_real(r) for (st, _), sel in selections.items() if st == s for r in sel.runs)
  ]
  if not procedural:
    return ""
  return " Procedural columns: " + ", ".join(PROCEDURAL_COLUMNS[s] for s in procedural) + "."


def comparison_cells(selections, columns) -> list[str]:
  """Per Table 1 column: ours against the column's best hand-designed representation (lowest
  mean validation error at its chosen lr: `tables.best_on_validation`), the seed-level t interval
  of the per-seed ratios on the same test views (`stats.seed_compare_runs`)."""
  cells = []
  for _, _, setting, error in columns:
    ours = selections.get((setting, "ours"))
    best = C.best_on_validation(
      {rep: sel for (s, rep), sel in selections.items() if s == setting}, error
    )
    if ours is None or best is None:
      cells.append("–")
      continue
    comp = stats.seed_compare_runs(
      ours.runs, selections[setting, best].runs, error, baseline=best, population=False
    )
    cells.append(stats.fmt_seed_comparison(comp))
  return cells


def build(results: Sequence[dict]) -> str:
  """The Markdown document of Table 1 from results.json contents."""
  selections = {k: v for k, v in C.select(results).items() if k[0] in SETTINGS}
  # Only the columns with runs, each row labelled in those columns' pose terms.
  shown = {k[0] for k in selections}
  columns = [c for c in C.TABLE1_COLUMNS if c[2] in shown] or list(C.TABLE1_COLUMNS)
  settings = sorted({c[2] for c in columns})
  header = ["representation"] + [h for _, h, _, _ in columns]
  rows, paper_rows = [], []
  reps = [r for r in C.TABLE1_ROWS if any(k[1] == r for k in selections)]
  reps += sorted({k[1] for k in selections} - set(reps))
  intervals = 0
  for rep in reps:
    row = [C.row_label(rep, settings)]
    for _, _, setting, error in columns:
      sel = selections.get((setting, rep))
      iv = stats.cell_interval(sel.runs, error) if sel else None
      if iv is not None:
        intervals += 1
        row.append(stats.fmt_interval(iv, digits=C.digits_for(iv.value)))
      else:
        row.append(C.fmt_mean_std(*C.seed_stats(sel.runs, error)[:2]) if sel else "–")
    rows.append(row)
  if intervals:
    rows.append(["ours / best hand-designed", *comparison_cells(selections, columns)])
  for rep in C.TABLE1_ROWS:
    if rep not in C.PAPER_TABLE1:  # rot6d, svd9d: newer than the paper
      continue
    paper = C.PAPER_TABLE1[rep]
    cells = [f"{paper[k]:g}" if k in paper else "–" for k, _, _, _ in columns]
    paper_rows.append([C.row_label(rep, settings), *cells])
  seeds = sorted({len(s.runs) for s in selections.values()})
  runs = [r for s in selections.values() for r in s.runs]
  real = [C.is_real(r) for r in runs]
  kind = "real data" if real and all(real) else "mixed data" if any(real) else "procedural data"
  title = "camrep's procedural families" if kind == "procedural data" else kind
  notes = C.data_notes(selections, [("car", "car"), ("gqn", "rooms"), ("gibson", "area")])
  text = [
    f"# Table 1: pose regression on {title}",
    "",
    f"Measured on {kind} ({C.width_text(runs)}; "
    f"{len(results)} runs read): mean test errors over "
    f"{'/'.join(map(str, seeds)) or '0'} seeds at the learning rate chosen on the validation "
    "split; "
    + (
      "each cell the mean over seeds and test views [95% bootstrap interval: seeds and test "
      f"views resampled, {stats.B} replicates] (cells without per-view errors: mean ± sample "
      "std over seeds); last row: ours / the column's best hand-designed representation "
      "(lowest mean validation error), the geometric mean of the per-seed ratios of mean "
      "errors on the same test views [95% seed-level t interval] and the verdict (better / tie "
      "/ worse: interval below / containing / above 1; unadjusted)."
      if intervals
      else "each cell the mean ± sample std over seeds."
    )
    + procedural_note(selections),
    "",
    C.markdown_table(header, rows),
    "",
    "Data of each column:",
    "",
    *notes,
    "",
    "## Paper's Table 1 (for reference: real ShapeNet cars, GQN rooms and Gibson, paper-size "
    "training; not the data above)",
    "",
    C.markdown_table(header, paper_rows),
    "",
    "MLP embedding: the supplement's car result. Baselines in the paper have one extra dense "
    "layer to equalise parameter counts (here too: `hparams.<setting>.baselines` in "
    "configs/regression.py).",
    "",
    "## Learning-rate selection",
    "",
    "Score = mean over the setting's columns of (validation error / the paper's error of "
    "ours), lower is better, averaged over the listed seeds.",
    "",
    C.selection_table(selections, lambda rep: C.row_label(rep, settings)),
    "",
  ]
  return "\n".join(text)


def unfinished(patterns: Sequence[str]) -> list[str]:
  """The run directories the patterns match that hold no finished run (no results.json, which
  the regression driver writes atomically, last, and no record run.json)."""
  dirs = {p for pattern in patterns for p in glob.glob(pattern) if os.path.isdir(p)}
  return sorted(d for d in dirs if not runs.is_finished(d))


def main(argv: Sequence[str] | None = None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--runs", nargs="+", required=True, help="glob(s) of run dirs / results.json")
  p.add_argument("--out", required=True, help="Markdown file to write")
  p.add_argument(
    "--skip_damaged",
    action="store_true",
    help="skip runs whose files cannot be read (named on stderr) instead of refusing",
  )
  args = p.parse_args(argv)
  try:
    results = C.load_results(args.runs, skip_damaged=args.skip_damaged)
    for run in unfinished(args.runs):
      print(f"skipped {run}: no {C.RESULTS_FILE} (unfinished run)", file=sys.stderr)
    if not results:
      print(f"error: no results.json matches {args.runs}", file=sys.stderr)
      return 2
    text = build(results)
  except C.TableError as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
  with open(args.out, "w", encoding="utf-8") as f:
    f.write(text)
  print(text)
  print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

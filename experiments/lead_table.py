"""The comparison in one table: per column, the paper's numbers, camrep's best hand-designed
representation and ours with 95% intervals, their paired ratio and a verdict.

  python experiments/lead_table.py --runs results/converge/regression --out results/lead_table.md

Reads the regression runs under RUNS (RUNS/<column>/<representation>/<lr>_seed<k>/, as
`python -m camrep.comparison` lays them out: columns car, gqn (rooms), gibson (area),
seven_scenes and the capture columns car_<NAME>); per column, each representation's learning
rate is chosen on the validation split (`camrep.regression.tables.select`). One row per table
column of the paper (car rotation; rooms and area x, y, yaw; 7-Scenes median position and
rotation) and per capture column (two rows: its mean and its median over test views):

  - paper: the paper's "ours" and its best hand-designed representation in that column (Table 1;
    Table 2's PoseNet + log q [MapNet] for 7-Scenes), real data at paper size, for reference;
  - camrep, best hand-designed: the hand-designed representation with the lowest validation
    statistic at its chosen lr (`camrep.regression.tables.best_on_validation`: no test error is
    read by any choice), with its interval;
  - camrep, ours: with its interval (t over the per-seed statistics);
  - ours / best: the geometric mean of the per-seed ratios on the same test views with its
    seed-level 95% t interval (`camrep.regression.stats.seed_ratio`), and beside it the same
    interval widened by the test views' sampling (`stats.seed_view_ratio`);
  - p, Holm-adjusted over every comparison of the table (m of them, in the header), and the
    verdict: better / worse where it is below 0.05, else tie;
  - seeds, the seeds each chosen lr's validation score averaged ("all", or e.g. "seed 0" where
    the grid's other lrs ran seed 0 only), whether either chosen learning rate sits at its
    grid's edge, and how many of the runs reached their step cap instead of being stopped by
    the plateau rule (results.json "stopping"; runs without a rule count as stopped).

Controls (representations other than the hand-designed ones, ours and the MLP: an untrained pose
system, frozen generators) get a row each against the same best hand-designed representation.
Statistics per-scene medians averaged over scenes for 7-Scenes. A column whose runs lack
per-view errors (errors_<split>.npz) or its ours or baselines is listed with "–". Runs in
seconds; a note under the table states the method.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from camrep.regression import stats
from camrep.regression import tables as C
from camrep.regression.lead import compared

HEADER = (
  "column",
  "paper: ours vs best hand-designed",
  "camrep: best hand-designed (chosen on validation)",
  "camrep: ours",
  "ours / best, seed-level t [95%]",
  "ours / best, seeds (t) + views (bootstrap) [95%]",
  "p (Holm-adjusted, m = {m})",
  "verdict (Holm, family-wise 5%)",
  "seeds",
  "lr chosen on validation of",
  "chosen lr at grid edge",
  "runs at their step cap",
)

NOTE = (
  "Cells: mean over seeds [95% t interval over the per-seed statistics, S - 1 df]; the ratio: "
  "geometric mean of the per-seed ratios ours / best on the same test views [95% seed-level t "
  "interval of the log ratio: this test set's value]; beside it the same interval widened by "
  "the test views' sampling (its variance from resampling the views, every seed kept; "
  "Welch-Satterthwaite df: the population of views). Verdict: better / worse where the "
  "Holm-adjusted p of the seed-level t test (mean log ratio 0) is below 0.05 over the m = {m} "
  "comparisons of this table, else tie. Best hand-designed: the lowest validation statistic at "
  "its chosen lr (no test error is read to choose it or any lr)."
)


def build(runs: str, *, skip_damaged: bool = False) -> str:
  """The Markdown table of every column RUNS holds runs of, with its note.

  Raises:
    FileNotFoundError: RUNS holds no regression runs.
    camrep.regression.tables.TableError: a damaged run (without skip_damaged), or two runs of
      one cell.
  """
  found, adjusted = compared(runs, skip_damaged=skip_damaged)
  m = int(sum(1 for x in adjusted if x == x))
  table = []
  for r, adj in zip(found, adjusted, strict=True):
    c = r.comparison
    table.append(
      [
        r.label,
        r.paper,
        r.best_cell,
        r.cell,
        stats.fmt_interval(c.ratio, digits=2) if c else "–",
        stats.fmt_interval(c.population, digits=2) if c and c.population else "–",
        f"{adj:.3f}" if adj == adj else "–",
        f"**{c.verdict(adj)}**" if c else "–",
        r.seeds,
        r.lr_seeds,
        r.edges,
        r.capped,
      ]
    )
  header = [h.format(m=m) for h in HEADER]
  return C.markdown_table(header, table) + "\n\n" + NOTE.format(m=m)


def main(argv: Sequence[str] | None = None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--runs", required=True, help="RUNS: <column>/<representation>/<run> dirs")
  p.add_argument("--out", default="", help="Markdown file to write (default: print only)")
  p.add_argument(
    "--skip_damaged",
    action="store_true",
    help="skip runs whose files cannot be read (named on stderr) instead of refusing",
  )
  args = p.parse_args(argv)
  try:
    text = build(args.runs, skip_damaged=args.skip_damaged)
  except (FileNotFoundError, C.TableError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  print(text)
  if args.out:
    with open(args.out, "w", encoding="utf-8") as f:
      f.write(text + "\n")
    print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

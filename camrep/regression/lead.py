"""The lead comparison: per column of the paper's tables (and per capture column), ours and each
control against the best hand-designed representation chosen on validation, with the seed-level
comparison (`stats.seed_compare_runs`) and the Holm adjustment over every compared pair.

Regression runs are read under RUNS/<column>/<representation>/<lr>_seed<k>/, as
`python -m camrep.comparison` lays them out (columns car, gqn, gibson, seven_scenes and the
capture columns car_<NAME>); per column each representation's learning rate is chosen on the
validation split (`tables.select`), the baseline is the hand-designed representation with the
lowest validation statistic at its chosen lr (`tables.best_on_validation`): no test error is read
by any choice. Statistics are per-scene medians averaged over scenes for 7-Scenes. The readers:
experiments/lead_table.py (the table), claims_table.py and coverage.py.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence

import numpy as np

from camrep.regression import stats
from camrep.regression import tables as C


@dataclasses.dataclass(frozen=True)
class Column:
  """One row of the lead table: a table column of the paper (or a capture column)."""

  label: str
  directory: str  # RUNS/<directory>/<representation>/<run>
  error: str
  reduce: str = "mean"
  by_scene: bool = False
  paper_ours: float | None = None
  paper_best: tuple[str, float] | None = None  # (label, value)
  unit: str = ""


def _paper_best(key: str) -> tuple[str, float]:
  vals = {r: v[key] for r, v in C.PAPER_TABLE1.items() if r in stats.HAND_DESIGNED and key in v}
  rep = min(vals, key=vals.get)
  return rep, vals[rep]


# The paper's Table 2 baseline: PoseNet + log q (MapNet's numbers), median over each scene,
# averaged over the 7 scenes.
PAPER_LOGQ_7SCENES = (0.22, 8.07)

COLUMNS = tuple(
  Column(
    header,
    setting,
    error,
    paper_ours=C.PAPER_TABLE1["ours"][key],
    paper_best=_paper_best(key),
  )
  for key, header, setting, error in C.TABLE1_COLUMNS
) + tuple(
  Column(
    f"7-Scenes {what}, median)",
    "seven_scenes",
    error,
    "median",
    True,
    C.PAPER_TABLE2["average"][i],
    ("PoseNet + log q", PAPER_LOGQ_7SCENES[i]),
  )
  for i, (what, error) in enumerate(
    (("position (m", "position_error"), ("rotation (deg", "rotation_error_deg"))
  )
)


def capture_columns(runs: str) -> tuple[Column, ...]:
  """The capture columns (car setting on one capture) that RUNS holds: the mean over test views
  (the car column's statistic), then the median over each seed's test views. A capture has 9-50
  test views, and on the LLFF captures one or two views with errors of 50-180 degrees (a pose
  mistaken for its mirror) move every representation's mean by several degrees; the median row
  shows the typical view. lrs are chosen on the validation mean either way."""
  names = sorted(d for d in os.listdir(runs) if d.startswith("car_")) if os.path.isdir(runs) else []
  return tuple(
    Column(f"{n[4:]} rotation (deg{what}; capture)", n, "rotation_error_deg", reduce)
    for n in names
    for what, reduce in (("", "mean"), (", median", "median"))
  )


# Representations that are neither a target under comparison nor ours: controls of the same
# protocol (an untrained pose system, ours' grid with frozen generators), each compared with the
# column's best hand-designed representation in a row of its own. Unknown names show as given.
CONTROL_LABELS = {
  "untrained": "untrained pose system",
  "frozen_gen": "frozen generators",
}
NOT_CONTROLS = frozenset((*stats.HAND_DESIGNED, "ours", "mlp"))


@dataclasses.dataclass
class Row:
  """One compared pair of a column before the table's Holm adjustment."""

  column: Column
  representation: str  # ours or a control, against the best hand-designed
  data: str  # the data kind of ours' runs (`data_kind`)
  label: str
  paper: str
  best_cell: str
  cell: str
  comparison: stats.SeedComparison | None
  seeds: str
  lr_seeds: str
  edges: str
  capped: str
  candidates: int  # how many hand-designed representations the best was chosen from


def rows(
  runs: str,
  column: Column,
  *,
  skip_damaged: bool = False,
  results: Sequence[dict] | None = None,
) -> list[Row]:
  """The rows of `column` (ours, then each control, against the best hand-designed
  representation chosen on validation), [] when RUNS holds none of its runs.

  Args:
    runs: RUNS.
    column: the row's column.
    skip_damaged: see `camrep.regression.tables.load_results`.
    results: the column's runs, already read (default: read from RUNS/<column.directory>).
  """
  if results is None:
    pattern = os.path.join(runs, column.directory, "*", "*")
    results = C.load_results([pattern], skip_damaged=skip_damaged)
  if not results:
    return []
  by_rep = {rep: sel for (_, rep), sel in C.select(results).items()}
  best = C.best_on_validation(by_rep, column.error, column.reduce)
  fmt = lambda iv: stats.fmt_interval(iv, digits=C.digits_for(iv.value)) if iv else "–"

  def cell(rep):
    if rep not in by_rep:
      return None
    return stats.cell_interval(
      by_rep[rep].runs, column.error, column.reduce, by_scene=column.by_scene, method="seed_t"
    )

  paper = "–"
  if column.paper_ours is not None and column.paper_best is not None:
    name, value = column.paper_best
    paper = f"{column.paper_ours:g} vs {value:g} ({C.ROW_LABELS.get(name, name)})"
  best_cell = f"{fmt(cell(best))} ({best})" if best else "–"
  controls = sorted(r for r in by_rep if r not in NOT_CONTROLS)
  out = []
  for rep in [r for r in ("ours", *controls) if r in by_rep]:
    comp = None
    if best is not None:
      comp = stats.seed_compare_runs(
        by_rep[rep].runs,
        by_rep[best].runs,
        column.error,
        column.reduce,
        baseline=best,
        by_scene=column.by_scene,
      )
    shown = [r for r in (rep, best) if r in by_rep]
    edges, capped, lr_seeds = [], [], []
    for r in shown:
      sel = by_rep[r]
      if C.grid_edge(sel):
        edges.append(f"{r}: {C.grid_edge(sel)} ({C.fmt_lr(sel.lr)})")
      n = sum(1 for run in sel.runs if not (run.get("stopping") or {}).get("stopped_early", True))
      capped.append(f"{r} {n}/{len(sel.runs)}")
      scored = "all" if sel.on_all_seeds else "seed " + ",".join(map(str, sel.scored_seeds))
      lr_seeds.append(f"{r}: {scored}")
    label = column.label if rep == "ours" else f"{column.label}: {CONTROL_LABELS.get(rep, rep)}"
    out.append(
      Row(
        column,
        rep,
        data_kind(by_rep[rep].runs[0]),
        label,
        paper if rep == "ours" else "–",
        best_cell,
        fmt(cell(rep)),
        comp,
        "/".join(map(str, sorted({len(by_rep[r].runs) for r in shown}))),
        "; ".join(lr_seeds),
        "; ".join(edges) or "no",
        ", ".join(capped) or "–",
        sum(1 for r in by_rep if r in stats.HAND_DESIGNED),
      )
    )
  return out


def data_kind(run: dict) -> str:
  """What a run's data is, in the claims' terms: a procedural family, a render (NeRF-synthetic
  Blender scenes) or a real capture (LLFF photographs, or another prepared real source)."""
  d = run.get("data", {})
  source = d.get("source")
  if source == "nerf":
    return "render (NeRF-synthetic)"
  if source == "llff":
    return "real capture (LLFF)"
  if source:
    return f"real data ({source})"
  return f"procedural family ({d.get('family', '?')})"


def compared(runs: str, *, skip_damaged: bool = False) -> tuple[list[Row], np.ndarray]:
  """Every row RUNS holds runs of, and the Holm-adjusted p values over all of them.

  Raises:
    FileNotFoundError: RUNS holds no regression runs.
    camrep.regression.tables.TableError: a damaged run (without skip_damaged), or two runs of
      one cell.
  """
  columns = COLUMNS + capture_columns(runs)
  # Every run is read once, so that each damaged one is named (or skipped with one warning)
  # together with the others, whichever column it belongs to.
  directories = sorted({c.directory for c in columns})
  patterns = [os.path.join(runs, d, "*", "*") for d in directories]
  by_directory = {d: [] for d in directories}
  for r in C.load_results(patterns, skip_damaged=skip_damaged):
    by_directory[os.path.relpath(r["_path"], runs).split(os.sep)[0]].append(r)
  found = [r for c in columns for r in rows(runs, c, results=by_directory[c.directory])]
  if not found:
    raise FileNotFoundError(f"no regression runs with results.json under {runs}")
  p = [r.comparison.p if r.comparison else float("nan") for r in found]
  return found, stats.holm(p)

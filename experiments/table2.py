"""Table 2 of the paper: 6-DOF pose regression per 7-Scenes scene (median errors).

Reads the results.json files of `camrep.regression` runs of the seven_scenes setting (the
`scene6dof` family: the real 7-Scenes camera trajectories inside procedural rooms, or a 7-Scenes
directory prepared by `camrep.data.prepare`; the data is stated under the table), picks each
representation's learning rate on the validation errors (`camrep.regression.tables`), and writes a
Markdown table: per scene the median position error (m) and median rotation error (deg) of the
test trajectory, ours vs quaternion vs log quaternion, each the mean over seeds at the chosen lr
with a 95% bootstrap interval (seeds and the scene's test views resampled; mean ± sample std over
seeds for runs without per-view errors); "average" is the mean over scenes of the per-scene
medians (as the paper). The
paper's real-data medians of ours are given alongside, labelled as such.

  python experiments/table2.py --runs 'DIR/regression/seven_scenes/*/*' --out results/table2.md

Runs in a second; prints the Markdown too.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Sequence

import numpy as np

from camrep.regression import stats
from camrep.regression import tables as C

ERRORS = ("position_error", "rotation_error_deg")


def _scene_medians(run: dict, scene: str) -> tuple[float, float]:
  t = run["test"].get(scene)
  if t is None:
    return math.nan, math.nan
  return t["position_error"]["median"], t["rotation_error_deg"]["median"]


def _cell(values: list[tuple[float, float]]) -> str:
  pos = np.array([v[0] for v in values])
  rot = np.array([v[1] for v in values])
  if len(pos) == 0 or not np.all(np.isfinite(pos)):
    return "–"
  sd = (lambda x: float(np.std(x, ddof=1))) if len(pos) > 1 else (lambda x: math.nan)
  p = C.fmt_mean_std(float(pos.mean()), sd(pos), digits=2)
  r = C.fmt_mean_std(float(rot.mean()), sd(rot), digits=1)
  return f"{p} m, {r}°"


def _scene_interval_cell(runs: Sequence[dict], sid: str) -> str | None:
  """A scene's cell with 95% intervals: each seed's median over the scene's test views, averaged
  over seeds [bootstrap: seeds and the scene's views resampled]; None without per-view errors
  (errors_test.npz) or without that scene's views."""
  cells = []
  for error, digits in zip(ERRORS, (2, 1), strict=True):
    m = stats.seed_matrix(runs, error)
    if m is None:
      return None
    errors, scenes, _ = m
    views = np.asarray(scenes).astype(str) == str(sid)
    if not views.any():
      return None
    cells.append(
      stats.fmt_interval(stats.interval(errors[:, views], None, "median"), digits=digits)
    )
  return f"{cells[0]} m, {cells[1]}°"


def comparison_cells(selections, reps) -> list[str]:
  """Under ours' column: ours against the best hand-designed representation (lowest mean
  validation median: `tables.best_on_validation`) for position and rotation, the seed-level t
  interval of the per-seed ratios of the averages of per-scene medians on the same test views
  (`stats.seed_compare_runs`); the other columns empty."""
  ours = selections.get(("seven_scenes", "ours"))
  column = {rep: sel for (s, rep), sel in selections.items() if s == "seven_scenes"}
  parts = []
  for i, error in enumerate(ERRORS):
    best = C.best_on_validation(column, error, "median")
    comp = None
    if ours is not None and best is not None:
      comp = stats.seed_compare_runs(
        ours.runs,
        selections["seven_scenes", best].runs,
        error,
        "median",
        baseline=best,
        by_scene=True,
        population=False,
      )
    parts.append(f"{'position' if i == 0 else 'rotation'} {stats.fmt_seed_comparison(comp)}")
  return ["; ".join(parts) if rep == "ours" else "" for rep in reps]


def build(results: Sequence[dict]) -> str:
  """The Markdown document of Table 2 from results.json contents."""
  selections = {k: v for k, v in C.select(results).items() if k[0] == "seven_scenes"}
  reps = [r for r in C.TABLE2_ROWS if ("seven_scenes", r) in selections]
  reps += sorted({k[1] for k in selections} - set(reps))
  names: dict[str, str] = {}
  for sel in selections.values():
    for run in sel.runs:
      names.update(run.get("data", {}).get("scene_names", {}))
  scene_ids = sorted(names, key=int)
  header = ["scene"] + [C.ROW_LABELS.get(r, r) for r in reps] + ["paper, ours (real 7-Scenes)"]
  rows = []
  for sid in scene_ids:
    name = names[sid]
    row = [name]
    for rep in reps:
      runs = selections["seven_scenes", rep].runs
      cell = _scene_interval_cell(runs, sid)
      row.append(cell or _cell([_scene_medians(run, sid) for run in runs]))
    ref = C.PAPER_TABLE2.get(name)
    row.append(f"{ref[0]:.2f} m, {ref[1]:.2f}°" if ref else "–")
    rows.append(row)
  avg = ["average"]
  intervals = 0
  for rep in reps:
    runs = selections["seven_scenes", rep].runs
    ivs = [stats.cell_interval(runs, e, "median", by_scene=True) for e in ERRORS]
    if all(ivs):
      intervals += 1
      avg.append(
        f"{stats.fmt_interval(ivs[0], digits=2)} m, {stats.fmt_interval(ivs[1], digits=1)}°"
      )
      continue
    per_run = []
    for run in runs:
      meds = np.array([_scene_medians(run, sid) for sid in scene_ids])
      per_run.append(tuple(np.mean(meds, axis=0)) if len(meds) else (math.nan, math.nan))
    avg.append(_cell(per_run))
  ref = C.PAPER_TABLE2["average"]
  avg.append(f"{ref[0]:.2f} m, {ref[1]:.2f}° (7 scenes)")
  rows.append(avg)
  if intervals:
    rows.append(["ours / best hand-designed", *comparison_cells(selections, reps), ""])
  runs = [r for s in selections.values() for r in s.runs]
  real = bool(runs) and all(C.is_real(r) for r in runs)
  if real:
    title = "# Table 2: 6-DOF regression on 7-Scenes (prepared real images)"
    what = (
      f"Measured on a prepared 7-Scenes dataset ({C.width_text(runs)}): the real "
      "7-Scenes images and poses; train = the TrainSplit sequences, test = the TestSplit "
      "sequences."
    )
  else:
    title = "# Table 2: 6-DOF regression on the scene6dof family (7-Scenes trajectories)"
    what = (
      f"Measured on camrep's `scene6dof` family ({C.width_text(runs)}): the real "
      "7-Scenes camera trajectories rendered inside procedural furnished rooms; test = the "
      "7-Scenes test trajectories."
    )
  weights = sorted({str(r.get("resnet_weights") or "none (from scratch)") for r in runs})
  text = [
    title,
    "",
    what + " Per scene: median position error (m), median rotation error "
    "(deg), the mean over seeds at the learning rate chosen on the validation split "
    "(the end of each training trajectory)"
    + (
      f" [95% bootstrap interval: seeds and the scene's test views resampled, {stats.B} "
      "replicates; ± sample std over seeds where a run has no per-view errors]. "
      if intervals
      else " ± sample std over seeds. "
    )
    + (
      "Average: the mean over scenes of the per-scene medians, over seeds [95% bootstrap "
      f"interval: seeds resampled, and test views within each scene, {stats.B} replicates]; "
      "last row: ours / the best hand-designed representation (lowest mean validation "
      "median), the geometric mean of the per-seed ratios of those averages on the same test "
      "views [95% seed-level t interval], and the verdict (better / tie / worse: interval "
      "below / containing / above 1; unadjusted). "
      if intervals
      else ""
    )
    + "The last column is the paper's result on the real "
    "7-Scenes images (ResNet-34 pretrained on ImageNet, paper-size training), for reference "
    "only.",
    "",
    C.markdown_table(header, rows),
    "",
    "Data of the columns:",
    "",
    *C.data_notes(selections, [("seven_scenes", "all columns")]),
    f"- ResNet initialisation: {', '.join(weights)}",
    "",
    "## Learning-rate selection",
    "",
    "Score = mean of (validation median position error / 0.21 m, validation median rotation "
    "error / 7.92°), lower is better.",
    "",
    C.selection_table(selections),
    "",
  ]
  return "\n".join(text)


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
    loaded = C.load_results(args.runs, skip_damaged=args.skip_damaged)
    results = [r for r in loaded if r.get("setting") == "seven_scenes"]
    if not results:
      print(f"error: no seven_scenes results.json matches {args.runs}", file=sys.stderr)
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

"""Learning curves from run workdirs: one metric of metrics.jsonl against the step, per run.

Works for any camrep workdir (regression or view synthesis): a regression run logs its
evaluation errors every `eval_every_steps` (validation only, or every split with
`--config.evals.periodic_all_splits=True`), a view-synthesis run logs eval/psnr. Each metric
given becomes one table (a column per run) and one panel of the figure (PNG and a PDF twin);
runs with the same label (the same representation and lr: seeds) are drawn as their mean with a
band from their minimum to their maximum. E.g. the rooms regression's curves for "ours" and the
quaternion,

  .venv/bin/python experiments/learning_curve.py --runs /tmp/curve/ours /tmp/curve/quat \\
      --metrics eval/test_scenes/yaw_error_deg_mean,eval/test_scenes/x_error_mean \\
      --png /tmp/curve/rooms.png --md /tmp/curve/rooms.md

With --bands (a figure per setting, one line per representation, bands over seeds), runs are
grouped by representation (their config; view-synthesis runs by their pose input, rep.kind, or
as the frozen-generator control, e.g. the eval/psnr curves of a converge launch's synthesis
seeds): each table cell is "mean [min, max]" over the group's runs logged at that step (with
their number where runs had stopped), and the figure draws each group's mean with its min and
max as a band, e.g. the validation curves (`eval/validation/score`, logged by every
regression run with eval_every_steps) of a converge launch's chosen runs:

  .venv/bin/python experiments/learning_curve.py --bands --metrics eval/validation/score \
      --runs DIR/regression/car/*/lr1e-3_seed* --png /tmp/curve_car.png --md /tmp/curve_car.md

Reads finished or running workdirs (config.json, metrics.jsonl) or a finished run's compact
record (run.json, which keeps the `eval/` metrics; `camrep.regression.runs`); seconds.
`--from_md` redraws the figure from tables this script wrote, when the workdirs are gone (how
results/quick/curve_rooms.png was redrawn):

  .venv/bin/python experiments/learning_curve.py --from_md results/quick/curve_rooms.md \\
      --png results/quick/curve_rooms.png
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

import numpy as np

from camrep.regression import runs as runs_lib
from camrep.runtime import plots, writers
from camrep.runtime import workdir as workdir_lib


def _record(workdir: str) -> runs_lib.Run | None:
  """The run's compact record, when the directory holds one (None: read its files)."""
  if os.path.isfile(os.path.join(workdir, runs_lib.RECORD_FILE)):
    return runs_lib.load(workdir)
  return None


def _config(workdir: str) -> dict | None:
  record = _record(workdir)
  return record.config if record is not None else workdir_lib.read_stored_config(workdir)


def label_of(workdir: str) -> str:
  """A run's label: its regression representation and lr, else its directory name."""
  name = os.path.basename(os.path.normpath(workdir))
  config = _config(workdir)
  if config is None:
    return name
  rep = config.get("representation")
  if rep:
    lr = config.get("optax", {}).get("lr")
    return f"{rep} (lr {lr:g})" if lr else rep
  return name


def curve(workdir: str, metric: str) -> dict[int, float]:
  """{step: value} of `metric` in the workdir's metrics.jsonl (the last value of each step), or
  in its record."""
  record = _record(workdir)
  if record is not None:
    return dict(record.curves.get(metric, {}))
  out = {}
  for row in writers.read_metrics(workdir):
    if metric in row:
      out[int(row["step"])] = float(row[metric])
  return out


def markdown(labels: Sequence[str], metric: str, curves: Sequence[dict[int, float]]) -> str:
  steps = sorted(set().union(*curves))
  lines = [f"`{metric}`", "", "| step | " + " | ".join(labels) + " |"]
  lines.append("|---" * (len(labels) + 1) + "|")
  for s in steps:
    cells = [f"{c[s]:.4g}" if s in c else "" for c in curves]
    lines.append(f"| {s} | " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def figure(
  labels: Sequence[str],
  metrics: Sequence[str],
  curves: Sequence[Sequence[dict[int, float]]],
  title: str = "",
) -> plots.Figure:
  """One panel per metric (curves[i]: that metric's {step: value} per run); runs sharing a
  label are stacked as seeds; `title` over the panels."""
  steps = sorted(set().union(*(c for per_metric in curves for c in per_metric)))
  panels = []
  for metric, per_run in zip(metrics, curves, strict=True):
    series: dict[str, list] = {}
    for label, c in zip(labels, per_run, strict=True):
      series.setdefault(label, []).append([c.get(s, float("nan")) for s in steps])
    panels.append(
      plots.Panel(
        metric,
        metric.split("/")[-1],
        {k: np.asarray(v, np.float64) for k, v in series.items()},
        xlabel="step",
      )
    )
  return plots.curves_figure(steps, panels, suptitle=title)


def from_markdown(text: str) -> tuple[list[str], list[str], list[list[dict[int, float]]]]:
  """(labels, metrics, curves) of the tables `markdown` wrote (one table per metric)."""
  metrics, curves, labels = [], [], []
  lines = text.splitlines()
  for i, line in enumerate(lines):
    if not (line.startswith("`") and line.endswith("`")):
      continue
    metrics.append(line.strip("`"))
    rows = []
    for row in lines[i + 2 :]:
      if not row.startswith("|"):
        break
      rows.append([c.strip() for c in row.strip("|").split("|")])
    labels = rows[0][1:]
    per_run = [{} for _ in labels]
    for cells in rows[2:]:
      for j, cell in enumerate(cells[1:]):
        if cell:
          per_run[j][int(cells[0])] = float(cell)
    curves.append(per_run)
  return labels, metrics, curves


def group_of(workdir: str) -> str:
  """A run's group under --bands: its representation (regression); a view-synthesis run's pose
  input (rep.kind: grid, lowdim, mlp; "convdraw" for GQN's generator, "frozen_gen" for the grid
  with its generators frozen); else its label."""
  config = _config(workdir) or {}
  if config.get("representation"):
    return config["representation"]
  return runs_lib.pose_input(config) or label_of(workdir)


def bands(groups: Sequence[str], curves: Sequence[dict[int, float]]):
  """{group: {step: (mean, min, max, runs)}} over the curves of each group (per step, over the
  runs that logged it, and how many they are)."""
  by: dict[str, dict[int, list[float]]] = {}
  for g, c in zip(groups, curves, strict=True):
    for step, v in c.items():
      by.setdefault(g, {}).setdefault(step, []).append(v)
  return {
    g: {
      s: (float(np.mean(v)), float(np.min(v)), float(np.max(v)), len(v))
      for s, v in sorted(d.items())
    }
    for g, d in by.items()
  }


def _runs(n: int) -> str:
  return f"{n} run" + ("s" if n != 1 else "")


def band_markdown(metric: str, table, counts: dict[str, int]) -> str:
  """A --bands table: "mean [min, max]" a cell, and "(k runs)" after it where only k of the
  group's runs logged the step (the others had stopped)."""
  names = list(table)
  steps = sorted(set().union(*(table[g] for g in names)))
  head = [f"{g} ({_runs(counts[g])})" for g in names]
  lines = [
    f"`{metric}`: mean [min, max] over the runs that logged the step",
    "",
    "| step | " + " | ".join(head) + " |",
  ]
  lines.append("|---" * (len(names) + 1) + "|")
  for s in steps:
    cells = []
    for g in names:
      if s not in table[g]:
        cells.append("")
        continue
      mean, lo, hi, n = table[g][s]
      cells.append(f"{mean:.4g} [{lo:.4g}, {hi:.4g}]" + (f" ({_runs(n)})" if n < counts[g] else ""))
    lines.append(f"| {s} | " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--runs", nargs="+", default=[], help="workdirs")
  p.add_argument("--metrics", default="", help="comma-separated metrics.jsonl keys")
  p.add_argument("--from_md", default="", help="redraw --png from these tables instead of --runs")
  p.add_argument("--labels", default="", help="comma-separated labels (default: from config)")
  p.add_argument("--png", default="", help="output figure (one panel per metric)")
  p.add_argument("--md", default="", help="output Markdown tables")
  p.add_argument("--title", default="", help="the figure's title (and the Markdown's heading)")
  p.add_argument(
    "--bands", action="store_true", help="group runs by representation: mean [min, max]"
  )
  args = p.parse_args(argv)
  if args.from_md:
    if args.runs or not args.png:
      p.error("--from_md takes --png and no --runs")
    with open(args.from_md, encoding="utf-8") as f:
      labels, metrics, curves = from_markdown(f.read())
    os.makedirs(os.path.dirname(os.path.abspath(args.png)), exist_ok=True)
    fig = figure(labels, metrics, curves, args.title)
    print("wrote", ", ".join(plots.save(fig, args.png)))
    return 0
  if not (args.runs and args.metrics):
    p.error("give --runs and --metrics (or --from_md)")
  metrics = [m.strip() for m in args.metrics.split(",") if m.strip()]
  labels = [x.strip() for x in args.labels.split(",")] if args.labels else []
  if labels and len(labels) != len(args.runs):
    print("error: give one label per run", file=sys.stderr)
    return 2
  for w in args.runs:
    if not any(os.path.exists(os.path.join(w, f)) for f in ("metrics.jsonl", runs_lib.RECORD_FILE)):
      print(f"error: {w} has no metrics.jsonl or {runs_lib.RECORD_FILE}", file=sys.stderr)
      return 2
  labels = labels or [label_of(w) for w in args.runs]
  # --bands: runs of one representation are one line (their mean, a band from min to max).
  groups = [group_of(w) for w in args.runs] if args.bands else labels
  tables, all_curves = [], []
  for metric in metrics:
    curves = [curve(w, metric) for w in args.runs]
    missing = [w for w, c in zip(args.runs, curves, strict=True) if not c]
    if missing:
      print(f"error: {metric} is not logged in {', '.join(missing)}", file=sys.stderr)
      return 2
    if args.bands:
      table = bands(groups, curves)
      counts = {g: groups.count(g) for g in table}
      tables.append(band_markdown(metric, table, counts))
    else:
      tables.append(markdown(labels, metric, curves))
    all_curves.append(curves)
  text = (f"# {args.title}\n\n" if args.title else "") + "\n".join(tables)
  text += (
    "\nRuns: " + "; ".join(f"{lab}: `{w}`" for lab, w in zip(labels, args.runs, strict=True)) + "\n"
  )
  print(text)
  if args.md:
    os.makedirs(os.path.dirname(os.path.abspath(args.md)), exist_ok=True)
    with open(args.md, "w", encoding="utf-8") as f:
      f.write(text)
  if args.png:
    os.makedirs(os.path.dirname(os.path.abspath(args.png)), exist_ok=True)
    fig = figure(groups, metrics, all_curves, args.title)
    print("wrote", ", ".join(plots.save(fig, args.png)))
  return 0


if __name__ == "__main__":
  sys.exit(main())

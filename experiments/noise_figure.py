"""The paper's PSNR-vs-noise figure (section 4.3), from view-synthesis workdirs.

Each workdir is a `python -m camrep.main` run whose noise curve `python -m camrep.synthesis.evaluate
--workdir=W --what=noise` has written to W/eval/noise.json. The runs differ only in the decoder's
pose input (`--config.rep.kind`): the learned representation ("grid"), GQN's low-dimensional
pose vector ("lowdim") and the supplement's MLP embedding ("mlp"). Noise N(0, (alpha beta_i)^2)
is added to every element of the query pose input, beta_i being the element's std over the pose
grid (camrep.synthesis.evaluate.grid_betas), alpha = 0 .. 0.3. A run of configs/gqn_convdraw.py
(GQN's own generator, noised on its 7-D pose vector) is drawn as a fourth kind, "convdraw".

Runs are grouped by pose input (each run's config.json: rep.kind, or model.kind "convdraw");
runs of one pose input are its seeds (3 seeds per pose input at converge size). Writes the figure
(PSNR and SSIM against alpha, one curve per pose input: the mean over its seeds with a band from
their minimum to their maximum, the band being the range of 3 seeds rather than an interval a few
seeds cannot support) as a PNG and a PDF twin, and a Markdown table (one column per pose input,
each cell "mean [min, max]" over its seeds, a plain value for one run):

  .venv/bin/python experiments/noise_figure.py --runs /tmp/cmp/synthesis/gqn_grid \\
      /tmp/cmp/synthesis/gqn_lowdim /tmp/cmp/synthesis/gqn_mlp \\
      --png /tmp/noise_gqn.png --md /tmp/noise_gqn.md

Reads workdirs (config.json, eval/noise.json) or finished runs' compact records (run.json,
`camrep.regression.runs`); seconds. `--from_md` redraws a figure from a
table this script wrote, when the workdirs are gone (how results/quick/noise_*.png were redrawn):

  .venv/bin/python experiments/noise_figure.py --from_md results/quick/noise_gqn.md \\
      --png results/quick/noise_gqn.png --setting gqn
"""

from __future__ import annotations

import argparse
import os
import re
import sys

import numpy as np

from camrep.regression import runs as runs_lib
from camrep.runtime import plots
from camrep.synthesis import evaluate

LABELS = {
  "grid": "ours (learned)",
  "lowdim": "GQN low-dim pose",
  "mlp": "MLP embedding",
  "convdraw": "GQN (ConvDRAW)",
  "frozen_gen": "ours, generators frozen",
}


def load(workdir: str) -> dict:
  """{label, kind, setting, step, alphas, psnr, ssim, psnr_std, num_images} of one run (its
  workdir, or its compact record)."""
  if os.path.isfile(os.path.join(workdir, runs_lib.RECORD_FILE)):
    run = runs_lib.load(workdir)
    config, noise = run.config, run.noise
  else:  # a workdir, finished or not
    config = runs_lib.read_json(os.path.join(workdir, "config.json"))
    path = os.path.join(workdir, evaluate.EVAL_SUBDIR, "noise.json")
    try:
      noise = runs_lib.read_json(path) if os.path.exists(path) else None
    except runs_lib.DamagedRun as e:
      raise ValueError(
        f"{path} is not valid JSON ({e.__cause__}), e.g. cut by a full disk: run `python -m "
        f"camrep.synthesis.evaluate --workdir={workdir} --what=noise` again"
      ) from None
  if noise is None:
    path = os.path.join(workdir, evaluate.EVAL_SUBDIR, "noise.json")
    raise FileNotFoundError(
      f"{path} does not exist: run `python -m camrep.synthesis.evaluate --workdir={workdir} "
      "--what=noise`"
    )
  kind = runs_lib.pose_input(config) or "grid"
  return {
    "label": LABELS.get(kind, kind),
    "kind": kind,
    "workdir": workdir,
    **{k: noise[k] for k in ("setting", "step", "alphas", "psnr", "ssim", "num_images")},
    "psnr_std": noise.get("psnr_std"),
  }


def _cell(values: np.ndarray, fmt: str) -> str:
  """One seed: the value; several: "mean [min, max]" over them."""
  if len(values) == 1:
    return format(float(values[0]), fmt)
  lo, hi = float(np.min(values)), float(np.max(values))
  return f"{float(np.mean(values)):{fmt}} [{lo:{fmt}}, {hi:{fmt}}]"


def markdown(runs: list[dict]) -> str:
  """The table: a column per pose input (label), a row per noise level, "PSNR / SSIM" cells as
  `_cell` over the label's seeds; then the PSNR each loses from the first to the last level and
  the runs read."""
  alphas = runs[0]["alphas"]
  psnr, ssim = by_label(runs, "psnr"), by_label(runs, "ssim")
  labels = list(psnr)
  heads = [
    f"{k} PSNR / SSIM" + (f" ({len(psnr[k])} seeds)" if len(psnr[k]) > 1 else "") for k in labels
  ]
  lines = ["| alpha | " + " | ".join(heads) + " |", "|---" * (len(labels) + 1) + "|"]
  for j, a in enumerate(alphas):
    cells = [f"{_cell(psnr[k][:, j], '.2f')} / {_cell(ssim[k][:, j], '.3f')}" for k in labels]
    lines.append(f"| {a:.3f} | " + " | ".join(cells) + " |")
  drop = {k: psnr[k][:, 0] - psnr[k][:, -1] for k in labels}
  lines += [
    "",
    "PSNR lost from alpha = 0 to alpha = "
    + f"{alphas[-1]:g}: "
    + ", ".join(f"{k} {_cell(d, '.2f')} dB" for k, d in drop.items()),
    "",
    "Runs: "
    + "; ".join(
      f"{r['label']}: `{r['workdir']}` step {r['step']}, {r['num_images']} held-out views"
      for r in runs
    ),
  ]
  return "\n".join(lines) + "\n"


_HEAD = re.compile(r"^(?P<label>.*) PSNR / SSIM(?: \((?P<seeds>\d+) seeds\))?$")
_VALUE = re.compile(r"^(?P<mean>\S+)(?: \[(?P<lo>\S+), (?P<hi>\S+)\])?$")


def from_markdown(text: str, setting: str = "") -> list[dict]:
  """The columns of a table `markdown` wrote: [{label, alphas, psnr, ssim, setting}] per column
  (psnr, ssim: the means), with "seeds" and the ranges "psnr_band" / "ssim_band" ((lo, hi)
  lists) for a column of several seeds."""
  rows = [line for line in text.splitlines() if line.startswith("|")]
  head = [_HEAD.match(c.strip()) for c in rows[0].strip("|").split("|")[1:]]
  alphas, cells = [], []
  for line in rows[2:]:
    parts = [c.strip() for c in line.strip("|").split("|")]
    alphas.append(float(parts[0]))
    cells.append([[_VALUE.match(v.strip()) for v in c.split(" / ")] for c in parts[1:]])
  out = []
  for i, h in enumerate(head):
    run = {"label": h["label"], "setting": setting, "alphas": alphas}
    for k, key in enumerate(("psnr", "ssim")):
      run[key] = [float(row[i][k]["mean"]) for row in cells]
      if h["seeds"]:
        lo = [float(row[i][k]["lo"]) for row in cells]
        run[f"{key}_band"] = (lo, [float(row[i][k]["hi"]) for row in cells])
    if h["seeds"]:
      run["seeds"] = int(h["seeds"])
    out.append(run)
  return out


def by_label(runs: list[dict], key: str) -> dict[str, np.ndarray]:
  """{label: (seeds, n) values of `key`}: runs that share a label (seeds) are stacked, labels in
  the order they first appear."""
  out: dict[str, list] = {}
  for r in runs:
    out.setdefault(r["label"], []).append(r[key])
  return {label: np.asarray(v, np.float64) for label, v in out.items()}


def _bands(runs: list[dict], key: str) -> dict[str, tuple]:
  """The ranges a table gave (`from_markdown` columns of several seeds), for `plots.Panel`."""
  return {r["label"]: (*r[f"{key}_band"], r["seeds"]) for r in runs if f"{key}_band" in r}


def figure(runs: list[dict], column: str = "") -> plots.Figure:
  """PSNR and SSIM against alpha, one curve (and seed band) per label; the panels name `column`
  (e.g. a capture's "chair (car setting)"), else the runs' setting."""
  name = column or runs[0]["setting"]
  suffix = f" ({name})" if name else ""
  panels = [
    plots.Panel(
      f"PSNR vs pose noise{suffix}",
      "PSNR (dB)",
      by_label(runs, "psnr"),
      "alpha",
      bands=_bands(runs, "psnr"),
    ),
    plots.Panel(
      f"SSIM vs pose noise{suffix}", "SSIM", by_label(runs, "ssim"), "alpha", _bands(runs, "ssim")
    ),
  ]
  return plots.curves_figure(runs[0]["alphas"], panels)


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--runs", nargs="+", default=[], help="view-synthesis workdirs")
  p.add_argument("--png", required=True, help="output figure (and its .pdf twin)")
  p.add_argument("--md", default="", help="output Markdown table (required with --runs)")
  p.add_argument("--from_md", default="", help="redraw from this table instead of --runs")
  p.add_argument("--setting", default="", help="with --from_md: the setting, for the titles")
  p.add_argument(
    "--column", default="", help="what the panels' titles name (default: the runs' setting)"
  )
  args = p.parse_args(argv)
  if bool(args.runs) == bool(args.from_md) or (args.runs and not args.md):
    p.error("give --runs and --md, or --from_md")
  if args.from_md:
    with open(args.from_md, encoding="utf-8") as f:
      loaded = from_markdown(f.read(), args.setting)
    os.makedirs(os.path.dirname(os.path.abspath(args.png)), exist_ok=True)
    print("wrote", ", ".join(plots.save(figure(loaded, args.column), args.png)))
    return 0
  try:
    loaded = [load(w) for w in args.runs]
  except (FileNotFoundError, ValueError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  if len({r["setting"] for r in loaded}) != 1:
    print("error: the runs are of different settings", file=sys.stderr)
    return 2
  if any(not np.allclose(r["alphas"], loaded[0]["alphas"]) for r in loaded):
    print("error: the runs' noise levels differ", file=sys.stderr)
    return 2
  for path in (args.png, args.md):
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  table = markdown(loaded)
  with open(args.md, "w", encoding="utf-8") as f:
    f.write(table)
  figures = plots.save(figure(loaded, args.column), args.png)
  print(table)
  print(f"wrote {', '.join(figures)} and {args.md}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

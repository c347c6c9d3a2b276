"""The multi-view transformer's comparison of camera conditionings, from view-synthesis workdirs.

Each workdir is a run of configs/lvsm.py (`python -m camrep.main`, one `model.camera` and seed;
the launcher's `--size lvsm_quick` writes them to DIR/lvsm/<column>/<camera>_seed<k>), with its
noise test on the query pose (`python -m camrep.synthesis.evaluate --what=noise`, eval/noise.json)
where it was run. Runs are grouped by column (the data: procedural rooms "rooms", the procedural
car family "car", a prepared capture "<source>:<directory name>") and conditioning; the runs of a
group are its seeds. Per column, one table row per conditioning:

  params        parameters of the transformer and the conditioning's learned pose system
                (final_metrics.json "num_params"), and the difference to the baseline's;
  PSNR, SSIM    held-out-view means (eval/psnr, eval/ssim at the run's end), mean over seeds with
                the seed-level 95% interval (`stats.values_interval`);
  vs baseline   the paired difference PSNR(camera) - PSNR(baseline) over the seeds both have
                (paired by seed number), its seed-level interval and verdict: the one-sample t
                test of the paired differences, Holm-adjusted over the column's conditionings
                (family-wise 5%), "better"/"worse" by the sign of the mean difference, "tie"
                otherwise; "-" with fewer than 2 paired seeds;
  context n     held-out PSNR with n context views (eval/psnr_context{n}; the trained count is
                eval/psnr), mean over seeds;
  noise drop    PSNR(alpha = 0) - PSNR(alpha max) of the noise test on the query pose, mean over
                seeds with its interval, and the paired difference to the baseline's drop (a
                smaller drop is "better");
  s / step      the cost of a training step: 1 / train/steps_per_sec of the run's last logged row,
                mean over seeds (machine and load as the runs had them).

Intervals (one place, `stats.values_interval`): the t interval of the per-seed values (S - 1
degrees of freedom, `stats.seed_t_interval`), as the lead table's seed-level intervals;
the noise-drop verdicts are a second Holm family per column.

The figure (`--png`, with a PDF twin): per column, held-out PSNR against the noise level alpha
and against the number of context views, one curve per conditioning (mean over seeds, band from
the seeds' minimum to maximum).

  .venv/bin/python experiments/lvsm_table.py --runs /tmp/cmp/lvsm --baseline raymap \\
      --out /tmp/cmp/lvsm_table.md --png /tmp/cmp/lvsm_noise.png

Reads workdirs or finished runs' compact records (run.json, `camrep.regression.runs`); seconds.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from camrep.regression import runs as runs_lib
from camrep.regression import stats, tables

CONTEXT = re.compile(r"^eval/psnr_context(\d+)$")
# Column names of the procedural sources; a prepared source is "<source>:<directory name>".
PROCEDURAL = {"rooms": "rooms", "object": "car"}


def column_of(config: Mapping[str, Any]) -> str:
  data = config.get("data", {})
  source = data.get("source", "rooms")
  if source in PROCEDURAL and not data.get("dir"):
    return PROCEDURAL[source]
  return f"{source}:{os.path.basename(os.path.normpath(data.get('dir', '')))}"


def load(path: str) -> dict[str, Any]:
  """One run's record: column, camera, seed, the final scalars, the noise curve (or None)."""
  run = runs_lib.load(path)
  if run.kind != "synthesis" or run.config.get("task") != "mvt":
    raise ValueError(f"{path} is not a multi-view transformer run (configs/lvsm.py)")
  final = run.final or {}
  if final.get("complete") is not True:
    raise ValueError(f"{path} is not complete (final_metrics.json lacks complete: true)")
  rate = final.get("train/steps_per_sec")
  contexts = {int(m.group(1)): float(v) for k, v in final.items() if (m := CONTEXT.match(k))}
  return {
    "path": path,
    "column": column_of(run.config),
    "camera": run.config.get("model", {}).get("camera", "?"),
    "seed": int(run.config.get("seed", 0)),
    "n_context": int(run.config.get("data", {}).get("n_context", 0)) or None,
    "psnr": float(final["eval/psnr"]),
    "ssim": float(final["eval/ssim"]),
    "contexts": contexts,
    "s_per_step": 1.0 / rate if rate else math.nan,
    "params": sum(int(v) for v in (final.get("num_params") or {}).values()) or None,
    "noise": run.noise,
  }


def find(paths: Sequence[str]) -> list[str]:
  """The run directories under `paths` (a directory holding final_metrics.json or run.json)."""
  out = []
  for p in paths:
    for root, dirs, files in os.walk(p):
      if runs_lib.FINAL_FILE in files or runs_lib.RECORD_FILE in files:
        out.append(root)
        dirs[:] = []
      dirs.sort()
  return sorted(set(out))


def _drop(noise: Mapping[str, Any] | None) -> float | None:
  if not noise:
    return None
  return float(noise["psnr"][0]) - float(noise["psnr"][-1])


def _fmt(iv: stats.Interval | None, digits: int = 2, *, sign: bool = False) -> str:
  if iv is None:
    return "-"
  f = f"{{:{'+' if sign else ''}.{digits}f}}"
  if iv.n_seeds < 2:
    return f.format(iv.value)
  return f"{f.format(iv.value)} [{f.format(iv.lo)}, {f.format(iv.hi)}]"


def group(records: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, dict[int, dict]]]:
  """{column: {camera: {seed: record}}}; two runs of one cell and seed are refused."""
  out: dict[str, dict[str, dict[int, dict]]] = {}
  for r in records:
    cell = out.setdefault(r["column"], {}).setdefault(r["camera"], {})
    if r["seed"] in cell:
      raise ValueError(
        f"two runs of {r['column']}/{r['camera']} seed {r['seed']}: {cell[r['seed']]['path']} "
        f"and {r['path']}"
      )
    cell[r["seed"]] = r
  return out


def column_table(cells: Mapping[str, Mapping[int, dict]], baseline: str) -> str:
  """The Markdown table of one column (module docstring)."""
  order = sorted(cells, key=lambda c: (c != baseline, c))
  base = cells.get(baseline, {})
  counts = sorted({n for seeds in cells.values() for r in seeds.values() for n in r["contexts"]})
  trained = sorted({r["n_context"] for seeds in cells.values() for r in seeds.values()} - {None})
  ctx = sorted(set(counts) | set(trained))
  base_params = next((r["params"] for r in base.values() if r["params"]), None)
  header = ["camera", "params", "seeds", "PSNR", "SSIM", f"PSNR - {baseline}", "verdict"]
  header += [f"ctx {n}" + (" (trained)" if n in trained else "") for n in ctx]
  header += ["noise drop", f"drop - {baseline}", "verdict", "s / step"]
  base_psnr = {s: r["psnr"] for s, r in base.items()}
  base_drops = {s: d for s, r in base.items() if (d := _drop(r["noise"])) is not None}
  drops_of = {
    c: {s: d for s, r in cells[c].items() if (d := _drop(r["noise"])) is not None} for c in order
  }
  others = [c for c in order if c != baseline]
  diffs = {
    c: stats.paired_seed_difference({s: r["psnr"] for s, r in cells[c].items()}, base_psnr)
    for c in others
  }
  ddiffs = {c: stats.paired_seed_difference(drops_of[c], base_drops) for c in others}
  verdict_of = dict(
    zip(others, stats.holm_verdicts([diffs[c] for c in others], higher_is_better=True), strict=True)
  )
  dverdict_of = dict(
    zip(
      others, stats.holm_verdicts([ddiffs[c] for c in others], higher_is_better=False), strict=True
    )
  )
  rows = []
  for camera in order:
    seeds = cells[camera]
    recs = [seeds[s] for s in sorted(seeds)]
    params = recs[0]["params"]
    if params is None:
      ptxt = "-"
    elif base_params is None or camera == baseline:
      ptxt = f"{params:,}"
    else:
      ptxt = f"{params:,} ({params - base_params:+,})"
    row = [camera, ptxt, str(len(recs)), _fmt(stats.values_interval([r["psnr"] for r in recs])[0])]
    row += [_fmt(stats.values_interval([r["ssim"] for r in recs])[0], 3)]
    row += [
      "-" if camera == baseline else _fmt(diffs[camera][0], sign=True),
      "" if camera == baseline else verdict_of[camera],
    ]
    for n in ctx:
      vals = [r["psnr"] if n == r["n_context"] else r["contexts"].get(n) for r in recs]
      vals = [v for v in vals if v is not None]
      row.append(f"{np.mean(vals):.2f}" if vals else "-")
    drops = drops_of[camera]
    row.append(_fmt(stats.values_interval(list(drops.values()))[0]) if drops else "-")
    row += ["-" if camera == baseline else _fmt(ddiffs[camera][0], sign=True)]
    row += ["" if camera == baseline else (dverdict_of[camera] if drops else "-")]
    secs = [r["s_per_step"] for r in recs if math.isfinite(r["s_per_step"])]
    row.append(f"{np.mean(secs):.3f}" if secs else "-")
    rows.append(row)
  return tables.markdown_table(header, rows)


def alpha_max(records: Sequence[Mapping[str, Any]]) -> str:
  alphas = {float(r["noise"]["alphas"][-1]) for r in records if r["noise"]}
  return ", ".join(f"{a:g}" for a in sorted(alphas)) or "-"


def markdown(grouped, baseline: str) -> str:
  lines = [
    "# Camera conditionings of the multi-view transformer",
    "",
    f"Mean over seeds [seed-level 95% t interval]; verdicts: the paired difference to {baseline} "
    "(by seed), its t test Holm-adjusted over the column's conditionings (family-wise 5%): "
    "better or worse by its sign where the adjusted p < 0.05, else tie; '-' with fewer "
    "than 2 paired seeds. noise drop: PSNR(alpha 0) - PSNR(alpha max) of the noise test on the "
    "query pose (smaller is better). s / step: 1 / train/steps_per_sec at the run's end.",
  ]
  for column, cells in grouped.items():
    recs = [r for seeds in cells.values() for r in seeds.values()]
    lines += ["", f"## {column} (noise alpha max {alpha_max(recs)})", ""]
    lines.append(column_table(cells, baseline))
  return "\n".join(lines) + "\n"


def figure(grouped, path: str) -> list[str]:
  """PSNR vs noise alpha and vs context count per column (mean, min-max band over seeds)."""
  import matplotlib

  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  fig, axes = plt.subplots(len(grouped), 2, figsize=(10, 3.6 * len(grouped)), squeeze=False)
  for (column, cells), (ax_n, ax_c) in zip(grouped.items(), axes, strict=True):
    for camera in sorted(cells):
      recs = list(cells[camera].values())
      noisy = [r["noise"] for r in recs if r["noise"]]
      if noisy and len({tuple(n["alphas"]) for n in noisy}) == 1:
        a = np.asarray(noisy[0]["alphas"])
        p = np.asarray([n["psnr"] for n in noisy])
        (line,) = ax_n.plot(a, p.mean(0), marker=".", label=camera)
        ax_n.fill_between(a, p.min(0), p.max(0), color=line.get_color(), alpha=0.2)
      counts = sorted({n for r in recs for n in r["contexts"]} | {r["n_context"] for r in recs})
      counts = [n for n in counts if n is not None]
      if counts:
        vals = [
          [r["psnr"] if n == r["n_context"] else r["contexts"].get(n, np.nan) for n in counts]
          for r in recs
        ]
        v = np.asarray(vals, np.float64)
        (line,) = ax_c.plot(counts, np.nanmean(v, 0), marker="o", label=camera)
        ax_c.fill_between(
          counts, np.nanmin(v, 0), np.nanmax(v, 0), color=line.get_color(), alpha=0.2
        )
    ax_n.set(title=f"{column}: PSNR vs query-pose noise", xlabel="alpha", ylabel="PSNR (dB)")
    ax_c.set(title=f"{column}: PSNR vs context views", xlabel="context views", ylabel="PSNR (dB)")
    for ax in (ax_n, ax_c):
      ax.grid(alpha=0.3)
    ax_c.legend(fontsize=8)
  fig.tight_layout()
  written = []
  for p in (path, os.path.splitext(path)[0] + ".pdf"):
    fig.savefig(p, dpi=120)
    written.append(p)
  plt.close(fig)
  return written


def main(argv: Sequence[str] | None = None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--runs", nargs="+", required=True, help="workdirs or directories above them")
  p.add_argument("--baseline", default="raymap", help="the verdicts' reference conditioning")
  p.add_argument("--out", default="", help="Markdown file (default: print)")
  p.add_argument("--png", default="", help="figure (PNG, with a PDF twin)")
  args = p.parse_args(argv)
  try:
    paths = find(args.runs)
    if not paths:
      raise ValueError(f"no finished runs under {args.runs}")
    records = [load(x) for x in paths]
    grouped = group(records)
  except (ValueError, FileNotFoundError, runs_lib.DamagedRun) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  md = markdown(grouped, args.baseline)
  if args.out:
    with open(args.out, "w", encoding="utf-8") as f:
      f.write(md)
    print(f"wrote {args.out}")
  else:
    print(md, end="")
  if args.png:
    print("wrote " + ", ".join(figure(grouped, args.png)))
  return 0


if __name__ == "__main__":
  sys.exit(main())

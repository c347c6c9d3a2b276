"""Where the spread of "ours" over seeds comes from: the view-synthesis seed and the regression
seed, crossed.

"ours" has two stages, each with its own seed: the view-synthesis run that learns the pose system
(`--config.seed=j`, DIR/synthesis/<column>_seed<j>) and the regression run on its frozen system
(`--config.seed=k`). A converge launch pairs them (j = k); crossing them, every regression seed on
every synthesis seed,

  python -m camrep.regression --config=configs/regression.py:car,quick \\
      --config.representation=ours --config.seed=K --config.optax.lr=LR \\
      --config.synthesis_workdir=DIR/synthesis/car_seedJ \\
      --workdir=DIR/crossed/car/lrLR_seedK_synJ ...

(`python -m camrep.comparison --size converge --crossed car` plans them), separates the two.
This script reads such runs (results.json, config.json, errors_<test split>.npz, or their compact
records run.json; each run's synthesis seed is its synthesis workdir's config.json "seed", else the
_seed<k> of its name) and writes a Markdown table:

- the test error (the setting's statistic of `--error` over the test views: the mean; 7-Scenes:
  per-scene medians averaged over scenes) of every (synthesis seed, regression seed) cell, with
  row and column means;
- the variance split of this two-way crossed design with one run per cell (two-way ANOVA without
  replication): sums of squares between synthesis seeds (rows), between regression seeds
  (columns) and the residual (their interaction and everything else), with the random-effects
  variance components by the method of moments, sigma^2_syn = max(0, (MS_rows - MS_res) / K),
  sigma^2_reg = max(0, (MS_cols - MS_res) / J), sigma^2_res = MS_res (J synthesis seeds, K
  regression seeds); with 3 x 3 cells these are rough (2 degrees of freedom each);
- with --decode, per synthesis seed, the decoding error of its pose system: the true test poses
  encoded as targets and decoded by the regression's own decoder (`targets.encode` /
  `targets.decode`: the nearest-grid arg-min with the run's quantisation, plus its Gauss-Newton
  refinement steps), i.e. the error of a perfect regressor on that pose system, next to the
  regression error of its row, and their correlation over synthesis seeds. A row whose decoding
  error is close to its regression error is limited by its pose system, not by its regressor.

  .venv/bin/python experiments/seed_spread.py --runs 'DIR/crossed/car/*' \\
      'DIR/regression/car/ours/lr1e-3_seed*' --decode --md DIR/seed_spread_car.md

Reads workdirs only, plus (with --decode) each synthesis workdir's latest checkpoint.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from camrep.regression import stats
from camrep.regression import tables as C
from camrep.runtime import workdir as workdir_lib

# The error each setting's table leads with (tables.TABLE1_COLUMNS; Table 2's rotation).
DEFAULT_ERROR = {
  "car": "rotation_error_deg",
  "gqn": "yaw_error_deg",
  "gibson": "yaw_error_deg",
  "seven_scenes": "rotation_error_deg",
}


def reduce_of(setting: str) -> str:
  """The per-scene reduction of the setting's table: 7-Scenes medians (Table 2), else means."""
  return "median" if setting == "seven_scenes" else "mean"


def synthesis_seed(workdir: str) -> int:
  """The seed of a view-synthesis workdir: its config.json "seed", else a name ending _seed<k>.

  Raises:
    ValueError: neither says.
  """
  config = workdir_lib.read_stored_config(workdir) if os.path.isdir(workdir) else None
  if config is not None and "seed" in config:
    return int(config["seed"])
  m = re.search(r"_seed(\d+)$", os.path.normpath(workdir))
  if m:
    return int(m.group(1))
  raise ValueError(f"{workdir}: no config.json with a seed, and no _seed<k> name")


def load_runs(patterns: Sequence[str], error: str = "") -> list[dict[str, Any]]:
  """The "ours" runs matching `patterns`, each {path, workdir, setting, lr, reg_seed, syn_seed,
  syn_workdir, error, errors (N,), scenes (N,), poses (N, P) or None}.

  Raises:
    ValueError: no run, a run that is not "ours" or has no per-view errors, or runs of several
      settings or learning rates.
  """
  results = C.load_results(patterns)
  if not results:
    raise ValueError(f"no results.json under {list(patterns)}")
  out = []
  for r in results:
    wd = os.path.dirname(r["_path"])
    if r.get("representation") != "ours":
      raise ValueError(f"{wd} is a {r.get('representation')!r} run, not 'ours'")
    syn = r.get("representation_params", {}).get("workdir")
    if not syn:
      syn = r["_run"].config.get("synthesis_workdir")
    if not syn:
      raise ValueError(f"{wd}: results.json names no synthesis workdir")
    err = error or DEFAULT_ERROR[r["setting"]]
    v = stats.view_errors(r, err)
    if v is None:
      raise ValueError(f"{wd}: no per-view {err} ({stats.errors_file(r) or 'errors file'})")
    out.append(
      {
        "path": r["_path"],
        "workdir": wd,
        "setting": r["setting"],
        "lr": float(r["lr"]),
        "reg_seed": int(r["seed"]),
        "syn_seed": synthesis_seed(syn),
        "syn_workdir": syn,
        "error": err,
        "errors": v["errors"],
        "scenes": v["scene"],
        "poses": v["pose"],
      }
    )
  for key, what in (("setting", "settings"), ("lr", "learning rates")):
    values = sorted({r[key] for r in out})
    if len(values) > 1:
      raise ValueError(f"the runs have several {what} {values}: give one cell's runs")
  return out


def grid(runs: Sequence[Mapping[str, Any]]) -> tuple[list[int], list[int], np.ndarray]:
  """(synthesis seeds J, regression seeds K, (J, K) statistics) of a fully crossed set of runs.

  Raises:
    ValueError: two runs in one cell, a missing cell, or runs on other test views.
  """
  syn = sorted({r["syn_seed"] for r in runs})
  reg = sorted({r["reg_seed"] for r in runs})
  cells: dict[tuple[int, int], Mapping] = {}
  first = runs[0]
  for r in runs:
    key = (r["syn_seed"], r["reg_seed"])
    if key in cells:
      raise ValueError(
        f"two runs of synthesis seed {key[0]} and regression seed {key[1]}: "
        f"{cells[key]['workdir']} and {r['workdir']}"
      )
    if len(r["errors"]) != len(first["errors"]) or (
      r["poses"] is not None
      and first["poses"] is not None
      and not np.allclose(r["poses"], first["poses"], atol=1e-5)
    ):
      raise ValueError(f"{r['workdir']} and {first['workdir']} have other test views")
    cells[key] = r
  missing = [(j, k) for j in syn for k in reg if (j, k) not in cells]
  if missing:
    raise ValueError(
      "not fully crossed: no run of (synthesis seed, regression seed) "
      + ", ".join(map(str, missing))
    )
  y = np.zeros((len(syn), len(reg)))
  for a, j in enumerate(syn):
    for b, k in enumerate(reg):
      r = cells[j, k]
      scenes = r["scenes"] if r["setting"] == "seven_scenes" else None
      y[a, b] = stats.statistic(r["errors"][None], scenes, reduce_of(r["setting"]))
  return syn, reg, y


def decoding_error(
  syn_workdir: str,
  setting: str,
  poses: np.ndarray,
  *,
  error: str,
  quantisation: str,
  refine_steps: int,
  scenes: np.ndarray | None = None,
) -> float:
  """The statistic of `error` of the true `poses` (N, P) encoded by the pose system of
  `syn_workdir` and decoded back (`targets.encode` / `targets.decode` of "ours", as the
  regression decodes its predictions): a perfect regressor's error on that pose system."""
  import jax.numpy as jnp

  from camrep.regression import pose_system, scoring
  from camrep.regression import targets as T

  system = pose_system.load_pose_system(syn_workdir, setting)
  true = jnp.asarray(poses, jnp.float32)
  kw = dict(spec=system["spec"], rep_params=system["rep"], mode=quantisation)
  heads = T.encode("ours", setting, true, **kw)
  decoded = T.decode("ours", setting, heads, refine_steps=refine_steps, **kw)
  errs = np.asarray(scoring.pose_errors(setting, decoded, true)[error], np.float64)
  scenes = scenes if setting == "seven_scenes" else None
  return stats.statistic(errs[None], scenes, reduce_of(setting))


def run_decoding(runs: Sequence[Mapping[str, Any]]) -> dict[int, float]:
  """{synthesis seed: decoding error} of the runs' pose systems, with the first run of each
  synthesis seed's quantisation and refinement (resolved as the regression resolved them)."""
  from camrep import pose_encodings
  from camrep.regression import learner

  out = {}
  for r in runs:
    if r["syn_seed"] in out:
      continue
    if r["poses"] is None:
      raise ValueError(f"{r['workdir']}: its errors file holds no true poses to decode")
    config = workdir_lib.read_config(r["workdir"])
    out[r["syn_seed"]] = decoding_error(
      r["syn_workdir"],
      r["setting"],
      r["poses"],
      error=r["error"],
      quantisation=learner.resolve_hparams(
        config, pose_encodings.get(config.representation)
      ).quantisation,
      refine_steps=int(config.model.refine_steps),
      scenes=r["scenes"],
    )
  return out


def _f(x: float) -> str:
  return "nan" if not math.isfinite(x) else f"{x:.{C.digits_for(abs(x) or 1.0)}f}"


def markdown(runs: Sequence[Mapping[str, Any]], decoding: Mapping[int, float] | None = None) -> str:
  """The report (see the module docstring)."""
  syn, reg, y = grid(runs)
  r0 = runs[0]
  split = stats.two_way_anova(y)
  stat = (
    "median per scene, averaged over scenes" if reduce_of(r0["setting"]) == "median" else "mean"
  )
  lines = [
    f"## Seed spread of ours: {r0['setting']}, {r0['error']} ({stat} over "
    f"{len(r0['errors'])} test views), lr {r0['lr']:g}",
    "",
    f"{len(syn)} view-synthesis seeds x {len(reg)} regression seeds, one regression run per cell.",
    "",
  ]
  head = ["synthesis seed \\ regression seed", *map(str, reg), "row mean"]
  if decoding:
    head.append("decoding error")
  rows = []
  for a, j in enumerate(syn):
    row = [str(j), *(_f(v) for v in y[a]), _f(float(y[a].mean()))]
    if decoding:
      row.append(_f(decoding[j]) if j in decoding else "-")
    rows.append(row)
  last = ["column mean", *(_f(v) for v in y.mean(axis=0)), _f(float(y.mean()))]
  if decoding:
    last.append(_f(float(np.mean([decoding[j] for j in syn if j in decoding]))))
  lines += [C.markdown_table(head, [*rows, last]), ""]
  lines += [
    "Variance split (two-way ANOVA without replication; variance components by the method of "
    "moments, negative estimates set to 0):",
    "",
  ]
  names = {
    "synthesis": "between synthesis seeds",
    "regression": "between regression seeds",
    "residual": "residual (interaction + rest)",
    "total": "total",
  }
  table = []
  for k, name in names.items():
    s = split[k]
    comp = [_f(s["component"]), _f(s["std"])] if "component" in s else ["", ""]
    table.append([name, str(s["df"]), f"{_f(s['ss'])} ({100 * s['share']:.0f}%)", *comp])
  head = ["source", "df", "sum of squares (share)", "variance component", "std"]
  lines += [C.markdown_table(head, table), ""]
  if decoding:
    common = [j for j in syn if j in decoding]
    d = np.array([decoding[j] for j in common])
    rm = np.array([y[syn.index(j)].mean() for j in common])
    ratio = float(d.mean() / rm.mean()) if rm.mean() else float("nan")
    corr = (
      float(np.corrcoef(d, rm)[0, 1])
      if len(common) >= 3 and d.std() > 0 and rm.std() > 0
      else float("nan")
    )
    lines += [
      f"Decoding error (a perfect regressor on each synthesis seed's pose system) averages "
      f"{_f(float(d.mean()))} against a regression error of {_f(float(rm.mean()))} "
      f"({100 * ratio:.0f}% of it); across synthesis seeds, the decoding error ranges "
      f"{_f(float(d.min()))}-{_f(float(d.max()))} and its Pearson correlation with the row "
      f"mean is {_f(corr)} ({len(common)} points).",
      "",
    ]
  lines.append("Runs: " + ", ".join(f"`{r['workdir']}`" for r in runs))
  return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None, *, decode: Callable | None = None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--runs", nargs="+", required=True, help="regression 'ours' run dirs (globs)")
  p.add_argument("--md", required=True, help="output Markdown")
  p.add_argument("--error", default="", help="error kind (default: the setting's table's)")
  p.add_argument(
    "--decode", action="store_true", help="also the decoding error of each pose system"
  )
  args = p.parse_args(argv)
  try:
    runs = load_runs(args.runs, args.error)
    grid(runs)
    decoding = (decode or run_decoding)(runs) if args.decode else None
    text = markdown(runs, decoding)
  except ValueError as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  os.makedirs(os.path.dirname(os.path.abspath(args.md)), exist_ok=True)
  with open(args.md, "w", encoding="utf-8") as f:
    f.write(text)
  print(text)
  print(f"wrote {args.md}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

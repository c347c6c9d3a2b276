"""From regression results (results.json of `camrep.regression` runs) to the paper's Tables 1 and 2.

Python and NumPy (the settings' selection scores from `camrep.settings`), shared by the table
readers in experiments/ and the comparison launcher (`camrep.comparison`):

  load_results(patterns)      finished runs (workdirs or run.json records) matching glob patterns
  validation_score(s, summ)   the scalar that picks the learning rate (lower is better)
  select(results)             per (setting, representation): the chosen lr and its runs (two runs
                              of one cell are refused: `DuplicateRuns`)
  grid_edge(selection)        whether the chosen lr is the lowest / highest of its grid
  seed_stats(runs, ...)       mean, sample std and count over seeds of one test statistic
  data_label(run)             which data a run used: procedural family or prepared dataset + split
  data_notes(selections, ...) per table column, the data its runs came from

Learning-rate choice: per (setting, representation), each lr's score is the mean of
`validation_score` over the seeds that every lr of the grid has (all seeds when they share none);
the lowest score wins (ties: the smaller lr). The score (`Setting.validation_score`) is the
mean over the setting's table columns of (validation error / the paper's error of "ours" in that
column), so position and angle errors count alike: car mean rotation error / 2.85 deg; gqn mean
(x / 0.053, y / 0.053, yaw / 4.07 deg); gibson mean (x / 0.021, y / 0.020, yaw / 0.87 deg);
seven_scenes median (position / 0.21 m, rotation / 7.92 deg), all over the whole validation set.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import os
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from camrep import settings
from camrep.data import records
from camrep.regression import runs as runs_lib
from camrep.regression import stats

RESULTS_FILE = runs_lib.RESULTS_FILE

# (column key, header, setting, error name): the paper's Table 1 columns (mean test errors).
TABLE1_COLUMNS = (
  ("car", "car rotation (deg)", "car", "rotation_error_deg"),
  ("gqn_x", "rooms x", "gqn", "x_error"),
  ("gqn_y", "rooms y", "gqn", "y_error"),
  ("gqn_ori", "rooms yaw (deg)", "gqn", "yaw_error_deg"),
  ("gibson_x", "area x (m)", "gibson", "x_error"),
  ("gibson_y", "area y (m)", "gibson", "y_error"),
  ("gibson_ori", "area yaw (deg)", "gibson", "yaw_error_deg"),
)
TABLE1_ROWS = ("euler", "axis_angle", "sincos", "quat", "logq", "rot6d", "svd9d", "mlp", "ours")
ROW_LABELS = {
  "euler": "(x, y, α) Euler",
  "axis_angle": "(x, y, axis-angle)",
  "sincos": "(x, y, sin α, cos α)",
  "quat": "(x, y, q)",
  "logq": "(x, y, log q)",
  "rot6d": "(x, y, 6-D Gram-Schmidt) [Zhou 2019; not in the paper]",
  "svd9d": "(x, y, 9-D SVD) [Levinson 2020; not in the paper]",
  "mlp": "MLP embedding",
  "ours": "ours",
  # The protocol's controls (`camrep.pose_encodings`): ours' grid at its random initialisation,
  # and the grid of a view-synthesis run whose generators stayed at their initial values.
  "untrained": "untrained pose system (control)",
  "frozen_gen": "ours, generators frozen (control)",
}

# Row labels of a table whose columns are all of one rotation-only setting (the car's view sphere,
# and its captures): the encoding applied to that setting's own pose columns (`pose_columns`).
ORIENTATION_LABELS = {
  "euler": "Euler angles of ({poses})",
  "axis_angle": "axis-angle of ({poses})",
  "sincos": "sin, cos of ({poses})",
  "quat": "q of ({poses})",
  "logq": "log q of ({poses})",
  "rot6d": "6-D Gram-Schmidt of ({poses}) [Zhou 2019; not in the paper]",
  "svd9d": "9-D SVD of ({poses}) [Levinson 2020; not in the paper]",
}


def pose_columns(setting: str) -> tuple[str, ...]:
  """The pose columns of a setting (`Setting.pose_columns`, which its procedural family, real
  readers and captures share): car ("azimuth", "polar"), rooms and area ("x", "y", "yaw"), ..."""
  return settings.get(setting).pose_columns


def row_label(rep: str, settings: Iterable[str]) -> str:
  """A representation's row label in a table of the columns of `settings`: the paper's
  "(x, y, q)" style where a setting has positions; the encoding of the setting's own pose
  columns where every column is one rotation-only setting ("q of (azimuth, polar)")."""
  poses = {pose_columns(s) for s in settings}
  if len(poses) == 1 and rep in ORIENTATION_LABELS:
    (cols,) = poses
    if not {"x", "y", "z"} & set(cols):
      return ORIENTATION_LABELS[rep].format(poses=", ".join(cols))
  return ROW_LABELS.get(rep, rep)


PAPER_TABLE1: dict[str, dict[str, float]] = {
  "euler": dict(
    car=7.75, gqn_x=0.069, gqn_y=0.071, gqn_ori=12.00, gibson_x=0.043, gibson_y=0.041,
    gibson_ori=7.03,
  ),
  "axis_angle": dict(car=11.29),
  "sincos": dict(
    car=7.29, gqn_x=0.108, gqn_y=0.104, gqn_ori=16.46, gibson_x=0.033, gibson_y=0.034,
    gibson_ori=1.19,
  ),
  "quat": dict(
    car=4.28, gqn_x=0.050, gqn_y=0.048, gqn_ori=5.34, gibson_x=0.043, gibson_y=0.042,
    gibson_ori=1.21,
  ),
  "logq": dict(
    car=5.35, gqn_x=0.051, gqn_y=0.051, gqn_ori=7.44, gibson_x=0.028, gibson_y=0.027,
    gibson_ori=1.17,
  ),
  "mlp": dict(car=3.63),  # the supplement's MLP embedding (car only)
  "ours": dict(
    car=2.85, gqn_x=0.053, gqn_y=0.053, gqn_ori=4.07, gibson_x=0.021, gibson_y=0.020,
    gibson_ori=0.87,
  ),
}  # fmt: skip
"""The paper's Table 1 (the authors' code): mean errors on real data at paper size."""

PAPER_TABLE2: dict[str, tuple[float, float]] = {
  "chess": (0.12, 4.83),
  "fire": (0.27, 8.91),
  "heads": (0.16, 12.84),
  "office": (0.19, 6.64),
  "pumpkin": (0.22, 5.45),
  "redkitchen": (0.24, 6.10),
  "stairs": (0.29, 10.70),
  "average": (0.21, 7.92),
}
"""The paper's Table 2, ours: median position (m) / rotation (deg) error per scene
of the real 7-Scenes data."""

TABLE2_ROWS = ("ours", "quat", "logq", "rot6d", "svd9d")


class TableError(ValueError):
  """Runs a table cannot be made from; the message names them."""


class DamagedRuns(TableError):
  """Finished-looking runs whose files cannot be read (a cut results.json, a damaged errors
  file); the message names each."""


class DuplicateRuns(TableError):
  """Two runs of one cell (setting, representation, lr and seed); the message names both."""


def load_results(
  patterns: Iterable[str], *, skip_damaged: bool = False, warn=None
) -> list[dict[str, Any]]:
  """The results of the regression runs that glob `patterns` match: run directories (their
  results.json, or their compact record run.json, `camrep.regression.runs`) or such files.

  Directories without a finished run (unfinished runs) and view-synthesis runs are skipped. Each
  result gets "_path" (its results.json or run.json) and "_run" (the `runs.Run`, whose per-view
  errors are read here: a damaged errors file is found now, not halfway through a table).

  Args:
    patterns: glob patterns.
    skip_damaged: skip runs that cannot be read, calling `warn(message)` for each (default:
      print to stderr), instead of raising.
    warn: see skip_damaged.

  Raises:
    DamagedRuns: a matched run cannot be read (without skip_damaged); every such run is named.
  """
  out, damaged = [], []
  for d in runs_lib.expand(patterns):
    if not runs_lib.is_finished(d):
      continue
    try:
      run = runs_lib.load(d, arrays=True)
    except runs_lib.DamagedRun as e:
      damaged.append(str(e))
      continue
    if run.kind != "regression":
      continue
    r = dict(run.results)
    record = run.path.endswith(runs_lib.RECORD_FILE)
    r["_path"] = run.path if record else os.path.join(d, RESULTS_FILE)
    r["_run"] = run
    out.append(r)
  out.sort(key=lambda r: r["_path"])
  if damaged and not skip_damaged:
    raise DamagedRuns(
      "damaged runs (a cut or unreadable file; remove or restore them, or pass --skip_damaged): "
      + "; ".join(damaged)
    )
  for message in damaged:
    (warn or (lambda m: print(f"warning: skipped {m}", file=sys.stderr, flush=True)))(message)
  return out


def validation_score_text(setting: str) -> str:
  """The selection score of `setting` in words, e.g. "mean of (x_error mean / 0.053, ...)"
  (`Setting.validation_score_text`)."""
  return settings.get(setting).validation_score_text()


def validation_score(setting: str, summary: Mapping[str, Any]) -> float:
  """The learning-rate selection score of a validation summary (`Setting.validation_score`)."""
  return settings.get(setting).validation_score(summary)


@dataclasses.dataclass
class Selection:
  """The chosen learning rate of one (setting, representation).

  Attributes:
    setting, representation: the group.
    lr: the chosen learning rate.
    runs: the results at that lr, one per seed (sorted by seed).
    scores: {lr: (validation score, seeds it was averaged over)} for every lr of the grid.
  """

  setting: str
  representation: str
  lr: float
  runs: list[dict[str, Any]]
  scores: dict[float, tuple[float, tuple[int, ...]]]

  @property
  def seeds(self) -> tuple[int, ...]:
    return tuple(r["seed"] for r in self.runs)

  @property
  def scored_seeds(self) -> tuple[int, ...]:
    """The seeds the chosen lr's validation score averaged (those every lr of the grid has)."""
    return self.scores[self.lr][1]

  @property
  def on_all_seeds(self) -> bool:
    """Whether the lr was chosen on the validation mean over all the seeds the cell reports."""
    return set(self.scored_seeds) == set(self.seeds)


def select(results: Sequence[Mapping[str, Any]]) -> dict[tuple[str, str], Selection]:
  """Groups results by (setting, representation) and picks each group's learning rate.

  Raises:
    DuplicateRuns: two runs of one (setting, representation, lr, seed) cell, e.g. two workdirs
      of one seed, or a capture column pooled with its setting's own runs.
  """
  groups: dict[tuple[str, str], dict[float, dict[int, Any]]] = collections.defaultdict(
    lambda: collections.defaultdict(dict)
  )
  for r in results:
    cell = groups[r["setting"], r["representation"]][float(r["lr"])]
    seed = int(r["seed"])
    if seed in cell:
      raise DuplicateRuns(
        f"two runs of {r['setting']}/{r['representation']} at lr {r['lr']:g}, seed {seed}: "
        f"{cell[seed].get('_path', '?')} and {r.get('_path', '?')}; give the runs of one "
        "launch or column only"
      )
    cell[seed] = r
  out = {}
  for (setting, rep), by_lr in sorted(groups.items()):
    common = set.intersection(*(set(s) for s in by_lr.values()))
    scores = {}
    for lr, by_seed in sorted(by_lr.items()):
      seeds = tuple(sorted(common or by_seed))
      vals = [validation_score(setting, by_seed[s]["validation"]) for s in seeds]
      scores[lr] = (float(np.mean(vals)), seeds)
    best = min(scores, key=lambda lr: (scores[lr][0], lr))
    runs = [by_lr[best][s] for s in sorted(by_lr[best])]
    out[setting, rep] = Selection(setting, rep, best, runs, scores)
  return out


def validation_statistic(
  runs: Sequence[Mapping[str, Any]], error: str, reduce: str = "mean"
) -> float:
  """The mean over runs (seeds) of validation["all"][error][reduce] (NaN when a run lacks it).

  The validation summaries hold the whole validation split only ("all"), so a column whose test
  statistic averages per-scene medians (7-Scenes) is judged on the median of all its
  validation views."""
  vals = []
  for r in runs:
    v = (r.get("validation") or {}).get("all", {}).get(error, {}).get(reduce)
    if v is None:
      return math.nan
    vals.append(float(v))
  return float(np.mean(vals)) if vals else math.nan


def best_on_validation(
  selections: Mapping[str, Selection], error: str, reduce: str = "mean"
) -> str | None:
  """The hand-designed representation of one column ({representation: Selection}) with the
  lowest `validation_statistic` at its chosen lr, or None: the baseline ours is compared with,
  chosen without reading a test error."""
  values = {rep: validation_statistic(sel.runs, error, reduce) for rep, sel in selections.items()}
  return stats.best_hand_designed(values)


def seed_stats(
  runs: Sequence[Mapping[str, Any]], error: str, stat: str = "mean", scene: str = "all"
) -> tuple[float, float, int]:
  """(mean, sample std (NaN for one run), n) over runs of test[scene][error][stat]."""
  vals = [r["test"][scene][error][stat] for r in runs if scene in r["test"]]
  if not vals:
    return math.nan, math.nan, 0
  std = float(np.std(vals, ddof=1)) if len(vals) > 1 else math.nan
  return float(np.mean(vals)), std, len(vals)


def is_real(run: Mapping[str, Any]) -> bool:
  """Whether a run read a prepared real dataset (its results.json data names a source)."""
  return bool(run.get("data", {}).get("source"))


def width_text(runs: Iterable[Mapping[str, Any]]) -> str:
  """The networks' width of `runs` for a table's caption, from their configs' variants: "quick-width
  models" (`:quick` configs: eighth-width networks, whatever the launch size that set their
  steps), "medium/quick-width models" for a mix."""
  variants = sorted({str(r.get("variant", "?")) for r in runs})
  return f"{'/'.join(variants) or 'no'}-width models"


def data_label(run: Mapping[str, Any]) -> str:
  """Which data a run used, in words: the procedural family and preset, or the prepared
  dataset's name, directory and test split (with its number of test views)."""
  d = run.get("data", {})
  split = d.get("test_split", "?")
  if is_real(run):
    n = d.get("num_test_views")
    return (
      f"prepared `{d.get('dataset', d['source'])}` (source {d['source']}) at "
      f"{d.get('dataset_path', d.get('dir', '?'))}, test split `{split}`"
      + (f" ({n} test views)" if n is not None else "")
      + records.instances_clause(d)
    )
  family, preset = d.get("family", "?"), d.get("preset", "?")
  look = look_overrides(d.get("family_overrides", {}))
  look_text = ", " + ", ".join(f"{k}={v}" for k, v in look.items()) if look else ""
  return f"procedural `{family}` family (preset {preset}{look_text}), test split `{split}`"


# Family fields that size a procedural set (how many scenes and views) rather than what its
# images look like; a table names every other override, so that two looks are never pooled.
_SIZE_FIELDS = ("seed", "image_size", "scenes", "batch_size", "supersample")


def look_overrides(overrides: Mapping[str, Any]) -> dict[str, Any]:
  """The family overrides that change what a scene looks like (wall_style, texture_contrast,
  ...), without those that only size the set (num_*, *_views, *_stride, image_size, ...);
  lists as tuples, sorted by name."""
  out = {}
  for k in sorted(overrides):
    if k in _SIZE_FIELDS or k.startswith("num_") or k.endswith(("_views", "_stride")):
      continue
    v = overrides[k]
    out[k] = tuple(v) if isinstance(v, list) else v
  return out


def data_notes(
  selections: Mapping[tuple[str, str], Selection], columns: Sequence[tuple[str, str]]
) -> list[str]:
  """Markdown lines "- column: data" for each (setting, column name), flagging a column whose
  runs used different data (they are averaged together, which is almost certainly unwanted)."""
  lines = []
  for setting, name in columns:
    labels = sorted(
      {data_label(r) for (s, _), sel in selections.items() if s == setting for r in sel.runs}
    )
    if not labels:
      continue
    if len(labels) == 1:
      lines.append(f"- {name}: {labels[0]}")
    else:
      lines.append(f"- {name}: MIXED DATA, runs of different data pooled: " + "; ".join(labels))
  return lines


def digits_for(value: float) -> int:
  """Decimals that show a value with about three significant digits (at most 4)."""
  if not math.isfinite(value) or value == 0:
    return 2
  return int(min(4, max(0, 2 - math.floor(math.log10(abs(value))))))


def fmt_mean_std(mean: float, std: float, *, digits: int | None = None) -> str:
  """ "1.23 ± 0.04" ("1.23" for one seed, "–" for none)."""
  if not math.isfinite(mean):
    return "–"
  d = digits_for(mean) if digits is None else digits
  if not math.isfinite(std):
    return f"{mean:.{d}f}"
  return f"{mean:.{d}f} ± {std:.{d}f}"


def fmt_lr(lr: float) -> str:
  return f"{lr:.0e}".replace("e-0", "e-")


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
  """A GitHub Markdown table."""
  lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
  lines += ["| " + " | ".join(r) + " |" for r in rows]
  return "\n".join(lines)


def grid_edge(sel: Selection) -> str:
  """Where the chosen lr sits in its grid: "lowest" / "highest" of the grid (the optimum may
  lie outside it: widen the grid), "only lr" (a grid of one), or "" (inside)."""
  grid = sorted(sel.scores)
  if len(grid) == 1:
    return "only lr"
  if sel.lr == grid[0]:
    return "lowest"
  if sel.lr == grid[-1]:
    return "highest"
  return ""


def selection_table(
  selections: Mapping[tuple[str, str], Selection], label: Callable[[str], str] | None = None
) -> str:
  """The learning-rate choice of every group: grid with scores, chosen lr, whether it is at the
  grid's edge, seeds, sizes; `label(representation)` names its row (default: ROW_LABELS)."""
  rows = []
  for (setting, rep), sel in selections.items():
    grid = ", ".join(
      f"{fmt_lr(lr)}: {score:.3g} (seeds {','.join(map(str, seeds))})"
      for lr, (score, seeds) in sel.scores.items()
    )
    r0 = sel.runs[0]
    rows.append(
      [
        setting,
        label(rep) if label else ROW_LABELS.get(rep, rep),
        grid,
        fmt_lr(sel.lr),
        f"**{grid_edge(sel)}**" if grid_edge(sel) else "no",
        ",".join(map(str, sel.seeds)),
        str(r0.get("steps", "?")),
        str(r0.get("params", "?")),
        str(r0.get("variant", "?")),
      ]
    )
  header = [
    "setting",
    "representation",
    "lr: validation score (seeds)",
    "chosen lr",
    "at grid edge",
    "test seeds",
    "steps",
    "params",
    "width",
  ]
  return markdown_table(header, rows)

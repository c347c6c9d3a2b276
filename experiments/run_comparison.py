"""Launch the whole pose-regression comparison (paper Tables 1 and 2; issue 5) as subprocesses.

  python experiments/run_comparison.py --size quick --out DIR [--dry_run]
  python experiments/run_comparison.py --size medium --out DIR --jobs 4 [--dry_run]  # one GPU
  python experiments/run_comparison.py --size paper --out DIR [--dry_run]   # for a GPU
  python experiments/run_comparison.py --size quick --settings seven_scenes \
      --data seven_scenes=PREPARED_DIR --out DIR     # Table 2 from prepared real 7-Scenes
  python experiments/run_comparison.py --size converge --out DIR --max_hours 2 \
      [--data car_chair=nerf:PREPARED_DIR ...] [--noise_runs] [--crossed car] [--dry_run]
      # issue 29, 2 CPU cores

`--size converge` (issue 29): the quick sizes with 3 seeds per cell; every regression run capped
(CONVERGE_CAPS) and stopped by the stopping rule (`--config.stop.*`, validation every cap / 20
steps); lr grids of three values, phase 1 trying up to two more (half a decade beyond the edge;
`--extend_grid N`: up to N) while seed 0's choice sits at its grid's edge; one view-synthesis
run per seed for "ours" (and the MLP embedding, on the car and on each capture column, and the
GQN noise runs), `synthesis/<name>_seed<k>`, regression seed k of
"ours" regressing synthesis seed k's pose system; every view-synthesis run but GQN's ConvDRAW is
trained to its own plateau (the trainer's `--config.stop.*` rule at its held-out evaluations,
capped at 4x its quick steps (the car 8x), CONVERGE_SYNTHESIS_CAPS; its curve in final_metrics.json
"stopping" and DIR/curve_synthesis_<column>.{png,md}); ConvDRAW trains 4x its quick length with
its schedules stretched to it (CONVERGE_CONVDRAW_STEPS). Estimates come from per-step times
measured on the shared 2-core CPU and from guessed shares of the caps (CONVERGE_* constants). `--max_hours H` starts no run after H hours (the
running one finishes); rerunning the same command resumes, skipping finished runs.
`--crossed COLUMN` (converge, off by default) adds, after phase 2, the crossed runs of that
column's "ours": every regression seed k on every other synthesis seed j's pose system, at the
lr seed 0 chose, into DIR/crossed/<column>/<lr>_seed<k>_syn<j> (outside regression/, so never
tabled with the paired runs), then experiments/seed_spread.py --decode over them and the paired
runs -> DIR/seed_spread_<column>.md (where ours' seed spread comes from).
`--archive DIR` (e.g. results/converge, committed): each finished run's records (config.json,
record.json, results.json or final_metrics.json, metrics.jsonl, errors_*.npz, eval/noise.json;
never checkpoints) and the launch's tables and figures are copied into DIR as soon as the run
ends, and a launch starts by restoring the runs DIR holds into --out: a launch cut short resumes
on another machine, losing only the runs in flight. A view-synthesis run restored without its
checkpoints is trained again (the same numbers on the same kind of CPU; on another, XLA's
round-off makes it a statistically equivalent run: the car's seed 0 differed by 0.04 dB at step
480 between two machines; the regression's record.json names the system it read) only while a run that
reads them (its seed's "ours" / MLP regressions, its noise evaluation, crossed runs) is missing.
With one synthesis run per seed (converge) the launch goes seed by seed, so that a cut loses
little: seed 0's synthesis runs and their evaluations, phase 1, then for each later seed its
synthesis runs, their evaluations and its phase-2 runs.
`--data car_NAME=SOURCE:DIR` (repeatable) adds a capture column "car_NAME": a capture prepared
by `python -m camrep.data.prepare --source SOURCE --input CAPTURE --data_dir DIR --preset small`
(SOURCE nerf, llff or colmap), regressed in the car setting into regression/car_NAME and tabled
alone in DIR/table1_car_NAME.md.

`--data SETTING=DIR` (repeatable) runs that setting on real data prepared by
`python -m camrep.data.prepare --source SOURCE --input RAW --data_dir DIR` (SOURCE: gqn for gqn,
srn_cars for car, gibson, seven_scenes) instead of its procedural family: both the view-synthesis
and the regression runs get `--config.data.source=SOURCE --config.data.dir=DIR
--config.data.preset=default` (the prepared dataset's only builder config), and the tables say
which data each column came from. Without it a setting uses its procedural family.

Steps, one subprocess at a time, or --jobs N of them at once within each step (each logs to
DIR/logs/<name>.log; finished steps are skipped, so an interrupted launch resumes where it
stopped):

  1. view-synthesis runs (`python -m camrep.main --config=configs/<setting>.py[:quick]
     --workdir=DIR/synthesis/<setting>`) for gqn, car, gibson, seven_scenes, plus car_mlp (the
     supplement's MLP embedding trained by view synthesis, `--config.rep.kind=mlp`) when the
     trainer supports rep.kind; a run whose final_metrics.json says "complete" is done (and
     named as skipped), otherwise it is started or resumed from its checkpoint;
  2. regression runs (`python -m camrep.regression --config=configs/regression.py[:quick]`) into
     DIR/regression/<setting>/<representation>/lr<lr>_seed<seed>: phase 1 trains seed 0 at every
     learning rate of the setting's grid; phase 2 trains the other seeds at the lr that seed 0's
     validation errors chose (`camrep.regression.tables.select`), or at every lr with --full_grid;
     a run with results.json is done. Rendered data and restored pose systems are cached in
     DIR/cache;
  3. tables: experiments/table1.py -> DIR/table1.md, experiments/table2.py -> DIR/table2.md,
     experiments/lead_table.py -> DIR/lead_table.md (every column in one table);
  4. figures: `python -m camrep.synthesis.evaluate --workdir DIR/synthesis/<name>` (noise robustness
     and Gram maps into each workdir's eval/), then, if experiments/noise_figure.py exists, one
     noise figure per setting with several pose inputs: DIR/noise_car.{png,md} (learned system
     vs MLP embedding) and, with --noise_runs (more GQN synthesis runs: rep.kind lowdim and mlp,
     and GQN's own generator, configs/gqn_convdraw.py, except at medium size),
     DIR/noise_gqn.{png,md}.

Representations: car all seven (ours, mlp, euler, axis_angle, sincos, quat, logq); gqn and
gibson ours, euler, sincos, quat, logq (axis-angle and MLP are car-only in the paper);
seven_scenes ours, quat, logq (Table 2).

Budget: --dry_run prints every command with an estimated time and the total. The quick size is
planned for about 2 hours on 2 CPU cores (estimates measured on a shared 2-core machine); the
medium size (the `:medium` config variants: quarter width, 64 px, 10x the quick steps and
2-5x its data, 3 seeds) for about an hour of one H100 with --jobs 4 (estimates not measured:
no GPU was lent when it was planned; BUILD_NOTES shows how they were derived); the paper size
is for a GPU (days of view synthesis per setting, as in the paper). With --jobs N > 1 every
subprocess gets XLA_PYTHON_CLIENT_MEM_FRACTION = 0.9 / N (unless set), so N JAX processes fit
on one GPU.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import glob
import math
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence

from camrep.configs import gqn_convdraw as gqn_convdraw_config
from camrep.regression import tables as C
from camrep.runtime import progress as progress_lib
from camrep.runtime import session

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SETTINGS = ("gqn", "car", "gibson", "seven_scenes")
# The real source each setting's --data directory holds (camrep.data.sources: the real source of each setting).
REAL_SOURCES = {"gqn": "gqn", "car": "srn_cars", "gibson": "gibson", "seven_scenes": "seven_scenes"}
SYNTHESIS_CONFIGS = {
  "gqn": "configs/gqn.py",
  "car": "configs/shapenet_car.py",
  "gibson": "configs/gibson.py",
  "seven_scenes": "configs/seven_scenes.py",
}
REPRESENTATIONS = {
  "car": ("ours", "mlp", "euler", "axis_angle", "sincos", "quat", "logq", "rot6d", "svd9d"),
  "gqn": ("ours", "euler", "sincos", "quat", "logq"),
  "gibson": ("ours", "euler", "sincos", "quat", "logq"),
  "seven_scenes": ("ours", "quat", "logq", "rot6d", "svd9d"),
}


@dataclasses.dataclass(frozen=True)
class Plan:
  """Sizes and time estimates of one launch size.

  Attributes:
    variant: config variant ("quick" or "" for paper size).
    seeds: regression seeds.
    lrs: learning-rate grid per setting.
    synthesis_s: estimated seconds per view-synthesis run, per setting ("capture": a capture
      column's, where given).
    regression_s: estimated seconds per regression run (data cached), per setting.
    data_s: one-time rendering of a setting's regression data, seconds.
    evaluate_s: `camrep.synthesis.evaluate` of one synthesis run, seconds.
  """

  variant: str
  seeds: tuple[int, ...]
  lrs: dict[str, tuple[float, ...]]
  synthesis_s: dict[str, float]
  regression_s: dict[str, float]
  data_s: dict[str, float]
  evaluate_s: float
  # converge (issue 29): --config.* flags of every regression run (cap, periodic validation,
  # stopping rule), of every synthesis run, one synthesis run per seed paired with "ours"'s
  # regression seed, and how many times phase 1 may extend an lr grid whose choice is at its edge.
  regression_flags: tuple[str, ...] = ()
  synthesis_flags: tuple[str, ...] = ()
  paired_synthesis: bool = False
  extend_grid: int = 0
  # converge: view-synthesis runs to their own plateau (the trainer's `stop` rule at its held-out
  # evaluations), capped at these steps per synthesis config ("gqn_convdraw": GQN's generator);
  # a config not named keeps its own total_steps and no rule. Empty: no rule anywhere.
  synthesis_caps: dict[str, int] = dataclasses.field(default_factory=dict)
  # GQN's ConvDRAW trained for this many steps with its schedules stretched to them (no plateau
  # rule: `synthesis_flags`); 0: its config's own length.
  convdraw_steps: int = 0


# Per-step times at quick size on this 2-core CPU, shared with other jobs (load average 3-9 at
# the time; at load ~18 the same steps took 3-9x longer), BUILD_NOTES "Issue 29".
# MEASURED: regressions of quat, 100 and 400 steps (car) / 50 and 250 steps (gqn), data cached:
# car train_seconds 9.2 / 12.1 s -> 9.7 ms a step, gqn 30.4 / 55.3 s -> 125 ms a step (4 rooms x
# 10 views and the context encoder). A car view-synthesis run of 120 steps: 0.38 s a step (steps
# 20-120), 91 s wall (~45 s start-up, data, evaluations). The GQN decoder's quick step: 2.5-3.0
# steps/s alone (BUILD_NOTES "quick GQN"), i.e. 0.33-0.4 s: 0.38 s taken. GQN's ConvDRAW quick
# step: 2.0-2.4 steps/s at load ~10 (BUILD_NOTES "ConvDRAW"); measured again below.
# NOT MEASURED (scaled or guessed): gibson and seven_scenes regression steps (the car's x 1.3 and
# x 1.1, from the older quick estimates); gibson and seven_scenes synthesis steps (the car's
# 0.38 s); ~30 s a regression run of start-up, compilation and evaluation; ~3 s per held-out
# evaluation of a synthesis run (20 of them under the plateau rule).
# Then the regressors' conv kernel gradients by XLA below 128 channels (fastconv "by_channels",
# BUILD_NOTES "The regression step"): the same-process A/B gave gqn 0.157 -> 0.069 s (2.3x) and
# car 0.017 -> 0.013 s a step (1.3x) at load 8-10; the constants are the old ones divided by those
# factors (gibson scaled like the car; seven_scenes' ResNet does not use fastconv, unchanged).
# "ours" on gqn measured 1.7x the quat step (its 192-d pose input to the context encoder): the
# plan times every representation at quat's step, so it underestimates those runs.
CONVERGE_REG_STEP_S = {"car": 0.0075, "gqn": 0.055, "gibson": 0.0097, "seven_scenes": 0.0107}
CONVERGE_REG_OVERHEAD_S = 30.0
CONVERGE_SYNTHESIS_STEP_S = {"gqn": 0.38, "car": 0.38, "gibson": 0.38, "seven_scenes": 0.38}
# ConvDRAW MEASURED 2026-11-26 in the converge noise launch: seed 0's 2,000 quick steps took
# 8 min 48 s wall (start and evaluations included), mostly alone on the 2 cores: 0.26 s a step.
CONVERGE_CONVDRAW_STEP_S = 0.26
# A capture column's synthesis step (one instance a step, `scenes_per_device=1`): measured
# 2026-11-26 beside another job, the three captures' seed-0 runs of 1,200-2,400 steps took
# 65-110 s each (whole runs, start included; the grey chair 2,400 steps in 65 s); ~0.05 s a step.
CONVERGE_CAPTURE_SYNTHESIS_STEP_S = 0.05
CONVERGE_SYNTHESIS_OVERHEAD_S = 45.0 + 20 * 3.0
# The :quick view-synthesis runs' own total_steps (configs/<setting>.py:quick, gqn_convdraw.py).
QUICK_SYNTHESIS_STEPS = {"gqn": 2000, "car": 600, "gibson": 600, "seven_scenes": 600}
QUICK_CONVDRAW_STEPS = 2000
# View synthesis to its own plateau (issue 29 part 3): capped at 4x the quick steps (car 8x), held-out
# evaluation every cap / 20 steps, the same rule as the regressions (2% over the last quarter of
# the steps, on the held-out MSE 10^(-PSNR/10): ~0.09 dB), not before the quick length (so no
# converge pose system is trained less than the quick one). GQN's ConvDRAW (noise figure only)
# has no rule: its learning-rate, sigma and KL schedules are fractions of its length
# (configs/gqn_convdraw.py `quick_schedules`), which an early stop would cut. It trains for the
# rooms' cap instead (CONVERGE_CONVDRAW_STEPS, 4x its quick length) with its schedules stretched
# to that length: at the quick length it was 2.7 dB under the GQN decoder's runs, and a 4x run of
# seed 0 was still 0.7 dB higher at step 3,200 (BUILD_NOTES, the fifth session).
# The car's cap is 8x: its first converge run (seed 0) reached 4x (2,400 steps) still improving,
# 19.37 -> 19.70 dB over the last quarter (7% in held-out MSE; BUILD_NOTES "The converge launch").
CONVERGE_SYNTHESIS_CAPS = {s: 4 * n for s, n in QUICK_SYNTHESIS_STEPS.items()} | {"car": 8 * 600}
CONVERGE_CONVDRAW_STEPS = 4 * QUICK_CONVDRAW_STEPS
# Expected steps trained as a share of the cap, for the estimates only (the rules decide).
# car MEASURED twice: configs/shapenet_car.py:quick, seed 0, stopped at step 960 of 2,400 in one
# session (18.62 dB) and ran to the 2,400 cap in the next (19.70 dB; the held-out PSNR wobbles by
# ~0.15 dB between evaluations, more than the rule's 2% = 0.09 dB): 0.6 of the 4,800 cap taken.
# The others GUESSED; update them from the "stopping" records ("steps") of finished runs
# (regression results.json, synthesis final_metrics.json).
CONVERGE_SYNTHESIS_EXPECTED_SHARE = {"gqn": 0.6, "car": 0.6, "gibson": 0.6, "seven_scenes": 0.6}
# Regression caps (steps) and the stopping rule (camrep/runtime/stopping.py) at converge size:
# rooms to 8,000 steps (results/quick/curve_rooms.md: ours still improving at 8,000), the others 6,000
# (4x quick) but the car (below); validation every cap / 20 steps; stop when the best validation score improved by
# less than 2% over the last quarter of the steps, not before a quarter of the cap.
# The car's cap is 24,000 (16x quick): at 6,000 its first runs (seed 0: ours, mlp, euler at lr
# 1e-3) were still improving 5-15% over the last quarter, and a car step costs ~5 ms.
CONVERGE_CAPS = {"gqn": 8_000, "car": 24_000, "gibson": 6_000, "seven_scenes": 6_000}
CONVERGE_MIN_IMPROVEMENT = 0.02
# Expected steps trained as a share of the cap (for the estimate only; the stopping rule decides;
# GUESSED, see CONVERGE_SYNTHESIS_EXPECTED_SHARE).
CONVERGE_EXPECTED_SHARE = 0.6


def _converge_plan() -> Plan:
  """`--size converge` (issue 29): the quick sizes, 3 seeds, regressions to their plateau (the
  stopping rule, capped), lr grids of three values around the quick choices, each extended by
  phase 1 (up to two more lrs) while its choice sits at an edge; one view-synthesis run per seed
  for "ours" (paired with the regression seed). Estimates from the measured per-step times."""
  reg_s = {
    s: CONVERGE_REG_OVERHEAD_S + CONVERGE_EXPECTED_SHARE * CONVERGE_CAPS[s] * t
    for s, t in CONVERGE_REG_STEP_S.items()
  }
  syn = {
    s: CONVERGE_SYNTHESIS_OVERHEAD_S
    + CONVERGE_SYNTHESIS_EXPECTED_SHARE[s] * CONVERGE_SYNTHESIS_CAPS[s] * t
    for s, t in CONVERGE_SYNTHESIS_STEP_S.items()
  }
  syn["capture"] = (
    CONVERGE_SYNTHESIS_OVERHEAD_S
    + CONVERGE_SYNTHESIS_EXPECTED_SHARE["car"]
    * CONVERGE_SYNTHESIS_CAPS["car"]
    * CONVERGE_CAPTURE_SYNTHESIS_STEP_S
  )
  return Plan(
    variant="quick",
    seeds=(0, 1, 2),
    lrs={
      # Rooms chose the top of (3e-4, 1e-3) at quick size: widened upwards.
      "car": (3e-4, 1e-3, 3e-3),
      "gqn": (3e-4, 1e-3, 3e-3),
      "gibson": (1e-3, 3e-3, 1e-2),
      "seven_scenes": (1e-4, 3e-4, 1e-3),
    },
    synthesis_s={**syn, "gqn_convdraw": 45.0 + CONVERGE_CONVDRAW_STEPS * CONVERGE_CONVDRAW_STEP_S},
    regression_s=reg_s,
    data_s={"gqn": 45, "car": 30, "gibson": 30, "seven_scenes": 20},
    evaluate_s=120,
    regression_flags=(
      "--config.stop.min_improvement=" + format(CONVERGE_MIN_IMPROVEMENT, "g"),
      "--config.stop.window=0.25",
    ),
    paired_synthesis=True,
    extend_grid=2,
    synthesis_caps=dict(CONVERGE_SYNTHESIS_CAPS),
    convdraw_steps=CONVERGE_CONVDRAW_STEPS,
  )


def synthesis_flags(plan: Plan, setting: str, kind: str = "") -> list[str]:
  """The plan's plateau flags of a view-synthesis run of `setting` with pose input `kind`, none
  without `synthesis_caps`; for GQN's generator ("convdraw") its length and the schedules
  stretched to it (`plan.convdraw_steps`; no rule, and no resuming at another length)."""
  if kind == "convdraw":
    n = plan.convdraw_steps
    if not n:
      return []
    stretched = gqn_convdraw_config.quick_schedules(n)
    return [f"--config.total_steps={n}", f"--config.eval_every_steps={n // 20}"] + [
      f"--config.{field}={steps}" for field, steps in stretched.items()
    ]
  cap = plan.synthesis_caps.get(setting)
  if not cap:
    return []
  return [
    f"--config.total_steps={cap}",
    f"--config.eval_every_steps={cap // 20}",
    f"--config.stop.min_improvement={CONVERGE_MIN_IMPROVEMENT:g}",
    "--config.stop.window=0.25",
    f"--config.stop.min_steps={cap // 4}",
    # A raised cap resumes a run that reached the old one (recorded in config_history.jsonl).
    "--config.allow_changes=total_steps,eval_every_steps,stop",
  ]


def regression_flags(plan: Plan, setting: str) -> list[str]:
  """The plan's extra flags of a regression run of `setting` (cap, eval period, stop)."""
  if not plan.regression_flags:
    return []
  cap = CONVERGE_CAPS[setting]
  return [
    f"--config.total_steps={cap}",
    f"--config.eval_every_steps={cap // 20}",
    f"--config.stop.min_steps={cap // 4}",
    *plan.regression_flags,
  ]


PLANS = {
  # Estimates (seconds on one H100), derived rather than measured (BUILD_NOTES, "Medium size"):
  # ~15 ms a quarter-width step (the eighth-width quick GQN step measured ~15 ms sharing an H100
  # with another run), plus ~60 s of start-up, compilation and evaluations per run.
  "medium": Plan(
    variant="medium",
    seeds=(0, 1, 2),
    lrs={
      "car": (1e-3, 3e-3),
      "gqn": (3e-4, 1e-3),
      "gibson": (3e-3, 1e-2),
      "seven_scenes": (3e-4, 1e-3),
    },
    synthesis_s={"gqn": 360, "car": 360, "gibson": 360, "seven_scenes": 360},
    regression_s={"gqn": 105, "car": 150, "gibson": 150, "seven_scenes": 150},
    data_s={"gqn": 150, "car": 120, "gibson": 60, "seven_scenes": 60},
    evaluate_s=60,
  ),
  "quick": Plan(
    variant="quick",
    seeds=(0, 1),
    lrs={
      "car": (1e-3, 3e-3),
      "gqn": (3e-4, 1e-3),
      # 1e-2 added after the first full run chose "ours" at the top of (1e-3, 3e-3).
      "gibson": (1e-3, 3e-3, 1e-2),
      "seven_scenes": (3e-4, 1e-3),
    },
    synthesis_s={"gqn": 600, "car": 600, "gibson": 540, "seven_scenes": 540},
    regression_s={"gqn": 100, "car": 50, "gibson": 65, "seven_scenes": 55},
    data_s={"gqn": 45, "car": 30, "gibson": 30, "seven_scenes": 20},
    evaluate_s=120,
  ),
  # Paper size: the authors' learning rates x (1/3, 1, 3) (the paper tuned baselines but gives
  # no values); times are rough guesses for one modern GPU.
  "paper": Plan(
    variant="",
    seeds=(0, 1, 2),
    lrs={
      "car": (3e-4, 1e-3, 3e-3),
      "gqn": (3e-5, 1e-4, 3e-4),
      "gibson": (3e-4, 1e-3, 3e-3),
      "seven_scenes": (1.5e-5, 5e-5, 1.5e-4),
    },
    synthesis_s={"gqn": 4 * 86400, "car": 2 * 86400, "gibson": 5 * 86400, "seven_scenes": 86400},
    regression_s={"gqn": 6 * 3600, "car": 3 * 3600, "gibson": 3600, "seven_scenes": 2 * 3600},
    data_s={"gqn": 1800, "car": 1800, "gibson": 3600, "seven_scenes": 600},
    evaluate_s=600,
  ),
  "converge": _converge_plan(),
}


@dataclasses.dataclass
class Job:
  """One subprocess: a name (its log file), argv, the file that marks it done, and an estimate."""

  name: str
  argv: list[str]
  done_file: str
  estimate_s: float

  def done(self) -> bool:
    """Whether the job's record exists; a view-synthesis run's final_metrics.json must also
    say it completed (a killed resumed run leaves it marked incomplete)."""
    if not self.done_file or not os.path.exists(self.done_file):
      return False
    if os.path.basename(self.done_file) == session.FINAL_FILE:
      return synthesis_done(os.path.dirname(self.done_file), self.argv)
    return True

  def command(self) -> str:
    return shlex.join(self.argv)


def synthesis_done(workdir: str, argv: Sequence[str]) -> bool:
  """A view-synthesis run is done when complete at the step cap its command gives
  (`--config.total_steps`), or stopped earlier by its plateau rule: a raised cap resumes a run
  that reached the old one."""
  if not session.is_complete(workdir):
    return False
  caps = [a.split("=", 1)[1] for a in argv if a.startswith("--config.total_steps=")]
  final = session.read_final(workdir)
  stopped = bool((final.get("stopping") or {}).get("stopped_early"))
  return not caps or stopped or final.get("step") == int(caps[-1])


def mlp_synthesis_supported() -> bool:
  """Whether the view-synthesis trainer has config.rep.kind (the MLP pose input)."""
  from camrep.configs import common

  return "kind" in common.base().rep


def setting_of(column: str) -> str:
  """The setting of a table column: the setting itself, or "car" for a capture column
  "car_<NAME>" (`--data car_NAME=SOURCE:DIR`)."""
  return column if column in SETTINGS else column.split("_", 1)[0]


def lr_tag(lr: float) -> str:
  return f"lr{lr:.0e}".replace("e-0", "e-")


def data_flags(setting: str, data: dict | None) -> list[str]:
  """The config flags that point a run of `setting` (or capture column) at its prepared real data
  (none without); a capture column's value is (source, dir), prepared with `--preset small`."""
  if not data or setting not in data:
    return []
  if isinstance(data[setting], tuple):
    source, path = data[setting]
    return [f"--config.data.source={source}", f"--config.data.dir={path}"]
  return [
    f"--config.data.source={REAL_SOURCES[setting]}",
    f"--config.data.dir={data[setting]}",
    "--config.data.preset=default",
  ]


def capture_of(name: str, data: dict | None) -> str | None:
  """The capture column a view-synthesis name belongs to ("car_chair" or "car_chair_mlp" ->
  "car_chair"; the longest capture column it starts with), or None for a setting's own."""
  caps = [c for c, d in (data or {}).items() if isinstance(d, tuple)]
  hits = [c for c in caps if name == c or name.startswith(f"{c}_")]
  return max(hits, key=len) if hits else None


def synthesis_jobs(
  out: str, plan: Plan, names: Sequence[str], py: str, data: dict[str, str] | None = None
) -> list[Job]:
  """View-synthesis runs: "<setting>" (the learned system) or "<setting>_<kind>" (another pose
  input, `--config.rep.kind=<kind>`), into DIR/synthesis/<name>; on the setting's prepared
  real data when `data` names it."""
  suffix = f":{plan.variant}" if plan.variant else ""
  jobs = []
  for full in names:
    name, _, seed = full.partition("_seed")
    setting = next(x for x in SETTINGS if name == x or name.startswith(f"{x}_"))
    kind = name[len(setting) + 1 :]
    cap = capture_of(name, data)
    capture = cap is not None
    if capture:  # a capture column: the car setting on the capture, one instance a step
      kind = name[len(cap) + 1 :]  # "" (the learned system) or "mlp"
    wd = os.path.join(out, "synthesis", full)
    if kind == "convdraw":  # GQN's own generator: its config, fed GQN's 7-D pose vector
      argv = [py, "-m", "camrep.main", f"--config=configs/gqn_convdraw.py{suffix}"]
    else:
      argv = [py, "-m", "camrep.main", f"--config={SYNTHESIS_CONFIGS[setting]}{suffix}"]
    argv.append(f"--workdir={wd}")
    if kind and kind != "convdraw":
      argv.append(f"--config.rep.kind={kind}")
    argv += data_flags(cap if capture else setting, data)
    if capture:
      argv.append("--config.data.scenes_per_device=1")
    if seed:
      argv.append(f"--config.seed={seed}")
    argv += list(plan.synthesis_flags) + synthesis_flags(plan, setting, kind)
    est = plan.synthesis_s.get(f"{setting}_{kind}", plan.synthesis_s[setting])
    if capture:
      est = plan.synthesis_s.get("capture", est)
    jobs.append(Job(f"synthesis_{full}", argv, os.path.join(wd, "final_metrics.json"), est))
  return jobs


def regression_job(
  out: str,
  plan: Plan,
  setting: str,
  rep: str,
  lr: float | None,
  seed: int,
  py: str,
  data: dict[str, str] | None = None,
) -> Job:
  """One regression run's job (lr None: a placeholder "<LR>", for --dry_run's phase 2), on the
  setting's prepared real data when `data` names it."""
  suffix = f",{plan.variant}" if plan.variant else ""
  tag = "lr<LR>" if lr is None else lr_tag(lr)
  column, setting = setting, setting_of(setting)
  wd = os.path.join(out, "regression", column, rep, f"{tag}_seed{seed}")
  argv = [
    py,
    "-m",
    "camrep.regression",
    f"--config=configs/regression.py:{setting}{suffix}",
    f"--workdir={wd}",
    f"--config.representation={rep}",
    f"--config.seed={seed}",
    f"--config.optax.lr={'<LR>' if lr is None else format(lr, 'g')}",
    f"--config.data.cache_dir={os.path.join(out, 'cache')}",
    *data_flags(column, data),
    *regression_flags(plan, setting),
  ]
  syn = os.path.join(out, "synthesis", column)
  pair = f"_seed{seed}" if plan.paired_synthesis else ""
  if rep == "ours":
    argv.append(f"--config.synthesis_workdir={syn}{pair}")
  elif rep == "mlp" and mlp_synthesis_supported():
    argv.append(f"--config.synthesis_workdir={syn}_mlp{pair}")
  name = f"regression_{column}_{rep}_{tag}_seed{seed}"
  return Job(name, argv, os.path.join(wd, C.RESULTS_FILE), plan.regression_s[setting])


def crossed_job(
  out: str,
  plan: Plan,
  column: str,
  lr: float | None,
  seed: int,
  synthesis_seed: int,
  py: str,
  data: dict[str, str] | None = None,
) -> Job:
  """A crossed "ours" run (`--crossed`): regression seed `seed` on the pose system of synthesis
  seed `synthesis_seed` (another seed than its own), into DIR/crossed/<column>/<lr>_seed<k>_syn<j>
  (outside regression/, so the tables never pool it with the paired runs)."""
  job = regression_job(out, plan, column, "ours", lr, seed, py, data)
  tag = "lr<LR>" if lr is None else lr_tag(lr)
  wd = os.path.join(out, "crossed", column, f"{tag}_seed{seed}_syn{synthesis_seed}")
  syn = os.path.join(out, "synthesis", f"{column}_seed{synthesis_seed}")
  argv = [
    f"--workdir={wd}"
    if a.startswith("--workdir=")
    else f"--config.synthesis_workdir={syn}"
    if a.startswith("--config.synthesis_workdir=")
    else a
    for a in job.argv
  ]
  name = f"crossed_{column}_{tag}_seed{seed}_syn{synthesis_seed}"
  return Job(name, argv, os.path.join(wd, C.RESULTS_FILE), job.estimate_s)


def crossed_jobs(launch: Launch, lr: float | None) -> list[Job]:
  """Every (regression seed k, synthesis seed j != k) run of the `--crossed` column at `lr`
  (None: the placeholder of --dry_run); the paired runs (j = k) are the launch's own."""
  L = launch
  if not L.crossed:
    return []
  seeds = L.plan.seeds
  return [
    crossed_job(L.out, L.plan, L.crossed, lr, k, j, L.python, L.data)
    for k in seeds
    for j in seeds
    if j != k
  ]


def seed_spread_job(launch: Launch, lr: float) -> Job:
  """experiments/seed_spread.py over the crossed runs and the paired ones at `lr`, with the
  decoding error of each pose system, into DIR/seed_spread_<column>.md."""
  L = launch
  col = L.crossed
  runs = [
    os.path.join(L.out, "crossed", col, f"{lr_tag(lr)}_seed*_syn*"),
    os.path.join(L.out, "regression", col, "ours", f"{lr_tag(lr)}_seed*"),
  ]
  argv = [L.python, "experiments/seed_spread.py", "--decode", "--runs", *runs]
  argv += ["--md", os.path.join(L.out, f"seed_spread_{col}.md")]
  return Job(f"seed_spread_{col}", argv, "", 60)


def extension_lr(out: str, column: str, rep: str, plan: Plan) -> float | None:
  """Phase 1 of a plan with `extend_grid`: the next lr (x3 beyond the edge) to try with seed 0
  when the lr chosen so far is the lowest or highest of those run, within `extend_grid` lrs
  beyond the plan's grid; None when the choice is inside or the extension is used up."""
  pattern = os.path.join(out, "regression", column, rep, f"*_seed{plan.seeds[0]}")
  sel = C.select(C.load_results([pattern])).get((setting_of(column), rep))
  if sel is None or not plan.extend_grid:
    return None
  grid = plan.lrs[setting_of(column)]
  extra = [lr for lr in sel.scores if lr not in grid]
  edge = C.grid_edge(sel)
  if len(extra) >= plan.extend_grid or edge not in ("lowest", "highest"):
    return None
  return half_decade(sel.lr, up=edge == "highest")


def half_decade(lr: float, *, up: bool) -> float:
  """The next value of the 1, 3, 10, ... grid above (or below) `lr`: 1e-3 -> 3e-3 -> 1e-2."""
  x = math.log10(lr) + (0.5 if up else -0.5)
  k = math.floor(x)
  frac = x - k
  mantissa, k = (1, k) if frac < 0.24 else (3, k) if frac < 0.74 else (1, k + 1)
  return float(f"{mantissa}e{k}")


def table_jobs(out: str, py: str, settings: Sequence[str]) -> list[Job]:
  """table1 / table2 of the settings (each read from its own regression/<setting> runs, so that
  capture columns are not pooled with the car's); one table1_<column>.md per capture column.
  table1.md holds every Table 1 column DIR has runs of, not only this launch's settings: a launch
  of one setting (a chunk, an extension) rewrites it without dropping the others' columns."""
  jobs = []
  t1 = ("car", "gqn", "gibson")
  if any(s in settings for s in t1):
    runs = [os.path.join(out, "regression", s, "*", "*") for s in t1]
    argv = [py, "experiments/table1.py", "--runs", *runs, "--out", os.path.join(out, "table1.md")]
    jobs.append(Job("table1", argv, "", 3))
  if "seven_scenes" in settings:
    runs = os.path.join(out, "regression", "seven_scenes", "*", "*")
    argv = [py, "experiments/table2.py", "--runs", runs, "--out", os.path.join(out, "table2.md")]
    jobs.append(Job("table2", argv, "", 3))
  for col in [c for c in settings if c not in SETTINGS]:
    runs = os.path.join(out, "regression", col, "*", "*")
    md = os.path.join(out, f"table1_{col}.md")
    jobs.append(
      Job(f"table1_{col}", [py, "experiments/table1.py", "--runs", runs, "--out", md], "", 3)
    )
  # Every column in one table: paper, best hand-designed, ours, paired ratio, verdict.
  lead = [py, "experiments/lead_table.py", "--runs", os.path.join(out, "regression")]
  jobs.append(Job("lead_table", [*lead, "--out", os.path.join(out, "lead_table.md")], "", 3))
  return jobs


def figure_jobs(
  out: str, plan: Plan, synth: Sequence[Job], py: str, data: dict | None = None
) -> list[Job]:
  """Noise robustness and Gram maps of every synthesis run (`camrep.synthesis.evaluate`), then one
  noise figure per setting or capture column with several pose inputs
  (experiments/noise_figure.py, if present)."""
  jobs = []
  names = [j.name.removeprefix("synthesis_") for j in synth]
  for name in names:
    wd = os.path.join(out, "synthesis", name)
    argv = [py, "-m", "camrep.synthesis.evaluate", "--workdir", wd]
    done = os.path.join(wd, "eval", "noise.json")
    jobs.append(Job(f"evaluate_{name}", argv, done, plan.evaluate_s))
  script = os.path.join("experiments", "noise_figure.py")
  if os.path.exists(os.path.join(ROOT, script)):
    captures = [c for c, d in (data or {}).items() if isinstance(d, tuple)]
    for setting in [*SETTINGS, *captures]:
      # Pose inputs of the setting (with seeds at converge size: every seed's run, for bands).
      inputs = ("", "_mlp", "_lowdim", "_convdraw")
      group = [n for n in names if n.partition("_seed")[0] in {setting + k for k in inputs}]
      if (
        setting not in {n.partition("_seed")[0] for n in group}
        or len({n.partition("_seed")[0] for n in group}) < 2
      ):
        continue
      argv = [py, script, "--runs", *(os.path.join(out, "synthesis", n) for n in group)]
      if setting in captures:  # "car_chair" -> "chair, car setting"
        base = setting_of(setting)
        argv += ["--column", f"{setting.removeprefix(base + '_')}, {base} setting"]
      argv += ["--png", os.path.join(out, f"noise_{setting}.png")]
      argv += ["--md", os.path.join(out, f"noise_{setting}.md")]
      jobs.append(Job(f"noise_figure_{setting}", argv, "", 10))
  return jobs


def run_job(job: Job, logs: str, *, index: str, env: dict[str, str] | None = None) -> bool:
  """Runs a job (stdout and stderr to logs/<name>.log, environment `env` or this one's); True on
  success."""
  os.makedirs(logs, exist_ok=True)
  log_path = os.path.join(logs, f"{job.name}.log")
  print(
    f"[{index}] {job.name} (est. {progress_lib.format_duration(job.estimate_s)}) ...", flush=True
  )
  t0 = time.perf_counter()
  with open(log_path, "w", encoding="utf-8") as log:
    log.write(f"$ {job.command()}\n")
    log.flush()
    rc = subprocess.call(job.argv, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, env=env)
  took = progress_lib.format_duration(time.perf_counter() - t0)
  if rc == 0:
    print(f"    done in {took}", flush=True)
    return True
  with open(log_path, encoding="utf-8") as f:
    tail = f.read().splitlines()[-8:]
  print(f"    FAILED (exit {rc}) after {took}; {log_path}:", flush=True)
  for line in tail:
    print(f"      {line}", flush=True)
  return False


def job_env(jobs: int) -> dict[str, str] | None:
  """The subprocesses' environment: with `jobs` > 1 at once, each JAX process may take 0.9 / jobs
  of a GPU's memory (XLA_PYTHON_CLIENT_MEM_FRACTION, unless set); None: this one's."""
  if jobs <= 1 or "XLA_PYTHON_CLIENT_MEM_FRACTION" in os.environ:
    return None
  return {**os.environ, "XLA_PYTHON_CLIENT_MEM_FRACTION": f"{0.9 / jobs:.3f}"}


def run_jobs(
  jobs: Sequence[Job],
  logs: str,
  *,
  at_once: int,
  label: str,
  deadline: float | None = None,
  after: Callable[[Job], None] | None = None,
) -> list[str]:
  """Runs the jobs that are not done, `at_once` subprocesses at a time (they must not depend on
  each other); none is started after `deadline` (time.monotonic(); --max_hours), and those are
  not failures (a rerun starts them); `after(job)` is called once a job has succeeded (the
  archive's copy, `--archive`). Returns the names of those that failed."""
  todo = [j for j in jobs if not j.done()]
  for j in jobs:
    if j not in todo:
      print(f"[{label}skipped] {j.name}: done ({j.done_file})", flush=True)
  env = job_env(at_once)

  def one(i_job: tuple[int, Job]) -> str | None:
    i, job = i_job
    if deadline is not None and time.monotonic() > deadline:
      print(f"[{label}{i + 1}/{len(todo)}] {job.name}: not started (--max_hours)", flush=True)
      return None
    ok = run_job(job, logs, index=f"{label}{i + 1}/{len(todo)}", env=env)
    if ok and after is not None:
      after(job)
    return None if ok else job.name

  if at_once <= 1:
    results = [one(x) for x in enumerate(todo)]
  else:
    with concurrent.futures.ThreadPoolExecutor(max_workers=at_once) as pool:
      results = list(pool.map(one, enumerate(todo)))
  return [name for name in results if name]


def chosen_lr(out: str, setting: str, rep: str, plan: Plan) -> float | None:
  """The lr that the phase-1 (seed 0) validation errors choose, or None without results."""
  pattern = os.path.join(out, "regression", setting, rep, f"*_seed{plan.seeds[0]}")
  grid = plan.lrs[setting_of(setting)]
  results = [r for r in C.load_results([pattern]) if plan.extend_grid or float(r["lr"]) in grid]
  sel = C.select(results).get((setting_of(setting), rep))
  return None if sel is None else sel.lr


def plan_regression(
  out: str,
  plan: Plan,
  settings: Sequence[str],
  reps: dict[str, tuple[str, ...]],
  py: str,
  *,
  full_grid: bool,
  data: dict[str, str] | None = None,
) -> tuple[list[Job], list[tuple[str, str, int]]]:
  """(phase-1 jobs, phase-2 (setting, rep, seed) whose lr is chosen after phase 1)."""
  first, later = [], []
  seeds = plan.seeds if full_grid else plan.seeds[:1]
  for s in settings:
    for rep in reps[s]:
      for seed in seeds:
        for lr in plan.lrs[setting_of(s)]:
          first.append(regression_job(out, plan, s, rep, lr, seed, py, data))
      if not full_grid:
        later += [(s, rep, seed) for seed in plan.seeds[1:]]
  return first, later


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--size", choices=sorted(PLANS), default="quick")
  p.add_argument("--out", required=True, help="output directory (synthesis/, regression/, ...)")
  p.add_argument("--dry_run", action="store_true", help="print the commands and estimates only")
  p.add_argument("--settings", default=",".join(SETTINGS), help="comma-separated subset")
  p.add_argument(
    "--representations", default="", help="comma-separated subset (default: per setting)"
  )
  p.add_argument("--full_grid", action="store_true", help="every seed at every learning rate")
  p.add_argument(
    "--skip_figures", action="store_true", help="no camrep.synthesis.evaluate / noise figure"
  )
  p.add_argument(
    "--noise_runs",
    action="store_true",
    help="also train gqn_lowdim, gqn_mlp and (not at medium size) gqn_convdraw synthesis runs for "
    "the GQN noise figure (+~30 min at quick size)",
  )
  p.add_argument(
    "--data",
    action="append",
    default=[],
    metavar="SETTING=DIR",
    help="run SETTING on real data prepared by camrep.data.prepare in DIR (repeatable)",
  )
  p.add_argument(
    "--max_hours",
    type=float,
    default=0.0,
    help="stop launching new runs after this many hours (0: no limit); rerun to resume",
  )
  p.add_argument("--python", default=sys.executable, help="interpreter of the subprocesses")
  p.add_argument(
    "--jobs", type=int, default=1, help="subprocesses at once within each step (GPU: 4 for medium)"
  )
  p.add_argument(
    "--extend_grid",
    type=int,
    default=None,
    metavar="N",
    help="converge size: how many lrs beyond its grid phase 1 may try while seed 0's choice "
    "sits at an edge (default: the plan's, 2); raise it to resume a launch whose choice stayed "
    "at the edge after the plan's extensions",
  )
  p.add_argument(
    "--crossed",
    default="",
    metavar="COLUMN",
    help="converge size: also cross the seeds of COLUMN's ours (every regression seed on every "
    "other synthesis seed, at the chosen lr) and write DIR/seed_spread_COLUMN.md",
  )
  p.add_argument(
    "--archive",
    default="",
    metavar="DIR",
    help="keep each finished run's records (configs, results, curves, errors, noise "
    "evaluations; no checkpoints) in DIR, e.g. results/converge, and start by restoring the runs "
    "DIR holds: a launch cut short resumes on another machine",
  )
  p.add_argument(
    "--noise_kinds",
    default="lowdim,mlp,convdraw",
    help="with --noise_runs: which other GQN pose inputs / generators to train (subset of "
    "lowdim, mlp, convdraw)",
  )
  args = p.parse_args(argv)
  bad_kinds = {k.strip() for k in args.noise_kinds.split(",") if k.strip()} - {
    "lowdim",
    "mlp",
    "convdraw",
  }
  if bad_kinds:
    p.error(f"--noise_kinds: unknown {sorted(bad_kinds)}; choose from lowdim, mlp, convdraw")
  args.settings = [s.strip() for s in args.settings.split(",") if s.strip()]
  bad = set(args.settings) - set(SETTINGS)
  if bad:
    p.error(f"unknown settings {sorted(bad)}; choose from {SETTINGS}")
  if args.jobs < 1:
    p.error(f"--jobs must be at least 1, got {args.jobs}")
  data = {}
  for item in args.data:
    setting, sep, path = item.partition("=")
    if sep and setting.startswith("car_") and setting[4:].isidentifier():
      # A capture column: car_NAME=SOURCE:DIR (a capture prepared with --preset small).
      source, colon, path = path.partition(":")
      if not colon or not source or not path:
        p.error(f"--data {item}: a capture column expects car_NAME=SOURCE:DIR (e.g. nerf:/data)")
      if not os.path.isdir(path):
        p.error(f"--data {item}: {path} is not a directory (prepare it with camrep.data.prepare)")
      data[setting] = (source, os.path.abspath(path))
      continue
    if not sep or setting not in SETTINGS or not path:
      p.error(
        f"--data expects SETTING=DIR with SETTING one of {SETTINGS} (or car_NAME=SOURCE:DIR for "
        f"a capture column), got {item!r}"
      )
    if not os.path.isdir(path):
      p.error(f"--data {item}: {path} is not a directory (prepare it with camrep.data.prepare)")
    data[setting] = os.path.abspath(path)
  args.data = data
  if args.crossed:
    if not PLANS[args.size].paired_synthesis:
      p.error("--crossed needs a size with one synthesis run per seed (--size converge)")
    columns = args.settings + [c for c in data if c not in SETTINGS]
    if args.crossed not in columns or setting_of(args.crossed) not in args.settings:
      p.error(f"--crossed {args.crossed}: not a column of this launch ({columns})")
  return args


@dataclasses.dataclass
class Launch:
  """Every job of one comparison: synthesis and phase-1 regression jobs, phase-2 (setting,
  representation, seed) triples whose lr phase 1 chooses, tables and figures."""

  plan: Plan
  out: str
  python: str
  settings: list[str]
  synth: list[Job]
  first: list[Job]
  later: list[tuple[str, str, int]]
  tables: list[Job]
  figures: list[Job]
  data: dict[str, str] = dataclasses.field(default_factory=dict)
  crossed: str = ""  # --crossed: the column whose ours seeds are crossed
  archive: str = ""  # --archive: where each finished run's records are kept


def make_launch(args: argparse.Namespace) -> Launch:
  plan = PLANS[args.size]
  extend = getattr(args, "extend_grid", None)
  if extend is not None:
    if extend < 0 or not plan.regression_flags:
      raise SystemExit(f"--extend_grid {extend}: a count >= 0, at a size with a stopping rule")
    plan = dataclasses.replace(plan, extend_grid=extend)
  captures = [c for c in getattr(args, "data", {}) if c not in SETTINGS]
  settings = args.settings + [c for c in captures if setting_of(c) in args.settings]
  only = {r.strip() for r in args.representations.split(",") if r.strip()}
  reps = {
    s: tuple(r for r in REPRESENTATIONS[setting_of(s)] if not only or r in only) for s in settings
  }
  out, py = os.path.abspath(args.out), args.python
  kinds = mlp_synthesis_supported()
  names = [s for s in settings if "ours" in reps[s]]
  if kinds:  # the MLP embedding's own synthesis runs, for the car and each capture column
    names += [f"{s}_mlp" for s in settings if setting_of(s) == "car" and "mlp" in reps[s]]
  if kinds and args.noise_runs and "gqn" in settings:
    kinds = [k.strip() for k in args.noise_kinds.split(",") if k.strip()]
    if plan.variant == "medium":  # configs/gqn_convdraw.py has no :medium size yet
      kinds = [k for k in kinds if k != "convdraw"]
    extra = ["gqn", *(f"gqn_{k}" for k in kinds)]
    names += [n for n in extra if n not in names]
  if plan.paired_synthesis:  # one synthesis run per seed, paired with the regression seed
    names = [f"{n}_seed{k}" for n in names for k in plan.seeds]
  data = {s: d for s, d in getattr(args, "data", {}).items() if s in settings}
  synth = synthesis_jobs(out, plan, names, py, data)
  first, later = plan_regression(out, plan, settings, reps, py, full_grid=args.full_grid, data=data)
  tables = table_jobs(out, py, settings)
  figures = [] if args.skip_figures else figure_jobs(out, plan, synth, py, data)
  crossed = getattr(args, "crossed", "")
  if crossed and "ours" not in reps.get(crossed, ()):
    raise SystemExit(f"--crossed {crossed}: the launch runs no ours there (--representations)")
  archive = os.path.abspath(args.archive) if getattr(args, "archive", "") else ""
  return Launch(
    plan, out, py, settings, synth, first, later, tables, figures, data, crossed, archive
  )


def phase2_jobs(launch: Launch) -> list[tuple[tuple[str, str, int], Job]]:
  """Each phase-2 (setting, rep, seed) with its job: at the lr seed 0's validation errors choose
  so far, or the <LR> placeholder while phase 1 has no results (for the plan and its estimate;
  `execute` chooses again once phase 1 and its extensions are done)."""
  L = launch
  out = []
  for s, rep, seed in L.later:
    lr = chosen_lr(L.out, s, rep, L.plan)
    out.append(((s, rep, seed), regression_job(L.out, L.plan, s, rep, lr, seed, L.python, L.data)))
  return out


def print_plan(launch: Launch, size: str, *, commands: bool, at_once: int = 1) -> None:
  """The summary line (runs, estimate of what is not done yet, divided by `at_once` jobs at a
  time: the best case); with `commands`, every job."""
  L, plan = launch, launch.plan
  todo_first = [j for j in L.synth + L.first if not j.done()]
  est = sum(j.estimate_s for j in todo_first)
  later = phase2_jobs(L)
  est += sum(plan.regression_s[setting_of(s)] for (s, _, _), j in later if not j.done())
  cached = os.path.isdir(os.path.join(L.out, "cache"))
  est += sum(plan.data_s[setting_of(s)] for s in L.settings if not cached)
  est += sum(j.estimate_s for j in L.tables + L.figures if not j.done())
  n_runs = len(L.first) + len(L.later)
  where = {
    "quick": " (on 2 CPU cores)",
    "medium": " (one H100; derived, not measured)",
    "converge": " (on 2 CPU cores, from per-step times measured while shared, load 3-9; "
    f"regressions at {CONVERGE_EXPECTED_SHARE:g} of their step caps)",
  }
  at = f", {at_once} jobs at a time at best" if at_once > 1 else ""
  if plan.extend_grid:  # groups whose seed-0 choice is settled inside its grid need none
    settled = all(j.done() for j in L.first)
    groups = {
      g
      for g in map(_group, L.first)
      if not settled or extension_lr(L.out, g[0], g[1], plan) is not None
    }
    worst = len(groups) * plan.extend_grid
    worst_s = sum(plan.regression_s[setting_of(c)] for c, _ in groups) * plan.extend_grid
    at += (
      f"; plus up to {worst} phase-1 runs (up to {progress_lib.format_duration(worst_s)}) "
      "extending an lr grid whose choice is at its edge"
    )
  print(
    f"{size} comparison into {L.out}: {len(L.synth)} view-synthesis runs, {n_runs} regression "
    f"runs ({len(L.first)} in phase 1, {len(L.later)} in phase 2), {len(L.tables)} tables, "
    f"{len(L.figures)} figure steps; estimated {progress_lib.format_duration(est / at_once)} for "
    f"what is not done yet{where.get(size, ' (GPU; rough guess)')}{at}.",
    flush=True,
  )
  for s in L.settings:
    if isinstance(L.data.get(s), tuple):
      where = f"capture prepared as {L.data[s][0]} in {L.data[s][1]} (car setting)"
    elif s in L.data:
      where = f"prepared {REAL_SOURCES[s]} data in {L.data[s]}"
    else:
      where = "its procedural family (configs/regression.py settings)"
    print(f"  data of {s}: {where}", flush=True)
  crossed = crossed_jobs(L, None)
  if crossed:
    est_s = len(crossed) * plan.regression_s[setting_of(L.crossed)] + 60
    print(
      f"  crossed seeds of {L.crossed}'s ours: {len(crossed)} more regression runs, estimated "
      f"{progress_lib.format_duration(est_s)} (not in the estimate above)",
      flush=True,
    )
  if not commands:
    return
  for j in L.synth + L.first:
    state = "done" if j.done() else f"~{progress_lib.format_duration(j.estimate_s)}"
    print(f"[{state}] {j.command()}")
  for (s, _, _), job in later:
    est_s = plan.regression_s[setting_of(s)]
    state = "done" if job.done() else f"~{progress_lib.format_duration(est_s)}"
    print(f"[{state}, phase 2] {job.command()}")
  print("  (phase 2: <LR> = the lr chosen on seed 0's validation errors, where not chosen yet)")
  for job in crossed_jobs(L, None):
    est_s = plan.regression_s[setting_of(L.crossed)]
    print(f"[~{progress_lib.format_duration(est_s)}, crossed] {job.command()}")
  if L.crossed:
    print(
      f"[~1min] experiments/seed_spread.py --decode over {L.out}/crossed/{L.crossed} and the "
      f"paired ours runs at <LR> -> {L.out}/seed_spread_{L.crossed}.md"
    )
  if plan.regression_flags:
    print(
      "[~5s each] experiments/learning_curve.py --bands --metrics eval/validation/score per "
      f"column, runs at the chosen lr -> {L.out}/curve_<column>.{{png,md}}"
    )
  if plan.synthesis_caps:
    print(
      "[~5s each] experiments/learning_curve.py --bands --metrics eval/psnr per column, its "
      f"view-synthesis runs -> {L.out}/curve_synthesis_<column>.{{png,md}} (each run's plateau "
      'record: final_metrics.json "stopping")'
    )
  for j in L.tables + L.figures:
    print(f"[~{progress_lib.format_duration(j.estimate_s)}] {j.command()}")


def execute(launch: Launch, *, at_once: int = 1, deadline: float | None = None) -> list[str]:
  """Runs what is not done yet, seed by seed: seed 0's view-synthesis runs (with their
  noise / Gram evaluations), phase 1 (extended while a chosen lr sits at its grid's edge, when
  the plan allows), then for each later seed its view-synthesis runs and its phase-2 runs at the
  chosen lr; then the crossed runs, tables, curves and noise figures. A plan without one
  synthesis run per seed trains all of them first. `at_once` subprocesses at a time within each
  of these steps; no run is started after `deadline` (time.monotonic()). With an archive
  (`--archive`), each finished run's records are copied into it as soon as the run ends, so a
  launch cut short loses at most the runs in flight, and a view-synthesis run is only needed
  while a run that reads its checkpoints is not done.

  Returns:
    The names of the jobs that failed.
  """
  L = launch
  logs = os.path.join(L.out, "logs")
  after = (lambda job: sync_archive(L.out, L.archive)) if L.archive else None
  kw = dict(at_once=at_once, deadline=deadline, after=after)
  seeds = L.plan.seeds
  failed = run_synthesis(L, synthesis_of_seed(L, seeds[0]), logs, kw)
  failed += run_jobs(L.first, logs, label="phase 1: ", **kw)
  for _ in range(L.plan.extend_grid):
    ext = extension_jobs(L)
    if not ext:
      break
    failed += run_jobs(ext, logs, label="phase 1, lr grid extended: ", **kw)
  for seed in seeds[1:]:
    failed += run_synthesis(L, synthesis_of_seed(L, seed), logs, kw)
    later = []
    for s, rep, k in L.later:
      if k != seed:
        continue
      lr = chosen_lr(L.out, s, rep, L.plan)
      if lr is None:
        print(f"[phase 2] {s}/{rep} seed {k}: no phase-1 results; skipped", flush=True)
        failed.append(f"regression_{s}_{rep}_seed{k}")
        continue
      later.append(regression_job(L.out, L.plan, s, rep, lr, k, L.python, L.data))
    failed += run_jobs(later, logs, label=f"phase 2, seed {seed}: ", **kw)
  if L.crossed:
    lr = chosen_lr(L.out, L.crossed, "ours", L.plan)
    if lr is None:
      print(f"[crossed] {L.crossed}/ours: no phase-1 results; skipped", flush=True)
      failed.append(f"crossed_{L.crossed}")
    else:
      failed += run_jobs(crossed_jobs(L, lr), logs, label="crossed: ", **kw)
      failed += run_jobs([seed_spread_job(L, lr)], logs, label="", **{**kw, "at_once": 1})
  rest = [j for j in L.figures if not j.name.startswith("evaluate_")]
  failed += run_jobs(L.tables + curve_jobs(L) + rest, logs, label="", **{**kw, "at_once": 1})
  if L.archive:
    sync_archive(L.out, L.archive)
  return failed


def synthesis_of_seed(launch: Launch, seed: int) -> list[Job]:
  """The view-synthesis jobs trained before seed `seed`'s regressions: those named
  "<name>_seed<seed>" with one synthesis run per seed, else all of them with the first seed."""
  L = launch
  if not L.plan.paired_synthesis:
    return list(L.synth) if seed == L.plan.seeds[0] else []
  return [j for j in L.synth if j.name.endswith(f"_seed{seed}")]


def extension_jobs(launch: Launch) -> list[Job]:
  """Phase 1's next grid extension: one seed-0 run per (column, representation) whose chosen lr
  sits at its grid's edge (`extension_lr`)."""
  L = launch
  groups = sorted({(s, rep) for s, rep, _ in L.later} | {_group(j) for j in L.first})
  jobs = []
  for col, rep in groups:
    lr = extension_lr(L.out, col, rep, L.plan)
    if lr is not None:
      jobs.append(regression_job(L.out, L.plan, col, rep, lr, L.plan.seeds[0], L.python, L.data))
  return jobs


def run_synthesis(launch: Launch, jobs: Sequence[Job], logs: str, kw: dict) -> list[str]:
  """Trains the view-synthesis `jobs` that are not done, then their noise / Gram evaluations.

  A run whose records came from the archive (complete, without checkpoints) is trained again
  (from scratch: the same numbers on the same kind of CPU) only while a job that reads its
  checkpoints is not done (`pending_synthesis`), else skipped."""
  L = launch
  pending = pending_synthesis(L)
  todo = []
  for j in jobs:
    wd = os.path.dirname(j.done_file)
    if not archived_only(wd):
      todo.append(j)
    elif wd in pending:
      print(
        f"[synthesis] {j.name}: its record is from the archive and a run still needs its "
        "checkpoints; training it again",
        flush=True,
      )
      shutil.rmtree(wd)
      todo.append(j)
    else:
      print(f"[synthesis: skipped] {j.name}: archived, nothing left needs it", flush=True)
  for j in list(todo):
    wd = os.path.dirname(j.done_file)
    if session.is_complete(wd) and not j.done() and not resumable(j.argv):
      # Complete at another length, and its schedules are fractions of its length (ConvDRAW):
      # training on would not give the run the command asks for.
      print(
        f"[synthesis] {j.name}: complete at step {session.read_final(wd).get('step')}, not at "
        f"the {flag_value(j.argv, '--config.total_steps')} steps asked, and its schedules follow "
        "its length; training it again from scratch",
        flush=True,
      )
      shutil.rmtree(wd)
  for j in todo:  # a run that trains on (a raised cap) makes its old evaluation stale
    stale = os.path.join(os.path.dirname(j.done_file), "eval", "noise.json")
    if not j.done() and os.path.exists(stale):
      os.remove(stale)
  failed = run_jobs(todo, logs, label="synthesis: ", **kw)
  names = {j.name.removeprefix("synthesis_") for j in jobs}
  evaluations = [j for j in L.figures if j.name.removeprefix("evaluate_") in names]
  failed += run_jobs(evaluations, logs, label="evaluate: ", **kw)
  return failed


def resumable(argv: Sequence[str]) -> bool:
  """Whether a view-synthesis command may resume a run trained to another length: its
  `--config.allow_changes` names total_steps (the plateau runs), which ConvDRAW's does not."""
  allowed = flag_value(argv, "--config.allow_changes") or ""
  return "total_steps" in allowed.split(",")


def flag_value(argv: Sequence[str], flag: str) -> str | None:
  """The value of the last `flag=VALUE` in argv, or None."""
  values = [a.split("=", 1)[1] for a in argv if a.startswith(flag + "=")]
  return values[-1] if values else None


def pending_synthesis(launch: Launch) -> set[str]:
  """The view-synthesis workdirs that a job not yet done reads (its pose system, noise
  evaluation, crossed runs); a phase-2 run whose lr phase 1 has not chosen yet counts."""
  L = launch
  jobs = list(L.first) + extension_jobs(L) + [job for _, job in phase2_jobs(L)]
  if L.crossed:
    jobs += crossed_jobs(L, chosen_lr(L.out, L.crossed, "ours", L.plan))
  need = set()
  for j in jobs:
    if not j.done():
      flag = "--config.synthesis_workdir="
      need |= {a.removeprefix(flag) for a in j.argv if a.startswith(flag)}
  for j in L.figures:
    if j.name.startswith("evaluate_") and not j.done():
      need.add(j.argv[j.argv.index("--workdir") + 1])
  return need


# --------------------------------------------------------------------------------------------
# The archive (--archive DIR, e.g. results/converge): what a launch keeps of each finished run,
# small enough for git, so that a launch cut short resumes on another machine.

# Files kept per run (paths inside its workdir); never checkpoints, images or TensorBoard files.
ARCHIVED_FILES = (
  "config.json",
  "record.json",
  C.RESULTS_FILE,
  session.FINAL_FILE,
  "metrics.jsonl",
  os.path.join("eval", "noise.json"),
)
ARCHIVED_PATTERNS = ("errors_*.npz",)
# Run workdirs inside a launch's DIR, and the launch's own tables and figures.
RUN_PATTERNS = ("synthesis/*", "regression/*/*/*", "crossed/*/*")
TOP_PATTERNS = ("*.md", "*.png", "*.pdf")


def has_checkpoint(workdir: str) -> bool:
  """Whether a view-synthesis workdir holds a checkpoint (a step directory)."""
  ckpt = os.path.join(workdir, "checkpoints")
  return os.path.isdir(ckpt) and any(n.isdigit() for n in os.listdir(ckpt))


def archived_only(workdir: str) -> bool:
  """A view-synthesis run restored from the archive: complete, without checkpoints."""
  return session.is_complete(workdir) and not has_checkpoint(workdir)


def run_finished(workdir: str) -> bool:
  """A regression run with its results, or a complete view-synthesis run."""
  return os.path.exists(os.path.join(workdir, C.RESULTS_FILE)) or session.is_complete(workdir)


def archived_files(workdir: str) -> list[str]:
  """The files of `workdir` an archive keeps, as paths relative to it."""
  names = [f for f in ARCHIVED_FILES if os.path.isfile(os.path.join(workdir, f))]
  for pattern in ARCHIVED_PATTERNS:
    names += sorted(os.path.basename(p) for p in glob.glob(os.path.join(workdir, pattern)))
  return names


def _copy_if_changed(src: str, dst: str) -> bool:
  """Copies src to dst (through a temporary file and a rename) unless dst has the same bytes."""
  with open(src, "rb") as f:
    data = f.read()
  if os.path.exists(dst):
    with open(dst, "rb") as f:
      if f.read() == data:
        return False
  os.makedirs(os.path.dirname(dst), exist_ok=True)
  tmp = f"{dst}.tmp{os.getpid()}"
  with open(tmp, "wb") as f:
    f.write(data)
  os.replace(tmp, dst)
  return True


def sync_archive(out: str, archive: str) -> int:
  """Copies into `archive` the kept files of every finished run in `out` and the launch's tables
  and figures, where missing or changed; returns how many files it wrote."""
  n = 0
  for pattern in RUN_PATTERNS:
    for wd in sorted(glob.glob(os.path.join(out, pattern))):
      if os.path.isdir(wd) and run_finished(wd):
        rel = os.path.relpath(wd, out)
        for f in archived_files(wd):
          n += _copy_if_changed(os.path.join(wd, f), os.path.join(archive, rel, f))
  for pattern in TOP_PATTERNS:
    for path in sorted(glob.glob(os.path.join(out, pattern))):
      n += _copy_if_changed(path, os.path.join(archive, os.path.basename(path)))
  return n


def restore_archive(archive: str, out: str) -> int:
  """Copies into `out` every archived run that `out` does not hold finished (a view-synthesis
  run only where `out` has no workdir of that name: a partial run there resumes from its own
  checkpoints); returns how many runs it restored."""
  n = 0
  for pattern in RUN_PATTERNS:
    for src in sorted(glob.glob(os.path.join(archive, pattern))):
      rel = os.path.relpath(src, archive)
      dst = os.path.join(out, rel)
      if not os.path.isdir(src) or run_finished(dst):
        continue
      if rel.startswith("synthesis") and os.path.exists(dst):
        continue
      for f in archived_files(src):
        _copy_if_changed(os.path.join(src, f), os.path.join(dst, f))
      n += 1
  return n


def curve_jobs(launch: Launch) -> list[Job]:
  """With a stopping rule (converge): per column, the validation curves of every representation's
  runs at its chosen lr, bands over seeds (experiments/learning_curve.py --bands) into
  DIR/curve_<column>.{png,md}; with the synthesis plateau rule, per setting (and capture column)
  the held-out PSNR curves of its view-synthesis runs, one line per pose input with a band over
  seeds, into DIR/curve_synthesis_<column>.{png,md}."""
  L = launch
  jobs = synthesis_curve_jobs(L)
  if not L.plan.regression_flags:
    return jobs
  for col in sorted({c for c, _ in map(_group, L.first)}):
    runs = []
    for rep in sorted({r for c, r in map(_group, L.first) if c == col}):
      lr = chosen_lr(L.out, col, rep, L.plan)
      if lr is not None:
        pattern = os.path.join(L.out, "regression", col, rep, f"{lr_tag(lr)}_seed*")
        runs += sorted(d for d in glob.glob(pattern) if os.path.isdir(d))
    if not runs:
      continue
    argv = [L.python, "experiments/learning_curve.py", "--bands", "--metrics"]
    argv += ["eval/validation/score", "--runs", *runs, "--title", curve_title(col)]
    argv += ["--png", os.path.join(L.out, f"curve_{col}.png")]
    argv += ["--md", os.path.join(L.out, f"curve_{col}.md")]
    jobs.append(Job(f"curve_{col}", argv, "", 5))
  return jobs


def synthesis_column(name: str, data: dict | None = None) -> str:
  """The column of a view-synthesis run's name ("car_mlp_seed1" -> "car"; a capture column's
  "car_chair_seed0" -> "car_chair")."""
  base = name.partition("_seed")[0]
  cap = capture_of(base, data)
  if cap is not None:
    return cap
  return next(x for x in SETTINGS if base == x or base.startswith(f"{x}_"))


def synthesis_curve_jobs(launch: Launch) -> list[Job]:
  """The held-out PSNR curves of the view-synthesis runs, per column (see `curve_jobs`)."""
  L = launch
  if not L.plan.synthesis_caps:
    return []
  by_column: dict[str, list[str]] = {}
  for j in L.synth:
    name = j.name.removeprefix("synthesis_")
    wd = os.path.join(L.out, "synthesis", name)
    if os.path.isdir(wd):
      by_column.setdefault(synthesis_column(name, L.data), []).append(wd)
  jobs = []
  for col, runs in sorted(by_column.items()):
    argv = [L.python, "experiments/learning_curve.py", "--bands", "--metrics", "eval/psnr"]
    title = f"{col}: held-out PSNR (dB) of the view-synthesis runs; mean of seeds, band min-max"
    argv += ["--runs", *runs, "--title", title]
    argv += ["--png", os.path.join(L.out, f"curve_synthesis_{col}.png")]
    argv += ["--md", os.path.join(L.out, f"curve_synthesis_{col}.md")]
    jobs.append(Job(f"curve_synthesis_{col}", argv, "", 5))
  return jobs


def curve_title(column: str) -> str:
  """The title of a column's validation curves: what the score is, how the bands are made."""
  score = C.validation_score_text(setting_of(column))
  return (
    f"{column}: validation score = {score} (lower is better)\n"
    "each representation at its chosen lr; line = mean of seeds, band = min to max"
  )


def _group(job: Job) -> tuple[str, str]:
  """(column, representation) of a regression job, from its workdir flag."""
  wd = next(a for a in job.argv if a.startswith("--workdir=")).removeprefix("--workdir=")
  parts = wd.split(os.sep)
  return parts[-3], parts[-2]


def _interrupt(signum, frame):
  raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
  args = _parse_args(argv)
  launch = make_launch(args)
  if args.dry_run:
    try:
      print_plan(launch, args.size, commands=True, at_once=args.jobs)
      sys.stdout.flush()
    except BrokenPipeError:  # `--dry_run | head -1`: the reader has what it wanted
      os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0
  if launch.archive:
    n = restore_archive(launch.archive, launch.out)
    print(f"restored {n} finished runs from the archive {launch.archive}", flush=True)
  print_plan(launch, args.size, commands=False, at_once=args.jobs)
  t0 = time.perf_counter()
  deadline = time.monotonic() + 3600 * args.max_hours if args.max_hours > 0 else None
  # SIGTERM (`kill PID`; a launch started with `&` from a script ignores SIGINT) stops it as Ctrl-C.
  old_handler = signal.signal(signal.SIGTERM, _interrupt)
  try:
    failed = execute(launch, at_once=args.jobs, deadline=deadline)
  except KeyboardInterrupt:  # Ctrl-C, `kill`, or `timeout` around a chunk: a stop, not a crash
    took = progress_lib.format_duration(time.perf_counter() - t0)
    kept = f" and archived in {launch.archive}" if launch.archive else ""
    print(
      f"\ninterrupted after {took}: the runs that finished are kept{kept}; the runs in flight "
      "resume from their last checkpoints when the same command is run again",
      file=sys.stderr,
      flush=True,
    )
    return 130
  finally:
    signal.signal(signal.SIGTERM, old_handler)
  took = progress_lib.format_duration(time.perf_counter() - t0)
  if deadline is not None and time.monotonic() > deadline:
    print(
      f"--max_hours {args.max_hours:g} reached after {took}: runs not started; run the same "
      "command again to resume",
      flush=True,
    )
    return 1 if failed else 0
  if failed:
    print(f"finished in {took} with {len(failed)} failures: {', '.join(failed)}", flush=True)
    return 1
  out = launch.out
  print(f"finished in {took}; tables in {out}/table1.md and {out}/table2.md", flush=True)
  return 0


if __name__ == "__main__":
  sys.exit(main())

"""Launch the whole pose-regression comparison (paper Tables 1 and 2; issue 5) as subprocesses.

  python experiments/run_comparison.py --size quick --out DIR [--dry_run]
  python experiments/run_comparison.py --size medium --out DIR --jobs 4 [--dry_run]  # one GPU
  python experiments/run_comparison.py --size paper --out DIR [--dry_run]   # for a GPU
  python experiments/run_comparison.py --size quick --settings seven_scenes \
      --data seven_scenes=PREPARED_DIR --out DIR     # Table 2 from prepared real 7-Scenes

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
  3. tables: experiments/table1.py -> DIR/table1.md, experiments/table2.py -> DIR/table2.md;
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
import os
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence

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
    synthesis_s: estimated seconds per view-synthesis run, per setting.
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
      return session.is_complete(os.path.dirname(self.done_file))
    return True

  def command(self) -> str:
    return shlex.join(self.argv)


def mlp_synthesis_supported() -> bool:
  """Whether the view-synthesis trainer has config.rep.kind (the MLP pose input)."""
  from camrep.configs import common

  return "kind" in common.base().rep


def lr_tag(lr: float) -> str:
  return f"lr{lr:.0e}".replace("e-0", "e-")


def data_flags(setting: str, data: dict[str, str] | None) -> list[str]:
  """The config flags that point a run of `setting` at its prepared real data (none without)."""
  if not data or setting not in data:
    return []
  return [
    f"--config.data.source={REAL_SOURCES[setting]}",
    f"--config.data.dir={data[setting]}",
    "--config.data.preset=default",
  ]


def synthesis_jobs(
  out: str, plan: Plan, names: Sequence[str], py: str, data: dict[str, str] | None = None
) -> list[Job]:
  """View-synthesis runs: "<setting>" (the learned system) or "<setting>_<kind>" (another pose
  input, `--config.rep.kind=<kind>`), into DIR/synthesis/<name>; on the setting's prepared
  real data when `data` names it."""
  suffix = f":{plan.variant}" if plan.variant else ""
  jobs = []
  for name in names:
    setting = next(x for x in SETTINGS if name == x or name.startswith(f"{x}_"))
    kind = name[len(setting) + 1 :]
    wd = os.path.join(out, "synthesis", name)
    if kind == "convdraw":  # GQN's own generator: its config, fed GQN's 7-D pose vector
      argv = [py, "-m", "camrep.main", f"--config=configs/gqn_convdraw.py{suffix}"]
    else:
      argv = [py, "-m", "camrep.main", f"--config={SYNTHESIS_CONFIGS[setting]}{suffix}"]
    argv.append(f"--workdir={wd}")
    if kind and kind != "convdraw":
      argv.append(f"--config.rep.kind={kind}")
    argv += data_flags(setting, data)
    est = plan.synthesis_s[setting]
    jobs.append(Job(f"synthesis_{name}", argv, os.path.join(wd, "final_metrics.json"), est))
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
  suffix = f":{plan.variant}" if plan.variant else ""
  tag = "lr<LR>" if lr is None else lr_tag(lr)
  wd = os.path.join(out, "regression", setting, rep, f"{tag}_seed{seed}")
  argv = [
    py,
    "-m",
    "camrep.regression",
    f"--config=configs/regression.py{suffix}",
    f"--workdir={wd}",
    f"--config.setting={setting}",
    f"--config.representation={rep}",
    f"--config.seed={seed}",
    f"--config.optax.lr={'<LR>' if lr is None else format(lr, 'g')}",
    f"--config.data.cache_dir={os.path.join(out, 'cache')}",
    *data_flags(setting, data),
  ]
  syn = os.path.join(out, "synthesis", setting)
  if rep == "ours":
    argv.append(f"--config.synthesis_workdir={syn}")
  elif rep == "mlp" and mlp_synthesis_supported():
    argv.append(f"--config.synthesis_workdir={syn}_mlp")
  name = f"regression_{setting}_{rep}_{tag}_seed{seed}"
  return Job(name, argv, os.path.join(wd, C.RESULTS_FILE), plan.regression_s[setting])


def table_jobs(out: str, py: str, settings: Sequence[str]) -> list[Job]:
  runs = os.path.join(out, "regression", "*", "*", "*")
  jobs = []
  if set(settings) & {"car", "gqn", "gibson"}:
    argv = [py, "experiments/table1.py", "--runs", runs, "--out", os.path.join(out, "table1.md")]
    jobs.append(Job("table1", argv, "", 3))
  if "seven_scenes" in settings:
    argv = [py, "experiments/table2.py", "--runs", runs, "--out", os.path.join(out, "table2.md")]
    jobs.append(Job("table2", argv, "", 3))
  return jobs


def figure_jobs(out: str, plan: Plan, synth: Sequence[Job], py: str) -> list[Job]:
  """Noise robustness and Gram maps of every synthesis run (`camrep.synthesis.evaluate`), then one noise
  figure per setting with several pose inputs (experiments/noise_figure.py, if present)."""
  jobs = []
  names = [j.name.removeprefix("synthesis_") for j in synth]
  for name in names:
    wd = os.path.join(out, "synthesis", name)
    argv = [py, "-m", "camrep.synthesis.evaluate", "--workdir", wd]
    done = os.path.join(wd, "eval", "noise.json")
    jobs.append(Job(f"evaluate_{name}", argv, done, plan.evaluate_s))
  script = os.path.join("experiments", "noise_figure.py")
  if os.path.exists(os.path.join(ROOT, script)):
    for setting in SETTINGS:
      group = [n for n in names if n == setting or n.startswith(f"{setting}_")]
      if setting not in group or len(group) < 2:
        continue
      argv = [py, script, "--runs", *(os.path.join(out, "synthesis", n) for n in group)]
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


def run_jobs(jobs: Sequence[Job], logs: str, *, at_once: int, label: str) -> list[str]:
  """Runs the jobs that are not done, `at_once` subprocesses at a time (they must not depend on
  each other); returns the names of those that failed."""
  todo = [j for j in jobs if not j.done()]
  for j in jobs:
    if j not in todo:
      print(f"[{label}skipped] {j.name}: done ({j.done_file})", flush=True)
  env = job_env(at_once)

  def one(i_job: tuple[int, Job]) -> str | None:
    i, job = i_job
    ok = run_job(job, logs, index=f"{label}{i + 1}/{len(todo)}", env=env)
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
  results = [r for r in C.load_results([pattern]) if float(r["lr"]) in plan.lrs[setting]]
  sel = C.select(results).get((setting, rep))
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
        for lr in plan.lrs[s]:
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
  p.add_argument("--python", default=sys.executable, help="interpreter of the subprocesses")
  p.add_argument(
    "--jobs", type=int, default=1, help="subprocesses at once within each step (GPU: 4 for medium)"
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
    if not sep or setting not in SETTINGS or not path:
      p.error(f"--data expects SETTING=DIR with SETTING one of {SETTINGS}, got {item!r}")
    if not os.path.isdir(path):
      p.error(f"--data {item}: {path} is not a directory (prepare it with camrep.data.prepare)")
    data[setting] = os.path.abspath(path)
  args.data = data
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


def make_launch(args: argparse.Namespace) -> Launch:
  plan = PLANS[args.size]
  settings = args.settings
  only = {r.strip() for r in args.representations.split(",") if r.strip()}
  reps = {s: tuple(r for r in REPRESENTATIONS[s] if not only or r in only) for s in settings}
  out, py = os.path.abspath(args.out), args.python
  kinds = mlp_synthesis_supported()
  names = [s for s in settings if "ours" in reps[s]]
  if kinds and "mlp" in reps.get("car", ()):
    names.append("car_mlp")
  if kinds and args.noise_runs and "gqn" in settings:
    kinds = [k.strip() for k in args.noise_kinds.split(",") if k.strip()]
    if plan.variant == "medium":  # configs/gqn_convdraw.py has no :medium size yet
      kinds = [k for k in kinds if k != "convdraw"]
    extra = ["gqn", *(f"gqn_{k}" for k in kinds)]
    names += [n for n in extra if n not in names]
  data = {s: d for s, d in getattr(args, "data", {}).items() if s in settings}
  synth = synthesis_jobs(out, plan, names, py, data)
  first, later = plan_regression(out, plan, settings, reps, py, full_grid=args.full_grid, data=data)
  tables = table_jobs(out, py, settings)
  figures = [] if args.skip_figures else figure_jobs(out, plan, synth, py)
  return Launch(plan, out, py, settings, synth, first, later, tables, figures, data)


def print_plan(launch: Launch, size: str, *, commands: bool, at_once: int = 1) -> None:
  """The summary line (runs, estimate of what is not done yet, divided by `at_once` jobs at a
  time: the best case); with `commands`, every job."""
  L, plan = launch, launch.plan
  todo_first = [j for j in L.synth + L.first if not j.done()]
  est = sum(j.estimate_s for j in todo_first) + sum(plan.regression_s[s] for s, _, _ in L.later)
  est += sum(plan.data_s[s] for s in L.settings if not os.path.isdir(os.path.join(L.out, "cache")))
  est += sum(j.estimate_s for j in L.tables + L.figures if not j.done())
  n_runs = len(L.first) + len(L.later)
  where = {"quick": " (on 2 CPU cores)", "medium": " (one H100; derived, not measured)"}
  at = f", {at_once} jobs at a time at best" if at_once > 1 else ""
  print(
    f"{size} comparison into {L.out}: {len(L.synth)} view-synthesis runs, {n_runs} regression "
    f"runs ({len(L.first)} in phase 1, {len(L.later)} in phase 2), {len(L.tables)} tables, "
    f"{len(L.figures)} figure steps; estimated {progress_lib.format_duration(est / at_once)} for "
    f"what is not done yet{where.get(size, ' (GPU; rough guess)')}{at}.",
    flush=True,
  )
  for s in L.settings:
    where = (
      f"prepared {REAL_SOURCES[s]} data in {L.data[s]}"
      if s in L.data
      else "its procedural family (configs/regression.py settings)"
    )
    print(f"  data of {s}: {where}", flush=True)
  if not commands:
    return
  for j in L.synth + L.first:
    state = "done" if j.done() else f"~{progress_lib.format_duration(j.estimate_s)}"
    print(f"[{state}] {j.command()}")
  for s, rep, seed in L.later:
    job = regression_job(L.out, plan, s, rep, None, seed, L.python, L.data)
    print(f"[~{progress_lib.format_duration(plan.regression_s[s])}, phase 2] {job.command()}")
  print("  (phase 2: <LR> = the lr chosen on seed 0's validation errors)")
  for j in L.tables + L.figures:
    print(f"[~{progress_lib.format_duration(j.estimate_s)}] {j.command()}")


def execute(launch: Launch, *, at_once: int = 1) -> list[str]:
  """Runs what is not done yet, in order: view synthesis, phase 1, phase 2 at the chosen lr,
  tables, figures; `at_once` subprocesses at a time within each of these steps.

  Returns:
    The names of the jobs that failed.
  """
  L = launch
  logs = os.path.join(L.out, "logs")
  failed = run_jobs(L.synth, logs, at_once=at_once, label="synthesis: ")
  failed += run_jobs(L.first, logs, at_once=at_once, label="phase 1: ")
  later = []
  for s, rep, seed in L.later:
    lr = chosen_lr(L.out, s, rep, L.plan)
    if lr is None:
      print(f"[phase 2] {s}/{rep} seed {seed}: no phase-1 results; skipped", flush=True)
      failed.append(f"regression_{s}_{rep}_seed{seed}")
      continue
    later.append(regression_job(L.out, L.plan, s, rep, lr, seed, L.python, L.data))
  failed += run_jobs(later, logs, at_once=at_once, label="phase 2: ")
  failed += run_jobs(L.tables, logs, at_once=1, label="")
  evaluations = [j for j in L.figures if j.name.startswith("evaluate_")]
  failed += run_jobs(evaluations, logs, at_once=at_once, label="evaluate: ")
  rest = [j for j in L.figures if j not in evaluations]
  failed += run_jobs(rest, logs, at_once=1, label="")
  return failed


def main(argv: Sequence[str] | None = None) -> int:
  args = _parse_args(argv)
  launch = make_launch(args)
  print_plan(launch, args.size, commands=args.dry_run, at_once=args.jobs)
  if args.dry_run:
    return 0
  t0 = time.perf_counter()
  failed = execute(launch, at_once=args.jobs)
  took = progress_lib.format_duration(time.perf_counter() - t0)
  if failed:
    print(f"finished in {took} with {len(failed)} failures: {', '.join(failed)}", flush=True)
    return 1
  out = launch.out
  print(f"finished in {took}; tables in {out}/table1.md and {out}/table2.md", flush=True)
  return 0


if __name__ == "__main__":
  sys.exit(main())

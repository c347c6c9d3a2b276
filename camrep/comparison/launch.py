"""The comparison's jobs and their execution: what runs, in which order, and what is done.

Every run is a subprocess (`python -m camrep.main`, `python -m camrep.regression`, the table and
figure readers in experiments/) started in the checkout's root with its output in
DIR/logs/<name>.log; a job is done when its run's record says so (`camrep.regression.runs`),
so a launch that stops resumes where it stopped. Order (`execute`): seed by seed, so that a cut
loses little: seed 0's view-synthesis runs and their evaluations, phase 1 (seed 0 at every lr,
extended while a choice sits at its grid's edge), then for each later seed its view-synthesis
runs and its phase-2 runs at the chosen lr; then crossed runs, tables, curves and figures. The
full grid (`--full_grid`, the protocol size) has no phase 2: every seed's view synthesis comes
before phase 1, which reads them all.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import glob
import math
import os
import pathlib
import shlex
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Sequence

from camrep import pose_encodings
from camrep.comparison import archive as archive_lib
from camrep.comparison import plan as plan_lib
from camrep.regression import runs
from camrep.regression import tables as C
from camrep.runtime import progress as progress_lib
from camrep.runtime import xla_cpu
from camrep.synthesis import restore as restore_lib

ROOT = str(pathlib.Path(__file__).resolve().parents[2])
SETTINGS = plan_lib.SETTINGS
# Seconds a stopped run (Ctrl-C, SIGTERM) gets to save its checkpoint before it is killed.
STOP_GRACE_S = 60.0
_STOPPING = threading.Event()


@dataclasses.dataclass
class Job:
  """One subprocess: a name (its log file), argv, the workdir whose record marks it done (""
  for tables and figures, which always run), what kind of job it is, and an estimate. A
  regression grid (runs trained as one program, `camrep.regression.vectorised`) has the workdirs
  of its runs in `members` (its workdir is theirs' parent)."""

  name: str
  argv: list[str]
  workdir: str
  estimate_s: float
  kind: str = "table"  # "synthesis", "regression", "evaluate" or "table"
  members: tuple[str, ...] = ()

  @property
  def workdirs(self) -> tuple[str, ...]:
    """The workdirs of its runs: its members, else its own (none for tables and figures)."""
    return self.members or ((self.workdir,) if self.workdir else ())

  def done(self) -> bool:
    """Whether the job's run is finished and readable: a regression run's results (every
    member's, for a grid); a view-synthesis run complete at the step cap its command gives (or
    stopped earlier by its plateau rule); an evaluation's noise curve."""
    if self.members:
      return all(damage(w) is None and runs.is_finished(w) for w in self.members)
    if not self.workdir or self.kind == "table" or damage(self.workdir) is not None:
      return False
    if self.kind == "regression":
      return runs.is_finished(self.workdir)
    final = read_final(self.workdir)
    if self.kind == "synthesis":
      return synthesis_done(final, self.argv, trained_cap(self.workdir))
    return _noise(self.workdir) is not None

  def command(self) -> str:
    return shlex.join(self.argv)


_DAMAGE: dict[str, tuple[tuple, runs.DamagedRun | None]] = {}


def _signature(workdir: str) -> tuple:
  """The names, sizes and times of a workdir's files: what `damage` is cached on."""
  out = []
  for d in (workdir, os.path.join(workdir, "eval")):
    if os.path.isdir(d):
      for e in sorted(os.scandir(d), key=lambda e: e.name):
        if e.is_file():
          st = e.stat()
          out.append((d, e.name, st.st_size, st.st_mtime_ns))
  return tuple(out)


def damage(workdir: str) -> runs.DamagedRun | None:
  """`runs.damage` of a workdir, cached while its files are unchanged."""
  sig = _signature(workdir)
  hit = _DAMAGE.get(workdir)
  if hit is None or hit[0] != sig:
    hit = _DAMAGE[workdir] = (sig, runs.damage(workdir))
  return hit[1]


def read_final(workdir: str) -> dict:
  """A view-synthesis run's final record ({} without one or when it cannot be read)."""
  try:
    run = runs.load(workdir)
  except (FileNotFoundError, runs.DamagedRun):
    return {}
  return run.final or {}


def _noise(workdir: str) -> dict | None:
  try:
    return runs.load(workdir).noise
  except (FileNotFoundError, runs.DamagedRun):
    return None


def synthesis_done(final: dict, argv: Sequence[str], trained: int | None = None) -> bool:
  """A view-synthesis run is done when complete at the step cap its command gives
  (`--config.total_steps`), or stopped earlier by its plateau rule under that cap (`trained`, the
  cap it ran under; None where its record does not say: taken as that cap): a raised cap resumes
  a run that reached the old one; one that stopped at its plateau under another cap is stale
  (`stale_runs`: its rule's window and evaluations follow the cap)."""
  if final.get("complete") is not True:
    return False
  cap = flag_value(argv, "--config.total_steps")
  if cap is None:
    return True
  if (final.get("stopping") or {}).get("stopped_early"):
    return trained is None or trained == int(cap)
  return final.get("step") == int(cap)


def trained_cap(workdir: str) -> int | None:
  """The step cap a view-synthesis run last trained under: its config's total_steps, or the
  last change of it its final record lists (a resume with a raised cap); None without a
  readable record that says."""
  try:
    run = runs.load(workdir)
  except (FileNotFoundError, runs.DamagedRun):
    return None
  cap = run.config.get("total_steps")
  for change in (run.final or {}).get("config_changes") or []:
    if "total_steps" in (change.get("changes") or {}):
      cap = change["changes"]["total_steps"][1]
  return None if cap is None else int(cap)


def flag_value(argv: Sequence[str], flag: str) -> str | None:
  """The value of the last `flag=VALUE` in argv, or None."""
  values = [a.split("=", 1)[1] for a in argv if a.startswith(flag + "=")]
  return values[-1] if values else None


def resumable(argv: Sequence[str]) -> bool:
  """Whether a view-synthesis command may resume a run trained to another length: its
  `--config.allow_changes` names total_steps (the plateau runs), which ConvDRAW's does not."""
  return "total_steps" in (flag_value(argv, "--config.allow_changes") or "").split(",")


def has_checkpoint(workdir: str) -> bool:
  """Whether a view-synthesis workdir holds a checkpoint (a step directory)."""
  ckpt = os.path.join(workdir, "checkpoints")
  return os.path.isdir(ckpt) and any(n.isdigit() for n in os.listdir(ckpt))


def archived_only(workdir: str) -> bool:
  """A view-synthesis run restored from an archive: complete, without checkpoints."""
  return read_final(workdir).get("complete") is True and not has_checkpoint(workdir)


def setting_of(column: str) -> str:
  """The setting of a table column: the setting itself, or "car" for a capture column
  "car_<NAME>" (`--data car_NAME=SOURCE:DIR`)."""
  return column if column in SETTINGS else column.split("_", 1)[0]


lr_tag = runs.lr_tag


def capture_of(name: str, data: dict | None) -> str | None:
  """The capture column a view-synthesis name belongs to ("car_chair" or "car_chair_mlp" ->
  "car_chair"; the longest capture column it starts with), or None for a setting's own."""
  caps = [c for c, d in (data or {}).items() if isinstance(d, tuple)]
  hits = [c for c in caps if name == c or name.startswith(f"{c}_")]
  return max(hits, key=len) if hits else None


def data_flags(column: str, data: dict | None) -> list[str]:
  """The config flags that point a run of a setting (or capture column) at its prepared real
  data (none without); a capture column's value is (source, dir), prepared with --preset small."""
  if not data or column not in data:
    return []
  if isinstance(data[column], tuple):
    source, path = data[column]
    return [f"--config.data.source={source}", f"--config.data.dir={path}"]
  return [
    f"--config.data.source={plan_lib.real_source(column)}",
    f"--config.data.dir={data[column]}",
    "--config.data.preset=default",
  ]


@dataclasses.dataclass
class Launch:
  """Every job of one comparison: synthesis and phase-1 regression jobs, phase-2 (column,
  representation, seed) triples whose lr phase 1 chooses, tables and figures."""

  plan: plan_lib.Plan
  out: str
  python: str
  settings: list[str]
  synth: list[Job]
  first: list[Job]
  later: list[tuple[str, str, int]]
  tables: list[Job]
  figures: list[Job]
  data: dict = dataclasses.field(default_factory=dict)
  crossed: str = ""  # --crossed: the column whose ours seeds are crossed
  archive: str = ""  # --archive: where each finished run's record is kept


def synthesis_jobs(
  out: str, plan: plan_lib.Plan, names: Sequence[str], py: str, data: dict | None = None
) -> list[Job]:
  """View-synthesis runs "<setting>[_<kind>][_seed<k>]" (the learned system, another pose input
  `--config.rep.kind=<kind>`, or "frozen_gen": the learned system with
  `--config.rep.freeze_generators=True`; a capture column's "car_<NAME>[_<kind>]"), into
  DIR/synthesis/<name>, on the prepared real data `data` names, with the plan's extra flags of
  the setting on its procedural data, or of a capture column (`Plan.synthesis_extra`)."""
  jobs = []
  for full in names:
    name, _, seed = full.partition("_seed")
    setting = next(x for x in SETTINGS if name == x or name.startswith(f"{x}_"))
    kind = name[len(setting) + 1 :]
    cap = capture_of(name, data)
    if cap is not None:  # a capture column: the car setting on the capture, one instance a step
      kind = name[len(cap) + 1 :]  # "" (the learned system), "mlp" or "frozen_gen"
    wd = os.path.join(out, "synthesis", full)
    if kind == "convdraw":  # GQN's own generator, fed GQN's low-dimensional pose vector
      config = plan.convdraw_config(setting)
      if config is None:
        raise ValueError(f"{full}: GQN's generator has no config at --size {plan.name}")
    else:
      config = plan_lib.settings()[setting]["synthesis_config"] + plan.suffix
    argv = [py, "-m", "camrep.main", f"--config={config}", f"--workdir={wd}"]
    if kind == plan_lib.FROZEN_GENERATORS:
      argv.append("--config.rep.freeze_generators=True")
    elif kind and kind != "convdraw":
      argv.append(f"--config.rep.kind={kind}")
    if cap is not None:
      argv += plan_lib.capture_synthesis_flags(plan)
    elif kind != "convdraw" and not data_flags(setting, data):  # procedural data only
      argv += list(plan.synthesis_extra.get(setting, ()))
    argv += data_flags(cap or setting, data)
    if cap is not None:
      argv.append("--config.data.scenes_per_device=1")
    if seed:
      argv.append(f"--config.seed={seed}")
    argv += plan_lib.synthesis_flags(plan, setting, kind)
    est = plan.synthesis_s.get(f"{setting}_{kind}", plan.synthesis_s[setting])
    if cap is not None:
      est = plan.synthesis_s.get("capture", est)
    jobs.append(Job(f"synthesis_{full}", argv, wd, est, "synthesis"))
  return jobs


def regression_job(
  out: str,
  plan: plan_lib.Plan,
  column: str,
  rep: str,
  lr: float | None,
  seed: int,
  py: str,
  data: dict | None = None,
) -> Job:
  """One regression run's job (lr None: a placeholder "<LR>", for --dry_run's phase 2), on the
  column's prepared real data when `data` names it."""
  tag = "lr<LR>" if lr is None else lr_tag(lr)
  setting = setting_of(column)
  wd = os.path.join(out, "regression", column, rep, f"{tag}_seed{seed}")
  argv = [
    py,
    "-m",
    "camrep.regression",
    f"--config=configs/regression.py:{setting}{plan.suffix.replace(':', ',')}",
    f"--workdir={wd}",
    f"--config.representation={rep}",
    f"--config.seed={seed}",
    f"--config.optax.lr={'<LR>' if lr is None else format(lr, 'g')}",
    f"--config.data.cache_dir={os.path.join(out, 'cache')}",
    *data_flags(column, data),
    *plan_lib.regression_flags(plan, setting),
  ]
  syn = os.path.join(out, "synthesis", column)
  pair = f"_seed{seed}" if plan.paired_synthesis else ""
  suffix = plan_lib.synthesis_suffix(rep)
  if suffix is not None:  # ours and its controls, mlp: the run of their pose input
    argv.append(f"--config.synthesis_workdir={syn}{suffix}{pair}")
  name = f"regression_{column}_{rep}_{tag}_seed{seed}"
  return Job(name, argv, wd, plan.regression_s[setting], "regression")


def regression_grid_job(
  out: str,
  plan: plan_lib.Plan,
  column: str,
  rep: str,
  lrs: Sequence[float] | None,
  seeds: Sequence[int],
  py: str,
  data: dict | None = None,
) -> Job:
  """The regression runs of one column and representation at `lrs` x `seeds` trained as one
  program (`python -m camrep.regression --lrs --seeds`, `camrep.regression.vectorised`), each into
  the workdir its own run would have (lrs None: the "<LR>" placeholder of --dry_run's phase 2);
  an "ours" or "mlp" member reads the synthesis run of its seed where the plan pairs them."""
  one = regression_job(out, plan, column, rep, None, seeds[0], py, data)
  drop = ("--workdir=", "--config.seed=", "--config.optax.lr=", "--config.synthesis_workdir=")
  argv = [a for a in one.argv if not a.startswith(drop)]
  group = os.path.join(out, "regression", column, rep)
  tags = ["lr<LR>"] if lrs is None else [lr_tag(x) for x in lrs]
  argv[4:4] = [
    f"--workdir={group}",
    f"--lrs={'<LR>' if lrs is None else ','.join(format(x, 'g') for x in lrs)}",
    f"--seeds={','.join(str(k) for k in seeds)}",
  ]
  syn = flag_value(one.argv, "--config.synthesis_workdir")
  if syn is not None:
    if plan.paired_synthesis:
      syn = syn.removesuffix(f"_seed{seeds[0]}") + "_seed{seed}"
    argv.append(f"--config.synthesis_workdir={syn}")
  members = tuple(os.path.join(group, f"{t}_seed{k}") for t in tags for k in seeds)
  name = f"regression_{column}_{rep}_{'-'.join(tags)}_seed{'-'.join(map(str, seeds))}"
  est = plan_lib.group_s(plan, setting_of(column), len(members))
  return Job(name, argv, group, est, "regression", members)


def synthesis_reads(job: Job) -> set[str]:
  """The view-synthesis workdirs a regression job reads (each member's seed's for a grid whose
  --config.synthesis_workdir holds {seed})."""
  v = flag_value(job.argv, "--config.synthesis_workdir")
  if v is None:
    return set()
  seeds = (flag_value(job.argv, "--seeds") or "").split(",")
  return {v.replace("{seed}", k) for k in seeds} if "{seed}" in v else {v}


def checkpoint_reads(job: Job) -> set[str]:
  """The view-synthesis workdirs whose checkpoints a regression job reads: `synthesis_reads`, but
  not those holding what it reads without them (`pose_system.restore_pose_system`): config.json
  with the run's final pose system (pose_system.npz, an archive's), or for a representation read
  at its initial state ("untrained") config.json alone."""
  reads = synthesis_reads(job)
  rep = flag_value(job.argv, "--config.representation")
  initial = bool(reads and rep and pose_encodings.get(rep).initial_state)

  def enough(w: str) -> bool:
    has = lambda name: os.path.isfile(os.path.join(w, name))
    return has(runs.CONFIG_FILE) and (initial or has(restore_lib.POSE_FILE))

  return {w for w in reads if not enough(w)}


def crossed_job(
  launch: Launch, column: str, lr: float | None, seed: int, synthesis_seed: int
) -> Job:
  """A crossed "ours" run (`--crossed`): regression seed `seed` on the pose system of synthesis
  seed `synthesis_seed`, into DIR/crossed/<column>/<lr>_seed<k>_syn<j> (outside regression/, so
  the tables never pool it with the paired runs)."""
  L = launch
  job = regression_job(L.out, L.plan, column, "ours", lr, seed, L.python, L.data)
  tag = "lr<LR>" if lr is None else lr_tag(lr)
  wd = os.path.join(L.out, "crossed", column, f"{tag}_seed{seed}_syn{synthesis_seed}")
  syn = os.path.join(L.out, "synthesis", f"{column}_seed{synthesis_seed}")
  swap = {
    "--workdir=": f"--workdir={wd}",
    "--config.synthesis_workdir=": f"--config.synthesis_workdir={syn}",
  }
  argv = [next((v for k, v in swap.items() if a.startswith(k)), a) for a in job.argv]
  name = f"crossed_{column}_{tag}_seed{seed}_syn{synthesis_seed}"
  return Job(name, argv, wd, job.estimate_s, "regression")


def crossed_jobs(launch: Launch, lr: float | None) -> list[Job]:
  """Every (regression seed k, synthesis seed j != k) run of the `--crossed` column at `lr`
  (None: the placeholder of --dry_run); the paired runs (j = k) are the launch's own."""
  if not launch.crossed:
    return []
  seeds = launch.plan.seeds_for(setting_of(launch.crossed))
  return [crossed_job(launch, launch.crossed, lr, k, j) for k in seeds for j in seeds if j != k]


def seed_spread_job(launch: Launch, lr: float) -> Job:
  """experiments/seed_spread.py over the crossed runs and the paired ones at `lr`, with the
  decoding error of each pose system, into DIR/seed_spread_<column>.md."""
  L, col = launch, launch.crossed
  runs_ = [
    os.path.join(L.out, "crossed", col, f"{lr_tag(lr)}_seed*_syn*"),
    os.path.join(L.out, "regression", col, "ours", f"{lr_tag(lr)}_seed*"),
  ]
  argv = [L.python, "experiments/seed_spread.py", "--decode", "--runs", *runs_]
  return Job(
    f"seed_spread_{col}", [*argv, "--md", os.path.join(L.out, f"seed_spread_{col}.md")], "", 60
  )


def chosen_lr(out: str, column: str, rep: str, plan: plan_lib.Plan) -> float | None:
  """The lr that the phase-1 (seed 0) validation errors choose; with a full grid
  (`plan.full_grid`: every seed ran at every lr), the one the validation mean over the seeds
  chooses, as the tables choose it (`tables.select`). None without results."""
  seeds = "*" if plan.full_grid else plan.seeds[0]
  pattern = os.path.join(out, "regression", column, rep, f"*_seed{seeds}")
  grid = plan.lrs[setting_of(column)]
  results = [r for r in _results([pattern]) if plan.extend_grid or float(r["lr"]) in grid]
  sel = C.select(results).get((setting_of(column), rep))
  return None if sel is None else sel.lr


def _results(patterns: Sequence[str]) -> list[dict]:
  """The readable results matching `patterns` (a damaged run is not finished: it trains again)."""
  return C.load_results(patterns, skip_damaged=True, warn=lambda m: None)


def extension_lr(out: str, column: str, rep: str, plan: plan_lib.Plan) -> float | None:
  """Phase 1 of a plan with `extend_grid`: the next lr (x3 beyond the edge) to try with seed 0
  when the lr chosen so far is the lowest or highest of those run, within `extend_grid` lrs
  beyond the plan's grid; None when the choice is inside or the extension is used up."""
  pattern = os.path.join(out, "regression", column, rep, f"*_seed{plan.seeds[0]}")
  sel = C.select(_results([pattern])).get((setting_of(column), rep))
  if sel is None or not plan.extend_grid:
    return None
  extra = [lr for lr in sel.scores if lr not in plan.lrs[setting_of(column)]]
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
  of one setting (a chunk, an extension) rewrites it without dropping the others' columns. So do
  the lead table and the claims table (`experiments/claims_table.py`: DIR's regression and
  view-synthesis runs)."""
  jobs = []
  for table in ("table1", "table2"):
    # Every column of the table DIR may hold, read from its own regression/<setting> runs.
    of_table = [s for s, v in plan_lib.settings().items() if v["table"] == table]
    if any(s in settings for s in of_table):
      runs_ = [os.path.join(out, "regression", s, "*", "*") for s in of_table]
      md = os.path.join(out, f"{table}.md")
      jobs.append(Job(table, [py, f"experiments/{table}.py", "--runs", *runs_, "--out", md], "", 3))
  for col in [c for c in settings if c not in SETTINGS]:
    runs_ = os.path.join(out, "regression", col, "*", "*")
    md = os.path.join(out, f"table1_{col}.md")
    jobs.append(
      Job(f"table1_{col}", [py, "experiments/table1.py", "--runs", runs_, "--out", md], "", 3)
    )
  lead = [py, "experiments/lead_table.py", "--runs", os.path.join(out, "regression")]
  jobs.append(Job("lead_table", [*lead, "--out", os.path.join(out, "lead_table.md")], "", 3))
  claims = [py, "-m", "experiments.claims_table", "--records", out]  # imports experiments/
  jobs.append(Job("claims", [*claims, "--out", os.path.join(out, "claims.md")], "", 3))
  return jobs


def finished_synthesis(out: str, *, evaluated: bool = False) -> list[str]:
  """The names of the complete view-synthesis runs in DIR/synthesis (this launch's, an earlier
  launch's, or restored from an archive), sorted; `evaluated`: only those with a noise test."""
  root = os.path.join(out, "synthesis")
  if not os.path.isdir(root):
    return []
  return [
    n
    for n in sorted(os.listdir(root))
    if read_final(os.path.join(root, n)).get("complete") is True
    and (not evaluated or _noise(os.path.join(root, n)) is not None)
  ]


def _input_rank(column: str) -> dict[str, int]:
  """The place of each pose input of a column's view-synthesis runs ("<column>[_kind]" -> rank),
  in the order a full launch names them: ours, the MLP embedding where it is one of the column's
  representations, the grid with frozen generators (the control), then
  `plan_lib.NOISE_INPUTS`."""
  reps = plan_lib.settings()[setting_of(column)]["representations"]
  kinds = ["", *(["_mlp"] if "mlp" in reps else []), f"_{plan_lib.FROZEN_GENERATORS}"]
  kinds += [f"_{k}" for k in plan_lib.NOISE_INPUTS]
  return {column + k: i for i, k in enumerate(dict.fromkeys(kinds))}


def _in_order(names: Sequence[str], rank: dict[str, int]) -> list[str]:
  """The runs among `names` whose "<base>" (before "_seed") `rank` places, in its order, seed by
  seed, each once."""
  picked = [n for n in dict.fromkeys(names) if n.partition("_seed")[0] in rank]
  return sorted(picked, key=lambda n: (rank[n.partition("_seed")[0]], _seed_of(n)))


def _seed_of(name: str) -> int:
  """The seed of a run name "<base>_seed<k>" (0 without one)."""
  return int(name.partition("_seed")[2] or 0)


def figure_jobs(
  out: str, plan: plan_lib.Plan, synth: Sequence[Job], py: str, data: dict | None = None
) -> list[Job]:
  """Noise robustness and Gram maps of every synthesis run (`camrep.synthesis.evaluate`), then one
  noise figure per setting or capture column with several pose inputs, the frozen-generator
  control among them (experiments/noise_figure.py). A column's figure also draws the evaluated
  runs DIR holds beyond the launch's (`finished_synthesis`), so that a launch of one
  `--noise_kinds` does not redraw it without the pose inputs trained before (`execute` builds
  these jobs again after its runs, to draw what they added)."""
  jobs = []
  names = [j.name.removeprefix("synthesis_") for j in synth]
  others = finished_synthesis(out, evaluated=True)
  for name in names:
    wd = os.path.join(out, "synthesis", name)
    argv = [py, "-m", "camrep.synthesis.evaluate", "--workdir", wd]
    jobs.append(Job(f"evaluate_{name}", argv, wd, plan.evaluate_s, "evaluate"))
  captures = [c for c, d in (data or {}).items() if isinstance(d, tuple)]
  for column in [*SETTINGS, *captures]:
    # The column's pose inputs (with seeds at converge size: every seed's run, for bands).
    rank = _input_rank(column)
    if not _in_order(names, rank):
      continue  # the launch trains none of the column's pose inputs
    group = _in_order([*names, *others], rank)
    kinds = {n.partition("_seed")[0] for n in group}
    if column not in kinds or len(kinds) < 2:
      continue
    argv = [py, "experiments/noise_figure.py", "--runs"]
    argv += [os.path.join(out, "synthesis", n) for n in group]
    if column in captures:  # "car_chair" -> "chair, car setting"
      base = setting_of(column)
      argv += ["--column", f"{column.removeprefix(base + '_')}, {base} setting"]
    argv += ["--png", os.path.join(out, f"noise_{column}.png")]
    argv += ["--md", os.path.join(out, f"noise_{column}.md")]
    jobs.append(Job(f"noise_figure_{column}", argv, "", 10))
  return jobs


def _group(job: Job) -> tuple[str, str]:
  """(column, representation) of a regression job, from its (first run's) workdir."""
  parts = job.workdirs[0].split(os.sep)
  return parts[-3], parts[-2]


def curve_title(column: str) -> str:
  """The title of a column's validation curves: what the score is, how the bands are made."""
  score = C.validation_score_text(setting_of(column))
  return (
    f"{column}: validation score = {score} (lower is better)\n"
    "each representation at its chosen lr; line = mean of seeds, band = min to max"
  )


def synthesis_column(name: str, data: dict | None = None) -> str:
  """The column of a view-synthesis run's name ("car_mlp_seed1" -> "car"; a capture column's
  "car_chair_seed0" -> "car_chair")."""
  base = name.partition("_seed")[0]
  return capture_of(base, data) or next(
    x for x in SETTINGS if base == x or base.startswith(f"{x}_")
  )


def curve_jobs(launch: Launch) -> list[Job]:
  """With a stopping rule: per column, the validation curves of every representation's runs at
  its chosen lr, bands over seeds (experiments/learning_curve.py --bands) into
  DIR/curve_<column>.{png,md}; and per column the held-out PSNR curves of its view-synthesis
  runs, one line per pose input with a band over seeds, into DIR/curve_synthesis_<column>."""
  L = launch
  jobs = []
  if L.plan.synthesis_caps:
    # Per column, the launch's runs with a workdir and every complete run DIR holds of the same
    # pose inputs (a launch of one --noise_kinds draws the column's other inputs too).
    names = [j.name.removeprefix("synthesis_") for j in L.synth if os.path.isdir(j.workdir)]
    by_column: dict[str, list[str]] = {}
    for name in names:
      by_column.setdefault(synthesis_column(name, L.data), []).append(name)
    others = finished_synthesis(L.out)
    for col in sorted(by_column):
      rank, mine = _input_rank(col), by_column[col]
      unranked = [n for n in mine if n.partition("_seed")[0] not in rank]
      ordered = [*_in_order([*mine, *others], rank), *unranked]
      wds = [os.path.join(L.out, "synthesis", n) for n in ordered]
      title = f"{col}: held-out PSNR (dB) of the view-synthesis runs; mean of seeds, band min-max"
      argv = [L.python, "experiments/learning_curve.py", "--bands", "--metrics", "eval/psnr"]
      argv += ["--runs", *wds, "--title", title]
      argv += ["--png", os.path.join(L.out, f"curve_synthesis_{col}.png")]
      argv += ["--md", os.path.join(L.out, f"curve_synthesis_{col}.md")]
      jobs.append(Job(f"curve_synthesis_{col}", argv, "", 5))
  if not L.plan.stop:
    return jobs
  groups = [_group(j) for j in L.first]
  for col in sorted({c for c, _ in groups}):
    wds = []
    # Every representation DIR has runs of in the column, not only this launch's (a launch of
    # one representation redraws the column's whole curve): the plan's order, then the rest.
    ranked = [*plan_lib.settings()[setting_of(col)]["representations"], *L.plan.controls]
    have = {os.path.basename(d) for d in glob.glob(os.path.join(L.out, "regression", col, "*"))}
    have |= {r for c, r in groups if c == col}
    for rep in [*(r for r in ranked if r in have), *sorted(have - set(ranked))]:
      lr = chosen_lr(L.out, col, rep, L.plan)
      if lr is not None:
        pattern = os.path.join(L.out, "regression", col, rep, f"{lr_tag(lr)}_seed*")
        wds += sorted(d for d in glob.glob(pattern) if runs.is_finished(d))
    if not wds:
      continue
    argv = [L.python, "experiments/learning_curve.py", "--bands", "--metrics"]
    argv += ["eval/validation/score", "--runs", *wds, "--title", curve_title(col)]
    argv += ["--png", os.path.join(L.out, f"curve_{col}.png")]
    argv += ["--md", os.path.join(L.out, f"curve_{col}.md")]
    jobs.append(Job(f"curve_{col}", argv, "", 5))
  return jobs


def make_launch(
  plan: plan_lib.Plan,
  out: str,
  *,
  settings: Sequence[str],
  representations: Sequence[str] = (),
  data: dict | None = None,
  python: str = "python",
  full_grid: bool = False,
  vectorise: bool = True,
  skip_figures: bool = False,
  noise_kinds: Sequence[str] = (),
  crossed: str = "",
  archive: str = "",
) -> Launch:
  """Every job of a launch (see the package docstring for what each argument asks; `vectorise`
  False: one process per regression run even where the plan vectorises them)."""
  if not vectorise:
    plan = dataclasses.replace(plan, vectorise={})
  if full_grid:  # the lr then chosen on every seed's validation (`chosen_lr`)
    plan = dataclasses.replace(plan, full_grid=True)
  data = dict(data or {})
  captures = [c for c in data if c not in SETTINGS]
  columns = list(settings) + [c for c in captures if setting_of(c) in settings]
  reps = {
    c: tuple(
      r
      for r in plan_lib.settings()[setting_of(c)]["representations"] + plan.controls
      if not representations or r in representations
    )
    for c in columns
  }
  out = os.path.abspath(out)
  # The runs whose pose inputs the regressions read: the learned grid (ours, untrained), the MLP
  # embedding's own (car and each capture column), the grid with frozen generators.
  names = {}  # each view-synthesis run's name: its column
  for c in columns:
    for rep in reps[c]:
      suffix = plan_lib.synthesis_suffix(rep)
      if suffix is not None:
        names.setdefault(c + suffix, c)
  for s in columns if noise_kinds else []:
    inputs = plan_lib.settings().get(s, {}).get("noise_inputs", ())
    kinds = [k for k in noise_kinds if k in inputs and (k != "convdraw" or plan.convdraw_config(s))]
    for n in [s, *(f"{s}_{k}" for k in kinds)] if inputs else ():  # the noise figure's inputs
      names.setdefault(n, s)
  if plan.paired_synthesis:  # one synthesis run per seed of its column (its regression seed's)
    names = {f"{n}_seed{k}": c for n, c in names.items() for k in plan.seeds_for(setting_of(c))}
  names = list(names)
  data = {c: d for c, d in data.items() if c in columns}
  synth = synthesis_jobs(out, plan, names, python, data)
  first, later = [], []
  for c in columns:
    for rep in reps[c]:
      seeds = plan.seeds_for(setting_of(c)) if full_grid else plan.seeds[:1]
      lrs = plan.lrs[setting_of(c)]
      if plan.vectorise:  # phase 1 (or the full grid) as one program
        first.append(regression_grid_job(out, plan, c, rep, lrs, seeds, python, data))
      else:
        first += [
          regression_job(out, plan, c, rep, lr, seed, python, data) for seed in seeds for lr in lrs
        ]
      if not full_grid:
        later += [(c, rep, seed) for seed in plan.seeds_for(setting_of(c))[1:]]
  tables = table_jobs(out, python, columns)
  figures = [] if skip_figures else figure_jobs(out, plan, synth, python, data)
  if crossed and "ours" not in reps.get(crossed, ()):
    raise ValueError(f"--crossed {crossed}: the launch runs no ours there (--representations)")
  return Launch(
    plan, out, python, columns, synth, first, later, tables, figures, data, crossed,
    os.path.abspath(archive) if archive else "",
  )  # fmt: skip


def phase2_jobs(launch: Launch) -> list[tuple[tuple[str, str, int], Job]]:
  """Each phase-2 (column, rep, seed) with its job: at the lr seed 0's validation errors choose
  so far, or the <LR> placeholder while phase 1 has no results."""
  L = launch
  return [
    (
      (c, rep, seed),
      regression_job(
        L.out, L.plan, c, rep, chosen_lr(L.out, c, rep, L.plan), seed, L.python, L.data
      ),
    )
    for c, rep, seed in L.later
  ]


def phase2_grid_jobs(launch: Launch) -> list[Job]:
  """A vectorised plan's phase 2: per (column, representation), its later seeds as one program
  at the lr that seed 0's validation errors choose so far (the <LR> placeholder while phase 1
  has no results)."""
  L = launch
  groups: dict[tuple[str, str], list[int]] = {}
  for c, rep, seed in L.later:
    groups.setdefault((c, rep), []).append(seed)
  jobs = []
  for (c, rep), seeds in groups.items():
    lr = chosen_lr(L.out, c, rep, L.plan)
    lrs = None if lr is None else [lr]
    jobs.append(regression_grid_job(L.out, L.plan, c, rep, lrs, seeds, L.python, L.data))
  return jobs


def extension_jobs(launch: Launch) -> list[Job]:
  """Phase 1's next grid extension: one seed-0 run per (column, representation) whose chosen lr
  sits at its grid's edge (`extension_lr`)."""
  L = launch
  groups = sorted({(c, rep) for c, rep, _ in L.later} | {_group(j) for j in L.first})
  jobs = []
  for col, rep in groups:
    lr = extension_lr(L.out, col, rep, L.plan)
    if lr is not None:
      jobs.append(regression_job(L.out, L.plan, col, rep, lr, L.plan.seeds[0], L.python, L.data))
  return jobs


# --------------------------------------------------------------------------------------------
# Runs made stale by a changed view-synthesis cap.

STALE_DIR = "stale"
"""Where a launch moves its stale runs, under DIR and the archive alike: <root>/stale/<the run's
path>.stale-<cap>, outside every pattern that finds runs (`archive.RUN_PATTERNS`, the tables'
globs), never deleted."""


@dataclasses.dataclass(frozen=True)
class StaleRun:
  """A run a launch must train again because of a view-synthesis cap: a view-synthesis run that
  stopped at its plateau under another cap (`trained`) than its command's (`cap`), whose plateau
  rule's window and evaluations follow the cap; or a run that reads one (its pose system).

  Attributes:
    root: the launch's DIR or its archive.
    rel: the run's path under `root` ("synthesis/<name>", "regression/<column>/<rep>/<run>",
      "crossed/<column>/<run>").
    synthesis: the name of the stale view-synthesis run (itself, or the one it reads).
    trained: the cap that run trained under.
    cap: the cap the launch's command gives it.
  """

  root: str
  rel: str
  synthesis: str
  trained: int
  cap: int

  @property
  def path(self) -> str:
    return os.path.join(self.root, self.rel)

  def aside(self) -> str:
    """A free path <root>/stale/<rel>.stale-<trained>[.<n>] for it."""
    base = os.path.join(self.root, STALE_DIR, f"{self.rel}.stale-{self.trained}")
    path, n = base, 0
    while os.path.exists(path):
      n += 1
      path = f"{base}.{n}"
    return path

  def describe(self) -> str:
    why = (
      f"stopped at its plateau under --config.total_steps={self.trained}, the plan's cap is "
      f"{self.cap}"
      if self.rel == os.path.join("synthesis", self.synthesis)
      else f"reads synthesis/{self.synthesis}, stale (cap {self.trained}, the plan's {self.cap})"
    )
    return f"{self.path}: {why}"


def synthesis_read(rel: str, plan: plan_lib.Plan) -> str | None:
  """The name of the view-synthesis run whose pose system the regression or crossed run at `rel`
  (its path under DIR) reads (`regression_job`, `crossed_job`), or None (a baseline, another
  path)."""
  parts = rel.split(os.sep)
  if parts[0] == "regression" and len(parts) == 4:
    column, rep, name = parts[1:]
    if rep not in pose_encodings.REPRESENTATIONS or "_seed" not in name:
      return None
    suffix = plan_lib.synthesis_suffix(rep)
    if suffix is None:
      return None
    return (
      column + suffix + (f"_seed{name.rpartition('_seed')[2]}" if plan.paired_synthesis else "")
    )
  if parts[0] == "crossed" and len(parts) == 3 and "_syn" in parts[2]:
    return f"{parts[1]}_seed{parts[2].rpartition('_syn')[2]}"
  return None


def stale_runs(launch: Launch) -> list[StaleRun]:
  """The launch's view-synthesis runs, in DIR or its archive, that stopped at their plateau under
  another cap than their command gives (complete at an old cap, a run resumes instead:
  `synthesis_done`), and every run there that reads one of them."""
  L = launch
  roots = [L.out, *([L.archive] if L.archive else [])]
  found, caps = [], {}
  for j in L.synth:
    cap = flag_value(j.argv, "--config.total_steps")
    if cap is None:
      continue
    name = j.name.removeprefix("synthesis_")
    for root in roots:
      wd = os.path.join(root, "synthesis", name)
      final, trained = read_final(wd), trained_cap(wd)
      stopped = (final.get("stopping") or {}).get("stopped_early")
      if final.get("complete") is True and stopped and trained not in (None, int(cap)):
        caps[name] = (trained, int(cap))
        found.append(StaleRun(root, os.path.join("synthesis", name), name, trained, int(cap)))
  for root in roots if caps else ():
    for rel in archive_lib.run_dirs(root):
      name = synthesis_read(rel, L.plan)
      if name in caps:
        found.append(StaleRun(root, rel, name, *caps[name]))
  return found


def set_aside_stale(launch: Launch) -> list[tuple[str, str]]:
  """Moves every stale run (`stale_runs`) to its `StaleRun.aside` path, with a line naming it;
  the launch then trains it again. Returns the (old, new) paths."""
  moved = []
  for r in stale_runs(launch):
    new = r.aside()
    os.makedirs(os.path.dirname(new), exist_ok=True)
    shutil.move(r.path, new)
    print(f"stale: {r.describe()}; moved to {new}, trained again", flush=True)
    moved.append((r.path, new))
  return moved


# --------------------------------------------------------------------------------------------
# Running the jobs.


def run_job(job: Job, logs: str, *, index: str, env: dict[str, str] | None = None) -> bool:
  """Runs a job (stdout and stderr to logs/<name>.log, environment `env` or this one's); True on
  success. Stopped (Ctrl-C, SIGTERM, or another job's stop), it sends the run SIGTERM, which
  makes a training run save a checkpoint and exit, waits up to STOP_GRACE_S for it (a second
  Ctrl-C kills it at once) and raises KeyboardInterrupt."""
  os.makedirs(logs, exist_ok=True)
  log_path = os.path.join(logs, f"{job.name}.log")
  print(
    f"[{index}] {job.name} (est. {progress_lib.format_duration(job.estimate_s)}) ...", flush=True
  )
  t0 = time.perf_counter()
  with open(log_path, "w", encoding="utf-8") as log:
    log.write(f"$ {job.command()}\n")
    log.flush()
    proc = subprocess.Popen(job.argv, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, env=env)
    try:
      while (rc := _wait(proc, 0.5)) is None:
        if _STOPPING.is_set():
          raise KeyboardInterrupt
    except KeyboardInterrupt:
      _STOPPING.set()
      _stop(proc)
      raise
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


def _wait(proc: subprocess.Popen, timeout: float) -> int | None:
  try:
    return proc.wait(timeout)
  except subprocess.TimeoutExpired:
    return None


def _stop(proc: subprocess.Popen) -> None:
  """SIGTERM, then up to STOP_GRACE_S for the run to save and exit, then SIGKILL."""
  if proc.poll() is not None:
    return
  proc.send_signal(signal.SIGTERM)
  try:
    proc.wait(STOP_GRACE_S)
  except (subprocess.TimeoutExpired, KeyboardInterrupt):
    proc.kill()
    proc.wait()


def job_env(jobs: int) -> dict[str, str] | None:
  """The subprocesses' environment: with `jobs` > 1 at once, each JAX process may take 0.9 / jobs
  of a GPU's memory (XLA_PYTHON_CLIENT_MEM_FRACTION, unless set) and runs XLA:CPU on one thread
  (`xla_cpu.one_thread`, unless XLA_FLAGS name it; GPU programs are unchanged): the jobs share the
  cores, and on 2 cores two one-thread regression programs did 2.0x (car) and 1.33x (7-Scenes)
  the member-steps per second of one program on both (`camrep.bench.regression_grid`,
  BUILD_NOTES.md). None: this one's."""
  if jobs <= 1:
    return None
  env = dict(os.environ)
  env.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", f"{0.9 / jobs:.3f}")
  xla_cpu.one_thread(env)
  return env


def sharing_cores(job: Job, jobs: int) -> Job:
  """`job` as it runs beside `jobs` - 1 others: a regression grid spreads its members over its
  share of the cores (`--host_devices`, at least 1; alone, the grid takes them all); others
  unchanged."""
  if jobs <= 1 or not job.members or flag_value(job.argv, "--host_devices") is not None:
    return job
  share = max(1, xla_cpu.usable_cores() // jobs)
  return dataclasses.replace(job, argv=[*job.argv, f"--host_devices={share}"])


def set_aside_damaged(jobs: Sequence[Job]) -> None:
  """Renames the unreadable file of each job's damaged run (`archive.set_aside`), with a warning
  naming it: the run is not finished, and trains again."""
  for j in jobs:
    for w in j.workdirs:
      if (d := damage(w)) is not None:
        new = archive_lib.set_aside(d)
        print(f"warning: {d}; the run is trained again (the file is kept as {new})", flush=True)


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
  archive's copy). Returns the names of those that failed."""
  _STOPPING.clear()  # a stop ends the launch (KeyboardInterrupt): a new batch of jobs starts clear
  set_aside_damaged(jobs)
  todo = [j for j in jobs if not j.done()]
  for j in jobs:
    if j not in todo:
      print(f"[{label}skipped] {j.name}: done ({j.workdir})", flush=True)
  at_once = min(at_once, max(1, len(todo)))  # the cores shared by the jobs that can run
  env = job_env(at_once)

  def one(i_job: tuple[int, Job]) -> str | None:
    i, job = i_job
    if _STOPPING.is_set():
      return None
    if deadline is not None and time.monotonic() > deadline:
      print(f"[{label}{i + 1}/{len(todo)}] {job.name}: not started (--max_hours)", flush=True)
      return None
    try:
      ok = run_job(sharing_cores(job, at_once), logs, index=f"{label}{i + 1}/{len(todo)}", env=env)
    except KeyboardInterrupt:  # a stop in any job: none other starts
      _STOPPING.set()
      raise
    if ok and after is not None:
      after(job)
    return None if ok else job.name

  if at_once <= 1:
    results = [one(x) for x in enumerate(todo)]
  else:
    with concurrent.futures.ThreadPoolExecutor(max_workers=at_once) as pool:
      futures = [pool.submit(one, x) for x in enumerate(todo)]
      try:
        results = [f.result() for f in futures]
      except KeyboardInterrupt:  # the running jobs stop (run_job), no other one starts
        _STOPPING.set()
        for f in futures:
          f.cancel()
        concurrent.futures.wait(futures)
        raise
  if _STOPPING.is_set():
    raise KeyboardInterrupt
  return [name for name in results if name]


def synthesis_of_seed(launch: Launch, seed: int) -> list[Job]:
  """The view-synthesis jobs trained before seed `seed`'s regressions: those named
  "<name>_seed<seed>" with one synthesis run per seed, else all of them with the first seed."""
  L = launch
  if not L.plan.paired_synthesis:
    return list(L.synth) if seed == L.plan.seeds[0] else []
  return [j for j in L.synth if j.name.endswith(f"_seed{seed}")]


def pending_synthesis(launch: Launch) -> set[str]:
  """The view-synthesis workdirs whose checkpoints a job not yet done reads (its pose system,
  noise evaluation, crossed runs: `checkpoint_reads`); a phase-2 run whose lr phase 1 has not
  chosen yet counts."""
  L = launch
  jobs = list(L.first) + extension_jobs(L) + [job for _, job in phase2_jobs(L)]
  if L.crossed:
    jobs += crossed_jobs(L, chosen_lr(L.out, L.crossed, "ours", L.plan))
  if L.plan.vectorise:
    jobs += phase2_grid_jobs(L)
  need = set()
  for j in jobs:
    if not j.done():
      need |= checkpoint_reads(j)
  for j in L.figures:
    if j.kind == "evaluate" and not j.done():
      need.add(j.workdir)
  return need


def run_synthesis(launch: Launch, jobs: Sequence[Job], logs: str, kw: dict) -> list[str]:
  """Trains the view-synthesis `jobs` that are not done, then their noise / Gram evaluations.

  A run whose record came from the archive (complete, without checkpoints) is trained again
  (from scratch: the same numbers on the same kind of CPU) only while a job that reads its
  checkpoints is not done (`pending_synthesis`), else skipped."""
  L = launch
  pending = pending_synthesis(L)
  todo = []
  for j in jobs:
    if not archived_only(j.workdir):
      todo.append(j)
    elif j.workdir in pending:
      print(
        f"[synthesis] {j.name}: its record is from the archive and a run still needs its "
        "checkpoints; training it again",
        flush=True,
      )
      shutil.rmtree(j.workdir)
      todo.append(j)
    else:
      print(f"[synthesis: skipped] {j.name}: archived, nothing left needs it", flush=True)
  for j in todo:
    final = read_final(j.workdir)
    if final.get("complete") is True and not j.done() and not resumable(j.argv):
      # Complete at another length, and its schedules are fractions of its length (ConvDRAW):
      # training on would not give the run the command asks for.
      print(
        f"[synthesis] {j.name}: complete at step {final.get('step')}, not at the "
        f"{flag_value(j.argv, '--config.total_steps')} steps asked, and its schedules follow "
        "its length; training it again from scratch",
        flush=True,
      )
      shutil.rmtree(j.workdir)
  for j in todo:  # a run that trains on (a raised cap) makes its old evaluation stale
    stale = os.path.join(j.workdir, runs.NOISE_FILE)
    if not j.done() and os.path.exists(stale):
      os.remove(stale)
  failed = run_jobs(todo, logs, label="synthesis: ", **kw)
  names = {j.name.removeprefix("synthesis_") for j in jobs}
  evaluations = [j for j in L.figures if j.name.removeprefix("evaluate_") in names]
  failed += run_jobs(evaluations, logs, label="evaluate: ", **kw)
  return failed


def execute(launch: Launch, *, at_once: int = 1, deadline: float | None = None) -> list[str]:
  """Runs what is not done yet, in the order of the module docstring, `at_once` subprocesses at
  a time within each step; no run is started after `deadline` (time.monotonic()). With an
  archive, each finished run's record is copied into it as soon as the run ends.

  Returns:
    The names of the jobs that failed.
  """
  L = launch
  logs = os.path.join(L.out, "logs")
  after = (lambda job: archive_lib.sync(L.out, L.archive)) if L.archive else None
  kw = dict(at_once=at_once, deadline=deadline, after=after)
  # Phase 1 reads the view synthesis of seed 0, or of every seed where it is the full grid.
  n_first = 1 if L.later else len(L.plan.seeds)
  later_seeds = L.plan.seeds[n_first:]
  failed = []
  for seed in L.plan.seeds[:n_first]:
    failed += run_synthesis(L, synthesis_of_seed(L, seed), logs, kw)
  failed += run_jobs(L.first, logs, label="phase 1: ", **kw)
  for _ in range(L.plan.extend_grid):
    ext = extension_jobs(L)
    if not ext:
      break
    failed += run_jobs(ext, logs, label="phase 1, lr grid extended: ", **kw)
  if L.plan.vectorise:  # every later seed's synthesis first: phase 2 is one program per group
    for seed in later_seeds:
      failed += run_synthesis(L, synthesis_of_seed(L, seed), logs, kw)
    later = []
    for job in phase2_grid_jobs(L):
      if "--lrs=<LR>" in job.argv:
        print(f"[phase 2] {job.name}: no phase-1 results; skipped", flush=True)
        failed.append(job.name)
      else:
        later.append(job)
    failed += run_jobs(later, logs, label="phase 2: ", **kw)
  for seed in later_seeds if not L.plan.vectorise else ():
    failed += run_synthesis(L, synthesis_of_seed(L, seed), logs, kw)
    later = []
    for c, rep, k in L.later:
      if k != seed:
        continue
      lr = chosen_lr(L.out, c, rep, L.plan)
      if lr is None:
        print(f"[phase 2] {c}/{rep} seed {k}: no phase-1 results; skipped", flush=True)
        failed.append(f"regression_{c}_{rep}_seed{k}")
        continue
      later.append(regression_job(L.out, L.plan, c, rep, lr, k, L.python, L.data))
    failed += run_jobs(later, logs, label=f"phase 2, seed {seed}: ", **kw)
  if L.crossed:
    lr = chosen_lr(L.out, L.crossed, "ours", L.plan)
    if lr is None:
      print(f"[crossed] {L.crossed}/ours: no phase-1 results; skipped", flush=True)
      failed.append(f"crossed_{L.crossed}")
    else:
      failed += run_jobs(crossed_jobs(L, lr), logs, label="crossed: ", **kw)
      failed += run_jobs([seed_spread_job(L, lr)], logs, label="", **{**kw, "at_once": 1})
  # The noise figures drawn from every evaluated run DIR holds by now (figure_jobs reads DIR).
  figures = figure_jobs(L.out, L.plan, L.synth, L.python, L.data) if L.figures else []
  rest = [j for j in figures if j.kind != "evaluate"]
  failed += run_jobs(L.tables + curve_jobs(L) + rest, logs, label="", **{**kw, "at_once": 1})
  if L.archive:
    archive_lib.sync(L.out, L.archive)
  return failed


def remaining_s(launch: Launch, *, at_once: int = 1, later=None) -> float:
  """Seconds of what is not done yet (phase 2 at the lr chosen so far, data rendering while
  DIR has no cache, tables and figures), divided by `at_once` jobs at a time (the best case)."""
  L, plan = launch, launch.plan
  est = sum(j.estimate_s for j in L.synth + L.first if not j.done())
  if plan.vectorise:
    est += sum(j.estimate_s for j in phase2_grid_jobs(L) if not j.done())
  else:
    later = phase2_jobs(L) if later is None else later
    est += sum(plan.regression_s[setting_of(c)] for (c, _, _), j in later if not j.done())
  if not os.path.isdir(os.path.join(L.out, "cache")):
    est += sum(plan.data_s[setting_of(c)] for c in L.settings)
  est += sum(j.estimate_s for j in L.tables + L.figures if not j.done())
  return est / at_once


def vectorised_saving_s(launch: Launch) -> tuple[int, int, float]:
  """A vectorised plan's (programs, runs they train, seconds saved against one process per run)
  over the regression grids not done yet; (0, 0, 0.0) without vectorising."""
  L, plan = launch, launch.plan
  if not plan.vectorise:
    return 0, 0, 0.0
  grids = [j for j in L.first + phase2_grid_jobs(L) if j.members and not j.done()]
  n = sum(len(j.members) for j in grids)
  alone = sum(len(j.members) * plan.regression_s[setting_of(_group(j)[0])] for j in grids)
  return len(grids), n, alone - sum(j.estimate_s for j in grids)


def print_plan(launch: Launch, *, commands: bool, at_once: int = 1) -> None:
  """The summary line (runs, estimate of what is not done yet, divided by `at_once` jobs at a
  time: the best case); with `commands`, every job."""
  L, plan = launch, launch.plan
  fmt = progress_lib.format_duration
  later = [] if plan.vectorise else phase2_jobs(L)
  est = remaining_s(L, at_once=at_once, later=later)
  at = f", {at_once} jobs at a time at best" if at_once > 1 else ""
  if plan.extend_grid:  # groups whose seed-0 choice is settled inside its grid need none
    settled = all(j.done() for j in L.first)
    groups = {
      g for g in map(_group, L.first) if not settled or extension_lr(L.out, *g, plan) is not None
    }
    worst_s = sum(plan.regression_s[setting_of(c)] for c, _ in groups) * plan.extend_grid
    at += (
      f"; plus up to {len(groups) * plan.extend_grid} phase-1 runs (up to {fmt(worst_s)}) "
      "extending an lr grid whose choice is at its edge"
    )
  n_first = sum(len(j.workdirs) for j in L.first)
  print(
    f"{plan.name} comparison into {L.out}: {len(L.synth)} view-synthesis runs, "
    f"{n_first + len(L.later)} regression runs ({n_first} in phase 1, {len(L.later)} "
    f"in phase 2), {len(L.tables)} tables, {len(L.figures)} figure steps; estimated "
    f"{fmt(est)} for what is not done yet ({plan.where}){at}.",
    flush=True,
  )
  if plan.vectorise:
    programs, n, saved = vectorised_saving_s(L)
    v = plan.vectorise
    order = (
      "phase 1 one per column and representation over its lrs, phase 2 one over its later "
      "seeds (after every seed's view synthesis)"
      if L.later
      else "one per column and representation over its lrs and seeds (the full grid: after "
      "every seed's view synthesis, no phase 2)"
    )
    print(
      f"  vectorised regressions (python -m camrep.regression --lrs --seeds): {n} runs as "
      f"{programs} programs, {order}; saves ~{fmt(saved)} "
      f"of the estimate ({v['startup_s']:g} s of start-up a run paid once a program, steps "
      f"{v['step_speedup']:g}x as fast)",
      flush=True,
    )
  for c in L.settings:
    if isinstance(L.data.get(c), tuple):
      where = f"capture prepared as {L.data[c][0]} in {L.data[c][1]} (car setting)"
    elif c in L.data:
      where = f"prepared {plan_lib.real_source(c)} data in {L.data[c]}"
    else:
      where = "its procedural family (configs/regression.py settings)"
    print(f"  data of {c}: {where}", flush=True)
  damaged = [
    (j.name, d) for j in L.synth + L.first for w in j.workdirs if (d := damage(w)) is not None
  ]
  for name, d in damaged:
    print(f"  {name}: {d}; the launch trains it again", flush=True)
  for r in stale_runs(L):
    print(f"  stale: {r.describe()}; the launch moves it to {r.aside()} and trains it again")
  crossed = crossed_jobs(L, None)
  if crossed:
    est_s = len(crossed) * plan.regression_s[setting_of(L.crossed)] + 60
    print(
      f"  crossed seeds of {L.crossed}'s ours: {len(crossed)} more regression runs, estimated "
      f"{fmt(est_s)} (not in the estimate above)",
      flush=True,
    )
  if not commands:
    return
  for j in L.synth + L.first:
    print(f"[{'done' if j.done() else '~' + fmt(j.estimate_s)}] {j.command()}")
  if plan.vectorise:
    for job in phase2_grid_jobs(L):
      print(f"[{'done' if job.done() else '~' + fmt(job.estimate_s)}, phase 2] {job.command()}")
  else:
    for (c, _, _), job in later:
      state = "done" if job.done() else f"~{fmt(plan.regression_s[setting_of(c)])}"
      print(f"[{state}, phase 2] {job.command()}")
  if L.later:
    print("  (phase 2: <LR> = the lr chosen on seed 0's validation errors, where not chosen yet)")
  for job in crossed:
    print(f"[~{fmt(plan.regression_s[setting_of(L.crossed)])}, crossed] {job.command()}")
  if L.crossed:
    print(
      f"[~1min] experiments/seed_spread.py --decode over {L.out}/crossed/{L.crossed} and the "
      f"paired ours runs at <LR> -> {L.out}/seed_spread_{L.crossed}.md"
    )
  if plan.stop:
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
  for j in L.tables + L.figures:  # an evaluation is done once its noise curve is recorded
    print(f"[{'done' if j.done() else '~' + fmt(j.estimate_s)}] {j.command()}")

"""The multi-view transformer's comparison of camera conditionings, as a launcher plan:
`python -m camrep.comparison --size lvsm_quick --out DIR [--data car_NAME=SOURCE:DIR] [--dry_run]`.

A plan (`[transformer.NAME]` of plans.toml) is cameras x seeds x columns of view-synthesis runs of
configs/lvsm.py (`camrep.synthesis.conditionings`): columns "rooms" and "car" (procedural) and
each capture column `--data car_NAME=SOURCE:DIR` gives (the car setting on a prepared capture).
Steps, each finished run skipped (a launch that stops resumes where it stopped):

  1. each view-synthesis run into DIR/lvsm/<column>/<camera>_seed<k> (held-out PSNR/SSIM at the
     trained and at `evals.context_counts` context views, train/steps_per_sec: the cost per step),
     seed-major (every cell's first seed before any second one), and as soon as it ends its noise
     test on the query pose before conditioning (`camrep.synthesis.evaluate --what=noise`,
     `noise.NOISE_ON` "pose": the same for every conditioning) into its eval/;
  2. experiments/lvsm_table.py over DIR/lvsm -> DIR/lvsm_table.md and DIR/lvsm_noise.png
     (seed-level intervals and verdicts against the plan's baseline, raymap).

`--settings` narrows the columns by their setting (gqn: rooms; car: car and the captures) and
`--representations` the cameras; the regression plans' own flags are refused.

`--archive DIR` (e.g. results/lvsm), as for the regression plans (`camrep.comparison.archive`):
each run's compact record is written into DIR when the run ends and again with its noise curve,
each time with the table and figure made again from every finished run (DIR's table is always
that of its records), and a launch starts by restoring the records DIR holds, so a launch longer
than a machine is kept goes on from a fresh clone. A restored run has no checkpoints: one whose
noise test is missing is trained again.

Parameter counts: the transformer trunk is the same for every conditioning; what differs is the
conditioning's own input projection (raymap's 6 p^2 Pluecker features, learned_abs's v(p) into
the token embedding) and the learned pose system ("rep"). They are counted from the library
(`parameter_counts`) and printed by the dry run, not matched by changing widths: a width change
would change the head dimension the relative encodings tile (see `relative_attention.HeadLayout`).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import shutil
import threading
from collections.abc import Mapping, Sequence
from typing import Any

from camrep import settings as settings_lib
from camrep.comparison import archive as archive_lib
from camrep.comparison import launch as launch_lib
from camrep.comparison import plan as plan_lib
from camrep.runtime import progress as progress_lib

# Columns of a plan that are procedural (the others are the captures of --data), and the
# setting of each (`--settings` chooses columns by it; a capture column is the car setting's).
COLUMNS = ("rooms", "car")
SETTING_OF = {"rooms": settings_lib.GQN, "car": settings_lib.CAR}


def setting_of(column: str) -> str:
  """The setting name of a column: the rooms' GQN, the car's and every capture column's car."""
  return SETTING_OF.get(column, settings_lib.CAR).name


@dataclasses.dataclass(frozen=True)
class TransformerPlan:
  """One transformer comparison (plans.toml `[transformer.NAME]`).

  Attributes:
    name: the plan ("lvsm_quick").
    config: the config file (configs/lvsm.py).
    variants: config variant per column, "capture" for the capture columns.
    cameras: the conditionings compared (keys of `conditionings.CONDITIONINGS`).
    seeds: seeds of every cell.
    columns: the procedural columns.
    capture: the capture column the plan expects, as a --data value (named by the dry run).
    baseline: the conditioning the verdicts compare against.
    step_s: estimated seconds per training step, per column ("capture" for the captures).
    run_overhead_s: seconds of start-up, compilation and evaluations per run.
    noise_s: seconds of one run's noise test.
    where: what the estimate assumes, in words.
  """

  name: str
  config: str
  variants: dict[str, str]
  cameras: tuple[str, ...]
  seeds: tuple[int, ...]
  columns: tuple[str, ...]
  capture: str
  baseline: str
  step_s: dict[str, float]
  run_overhead_s: float
  noise_s: float
  where: str = ""

  def variant(self, column: str) -> str:
    return self.variants[column if column in COLUMNS else "capture"]

  def total_steps(self, column: str) -> int:
    """total_steps of the column's config variant."""
    return int(_config(self.variant(column)).total_steps)

  def run_s(self, column: str) -> float:
    """Estimated seconds of one training run of `column`."""
    per = self.step_s[column if column in COLUMNS else "capture"]
    return self.run_overhead_s + self.total_steps(column) * per


@functools.cache
def _config(variant: str):
  from camrep.configs import lvsm

  return lvsm.get_config(variant)


@functools.cache
def plans() -> dict[str, TransformerPlan]:
  """Every `[transformer.NAME]` of plans.toml, checked against the library."""
  from camrep.synthesis import conditionings

  out = {}
  for name, d in plan_lib._read().get("transformer", {}).items():
    cameras = tuple(d["cameras"])
    unknown = sorted(set(cameras) - set(conditionings.CONDITIONINGS))
    if unknown or d["baseline"] not in cameras:
      raise ValueError(
        f"{plan_lib.PLANS_FILE}: transformer.{name}: unknown cameras {unknown} or baseline "
        f"{d['baseline']!r} not among them"
      )
    if set(d["columns"]) - set(COLUMNS):
      raise ValueError(f"{plan_lib.PLANS_FILE}: transformer.{name}: columns are {COLUMNS}")
    out[name] = TransformerPlan(
      name=name,
      config=d["config"],
      variants=dict(d["variants"]),
      cameras=cameras,
      seeds=tuple(int(s) for s in d["seeds"]),
      columns=tuple(d["columns"]),
      capture=d.get("capture", ""),
      baseline=d["baseline"],
      step_s={k: float(v) for k, v in d["step_s"].items()},
      run_overhead_s=float(d["run_overhead_s"]),
      noise_s=float(d["noise_s"]),
      where=d.get("where", ""),
    )
  return out


def parameter_counts(plan: TransformerPlan, column: str = "rooms") -> dict[str, dict[str, int]]:
  """{camera: {"model": n, "rep": n}}: each conditioning's parameter count on `column`'s config
  (shapes only: `jax.eval_shape` of the model's init on a batch of the config's layout)."""
  import jax
  import numpy as np

  from camrep.synthesis import components

  out = {}
  for camera in plan.cameras:
    config = _config(plan.variant(column)).copy_and_resolve_references()
    config.model.camera = camera
    model = components.make_model(components.resolve(config), 1)
    spec, d = model.spec, config.data
    size = 64
    batch = {
      "image": jax.ShapeDtypeStruct((1, d.views_per_scene, size, size, 3), np.uint8),
      "pose": jax.ShapeDtypeStruct((1, d.views_per_scene, spec.pose_dim), np.float32),
      "scene": jax.ShapeDtypeStruct((1,), np.int32),
    }
    params = jax.eval_shape(model.init, jax.random.key(0), batch)
    out[camera] = {
      group: int(sum(np.prod(a.shape) for a in jax.tree.leaves(params[group])))
      for group in ("model", "rep")
    }
  return out


def columns(plan: TransformerPlan, data: Mapping[str, Any] | None) -> list[str]:
  """The plan's procedural columns and the capture columns of --data (car_NAME)."""
  captures = [c for c, v in (data or {}).items() if isinstance(v, tuple)]
  return [*plan.columns, *captures]


def select(
  plan: TransformerPlan,
  settings: Sequence[str] = (),
  cameras: Sequence[str] = (),
  data: Mapping[str, Any] | None = None,
) -> tuple[TransformerPlan, dict[str, Any]]:
  """The plan narrowed to the columns of `settings` (by `setting_of`; the capture columns of
  `data` follow the car setting) and to `cameras`, in the plan's order (empty: all), with the
  capture columns of `data` it keeps. Raises ValueError on a camera the plan does not compare or
  on settings none of whose columns it has."""
  unknown = sorted(set(cameras) - set(plan.cameras))
  if unknown:
    raise ValueError(
      f"--representations {','.join(unknown)}: not a conditioning of --size {plan.name} "
      f"(choose from {','.join(plan.cameras)})"
    )
  every = columns(plan, data)
  chosen = [c for c in every if not settings or setting_of(c) in settings]
  if not chosen:
    have = ", ".join(f"{setting_of(c)} ({c})" for c in every)
    raise ValueError(
      f"--settings {','.join(settings)}: --size {plan.name} has no column of it; its columns' "
      f"settings: {have}"
    )
  narrowed = dataclasses.replace(
    plan,
    cameras=tuple(c for c in plan.cameras if not cameras or c in cameras),
    columns=tuple(c for c in plan.columns if c in chosen),
  )
  return narrowed, {c: v for c, v in (data or {}).items() if c in chosen}


def run_dir(out: str, column: str, camera: str, seed: int) -> str:
  return os.path.join(out, "lvsm", column, f"{camera}_seed{seed}")


def synthesis_jobs(
  plan: TransformerPlan, out: str, py: str, data: Mapping[str, Any] | None = None
) -> list[launch_lib.Job]:
  """One view-synthesis run per column, camera and seed (seed-major: every cell's first seed
  before any second one, so a launch cut short has whole seeds)."""
  jobs = []
  for seed in plan.seeds:
    for column in columns(plan, data):
      for camera in plan.cameras:
        wd = run_dir(out, column, camera, seed)
        argv = [py, "-m", "camrep.main", f"--config={plan.config}:{plan.variant(column)}"]
        argv += [f"--workdir={wd}", f"--config.model.camera={camera}", f"--config.seed={seed}"]
        if column not in COLUMNS:
          argv += launch_lib.data_flags(column, dict(data))
          argv.append("--config.data.scenes_per_device=1")
        name = f"lvsm_{column}_{camera}_seed{seed}"
        jobs.append(launch_lib.Job(name, argv, wd, plan.run_s(column), "synthesis"))
  return jobs


def noise_jobs(plan: TransformerPlan, synth: Sequence[launch_lib.Job], py: str):
  """The noise test on the query pose of every run (`--what=noise`: the Gram maps need v(p))."""
  jobs = []
  for j in synth:
    argv = [py, "-m", "camrep.synthesis.evaluate", "--workdir", j.workdir, "--what=noise"]
    argv.append("--noise_on=pose")
    name = j.name.replace("lvsm_", "noise_", 1)
    jobs.append(launch_lib.Job(name, argv, j.workdir, plan.noise_s, "evaluate"))
  return jobs


def table_job(plan: TransformerPlan, out: str, py: str) -> launch_lib.Job:
  argv = [py, "experiments/lvsm_table.py", "--runs", os.path.join(out, "lvsm")]
  argv += ["--baseline", plan.baseline, "--out", os.path.join(out, "lvsm_table.md")]
  argv += ["--png", os.path.join(out, "lvsm_noise.png")]
  return launch_lib.Job("lvsm_table", argv, "", 5)


@dataclasses.dataclass
class TransformerLaunch:
  plan: TransformerPlan
  out: str
  synth: list[launch_lib.Job]
  noise: list[launch_lib.Job]
  table: launch_lib.Job
  data: dict
  archive: str = ""  # --archive: where each finished run's record is kept


def make_launch(
  plan: TransformerPlan,
  out: str,
  *,
  python: str = "python",
  data: Mapping[str, Any] | None = None,
  archive: str = "",
  settings: Sequence[str] = (),
  cameras: Sequence[str] = (),
) -> TransformerLaunch:
  """Every job of a transformer comparison into `out` (records kept in `archive`, if given), of
  the columns of `settings` and the `cameras` (`select`; empty: all)."""
  out = os.path.abspath(out)
  data = {c: v for c, v in (data or {}).items() if isinstance(v, tuple)}
  plan, data = select(plan, settings, cameras, data)
  synth = synthesis_jobs(plan, out, python, data)
  return TransformerLaunch(
    plan,
    out,
    synth,
    noise_jobs(plan, synth, python),
    table_job(plan, out, python),
    data,
    os.path.abspath(archive) if archive else "",
  )


def done(L: TransformerLaunch, job: launch_lib.Job) -> bool:
  """Whether `job` is done in the launch's DIR, or will be once the archive is restored: its run
  finished there with its noise test (`execute` trains a restored run without one again), and
  DIR holds no workdir of its own that would be resumed instead."""
  if job.done():
    return True
  if not L.archive or os.path.exists(job.workdir):
    return False
  rel = os.path.relpath(job.workdir, L.out)
  archived = dataclasses.replace(job, workdir=os.path.join(L.archive, rel))
  return archived.done() and dataclasses.replace(archived, kind="evaluate").done()


def print_plan(L: TransformerLaunch, *, commands: bool, at_once: int = 1) -> None:
  """The summary (runs, parameter counts, cost per step, estimate of what is not done yet, the
  archive's runs counted done); with `commands`, every job with its estimate."""
  fmt = progress_lib.format_duration
  plan = L.plan
  todo = [j for j in L.synth + L.noise if not done(L, j)]
  est = (sum(j.estimate_s for j in todo) + L.table.estimate_s) / at_once
  cols = columns(plan, L.data)
  at = f", {at_once} jobs at a time at best" if at_once > 1 else ""
  print(
    f"{plan.name} transformer comparison into {L.out}: {len(plan.cameras)} conditionings x "
    f"{len(plan.seeds)} seeds x {len(cols)} columns ({', '.join(cols)}) = {len(L.synth)} "
    f"view-synthesis runs, {len(L.noise)} noise tests, 1 table; estimated {fmt(est)} for what "
    f"is not done yet ({plan.where}){at}.",
    flush=True,
  )
  if not L.data and settings_lib.CAR.name in map(setting_of, plan.columns):
    print(
      f"  no capture column: add --data {plan.capture} (the car setting on a shared capture)",
      flush=True,
    )
  for c in cols:
    steps = plan.total_steps(c)
    per = plan.step_s[c if c in COLUMNS else "capture"]
    print(
      f"  {c}: {plan.config}:{plan.variant(c)}, {steps} steps at ~{per:g} s a step "
      f"(+{plan.run_overhead_s:g} s a run) = ~{fmt(plan.run_s(c))} a run",
      flush=True,
    )
  counts = parameter_counts(plan)
  trunk = min(v["model"] for v in counts.values())
  print(
    f"  parameters (rooms; the trunk of {trunk:,} is shared, the difference is the "
    "conditioning's own input projection and learned pose system, not matched by width):",
    flush=True,
  )
  for camera, v in counts.items():
    extra = v["model"] - trunk + v["rep"]
    print(
      f"    {camera:12s} model {v['model']:>9,} rep {v['rep']:>6,} total "
      f"{v['model'] + v['rep']:>9,} (+{extra:,}, {100 * extra / trunk:.1f}%)",
      flush=True,
    )
  if not commands:
    return
  for j in L.synth + L.noise:
    print(f"[{'done' if done(L, j) else '~' + fmt(j.estimate_s)}] {j.command()}")
  print(f"[~{fmt(L.table.estimate_s)}] {L.table.command()}")


def execute(L: TransformerLaunch, *, at_once: int = 1, deadline: float | None = None):
  """Runs what is not done: the noise tests of runs finished before, each training run followed
  by its noise test, the table; with an archive, the records, the table and the figure are
  copied into it after each of those, so that its table is always that of its records.
  Returns the names of the jobs that failed."""
  logs = os.path.join(L.out, "logs")
  noise_of = {s.name: n for s, n in zip(L.synth, L.noise, strict=True)}
  for s in L.synth:  # a restored record cannot take its noise test: no checkpoints
    if launch_lib.archived_only(s.workdir) and not noise_of[s.name].done():
      print(
        f"[transformer] {s.name}: its record is from the archive, without its noise test; "
        "training it again",
        flush=True,
      )
      shutil.rmtree(s.workdir)
  env = launch_lib.job_env(at_once)
  archiving = threading.Lock()  # one table at a time (jobs may run side by side)

  def archive(_=None) -> None:
    if L.archive:
      with archiving:
        launch_lib.run_job(L.table, logs, index="table", env=env)  # a failure shows at the end
        archive_lib.sync(L.out, L.archive)

  failed_noise = []

  def then_noise(job: launch_lib.Job) -> None:  # in the run's own worker, as soon as it ends
    archive()
    noise = noise_of[job.name]
    if not noise.done():
      if not launch_lib.run_job(noise, logs, index=f"noise of {job.name}", env=env):
        failed_noise.append(noise.name)
      archive()

  kw = dict(at_once=at_once, deadline=deadline)
  if L.archive:
    archive_lib.sync(L.out, L.archive)
  # The noise tests of runs that finished before this launch, then each run with its own.
  ready = [n for n, s in zip(L.noise, L.synth, strict=True) if s.done()]
  failed = launch_lib.run_jobs(ready, logs, label="noise: ", after=archive, **kw)
  failed += launch_lib.run_jobs(L.synth, logs, label="transformer: ", after=then_noise, **kw)
  failed += failed_noise
  failed += launch_lib.run_jobs([L.table], logs, label="", **{**kw, "at_once": 1})
  if L.archive:
    archive_lib.sync(L.out, L.archive)
  return failed

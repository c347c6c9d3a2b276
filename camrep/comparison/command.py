"""The command line of the comparison launcher, `python -m camrep.comparison --size SIZE --out DIR`
(see the package docstring); `--dry_run` prints every command with its estimate."""

from __future__ import annotations

import argparse
import dataclasses
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence

from camrep.comparison import archive as archive_lib
from camrep.comparison import launch as launch_lib
from camrep.comparison import plan as plan_lib
from camrep.comparison import transformer
from camrep.regression import tables
from camrep.runtime import cli
from camrep.runtime import progress as progress_lib
from camrep.runtime import workdir as workdir_lib

NOISE_KINDS = plan_lib.NOISE_INPUTS


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
  """The command line, checked (exit 2 with `error:` on a mistake)."""
  sizes = plan_lib.plans()
  p = argparse.ArgumentParser(
    prog="python -m camrep.comparison", description=__doc__.splitlines()[0]
  )
  p.add_argument(
    "--size",
    choices=sorted(sizes) + sorted(transformer.plans()),
    default="quick",
    help="a regression plan, or a transformer plan (lvsm_*: camera conditionings, configs/lvsm.py)",
  )
  p.add_argument("--out", required=True, help="output directory (synthesis/, regression/, ...)")
  p.add_argument("--dry_run", action="store_true", help="print the commands and estimates only")
  p.add_argument(
    "--settings",
    default="",
    help="comma-separated subset (default: all; a transformer plan's columns by their setting: "
    "gqn the rooms, car the car and the captures)",
  )
  p.add_argument(
    "--representations",
    default="",
    help="comma-separated subset (default: all; a transformer plan's camera conditionings)",
  )
  p.add_argument("--full_grid", action="store_true", help="every seed at every learning rate")
  p.add_argument(
    "--no_vectorise",
    action="store_true",
    help="one process per regression run, seed by seed, where the plan trains a column's runs as "
    "one program (converge, medium)",
  )
  p.add_argument("--skip_figures", action="store_true", help="no evaluations or noise figures")
  p.add_argument(
    "--noise_runs",
    action="store_true",
    help="also train the noise figures' other pose inputs (a setting's noise_inputs in "
    "camrep/comparison/plans.toml, those of --noise_kinds)",
  )
  p.add_argument(
    "--noise_kinds",
    default=",".join(NOISE_KINDS),
    help="with --noise_runs: which other pose inputs / generators (ConvDRAW: GQN's layout only, "
    "not at medium size)",
  )
  p.add_argument(
    "--data",
    action="append",
    default=[],
    metavar="SETTING=DIR",
    help="run SETTING on real data prepared in DIR, or add a capture column car_NAME=SOURCE:DIR "
    "(repeatable)",
  )
  p.add_argument(
    "--max_hours", type=float, default=0.0, help="start no run after this many hours (0: no limit)"
  )
  p.add_argument("--python", default=sys.executable, help="interpreter of the subprocesses")
  p.add_argument("--jobs", type=int, default=1, help="subprocesses at once within each step")
  p.add_argument(
    "--extend_grid",
    type=int,
    default=None,
    metavar="N",
    help="sizes with a stopping rule: how many lrs beyond its grid phase 1 may try while seed "
    "0's choice sits at an edge (default: the plan's)",
  )
  p.add_argument(
    "--crossed",
    default="",
    metavar="COLUMN",
    help="converge size: also cross the seeds of COLUMN's ours and write DIR/seed_spread_COLUMN.md",
  )
  p.add_argument(
    "--archive",
    default="",
    metavar="DIR",
    help="keep each finished run's record in DIR (e.g. results/converge) and start by restoring "
    "the runs DIR holds: a launch cut short resumes on another machine",
  )
  args = p.parse_args(argv)
  kinds = [k.strip() for k in args.noise_kinds.split(",") if k.strip()]
  if set(kinds) - set(NOISE_KINDS):
    p.error(
      f"--noise_kinds: unknown {sorted(set(kinds) - set(NOISE_KINDS))}; choose from {NOISE_KINDS}"
    )
  args.noise_kinds = kinds if args.noise_runs else []
  args.settings = [s.strip() for s in args.settings.split(",") if s.strip()] or list(
    plan_lib.SETTINGS
  )
  unknown = sorted(set(args.settings) - set(plan_lib.SETTINGS))
  if unknown:
    p.error(f"unknown settings {unknown}; choose from {plan_lib.SETTINGS}")
  args.representations = [r.strip() for r in args.representations.split(",") if r.strip()]
  if args.jobs < 1:
    p.error(f"--jobs must be at least 1, got {args.jobs}")
  for flag, path in (("--out", args.out), ("--archive", args.archive)):
    if path and os.path.exists(path) and not os.path.isdir(path):
      p.error(f"{flag} {path} is a file, not a directory")
  args.data = _data(p, args.data)
  if args.size in transformer.plans():
    args.plan = transformer.plans()[args.size]
    _check_transformer_args(p, args)
    return args
  plan = sizes[args.size]
  if args.extend_grid is not None:
    if args.extend_grid < 0 or not plan.stop:
      p.error(f"--extend_grid {args.extend_grid}: a count >= 0, at a size with a stopping rule")
    plan = dataclasses.replace(plan, extend_grid=args.extend_grid)
  args.plan = plan
  offered = {r for s in args.settings for r in plan_lib.settings()[s]["representations"]}
  offered |= set(plan.controls)
  if set(args.representations) - offered:
    p.error(
      f"--representations: {sorted(set(args.representations) - offered)} not in the "
      f"{args.size} size's columns {args.settings}; choose from {sorted(offered)}"
    )
  if args.crossed:
    if not plan.paired_synthesis:
      p.error("--crossed needs a size with one synthesis run per seed (--size converge)")
    columns = args.settings + [c for c in args.data if c not in plan_lib.SETTINGS]
    if args.crossed not in columns or launch_lib.setting_of(args.crossed) not in args.settings:
      p.error(f"--crossed {args.crossed}: not a column of this launch ({columns})")
  return args


# Flags of the regression plans, refused with a transformer plan rather than ignored.
REGRESSION_ONLY = (
  "full_grid",
  "no_vectorise",
  "skip_figures",
  "noise_runs",
  "extend_grid",
  "crossed",
)


def _check_transformer_args(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
  """A transformer plan takes --settings (its columns by setting) and --representations (its
  cameras); the regression plans' own flags and real data for a setting are refused."""
  given = [f"--{a}" for a in REGRESSION_ONLY if getattr(args, a) != p.get_default(a)]
  if given:
    p.error(f"{', '.join(given)}: flags of the regression plans, not of --size {args.size}")
  settings = [c for c, v in args.data.items() if not isinstance(v, tuple)]
  if settings:
    p.error(
      f"--data {settings[0]}=DIR: --size {args.size} trains on its procedural columns and on "
      "capture columns (--data car_NAME=SOURCE:DIR)"
    )
  try:
    transformer.select(args.plan, args.settings, args.representations, args.data)
  except ValueError as e:
    p.error(str(e))


def _data(p: argparse.ArgumentParser, items: Sequence[str]) -> dict:
  """{setting: DIR} and {car_NAME: (SOURCE, DIR)} of the --data flags."""
  settings = plan_lib.SETTINGS
  data = {}
  for item in items:
    column, sep, path = item.partition("=")
    if sep and column.startswith("car_") and column[4:].isidentifier():
      source, colon, path = path.partition(":")
      if not colon or not source or not path:
        p.error(f"--data {item}: a capture column expects car_NAME=SOURCE:DIR (e.g. nerf:/data)")
    elif not sep or column not in settings or not path:
      p.error(
        f"--data expects SETTING=DIR with SETTING one of {settings} (or car_NAME=SOURCE:DIR for "
        f"a capture column), got {item!r}"
      )
    if not os.path.isdir(path):
      p.error(f"--data {item}: {path} is not a directory (prepare it with camrep.data.prepare)")
    data[column] = (
      (source, os.path.abspath(path)) if column not in settings else os.path.abspath(path)
    )
  return data


def make_launch(args: argparse.Namespace) -> launch_lib.Launch:
  """The launch that parsed arguments ask for."""
  try:
    return launch_lib.make_launch(
      args.plan,
      args.out,
      settings=args.settings,
      representations=args.representations,
      data=args.data,
      python=args.python,
      full_grid=args.full_grid or args.plan.full_grid,
      vectorise=not args.no_vectorise,
      skip_figures=args.skip_figures,
      noise_kinds=args.noise_kinds,
      crossed=args.crossed,
      archive=args.archive,
    )
  except ValueError as e:
    raise cli.UsageError(str(e)) from None


def regression_resumes() -> bool:
  """Whether a regression run stopped mid-way resumes from a checkpoint (its config has a
  checkpoint period) rather than starting over."""
  from camrep.configs import regression

  return "ckpt_every_steps" in regression.get_config("quick")


def interrupted_message(took: str, archive: str, regressions: bool = True) -> str:
  """What a stopped launch kept, and what becomes of its runs in flight (`regressions`: whether
  the plan has regression runs; a transformer plan has view-synthesis runs only)."""
  kept = f" and archived in {archive}" if archive else ""
  message = (
    f"interrupted after {took}: the runs that finished are kept{kept}. The runs in flight were "
    "stopped; when the same command is run again, view-synthesis runs resume from their last "
    "checkpoint"
  )
  if not regressions:
    return message
  if regression_resumes():
    return f"{message} and regression runs resume from their last checkpoint too"
  return f"{message} and regression runs start over (they keep no checkpoint)"


def _interrupt(signum, frame):
  raise KeyboardInterrupt


def _lock(out: str) -> workdir_lib.WorkdirLock:
  """The lock of a launch's DIR: a second launch on it refuses, naming the first."""
  os.makedirs(out, exist_ok=True)
  lock = workdir_lib.WorkdirLock(out)
  try:
    lock.acquire()
  except workdir_lib.WorkdirError:
    h = lock.holder() or {}
    raise cli.UsageError(
      f"--out {out} is in use by another launch (PID {h.get('pid', '?')} on "
      f"{h.get('host', '?')}, started {h.get('started', '?')}; {lock.path}). Wait for it to "
      "finish or use another --out; if that process is gone, delete the lock file."
    ) from None
  return lock


def _locked(out: str, archive: str, body, regressions: bool = True) -> tuple[list[str], str] | int:
  """Runs a launch's `body()` (-> the failed jobs' names) holding DIR's lock, with SIGTERM taken
  as Ctrl-C: (failed, the time it took as text), or 130 after a stop (one line on what is kept
  and how to resume, `interrupted_message`; `regressions`: whether the plan has any)."""
  lock = _lock(out)
  old_handler = signal.signal(signal.SIGTERM, _interrupt)
  t0 = time.perf_counter()
  try:
    failed = body()
  except KeyboardInterrupt:  # Ctrl-C, `kill`, or `timeout` around a chunk: a stop, not a crash
    took = progress_lib.format_duration(time.perf_counter() - t0)
    print(f"\n{interrupted_message(took, archive, regressions)}", file=sys.stderr, flush=True)
    return 130
  finally:
    signal.signal(signal.SIGTERM, old_handler)
    lock.release()
  return failed, progress_lib.format_duration(time.perf_counter() - t0)


def run(argv: Sequence[str] | None = None) -> int:
  """The launcher; returns its exit status (raises cli.UsageError on a user's mistake)."""
  args = parse_args(argv)
  if not os.path.isdir(os.path.join(launch_lib.ROOT, "configs")):
    raise cli.UsageError(
      f"the comparison runs from a camrep checkout (configs/, experiments/); {launch_lib.ROOT} "
      "is not one (install camrep with `pip install -e .` from a clone)"
    )
  if isinstance(args.plan, transformer.TransformerPlan):
    return run_transformer(args)
  launch = make_launch(args)
  if args.dry_run:

    def plan() -> None:
      if launch.archive and os.path.isdir(launch.archive):
        n = len(archive_lib.run_dirs(launch.archive))
        print(
          f"--archive {launch.archive}: its {n} runs are restored when the launch starts; this "
          f"dry run reads {launch.out} only: those it lacks show as not done",
          flush=True,
        )
      launch_lib.print_plan(launch, commands=True, at_once=args.jobs)

    return _dry_run(plan)
  deadline = None

  def body() -> list[str]:
    nonlocal deadline
    launch_lib.set_aside_stale(launch)  # before the archive's stale records come back
    if launch.archive:
      n = archive_lib.restore(launch.archive, launch.out)
      print(f"restored {n} finished runs from the archive {launch.archive}", flush=True)
    launch_lib.print_plan(launch, commands=False, at_once=args.jobs)
    deadline = time.monotonic() + 3600 * args.max_hours if args.max_hours > 0 else None
    return launch_lib.execute(launch, at_once=args.jobs, deadline=deadline)

  ran = _locked(launch.out, launch.archive, body)
  if isinstance(ran, int):
    return ran
  failed, took = ran
  if _stopped_at_deadline(args, deadline, took):
    return 1 if failed else 0
  if failed:
    print(f"finished in {took} with {len(failed)} failures: {', '.join(failed)}", flush=True)
    return 1
  print(
    f"finished in {took}; tables in {launch.out}/table1.md and {launch.out}/table2.md", flush=True
  )
  return 0


def _dry_run(print_plan: Callable[[], None]) -> int:
  """Prints a dry run's plan; a reader that closes the pipe early (`--dry_run | head -1`) has
  what it wanted: no traceback."""
  try:
    print_plan()
    sys.stdout.flush()
  except BrokenPipeError:
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
  return 0


def _stopped_at_deadline(args: argparse.Namespace, deadline: float | None, took: str) -> bool:
  """Whether the launch passed its --max_hours deadline (runs left unstarted); says so."""
  if deadline is None or time.monotonic() <= deadline:
    return False
  print(
    f"--max_hours {args.max_hours:g} reached after {took}: runs not started; run the same "
    "command again to resume",
    flush=True,
  )
  return True


def run_transformer(args: argparse.Namespace) -> int:
  """A transformer plan (`camrep.comparison.transformer`): its dry run, or its launch."""
  launch = transformer.make_launch(
    args.plan,
    args.out,
    python=args.python,
    data=args.data,
    archive=args.archive,
    settings=args.settings,
    cameras=args.representations,
  )
  if args.dry_run:
    return _dry_run(lambda: transformer.print_plan(launch, commands=True, at_once=args.jobs))

  deadline = None

  def body() -> list[str]:
    nonlocal deadline
    if launch.archive:
      n = archive_lib.restore(launch.archive, launch.out)
      print(f"restored {n} finished runs from the archive {launch.archive}", flush=True)
    transformer.print_plan(launch, commands=False, at_once=args.jobs)
    deadline = time.monotonic() + 3600 * args.max_hours if args.max_hours > 0 else None
    return transformer.execute(launch, at_once=args.jobs, deadline=deadline)

  ran = _locked(launch.out, launch.archive, body, regressions=False)
  if isinstance(ran, int):
    return ran
  failed, took = ran
  if _stopped_at_deadline(args, deadline, took):
    return 1 if failed else 0
  if failed:
    print(f"finished in {took} with {len(failed)} failures: {', '.join(failed)}", flush=True)
    return 1
  print(f"finished in {took}; table in {launch.out}/lvsm_table.md", flush=True)
  return 0


def main(argv: Sequence[str] | None = None) -> int:
  """`run` with a user's mistake (or runs that cannot be tabled: two runs of one cell) on one
  `error:` line (exit 2)."""
  try:
    return run(argv)
  except (cli.UsageError, tables.TableError) as e:
    sys.stdout.flush()
    print(f"error: {e}", file=sys.stderr, flush=True)
    return 2

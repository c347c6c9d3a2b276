"""Benchmark: a grid of regression runs (seeds x lrs) as one vectorised program against the same
runs one after another (`camrep.regression.vectorised`).

Builds every member of `configs/regression.py:<setting>,<variant>` at `--seeds` x `--lrs` (its
seed's init and batches, its lr), then times, interleaved in one process `--rounds` times (these
machines are shared: compare the ratio of one run):

  grid        `vectorised.group_step(1, program)` for each of `--programs`: "loop" (one jitted
              step shared by the members, called member by member on their own states),
              "unrolled" (each member's step side by side in one jitted program) and "vmap" (one
              `jax.vmap` of `learner.train_step` over the members' stacked states and batches),
              `--steps` steps of all M members;
  sequential  each member's own jitted `learner.train_step` (the single run's), `--steps` steps,
              member after member.

Batches are built before the timing (each seed's first `--steps` batches, laid out as each
program takes them): the figures are the programs', not the host's. Compilation is left out (each
side warmed up first). Printed per round and as the median over rounds: member-steps per second of
each side, the grid's steps per second per member (every member advances at that rate), the
single run's own rate, and the speedup (the sequential side's time over the grid's, for the same
member-steps); the load average (`os.getloadavg`) before and after. The last line reads
`speedup=<median> program=<the faster> grid_member_steps_per_s=<median>
sequential_member_steps_per_s=<median>`.

With `--host_devices=N` (N > 1) the two sides run in two processes, built one after the other and
timed in turn (`Children`): the group's "loop" program where the CPU shows N one-thread host
devices (its members placed over them, as `camrep.regression.vectorised` does on a CPU), the runs
alone where it shows one device on a thread pool of every core, as a single run trains. Batches
are built before the timing: the figures leave out the host's data work and the evaluations,
which a whole grid command pays (BUILD_NOTES.md has both).

Commands (2-core CPU; ~5 min each with the car's data rendered once into the cache):

  .venv/bin/python -m camrep.bench.regression_grid --setting=car --variant=quick --steps=10 \\
    --rounds=3
  .venv/bin/python -m camrep.bench.regression_grid --setting=car --variant=quick --seeds=0,1 \\
    --lrs=1e-3,1e-2 --steps=20 --rounds=3 --programs=loop --host_devices=2
"""

from __future__ import annotations

import argparse
import os
import time


def _parse(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--setting", default="car", help="configs/regression.py setting")
  p.add_argument("--variant", default="quick", help="configs/regression.py variant")
  p.add_argument("--representation", default="quat", help="a baseline (no synthesis workdir)")
  p.add_argument("--seeds", default="0,1,2", help="the grid's seeds")
  p.add_argument("--lrs", default="3e-4,1e-3,3e-3,1e-2", help="the grid's learning rates")
  p.add_argument("--steps", type=int, default=10, help="timed steps per side per round")
  p.add_argument("--rounds", type=int, default=3, help="interleaved repeats")
  p.add_argument(
    "--programs",
    default="loop,unrolled,vmap",
    help="group step forms (camrep.regression.vectorised)",
  )
  p.add_argument("--cache", default="/tmp/camrep_bench_regression_cache", help="data cache")
  p.add_argument(
    "--host_devices",
    type=int,
    default=1,
    help="N > 1: the group in a process whose CPU shows N one-thread host devices "
    "(camrep.runtime.xla_cpu), the runs alone in another on the default single device",
  )
  p.add_argument("--child", choices=("grid", "sequential"), help=argparse.SUPPRESS)
  args = p.parse_args(argv)
  if args.host_devices < 1:
    p.error(f"--host_devices must be >= 1, got {args.host_devices}")
  if args.host_devices > 1 and set(args.programs.split(",")) - {"loop"}:
    p.error("--host_devices > 1 times --programs=loop only (the others' stacked members would run "
            "on one one-thread device)")  # fmt: skip
  return args


RESULT = "RESULT "
"""The prefix of a child's answers on its stdout (other lines, a library's prints, are skipped)."""


class Children:
  """The two sides of `--host_devices` N > 1 in two processes, each built alone, then timed in
  turn: the group's "loop" program where the CPU shows N one-thread host devices (the members
  placed over them, as `vectorised._Group`), the runs alone where it shows one device on a thread
  pool of every core (as a single run trains). `round()` as `GridTimer`'s.

  Raises:
    RuntimeError: a child ended without its answer (its error is on stderr above); both stopped.
  """

  def __init__(self, argv: list[str], host_devices: int, *, log=print):
    import subprocess
    import sys

    from camrep.runtime import xla_cpu

    grid_env = dict(os.environ)
    xla_cpu.host_devices(host_devices, grid_env)
    self._procs, self.compile_s = {}, {}
    try:
      for side, env in (("grid", grid_env), ("sequential", None)):
        cmd = [sys.executable, "-m", "camrep.bench.regression_grid", *argv, f"--child={side}"]
        self._procs[side] = proc = subprocess.Popen(
          cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, text=True
        )
        ready = self._answer(side, proc)  # built before the other starts: compiles alone
        log(f"{side} process: devices {ready['devices']}")
        if side == "grid":
          self.members, self.steps = ready["members"], ready["steps"]
          self.programs = tuple(ready["programs"])
        self.compile_s |= ready["compile_s"]
    except BaseException:
      self.kill()
      raise

  @staticmethod
  def _answer(side: str, proc) -> dict:
    import json

    for line in proc.stdout:
      if line.startswith(RESULT):
        return json.loads(line.removeprefix(RESULT))
    raise RuntimeError(f"the {side} process ended (exit {proc.wait()}); its error is above")

  def round(self) -> dict[str, float]:
    row = {}
    try:
      for side, proc in self._procs.items():  # one side at a time: the other waits
        proc.stdin.write("round\n")
        proc.stdin.flush()
        row |= self._answer(side, proc)
    except BaseException:
      self.kill()
      raise
    return row

  def kill(self) -> None:
    for proc in self._procs.values():
      if proc.poll() is None:
        proc.kill()
      proc.wait()

  def close(self) -> None:
    """Ends both children.

    Raises:
      RuntimeError: one exited with an error."""
    for proc in self._procs.values():
      if proc.poll() is None:
        proc.stdin.close()
    failed = {side: rc for side, proc in self._procs.items() if (rc := proc.wait()) != 0}
    if failed:
      raise RuntimeError(f"benchmark processes exited with errors: {failed}")


def _child(args, timer_args: dict) -> None:
  """One side of `Children`: builds its timer, says so (a `RESULT` line), then times a round per
  "round" line of stdin until it closes."""
  import json
  import sys

  import jax

  grid = args.child == "grid"
  side = {"programs": timer_args["programs"] if grid else (), "sequential": not grid}
  timer = GridTimer(**(timer_args | side), log=lambda s: print(s, file=sys.stderr, flush=True))
  ready = {
    "members": timer.members, "steps": timer.steps, "programs": list(timer.programs),
    "compile_s": timer.compile_s, "devices": [str(d) for d in jax.local_devices()],
  }  # fmt: skip
  print(RESULT + json.dumps(ready), flush=True)
  for line in sys.stdin:
    if line.strip() == "round":
      print(RESULT + json.dumps(timer.round()), flush=True)


class GridTimer:
  """The members of a grid, their single-run steps and the vectorised group step, ready to time.

  Attributes:
    members: M, the grid's size.
    programs: the group step's forms timed (`vectorised.group_step`).
    compile_s: {program, "sequential"} seconds of the first (compiling) call of each side.
  """

  def __init__(self, setting: str, *, variant: str, representation: str, seeds, lrs,
               steps: int, programs=("loop", "unrolled", "vmap"), sequential: bool = True,
               cache_dir: str = "", log=print):  # fmt: skip
    import jax
    import numpy as np

    from camrep.configs import regression
    from camrep.regression import driver, learner, vectorised
    from camrep.regression import views as views_lib

    config = regression.get_config(f"{setting},{variant}")
    config.representation = representation
    config.data.cache_dir = cache_dir
    specs = vectorised.members(config, "", list(lrs), list(seeds))
    data, states, batches = None, [], {}
    for _, run in specs:
      c = run.config
      setup = driver.prepare(run, log=log, data=data)
      data = setup.data
      stage = driver.RegressionStage(setup, {}, predict_fn=None)
      states.append(stage.init())
      if c.seed not in batches:  # step k trains on batch k - 1 (`RegressionStage.chunks`)
        batches[c.seed] = [
          views_lib.learner_batch(setup.batching, data.train, stage.pipe.batch(i))
          for i in range(steps)
        ]
    configs = [r.config for _, r in specs]
    self.members, self.steps, self.programs = len(specs), steps, tuple(programs)
    self.sequential = sequential
    step = lambda: jax.jit(learner.train_step, donate_argnums=0)  # noqa: E731 - one per member
    self._single = [
      (step(), s, [jax.device_put(b) for b in batches[c.seed]])
      for s, c in zip(states, configs, strict=True)
    ] if sequential else []  # fmt: skip
    unit = vectorised._unit(states)
    lrs = [c.optax.lr for c in configs]
    # As the grid's program holds them (`vectorised._Group`): the loop's own states (copies: it
    # donates them) placed in turn over the local devices, each seed's batch once on each of its
    # members' devices; the others' stacked.
    where = vectorised.place(len(configs), jax.local_devices())
    self._groups, self._rates, self._batches = {}, {}, {}
    for p in programs:
      if vectorised.listed(p):
        own = [
          jax.device_put(jax.tree.map(jax.numpy.copy, s), d)
          for s, d in zip(unit, where, strict=True)
        ]
        self._groups[p] = [vectorised.group_step(1, p), own]
        self._rates[p] = [np.float32(x) for x in lrs]
        on = {
          (c.seed, d): [jax.device_put(b, d) for b in batches[c.seed]]
          for c, d in zip(configs, where, strict=True)
        }
        self._batches[p] = [
          [on[c.seed, d][i] for c, d in zip(configs, where, strict=True)] for i in range(steps)
        ]
      else:
        self._groups[p] = [vectorised.group_step(1, p), vectorised.stack(unit)]
        self._rates[p] = jax.numpy.asarray(lrs, jax.numpy.float32)
        self._batches[p] = [
          jax.device_put(vectorised.stack([batches[c.seed][i] for c in configs]))
          for i in range(steps)
        ]
    self.compile_s = {}
    for p in programs:
      t = time.perf_counter()
      self.time_grid(p, 1)
      self.compile_s[p] = time.perf_counter() - t
    if sequential:
      t = time.perf_counter()
      self.time_sequential(1)
      self.compile_s["sequential"] = time.perf_counter() - t

  def round(self) -> dict[str, float]:
    """One round's seconds: {program: `time_grid`, "sequential": `time_sequential`}, those it
    times."""
    row = {p: self.time_grid(p) for p in self.programs}
    return row | ({"sequential": self.time_sequential()} if self.sequential else {})

  def time_grid(self, program: str, steps: int | None = None) -> float:
    """Seconds of `steps` (default all) group steps (`program`) of every member."""
    import jax

    fn, states = self._groups[program]
    t = time.perf_counter()
    for b in self._batches[program][: steps or self.steps]:
      states, m, _ = fn(states, b, self._rates[program])
    jax.block_until_ready((states, m))
    self._groups[program][1] = states
    return time.perf_counter() - t

  def time_sequential(self, steps: int | None = None) -> float:
    """Seconds of `steps` (default all) single-run steps of each member, one after another."""
    import jax

    total = 0.0
    for i, (step, state, bs) in enumerate(self._single):
      t = time.perf_counter()
      for b in bs[: steps or self.steps]:
        state, m = step(state, b)
      jax.block_until_ready((state.params, m))
      total += time.perf_counter() - t
      self._single[i] = (step, state, bs)
    return total


def measure(timer: GridTimer | Children, *, rounds: int, log=print) -> dict:
  """Times every side `rounds` times, interleaved (each program of the group, then the members
  one after another); returns per-round rows and, per program, the medians over rounds:
  {program: {"member_steps_per_s", "steps_per_s_per_member", "speedup"}, "sequential":
  {"member_steps_per_s"}, "rounds": [...]}."""
  import numpy as np

  rows = []
  work = timer.members * timer.steps
  for r in range(rounds):
    row = timer.round()
    rows.append(row)
    log(
      f"round {r + 1}: sequential {work / row['sequential']:.1f} member-steps/s; "
      + "; ".join(
        f"{p} {work / row[p]:.1f} member-steps/s ({timer.steps / row[p]:.2f} steps/s per "
        f"member), speedup {row['sequential'] / row[p]:.2f}x"
        for p in timer.programs
      )
    )
  med = lambda f: float(np.median([f(r) for r in rows]))  # noqa: E731
  out = {"sequential": {"member_steps_per_s": med(lambda r: work / r["sequential"])}}
  for p in timer.programs:
    out[p] = {
      "member_steps_per_s": med(lambda r, p=p: work / r[p]),
      "steps_per_s_per_member": med(lambda r, p=p: timer.steps / r[p]),
      "speedup": med(lambda r, p=p: r["sequential"] / r[p]),
    }
  return out | {"rounds": rows}


def main(argv=None) -> None:
  import sys

  args = _parse(argv)
  seeds = [int(x) for x in args.seeds.split(",")]
  lrs = [float(x) for x in args.lrs.split(",")]
  timer_args = dict(
    setting=args.setting, variant=args.variant, representation=args.representation, seeds=seeds,
    lrs=lrs, steps=args.steps, programs=args.programs.split(","), cache_dir=args.cache,
  )  # fmt: skip
  if args.child:
    _child(args, timer_args)
    return
  load0 = os.getloadavg()
  print(f"load average before: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}", flush=True)
  if args.host_devices > 1:  # the sides in two processes: XLA_FLAGS are read once per process
    given = sys.argv[1:] if argv is None else list(argv)
    timer = Children(given, args.host_devices, log=lambda s: print(s, flush=True))
  else:
    timer = GridTimer(**timer_args, log=lambda s: print(s, flush=True))
  print(
    f"{args.setting},{args.variant} {args.representation}: {timer.members} members "
    f"({len(seeds)} seeds x {len(lrs)} lrs), {args.steps} steps per side per round"
    + (f", the group on {args.host_devices} host devices" if args.host_devices > 1 else "")
    + "; first calls (compile): "
    + ", ".join(f"{k} {v:.1f} s" for k, v in timer.compile_s.items()),
    flush=True,
  )
  out = measure(timer, rounds=args.rounds, log=lambda s: print(s, flush=True))
  if isinstance(timer, Children):
    timer.close()
  load1 = os.getloadavg()
  print(f"load average after: {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}", flush=True)
  seq = out["sequential"]["member_steps_per_s"]
  print(
    f"median over {args.rounds} rounds: sequential {seq:.1f} member-steps/s (a single run "
    f"{seq:.1f} steps/s); "
    + "; ".join(
      f"{p} {out[p]['member_steps_per_s']:.1f} member-steps/s "
      f"({out[p]['steps_per_s_per_member']:.2f} steps/s per member), speedup "
      f"{out[p]['speedup']:.2f}x"
      for p in timer.programs
    ),
    flush=True,
  )
  best = max(timer.programs, key=lambda p: out[p]["speedup"])
  print(
    f"speedup={out[best]['speedup']:.2f} program={best} "
    f"grid_member_steps_per_s={out[best]['member_steps_per_s']:.1f} "
    f"sequential_member_steps_per_s={seq:.1f}",
    flush=True,
  )


if __name__ == "__main__":
  main()

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

Command (2-core CPU; ~5 min with the car's data rendered once into the cache):

  .venv/bin/python -m camrep.bench.regression_grid --setting=car --variant=quick --steps=10 \\
    --rounds=3
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
  return p.parse_args(argv)


class GridTimer:
  """The members of a grid, their single-run steps and the vectorised group step, ready to time.

  Attributes:
    members: M, the grid's size.
    programs: the group step's forms timed (`vectorised.group_step`).
    compile_s: {program, "sequential"} seconds of the first (compiling) call of each side.
  """

  def __init__(self, setting: str, *, variant: str, representation: str, seeds, lrs,
               steps: int, programs=("loop", "unrolled", "vmap"), cache_dir: str = "",
               log=print):  # fmt: skip
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
    step = lambda: jax.jit(learner.train_step, donate_argnums=0)  # noqa: E731 - one per member
    self._single = [
      (step(), s, [jax.device_put(b) for b in batches[c.seed]])
      for s, c in zip(states, configs, strict=True)
    ]
    unit = vectorised._unit(states)
    lrs = [c.optax.lr for c in configs]
    # As the grid's program holds them (`vectorised._Group`): the loop's own states (copies: it
    # donates them) and each seed's batch once on the device; the others' stacked.
    self._groups, self._rates, self._batches = {}, {}, {}
    for p in programs:
      if vectorised.listed(p):
        own = [jax.tree.map(jax.numpy.copy, s) for s in unit]
        self._groups[p] = [vectorised.group_step(1, p), own]
        self._rates[p] = [np.float32(x) for x in lrs]
        on_device = {k: [jax.device_put(b) for b in bs] for k, bs in batches.items()}
        self._batches[p] = [[on_device[c.seed][i] for c in configs] for i in range(steps)]
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
    t = time.perf_counter()
    self.time_sequential(1)
    self.compile_s["sequential"] = time.perf_counter() - t

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


def measure(timer: GridTimer, *, rounds: int, log=print) -> dict:
  """Times every side `rounds` times, interleaved (each program of the group, then the members
  one after another); returns per-round rows and, per program, the medians over rounds:
  {program: {"member_steps_per_s", "steps_per_s_per_member", "speedup"}, "sequential":
  {"member_steps_per_s"}, "rounds": [...]}."""
  import numpy as np

  rows = []
  work = timer.members * timer.steps
  for r in range(rounds):
    row = {p: timer.time_grid(p) for p in timer.programs}
    row["sequential"] = timer.time_sequential()
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
  args = _parse(argv)
  seeds = [int(x) for x in args.seeds.split(",")]
  lrs = [float(x) for x in args.lrs.split(",")]
  load0 = os.getloadavg()
  print(f"load average before: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}", flush=True)
  timer = GridTimer(
    args.setting, variant=args.variant, representation=args.representation, seeds=seeds,
    lrs=lrs, steps=args.steps, programs=args.programs.split(","), cache_dir=args.cache,
    log=lambda s: print(s, flush=True),
  )  # fmt: skip
  print(
    f"{args.setting},{args.variant} {args.representation}: {timer.members} members "
    f"({len(seeds)} seeds x {len(lrs)} lrs), {args.steps} steps per side per round; first "
    "calls (compile): " + ", ".join(f"{k} {v:.1f} s" for k, v in timer.compile_s.items()),
    flush=True,
  )
  out = measure(timer, rounds=args.rounds, log=lambda s: print(s, flush=True))
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

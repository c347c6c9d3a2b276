"""Benchmark: the cost of a training step of the multi-view transformer under each camera
conditioning (configs/lvsm.py, `--config.model.camera`), in one process.

Builds the train step of every `--cameras` conditioning at `--variant` (`train_step.StepTimer`: the
pmapped `camrep.synthesis.step` step on the config's batch, compiled and warmed up once), then
times them interleaved `--rounds` times, `--steps` steps each (these machines are shared: compare
the ratios of one run, not figures of two). Printed per conditioning: parameters of the model and
of its learned pose system, compile seconds, seconds per step (median over rounds of each round's
median; min-max), analytic FLOPs per step (`camrep.runtime.flops`), and the time ratio to
`--baseline` (raymap, the comparison's baseline). The comparison's table reads the cost from each
run's own log (machine and load as the run had them); this is the like-for-like figure. The load
average is printed before and after. The last line reads `baseline=<name> <camera>=<ratio> ...`.

  .venv/bin/python -m camrep.bench.conditionings --variant=quick --steps=5 --rounds=3
"""

from __future__ import annotations

import argparse
import os


def _parse(argv=None):
  from camrep.synthesis import conditionings

  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--variant", default="quick", help="configs/lvsm.py variant (quick, object, ...)")
  p.add_argument("--cameras", default=",".join(conditionings.CONDITIONINGS), help="conditionings")
  p.add_argument("--baseline", default="raymap", help="the conditioning the ratios are against")
  p.add_argument("--steps", type=int, default=5, help="timed steps per conditioning per round")
  p.add_argument("--rounds", type=int, default=3, help="interleaved repeats")
  args = p.parse_args(argv)
  args.cameras = [c.strip() for c in args.cameras.split(",") if c.strip()]
  unknown = sorted(set(args.cameras) - set(conditionings.CONDITIONINGS))
  if unknown:
    p.error(f"unknown cameras {unknown}; choose from {', '.join(conditionings.CONDITIONINGS)}")
  if args.baseline not in args.cameras:
    p.error(f"--baseline {args.baseline} is not among --cameras")
  if args.steps < 1 or args.rounds < 1:
    p.error("--steps and --rounds must be at least 1")
  return args


def timers(variant: str, cameras: list[str], log=print) -> dict:
  """{camera: StepTimer} of configs/lvsm.py:`variant`, one per conditioning, built in turn."""
  from camrep.bench import train_step as bts
  from camrep.configs import lvsm

  out = {}
  for camera in cameras:
    config = lvsm.get_config(variant)
    config.model.camera = camera
    out[camera] = bts.StepTimer(config)
    log(f"{camera}: compiled in {out[camera].compile_s:.1f} s")
  return out


def measure(timers: dict, *, steps: int, rounds: int) -> dict:
  """Each timer's seconds per step, interleaved: {camera: {"sec", "min", "max", "flops"}}, the
  median over rounds of each round's median step, and the extremes of the rounds' medians."""
  import numpy as np

  per = {c: [] for c in timers}
  for _ in range(rounds):
    for camera, t in timers.items():
      per[camera].append(float(np.median(t.times(steps))))
  return {
    c: {"sec": float(np.median(v)), "min": min(v), "max": max(v), "flops": timers[c].flops}
    for c, v in per.items()
  }


def main(argv=None) -> None:
  args = _parse(argv)
  from camrep.comparison import transformer

  load0 = os.getloadavg()
  print(f"load average before: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}", flush=True)
  built = timers(args.variant, args.cameras, log=lambda s: print(s, flush=True))
  out = measure(built, steps=args.steps, rounds=args.rounds)
  load1 = os.getloadavg()
  print(f"load average after: {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}", flush=True)
  plan = transformer.plans()["lvsm_quick"]
  column = "car" if args.variant == "object" else "rooms"
  counts = (
    transformer.parameter_counts(plan, column) if args.variant == plan.variant(column) else {}
  )
  base = out[args.baseline]["sec"]
  print(
    f"configs/lvsm.py:{args.variant}, {built[args.baseline].images} images a step, median over "
    f"{args.rounds} rounds of {args.steps} steps:",
    flush=True,
  )
  print("| camera | params (model / rep) | compile s | s / step (min-max) | GFLOP / step | "
        f"time / {args.baseline} |")  # fmt: skip
  print("|---|---|---|---|---|---|")
  for camera, r in out.items():
    n = counts.get(camera)
    params = f"{n['model']:,} / {n['rep']:,}" if n else "-"
    print(
      f"| {camera} | {params} | {built[camera].compile_s:.1f} | {r['sec']:.3f} "
      f"({r['min']:.3f}-{r['max']:.3f}) | {r['flops'] / 1e9:.1f} | {r['sec'] / base:.2f} |",
      flush=True,
    )
  ratios = " ".join(f"{c}={r['sec'] / base:.3f}" for c, r in out.items())
  print(f"baseline={args.baseline} {ratios}", flush=True)


if __name__ == "__main__":
  main()

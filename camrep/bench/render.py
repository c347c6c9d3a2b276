"""Benchmarks the procedural renderer: images per second per family and image size.

Command (about 30 s on an idle 2-core CPU; each line compiles once, then times --batches calls):
  python -m camrep.bench.render
  python -m camrep.bench.render --families rooms object --sizes 64 128 --batches 5

Each family renders its own first scene (small preset) at its batch size and supersample 1.
By default: every family at its default image size (rooms 64, others 128) plus rooms at 128.
The compile time (first call, includes tracing) is printed separately from the steady rate,
which is measured after warm-up with `block_until_ready`.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import jax
import numpy as np

from camrep.data import procedural
from camrep.data.procedural import render


def bench(name: str, size: int | None, batches: int) -> dict:
  """Times `render.render_batch` for one family and image size.

  Args:
    name: family name.
    size: image size (None: the family's default).
    batches: timed calls after the warm-up call.

  Returns:
    Dict with family, size, batch, compile_s and images_per_s.
  """
  size = size or procedural.make_config(name).image_size
  family = procedural.make_family(name, "small", image_size=size)
  bs = family.config.batch_size
  poses = family.poses("train", 0)
  poses = np.resize(poses, (bs, poses.shape[1]))
  c2w = family.poses_to_c2w(0, poses)
  scenes = render.stack_scenes([family.scene(0)] * bs)

  def call():
    return render.render_batch(scenes, c2w, family.camera, shadows=family.config.shadows)

  t0 = time.perf_counter()
  call().block_until_ready()
  compile_s = time.perf_counter() - t0
  t0 = time.perf_counter()
  for _ in range(batches):
    call().block_until_ready()
  rate = batches * bs / (time.perf_counter() - t0)
  return dict(family=name, size=size, batch=bs, compile_s=compile_s, images_per_s=rate)


def main(argv: Sequence[str] | None = None) -> None:
  """Command-line entry point (see the module docstring)."""
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--families", nargs="+", default=None, choices=procedural.FAMILIES)
  parser.add_argument(
    "--sizes", nargs="+", type=int, default=None, help="default: each family's own"
  )
  parser.add_argument("--batches", type=int, default=3)
  args = parser.parse_args(argv)
  if args.families is None and args.sizes is None:
    runs = [(f, None) for f in procedural.FAMILIES] + [("rooms", 128)]
  else:
    runs = [(f, s) for f in args.families or procedural.FAMILIES for s in args.sizes or [None]]
  print(f"jax {jax.__version__} on {jax.devices()[0].platform}")
  print(f"{'family':<10} {'size':>5} {'batch':>6} {'compile s':>10} {'images/s':>9}")
  for name, size in runs:
    r = bench(name, size, args.batches)
    cols = f"{r['family']:<10} {r['size']:>5} {r['batch']:>6}"
    print(f"{cols} {r['compile_s']:>10.1f} {r['images_per_s']:>9.1f}")


if __name__ == "__main__":
  main()

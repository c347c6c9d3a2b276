"""`python -m camrep.synthesis.evaluate`: noise robustness and Gram maps of a trained run (paper
section 4.3, digest 5).

Reads a training workdir (config.json and checkpoints/ written by `camrep.synthesis.train`) back
with `restore.load_run`, then runs `noise.noise_robustness` and `gram.gram_maps`:

  python -m camrep.synthesis.evaluate --workdir DIR [--what noise,gram] [--levels 13]
    [--out DIR/eval]

writes DIR/eval/noise.json, noise.png (PSNR and SSIM vs alpha), gram_<dof>.png (each with a PDF
twin) and gram.npz.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

import jax
import numpy as np
from absl import logging as absl_logging

from camrep import pose as P
from camrep.data.errors import DataError
from camrep.runtime.checkpoint import CheckpointError
from camrep.runtime.runconfig import ConfigError
from camrep.synthesis import components, restore
from camrep.synthesis import gram as gram_lib
from camrep.synthesis import noise as noise_lib

Array = jax.Array

EVAL_SUBDIR = "eval"


# --------------------------------------------------------------------------------------------
# Loading a run.


# --------------------------------------------------------------------------------------------
# Noise robustness.


# --------------------------------------------------------------------------------------------
# Gram maps.


# --------------------------------------------------------------------------------------------
# Figures (cv2; images are RGB uint8).


# --------------------------------------------------------------------------------------------
# Command line.


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
  p = argparse.ArgumentParser(
    prog="python -m camrep.synthesis.evaluate",
    description="Noise robustness and Gram maps of a trained camrep run (digest section 5).",
  )
  p.add_argument("--workdir", required=True, help="training workdir (config.json, checkpoints/)")
  p.add_argument("--what", default="noise,gram", help="comma-separated: noise, gram")
  p.add_argument(
    "--levels", type=int, default=noise_lib.DEFAULT_LEVELS, help="alpha = 0.025 j, j < levels"
  )
  p.add_argument(
    "--alphas",
    default=None,
    help="comma-separated noise levels instead of --levels (e.g. 0,0.3,1,3,10: how much the "
    "model uses its pose input)",
  )
  p.add_argument("--out", default=None, help="output directory (default WORKDIR/eval)")
  p.add_argument("--step", type=int, default=None, help="checkpoint step (default: latest)")
  p.add_argument(
    "--num_scenes",
    type=int,
    default=None,
    help="held-out scenes to evaluate (default: the config's evals.num_scenes)",
  )
  p.add_argument(
    "--draw_temperature",
    type=float,
    default=None,
    help="GQN's generator only: latent temperature of the prediction (default: the config's "
    "model.draw_temperature; 1 a prior sample, 0 the prior mean)",
  )
  p.add_argument("--seed", type=int, default=0, help="seed of the noise and quantisation draws")
  p.add_argument(
    "--quantisation",
    choices=P.QUANTISATION_MODES,
    default=None,
    help="quantisation of the exact poses (default: random for gqn/car, nearest otherwise)",
  )
  args = p.parse_args(argv)
  what = {w.strip() for w in args.what.split(",") if w.strip()}
  if not what or what - {"noise", "gram"}:
    p.error(f"--what takes a comma-separated subset of noise,gram; got {args.what!r}")
  if args.levels < 1:
    p.error("--levels must be at least 1")
  if args.alphas is not None:
    try:
      args.alphas = np.array([float(a) for a in args.alphas.split(",") if a.strip()])
    except ValueError:
      p.error(f"--alphas takes comma-separated numbers; got {args.alphas!r}")
    if not len(args.alphas) or (args.alphas < 0).any():
      p.error(f"--alphas takes non-negative noise levels; got {args.alphas!r}")
  else:
    args.alphas = noise_lib.default_alphas(args.levels)
  args.what = what
  return args


def main(argv: Sequence[str] | None = None) -> int:
  """The command line; returns the exit status."""
  args = _parse_args(argv)
  # Orbax logs at WARNING that a read-only manager ignores its save options.
  absl_logging.set_verbosity(absl_logging.ERROR)
  log = lambda s: print(s, flush=True)
  try:
    run = restore.load_run(args.workdir, step=args.step)
  except (FileNotFoundError, CheckpointError, ConfigError, DataError) as e:
    # A checkpoint whose arrays do not fit the workdir's config.json is refused here (exit 2).
    print(f"error: {e}", file=sys.stderr, flush=True)
    return 2
  if args.num_scenes is not None:
    run.config.evals.num_scenes = args.num_scenes
  if args.draw_temperature is not None:
    run.config.model.draw_temperature = args.draw_temperature
  out = args.out or os.path.join(args.workdir, EVAL_SUBDIR)
  os.makedirs(out, exist_ok=True)
  log(f"restored step {run.step} of {args.workdir} ({components.setting(run.config)})")
  written = []
  if "noise" in args.what:
    result = noise_lib.noise_robustness(
      run,
      key=jax.random.key(args.seed),
      alphas=args.alphas,
      quantisation=args.quantisation,
      progress=log,
    )
    log(f"\nquantisation {result['quantisation']}, {result['num_images']} images")
    log(f"{'alpha':>7} {'PSNR':>8} {'SSIM':>7}")
    for a, p, s in zip(result["alphas"], result["psnr"], result["ssim"], strict=True):
      log(f"{a:7.3f} {p:8.3f} {s:7.4f}")
    written += noise_lib.write_noise(out, run, result)
  if "gram" in args.what:
    log("gram maps: " + ", ".join(run.spec.names))
    written += gram_lib.write_grams(out, run, gram_lib.gram_maps(run))
  log("wrote:\n  " + "\n  ".join(written))
  return 0


if __name__ == "__main__":
  sys.exit(main())

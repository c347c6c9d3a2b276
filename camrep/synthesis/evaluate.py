"""Noise robustness and Gram maps of a trained run (paper section 4.3, the authors' code):
`python -m camrep.synthesis.evaluate --workdir=DIR [--what=noise,gram] [--levels=13] [--out=DIR]`.

Reads a training workdir (config.json and checkpoints/ written by `camrep.synthesis.train`) back
with `restore.load_run`, then runs `noise.noise_robustness` and `gram.gram_maps`, and writes
DIR/eval/noise.json, noise.png (PSNR and SSIM vs alpha), gram_<dof>.png (each with a PDF
twin) and gram.npz. The output
directory is checked for writing before anything is restored and locked while it is written (a
second evaluation of it waits for the first), and the files are written into a staging directory
there and moved in only once all are written: a full disk or a read-only
workdir ends with one `error:` line (exit 2) and leaves no half-written file. Exit status as
every camrep tool (`camrep.runtime.cli`).
"""

from __future__ import annotations

import math
import os
import shutil
import sys
import tempfile
from collections.abc import Sequence

import jax
import numpy as np
from absl import flags
from absl import logging as absl_logging

from camrep import pose as P
from camrep.runtime import cli
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import components, restore
from camrep.synthesis import gram as gram_lib
from camrep.synthesis import noise as noise_lib

Array = jax.Array

EVAL_SUBDIR = "eval"


# --------------------------------------------------------------------------------------------
# Command line.

WHAT = ("noise", "gram")


def define_flags(fv: flags.FlagValues, argv: Sequence[str] = ()) -> None:
  """The tool's flags (`cli.Define`)."""
  del argv
  flags.DEFINE_string(
    "workdir", None, "Training workdir (config.json, checkpoints/).", flag_values=fv, required=True
  )
  flags.DEFINE_list(
    "what", list(WHAT), f"What to compute: a subset of {','.join(WHAT)}.", flag_values=fv
  )
  flags.DEFINE_integer(
    "levels",
    noise_lib.DEFAULT_LEVELS,
    "Noise levels alpha = 0.025 j, j < levels.",
    lower_bound=1,
    flag_values=fv,
  )
  flags.DEFINE_list(
    "alphas",
    None,
    "Noise levels instead of --levels (e.g. 0,0.3,1,3,10: how much the model uses its pose input).",
    flag_values=fv,
  )
  flags.DEFINE_string("out", None, "Output directory (default WORKDIR/eval).", flag_values=fv)
  flags.DEFINE_integer(
    "step", None, "Checkpoint step (default: the latest).", lower_bound=0, flag_values=fv
  )
  flags.DEFINE_integer(
    "num_scenes",
    None,
    "Held-out scenes to evaluate (default: the config's evals.num_scenes).",
    lower_bound=1,
    flag_values=fv,
  )
  flags.DEFINE_float(
    "draw_temperature",
    None,
    "GQN's generator only: latent temperature of the prediction (default: the config's "
    "model.draw_temperature; 1 a prior sample, 0 the prior mean).",
    lower_bound=0.0,
    flag_values=fv,
  )
  flags.DEFINE_integer(
    "seed", 0, "Seed of the noise and quantisation draws.", lower_bound=0, flag_values=fv
  )
  flags.DEFINE_enum(
    "noise_on",
    None,
    noise_lib.NOISE_ON,
    "Where the noise goes: the query's pose vectors v(p) (the paper's test; the decoders' "
    "default) or the query pose before conditioning (the multi-view transformer's default: "
    "the same for every camera conditioning).",
    flag_values=fv,
  )
  flags.DEFINE_enum(
    "quantisation",
    None,
    P.QUANTISATION_MODES,
    "Quantisation of the exact poses (default: random for gqn/car, nearest otherwise).",
    flag_values=fv,
  )


def _alphas(fv: flags.FlagValues) -> np.ndarray:
  if fv.alphas is None:
    return noise_lib.default_alphas(fv.levels)
  try:
    alphas = np.array([float(a) for a in fv.alphas if a.strip()])
  except ValueError:
    raise cli.UsageError(f"--alphas takes comma-separated numbers; got {fv.alphas!r}") from None
  if not len(alphas) or (alphas < 0).any() or not np.isfinite(alphas).all():
    raise cli.UsageError(f"--alphas takes finite non-negative noise levels; got {fv.alphas!r}")
  return alphas


def run_cli(fv: flags.FlagValues) -> int:
  """The tool (`cli.Body`): checks the output directory, restores the run, writes the files."""
  alphas = _alphas(fv)
  what = {w.strip() for w in fv.what if w.strip()}
  if not what or what - set(WHAT):
    raise cli.UsageError(
      f"--what takes a comma-separated subset of {','.join(WHAT)}; got {fv.what}"
    )
  # Orbax logs at WARNING that a read-only manager ignores its save options.
  absl_logging.set_verbosity(absl_logging.ERROR)
  log = lambda s: print(s, flush=True)
  if not os.path.isdir(fv.workdir):
    raise FileNotFoundError(f"workdir {fv.workdir!r} does not exist")
  out = fv.out or os.path.join(fv.workdir, EVAL_SUBDIR)
  # As training does for its workdir: a read-only or full output directory fails now, not
  # after minutes of restoring and evaluating.
  existed = os.path.isdir(out)
  workdir_lib.check_workdir(out)
  # One evaluation writes an output directory at a time: a second waits for the first
  # (a training run of the workdir holds the workdir's own lock, not this one).
  lock = workdir_lib.WorkdirLock(out)
  try:
    lock.acquire(wait=math.inf, log=log)
    try:
      return _evaluate(fv, out, alphas, what, log)
    finally:
      lock.release()
  except BaseException:
    if not existed:  # leave the workdir as it was (the staged files are gone already)
      try:
        os.rmdir(out)
      except OSError:
        pass
    raise


def _evaluate(fv: flags.FlagValues, out: str, alphas, what, log) -> int:
  # A checkpoint whose arrays do not fit the workdir's config.json is refused here (exit 2).
  run_ = restore.load_run(fv.workdir, step=fv.step)
  if fv.num_scenes is not None:
    run_.config.evals.num_scenes = fv.num_scenes
  if fv.draw_temperature is not None:
    if run_.model.temperature is None:  # a decoder: no latents to draw
      raise cli.UsageError(
        f"--draw_temperature: the run in {fv.workdir} has no generative model (model.kind "
        f"{run_.config.model.get('kind', 'decoder')!r}); the flag is for GQN's generator only"
      )
    run_.config.model.draw_temperature = fv.draw_temperature
  on = fv.noise_on or run_.model.noise_on
  needs_vectors = sorted({"gram"} & what | ({"noise"} & what if on == "vectors" else set()))
  if needs_vectors and not run_.model.reads_pose_vectors:
    raise cli.UsageError(
      f"--what={','.join(needs_vectors)} (--noise_on={on}): the run in {fv.workdir} (model.camera "
      f"{run_.config.model.get('camera')!r}) feeds its model no per-DOF pose vectors v(p): the "
      "Gram maps show them and --noise_on=vectors perturbs them; of the multi-view "
      "transformer's conditionings only learned_abs has them (--noise_on=pose noises the pose "
      "itself, for every conditioning)"
    )
  log(f"restored step {run_.step} of {fv.workdir} ({components.setting(run_.config)})")
  result = None
  if "noise" in what:
    result = noise_lib.noise_robustness(
      run_,
      key=jax.random.key(fv.seed),
      alphas=alphas,
      quantisation=fv.quantisation,
      progress=log,
      on=on,
    )
    log(
      f"\nnoise on the {on}, quantisation {result['quantisation']}, {result['num_images']} images"
    )
    log(f"{'alpha':>7} {'PSNR':>8} {'SSIM':>7}")
    for a, p, s in zip(result["alphas"], result["psnr"], result["ssim"], strict=True):
      log(f"{a:7.3f} {p:8.3f} {s:7.4f}")
  grams = gram_lib.gram_maps(run_) if "gram" in what else None
  if grams is not None:
    log("gram maps: " + ", ".join(run_.spec.names))
  written = write_outputs(out, run_, noise=result, grams=grams)
  log("wrote:\n  " + "\n  ".join(written))
  return 0


def write_outputs(out: str, run_, *, noise=None, grams=None) -> list[str]:
  """Writes the noise and Gram files into a staging directory in `out`, then moves them in:
  a failed write (disk full) leaves `out` as it was.

  Returns:
    The written paths (in `out`).
  """
  stage = tempfile.mkdtemp(prefix=".staging-", dir=out)
  try:
    staged = []
    if noise is not None:
      staged += noise_lib.write_noise(stage, run_, noise)
    if grams is not None:
      staged += gram_lib.write_grams(stage, run_, grams)
    written = []
    for path in staged:
      final = os.path.join(out, os.path.relpath(path, stage))
      os.replace(path, final)
      written.append(final)
    return written
  finally:
    shutil.rmtree(stage, ignore_errors=True)


def main(argv: Sequence[str] | None = None) -> int:
  """In-process entry (tests, notebooks): `argv` are the flags; returns the exit status."""
  return cli.call(define_flags, run_cli, sys.argv[1:] if argv is None else argv, prog=__name__)


if __name__ == "__main__":
  cli.main(define_flags, run_cli)

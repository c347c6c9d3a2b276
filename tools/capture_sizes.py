"""One held-out view of a capture beside what view-synthesis runs at several sizes predict for it.

Each run is a view-synthesis workdir on the same prepared capture (e.g. `shapenet_car.py:quick`
on a `--preset small` dataset, 64 px, and `shapenet_car.py:capture` on the full-size one,
128 px); the picture shows the first run's target view, then each run's prediction of its own
evaluation view (the first held-out view of the first scene: the same view when the runs read the
same capture), titled with the run's image size and its held-out PSNR, as its final evaluation
computes it (printed beside the baseline's: the mean of its training views). Smaller predictions are
scaled up (nearest neighbour) to the largest size.

  .venv/bin/python tools/capture_sizes.py --runs /tmp/cap64_syn /tmp/cap128_syn \
      --out results/capture_sizes.png
"""

from __future__ import annotations

import argparse
import os
import sys

import cv2
import numpy as np


def views(workdir: str) -> dict:
  """{size, target, prediction, psnr, psnr_baseline} of a run's final held-out evaluation;
  images (H, W, 3) float in [-1, 1]."""
  from camrep.synthesis import heldout, restore

  run = restore.load_run(workdir)
  batches = heldout.eval_batches(run.model, run.train_pipe, run.test_pipe)
  scalars, first = heldout.evaluate(heldout.make_predict(run.model), run.params, batches)
  target = np.asarray(first["target"])[0, 0]
  return {
    "size": int(target.shape[0]),
    "step": run.step,
    "target": target,
    "prediction": np.asarray(first["prediction"])[0, 0],
    "psnr": float(first["psnr"][0]),
    "psnr_baseline": float(first["psnr_baseline"][0]),
    "mean_psnr": scalars["eval/psnr"],
  }


def _scaled(image: np.ndarray, size: int) -> np.ndarray:
  if image.shape[0] == size:
    return image
  return cv2.resize(image, (size, size), interpolation=cv2.INTER_NEAREST)


def figure(runs: list[dict]) -> np.ndarray:
  """(H, W, 3) uint8: the target of the largest run, then each run's prediction."""
  from camrep.runtime import grids

  size = max(r["size"] for r in runs)
  target = max(runs, key=lambda r: r["size"])["target"]
  row = [target] + [_scaled(r["prediction"], size) for r in runs]
  labels = ["held-out view"] + [f"{r['size']} px: {r['psnr']:.1f} dB" for r in runs]
  return grids.image_grid([row], labels=labels)


def main(argv: list[str] | None = None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--runs", nargs="+", required=True, help="view-synthesis workdirs")
  p.add_argument("--out", required=True, help="PNG to write")
  args = p.parse_args(argv)
  missing = [w for w in args.runs if not os.path.isdir(w)]
  if missing:
    p.error(f"not a directory: {', '.join(missing)}")
  runs = [views(w) for w in args.runs]
  for w, r in zip(args.runs, runs, strict=True):
    print(
      f"{w}: {r['size']} px, step {r['step']}, held-out view PSNR {r['psnr']:.2f} dB against "
      f"{r['psnr_baseline']:.2f} for the mean of its training views"
    )
  image = figure(runs)
  os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
  if not cv2.imwrite(args.out, cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
    p.error(f"cannot write {args.out}")
  print(f"wrote {args.out} ({image.shape[1]} x {image.shape[0]})")
  return 0


if __name__ == "__main__":
  sys.exit(main())

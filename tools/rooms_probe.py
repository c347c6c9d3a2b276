"""Probes the rooms regression: does the GQN rooms regressor fit its training rooms, and does it
use its context views?

Trains the quick gqn regressor (configs/regression.py:quick, quat target) on a rooms set of the
given look and prints, every 2 x --every steps, the x / y / yaw errors and the spread of the
predicted poses on: the training views themselves (context = the room's first 6 views), held-out
views of the training rooms, new rooms, and the first two again with another room's context
(the context ablation). --norm swaps the regressor's AdaIN for a variant (film: gamma x + beta;
in_noctx / none_noctx: no context at all).

  .venv/bin/python tools/rooms_probe.py --rooms 400 --test_rooms 32 --steps 1000 \
      --every 125 --wall tinted --lr 1e-3
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from camrep.configs import regression as regression_config
from camrep.models import layers
from camrep.regression import config_schema, driver, learner, scoring, views


def _adain_variant(name):
  inorm = layers.instance_norm
  g = lambda v: v[..., None, None, :]  # noqa: E731
  return {
    "in": lambda x, ga, be, eps=1e-7: g(ga) * inorm(x, eps) + g(be),
    "film": lambda x, ga, be, eps=0: g(ga) * x + g(be),
    "in_noctx": lambda x, ga, be, eps=1e-7: inorm(x, eps),
    "none_noctx": lambda x, ga, be, eps=0: x,
  }[name]


def _other_context(batches):
  out = []
  for b in batches:
    b = dict(b)
    b["context_image"] = np.roll(b["context_image"], 1, 0)
    b["context_pose"] = np.roll(b["context_pose"], 1, 0)
    out.append(b)
  return out


def main():
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--rooms", type=int, default=12)
  ap.add_argument("--test_rooms", type=int, default=4)
  ap.add_argument("--views", type=int, default=10)
  ap.add_argument("--steps", type=int, default=400)
  ap.add_argument("--every", type=int, default=100)
  ap.add_argument("--rep", default="quat")
  ap.add_argument("--wall", default="compass", help="tinted | distinct | compass")
  ap.add_argument("--light", type=float, default=None, help="fixed light azimuth (deg)")
  ap.add_argument("--contrast", default="0.0,0.08")
  ap.add_argument("--lr", type=float, default=None)
  ap.add_argument("--width", type=float, default=0.125)
  ap.add_argument("--bs", type=int, default=4)
  ap.add_argument("--norm", default="in", help="in | film | in_noctx | none_noctx")
  ap.add_argument("--cache_dir", default="/tmp/rooms_probe_cache")
  a = ap.parse_args()

  c = regression_config.get_config("gqn,quick")
  c.representation = a.rep
  c.data.family.update(
    dict(
      num_train_scenes=a.rooms,
      num_test_scenes=a.test_rooms,
      train_views=a.views,
      wall_style=a.wall,
      texture_contrast=tuple(float(x) for x in a.contrast.split(",")),
    )
  )
  if a.light is not None:
    c.data.family.light_azimuth_deg = a.light
  c.total_steps, c.data.batch_size, c.model.width = a.steps, a.bs, a.width
  c.data.cache_dir = a.cache_dir
  c.evals.extra_splits = "test"
  if a.lr:
    c.optax.lr = a.lr
  layers.adain = _adain_variant(a.norm)  # read by the regressor at trace time
  setup = driver.prepare(config_schema.check(c))
  train, b = setup.data.train, setup.batching
  sub = train.subset(np.isin(train.scenes, train.scene_ids()[:40]))
  sets = {
    "train(own)": views.eval_batches(b, views.EvalSet(sub, sub)),
    "test(held-out views)": views.eval_batches(b, setup.data.evals["test"]),
    "test_scenes(new rooms)": views.eval_batches(b, setup.data.evals["test_scenes"]),
  }
  sets["held-out views, other room's context"] = _other_context(sets["test(held-out views)"])
  sets["train(own), other room's context"] = _other_context(sets["train(own)"])
  batches = views.train_batches(b, train)
  first = next(views.train_batches(b, train))
  key = jax.random.fold_in(jax.random.key(0), 0)
  state = learner.init(key, setup.reg, first, rep_params=setup.rep_params)
  step_fn, pred_fn = jax.jit(learner.train_step), jax.jit(learner.predict_poses)
  t = time.time()
  for s in range(1, a.steps + 1):
    state, m = step_fn(state, next(batches))
    if s == 1 or s % a.every == 0:
      print(f"step {s} " + " ".join(f"{k}={float(v):.4f}" for k, v in m.items()), flush=True)
    if s % (2 * a.every) == 0 or s == a.steps:
      for name, bs in sets.items():
        e = scoring.evaluate_regression(state, bs, predict_fn=pred_fn)
        print(
          f"  step {s} {name}: x {e['x_error'].mean():.3f} y {e['y_error'].mean():.3f} "
          f"yaw {e['yaw_error_deg'].mean():.1f} (n={len(e['scene'])}) "
          f"pred std {np.round(e['pred'].std(0), 3)} label std {np.round(e['pose'].std(0), 3)}",
          flush=True,
        )
  print(f"{time.time() - t:.0f}s")


if __name__ == "__main__":
  main()

"""A sanity test: the GQN rooms regression learns on the rooms its quick config renders.

The cause it catches: rooms whose views can only be placed relative to the room's own context
views. A square room looks the same after a quarter turn, and every cue that tells a view from
its twins (wall tints, the light's azimuth, the objects) used to be drawn afresh per room, so no
single view says which way is which; the loss is then minimised by a constant pose and the
regressor stays there (measured on such rooms: prediction spread ~0.01 against labels spread
0.46, and the same errors with another room's context). The quick rooms have walls whose hues
follow the world directions (`wall_style='compass'`); the old look stays as `wall_style='tinted'`.
"""

from __future__ import annotations

import os

import jax
import numpy as np
import pytest

from camrep.configs import regression as regression_config
from camrep.regression import config_schema, driver, learner, scoring
from camrep.regression import views as views_lib

pytestmark = pytest.mark.slow


def _small_quick_config(**family):
  """configs/regression.py:quick's gqn setting (its rooms' look) at a size that trains in
  seconds: 32 px, 40 rooms of 10 views, 300 steps at lr 1e-3; checked and resolved."""
  c = regression_config.get_config("gqn,quick")
  c.representation = "quat"
  c.data.family.update(
    dict(image_size=32, num_train_scenes=40, num_test_scenes=8, train_views=10, test_views=2),
  )
  c.data.family.update(family)
  c.total_steps, c.data.batch_size = 300, 4
  c.optax.lr = 1e-3
  c.evals.extra_splits = "test"
  return config_schema.check(c)


def _train_and_score(run):
  config, batching = run.config, views_lib.Batching.of(run.config, run.setting)
  data = views_lib.make_data(config, run.source)
  reg = driver.make_regressor(run, None, int(data.train.scenes.max()) + 1)
  batches = views_lib.train_batches(batching, data.train)
  first = next(views_lib.train_batches(batching, data.train))
  state = learner.init(jax.random.key(0), reg, first)
  step = jax.jit(learner.train_step)
  for _ in range(config.total_steps):
    state, _ = step(state, next(batches))
  predict = jax.jit(learner.predict_poses)
  own = views_lib.EvalSet(data.train, data.train)
  out = {}
  splits = (
    ("train", own),
    ("test", data.evals["test"]),
    ("test_scenes", data.evals["test_scenes"]),
  )
  for name, eval_set in splits:
    errs = scoring.evaluate_regression(
      state, views_lib.eval_batches(batching, eval_set), predict_fn=predict
    )
    out[name] = {k: float(np.mean(errs[k])) for k in ("x_error", "yaw_error_deg")}
  return out


def _report(got):
  return {s: {k: round(v, 3) for k, v in d.items()} for s, d in got.items()}


def test_quick_rooms_regression_learns_the_yaw():
  """The quick config's rooms: after 300 steps the yaw error is far below chance (90 deg) on the
  training views, on held-out views of the training rooms and on new rooms (pose
  observable in rooms never seen; with the old look the held-out views stay at chance: the next
  test)."""
  got = _train_and_score(_small_quick_config())
  print(_report(got))
  assert got["train"]["yaw_error_deg"] < 45.0, got
  assert got["test"]["yaw_error_deg"] < 45.0, got
  assert got["test_scenes"]["yaw_error_deg"] < 45.0, got


@pytest.mark.skipif(
  not os.environ.get("CAMREP_DOC_TESTS"),
  reason="documents the cause (~1 min of CPU); set CAMREP_DOC_TESTS=1 to run it",
)
def test_old_rooms_look_stays_at_chance():
  """The old look (wall_style="tinted", the family's default) at the same size: held-out views
  of the training rooms stay at chance, whatever the training views do (the cause, kept
  documented; it is not a bug on the path)."""
  got = _train_and_score(_small_quick_config(wall_style="tinted"))
  print(_report(got))
  assert got["test"]["yaw_error_deg"] > 60.0, got

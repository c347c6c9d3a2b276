"""Scoring a pose regressor (paper section 4.4, Tables 1 and 2): per-example position and
orientation errors, and their mean / median summaries over all examples and per scene.
"""

from __future__ import annotations

import collections
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from camrep import settings as settings_lib
from camrep.regression.learner import RegressionState, predict_poses

Array = jax.Array


def pose_errors(setting: settings_lib.Setting | str, pred: Array, true: Array) -> dict[str, Array]:
  """Per-example pose errors of a setting (`Setting.pose_errors`; a name is looked up).

  gqn, gibson: "x_error", "y_error" (|.| in scene units / m), "position_error" (Euclidean),
    "yaw_error_deg" (wrapped to [0, 180]).
  car: "rotation_error_deg" = 2 arccos|<q_hat, q>| of the `settings.car_rotation`s,
    "azimuth_error_deg" (wrapped), "polar_error_deg".
  seven_scenes: "position_error" (m), "rotation_error_deg" of the sxyz rotations.

  Args:
    pred, true: (..., P) poses.

  Returns:
    {name: (...)}.
  """
  return settings_lib.get(setting).pose_errors(pred, true)


# `pose_errors` of a batch as one program per setting and shape (op by op, its dozen eager ops
# would each compile in every process that scores).
_batch_errors = jax.jit(pose_errors, static_argnums=0)


def evaluate_regression(
  state: RegressionState,
  batches: Iterable[Mapping[str, Array]],
  *,
  predict_fn: Callable | None = None,
  setting: settings_lib.Setting | None = None,
) -> dict[str, np.ndarray]:
  """Per-example errors over an evaluation set.

  Args:
    state: a trained state.
    batches: batches as described in the module docstring (with "scene"; optional "mask").
    predict_fn: (state, batch) -> poses; default `jax.jit(predict_poses)`, compiled once here.
    setting: the setting of the errors; default the state's.

  Returns:
    flat per-example arrays (N,): the `pose_errors` entries, "scene", "view" (when the batches
    carry view ids), plus "pose" and "pred" (N, P). Padding (mask false) is dropped.
  """
  predict_fn = predict_fn or jax.jit(predict_poses)
  setting = setting or state.regressor.setting
  out = collections.defaultdict(list)
  for batch in batches:
    batch = {k: jnp.asarray(v) for k, v in batch.items()}
    pred = predict_fn(state, batch)
    true = batch["pose"]
    lead = true.shape[:-1]
    errs = _batch_errors(settings_lib.get(setting), pred, true)
    scene = batch.get("scene")
    scene = np.zeros(lead, np.int32) if scene is None else np.asarray(scene)
    scene = np.broadcast_to(scene.reshape(scene.shape + (1,) * (len(lead) - scene.ndim)), lead)
    mask = np.asarray(batch.get("mask", np.ones(lead, bool)), bool).reshape(-1)
    for k, v in errs.items():
      out[k].append(np.asarray(v).reshape(-1)[mask])
    out["scene"].append(scene.reshape(-1)[mask])
    if "view" in batch:
      out["view"].append(np.broadcast_to(np.asarray(batch["view"]), lead).reshape(-1)[mask])
    out["pose"].append(np.asarray(true).reshape(-1, true.shape[-1])[mask])
    out["pred"].append(np.asarray(pred).reshape(-1, true.shape[-1])[mask])
  return {k: np.concatenate(v) for k, v in out.items()}


def summarise_errors(errors: Mapping[str, np.ndarray]) -> dict[Any, dict[str, dict[str, float]]]:
  """Mean and median of every error, per scene and over all examples.

  Args:
    errors: from `evaluate_regression` (per-example arrays with "scene").

  Returns:
    {"all" or scene id: {error name: {"mean": float, "median": float}}}; the paper reports means
    (GQN, car, Gibson) and per-scene medians (7-Scenes).
  """
  names = [k for k in errors if k not in ("scene", "view", "pose", "pred")]
  scene = np.asarray(errors["scene"])
  groups: dict[Any, np.ndarray] = {"all": np.ones(scene.shape, bool)}
  for s in np.unique(scene):
    groups[int(s)] = scene == s
  return {
    g: {
      k: {
        "mean": float(np.mean(errors[k][m])),
        "median": float(np.median(errors[k][m])),
      }
      for k in names
    }
    for g, m in groups.items()
  }

"""Held-out-view evaluation of view synthesis (paper section 4.2): PSNR / SSIM of predicted
held-out views against a trivial baseline, on a fixed evaluation set built once per run.

Models that render from context views (the GQN layout) are also evaluated with other numbers of
context views than they train with, `config.evals.context_counts` (generalisation to more context
views, PRoPE's test): the same scenes and targets, the first n training views as context, written
as eval/psnr_context{n} and eval/ssim_context{n} beside eval/psnr.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from camrep import metrics as metrics_lib
from camrep.data.errors import DataError
from camrep.runtime import grids
from camrep.synthesis import synthesizers

Array = jax.Array


def eval_batches(
  model: synthesizers.Synthesizer, train_pipe, test_pipe, *, n_context: int | None = None
) -> list[dict[str, np.ndarray]]:
  """Held-out-view evaluation set of `model.config.evals`: the first test view of each of the
  first `evals.num_scenes` scenes; where the split has fewer scenes, the first k test views of
  each (k = ceil(num_scenes / scenes), at most the fewest test views of a scene), so that a
  one-scene capture is evaluated on num_scenes of its views, not one. Context: the scene's first
  training views (`n_context` views, default the model's `n_context`; per-scene tables: up to
  evals.baseline_views views whose mean image is the baseline). Batches of evals.batch_scenes
  targets; "scene" (E,) repeats a scene's id for each of its targets."""
  ev = model.config.evals
  test_ids = np.intersect1d(test_pipe.all_scene_ids, train_pipe.all_scene_ids)
  if len(test_ids) == 0:
    raise DataError(None, "no scene has both training and held-out views to evaluate on")
  ids = test_ids[: ev.num_scenes]
  per = min(-(-ev.num_scenes // len(ids)), min(test_pipe.num_scene_views(s) for s in ids))
  c = model.n_context if n_context is None else n_context
  if c is None:  # baseline only: the mean of (up to baseline_views of) the scene's training views
    c = min(ev.baseline_views, min(train_pipe.num_scene_views(s) for s in ids))
  ctx = {s: train_pipe.scene_views(s, c) for s in ids}
  tgt = {s: test_pipe.scene_views(s, per) for s in ids}
  targets = [(s, v) for s in ids for v in range(per)]
  out = []
  for start in range(0, len(targets), ev.batch_scenes):
    chunk = targets[start : start + ev.batch_scenes]
    out.append(
      {
        "context_image": np.stack([ctx[s][0] for s, _ in chunk]),
        "context_pose": np.stack([ctx[s][1] for s, _ in chunk]),
        "target_image": np.stack([tgt[s][0][v : v + 1] for s, v in chunk]),
        "target_pose": np.stack([tgt[s][1][v : v + 1] for s, v in chunk]),
        "scene": np.array([s for s, _ in chunk], np.int32),
      }
    )
  return out


def make_predict(model: synthesizers.Synthesizer):
  """jit(params, batch) -> (prediction, scores): the prediction (E, 1, H, W, 3) in [-1, 1] and, in
  the same program (as `noise.make_noisy_predict`), per-image PSNR and SSIM (E, 1) against the
  target of the prediction, the baseline (the mean context view) and each of the model's
  `variants`: {"pred": (psnr, ssim), "base": (psnr, ssim), "others": {name: (psnr, ssim)}}.

  variants: {} for decoders; GQN's generator: {"sample": temperature 1, "prior_mean": temperature
  0} (the prediction is at the config's temperature).
  """

  def predict(params, b):
    pred = model.predict(params, b)
    others = {name: model.predict(params, b, temperature=t) for name, t in model.variants.items()}
    ctx = synthesizers.to_float_images(b["context_image"])
    baseline = jnp.broadcast_to(jnp.mean(ctx, axis=1, keepdims=True), pred.shape)
    tgt = synthesizers.to_float_images(b["target_image"])
    both = lambda x: (metrics_lib.psnr(x, tgt), metrics_lib.ssim(x, tgt))
    scores = {"pred": both(pred), "base": both(baseline)}
    return pred, {**scores, "others": {k: both(o) for k, o in others.items()}}

  return jax.jit(predict)


def evaluate(predict, params, batches) -> tuple[dict[str, float], dict[str, np.ndarray]]:
  """PSNR as the paper (mean of per-image PSNR on [0, 1]), SSIM, and the baseline's PSNR.

  Returns:
    (scalars {"eval/psnr", "eval/ssim", "eval/psnr_baseline", "eval/ssim_baseline"},
     arrays of the first batch for image grids and per-example values).
  """
  psnr, ssim, psnr_b, ssim_b = [], [], [], []
  extra: dict[str, list] = {}
  first = None
  for b in batches:
    pred, scores = predict(params, {k: jnp.asarray(v) for k, v in b.items()})
    scores = jax.tree.map(lambda x: np.asarray(x).ravel(), scores)
    for name, (p, s) in scores["others"].items():
      extra.setdefault(f"eval/psnr_{name}", []).append(p)
      extra.setdefault(f"eval/ssim_{name}", []).append(s)
    psnr.append(scores["pred"][0])
    ssim.append(scores["pred"][1])
    psnr_b.append(scores["base"][0])
    ssim_b.append(scores["base"][1])
    if first is None:
      first = {
        "context": b["context_image"],
        "target": b["target_image"],
        "prediction": np.asarray(pred),
      }
  psnr, ssim, psnr_b, ssim_b = (np.concatenate(x) for x in (psnr, ssim, psnr_b, ssim_b))
  scalars = {
    "eval/psnr": float(np.mean(psnr)),
    "eval/ssim": float(np.mean(ssim)),
    "eval/psnr_baseline": float(np.mean(psnr_b)),
    "eval/ssim_baseline": float(np.mean(ssim_b)),
    **{k: float(np.mean(np.concatenate(v))) for k, v in extra.items()},
  }
  first.update(psnr=psnr, ssim=ssim, psnr_baseline=psnr_b)
  return scalars, first


def context_counts(model: synthesizers.Synthesizer) -> tuple[int, ...]:
  """The context counts `config.evals.context_counts` evaluates a model at besides its own
  (sorted, without `model.n_context`); () for models without context views or without the
  field."""
  if model.n_context is None:
    return ()
  counts = model.config.evals.get("context_counts", ()) or ()
  return tuple(sorted({int(n) for n in counts} - {model.n_context}))


def context_metric(name: str, n: int) -> str:
  """The scalar of `name` ("psnr", "ssim") with n context views: "eval/{name}_context{n}"."""
  return f"eval/{name}_context{n}"


def context_sweep(predict, params, sweep: dict[int, list]) -> dict[str, float]:
  """eval/psnr_context{n}, eval/ssim_context{n} of each evaluation set {n: batches}."""
  out = {}
  for n, batches in sweep.items():
    scalars, _ = evaluate(predict, params, batches)
    out[context_metric("psnr", n)] = scalars["eval/psnr"]
    out[context_metric("ssim", n)] = scalars["eval/ssim"]
  return out


def evaluate_and_log(
  writer, predict, batches, params, step: int, *, grid_scenes: int, log, sweep=None
) -> dict[str, float]:
  """`evaluate` written as eval/* scalars plus the eval/grid image of the first `grid_scenes`
  scenes; `log` gets one line. `sweep` {n: batches}: the same scenes with n context views
  (`context_sweep`), written in the same row."""
  scalars, first = evaluate(predict, params, batches)
  if sweep:
    scalars.update(context_sweep(predict, params, sweep))
  writer.write_scalars(step, scalars)
  g = grid_scenes
  grid = grids.view_synthesis_grid(
    first["context"][:g], first["target"][:g], first["prediction"][:g]
  )
  writer.write_images(step, {"eval/grid": grid})
  log(f"step {step}: " + " ".join(f"{k}={v:.3f}" for k, v in scalars.items()))
  return scalars


def make_evaluate(model: synthesizers.Synthesizer, train_pipe, test_pipe, writer, *, log):
  """evaluate(params, step) -> eval scalars: `evaluate_and_log` on the evaluation set of
  `eval_batches` and its `context_counts` variants, built here once for the whole run."""
  sweep = {
    n: eval_batches(model, train_pipe, test_pipe, n_context=n) for n in context_counts(model)
  }
  return functools.partial(
    evaluate_and_log,
    writer,
    make_predict(model),
    eval_batches(model, train_pipe, test_pipe),
    grid_scenes=model.config.evals.grid_scenes,
    log=log,
    sweep=sweep,
  )

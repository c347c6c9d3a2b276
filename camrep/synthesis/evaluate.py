"""Evaluation of a trained run: noise robustness of view synthesis and Gram maps (digest 5).

Reads a training workdir (config.json and checkpoints/ written by `camrep.synthesis.train`) back:

  run = load_run(workdir)                      config, pose spec, model, params, pipelines
  noise_robustness(run, key=jax.random.key(0))  PSNR / SSIM vs pose-vector noise level alpha
  gram_maps(run)                               {dof: V V^T} over each DOF's range

Noise-robustness experiment (paper figure "PSNR vs noise", digest 5): beta_i is the std of
element i over the DOF's normalised grid vectors (`pose.grid_std`, computed once per DOF). At
level alpha every element i of every query pose sub-vector, computed for the exact pose, gets
independent N(0, (alpha beta_i)^2) noise, without renormalisation; fresh noise per image and per
level. GQN: only the query (decoder) pose vectors are noised, not the encoder's context poses.
The exact pose is quantised by the random lower/upper neighbour rule for the GQN and car
settings (the authors' test) and by rounding for Gibson and 7-Scenes; the training loop's eval
always rounds ("nearest"), so alpha = 0 with quantisation="nearest" reproduces its PSNR. The
images are the training loop's held-out-view evaluation set (`train.eval_batches`): per scene
the first test view as the query, and for GQN the first n_context training views as context.

Command line:

  python -m camrep.synthesis.evaluate --workdir DIR [--what noise,gram] [--levels 13]
    [--out DIR/eval]

writes DIR/eval/noise.json, noise.png (PSNR and SSIM vs alpha), gram_<dof>.png and gram.npz.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import cv2
import flax.serialization
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from absl import logging as absl_logging

from camrep import metrics as metrics_lib
from camrep import pose as P
from camrep.runtime import writers
from camrep.synthesis import train

Array = jax.Array

DEFAULT_LEVELS = 13
ALPHA_STEP = 0.025
EVAL_SUBDIR = "eval"


def default_alphas(levels: int = DEFAULT_LEVELS) -> np.ndarray:
  """alpha = 0.025 j for j = 0 .. levels - 1 (paper: 13 levels, 0 to 0.30)."""
  return ALPHA_STEP * np.arange(levels)


def default_quantisation(config: ml_collections.ConfigDict) -> str:
  """The noise test's quantisation (authors): random neighbour for GQN and car, else rounding."""
  return "random" if train.setting(config) in ("gqn", "car") else "nearest"


# --------------------------------------------------------------------------------------------
# Loading a run.


@dataclasses.dataclass
class Run:
  """A trained run, restored from its workdir.

  Attributes:
    workdir: the training workdir.
    config: the run's config, read back from workdir/config.json.
    spec: its pose system.
    model: its view-synthesis model (flax module).
    params: {"model": flax params, "rep": pose-system params} of the restored checkpoint.
    step: the restored checkpoint's step.
    train_pipe: training-split pipeline (context views of the evaluation set).
    test_pipe: held-out-view pipeline (for_eval).
  """

  workdir: str
  config: ml_collections.ConfigDict
  spec: P.PoseSystemSpec
  model: Any
  params: dict
  step: int
  train_pipe: Any
  test_pipe: Any


def read_config(workdir: str) -> ml_collections.ConfigDict:
  """workdir/config.json (written by `writers.MetricWriter.write_config`) as a ConfigDict.

  Raises:
    FileNotFoundError: no such workdir, or it has no config.json.
  """
  if not os.path.isdir(workdir):
    raise FileNotFoundError(f"workdir {workdir!r} does not exist")
  path = os.path.join(workdir, writers.CONFIG_FILE)
  if not os.path.exists(path):
    raise FileNotFoundError(
      f"{path} not found: {workdir!r} is not a camrep training workdir "
      "(`python -m camrep.main --config=... --workdir=DIR` writes it)"
    )
  with open(path, encoding="utf-8") as f:
    return ml_collections.ConfigDict(json.load(f))


def _zeros(x):
  return np.zeros(x.shape, x.dtype)


def load_run(workdir: str, *, step: int | None = None) -> Run:
  """Rebuilds a run as `train.train_and_evaluate` does and restores a checkpoint's parameters.

  Args:
    workdir: a training workdir (config.json, checkpoints/).
    step: the checkpoint step to restore; None: the latest readable one.

  Returns:
    The `Run`.

  Raises:
    FileNotFoundError: no workdir, no config.json, or no checkpoint.
    camrep.runtime.checkpoint.CheckpointError: the requested step is missing, or no checkpoint is
      readable or matches the config's model.
  """
  from camrep.runtime import checkpoint as ckpt_lib

  config = read_config(workdir)
  try:
    checkpointer = ckpt_lib.Checkpointer(workdir, read_only=True)
  except ckpt_lib.CheckpointError:
    raise FileNotFoundError(f"no checkpoint in {workdir!r} (no checkpoints/ directory)") from None
  try:
    steps = checkpointer.all_steps()
    if not steps:
      raise FileNotFoundError(f"no checkpoint in {checkpointer.directory}")
    if step is not None and step not in steps:
      raise ckpt_lib.CheckpointError(
        f"no checkpoint for step {step} in {checkpointer.directory}; available: {steps}"
      )
    # As train.train_and_evaluate (the template's shapes come from the training layout).
    train_pipe = train.make_pipeline(config, "train", num_devices=jax.local_device_count())
    test_pipe = train.make_pipeline(config, "test", num_devices=1, for_eval=True)
    spec = train.pose_spec(config)
    model = train.make_model(config, train.num_train_scenes(train_pipe))
    init_key = jax.random.split(jax.random.key(config.seed))[0]
    template = jax.eval_shape(
      lambda: train.create_train_state(init_key, config, model, spec, train_pipe.batch(0))
    )
    state_d, _, restored = checkpointer.restore(
      train.state_dict(jax.tree.map(_zeros, template)), step=step
    )
  finally:
    checkpointer.close()
  state = flax.serialization.from_state_dict(template, state_d)
  params = jax.tree.map(jnp.asarray, state.params)
  return Run(
    workdir=workdir,
    config=config,
    spec=spec,
    model=model,
    params=params,
    step=int(restored),
    train_pipe=train_pipe,
    test_pipe=test_pipe,
  )


# --------------------------------------------------------------------------------------------
# Noise robustness.


def dof_poses(spec: P.PoseSystemSpec, name: str, values: Array) -> Array:
  """Poses (K, pose_dim) whose DOF `name` takes `values` ((K,) or (K, 2)), other columns 0."""
  values = jnp.asarray(values, jnp.float32)
  cols = values if values.ndim == 2 else values[:, None]
  poses = jnp.zeros((cols.shape[0], spec.pose_dim), jnp.float32)
  return poses.at[:, spec.columns(name)].set(cols)


def grid_betas(params_rep: dict, spec: P.PoseSystemSpec, config=None) -> dict[str, np.ndarray]:
  """beta per DOF: {name: (d,)} std of each element over the DOF's normalised grid vectors.

  With a config whose `rep.kind` is not the learned grid ("lowdim", "mlp"), the population is
  the same grid points (`P.candidates` at the grid spacing) pushed through that pose input, so
  every kind is noised relative to its own spread over the same poses.
  """
  if config is None or train.rep_kind(config) == "grid":
    return {n: np.asarray(P.grid_std(params_rep, spec, n)) for n in spec.names}
  out = {}
  for d in spec.dofs:
    poses = dof_poses(spec, d.name, P.candidates(spec, d.name, d.spacing))
    v = train.pose_vectors(config, spec, params_rep, poses)[d.name]
    out[d.name] = np.asarray(jnp.std(v, axis=0))
  return out


def pose_vectors(
  params_rep: dict,
  spec: P.PoseSystemSpec,
  poses: Array,
  keys: Array | None,
  *,
  mode: str,
  config=None,
) -> dict[str, Array]:
  """Vectors of exact poses, one quantisation key per image: (E, V, P) -> {name: (E, V, d)}.

  Args:
    keys: (E,) PRNG keys, used (and required) only for mode="random".
    config: the run's config; its `rep.kind` picks the pose input (default: the learned grid).
  """
  if config is not None and train.rep_kind(config) != "grid":
    return train.pose_vectors(config, spec, params_rep, poses)
  if mode == "random":
    if keys is None:
      raise ValueError("quantisation 'random' needs per-image keys")
    return jax.vmap(lambda p, k: P.embed(params_rep, spec, p, mode=mode, key=k))(poses, keys)
  return P.embed(params_rep, spec, poses, mode=mode)


def add_noise(
  vectors: Mapping[str, Array],
  spec: P.PoseSystemSpec,
  keys: Array,
  *,
  alpha: Array | float,
  betas: Mapping[str, Array],
) -> dict[str, Array]:
  """v + alpha * beta * z per element, z ~ N(0, 1) independent (digest 5), no renormalisation.

  Args:
    vectors: {name: (E, ..., d)}.
    keys: (E,) per-image keys; DOF i of image e draws from fold_in(keys[e], i).
    alpha: noise level.
    betas: {name: (d,)}.

  Returns:
    {name: (E, ..., d)}.
  """
  out = {}
  for i, name in enumerate(spec.names):
    v = vectors[name]
    draw = lambda k, i=i, shape=v.shape[1:]: jax.random.normal(jax.random.fold_in(k, i), shape)
    z = jax.vmap(draw)(keys).astype(v.dtype)
    out[name] = v + alpha * jnp.asarray(betas[name], v.dtype) * z
  return out


def image_keys(key: Array, image_ids: Array) -> tuple[Array, Array, Array]:
  """Per-image (context quantisation, query quantisation, noise) keys, each (E,).

  Image n's keys come from fold_in(key, n), so they do not depend on the batching.
  """
  keys = jax.vmap(lambda i: jax.random.split(jax.random.fold_in(key, i), 3))(image_ids)
  return keys[:, 0], keys[:, 1], keys[:, 2]


def make_noisy_predict(config, model, spec: P.PoseSystemSpec, mode: str):
  """jit(params, batch, key, alpha, betas, image_ids) -> (psnr (E,), ssim (E,), pred).

  The query pose vectors get `add_noise` with the `image_keys` of each image; context poses
  (GQN's encoder input) are embedded with the same quantisation but not noised.

  Args (of the returned function):
    params: {"model", "rep"}.
    batch: an `train.eval_batches` element: context_image (E, C, H, W, 3) uint8,
      context_pose (E, C, P), target_image (E, 1, H, W, 3), target_pose (E, 1, P), scene (E,).
    key: the level's key.
    alpha: scalar noise level.
    betas: {name: (d,)}.
    image_ids: (E,) int32 global image indices.

  Returns (of the returned function):
    per-image PSNR (E,), SSIM (E,) and the prediction (E, 1, H, W, 3) in [-1, 1].
  """
  if mode not in P.QUANTISATION_MODES:
    raise ValueError(f"unknown quantisation {mode!r}; choose one of {P.QUANTISATION_MODES}")

  def predict(params, b, key, alpha, betas, image_ids):
    k_ctx, k_query, k_noise = image_keys(key, image_ids)
    query = pose_vectors(params["rep"], spec, b["target_pose"], k_query, mode=mode, config=config)
    q = P.concat(add_noise(query, spec, k_noise, alpha=alpha, betas=betas), spec)
    if config.task == "gqn":
      ctx = train.to_float_images(b["context_image"])
      c = pose_vectors(params["rep"], spec, b["context_pose"], k_ctx, mode=mode, config=config)
      c = P.concat(c, spec)
      pred, _ = model.apply({"params": params["model"]}, ctx, c, q)
    else:
      pred, _ = model.apply({"params": params["model"]}, b["scene"], q)
    target = train.to_float_images(b["target_image"])
    return metrics_lib.psnr(pred, target), metrics_lib.ssim(pred, target), pred

  return jax.jit(predict)


def noise_robustness(
  run: Run,
  *,
  key: Array,
  alphas: Sequence[float] | np.ndarray | None = None,
  quantisation: str | None = None,
  batches: list[dict[str, np.ndarray]] | None = None,
  progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
  """Mean per-image PSNR and SSIM of held-out views against pose-vector noise (digest 5).

  Args:
    run: a loaded run.
    key: PRNG key; level j uses fold_in(key, j), image n within it fold_in(level key, n).
    alphas: noise levels; default `default_alphas()` (0, 0.025, ..., 0.3).
    quantisation: "random", "nearest" or "floor" for the exact poses; default
      `default_quantisation(run.config)`.
    batches: the evaluation set; default `train.eval_batches(config, train_pipe, test_pipe)`.
    progress: called with one line per level (e.g. `print`).

  Returns:
    {"alphas": (L,), "psnr": (L,), "ssim": (L,) means over images; "psnr_per_image",
     "ssim_per_image": (L, N); "beta": {dof: (d,)}; "quantisation": str; "step": int;
     "num_images": N}.
  """
  alphas = default_alphas() if alphas is None else np.asarray(alphas, np.float64).ravel()
  mode = quantisation or default_quantisation(run.config)
  if batches is None:
    batches = train.eval_batches(run.config, run.train_pipe, run.test_pipe)
  betas = grid_betas(run.params["rep"], run.spec, run.config)
  betas_j = {n: jnp.asarray(b) for n, b in betas.items()}
  predict = make_noisy_predict(run.config, run.model, run.spec, mode)
  dev_batches = [{k: jnp.asarray(v) for k, v in b.items()} for b in batches]
  offsets = np.cumsum([0] + [len(b["scene"]) for b in batches])
  psnr_all, ssim_all = [], []
  t0 = time.perf_counter()
  for j, alpha in enumerate(alphas):
    k_level = jax.random.fold_in(key, j)
    ps, ss = [], []
    for b, start in zip(dev_batches, offsets[:-1], strict=True):
      ids = jnp.arange(start, start + b["scene"].shape[0], dtype=jnp.int32)
      p, s, _ = predict(run.params, b, k_level, jnp.float32(alpha), betas_j, ids)
      ps.append(np.asarray(p).ravel())
      ss.append(np.asarray(s).ravel())
    psnr_all.append(np.concatenate(ps))
    ssim_all.append(np.concatenate(ss))
    if progress is not None:
      elapsed = time.perf_counter() - t0
      eta = elapsed / (j + 1) * (len(alphas) - j - 1)
      progress(
        f"noise level {j + 1}/{len(alphas)} alpha={alpha:.3f}: "
        f"PSNR {np.mean(psnr_all[-1]):.3f} SSIM {np.mean(ssim_all[-1]):.4f} "
        f"({writers.format_duration(elapsed)} elapsed, ETA {writers.format_duration(eta)})"
      )
  psnr_all, ssim_all = np.stack(psnr_all), np.stack(ssim_all)
  return {
    "alphas": alphas,
    "psnr": psnr_all.mean(axis=1),
    "ssim": ssim_all.mean(axis=1),
    "psnr_per_image": psnr_all,
    "ssim_per_image": ssim_all,
    "beta": betas,
    "quantisation": mode,
    "step": run.step,
    "num_images": int(psnr_all.shape[1]),
  }


# --------------------------------------------------------------------------------------------
# Gram maps.


def gram_values(spec: P.PoseSystemSpec, name: str) -> Array:
  """The values of a Gram map: 1-degree steps for angles, the grid points otherwise.

  Returns:
    (K,) values, or (K, 2) positions for a polar DOF (flat index gx * n_side + gy).
  """
  d = spec.dof(name)
  res = math.pi / 180 if isinstance(d, P.AngularDof) else d.spacing
  return P.candidates(spec, name, res)


def gram_maps(run: Run) -> dict[str, np.ndarray]:
  """{dof name: (K, K) Gram matrix V V^T} of the run's pose vectors over `gram_values`.

  Unit-norm DOFs have ones on the diagonal (up to the norm error of exp_method "taylor2" between
  grid points); a polar DOF with block_norm has 1 / n_blocks.
  """
  rep = run.params["rep"]
  if train.rep_kind(run.config) != "grid":  # the same map of another pose input's vectors
    out = {}
    for n in run.spec.names:
      v = train.pose_vectors(
        run.config, run.spec, rep, dof_poses(run.spec, n, gram_values(run.spec, n))
      )[n]
      out[n] = np.asarray(v @ v.T)
    return out
  return {
    n: np.asarray(_jit_gram(rep, run.spec, n, values=gram_values(run.spec, n)))
    for n in run.spec.names
  }


_jit_gram = jax.jit(P.gram, static_argnums=(1, 2))


# --------------------------------------------------------------------------------------------
# Figures (cv2; images are RGB uint8).

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_BLACK = (0, 0, 0)


def _text(img, text, org, *, scale=0.45, color=_BLACK, thickness=1, anchor="left"):
  """Draws text with its baseline at org[1]; anchor "left", "center" or "right" in x."""
  (w, _), _ = cv2.getTextSize(text, _FONT, scale, thickness)
  x, y = org
  if anchor == "center":
    x -= w // 2
  elif anchor == "right":
    x -= w
  cv2.putText(img, text, (int(x), int(y)), _FONT, scale, color, thickness, cv2.LINE_AA)


def _nice_ticks(lo: float, hi: float, n: int = 6) -> np.ndarray:
  """About n round tick values; the first <= lo, the last >= hi."""
  if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
    hi = lo + 1.0
  raw = (hi - lo) / max(n - 1, 1)
  mag = 10 ** math.floor(math.log10(raw))
  step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
  first, last = math.floor(lo / step + 1e-9), math.ceil(hi / step - 1e-9)
  return step * np.arange(first, last + 1)


def _fmt(v: float, step: float) -> str:
  decimals = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 0
  decimals += 1 if abs(round(step * 10**decimals) - step * 10**decimals) > 1e-6 else 0
  return f"{v:.{decimals}f}"


SERIES_COLORS = ((31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14))


def line_plot(
  x: Sequence[float] | np.ndarray,
  y: Sequence[float] | np.ndarray | Mapping[str, Sequence[float]],
  *,
  title: str,
  xlabel: str,
  ylabel: str,
  size: tuple[int, int] = (560, 420),
  color: tuple[int, int, int] = (31, 119, 180),
) -> np.ndarray:
  """A line plot with markers, axes, ticks, grid, labels and a title.

  Args:
    x: (n,) values.
    y: (n,) values, or {label: (n,) values} for several series with a legend (colours from
      `SERIES_COLORS`); non-finite values are left out.
    size: (width, height) in pixels.
    color: RGB line colour of a single series.

  Returns:
    (height, width, 3) uint8 RGB image.
  """
  x = np.asarray(x, np.float64)
  series = (
    {k: np.asarray(v, np.float64) for k, v in y.items()}
    if isinstance(y, Mapping)
    else {"": np.asarray(y, np.float64)}
  )
  colors = (
    dict(zip(series, SERIES_COLORS * 4, strict=False)) if isinstance(y, Mapping) else {"": color}
  )
  width, height = size
  img = np.full((height, width, 3), 255, np.uint8)
  left, right, top, bottom = 70, 20, 40, 55
  pw, ph = width - left - right, height - top - bottom
  every = np.concatenate(list(series.values()))
  ok = np.isfinite(every)
  ylo, yhi = (float(every[ok].min()), float(every[ok].max())) if ok.any() else (0.0, 1.0)
  pad = 0.08 * (yhi - ylo) if yhi > ylo else max(abs(yhi) * 0.05, 0.05)
  yt = _nice_ticks(ylo - pad, yhi + pad)
  xt = _nice_ticks(float(x.min()), float(x.max()))
  x0, x1 = min(xt[0], x.min()), max(xt[-1], x.max())
  y0, y1 = yt[0], yt[-1]
  px = lambda v: left + (v - x0) / (x1 - x0 or 1.0) * pw
  py = lambda v: top + ph - (v - y0) / (y1 - y0 or 1.0) * ph
  for v in xt:
    X = round(px(v))
    cv2.line(img, (X, top), (X, top + ph), (225, 225, 225), 1)
    cv2.line(img, (X, top + ph), (X, top + ph + 5), _BLACK, 1)
    _text(img, _fmt(v, xt[1] - xt[0]), (X, top + ph + 20), anchor="center")
  for v in yt:
    Y = round(py(v))
    cv2.line(img, (left, Y), (left + pw, Y), (225, 225, 225), 1)
    cv2.line(img, (left - 5, Y), (left, Y), _BLACK, 1)
    _text(img, _fmt(v, yt[1] - yt[0]), (left - 8, Y + 5), anchor="right")
  cv2.rectangle(img, (left, top), (left + pw, top + ph), _BLACK, 1)
  for i, (label, yv) in enumerate(series.items()):
    ok = np.isfinite(yv)
    c = colors[label]
    pts = np.array([[px(a), py(b)] for a, b in zip(x[ok], yv[ok], strict=True)])
    if len(pts):
      pts_i = np.round(pts).astype(np.int32)
      cv2.polylines(img, [pts_i.reshape(-1, 1, 2)], False, c, 2, cv2.LINE_AA)
      for p in pts_i:
        cv2.circle(img, (int(p[0]), int(p[1])), 4, c, -1, cv2.LINE_AA)
    if label:  # legend, top right inside the axes
      ly = top + 18 + 20 * i
      cv2.line(img, (left + pw - 150, ly - 4), (left + pw - 125, ly - 4), c, 2, cv2.LINE_AA)
      _text(img, label, (left + pw - 118, ly))
  _text(img, title, (width // 2, 25), scale=0.6, anchor="center")
  _text(img, xlabel, (left + pw // 2, height - 12), scale=0.5, anchor="center")
  # Rotated y label: draw horizontally on a strip, rotate, paste left of the tick labels.
  (tw, th), _ = cv2.getTextSize(ylabel, _FONT, 0.5, 1)
  strip = np.full((th + 8, min(tw + 4, ph)), 255, np.uint8)
  cv2.putText(strip, ylabel, (2, th + 2), _FONT, 0.5, 0, 1, cv2.LINE_AA)
  strip = cv2.rotate(strip, cv2.ROTATE_90_COUNTERCLOCKWISE)
  ys = top + (ph - strip.shape[0]) // 2
  img[ys : ys + strip.shape[0], 4 : 4 + strip.shape[1]] = strip[..., None]
  return img


def noise_figure(result: Mapping[str, Any], *, title: str = "") -> np.ndarray:
  """PSNR and SSIM against alpha, side by side: (420, 1120, 3) uint8 RGB."""
  a = result["alphas"]
  suffix = f" ({title})" if title else ""
  left = line_plot(
    a, result["psnr"], title=f"PSNR vs noise{suffix}", xlabel="alpha", ylabel="PSNR (dB)"
  )
  right = line_plot(
    a,
    result["ssim"],
    title=f"SSIM vs noise{suffix}",
    xlabel="alpha",
    ylabel="SSIM",
    color=(214, 39, 40),
  )
  return np.concatenate([left, right], axis=1)


def heat_map(
  m: np.ndarray,
  *,
  title: str,
  caption: str = "",
  min_size: int = 400,
  max_size: int = 1024,
  colormap: int = cv2.COLORMAP_VIRIDIS,
) -> np.ndarray:
  """A (K, K) matrix as a colour-mapped image with a title, caption and colour bar.

  Small matrices are upscaled by an integer factor (nearest neighbour, so cells stay sharp) to at
  least `min_size` pixels; larger than `max_size` ones are shrunk (area averaging).

  Returns:
    uint8 RGB image.
  """
  m = np.asarray(m, np.float64)
  lo, hi = float(np.nanmin(m)), float(np.nanmax(m))
  span = hi - lo if hi > lo else 1.0
  gray = np.clip(np.round((np.nan_to_num(m, nan=lo) - lo) / span * 255), 0, 255).astype(np.uint8)
  K = max(m.shape)
  if K > max_size:
    side = (max_size * m.shape[1] // K, max_size * m.shape[0] // K)
    gray = cv2.resize(gray, side, interpolation=cv2.INTER_AREA)
  else:
    f = max(1, math.ceil(min_size / K))
    gray = cv2.resize(gray, (m.shape[1] * f, m.shape[0] * f), interpolation=cv2.INTER_NEAREST)
  body = cv2.applyColorMap(gray, colormap)  # BGR
  h, w = body.shape[:2]
  top, bottom, bar_w, right = 40, 40 if caption else 16, 18, 80
  img = np.full((top + h + bottom, 16 + w + 16 + bar_w + right, 3), 255, np.uint8)
  img[top : top + h, 16 : 16 + w] = body
  ramp = np.linspace(255, 0, h).round().astype(np.uint8)[:, None].repeat(bar_w, axis=1)
  bx = 16 + w + 16
  img[top : top + h, bx : bx + bar_w] = cv2.applyColorMap(ramp, colormap)
  cv2.rectangle(img, (bx, top), (bx + bar_w - 1, top + h - 1), _BLACK, 1)
  ticks = _nice_ticks(lo, hi, 5)
  ticks = ticks[(ticks >= lo - 1e-9) & (ticks <= hi + 1e-9)]
  step = ticks[1] - ticks[0] if len(ticks) > 1 else span
  for v in ticks:
    Y = round(top + (hi - v) / span * (h - 1))
    cv2.line(img, (bx + bar_w, Y), (bx + bar_w + 4, Y), _BLACK, 1)
    _text(img, _fmt(v, step), (bx + bar_w + 7, min(max(Y + 5, top + 10), top + h)))
  rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
  _text(rgb, title, (16, 27), scale=0.6)
  if caption:
    _text(rgb, caption, (16, top + h + 26), scale=0.45)
  return rgb


def _write_png(path: str, rgb: np.ndarray) -> None:
  ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
  if not ok:
    raise RuntimeError(f"PNG encoding of {path} failed")
  with open(path, "wb") as f:
    f.write(png.tobytes())


def _gram_caption(spec: P.PoseSystemSpec, name: str, k: int) -> str:
  d = spec.dof(name)
  if isinstance(d, P.AngularDof):
    return f"{k} values, 1-degree steps from {math.degrees(d.low):.0f} deg"
  if isinstance(d, P.PolarDof):
    return f"{d.n_side} x {d.n_side} grid points, flat index gx * {d.n_side} + gy"
  return f"{k} grid points, {d.low:g} to {d.high:g} step {d.spacing:g}"


# --------------------------------------------------------------------------------------------
# Command line.


def _beta_stats(betas: Mapping[str, np.ndarray]) -> dict[str, dict[str, float]]:
  return {
    n: {"d": int(b.size), "mean": float(b.mean()), "min": float(b.min()), "max": float(b.max())}
    for n, b in betas.items()
  }


def write_noise(out: str, run: Run, result: Mapping[str, Any]) -> list[str]:
  """Writes out/noise.json and out/noise.png; returns their paths."""
  record = {
    "workdir": os.path.abspath(run.workdir),
    "step": int(result["step"]),
    "setting": train.setting(run.config),
    "quantisation": result["quantisation"],
    "num_images": int(result["num_images"]),
    "alphas": [round(float(a), 10) for a in result["alphas"]],
    "psnr": [float(v) for v in result["psnr"]],
    "ssim": [float(v) for v in result["ssim"]],
    "psnr_std": [float(v) for v in np.std(result["psnr_per_image"], axis=1)],
    "beta": _beta_stats(result["beta"]),
  }
  paths = [os.path.join(out, "noise.json"), os.path.join(out, "noise.png")]
  with open(paths[0], "w", encoding="utf-8") as f:
    json.dump(record, f, indent=1)
  title = f"{train.setting(run.config)}, step {result['step']}, {result['num_images']} images"
  _write_png(paths[1], noise_figure(result, title=title))
  return paths


def write_grams(out: str, run: Run, grams: Mapping[str, np.ndarray]) -> list[str]:
  """Writes out/gram_<dof>.png and out/gram.npz ({dof}: Gram, {dof}_values: values)."""
  paths = []
  arrays = {}
  for name, g in grams.items():
    arrays[name] = g
    arrays[f"{name}_values"] = np.asarray(gram_values(run.spec, name))
    path = os.path.join(out, f"gram_{name}.png")
    title = f"Gram V V^T of {name} ({g.shape[0]} x {g.shape[1]}), step {run.step}"
    _write_png(path, heat_map(g, title=title, caption=_gram_caption(run.spec, name, g.shape[0])))
    paths.append(path)
  npz = os.path.join(out, "gram.npz")
  np.savez(npz, **arrays)
  return [*paths, npz]


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
  p = argparse.ArgumentParser(
    prog="python -m camrep.synthesis.evaluate",
    description="Noise robustness and Gram maps of a trained camrep run (digest section 5).",
  )
  p.add_argument("--workdir", required=True, help="training workdir (config.json, checkpoints/)")
  p.add_argument("--what", default="noise,gram", help="comma-separated: noise, gram")
  p.add_argument("--levels", type=int, default=DEFAULT_LEVELS, help="alpha = 0.025 j, j < levels")
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
    args.alphas = default_alphas(args.levels)
  args.what = what
  return args


def main(argv: Sequence[str] | None = None) -> int:
  """The command line; returns the exit status."""
  args = _parse_args(argv)
  # Orbax logs at WARNING that a read-only manager ignores its save options.
  absl_logging.set_verbosity(absl_logging.ERROR)
  log = lambda s: print(s, flush=True)
  try:
    run = load_run(args.workdir, step=args.step)
  except FileNotFoundError as e:
    print(f"error: {e}", file=sys.stderr, flush=True)
    return 2
  if args.num_scenes is not None:
    run.config.evals.num_scenes = args.num_scenes
  out = args.out or os.path.join(args.workdir, EVAL_SUBDIR)
  os.makedirs(out, exist_ok=True)
  log(f"restored step {run.step} of {args.workdir} ({train.setting(run.config)})")
  written = []
  if "noise" in args.what:
    result = noise_robustness(
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
    written += write_noise(out, run, result)
  if "gram" in args.what:
    log("gram maps: " + ", ".join(run.spec.names))
    written += write_grams(out, run, gram_maps(run))
  log("wrote:\n  " + "\n  ".join(written))
  return 0


if __name__ == "__main__":
  sys.exit(main())

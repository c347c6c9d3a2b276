"""Robustness of view synthesis to noise on the pose vectors (paper section 4.3, the authors' code).

Noise-robustness experiment (paper figure "PSNR vs noise", the authors' code): beta_i is the std of
element i over the DOF's normalised grid vectors (`pose.grid_std`, computed once per DOF). At
level alpha every element i of every query pose sub-vector, computed for the exact pose, gets
independent N(0, (alpha beta_i)^2) noise, without renormalisation; fresh noise per image and per
level. GQN: only the query (decoder) pose vectors are noised, not the encoder's context poses;
GQN's own generator (model.kind "convdraw") gets the noise on its 7-D query pose vector the same
way, and samples its latents with the evaluation's fixed per-scene keys (the same at every level).
The exact pose is quantised by the random lower/upper neighbour rule for the GQN and car
settings (the authors' test) and by rounding for Gibson and 7-Scenes; the training loop's eval
always rounds ("nearest"), so alpha = 0 with quantisation="nearest" reproduces its PSNR. The
images are the training loop's held-out-view evaluation set (`heldout.eval_batches`): per scene
the first test view as the query, and for GQN the first n_context training views as context.

Noise on the pose (`NOISE_ON` "pose", the multi-view transformer's default): the query pose
itself gets the noise before any conditioning sees it, so every camera conditioning (raymaps,
GTA, PRoPE, the learned absolute and relative encodings, the control without cameras) is tested
on the same perturbed poses: column c of every query pose gets independent N(0, (alpha beta_c)^2)
noise, beta_c the std of column c over the grid of its DOF in one-column form
(`camera_conditioning.columnwise`: rooms x, y, yaw; car azimuth, polar), the pose-space analogue
of the vectors' beta. The noise keys are those of the vector test (`image_keys`), so runs with
the same seed see the same noisy poses. Periodic angles wrap where the conditioning reads them
(the learned grid wraps, the cameras' trigonometry does); positions pushed past a DOF's range
clamp in the learned grid and extrapolate in the cameras. A learned absolute system quantises the
noisy pose like an exact one (`quantisation`).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from camrep import metrics as metrics_lib
from camrep import pose as P
from camrep import pose_encodings
from camrep.models import camera_conditioning
from camrep.runtime import plots
from camrep.runtime import progress as progress_lib
from camrep.synthesis import components, heldout, synthesizers
from camrep.synthesis.restore import Run

Array = jax.Array

DEFAULT_LEVELS = 13

NOISE_ON = ("vectors", "pose")
"""Where the noise goes: the query's per-DOF pose vectors v(p) (the paper's test) or the query
pose before conditioning (every conditioning of the multi-view transformer)."""


ALPHA_STEP = 0.025


def default_alphas(levels: int = DEFAULT_LEVELS) -> np.ndarray:
  """alpha = 0.025 j for j = 0 .. levels - 1 (paper: 13 levels, 0 to 0.30)."""
  return ALPHA_STEP * np.arange(levels)


def default_quantisation(config: ml_collections.ConfigDict) -> str:
  """The noise test's quantisation (authors): random neighbour for GQN and car, else rounding."""
  return components.setting(config).noise_quantisation


def grid_betas(
  params_rep: dict, spec: P.PoseSystemSpec, model: synthesizers.Synthesizer | None = None
) -> dict[str, np.ndarray]:
  """beta per DOF: {name: (d,)} std of each element over the DOF's normalised grid vectors.

  With a `model`, its pose encoding's `spread`: for another pose input than the learned grid
  ("lowdim", "mlp") the population is the same grid points (`P.candidates` at the grid spacing)
  pushed through that pose input, so every kind is noised relative to its own spread over the
  same poses.
  """
  if model is None:
    return {n: np.asarray(P.grid_std(params_rep, spec, n)) for n in spec.names}
  return {n: np.asarray(v) for n, v in model.pose_encoding.spread(params_rep).items()}


def pose_vectors(
  params_rep: dict,
  spec: P.PoseSystemSpec,
  poses: Array,
  keys: Array | None,
  *,
  mode: str,
) -> dict[str, Array]:
  """The learned system's vectors of exact poses, one quantisation key per image:
  (E, V, P) -> {name: (E, V, d)}.

  Args:
    keys: (E,) PRNG keys, used (and required) only for mode="random".
  """
  return pose_encodings.GridEncoding(spec).embed_images(params_rep, poses, mode=mode, keys=keys)


def pose_betas(spec: P.PoseSystemSpec) -> np.ndarray:
  """beta per pose column (P,): the std of the column over its DOF's grid, of the system in
  one-column form (`camera_conditioning.columnwise`), so that a setting's pose columns get the
  same betas whichever pose system a run learns."""
  out = []
  for d in camera_conditioning.columnwise(spec).dofs:
    out.append(float(np.std(np.asarray(d.candidates(d.spacing), np.float64))))
  return np.asarray(out)


def add_pose_noise(poses: Array, keys: Array, *, alpha: Array | float, betas: Array) -> Array:
  """p + alpha * beta * z per pose column, z ~ N(0, 1) independent: (E, V, P) -> (E, V, P).

  Args:
    poses: (E, V, P) exact poses.
    keys: (E,) per-image keys; image e draws from keys[e].
    alpha: noise level.
    betas: (P,) per column (`pose_betas`).
  """
  z = jax.vmap(lambda k: jax.random.normal(k, poses.shape[1:]))(keys).astype(poses.dtype)
  return poses + alpha * jnp.asarray(betas, poses.dtype) * z


def add_noise(
  vectors: Mapping[str, Array],
  spec: P.PoseSystemSpec,
  keys: Array,
  *,
  alpha: Array | float,
  betas: Mapping[str, Array],
) -> dict[str, Array]:
  """v + alpha * beta * z per element, z ~ N(0, 1) independent (as the authors), no renormalisation.

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


def make_noisy_predict(model: synthesizers.Synthesizer, mode: str, on: str = "vectors"):
  """jit(params, batch, key, alpha, betas, image_ids) -> (psnr (E,), ssim (E,), pred).

  on="vectors": the query pose vectors get `add_noise` with the `image_keys` of each image;
  on="pose": the query poses get `add_pose_noise` with the same keys, before the model reads
  them. Context poses (GQN's encoder input, the transformer's context cameras) are embedded
  with the same quantisation but not noised.

  Args (of the returned function):
    params: {"model", "rep"}.
    batch: an `heldout.eval_batches` element: context_image (E, C, H, W, 3) uint8,
      context_pose (E, C, P), target_image (E, 1, H, W, 3), target_pose (E, 1, P), scene (E,).
    key: the level's key.
    alpha: scalar noise level.
    betas: {name: (d,)} (on="vectors") or (P,) (on="pose").
    image_ids: (E,) int32 global image indices.

  Returns (of the returned function):
    per-image PSNR (E,), SSIM (E,) and the prediction (E, 1, H, W, 3) in [-1, 1].
  """
  if mode not in P.QUANTISATION_MODES:
    raise ValueError(f"unknown quantisation {mode!r}; choose one of {P.QUANTISATION_MODES}")
  if on not in NOISE_ON:
    raise ValueError(f"unknown noise target {on!r}; choose one of {NOISE_ON}")

  def predict(params, b, key, alpha, betas, image_ids):
    k_ctx, k_query, k_noise = image_keys(key, image_ids)
    keys = (k_ctx, k_query)
    if on == "pose":
      noisy = add_pose_noise(b["target_pose"], k_noise, alpha=alpha, betas=betas)
      pred = model.predict(params, {**b, "target_pose": noisy}, mode=mode, keys=keys)
    else:
      noise = lambda v: add_noise(v, model.spec, k_noise, alpha=alpha, betas=betas)
      pred = model.predict(params, b, mode=mode, keys=keys, transform=noise)
    target = synthesizers.to_float_images(b["target_image"])
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
  on: str | None = None,
) -> dict[str, Any]:
  """Mean per-image PSNR and SSIM of held-out views against pose noise (the authors' code on the
  pose vectors; or on the pose before conditioning).

  Args:
    run: a loaded run.
    key: PRNG key; level j uses fold_in(key, j), image n within it fold_in(level key, n).
    alphas: noise levels; default `default_alphas()` (0, 0.025, ..., 0.3).
    quantisation: "random", "nearest" or "floor" for the exact poses; default
      `default_quantisation(run.config)`.
    batches: the evaluation set; default `heldout.eval_batches(model, train_pipe, test_pipe)`.
    progress: called with one line per level (e.g. `print`).
    on: `NOISE_ON`; default the model's `noise_on` ("vectors" for the decoders, "pose" for the
      multi-view transformer).

  Returns:
    {"alphas": (L,), "psnr": (L,), "ssim": (L,) means over images; "psnr_per_image",
     "ssim_per_image": (L, N); "beta": {dof: (d,)} (on="vectors") or {column: (1,)}
     (on="pose"); "on": str; "quantisation": str; "step": int; "num_images": N}.
  """
  alphas = default_alphas() if alphas is None else np.asarray(alphas, np.float64).ravel()
  mode = quantisation or default_quantisation(run.config)
  on = on or run.model.noise_on
  if batches is None:
    batches = heldout.eval_batches(run.model, run.train_pipe, run.test_pipe)
  if on == "pose":
    per_column = pose_betas(run.spec)
    columns = camera_conditioning.columnwise(run.spec).names
    betas = {c: per_column[i : i + 1] for i, c in enumerate(columns)}
    betas_j = jnp.asarray(per_column, jnp.float32)
  else:
    betas = grid_betas(run.params["rep"], run.spec, run.model)
    betas_j = {n: jnp.asarray(b) for n, b in betas.items()}
  predict = make_noisy_predict(run.model, mode, on)
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
        f"({progress_lib.format_duration(elapsed)} elapsed, "
        f"ETA {progress_lib.format_duration(eta)})"
      )
  psnr_all, ssim_all = np.stack(psnr_all), np.stack(ssim_all)
  return {
    "alphas": alphas,
    "psnr": psnr_all.mean(axis=1),
    "ssim": ssim_all.mean(axis=1),
    "psnr_per_image": psnr_all,
    "ssim_per_image": ssim_all,
    "beta": betas,
    "on": on,
    "quantisation": mode,
    "step": run.step,
    "num_images": int(psnr_all.shape[1]),
  }


def noise_figure(result: Mapping[str, Any], *, title: str = "") -> plots.Figure:
  """PSNR and SSIM against alpha, side by side (a matplotlib Figure)."""
  panels = [
    plots.Panel("PSNR vs pose noise", "PSNR (dB)", {"": result["psnr"]}, xlabel="alpha"),
    plots.Panel("SSIM vs pose noise", "SSIM", {"": result["ssim"]}, xlabel="alpha"),
  ]
  return plots.curves_figure(result["alphas"], panels, suptitle=title)


def _beta_stats(betas: Mapping[str, np.ndarray]) -> dict[str, dict[str, float]]:
  return {
    n: {"d": int(b.size), "mean": float(b.mean()), "min": float(b.min()), "max": float(b.max())}
    for n, b in betas.items()
  }


def write_noise(out: str, run: Run, result: Mapping[str, Any]) -> list[str]:
  """Writes out/noise.json and the figure out/noise.png (and its PDF twin); returns the paths."""
  record = {
    "workdir": os.path.abspath(run.workdir),
    "step": int(result["step"]),
    "setting": components.setting(run.config).name,
    "noise_on": result.get("on", "vectors"),
    "quantisation": result["quantisation"],
    "num_images": int(result["num_images"]),
    "alphas": [round(float(a), 10) for a in result["alphas"]],
    "psnr": [float(v) for v in result["psnr"]],
    "ssim": [float(v) for v in result["ssim"]],
    "psnr_std": [float(v) for v in np.std(result["psnr_per_image"], axis=1)],
    "beta": _beta_stats(result["beta"]),
  }
  if run.model.temperature is not None:  # GQN's generator: which latents
    record["draw_temperature"] = run.model.temperature
  path = os.path.join(out, "noise.json")
  with open(path, "w", encoding="utf-8") as f:
    json.dump(record, f, indent=1)
  title = f"{components.setting(run.config)}, step {result['step']}, {result['num_images']} images"
  return [path, *plots.save(noise_figure(result, title=title), os.path.join(out, "noise.png"))]

"""The parts of a view-synthesis run, built from its config (paper section 4.1, digest 1-2):
the setting, the pose system, the model and the data pipelines; `check_config` refuses
combinations the train step cannot run before anything is built.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from camrep import pose as P
from camrep import pose_inputs
from camrep.data import batches, sources
from camrep.data import pipeline as pipeline_lib
from camrep.data.errors import DataError
from camrep.models.composite import GQNSynthesis, TableSynthesis
from camrep.models.convdraw import GQNConvDraw
from camrep.runtime.runconfig import ConfigError

Array = jax.Array


def setting(config) -> str:
  """The paper's setting of the config's data source: gqn, car, gibson or seven_scenes."""
  return sources.setting_of(config.data.source)


# config.model.kind: camrep's decoders (trained on L_rec) or GQN's generator (trained on its ELBO).
MODEL_KINDS = ("decoder", "convdraw")

# Latent draws of GQN's generator at evaluation: scene s samples from fold_in(key(SAMPLE_SEED), s),
# so predictions do not depend on the batching, and the noise test at alpha = 0 repeats the eval.
SAMPLE_SEED = 20180615


# config.model.dtype -> the models' `dtype` (None: float32, Flax's inference from the parameters).
COMPUTE_DTYPES = {"float32": None, "bfloat16": jnp.bfloat16}


def compute_dtype(config):
  """The dtype of the model's computation from `config.model.dtype` (absent: float32)."""
  name = config.model.get("dtype", "float32")
  if name not in COMPUTE_DTYPES:
    raise ValueError(f"unknown model.dtype {name!r}; choose one of {tuple(COMPUTE_DTYPES)}")
  return COMPUTE_DTYPES[name]


def model_kind(config) -> str:
  kind = config.model.get("kind", "decoder")
  if kind not in MODEL_KINDS:
    raise ValueError(f"unknown model.kind {kind!r}; choose one of {MODEL_KINDS}")
  return kind


def check_config(config) -> None:
  """Raises ConfigError on combinations the train step cannot run (e.g. GQN layouts without
  query views, or data-pair rotation losses on a batch that holds no pairs)."""
  d, L = config.data, config.loss
  try:
    setting(config)
    kind = pose_inputs.rep_kind(config)
    mkind = model_kind(config)
    dtype = compute_dtype(config)
    num_workers(config)
  except ValueError as e:  # unknown data.source, rep.kind, model.kind, model.dtype; num_workers
    raise ConfigError(str(e)) from None
  if config.total_steps < 1:
    raise ConfigError(f"total_steps must be >= 1, got {config.total_steps}")
  if config.task == "gqn" and not 1 <= d.n_context < d.views_per_scene:
    raise ConfigError(
      f"data.n_context must be in [1, views_per_scene) so that each scene has query views, "
      f"got n_context={d.n_context}, views_per_scene={d.views_per_scene}"
    )
  if mkind == "convdraw" and (config.task != "gqn" or kind != "lowdim"):
    raise ConfigError(
      "model.kind='convdraw' (GQN's generator) needs task='gqn' and rep.kind='lowdim' (its 7-D "
      f"pose vector; the ELBO trains the model group only), got task={config.task!r}, "
      f"rep.kind={kind!r}"
    )
  if mkind == "convdraw" and dtype is not None:
    raise ConfigError(
      f"model.dtype={config.model.dtype!r} is implemented for model.kind='decoder' only; "
      "GQN's generator (convdraw) computes in float32"
    )
  if L.data_pairs and kind == "grid" and d.mode != "pairs":
    raise ConfigError(
      "loss.data_pairs reads the batch's views as (anchor, partner) pairs: it needs "
      f"data.mode='pairs', got {d.mode!r} (GQN rooms: leave data_pairs off)"
    )


def pose_spec(config) -> P.PoseSystemSpec:
  """The pose system of the config's setting (digest 1.7), with camrep's options from config.rep."""
  r = config.rep
  ang = math.radians(r.angle_spacing_deg)

  def angle(name, low=0.0, high=2 * math.pi, periodic=None):
    return P.AngularDof(
      name, spacing=ang, low=low, high=high, periodic=r.periodic if periodic is None else periodic
    )

  def polar(low, high):
    return P.PolarDof(
      "xy",
      low=low,
      high=high,
      spacing=r.position_spacing,
      n_directions=r.n_directions,
      variant=r.polar_variant,
      block_norm=r.block_norm,
      pair_radius=r.pair_radius,
    )

  s = setting(config)
  if s == "gqn":
    dofs = (polar(-1.0, 1.0), angle("yaw"))
  elif s == "gibson":
    dofs = (polar(0.0, 2.0), angle("yaw"))
  elif s == "car":
    dofs = (angle("azimuth"), angle("polar", high=math.pi, periodic=False))
  else:
    sp = r.position_spacing
    dofs = (
      P.LinearDof("x", 0.0, 4.0, sp),
      P.LinearDof("y", 0.0, 1.5, sp),
      P.LinearDof("z", 0.0, 3.0, sp),
      angle("theta"),
      angle("phi", high=math.pi, periodic=False),
      angle("psi"),
    )
  return P.PoseSystemSpec(
    dofs=dofs,
    n_blocks=r.n_blocks,
    block_size=r.block_size,
    exp_method=r.exp_method,
    n_steps=r.n_steps,
  )


def make_model(config, num_scenes: int):
  """The view-synthesis model of the config's setting, computing in `config.model.dtype`."""
  m = config.model
  if model_kind(config) == "convdraw":
    return GQNConvDraw(width=m.width, steps=m.draw_steps, z_channels=m.z_channels)
  dtype = compute_dtype(config)
  if config.task == "gqn":
    return GQNSynthesis(width=m.width, gamma_offset=1.0 if m.gamma_init_one else 0.0, dtype=dtype)
  return TableSynthesis(
    num_scenes=num_scenes,
    scene_dim=m.scene_dim,
    width=m.width,
    image_size=m.image_size,
    per_scene_norm=m.per_scene_norm,
    norm_eps=m.norm_eps,
    gamma_init_one=m.gamma_init_one,
    dtype=dtype,
  )


def draw_temperature(config) -> float:
  """GQN's generator at prediction: latent temperature (1: a prior sample, 0: the prior mean)."""
  return float(config.model.get("draw_temperature", 1.0))


def sample_keys(scene_ids: Array) -> Array:
  """(E,) scene ids -> (E,) PRNG keys of GQN's generator at evaluation (`SAMPLE_SEED`)."""
  base = jax.random.key(SAMPLE_SEED)
  return jax.vmap(lambda i: jax.random.fold_in(base, i))(scene_ids)


def render_gqn(
  config,
  model,
  params_model,
  context_images: Array,
  context_vecs: Array,
  query_vecs: Array,
  scene_ids: Array,
  temperature: float | None = None,
) -> Array:
  """Predicted query views of the GQN setting: (E, Q, H, W, 3) in [-1, 1].

  camrep's decoder: its output. GQN's generator: the mean image of one prior sample with the
  scenes' `sample_keys` (deterministic), clipped to [-1, 1]; latents at `temperature` (default
  config.model.draw_temperature: 1 GQN's sample, 0 the prior mean).
  """
  variables = {"params": params_model}
  if model_kind(config) == "convdraw":
    if temperature is None:
      temperature = draw_temperature(config)
    pred, _ = model.apply(
      variables,
      context_images,
      context_vecs,
      query_vecs,
      sample_keys(scene_ids),
      temperature,
      method="sample",
    )
    return jnp.clip(pred, -1.0, 1.0)
  pred, _ = model.apply(variables, context_images, context_vecs, query_vecs)
  return pred


def num_workers(config) -> int:
  """Worker processes of a prepared dataset's pipeline: `data.num_workers`, -1 (or absent) for
  `pipeline.default_num_workers()` (all usable cores but two)."""
  n = int(config.data.get("num_workers", -1))
  if n < -1:
    raise ValueError(f"data.num_workers must be >= -1 (-1: from the core count), got {n}")
  return pipeline_lib.default_num_workers() if n == -1 else n


def make_pipeline(
  config,
  split: str,
  *,
  num_devices: int,
  process_index: int = 0,
  process_count: int = 1,
  for_eval: bool = False,
):
  """Batches of `split` laid out for the pmapped step (see camrep.data.pipeline).

  Data comes from `config.data.dir` (a prepared tfds directory) when set, its training batches
  decoded by `num_workers(config)` worker processes; otherwise from the procedural family, held
  in memory (`data.in_memory`) or rendered batch by batch. With `for_eval` the pipeline only
  serves `scene_views` (a one-scene, one-view layout).
  """
  d = config.data
  pcfg = pipeline_lib.PipelineConfig(
    num_devices=num_devices,
    scenes_per_device=1 if for_eval else d.scenes_per_device,
    views_per_scene=1 if for_eval else d.views_per_scene,
    mode="random" if for_eval else d.mode,
    seed=config.seed,
    num_threads=d.num_threads,
    prefetch=d.prefetch,
  )
  kw = dict(process_index=process_index, process_count=process_count)
  if d.dir:
    pcfg = dataclasses.replace(pcfg, num_workers=0 if for_eval else num_workers(config))
    return pipeline_lib.tfds_pipeline(
      d.dir, d.source, split, pcfg, dataset_config=batches.prepared_config_name(d), **kw
    )
  if not sources.is_procedural(d.source):
    raise DataError(
      None,
      f"data.source {d.source!r} is a real dataset: prepare it with "
      f"`python -m camrep.data.prepare --source {d.source} --input PATH --data_dir DIR` "
      "and pass --config.data.dir=DIR",
    )
  family = sources.family_of_config(d)
  if d.in_memory:
    return pipeline_lib.memory_pipeline(family, split, pcfg, **kw)
  return pipeline_lib.render_pipeline(family, split, pcfg, **kw)


def num_train_scenes(pipe) -> int:
  """Size of the per-scene tables: one past the largest training scene id."""
  return int(pipe.all_scene_ids.max()) + 1


def to_float_images(images: Array) -> Array:
  """uint8 [0, 255] -> float32 [-1, 1] (digest 6.1)."""
  return images.astype(jnp.float32) * (2.0 / 255.0) - 1.0

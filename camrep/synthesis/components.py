"""The parts of a view-synthesis run, built from its config (paper section 4.1): what the
config's names stand for, looked up once (`resolve`: the setting, the pose system, the pose
input's and the model's classes, the compute dtype), the model (`make_model`), the data pipelines
and the training batches on the devices; `check_config` refuses combinations the train step
cannot run before anything is built.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from typing import Any

import jax
import ml_collections

from camrep import pose as P
from camrep import pose_encodings, settings
from camrep.data import records, sources
from camrep.data.errors import DataError
from camrep.data.feed import batches, fingerprint, storage
from camrep.data.feed import pipeline as pipeline_lib
from camrep.runtime import frame as frame_lib
from camrep.runtime.runconfig import ConfigError
from camrep.synthesis import synthesizers

Array = jax.Array


@dataclasses.dataclass(frozen=True)
class Resolved:
  """A view-synthesis config and what its names stand for, looked up once (`resolve`).

  Attributes:
    config: the run's config.
    setting: the paper's setting of `data.source` (`camrep.settings`).
    spec: the setting's pose system with camrep's options (`pose_spec`).
    encoding: the pose input's `PoseEncoding` class (`rep.kind`, default "grid").
    model: the `Synthesizer` class (`model.kind`, default "decoder", and `task`:
      `synthesizers.model_class`).
    dtype: the model's compute dtype (`model.dtype`, default "float32":
      `synthesizers.compute_dtype`; None for float32).
  """

  config: ml_collections.ConfigDict
  setting: settings.Setting
  spec: P.PoseSystemSpec
  encoding: type[pose_encodings.PoseEncoding]
  model: type[synthesizers.Synthesizer]
  dtype: Any


def resolve(config) -> Resolved:
  """The config `Resolved`: each name looked up once. Builds nothing (`check_config` checks the
  fields together; a workdir's config was checked when it was written).

  Raises:
    ConfigError: an unknown data.source, rep.kind, model.kind, model.dtype or task.
  """
  kind, m = config.rep.get("kind", "grid"), config.model
  try:
    setting_ = setting(config)
    if kind not in pose_encodings.SYNTHESIS_KINDS:
      raise ValueError(f"unknown rep.kind {kind!r}; choose one of {pose_encodings.SYNTHESIS_KINDS}")
    model = synthesizers.model_class(m.get("kind", "decoder"), config.task)
    dtype = synthesizers.compute_dtype(m.get("dtype", "float32"))
  except ValueError as e:
    raise ConfigError(str(e)) from None
  spec = _pose_spec(setting_, config.rep)
  return Resolved(config, setting_, spec, pose_encodings.ENCODINGS[kind], model, dtype)


def setting(config) -> settings.Setting:
  """The paper's setting of the config's data source (`camrep.settings`)."""
  return sources.setting_of(config.data.source)


def check_config(config) -> Resolved:
  """Raises ConfigError on combinations the train step cannot run (e.g. GQN layouts without
  query views, or data-pair rotation losses on a batch that holds no pairs).

  Returns:
    The config `Resolved`.
  """
  run = resolve(config)
  try:
    num_workers(config)
  except ValueError as e:
    raise ConfigError(str(e)) from None
  synthesizers.check_config(run)
  run.model.check(run)
  if config.total_steps < 1:
    raise ConfigError(f"total_steps must be >= 1, got {config.total_steps}")
  rule = frame_lib.stopping_rule(config)
  if rule.active and config.eval_every_steps <= 0:
    raise ConfigError(
      f"--config.stop.min_improvement={rule.min_improvement:g}: the plateau rule is checked at "
      "the held-out evaluations; set --config.eval_every_steps > 0"
    )
  return run


def pose_spec(config) -> P.PoseSystemSpec:
  """The pose system of the config's setting (`Setting.pose_spec`: its DOFs and ranges), with
  camrep's options (config.rep)."""
  return _pose_spec(setting(config), config.rep)


def _pose_spec(setting_: settings.Setting, r) -> P.PoseSystemSpec:
  return setting_.pose_spec(
    angle_spacing=math.radians(r.angle_spacing_deg),
    periodic=r.periodic,
    position_spacing=r.position_spacing,
    polar_variant=r.polar_variant,
    n_directions=r.n_directions,
    block_norm=r.block_norm,
    pair_radius=r.pair_radius,
    n_blocks=r.n_blocks,
    block_size=r.block_size,
    exp_method=r.exp_method,
    n_steps=r.n_steps,
  )


def spec_record(spec: P.PoseSystemSpec) -> dict:
  """A pose-system spec as JSON values: its fields, each DOF's `record` (its class, "kind", and
  fields)."""
  fields = {f.name: getattr(spec, f.name) for f in dataclasses.fields(spec) if f.name != "dofs"}
  dofs = [d.record() for d in spec.dofs]
  return fingerprint.plain({**fields, "dofs": dofs})


RECORD_VERSION = 1


def run_record(run: Resolved) -> dict:
  """What decides a run's data and model beyond its config (the workdir's record.json, checked
  at resume by `runtime.workdir.check_record`): {"version", "data": `fingerprint.data_record`
  (the family's resolved parameters or the prepared dataset's identity, and their
  fingerprint), "pose_spec": `spec_record` of the resolved pose system}. Renders nothing.

  Raises:
    DataError: the data cannot be found or its family built.
  """
  return {
    "version": RECORD_VERSION,
    "data": fingerprint.data_record(run.config.data),
    "pose_spec": spec_record(run.spec),
  }


def make_model(run: Resolved, num_scenes: int) -> synthesizers.Synthesizer:
  """The run's view-synthesis model (`run.model`) on its pose system.

  Args:
    run: the config `Resolved`.
    num_scenes: size of the per-scene tables (one past the largest training scene id).
  """
  return run.model(run, num_scenes)


def num_workers(config) -> int:
  """Worker processes of a prepared dataset's pipeline: `data.num_workers`, -1 (or absent) for
  `pipeline.default_num_workers()` (all usable cores but two)."""
  n = int(config.data.get("num_workers", -1))
  if n < -1:
    raise ValueError(f"data.num_workers must be >= -1 (-1: from the core count), got {n}")
  return pipeline_lib.default_num_workers() if n == -1 else n


def carved_validation(config) -> int | None:
  """k of a run whose held-out views are carved from a prepared captures dataset's training
  split (`--config.evals.split=validation` on a capture, which has no validation split of its
  own): every k-th training view of each capture by view id, k = round(1 /
  data.validation_fraction) (`records.validation_rows`), the views a regression of the same
  dataset validates on; `make_pipeline` trains on the other training views. None for every other
  run (no carve: each split as stored).

  Raises:
    DataError: the prepared dataset cannot be found.
  """
  d = config.data
  if config.evals.get("split", "test") != "validation" or not d.dir:
    return None
  if sources.is_procedural(d.source):
    return None  # a prepared family stores its own validation split
  path = storage.dataset_dir(d.dir, d.source, config=batches.prepared_config_name(d))
  if not records.capture_facts(storage.load_metadata(path)):
    return None
  return records.validation_every(d.validation_fraction)


def make_pipeline(
  config,
  split: str,
  *,
  num_devices: int,
  process_index: int = 0,
  process_count: int = 1,
  for_eval: bool = False,
):
  """Batches of `split` laid out for the pmapped step (see camrep.data.feed.pipeline).

  Data comes from `config.data.dir` (a prepared tfds directory) when set, its training batches
  decoded by `num_workers(config)` worker processes; otherwise from the procedural family, held
  in memory (`data.in_memory`) or rendered batch by batch. With `for_eval` the pipeline only
  serves `scene_views` (a one-scene, one-view layout). A captures dataset with
  `evals.split=validation` (`carved_validation`): "validation" is its training split's
  validation views, "train" the rest of it.
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
    every = carved_validation(config)
    if every is not None and split in ("train", "validation"):
      held = split == "validation"

      def select(index: storage.ViewIndex):
        val = records.validation_rows(index.scene, index.view, every)
        return val if held else ~val

      kw["select"], split = select, "train"
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


def make_pipelines(config):
  """(training batches of this process's shard for its local devices, held-out views of
  `evals.split`: "test", or "validation", which the plateau rule then reads instead of test)."""
  train_pipe = make_pipeline(
    config,
    "train",
    num_devices=jax.local_device_count(),
    process_index=jax.process_index(),
    process_count=jax.process_count(),
  )
  split = config.evals.get("split", "test")
  return train_pipe, make_pipeline(config, split, num_devices=1, for_eval=True)


def num_train_scenes(pipe) -> int:
  """Size of the per-scene tables: one past the largest training scene id."""
  return int(pipe.all_scene_ids.max()) + 1


def device_batches(config, pipe, start: int) -> Iterator[dict]:
  """The training batches from `start` on, copied to the devices `data.device_prefetch` steps
  ahead while the step runs; closing it stops the pipeline's worker processes, if any."""
  host = pipe.iterator(start_step=start, num_steps=max(config.total_steps - start, 0))
  n_ahead = int(config.data.get("device_prefetch", 2))
  try:
    it = (
      pipeline_lib.prefetch_to_device(host, n_ahead, devices=jax.local_devices())
      if n_ahead > 0
      else host
    )
    for b in it:
      yield {k: b[k] for k in ("image", "pose", "scene")}
  finally:
    if hasattr(host, "close"):
      host.close()

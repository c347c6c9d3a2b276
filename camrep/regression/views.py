"""The posed images a regression run learns from and is scored on (paper section 4.4), read
through the data layer view synthesis uses: every split is a `storage.ViewIndex` (ids and poses)
plus an image reader, training batches come from a `pipeline.BatchPipeline` over the training
views, and evaluation batches read their rows through the same reader.

Where the images come from:

  procedural  the setting's family (its procedural source, `config.data.family` overrides),
              rendered into memory; with `data.cache_dir`, prepared once into that directory as
              an ArrayRecord dataset (`storage.prepare`, one builder config per family config,
              reused by later runs) and decoded from it, the same pixels.
  real        `config.data.source` a real source and `config.data.dir` its prepared tfds
              directory, read as `camrep.main` reads it (dataset `data.source`, builder config
              `data.dataset_config`, else the preset's when the dataset has it, else its only
              one): decoded once into memory (resized to `data.image_size`), or with
              `data.stream` decoded batch by batch from the ArrayRecord files.

The paper's splits per real dataset (`real_split_plan`):

  seven_scenes  train = the TrainSplit sequences, test = the TestSplit sequences; validation the
                end of every scene's training trajectory (never a test sequence).
  srn_cars      train = cars_train, test = cars_train_test (held-out views of the same cars),
                test_scenes = cars_test (novel cars) when it was prepared.
  gibson        train / test = the areas' train / held-out test views.
  gqn           the scenes of the prepared train split (views 0..8), sorted by id: the last
                `data.test_scenes_fraction` are the held-out test scenes ("test_scenes"), the
                `validation_fraction` before them validation, the rest training; "test" = view
                9 of the training scenes.

The run's parts take what the config resolves to (`regression.config_schema.Resolved`): the data
source (`sources.Source`, whose setting is the run's), and the batch layout (`Batching`), never
the setting's name.

Training batches (`train_pipeline`): gqn draws `batch_size` scenes a step (epoch permutations of
the training scenes) with n_context + n_query distinct views each; the other settings draw
`batch_size` single views (epoch permutations of all training views: each view is its own group
of the pipeline). Both are a pure function of (seed, step), the draws the stage made before it
read through the pipeline (one process: NumPy's seed [seed, 1, step, 0] is [seed, 1, step]).
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import math
import os
import pathlib
from collections.abc import Callable, Iterator
from typing import Any

import grain
import numpy as np

from camrep import settings as settings_lib
from camrep.data import records, sources
from camrep.data.feed import pipeline, storage
from camrep.runtime.runconfig import ConfigError

ImageReader = Callable[[np.ndarray], np.ndarray]
"""Record positions int (...,) -> images uint8 (..., H, W, 3)."""


@dataclasses.dataclass(frozen=True)
class ViewSet:
  """N views: ids and poses in memory, images behind a reader (in memory or a prepared split).

  Attributes:
    index: the views' `storage.ViewIndex`; `index.record` addresses `read_images`.
    read_images: the reader of `index.record` positions.
  """

  index: storage.ViewIndex
  read_images: ImageReader

  @classmethod
  def in_memory(
    cls, images: np.ndarray, poses: np.ndarray, scenes: np.ndarray, views: np.ndarray
  ) -> ViewSet:
    """Views held as arrays: images (N, H, W, 3) uint8, poses (N, P), scenes and views (N,)."""
    n = len(images)
    index = storage.ViewIndex(
      record=np.arange(n, dtype=np.int64),
      index=np.arange(n, dtype=np.int64),
      scene=np.asarray(scenes, np.int64),
      view=np.asarray(views, np.int64),
      pose=np.asarray(poses, np.float32),
      pose_names=tuple(f"p{i}" for i in range(np.shape(poses)[-1])),
      image_shape=tuple(images.shape[1:3]),
    )
    return cls(index, images.__getitem__)

  @property
  def poses(self) -> np.ndarray:
    """(N, P) float32, in the setting's pose columns."""
    return self.index.pose

  @property
  def scenes(self) -> np.ndarray:
    """(N,) int64 scene ids."""
    return self.index.scene

  @property
  def views(self) -> np.ndarray:
    """(N,) int64 view ids within the scene."""
    return self.index.view

  @property
  def image_shape(self) -> tuple[int, int]:
    """(H, W) of the images `images` returns."""
    return tuple(self.index.image_shape)

  def images(self, rows) -> np.ndarray:
    """Images of `rows` (int (...,)): uint8 (..., H, W, 3)."""
    return self.read_images(self.index.record[np.asarray(rows)])

  def __len__(self) -> int:
    return len(self.index)

  def subset(self, rows: np.ndarray) -> ViewSet:
    """The views at `rows` (int indices or a boolean mask), read by the same reader."""
    return ViewSet(self.index.subset(rows), self.read_images)

  def scene_ids(self) -> np.ndarray:
    """Sorted distinct scene ids."""
    return np.unique(self.scenes)

  def scene_rows(self, scene: int) -> np.ndarray:
    """Rows of one scene, sorted by view id."""
    rows = np.flatnonzero(self.scenes == scene)
    return rows[np.argsort(self.views[rows], kind="stable")]


def _decoded(stored: storage.StoredSplit, size: int | None) -> ViewSet:
  """A prepared split decoded into memory (in the sidecar's order), resized to `size`."""
  index = stored.index
  images = [
    _resize(stored.read_images(index.record[start : start + 256]), size)
    for start in range(0, len(index), 256)
  ]
  images = np.concatenate(images)
  return ViewSet(
    dataclasses.replace(
      index, record=np.arange(len(index), dtype=np.int64), image_shape=tuple(images.shape[1:3])
    ),
    images.__getitem__,
  )


def _streamed(stored: storage.StoredSplit, size: int | None) -> ViewSet:
  """A prepared split whose images are decoded (and resized to `size`) when read."""

  def read(records: np.ndarray) -> np.ndarray:
    records = np.asarray(records)
    images = stored.read_images(records)
    flat = _resize(images.reshape(-1, *images.shape[-3:]), size)
    return flat.reshape(*records.shape, *flat.shape[1:])

  shape = (size, size) if size else tuple(stored.index.image_shape)
  return ViewSet(dataclasses.replace(stored.index, image_shape=shape), read)


def prepared_family(family, cache_dir: str) -> pathlib.Path:
  """The family's splits prepared as an ArrayRecord dataset under `cache_dir` (done once per
  family config, under a file lock, so concurrent runs prepare it once and reuse it)."""
  key = "c" + hashlib.sha256(repr(family.config).encode()).hexdigest()[:16]
  os.makedirs(cache_dir, exist_ok=True)
  with open(os.path.join(cache_dir, f".{family.name}_{key}.lock"), "w") as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)
    return storage.prepare(
      family, cache_dir, config=key, metadata={"family": repr(family.config)}, progress=False
    )


def load_split(family, split: str, *, cache_dir: str = "") -> ViewSet:
  """One split of a procedural family in memory: rendered, or with `cache_dir` decoded from the
  family prepared there (`prepared_family`)."""
  if cache_dir:
    return _decoded(storage.StoredSplit(prepared_family(family, cache_dir), split), None)
  index, images = storage.views_in_memory(family, split)
  return ViewSet(index, images.__getitem__)


def split_validation(
  setting: settings_lib.Setting, views: ViewSet, fraction: float, *, interleaved: bool = False
) -> tuple[ViewSet, ViewSet]:
  """(train, validation) parts of the training split (see the module docstring).

  A setting whose examples are scenes (`Setting.context_views`, gqn): the last
  ceil(fraction * n_scenes) scenes by id; the others: per scene the last
  ceil(fraction * n_views) views by view id (at least one view stays in training), or with
  `interleaved` (captures, whose test views are every 8th of a capture's views: validation must
  interpolate as test does, not extrapolate past the last views) every k-th view by view id from
  view k // 2 on, never the last (`records.validation_rows`, k = `records.validation_every`).
  """
  val = np.zeros(len(views), bool)
  ids = views.scene_ids()
  if setting.context_views:
    k = max(1, math.ceil(fraction * len(ids)))
    if k >= len(ids):
      raise ConfigError(f"validation would take all {len(ids)} training scenes")
    val = np.isin(views.scenes, ids[-k:])
  elif interleaved:
    val = records.validation_rows(views.scenes, views.views, records.validation_every(fraction))
  else:
    for s in ids:
      rows = views.scene_rows(s)
      k = min(max(1, math.ceil(fraction * len(rows))), len(rows) - 1)
      val[rows[len(rows) - k :]] = True
  return views.subset(~val), views.subset(val)


def interleaved_validation(meta: dict[str, Any]) -> bool:
  """Whether a prepared dataset's validation split interleaves (`split_validation`): a captures
  dataset (`records.capture_facts`), whose held-out test views lie between its training views."""
  return bool(records.capture_facts(meta))


@dataclasses.dataclass
class EvalSet:
  """Query views to regress and, for gqn, where each scene's context views come from.

  Attributes:
    queries: the views whose poses are regressed.
    context: gqn: the views holding each scene's first n_context (context) views; the queries
      exclude them when `context is queries`. None for the other settings.
  """

  queries: ViewSet
  context: ViewSet | None = None


@dataclasses.dataclass
class Data:
  """Everything a run reads: train views, evaluation sets, and facts for results.json."""

  train: ViewSet
  evals: dict[str, EvalSet]
  info: dict[str, Any]


def data_record(config, source: sources.Source) -> dict[str, Any]:
  """`fingerprint.data_record` of the data this regression reads from `source`: its prepared
  dataset (`open_dataset`) or its procedural family. Renders nothing.

  Raises:
    ConfigError: the dataset cannot be found, or the family refuses its parameters.
  """
  from camrep.data.errors import DataError
  from camrep.data.feed import fingerprint

  if not source.procedural:
    path, _ = open_dataset(config)
    return fingerprint.prepared_record(path)
  try:
    return fingerprint.procedural_record(config.data, source.name)
  except DataError as e:
    raise ConfigError(f"data.family: {e}") from None


def make_data(config, source: sources.Source) -> Data:
  """Train, validation and test sets of a config whose data come from `source` (see the module
  docstring)."""
  if not source.procedural:
    return make_real_data(config, source)
  setting, cache = source.setting, config.data.cache_dir
  family = sources.family_of_config(config.data, source.name)
  full_train = load_split(family, "train", cache_dir=cache)
  train, val = split_validation(setting, full_train, config.data.validation_fraction)
  gqn = setting.context_views
  evals = {"validation": EvalSet(val, val if gqn else None)}
  extra = [x.strip() for x in config.evals.extra_splits.split(",") if x.strip()]
  for name in [config.evals.test_split, *extra]:
    if name not in family.splits:
      raise ConfigError(f"family {family.name!r} has no split {name!r}; it has {family.splits}")
    views = load_split(family, name, cache_dir=cache)
    if gqn:
      # Held-out scenes bring their own context; held-out views use their scene's training views.
      evals[name] = EvalSet(views, views if name == "test_scenes" else full_train)
    else:
      evals[name] = EvalSet(views)
  if gqn:
    _check_gqn_counts(config.data, train, evals)
  info = {
    "family": family.name,
    "preset": config.data.preset,
    "family_overrides": config.data.family.to_dict(),
    "image_size": int(full_train.image_shape[0]),
    "train_views": len(train),
    "train_scenes": len(train.scene_ids()),
    "validation": (
      f"last {config.data.validation_fraction:g} of the training scenes"
      if gqn
      else f"last {config.data.validation_fraction:g} of each training scene's views"
    ),
    "test_split": config.evals.test_split,
    "num_examples": {},
  }
  if hasattr(family, "scene_name"):  # a family of named scenes (scene6dof)
    info["scene_names"] = {str(i): family.scene_name(i) for i in range(len(family.config.scenes))}
  return Data(train, evals, info)


# --------------------------------------------------------------------------------------------
# Real data prepared by camrep.data.prepare.


def open_dataset(config) -> tuple[str, dict[str, Any]]:
  """(dataset directory, its camrep_source.json) of the config's prepared real source.

  Raises:
    ConfigError: no data.dir, a missing directory or dataset, or a dataset of another source.
  """
  from camrep.data.errors import DataError

  d = config.data
  if not d.dir:
    raise ConfigError(
      f"data.source {d.source!r} is a real dataset: prepare it with `python -m "
      f"camrep.data.prepare --source {d.source} --input PATH --data_dir DIR` and pass "
      "--config.data.dir=DIR"
    )
  if not os.path.isdir(d.dir):
    raise ConfigError(f"data.dir {d.dir} does not exist (prepare it with camrep.data.prepare)")
  dataset_config = d.get("dataset_config") or None
  if dataset_config is None and d.preset != "default":
    if os.path.isdir(os.path.join(d.dir, d.source, d.preset)):
      dataset_config = d.preset  # as camrep.main reads it
  try:
    path = storage.dataset_dir(d.dir, d.source, config=dataset_config)
    meta = storage.load_metadata(path)
  except DataError as e:
    raise ConfigError(f"data.dir: {e} (data.source {d.source!r})") from None
  if meta.get("source") != d.source:
    raise ConfigError(f"{path} holds source {meta.get('source')!r}, not data.source {d.source!r}")
  return os.fspath(path), meta


def _resize(images: np.ndarray, size: int | None) -> np.ndarray:
  """(N, H, W, 3) uint8 -> (N, size, size, 3) (cv2 INTER_AREA); unchanged when size is None or
  already the images' size."""
  if not size or images.shape[1:3] == (size, size):
    return images
  import cv2

  interp = cv2.INTER_AREA if size < images.shape[1] else cv2.INTER_LINEAR
  return np.stack([cv2.resize(im, (size, size), interpolation=interp) for im in images])


def load_real_split(
  path: str, meta: dict[str, Any], split: str, *, image_size: int | None,
  max_bytes: float = float("inf"), stream: bool = False,
) -> ViewSet:  # fmt: skip
  """One split of a prepared dataset, decoded into memory in the sidecar's order; with `stream`,
  decoded when read (no memory limit).

  Raises:
    ConfigError: the split is absent or empty, or its decoded images exceed `max_bytes`.
  """
  from camrep.data.errors import DataError

  counts = meta.get("splits", {}).get(split)
  if counts is None:
    raise ConfigError(f"{path} has no split {split!r}; it has {sorted(meta.get('splits', {}))}")
  if counts.get("num_views", 0) == 0:
    raise ConfigError(f"{path}: split {split!r} holds no views")
  h, w = meta["image_shape"]
  size = int(image_size) if image_size else None
  n_bytes = counts["num_views"] * (size or h) * (size or w) * 3
  if n_bytes > max_bytes and not stream:
    raise ConfigError(
      f"{path} split {split!r}: {counts['num_views']} views need {n_bytes / 2**30:.1f} GiB "
      f"decoded, more than data.max_memory_gb={max_bytes / 2**30:g}: pass "
      "--config.data.stream=True (decode batches on the fly), lower data.image_size or raise "
      "the limit"
    )
  try:
    stored = storage.StoredSplit(pathlib.Path(path), split)
  except DataError as e:
    raise ConfigError(f"data.dir: {e}") from None
  return _streamed(stored, size) if stream else _decoded(stored, size)


def real_split_plan(setting: settings_lib.Setting, splits: Any) -> dict[str, str]:
  """Where each evaluation split of a real dataset comes from (see the module docstring).

  Args:
    setting: the paper's setting.
    splits: the prepared dataset's split names.

  Returns:
    {evaluation split: description}; only the splits this dataset can provide.
  """
  out = {}
  if setting.context_views:
    out["test_scenes"] = "held-out scenes carved from the prepared train split (last scenes by id)"
    if "test" in splits:
      out["test"] = "prepared test split (held-out view 9) of the training scenes"
    return out
  if "test" in splits:
    out["test"] = setting.real_test_description
  if "test_scenes" in splits:
    out["test_scenes"] = "prepared test_scenes split (novel scenes, e.g. SRN cars_test)"
  return out


def make_real_data(config, source: sources.Source) -> Data:
  """Train, validation and test sets from a prepared real dataset of `source` (see the module
  docstring).

  Raises:
    ConfigError: missing directory or dataset, a split the dataset lacks, an empty split, or too
      few views or scenes for the layout.
  """
  d, setting = config.data, source.setting
  path, meta = open_dataset(config)
  plan = real_split_plan(setting, meta.get("splits", {}))
  extra = [x.strip() for x in config.evals.extra_splits.split(",") if x.strip()]
  wanted = [config.evals.test_split, *extra]
  # Held-out novel scenes are scored whenever the dataset has them (SRN cars_test).
  gqn = setting.context_views
  wanted += [s for s in plan if s not in wanted and s == "test_scenes" and not gqn]
  for name in wanted:
    if name not in plan:
      raise ConfigError(
        f"{path} ({d.source}) cannot provide evaluation split {name!r}; it provides {sorted(plan)}"
      )
  load = dict(
    image_size=d.get("image_size"),
    max_bytes=float(d.get("max_memory_gb", 16.0)) * 2**30,
    stream=bool(d.get("stream", False)),
  )
  full_train = load_real_split(path, meta, "train", **load)
  heldout = None
  if gqn:
    ids = full_train.scene_ids()
    k = max(1, math.ceil(d.test_scenes_fraction * len(ids)))
    if k >= len(ids) - 1:
      raise ConfigError(
        f"{path}: {len(ids)} scenes are too few to hold out {k} test scenes and a validation part"
      )
    heldout = full_train.subset(np.isin(full_train.scenes, ids[-k:]))
    full_train = full_train.subset(~np.isin(full_train.scenes, ids[-k:]))
  interleaved = interleaved_validation(meta)
  train, val = split_validation(setting, full_train, d.validation_fraction, interleaved=interleaved)
  if gqn:  # how the validation views were chosen, in words (results.json)
    validation_rule = f"last {d.validation_fraction:g} of the remaining training scenes"
  elif interleaved:
    validation_rule = records.validation_description(d.validation_fraction)
  else:
    validation_rule = (
      f"last {d.validation_fraction:g} of each training scene's views "
      f"(by view id{setting.validation_note})"
    )
  if len(train) == 0 or len(val) == 0:
    raise ConfigError(f"{path}: the training split is too small to carve a validation part")
  evals = {"validation": EvalSet(val, val if gqn else None)}
  for name in wanted:
    if gqn and name == "test_scenes":
      evals[name] = EvalSet(heldout, heldout)
      continue
    views = load_real_split(path, meta, name, **load)
    if gqn:  # view 9 of the training scenes only; context from their training views
      views = views.subset(np.isin(views.scenes, train.scene_ids()))
      if len(views) == 0:
        raise ConfigError(f"{path}: split {name!r} has no view of a training scene")
      evals[name] = EvalSet(views, full_train)
    else:
      evals[name] = EvalSet(views)
  if gqn:
    _check_gqn_counts(d, train, evals)
  image_size = int(full_train.image_shape[0])
  info = {
    "source": d.source,
    "dataset": meta.get("name", d.source),
    "dir": os.path.abspath(d.dir),
    "dataset_path": path,
    "dataset_config": meta.get("config"),
    "prepared_from": meta.get("metadata", {}).get("input"),
    "prepared_splits": meta.get("splits", {}),
    "image_size": image_size,
    "train_split": "train" if not gqn else "train minus the held-out test scenes",
    "train_views": len(train),
    "train_scenes": len(train.scene_ids()),
    "validation": validation_rule,
    "test_split": config.evals.test_split,
    "streamed": bool(d.get("stream", False)),
    "splits": {name: plan.get(name, "") for name in wanted},
    "num_examples": {},
    "num_test_views": len(evals[config.evals.test_split].queries)
    - (_gqn_context_views(d.n_context, evals[config.evals.test_split]) if gqn else 0),
  }
  names = scene_names(meta)
  if names:
    info["scene_names"] = {str(i): n for i, n in enumerate(names)}
  info.update(records.naming(meta, info["splits"]))  # captures: names, true split descriptions
  return Data(train, evals, info)


def scene_names(meta: dict[str, Any]) -> list[str]:
  """Scene names of a prepared dataset of named scenes (7-Scenes) in scene-id order (the
  reader's `scenes`: the `--config.scenes=...` override, else its source's preset's, else every
  7-Scenes scene folder of the input), or [] when they cannot be told."""
  m = meta.get("metadata", {})
  scenes = m.get("overrides", {}).get("scenes")
  source = sources.SOURCES.get(meta.get("source"))
  if scenes is None and m.get("preset") and source is not None:
    scenes = source.presets.get(m["preset"], {}).get("scenes")
  root = m.get("input")
  if scenes is None and isinstance(root, str) and os.path.isdir(root):  # captures: a list
    scenes = sorted(
      x for x in os.listdir(root) if os.path.isfile(os.path.join(root, x, "TrainSplit.txt"))
    )
  return [str(x) for x in scenes or []]


def _gqn_context_views(n_context: int, e: EvalSet) -> int:
  """Context views excluded from a gqn evaluation set's queries (held-out scenes only)."""
  if e.context is not e.queries:
    return 0
  return sum(min(n_context, len(e.queries.scene_rows(s))) for s in e.queries.scene_ids())


def _check_gqn_counts(d, train: ViewSet, evals: dict[str, EvalSet]) -> None:
  """Raises ConfigError when a gqn scene has too few views for the context / query layout of
  the config's data section `d`."""
  for name, e in evals.items():
    ctx_counts = [len(e.context.scene_rows(s)) for s in e.queries.scene_ids()]
    need = d.n_context + (1 if e.context is e.queries else 0)
    if min(ctx_counts) < need:
      raise ConfigError(f"{name}: a scene has {min(ctx_counts)} views, {need} needed")
  if d.n_context + d.n_query > min(len(train.scene_rows(s)) for s in train.scene_ids()):
    raise ConfigError("a training scene has fewer than n_context + n_query views")


@dataclasses.dataclass(frozen=True)
class Batching:
  """How a run's views are batched (from its config: `Batching.of`).

  Attributes:
    scenes: whether an example is a scene with context views (`Setting.context_views`, gqn),
      else a single view.
    batch_size: training scenes (scenes) or views a step (`data.batch_size`).
    eval_batch_size: query views an evaluation batch (`evals.batch_size`).
    n_context, n_query: context and query views of a scene (scenes only; 0 otherwise).
    seed: the run's seed (the training batch order).
    num_threads: grain reader threads (0: read in the calling thread).
    prefetch: batches read ahead by the threads.
  """

  scenes: bool
  batch_size: int
  eval_batch_size: int
  n_context: int
  n_query: int
  seed: int
  num_threads: int = 0
  prefetch: int = 2

  @classmethod
  def of(cls, config, setting: settings_lib.Setting) -> Batching:
    """The batching of a regression config of `setting`."""
    d, scenes = config.data, setting.context_views
    return cls(
      scenes=scenes,
      batch_size=int(d.batch_size),
      eval_batch_size=int(config.evals.batch_size),
      n_context=int(d.n_context) if scenes else 0,  # the other settings' configs have none
      n_query=int(d.n_query) if scenes else 0,
      seed=int(config.seed),
      num_threads=int(d.get("num_threads", 0)),
      prefetch=int(d.get("prefetch", 2)),
    )


def train_pipeline(b: Batching, views: ViewSet) -> pipeline.BatchPipeline:
  """The `BatchPipeline` of the training views (see the module docstring): gqn one group per
  scene (its views in view-id order), the other settings one group per view.

  Raises:
    ConfigError: fewer training scenes (gqn) or views than a batch.
  """
  bs = b.batch_size
  if b.scenes:
    views = views.subset(np.lexsort((views.views, views.scenes)))
    index, groups, what = views.index, len(views.scene_ids()), "scenes"
  else:  # each view its own group: the batch's "scene" holds its row
    index = dataclasses.replace(views.index, scene=np.arange(len(views), dtype=np.int64))
    groups, what = len(views), "images"
  if groups // bs == 0:
    unit = "scenes" if b.scenes else "views"
    raise ConfigError(f"batch of {bs} {what} but only {groups} training {unit}")
  pcfg = pipeline.PipelineConfig(
    num_devices=1,
    scenes_per_device=bs,
    views_per_scene=b.n_context + b.n_query if b.scenes else 1,
    seed=b.seed,
    num_threads=b.num_threads,
    prefetch=b.prefetch,
  )
  return pipeline.BatchPipeline(index, views.read_images, pcfg, where="regression training views")


def learner_batch(b: Batching, views: ViewSet, batch: pipeline.Batch) -> dict[str, np.ndarray]:
  """A pipeline batch in the learner's layout.

  gqn: "context_image" (S, C, H, W, 3), "context_pose" (S, C, P), "image" (S, Q, H, W, 3),
  "pose" (S, Q, P), "scene" (S,), C = n_context, Q = n_query. Others: "image" (B, H, W, 3),
  "pose" (B, P), "scene" (B,).
  """
  image, pose = batch["image"][0], batch["pose"][0]
  if b.scenes:
    c = b.n_context
    return {
      "context_image": image[:, :c],
      "context_pose": pose[:, :c],
      "image": image[:, c:],
      "pose": pose[:, c:],
      "scene": batch["scene"][0],
    }
  rows = batch["scene"][0]
  return {"image": image[:, 0], "pose": pose[:, 0], "scene": views.scenes[rows].astype(np.int32)}


def train_batches(b: Batching, views: ViewSet) -> Iterator[dict[str, np.ndarray]]:
  """Endless training batches in the learner's layout (`learner_batch`), a pure function of
  (seed, step), read by `num_threads` grain reader threads, `prefetch` ahead."""
  pipe = train_pipeline(b, views)
  for batch in pipe.iterator():
    yield learner_batch(b, views, batch)


def _pad(x: np.ndarray, n: int) -> np.ndarray:
  """Pads axis 0 to n by repeating the last entry."""
  if len(x) == n:
    return x
  return np.concatenate([x, np.repeat(x[-1:], n - len(x), axis=0)])


def eval_plan(b: Batching, eval_set: EvalSet) -> list[dict[str, np.ndarray]]:
  """Rows and masks of fixed-shape evaluation batches (no image read): per batch "rows" (the
  query rows), "mask" (False for padding), gqn also "context_rows".

  gqn: per scene, context = the first n_context views (by id) of `eval_set.context`; queries =
  the scene's query views (minus the context views when both are the same set), padded to the
  largest count; `max(1, eval_batch_size // Q)` scenes per batch. Others: `eval_batch_size`
  views a batch.
  """
  q_views, bs = eval_set.queries, b.eval_batch_size
  if not b.scenes:
    plans = []
    for start in range(0, len(q_views), bs):
      rows = np.arange(start, min(start + bs, len(q_views)))
      plans.append({"rows": _pad(rows, bs), "mask": np.arange(bs) < len(rows)})
    return plans
  c = b.n_context
  same = eval_set.context is q_views
  ctx_rows, query_rows = [], []
  for s in q_views.scene_ids():
    ctx_rows.append(eval_set.context.scene_rows(s)[:c])
    qr = q_views.scene_rows(s)
    query_rows.append(qr[c:] if same else qr)
  n_q = max(len(r) for r in query_rows)
  per_batch = max(1, bs // n_q)
  plans = []
  for start in range(0, len(ctx_rows), per_batch):
    chunk = list(range(start, min(start + per_batch, len(ctx_rows))))
    qr = np.stack([_pad(query_rows[i], n_q) for i in chunk])
    qmask = np.stack([np.arange(n_q) < len(query_rows[i]) for i in chunk])
    cr = np.stack([ctx_rows[i] for i in chunk])
    qmask = np.concatenate([qmask, np.zeros((per_batch - len(chunk), n_q), bool)])
    plans.append({"rows": _pad(qr, per_batch), "context_rows": _pad(cr, per_batch), "mask": qmask})
  return plans


def eval_batches(b: Batching, eval_set: EvalSet) -> grain.IterDataset:
  """Fixed-shape evaluation batches with a "mask" (False for padding) and the queries' "view" ids,
  laid out by `eval_plan`, their images read when the batch is (so a streamed evaluation set is
  never held whole); re-iterable, read by `num_threads` grain threads.

  gqn: "context_image" (S, C, H, W, 3), "context_pose" (S, C, P), "image" (S, Q, H, W, 3),
  "pose" (S, Q, P), "scene" (S,), "view" (S, Q), "mask" (S, Q). Others: "image" (B, H, W, 3),
  "pose" (B, P), "scene" (B,), "view" (B,), "mask" (B,).
  """
  q_views, ctx, gqn = eval_set.queries, eval_set.context, b.scenes

  def read(plan: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    rows = plan["rows"]
    out = {}
    if gqn:
      out["context_image"] = ctx.images(plan["context_rows"])
      out["context_pose"] = ctx.poses[plan["context_rows"]]
    out["image"] = q_views.images(rows)
    out["pose"] = q_views.poses[rows]
    out["scene"] = q_views.scenes[rows[:, 0] if gqn else rows].astype(np.int32)
    out["view"] = q_views.views[rows].astype(np.int32)
    out["mask"] = plan["mask"]
    return out

  opts = grain.ReadOptions(
    num_threads=b.num_threads, prefetch_buffer_size=max(1, b.prefetch) if b.num_threads else 0
  )
  return grain.MapDataset.source(eval_plan(b, eval_set)).map(read).to_iter_dataset(opts)

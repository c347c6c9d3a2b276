"""The posed images a regression run learns from and is scored on (paper section 4.4): the
setting's procedural family rendered once into memory, or a real dataset prepared by
`python -m camrep.data.prepare` decoded once into memory (both cached on disk when asked), split
into train / validation / test, and batched for the learner.

Real data (`config.data.source` a real source, `config.data.dir` its prepared tfds directory,
read as `camrep.main` reads it: dataset `data.source`, builder config `data.dataset_config`, else
the preset's when the dataset has it, else its only one). The paper's splits per dataset
(`real_split_plan`):

  seven_scenes  train = the TrainSplit sequences, test = the TestSplit sequences; validation the
                end of every scene's training trajectory (never a test sequence).
  srn_cars      train = cars_train, test = cars_train_test (held-out views of the same cars),
                test_scenes = cars_test (novel cars) when it was prepared.
  gibson        train / test = the areas' train / held-out test views.
  gqn           the scenes of the prepared train split (views 0..8), sorted by id: the last
                `data.test_scenes_fraction` are the held-out test scenes ("test_scenes"), the
                `validation_fraction` before them validation, the rest training; "test" = view
                9 of the training scenes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import pathlib
from collections.abc import Callable, Iterator
from typing import Any

import jax
import numpy as np

from camrep.data import records
from camrep.runtime.runconfig import ConfigError

Array = jax.Array


@dataclasses.dataclass
class ViewSet:
  """Views held in memory, N of them.

  Attributes:
    images: (N, H, W, 3) uint8.
    poses: (N, P) float32, in the setting's pose columns.
    scenes: (N,) int64 scene ids.
    views: (N,) int64 view ids within the scene.
  """

  images: np.ndarray
  poses: np.ndarray
  scenes: np.ndarray
  views: np.ndarray

  def __len__(self) -> int:
    return len(self.scenes)

  def subset(self, rows: np.ndarray) -> ViewSet:
    """The views at `rows` (int indices or a boolean mask); streamed images stay streamed."""
    images = self.images
    images = images.subset(rows) if isinstance(images, StreamedImages) else images[rows]
    return ViewSet(images, self.poses[rows], self.scenes[rows], self.views[rows])

  def scene_ids(self) -> np.ndarray:
    """Sorted distinct scene ids."""
    return np.unique(self.scenes)

  def scene_rows(self, scene: int) -> np.ndarray:
    """Rows of one scene, sorted by view id."""
    rows = np.flatnonzero(self.scenes == scene)
    return rows[np.argsort(self.views[rows], kind="stable")]


class StreamedImages:
  """The images of a prepared split, decoded when indexed (`data.stream`): `x[rows]` reads the
  PNGs of those rows from the ArrayRecord files (any index shape (...,) -> (..., H, W, 3) uint8),
  resized to `size` when given. Stands in for `ViewSet.images` when a split does not fit in
  memory.

  Attributes:
    stored: the `camrep.data.storage.StoredSplit`.
    records: int64 (N,), record position of each row.
    size: output side, or None (as stored).
  """

  def __init__(self, stored, records: np.ndarray, size: int | None = None):
    self.stored, self.records, self.size = stored, np.asarray(records, np.int64), size

  @property
  def shape(self) -> tuple[int, int, int, int]:
    h, w = (self.size, self.size) if self.size else self.stored.index.image_shape
    return (len(self.records), h, w, 3)

  def __len__(self) -> int:
    return len(self.records)

  def subset(self, rows: np.ndarray) -> StreamedImages:
    """The rows `rows` (int indices or a boolean mask), still streamed."""
    return StreamedImages(self.stored, self.records[rows], self.size)

  def __getitem__(self, rows) -> np.ndarray:
    rows = np.asarray(rows)
    images = self.stored.read_images(self.records[rows])
    flat = _resize(images.reshape(-1, *images.shape[-3:]), self.size)
    return flat.reshape(*rows.shape, *flat.shape[1:])


def _family_key(family, split: str) -> str:
  text = f"{family.name}|{split}|{family.config!r}"
  return hashlib.sha256(text.encode()).hexdigest()[:16]


def load_split(family, split: str, *, cache_dir: str = "") -> ViewSet:
  """Renders (or reads from `cache_dir`) one split of a procedural family.

  The cache file `<cache_dir>/<family>_<split>_<hash of the family config>.npz` is written
  atomically, so concurrent or interrupted runs never read a partial file.
  """
  from camrep.data import pipeline

  path = ""
  if cache_dir:
    path = os.path.join(cache_dir, f"{family.name}_{split}_{_family_key(family, split)}.npz")
    if os.path.exists(path):
      with np.load(path) as z:
        return ViewSet(z["images"], z["poses"], z["scenes"], z["views"])
  index, images = pipeline.views_in_memory(family, split)
  views = ViewSet(images, index.pose.astype(np.float32), index.scene, index.view)
  if path:
    os.makedirs(cache_dir, exist_ok=True)
    tmp = f"{path}.{os.getpid()}.tmp.npz"
    np.savez(tmp, **dataclasses.asdict(views))
    os.replace(tmp, path)
  return views


def split_validation(setting: str, views: ViewSet, fraction: float) -> tuple[ViewSet, ViewSet]:
  """(train, validation) parts of the training split (see the module docstring).

  gqn: the last ceil(fraction * n_scenes) scenes by id; the others: per scene the last
  ceil(fraction * n_views) views by view id (at least one view stays in training).
  """
  val = np.zeros(len(views), bool)
  ids = views.scene_ids()
  if setting == "gqn":
    k = max(1, math.ceil(fraction * len(ids)))
    if k >= len(ids):
      raise ConfigError(f"validation would take all {len(ids)} training scenes")
    val = np.isin(views.scenes, ids[-k:])
  else:
    for s in ids:
      rows = views.scene_rows(s)
      k = min(max(1, math.ceil(fraction * len(rows))), len(rows) - 1)
      val[rows[len(rows) - k :]] = True
  return views.subset(~val), views.subset(val)


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


def make_family(config):
  """The config's procedural family (`camrep.data.procedural.make_family`)."""
  from camrep.data import procedural

  overrides = config.data.family.to_dict()
  overrides = {k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}
  return procedural.make_family(
    records.SOURCE_OF_SETTING[config.setting], preset=config.data.preset, **overrides
  )


def is_real(config) -> bool:
  """Whether the config reads a prepared real dataset (data.source a real source)."""
  source = config.data.get("source", "")
  return bool(source) and source not in records.PROCEDURAL


def make_data(config) -> Data:
  """Train, validation and test sets of a resolved config (see the module docstring)."""
  if is_real(config):
    return make_real_data(config)
  setting, cache = config.setting, config.data.cache_dir
  family = make_family(config)
  full_train = load_split(family, "train", cache_dir=cache)
  train, val = split_validation(setting, full_train, config.data.validation_fraction)
  gqn = setting == "gqn"
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
    _check_gqn_counts(config, train, evals)
  info = {
    "family": family.name,
    "preset": config.data.preset,
    "family_overrides": config.data.family.to_dict(),
    "image_size": int(full_train.images.shape[1]),
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
  if family.name == "scene6dof":
    info["scene_names"] = {str(i): family.scene_name(i) for i in range(len(family.config.scenes))}
  return Data(train, evals, info)


# --------------------------------------------------------------------------------------------
# Real data prepared by camrep.data.prepare.


def open_dataset(config) -> tuple[str, dict[str, Any]]:
  """(dataset directory, its camrep_source.json) of the config's prepared real source.

  Raises:
    ConfigError: no data.dir, a missing directory or dataset, or a dataset of another source.
  """
  from camrep.data import storage
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
  path: str, meta: dict[str, Any], split: str, *, image_size: int | None, cache_dir: str = "",
  max_bytes: float = float("inf"), stream: bool = False,
) -> ViewSet:  # fmt: skip
  """Decodes (or reads from `cache_dir`) one split of a prepared dataset, in the sidecar's order;
  with `stream`, the images stay on disk (`StreamedImages`, no cache, no memory limit).

  The cache file `<cache_dir>/<source>_<split>_<hash>.npz` is keyed by the dataset directory, its
  camrep_source.json (a re-prepared dataset gets a new key), the split and the image size.

  Raises:
    ConfigError: the split is absent or empty, or its decoded images exceed `max_bytes`.
  """
  from camrep.data import storage
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
  key = hashlib.sha256(
    f"{os.path.abspath(path)}|{json_dumps(meta)}|{split}|{size}".encode()
  ).hexdigest()[:16]
  cache = ""
  if cache_dir and not stream:
    cache = os.path.join(cache_dir, f"{meta['source']}_{split}_{key}.npz")
  if cache and os.path.exists(cache):
    with np.load(cache) as z:
      return ViewSet(z["images"], z["poses"], z["scenes"], z["views"])
  try:
    stored = storage.StoredSplit(pathlib.Path(path), split)
  except DataError as e:
    raise ConfigError(f"data.dir: {e}") from None
  index = stored.index
  if stream:
    return ViewSet(
      StreamedImages(stored, index.record, size), index.pose.astype(np.float32), index.scene,
      index.view,
    )  # fmt: skip
  images = []
  for start in range(0, len(index), 256):
    images.append(_resize(stored.read_images(index.record[start : start + 256]), size))
  views = ViewSet(np.concatenate(images), index.pose.astype(np.float32), index.scene, index.view)
  if cache:
    os.makedirs(cache_dir, exist_ok=True)
    tmp = f"{cache}.{os.getpid()}.tmp.npz"
    np.savez(tmp, **dataclasses.asdict(views))
    os.replace(tmp, cache)
  return views


def json_dumps(x: Any) -> str:
  """Canonical JSON text of `x` (sorted keys), for cache keys."""
  import json

  return json.dumps(x, sort_keys=True, default=str)


def real_split_plan(setting: str, splits: Any) -> dict[str, str]:
  """Where each evaluation split of a real dataset comes from (see the module docstring).

  Args:
    setting: the paper's setting.
    splits: the prepared dataset's split names.

  Returns:
    {evaluation split: description}; only the splits this dataset can provide.
  """
  out = {}
  if setting == "gqn":
    out["test_scenes"] = "held-out scenes carved from the prepared train split (last scenes by id)"
    if "test" in splits:
      out["test"] = "prepared test split (held-out view 9) of the training scenes"
    return out
  if "test" in splits:
    out["test"] = {
      "seven_scenes": "prepared test split (TestSplit sequences)",
      "car": "prepared test split (cars_train_test: held-out views of the training cars)",
      "gibson": "prepared test split (held-out views of the training areas)",
    }[setting]
  if "test_scenes" in splits:
    out["test_scenes"] = "prepared test_scenes split (novel scenes, e.g. SRN cars_test)"
  return out


def make_real_data(config) -> Data:
  """Train, validation and test sets from a prepared real dataset (see the module docstring).

  Raises:
    ConfigError: missing directory or dataset, a split the dataset lacks, an empty split, or too
      few views or scenes for the layout.
  """
  d, setting = config.data, config.setting
  path, meta = open_dataset(config)
  plan = real_split_plan(setting, meta.get("splits", {}))
  extra = [x.strip() for x in config.evals.extra_splits.split(",") if x.strip()]
  wanted = [config.evals.test_split, *extra]
  # Held-out novel scenes are scored whenever the dataset has them (SRN cars_test).
  wanted += [s for s in plan if s not in wanted and s == "test_scenes" and setting != "gqn"]
  for name in wanted:
    if name not in plan:
      raise ConfigError(
        f"{path} ({d.source}) cannot provide evaluation split {name!r}; it provides {sorted(plan)}"
      )
  load = dict(
    image_size=d.get("image_size"),
    cache_dir=d.cache_dir,
    max_bytes=float(d.get("max_memory_gb", 16.0)) * 2**30,
    stream=bool(d.get("stream", False)),
  )
  full_train = load_real_split(path, meta, "train", **load)
  gqn = setting == "gqn"
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
  train, val = split_validation(setting, full_train, d.validation_fraction)
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
    _check_gqn_counts(config, train, evals)
  image_size = int(full_train.images.shape[1])
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
    "validation": (
      f"last {d.validation_fraction:g} of the remaining training scenes"
      if gqn
      else f"last {d.validation_fraction:g} of each training scene's views (by view id"
      + ("; the end of the TrainSplit trajectory)" if setting == "seven_scenes" else ")")
    ),
    "test_split": config.evals.test_split,
    "streamed": bool(d.get("stream", False)),
    "splits": {name: plan.get(name, "") for name in wanted},
    "num_examples": {},
    "num_test_views": len(evals[config.evals.test_split].queries)
    - (_gqn_context_views(config, evals[config.evals.test_split]) if gqn else 0),
  }
  if setting == "seven_scenes":
    names = seven_scenes_names(meta)
    if names:
      info["scene_names"] = {str(i): n for i, n in enumerate(names)}
  return Data(train, evals, info)


def seven_scenes_names(meta: dict[str, Any]) -> list[str]:
  """Scene names of a prepared 7-Scenes dataset in scene-id order (the reader's `scenes`: the
  `--set scenes=...` override, else the preset's, else every scene folder of the input), or []
  when they cannot be told."""
  from camrep.data import prepare

  m = meta.get("metadata", {})
  scenes = m.get("overrides", {}).get("scenes")
  if scenes is None and m.get("preset"):
    scenes = prepare.PRESETS.get("seven_scenes", {}).get(m["preset"], {}).get("scenes")
  root = m.get("input")
  if scenes is None and isinstance(root, str) and os.path.isdir(root):  # captures: a list
    scenes = sorted(
      x for x in os.listdir(root) if os.path.isfile(os.path.join(root, x, "TrainSplit.txt"))
    )
  return [str(x) for x in scenes or []]


def _gqn_context_views(config, e: EvalSet) -> int:
  """Context views excluded from a gqn evaluation set's queries (held-out scenes only)."""
  if e.context is not e.queries:
    return 0
  return sum(
    min(config.data.n_context, len(e.queries.scene_rows(s))) for s in e.queries.scene_ids()
  )


def _check_gqn_counts(config, train: ViewSet, evals: dict[str, EvalSet]) -> None:
  """Raises ConfigError when a gqn scene has too few views for the context / query layout."""
  for name, e in evals.items():
    ctx_counts = [len(e.context.scene_rows(s)) for s in e.queries.scene_ids()]
    need = config.data.n_context + (1 if e.context is e.queries else 0)
    if min(ctx_counts) < need:
      raise ConfigError(f"{name}: a scene has {min(ctx_counts)} views, {need} needed")
  if config.data.n_context + config.data.n_query > min(
    len(train.scene_rows(s)) for s in train.scene_ids()
  ):
    raise ConfigError("a training scene has fewer than n_context + n_query views")


def train_batch_fn(config, views: ViewSet) -> Callable[[int], dict[str, np.ndarray]]:
  """The training batch at a step, a pure function of (seed, step) (`train_batches`' layout).

  Raises:
    ConfigError: fewer training scenes (gqn) or views than a batch.
  """
  bs, seed = config.data.batch_size, config.seed
  epochs: dict[int, np.ndarray] = {}

  def order(epoch: int, n: int) -> np.ndarray:
    perm = epochs.get(epoch)
    if perm is None:
      if len(epochs) >= 4:  # reader threads only ever need the current epoch(s)
        epochs.clear()
      perm = epochs[epoch] = np.random.default_rng([seed, 0, epoch]).permutation(n)
    return perm

  if config.setting == "gqn":
    ids = views.scene_ids()
    rows = [views.scene_rows(s) for s in ids]
    c, q = config.data.n_context, config.data.n_query
    per_epoch = len(ids) // bs
    if per_epoch == 0:
      raise ConfigError(f"batch of {bs} scenes but only {len(ids)} training scenes")

    def gqn_batch(step: int) -> dict[str, np.ndarray]:
      epoch, pos = divmod(step, per_epoch)
      chosen = order(epoch, len(ids))[pos * bs : (pos + 1) * bs]
      rng = np.random.default_rng([seed, 1, step])
      picked = np.stack([rng.choice(rows[i], c + q, replace=False) for i in chosen])
      return {
        "context_image": views.images[picked[:, :c]],
        "context_pose": views.poses[picked[:, :c]],
        "image": views.images[picked[:, c:]],
        "pose": views.poses[picked[:, c:]],
        "scene": ids[chosen].astype(np.int32),
      }

    return gqn_batch
  n = len(views)
  per_epoch = n // bs
  if per_epoch == 0:
    raise ConfigError(f"batch of {bs} images but only {n} training views")

  def batch(step: int) -> dict[str, np.ndarray]:
    epoch, pos = divmod(step, per_epoch)
    rows = order(epoch, n)[pos * bs : (pos + 1) * bs]
    return {
      "image": views.images[rows],
      "pose": views.poses[rows],
      "scene": views.scenes[rows].astype(np.int32),
    }

  return batch


def train_batches(config, views: ViewSet) -> Iterator[dict[str, np.ndarray]]:
  """Endless training batches in `learner`'s layout, a pure function of (seed, step).

  gqn: per step `batch_size` distinct scenes (epoch permutations), each with n_context + n_query
  distinct random views, the first n_context the context: "context_image" (S, V, H, W, 3),
  "context_pose" (S, V, P), "image" (S, Q, H, W, 3), "pose" (S, Q, P), "scene" (S,). Others:
  `batch_size` distinct views (epoch permutations of all training views): "image" (B, H, W, 3),
  "pose" (B, P), "scene" (B,).

  Streamed images (`StreamedImages`, data.stream) are decoded by grain reader threads
  (`data.num_threads`, `data.prefetch` batches ahead), as the view-synthesis pipeline does.
  """
  fn = train_batch_fn(config, views)
  threads = int(config.data.get("num_threads", 0))
  if isinstance(views.images, StreamedImages) and threads > 0:
    import grain

    ds = grain.MapDataset.range(0, 2**62).map(fn)
    opts = grain.ReadOptions(
      num_threads=threads, prefetch_buffer_size=max(1, int(config.data.get("prefetch", 2)))
    )
    yield from ds.to_iter_dataset(opts)
    return
  step = 0
  while True:
    yield fn(step)
    step += 1


def _pad(x: np.ndarray, n: int) -> np.ndarray:
  """Pads axis 0 to n by repeating the last entry."""
  if len(x) == n:
    return x
  return np.concatenate([x, np.repeat(x[-1:], n - len(x), axis=0)])


def eval_batches(config, eval_set: EvalSet) -> list[dict[str, np.ndarray]] | StreamedBatches:
  """Fixed-shape evaluation batches with a "mask" (False for padding) and the queries' "view" ids
  (a list; `StreamedBatches`, decoded batch by batch, when the images are streamed).

  gqn: per scene, context = the first n_context views (by id) of `eval_set.context`; queries =
  the scene's query views (minus the context views when both are the same set), padded to the
  largest count; `max(1, batch_size // Q)` scenes per batch. Others: `batch_size` views a batch.
  """
  q_views, bs = eval_set.queries, config.evals.batch_size
  out = []
  if config.setting != "gqn":
    for start in range(0, len(q_views), bs):
      rows = np.arange(start, min(start + bs, len(q_views)))
      mask = np.arange(bs) < len(rows)
      rows = _pad(rows, bs)
      out.append(
        {
          "image": _take(q_views.images, rows),
          "pose": q_views.poses[rows],
          "scene": q_views.scenes[rows].astype(np.int32),
          "view": q_views.views[rows].astype(np.int32),
          "mask": mask,
        }
      )
    return _batches(out)
  c = config.data.n_context
  same = eval_set.context is q_views
  ctx_rows, query_rows = [], []
  for s in q_views.scene_ids():
    ctx_all = eval_set.context.scene_rows(s)
    ctx_rows.append(ctx_all[:c])
    qr = q_views.scene_rows(s)
    query_rows.append(qr[c:] if same else qr)
  n_q = max(len(r) for r in query_rows)
  per_batch = max(1, bs // n_q)
  for start in range(0, len(ctx_rows), per_batch):
    chunk = list(range(start, min(start + per_batch, len(ctx_rows))))
    qr = np.stack([_pad(query_rows[i], n_q) for i in chunk])
    qmask = np.stack([np.arange(n_q) < len(query_rows[i]) for i in chunk])
    cr = np.stack([ctx_rows[i] for i in chunk])
    n_real = len(chunk)
    qr, cr = _pad(qr, per_batch), _pad(cr, per_batch)
    qmask = np.concatenate([qmask, np.zeros((per_batch - n_real, n_q), bool)])
    ctx = eval_set.context
    out.append(
      {
        "context_image": _take(ctx.images, cr),
        "context_pose": ctx.poses[cr],
        "image": _take(q_views.images, qr),
        "pose": q_views.poses[qr],
        "scene": q_views.scenes[qr[:, 0]].astype(np.int32),
        "view": q_views.views[qr].astype(np.int32),
        "mask": qmask,
      }
    )
  return _batches(out)


@dataclasses.dataclass(frozen=True)
class _Pending:
  """Rows of streamed images, decoded when an evaluation batch is used."""

  images: StreamedImages
  rows: np.ndarray


def _take(images, rows: np.ndarray):
  """images[rows] now (in memory), or a `_Pending` read (streamed)."""
  if isinstance(images, StreamedImages):
    return _Pending(images, rows)
  return images[rows]


class StreamedBatches:
  """Evaluation batches whose streamed images are decoded batch by batch, each time the batches
  are iterated (so an evaluation set larger than memory is never held whole)."""

  def __init__(self, batches: list[dict[str, Any]]):
    self._batches = batches

  def __len__(self) -> int:
    return len(self._batches)

  def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
    for b in self._batches:
      yield {k: v.images[v.rows] if isinstance(v, _Pending) else v for k, v in b.items()}


def _batches(out: list[dict[str, Any]]):
  """The batch list itself (in memory), or `StreamedBatches` when some images are streamed."""
  if any(isinstance(v, _Pending) for b in out for v in b.values()):
    return StreamedBatches(out)
  return out

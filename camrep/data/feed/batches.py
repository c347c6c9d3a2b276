"""The batch a pipeline hands to a train step, and its shape template built without reading data.

`ViewBatch` is what `camrep.data.feed.pipeline.BatchPipeline.batch` returns: posed views laid out
for a pmapped step, D = devices, S = scenes per device, V = views per scene, P = pose size. It is a
`flax.struct` pytree (so `jax.tree.map`, `jax.eval_shape` and `device_put` take it whole) that
also reads like the dict it replaces (`batch["image"]`, `batch.keys()`).

`dummy_batch(config)` gives the same layout filled with zeros from the config alone: a restore
builds its state template from it (`jax.eval_shape`), so restoring a run never renders or decodes
a view. `describe(data_config, split)` answers the other question a restore asks (which scene
ids a split holds, hence the size of the per-scene tables) from the family's config or the
prepared dataset's sidecar index, again without an image.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any

import flax.struct
import numpy as np

from camrep.data import sources
from camrep.data.feed import storage

FIELDS = ("image", "pose", "scene", "view")


@flax.struct.dataclass
class ViewBatch:
  """Posed views of one step, for a pmapped step.

  Attributes:
    image: uint8 (D, S, V, H, W, 3) RGB (a device `jax.Array` when rendered on an accelerator).
    pose: float32 (D, S, V, P), the source's pose columns (`sources.get(name).pose_names`).
    scene: int32 (D, S), scene ids.
    view: int32 (D, S, V), view ids within their scene.
  """

  image: Any
  pose: Any
  scene: Any
  view: Any

  def __getitem__(self, key: str) -> Any:
    if key not in FIELDS:
      raise KeyError(key)
    return getattr(self, key)

  def keys(self) -> tuple[str, ...]:
    return FIELDS

  def __iter__(self) -> Iterator[str]:
    return iter(FIELDS)

  def __len__(self) -> int:
    return len(FIELDS)


@dataclasses.dataclass(frozen=True)
class SplitInfo:
  """What a split holds, known without reading an image.

  Attributes:
    scene_ids: int64 (n,), the split's scene ids, sorted.
    image_shape: (H, W).
    pose_names: the P pose columns.
  """

  scene_ids: np.ndarray
  image_shape: tuple[int, int]
  pose_names: tuple[str, ...]


def prepared_config_name(data_config) -> str | None:
  """The builder config a run reads from `data.dir`: its preset unless that is "default"."""
  preset = data_config.get("preset", "default")
  return preset if preset != "default" else None


def describe(data_config, split: str = "train") -> SplitInfo:
  """The scene ids, image shape and pose columns of a run's split (`config.data`): from the
  prepared dataset's sidecar index when `data.dir` is set, else from the procedural family's
  config. Reads no image and renders nothing.

  Raises:
    DataError: unknown source, missing dataset or split.
  """
  d = data_config
  if d.get("dir", ""):
    path = storage.dataset_dir(d.dir, d.source, config=prepared_config_name(d))
    index = storage.ViewIndex.from_npz(path / f"views_index_{split}.npz")
    return SplitInfo(np.unique(index.scene), tuple(index.image_shape), tuple(index.pose_names))
  family = sources.family_of_config(d)
  ids = np.asarray(family.scene_ids(split), np.int64)
  return SplitInfo(ids, (family.image_size, family.image_size), tuple(family.pose_names))


def dummy_batch(config, *, num_devices: int = 1, info: SplitInfo | None = None) -> ViewBatch:
  """Zeros in the layout of a view-synthesis run's training batch, from the config alone.

  Args:
    config: the run's config (`data.scenes_per_device`, `data.views_per_scene`, the source).
    num_devices: D, the leading (pmap) axis.
    info: the training split's `describe` (computed when None).

  Returns:
    A `ViewBatch`: image uint8 (D, S, V, H, W, 3), pose float32 (D, S, V, P), scene int32
    (D, S), view int32 (D, S, V); the shapes and dtypes of `pipeline.batch(k)`.
  """
  info = describe(config.data, "train") if info is None else info
  lead = (num_devices, config.data.scenes_per_device, config.data.views_per_scene)
  return ViewBatch(
    image=np.zeros((*lead, *info.image_shape, 3), np.uint8),
    pose=np.zeros((*lead, len(info.pose_names)), np.float32),
    scene=np.zeros(lead[:2], np.int32),
    view=np.zeros(lead, np.int32),
  )

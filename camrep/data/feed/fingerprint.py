"""What identifies a run's data, computed without rendering or decoding a view: the record a
workdir keeps so that a resume (or a regression on a learned pose system) can tell the same data
from other data even when the config leaves it implicit (library defaults).

  data_record(config.data)   procedural: {"kind": "procedural", "source", "family": the family's
                             resolved parameters (defaults, then the preset, then
                             `data.family`), "renderer": render.RENDERER_VERSION,
                             "fingerprint", "world"};
                             prepared (`data.dir`): {"kind": "prepared", "source", "dataset"
                             (its directory when recorded; a move keeps the fingerprint),
                             "identity": its camrep_source.json less the preparation time and
                             the raw input's path, its inputs' per-frame stamps replaced by
                             their digest, "fingerprint"}.

Fingerprints are "sha256:<hex>" of canonical JSON:
  procedural "fingerprint": the family name, every resolved parameter, the renderer version:
             another value of any of them gives other images or poses.
  procedural "world":       the same without the extent fields (`EXTENT_FIELDS`: how many scenes
             and views, which 7-Scenes trajectories, the image resolution, the renderer's batch):
             the same generator of rooms (cars, areas) at another size or resolution, which is
             what a regression may read from a pose system learned by view synthesis (the
             regression configs use more scenes than the synthesis ones).
  prepared "fingerprint" (and "world"): the identity, the content of each split's sidecar index
             (views_index_SPLIT.npz: every view's scene, view id and pose; hashed array by array,
             not as a file, whose zip timestamps differ between two preparations) and the byte
             size of each record shard (PNG-encoded images: another image almost surely changes
             a shard's size). Images are not hashed: that would read the whole dataset.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pathlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from camrep.data import sources
from camrep.data.feed import batches, storage
from camrep.data.procedural import render
from camrep.data.records import digest

# Family parameters that choose how much of a generator's data there is (and at what
# resolution), not what a scene or its camera poses are: left out of the "world" fingerprint.
EXTENT_FIELDS = frozenset(
  {
    "num_train_scenes",
    "num_test_scenes",
    "num_scenes",
    "train_views",
    "test_views",
    "train_stride",
    "test_stride",
    "scenes",
    "image_size",
    "supersample",
    "batch_size",
  }
)


def plain(value: Any) -> Any:
  """JSON values (tuples become lists), as a record read back from disk holds them."""
  return json.loads(json.dumps(value, default=str))


def family_params(data_config, name: str | None = None) -> dict[str, Any]:
  """The procedural family's resolved parameters (`sources.family_of_config`; builds the family
  object, which renders nothing).

  Raises:
    DataError: not a procedural source, or settings the family does not accept.
  """
  family = sources.family_of_config(data_config, name)
  return plain(dataclasses.asdict(family.config))


def procedural_record(data_config, name: str | None = None) -> dict[str, Any]:
  """The record of a procedural source (see the module docstring)."""
  name = name or data_config.source
  params = family_params(data_config, name)
  world = {k: v for k, v in params.items() if k not in EXTENT_FIELDS}
  renderer = int(render.RENDERER_VERSION)
  return {
    "kind": "procedural",
    "source": name,
    "family": params,
    "renderer": renderer,
    "fingerprint": digest({"source": name, "family": params, "renderer": renderer}),
    "world": digest({"source": name, "family": world, "renderer": renderer}),
  }


def _array_digest(path: pathlib.Path) -> str:
  h = hashlib.sha256()
  with np.load(path, allow_pickle=False) as z:
    for key in sorted(z.files):
      a = np.ascontiguousarray(z[key])
      h.update(f"{key}:{a.dtype.str}:{a.shape};".encode())
      h.update(a.tobytes())
  return "sha256:" + h.hexdigest()


def prepared_record(path: str | os.PathLike) -> dict[str, Any]:
  """The record of a prepared dataset directory (`storage.dataset_dir`; see the module
  docstring). Reads its metadata, its sidecar indexes and the sizes of its record files.

  Raises:
    DataError: no camrep_source.json there.
  """
  path = pathlib.Path(path)
  meta = storage.load_metadata(path)
  identity = {k: v for k, v in meta.items() if k != "prepare_seconds"}
  if isinstance(identity.get("inputs"), Mapping):  # per-frame stamps: their digest stands for them
    identity["inputs"] = identity["inputs"].get("digest")
  settings = identity.get("metadata")
  if isinstance(settings, Mapping):  # where the raw data was read from is not what it is
    identity["metadata"] = {k: v for k, v in settings.items() if k != "input"}
  sidecars = {
    f.name: _array_digest(f) for f in sorted(path.glob("views_index_*.npz")) if f.is_file()
  }
  shards = {f.name: f.stat().st_size for f in sorted(path.glob("*.array_record-*")) if f.is_file()}
  identity = plain(identity)
  fingerprint = digest({"identity": identity, "sidecars": sidecars, "shards": shards})
  return {
    "kind": "prepared",
    "source": meta.get("source"),
    "dataset": os.fspath(path.resolve()),
    "identity": identity,
    "fingerprint": fingerprint,
    "world": fingerprint,
  }


def data_record(data_config, name: str | None = None) -> dict[str, Any]:
  """The record of a run's `config.data`: its prepared dataset (`data.dir`, the builder config
  of `data.preset`) or its procedural family.

  Raises:
    DataError: the prepared dataset or the family cannot be found or built.
  """
  if data_config.get("dir", ""):
    path = storage.dataset_dir(
      data_config.dir, data_config.source, config=batches.prepared_config_name(data_config)
    )
    return prepared_record(path)
  return procedural_record(data_config, name)

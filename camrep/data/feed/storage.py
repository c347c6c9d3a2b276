"""TFDS storage for any view-record source: build, sidecar index, read back (no TensorFlow).

Every camrep source (procedural family or real-format reader, see `ViewSource`) is stored the
same way: a `tfds.core.GeneratorBasedBuilder` with `file_format="array_record"`, one tfds split
per source split, read back with `as_data_source` (tf.data, `tfds.load` and the tfrecord format
all need TensorFlow, which we do not install; see the stack notes, section 1).

How the builder is parameterised by the source: tfds takes a builder's dataset name from a class
attribute, so `builder_class(name, ...)` creates one small subclass per dataset name with
`types.new_class(..., skip_registration=True)` (no clash in the global tfds registry when the
same name is built twice, e.g. in tests), and the source *instance* is handed to the
constructor. An optional `config` name (e.g. the preset, "small") becomes a
`tfds.core.BuilderConfig`, so one name can hold several variants side by side. Reading back
never needs the class: `tfds.builder_from_directory` rebuilds the builder from
`dataset_info.json`.

On-disk layout (`DATA_DIR/NAME[/CONFIG]/VERSION/`):

  NAME-SPLIT.array_record-000NN-of-000MM   records, features:
      image  PNG (H, W, 3) uint8 RGB (encoded by cv2 from BGR, so tfds/cv2 decode it back
             bit-exactly)
      pose   float32 (P,)           scene  int64         view  int64
      index  int64, the view's position in the source's `iter_views(split)` order (tfds
             shuffles records by hashed key, so record i is *not* view i)
  views_index_SPLIT.npz                  the sidecar: per view (sorted by `index`) its
      record position, index, scene, view and pose, so the pipeline can group views by scene
      and sample them without decoding a single PNG
  camrep_source.json                     name, pose names, image shape, per-split counts,
                                         whatever metadata the caller passed (overrides, input)
                                         and, as "source_info", the source's `describe()` when
                                         it has one (captures: normalisation, residuals, split
                                         rules); as "inputs", the source's `inputs()` when it
                                         has one (captures: a fingerprint of the files read)

One writer at a time per dataset: `prepare` holds `DATA_DIR/NAME[/CONFIG]/.camrep.lock` while it
writes, and a second writer is refused by name. A captures dataset in which a seen capture has no
held-out view is refused when its "test" split is opened (`check_held_out`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import functools
import json
import os
import pathlib
import re
import shutil
import sys
import tempfile
import time
import types
from collections.abc import Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import cv2
import numpy as np
import tqdm

from camrep.data.errors import DataError
from camrep.runtime import writers

if TYPE_CHECKING:
  import tensorflow_datasets as tfds

DEFAULT_VERSION = "1.0.0"
KNOWN_SPLITS = ("train", "test", "test_scenes")
METADATA_FILE = "camrep_source.json"


@runtime_checkable
class ViewSource(Protocol):
  """What every camrep data source provides (procedural families and real-format readers).

  Attributes:
    name: short dataset name, e.g. "rooms", "gqn", "srn_cars".
    pose_names: names of the P pose coordinates (see `camrep.data.sources`).
    image_size: side of the square images, or (H, W).

  A source may also have `splits` (a sequence of split names); without it the splits are the
  ones of `KNOWN_SPLITS` for which `num_scenes` succeeds and is positive.
  """

  name: str
  pose_names: Sequence[str]
  image_size: Any

  def num_scenes(self, split: str) -> int:
    """Number of scenes (instances, areas) in `split`."""
    ...

  def iter_views(self, split: str) -> Iterator[dict[str, Any]]:
    """Yields the view records of `split`.

    Yields:
      {"image": uint8 (H, W, 3) RGB, "pose": float32 (P,), "scene": int, "view": int}.
    """
    ...


def image_shape(source: ViewSource) -> tuple[int, int]:
  """The (H, W) of a source's images, from its `image_size` (an int or a (H, W[, 3]) tuple)."""
  size = source.image_size
  if isinstance(size, int | np.integer):
    return int(size), int(size)
  size = tuple(int(s) for s in size)
  if len(size) not in (2, 3):
    raise DataError(None, f"source {source.name!r}: image_size {size} is not S or (H, W)")
  return size[0], size[1]


def source_splits(source: ViewSource) -> tuple[str, ...]:
  """The splits a source provides, in a stable order.

  Uses `source.splits` when the source has it, otherwise probes `KNOWN_SPLITS` with
  `num_scenes` (an exception or 0 scenes means the split is absent).
  """
  declared = getattr(source, "splits", None)
  if declared is not None:
    return tuple(declared)
  found = []
  for split in KNOWN_SPLITS:
    try:
      if source.num_scenes(split) > 0:
        found.append(split)
    except (KeyError, ValueError):
      continue
  if not found:
    raise DataError(None, f"source {source.name!r} has none of the splits {KNOWN_SPLITS}")
  return tuple(found)


def encode_png(image_rgb: np.ndarray) -> bytes:
  """PNG bytes of an RGB uint8 image, written by cv2 from BGR (what tfds decodes back to RGB).

  Args:
    image_rgb: uint8 (H, W, 3).

  Returns:
    The encoded PNG.
  """
  ok, buf = cv2.imencode(".png", np.ascontiguousarray(image_rgb[..., ::-1]))
  if not ok:
    raise DataError(None, f"cv2 could not PNG-encode an image of shape {image_rgb.shape}")
  return buf.tobytes()


def decode_png(png: bytes) -> np.ndarray:
  """Inverse of `encode_png`: uint8 (H, W, 3) RGB, exactly as tfds' own cv2 decoder does it."""
  bgr = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
  if bgr is None:
    raise DataError(None, "cv2 could not decode a stored PNG")
  return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)  # A pure channel swap, contiguous output.


def check_record(
  record: Mapping[str, Any], shape: tuple[int, int], pose_dim: int, where: str
) -> None:
  """Raises DataError unless `record` follows the view-record contract.

  Args:
    record: a view record from a source.
    shape: the expected (H, W) of the image.
    pose_dim: the expected P of the pose.
    where: what to call the record in the message (source/split #i).
  """
  missing = [k for k in ("image", "pose", "scene", "view") if k not in record]
  if missing:
    raise DataError(None, f"{where}: record lacks {missing}")
  image = record["image"]
  if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape != (*shape, 3):
    got = (getattr(image, "dtype", type(image)), getattr(image, "shape", None))
    raise DataError(None, f"{where}: image must be uint8 {(*shape, 3)}, got {got}")
  pose = np.asarray(record["pose"])
  if pose.shape != (pose_dim,) or not np.all(np.isfinite(pose)):
    raise DataError(None, f"{where}: pose must be {pose_dim} finite numbers, got {pose!r}")


@functools.cache
def _builder_base() -> type:
  """`_SourceBuilderBase`, defined on first use: tfds (0.15 s to import) is needed only to write
  or read a prepared dataset, not by runs on in-memory data."""
  import tensorflow_datasets as tfds

  class _LocalDatasetInfo(tfds.core.DatasetInfo):
    """DatasetInfo that never looks for pre-computed info in the tfds GCS bucket.

    Our datasets are never there, and tfds' lookup leaks an empty temp directory per build.
    """

    def initialize_from_bucket(self) -> None:
      return None

  class _SourceBuilderBase(tfds.core.GeneratorBasedBuilder, skip_registration=True):
    """Writes the splits of the `ViewSource` passed to the constructor (see `builder_class`)."""

    VERSION = tfds.core.Version(DEFAULT_VERSION)

    def __init__(self, *, source: ViewSource, progress: bool = True, **kwargs):
      self._source = source
      self._progress = progress
      self._image_shape = image_shape(source)
      self._pose_dim = len(source.pose_names)
      self._splits = source_splits(source)
      super().__init__(**kwargs)

    def _info(self) -> tfds.core.DatasetInfo:
      return _LocalDatasetInfo(
        builder=self,
        description=(
          f"camrep view records of source {self._source.name!r}, "
          f"pose = {tuple(self._source.pose_names)}."
        ),
        features=tfds.features.FeaturesDict(
          {
            "image": tfds.features.Image(shape=(*self._image_shape, 3)),
            "pose": tfds.features.Tensor(shape=(self._pose_dim,), dtype=np.float32),
            "scene": tfds.features.Scalar(dtype=np.int64),
            "view": tfds.features.Scalar(dtype=np.int64),
            "index": tfds.features.Scalar(dtype=np.int64),
          }
        ),
      )

    def _log_download_bytes(self) -> None:
      """Silent: tfds' "Downloading and preparing dataset 0 bytes ..." misleads for a local
      conversion (`camrep.data.prepare` prints what it wrote)."""

    def _log_download_done(self) -> None:
      """Silent, as `_log_download_bytes`."""

    def _split_generators(self, dl_manager):
      del dl_manager  # Nothing to download: the source reads its own input.
      return {split: self._generate_examples(split) for split in self._splits}

    def _generate_examples(self, split: str):
      views = self._source.iter_views(split)
      if self._progress:
        try:  # `num_views(split)` is optional; it only gives the bar its total.
          total = int(self._source.num_views(split))
        except (AttributeError, TypeError, ValueError):
          total = None
        desc = f"{self._source.name}/{split}"
        views = tqdm.tqdm(views, desc=desc, total=total, unit=" views", mininterval=1.0)
      for i, record in enumerate(views):
        check_record(record, self._image_shape, self._pose_dim, f"{self._source.name}/{split} #{i}")
        yield (
          i,
          {
            "image": encode_png(record["image"]),
            "pose": np.asarray(record["pose"], dtype=np.float32),
            "scene": int(record["scene"]),
            "view": int(record["view"]),
            "index": i,
          },
        )

  return _SourceBuilderBase


def builder_class(
  name: str, *, version: str = DEFAULT_VERSION, config: str | None = None
) -> type[tfds.core.GeneratorBasedBuilder]:
  """A GeneratorBasedBuilder subclass that stores a source under dataset `name`.

  Args:
    name: the tfds dataset name (the directory under data_dir), snake_case.
    version: tfds version string "X.Y.Z".
    config: optional builder-config name (a sub-directory, e.g. the preset).

  Returns:
    A class whose constructor takes `source=` (a `ViewSource`) besides the usual tfds
    arguments (`data_dir`, `file_format`, `config`). It is not registered with tfds.
  """
  import tensorflow_datasets as tfds

  if not name.isidentifier() or name.lower() != name:
    raise DataError(None, f"dataset name {name!r} must be a lower-case identifier")

  def body(ns: dict[str, Any]) -> None:
    ns["name"] = name
    ns["VERSION"] = tfds.core.Version(version)
    ns["RELEASE_NOTES"] = {version: "camrep view records."}
    if config is not None:
      ns["BUILDER_CONFIGS"] = [tfds.core.BuilderConfig(name=config)]

  cls_name = "".join(part.capitalize() for part in name.split("_")) + "Views"
  return types.new_class(cls_name, (_builder_base(),), {"skip_registration": True}, body)


@dataclasses.dataclass(frozen=True)
class ViewIndex:
  """The sidecar of one stored split: every view's ids and pose, without its image.

  Rows are sorted by `index` (the source's iteration order).

  Attributes:
    record: int64 (N,), position of the view in the split's record store.
    index: int64 (N,), position in the source's `iter_views` order.
    scene: int64 (N,), scene id.
    view: int64 (N,), view id within the scene.
    pose: float32 (N, P).
    pose_names: the P pose coordinate names.
    image_shape: (H, W) of the images.
  """

  record: np.ndarray
  index: np.ndarray
  scene: np.ndarray
  view: np.ndarray
  pose: np.ndarray
  pose_names: tuple[str, ...]
  image_shape: tuple[int, int]

  def __len__(self) -> int:
    return int(self.record.shape[0])

  @property
  def num_scenes(self) -> int:
    """Number of distinct scene ids."""
    return int(np.unique(self.scene).size)

  def subset(self, rows: np.ndarray) -> ViewIndex:
    """The views at `rows` (int positions or a bool (N,) mask); `record` still addresses the
    split's record store."""
    return dataclasses.replace(
      self, record=self.record[rows], index=self.index[rows], scene=self.scene[rows],
      view=self.view[rows], pose=self.pose[rows],
    )  # fmt: skip

  def save(self, path: str | os.PathLike) -> None:
    """Writes the index as an .npz file."""
    np.savez(
      path,
      record=self.record,
      index=self.index,
      scene=self.scene,
      view=self.view,
      pose=self.pose,
      pose_names=np.asarray(self.pose_names),
      image_shape=np.asarray(self.image_shape, dtype=np.int64),
    )

  @classmethod
  def from_npz(cls, path: str | os.PathLike) -> ViewIndex:
    """Reads an index written by `save`."""
    try:
      with np.load(path) as z:
        return cls(
          record=z["record"],
          index=z["index"],
          scene=z["scene"],
          view=z["view"],
          pose=z["pose"],
          pose_names=tuple(str(s) for s in z["pose_names"]),
          image_shape=tuple(int(s) for s in z["image_shape"]),
        )
    except FileNotFoundError:
      raise DataError(path, "sidecar index missing; re-run camrep.data.prepare") from None
    except (KeyError, ValueError, OSError) as e:
      raise DataError(path, f"unreadable sidecar index ({e})") from None


def _index_from_records(
  data_source: Sequence[Mapping[str, Any]], pose_names: Sequence[str], shape: tuple[int, int]
) -> ViewIndex:
  """Builds the sidecar of a split from its record store (images are not decoded)."""
  n = len(data_source)
  index = np.empty(n, np.int64)
  scene = np.empty(n, np.int64)
  view = np.empty(n, np.int64)
  pose = np.empty((n, len(pose_names)), np.float32)
  chunk = 1024
  for start in range(0, n, chunk):
    rows = list(range(start, min(n, start + chunk)))
    for r, ex in zip(rows, data_source.__getitems__(rows), strict=True):
      index[r], scene[r], view[r], pose[r] = ex["index"], ex["scene"], ex["view"], ex["pose"]
  order = np.argsort(index, kind="stable")
  return ViewIndex(
    record=order.astype(np.int64),
    index=index[order],
    scene=scene[order],
    view=view[order],
    pose=pose[order],
    pose_names=tuple(pose_names),
    image_shape=shape,
  )


def prepare(
  source: ViewSource,
  data_dir: str | os.PathLike,
  *,
  name: str | None = None,
  version: str = DEFAULT_VERSION,
  config: str | None = None,
  metadata: Mapping[str, Any] | None = None,
  overwrite: bool = False,
  progress: bool = True,
) -> pathlib.Path:
  """Stores every split of `source` as tfds ArrayRecord files plus the sidecar index.

  Args:
    source: the view-record source.
    data_dir: tfds data directory (created if missing).
    name: dataset name; defaults to `source.name`.
    version: tfds version string.
    config: optional builder-config name (e.g. the preset).
    metadata: extra JSON-serialisable facts to record (overrides, input path, ...).
    overwrite: regenerate even when the dataset already exists (the old one is kept, moved
      aside, until the new one is complete, and put back if writing fails).
    progress: show a tqdm bar per split.

  Returns:
    The dataset directory `data_dir/name[/config]/version`.

  Raises:
    DataError: `data_dir` is a file or not UTF-8 (`check_path`), or another process is
      preparing the same dataset (a lock in `data_dir/name[/config]`).
    OSError: a full disk or a read-only file system (errno set, for `camrep.runtime.cli`); no
      half-written version is left, and an overwritten one is back in place.
  """
  name = name or source.name
  check_path(data_dir, "data_dir")
  parent = pathlib.Path(data_dir) / name / (config or "")
  with _writer_lock(parent):
    return _prepare_locked(
      source, data_dir, name, version, config, metadata, overwrite=overwrite, progress=progress
    )


def _prepare_locked(source, data_dir, name, version, config, metadata, *, overwrite, progress):
  """`prepare` under the writer's lock."""
  import tensorflow_datasets as tfds

  cls = builder_class(name, version=version, config=config)
  tfds.disable_progress_bar()  # Our per-view tqdm bar replaces tfds' (a process-wide switch).
  t0 = time.perf_counter()
  builder = cls(
    source=source,
    progress=progress,
    data_dir=os.fspath(data_dir),
    file_format="array_record",
    config=config,
  )
  path = pathlib.Path(builder.data_dir)
  sidecars = [path / f"views_index_{s}.npz" for s in source_splits(source)]
  if not overwrite and all(f.exists() for f in [path / METADATA_FILE, *sidecars]):
    return path  # Finished earlier (prepare writes the metadata last).
  # An overwritten dataset stays whole beside the new one until that is complete.
  aside = path.with_name(f".{path.name}.replaced-{os.getpid()}")
  if overwrite and path.exists():
    os.replace(path, aside)
  try:
    _write(builder, source, path, name, version, config, metadata, t0)
  except BaseException:
    if aside.exists():
      shutil.rmtree(path, ignore_errors=True)
      os.replace(aside, path)
    raise
  shutil.rmtree(aside, ignore_errors=True)
  return path


def _write(builder, source, path, name, version, config, metadata, t0) -> None:
  """The records (tfds), the sidecars, then the metadata that marks the dataset finished."""
  import tensorflow_datasets as tfds

  with tempfile.TemporaryDirectory() as download_dir:  # Nothing is downloaded; keep it tidy.
    try:
      builder.download_and_prepare(
        download_dir=download_dir,
        download_config=tfds.download.DownloadConfig(
          download_mode=tfds.download.GenerateMode.REUSE_DATASET_IF_EXISTS
        ),
      )
    except RuntimeError as e:  # array_record reports a full disk as text, without an errno
      err = _os_error_in_text(str(e), path)
      if err is None:
        raise
      raise err from e
    except AssertionError as e:  # tfds refuses a split without records (its incomplete copy gone)
      empty = re.search(r'split "([^"]+)": No examples were yielded', str(e))
      if empty is None:
        raise
      raise DataError(
        path,
        f"source {source.name!r} gave no view for its {empty.group(1)!r} split; nothing was "
        "kept. Check the input (or the settings that choose the split's views)",
      ) from None
  splits = {}
  shape = image_shape(source)
  for split in builder.info.splits:
    data_source = builder.as_data_source(split, decoders={"image": tfds.decode.SkipDecoding()})
    index = _index_from_records(data_source, source.pose_names, shape)
    index.save(path / f"views_index_{split}.npz")
    splits[split] = {"num_views": len(index), "num_scenes": index.num_scenes}
  meta = {
    "name": name,
    "source": source.name,
    "version": version,
    "config": config,
    "pose_names": list(source.pose_names),
    "image_shape": list(shape),
    "splits": splits,
    "prepare_seconds": round(time.perf_counter() - t0, 3),
    "metadata": dict(metadata or {}),
  }
  describe = getattr(source, "describe", None)
  if callable(describe):  # optional: facts the source states about itself (captures)
    meta["source_info"] = describe()
  inputs = getattr(source, "inputs", None)
  if callable(inputs):  # optional: a fingerprint of the files it read (captures)
    meta["inputs"] = inputs()
  text = json.dumps(meta, indent=2, sort_keys=True, default=str)
  writers.write_text_atomic(path / METADATA_FILE, text)  # last: it marks a finished dataset


def _os_error_in_text(text: str, path: pathlib.Path) -> OSError | None:
  """The OSError a message describes in words ("No space left on device", ...), or None."""
  for code in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES):
    if os.strerror(code) in text:
      return OSError(code, os.strerror(code), os.fspath(path))
  return None


@contextlib.contextmanager
def _writer_lock(parent: pathlib.Path) -> Iterator[None]:
  """One writer per dataset name (and config): `parent/.camrep.lock` (the workdirs' lock,
  `camrep.runtime.workdir.WorkdirLock`), refused by name while another process holds it.

  Raises:
    DataError: another live process is preparing the same dataset.
    OSError: the lock cannot be written (a full disk, a read-only file system).
  """
  from camrep.runtime import workdir as workdir_lib

  try:
    parent.mkdir(parents=True, exist_ok=True)
  except (FileExistsError, NotADirectoryError) as e:
    raise DataError(e.filename or parent, "a file is in the way of the dataset directory") from None
  lock = workdir_lib.WorkdirLock(os.fspath(parent))
  try:
    lock.acquire()
  except workdir_lib.WorkdirError as e:
    if isinstance(e.__cause__, OSError):
      raise e.__cause__ from None
    h = lock.holder() or {}
    who = f"PID {h.get('pid', '?')} on {h.get('host', '?')}, started {h.get('started', '?')}"
    raise DataError(
      parent,
      f"another process is preparing this dataset ({who}; lock {lock.path}): wait for it to "
      "finish (then prepare again to reuse its result), or prepare into another --data_dir or "
      "--config_name; if that process is gone (another host, a crashed machine), delete the lock "
      "file",
    ) from None
  try:
    yield
  finally:
    lock.release()


def check_path(path: str | os.PathLike, what: str) -> None:
  """Refuses a data path the record files cannot take, before anything is written.

  Raises:
    DataError: `path` exists and is not a directory, or is not UTF-8 text (a non-ASCII name
      under a non-UTF-8 locale: Python keeps its bytes as surrogates, which ArrayRecord's
      writer and reader refuse).
  """
  text = os.fspath(path)
  try:
    text.encode("utf-8")
  except UnicodeEncodeError:
    raise DataError(
      text.encode("utf-8", "backslashreplace").decode("ascii", "backslashreplace"),
      f"{what} is not valid in this locale's file-system encoding "
      f"({sys.getfilesystemencoding()}), and the record files take UTF-8 paths only: run under a "
      "UTF-8 locale (e.g. LC_ALL=C.UTF-8) or use an ASCII path",
    ) from None
  if os.path.exists(text) and not os.path.isdir(text):
    raise DataError(text, f"{what} names a file, not a directory")


def _version_dirs(base: pathlib.Path) -> list[pathlib.Path]:
  """Sub-directories of `base` that hold a finished tfds dataset version."""
  import tensorflow_datasets as tfds

  out = []
  for d in base.iterdir():
    if d.is_dir() and (d / "dataset_info.json").exists():
      try:
        tfds.core.Version(d.name)
      except ValueError:
        continue
      out.append(d)
  return sorted(out, key=lambda d: tfds.core.Version(d.name))


def dataset_dir(
  data_dir: str | os.PathLike,
  name: str,
  *,
  config: str | None = None,
  version: str | None = None,
) -> pathlib.Path:
  """Finds `data_dir/name[/config]/version` of a prepared dataset.

  Args:
    data_dir: the tfds data directory given to `prepare`.
    name: dataset name.
    config: builder-config name; may be omitted when the dataset has exactly one.
    version: version string; defaults to the newest prepared one.

  Returns:
    The dataset directory.

  Raises:
    DataError: the directory, dataset, config or version does not exist.
  """
  check_path(data_dir, "data_dir")
  root = pathlib.Path(data_dir)
  if not root.is_dir():
    raise DataError(root, "data_dir does not exist; run `python -m camrep.data.prepare` first")
  base = root / name
  if not base.is_dir():
    found = sorted(d.name for d in root.iterdir() if d.is_dir() and not d.name.startswith("."))
    raise DataError(root, f"no prepared dataset {name!r} here (found: {found or 'nothing'})")
  if config is not None:
    if not (base / config).is_dir():
      raise DataError(base / config, f"dataset {name!r} has no config {config!r}" + _variants(base))
    base = base / config
  versions = _version_dirs(base)
  if not versions and config is None:
    configs = [d for d in base.iterdir() if d.is_dir() and _version_dirs(d)]
    if len(configs) == 1:
      base, versions = configs[0], _version_dirs(configs[0])
    elif configs:
      names = sorted(d.name for d in configs)
      raise DataError(base, f"several configs {names}; pass config=")
  if not versions:
    raise DataError(base, "no finished dataset version here (preparation interrupted?)")
  if version is None:
    return versions[-1]
  for d in versions:
    if d.name == version:
      return d
  raise DataError(base, f"no version {version!r} (found: {[d.name for d in versions]})")


def _variants(base: pathlib.Path) -> str:
  """What `base` (DATA_DIR/NAME) holds, and how a config finds it, for "no config" errors."""
  found = []
  for d in [base, *sorted(p for p in base.iterdir() if p.is_dir())]:
    versions = _version_dirs(d)
    if not versions:
      continue
    try:
      shape = json.loads((versions[-1] / METADATA_FILE).read_text())["image_shape"]
      size = f" at {shape[0]}x{shape[1]} px"
    except (OSError, KeyError, ValueError):
      size = ""
    found.append(("default (no config)" if d == base else repr(d.name)) + size)
  if not found:
    return " (nothing is prepared under it)"
  return (
    f"; it holds {', '.join(found)}. The configs read the dataset of data.preset (':quick' ones "
    "'small'): prepare with `--preset small` (or `--config_name small` with your --config. "
    "overrides), or pass --config.data.preset=default to read the default one, when its image "
    "size is the model's"
  )


def load_metadata(path: str | os.PathLike) -> dict[str, Any]:
  """The `camrep_source.json` of a dataset directory returned by `dataset_dir`/`prepare`."""
  file = pathlib.Path(path) / METADATA_FILE
  try:
    return json.loads(file.read_text())
  except FileNotFoundError:
    raise DataError(file, "metadata missing; re-run camrep.data.prepare") from None
  except json.JSONDecodeError as e:
    raise DataError(file, f"not valid JSON ({e})") from None


def check_held_out(metadata: Mapping[str, Any], path: str | os.PathLike, split: str) -> None:
  """Refuses to evaluate on the "test" split of a captures dataset in which a seen capture has
  no view: its held-out figures would silently come from the other captures only.

  Args:
    metadata: the dataset's `camrep_source.json` (`load_metadata`).
    path: the dataset directory, for the message.
    split: the split being opened; only "test" is checked.

  Raises:
    DataError: naming the captures without held-out views, their split rule and the fixes.
  """
  info = metadata.get("source_info") or {}
  if split != "test" or info.get("kind") != "captures":
    return
  empty = [
    c
    for c in info.get("captures", [])
    if c.get("role") == "seen" and not c.get("splits", {}).get("test")
  ]
  if empty:
    names = "; ".join(f"{c.get('name')} ({c.get('split_rule', '?')})" for c in empty)
    raise DataError(
      path,
      f"cannot evaluate on its 'test' split: {len(empty)} seen capture(s) have no held-out view "
      f"in it: {names}. Prepare again with --overwrite and --config.holdout_every=K (K > 0; 8 "
      "is LLFF's convention) to hold out every K-th view, give the capture a test split of its "
      "own, or keep it whole for testing with --config.unseen",
    )


class StoredSplit(Sequence):
  """Random access to one stored split.

  `split[i]` is the view record at record position i (NOT source index i; see the sidecar):
  {"image": uint8 (H, W, 3), "pose": float32 (P,), "scene": int, "view": int, "index": int}.

  Attributes:
    path: the dataset directory.
    split: the split name.
    index: the sidecar `ViewIndex`.
    metadata: the parsed `camrep_source.json`.
    data_source: the tfds `ArrayRecordDataSource` (images left PNG-encoded).
  """

  def __init__(self, path: pathlib.Path, split: str):
    import tensorflow_datasets as tfds

    self.path = path
    self.split = split
    self.metadata = load_metadata(path)
    check_held_out(self.metadata, path, split)
    builder = tfds.builder_from_directory(os.fspath(path))
    available = list(builder.info.splits)
    if split not in available:
      raise DataError(path, f"unknown split {split!r}; available: {available}")
    self.data_source = builder.as_data_source(split, decoders={"image": tfds.decode.SkipDecoding()})
    self.index = ViewIndex.from_npz(path / f"views_index_{split}.npz")
    if len(self.index) != len(self.data_source):
      raise DataError(path, f"sidecar of {split!r} has {len(self.index)} views, records differ")

  def __len__(self) -> int:
    return len(self.data_source)

  def __reduce__(self):
    # Pickled as (path, split) and reopened on load: a grain worker process
    # (`PipelineConfig.num_workers`) opens its own ArrayRecord readers.
    return (StoredSplit, (self.path, self.split))

  def _decode(self, ex: Mapping[str, Any]) -> dict[str, Any]:
    return {
      "image": decode_png(ex["image"]),
      "pose": np.asarray(ex["pose"], np.float32),
      "scene": int(ex["scene"]),
      "view": int(ex["view"]),
      "index": int(ex["index"]),
    }

  def __getitem__(self, i):
    if isinstance(i, slice):
      return self.__getitems__(list(range(len(self))[i]))
    i = int(i)
    if not -len(self) <= i < len(self):
      raise IndexError(f"record {i} out of range for {len(self)} records")
    return self._decode(self.data_source[i % len(self)])

  def __iter__(self) -> Iterator[dict[str, Any]]:
    for start in range(0, len(self), 256):
      yield from self.__getitems__(range(start, min(len(self), start + 256)))

  def __getitems__(self, records: Sequence[int]) -> list[dict[str, Any]]:
    """Decoded records at the given record positions."""
    return [self._decode(ex) for ex in self.data_source.__getitems__([int(r) for r in records])]

  def read_images(self, records: np.ndarray) -> np.ndarray:
    """Decodes the images at record positions `records`.

    Args:
      records: int (...,) record positions.

    Returns:
      uint8 (..., H, W, 3) RGB.
    """
    records = np.asarray(records)
    flat = [int(r) for r in records.reshape(-1)]
    exs = self.data_source.__getitems__(flat)
    images = np.stack([decode_png(ex["image"]) for ex in exs]) if flat else None
    if images is None:
      return np.zeros((*records.shape, *self.index.image_shape, 3), np.uint8)
    return images.reshape(*records.shape, *images.shape[1:])


def views_in_memory(source: ViewSource, split: str) -> tuple[ViewIndex, np.ndarray]:
  """Reads a whole split of a source into memory.

  Args:
    source: the view-record source.
    split: split name.

  Returns:
    index: the split's `ViewIndex` (record = position in `images`).
    images: uint8 (N, H, W, 3).

  Raises:
    DataError: unknown split, empty split or a record breaking the contract.
  """
  splits = source_splits(source)
  if split not in splits:
    raise DataError(None, f"source {source.name!r} has no split {split!r}; available: {splits}")
  shape = image_shape(source)
  p = len(source.pose_names)
  images, poses, scenes, views = [], [], [], []
  for i, rec in enumerate(source.iter_views(split)):
    check_record(rec, shape, p, f"{source.name}/{split} #{i}")
    images.append(rec["image"])
    poses.append(np.asarray(rec["pose"], np.float32))
    scenes.append(int(rec["scene"]))
    views.append(int(rec["view"]))
  n = len(images)
  if n == 0:
    raise DataError(None, f"source {source.name!r} split {split!r} holds no views")
  index = ViewIndex(
    record=np.arange(n, dtype=np.int64),
    index=np.arange(n, dtype=np.int64),
    scene=np.asarray(scenes, np.int64),
    view=np.asarray(views, np.int64),
    pose=np.stack(poses),
    pose_names=tuple(source.pose_names),
    image_shape=shape,
  )
  return index, np.stack(images)


def load(
  data_dir: str | os.PathLike,
  name: str,
  split: str,
  *,
  config: str | None = None,
  version: str | None = None,
) -> StoredSplit:
  """Opens a prepared split for random access (tfds `builder_from_directory` + data source).

  Args:
    data_dir: the tfds data directory given to `prepare`.
    name: dataset name.
    split: "train", "test" or "test_scenes".
    config: builder-config name, when the dataset has several.
    version: version string; defaults to the newest.

  Returns:
    A `StoredSplit`.

  Raises:
    DataError: missing/empty data_dir, unknown dataset, config, version or split.
  """
  return StoredSplit(dataset_dir(data_dir, name, config=config, version=version), split)

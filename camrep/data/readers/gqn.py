"""DeepMind GQN datasets (`deepmind/gqn-datasets`) read from TFRecords without TensorFlow.

On-disk format (shared/reference/datasets_and_conventions.md, section 2a):

* `<root>/<dataset>/<train|test>/NNN-of-MMM.tfrecord`, 1-based, zero-padded to the width of MMM.
* Uncompressed TFRecord framing: per record `uint64 length`, `uint32 masked_crc32c(length)`,
  `data`, `uint32 masked_crc32c(data)` (little endian). Each record is one `tf.train.Example` =
  one scene with `frames` (bytes list of V JPEG strings) and `cameras` (float list of V x 5:
  x, y, z, yaw, pitch in radians, row-major per view).

The framing is parsed here (CRCs checked with `crc32c`) and the protobuf with the
`tf.train.Example` schema shipped by the `tfrecord` package, so a truncated or corrupt file
raises a `DataError` naming the file and the record index.

Pose: (x, y, yaw mod 2 pi). z and pitch are ignored, as in the paper and the authors' code
(`rooms_free_camera_no_object_rotations` has a camera at roughly constant height; pitch varies
but is not part of the paper's pose system). The authors used yaw + 2 pi (valid only for
yaw in [-2 pi, 0]); wrapping modulo 2 pi is identical whenever their assertion held.

Splits: a GQN record has no split of its own. The authors trained on a random permutation of
all 10 views of every scene and tested on view 9 of the same scenes (the authors' code: a
leak). camrep fixes the held-out view: "train" yields views 0..8, "test" view 9 (generally the
first `num_train_views` views vs the rest) of the same scenes, which come from one source split
of the release (the authors used the release's `test` split only; that is the default).
"""

from __future__ import annotations

import logging
import os
import re
import struct
from collections.abc import Iterator, Sequence

import crc32c
import numpy as np
from google.protobuf.message import DecodeError
from tfrecord import example_pb2

from camrep import settings
from camrep.data.errors import DataError
from camrep.data.readers.imageio import PathLike, check_image_size, decode_image

ROOMS = "rooms_free_camera_no_object_rotations"
"""The GQN dataset the paper uses."""

DEFAULT_XY_RANGE = (-1.0, 1.1)
"""Half-open [lo, hi) range of x and y, from the authors' grid assertion (v + 1) / 0.1 < 21."""

SPLITS = ("train", "test")
_FILE_RE = re.compile(r"^(\d+)-of-(\d+)\.tfrecord$")
_MASK_DELTA = 0xA282EAD8
_TWO_PI = 2 * np.pi


def masked_crc32c(data: bytes) -> int:
  """TFRecord's masked CRC32C: rotate right by 15 bits and add 0xa282ead8 (mod 2^32)."""
  crc = crc32c.crc32c(data)
  return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


def iter_tfrecord(path: PathLike) -> Iterator[bytes]:
  """Yields the raw records of an uncompressed TFRecord file, checking both CRCs.

  Args:
    path: the .tfrecord file.

  Yields:
    The data bytes of each record, in file order.

  Raises:
    DataError: naming the file and the 0-based record index, for a truncated header or payload,
      a length/data CRC mismatch, or an unreadable file.
  """
  try:
    f = open(path, "rb")
  except OSError as e:
    raise DataError(path, f"cannot open TFRecord file ({e.strerror or e})") from e
  with f:
    index = 0
    while True:
      header = f.read(12)
      if not header:
        return
      if len(header) < 12:
        raise DataError(path, f"record {index}: truncated header ({len(header)} of 12 bytes)")
      (length,) = struct.unpack("<Q", header[:8])
      (length_crc,) = struct.unpack("<I", header[8:])
      if masked_crc32c(header[:8]) != length_crc:
        raise DataError(path, f"record {index}: length CRC mismatch (corrupt framing)")
      data = f.read(length)
      if len(data) < length:
        raise DataError(path, f"record {index}: truncated payload ({len(data)} of {length} bytes)")
      footer = f.read(4)
      if len(footer) < 4:
        raise DataError(path, f"record {index}: truncated data CRC ({len(footer)} of 4 bytes)")
      if masked_crc32c(data) != struct.unpack("<I", footer)[0]:
        raise DataError(path, f"record {index}: data CRC mismatch (corrupt record)")
      yield data
      index += 1


def count_records(path: PathLike) -> int:
  """Counts the records of a TFRecord file by walking the framing (header CRCs checked).

  Raises:
    DataError: as `iter_tfrecord`, for a truncated file or a bad length CRC.
  """
  size = os.path.getsize(path)
  n, offset = 0, 0
  with open(path, "rb") as f:
    while offset < size:
      header = f.read(12)
      if len(header) < 12:
        raise DataError(path, f"record {n}: truncated header ({len(header)} of 12 bytes)")
      (length,) = struct.unpack("<Q", header[:8])
      if masked_crc32c(header[:8]) != struct.unpack("<I", header[8:])[0]:
        raise DataError(path, f"record {n}: length CRC mismatch (corrupt framing)")
      offset += 12 + length + 4
      if offset > size:
        raise DataError(path, f"record {n}: truncated payload ({offset - size} bytes short)")
      f.seek(offset)
      n += 1
  return n


def parse_example(data: bytes, path: PathLike, index: int) -> tuple[list[bytes], np.ndarray]:
  """Parses one GQN `tf.train.Example`.

  Args:
    data: serialized example.
    path, index: file and record index, for error messages.

  Returns:
    frames: V encoded JPEG strings.
    cameras: float32 (V, 5) x, y, z, yaw, pitch as stored.

  Raises:
    DataError: for an unparseable protobuf, missing features, inconsistent lengths or
      non-finite cameras.
  """
  ex = example_pb2.Example()
  try:
    ex.ParseFromString(data)
  except DecodeError as e:
    raise DataError(path, f"record {index}: not a tf.train.Example ({e})") from e
  feats = ex.features.feature
  for key, kind in (("frames", "bytes_list"), ("cameras", "float_list")):
    if key not in feats or feats[key].WhichOneof("kind") != kind:
      raise DataError(path, f"record {index}: feature {key!r} ({kind}) missing")
  frames = list(feats["frames"].bytes_list.value)
  cameras = np.asarray(feats["cameras"].float_list.value, dtype=np.float32)
  if not frames or cameras.size != 5 * len(frames):
    raise DataError(
      path, f"record {index}: {len(frames)} frames but {cameras.size} camera values (want 5 each)"
    )
  cameras = cameras.reshape(len(frames), 5)
  if not np.all(np.isfinite(cameras)):
    raise DataError(path, f"record {index}: non-finite camera values")
  return frames, cameras


def _decode_frame(
  data: bytes, path: PathLike, index: int, view: int, size: int | None
) -> np.ndarray:
  """Decodes one JPEG frame to uint8 (H, W, 3) RGB, checking it is size x size (None: any)."""
  where = f"{os.fspath(path)} (record {index}, view {view})"
  img = decode_image(data, where)
  check_image_size(img, None if size is None else (size, size), where)
  return img


def read_tfrecord(path: PathLike, *, frame_size: int | None = None) -> Iterator[dict]:
  """Yields the scenes of one GQN TFRecord file.

  Args:
    path: the .tfrecord file.
    frame_size: if given, every frame must be frame_size x frame_size.

  Yields:
    dict(frames=uint8 (V, H, W, 3) RGB decoded from JPEG with OpenCV,
         cameras=float32 (V, 5) x, y, z, yaw, pitch as stored).

  Raises:
    DataError: naming the file and the record index (see `iter_tfrecord`, `parse_example`), or
      for an undecodable or wrongly sized frame.
  """
  for index, data in enumerate(iter_tfrecord(path)):
    frames, cameras = parse_example(data, path, index)
    imgs = [_decode_frame(b, path, index, v, frame_size) for v, b in enumerate(frames)]
    shapes = {im.shape for im in imgs}
    if len(shapes) != 1:
      raise DataError(path, f"record {index}: frames of different sizes {sorted(shapes)}")
    yield dict(frames=np.stack(imgs), cameras=cameras)


def list_tfrecords(root: PathLike, dataset: str, split: str) -> list[str]:
  """Lists `<root>/<dataset>/<split>/NNN-of-MMM.tfrecord`, ordered by the 1-based file number.

  A subset of the files (a partial download) is accepted, but every name must be well formed.

  Args:
    root: the directory holding one folder per GQN dataset.
    dataset: e.g. "rooms_free_camera_no_object_rotations".
    split: the release's split folder, "train" or "test".

  Returns:
    Paths of the TFRecord files.

  Raises:
    DataError: for a missing or empty directory, a badly numbered file, or files with
      different totals MMM.
  """
  d = os.path.join(os.fspath(root), dataset, split)
  if not os.path.isdir(d):
    raise DataError(d, "GQN split directory does not exist")
  found = []
  for name in os.listdir(d):
    if not name.endswith(".tfrecord"):
      continue
    m = _FILE_RE.match(name)
    if m is None:
      raise DataError(os.path.join(d, name), "TFRecord name is not NNN-of-MMM.tfrecord")
    k, total = int(m.group(1)), int(m.group(2))
    if not 1 <= k <= total or len(m.group(1)) != len(m.group(2)):
      raise DataError(
        os.path.join(d, name), "file number must be 1-based and zero-padded to the width of MMM"
      )
    found.append((k, total, os.path.join(d, name)))
  if not found:
    raise DataError(d, "no NNN-of-MMM.tfrecord files in GQN split directory")
  totals = {t for _, t, _ in found}
  if len(totals) != 1:
    raise DataError(d, f"TFRecord files disagree on the number of shards: {sorted(totals)}")
  found.sort()
  if len(found) < next(iter(totals)):
    logging.info("%s: %d of %d TFRecord shards present", d, len(found), next(iter(totals)))
  return [p for _, _, p in found]


def cameras_to_poses(cameras: np.ndarray) -> np.ndarray:
  """GQN cameras (V, 5) = (x, y, z, yaw, pitch) -> poses (V, 3) = (x, y, yaw mod 2 pi).

  z and pitch are dropped, as in the paper.

  Args:
    cameras: (V, 5) as stored.

  Returns:
    float32 (V, 3) with yaw in [0, 2 pi).
  """
  cam = np.asarray(cameras, dtype=np.float64)
  yaw = np.mod(cam[:, 3], _TWO_PI)
  poses = np.stack([cam[:, 0], cam[:, 1], yaw], axis=-1).astype(np.float32)
  # A tiny negative yaw wraps to just below 2 pi, which float32 may round up to 2 pi.
  poses[poses[:, 2] >= np.float32(_TWO_PI), 2] = 0.0
  return poses


def check_xy_range(
  poses: np.ndarray, path: PathLike, index: int, *, xy_range: Sequence[float] = DEFAULT_XY_RANGE
) -> None:
  """Raises a `DataError` naming the file, record and view if x or y leaves [lo, hi).

  Args:
    poses: (V, 3) poses of one scene.
    path, index: file and record index, for the message.
    xy_range: (lo, hi).
  """
  lo, hi = xy_range
  bad = np.nonzero(np.any((poses[:, :2] < lo) | (poses[:, :2] >= hi), axis=-1))[0]
  if bad.size:
    v = int(bad[0])
    raise DataError(
      path,
      f"record {index}, view {v}: position {poses[v, :2].tolist()} outside [{lo}, {hi})",
    )


class GQN:
  """Reader for one GQN dataset: scenes of the TFRecords, views split 0..8 / 9.

  Attributes:
    name: "gqn".
    pose_names: (x, y, yaw).
    image_size: frame side length (frames must have it; GQN rooms is 64).
    files: the TFRecord files read, in order.
  """

  name = "gqn"
  pose_names = settings.GQN.pose_columns
  splits = SPLITS

  def __init__(
    self,
    root: PathLike,
    *,
    dataset: str = ROOMS,
    source_split: str = "test",
    image_size: int = 64,
    num_train_views: int = 9,
    xy_range: Sequence[float] = DEFAULT_XY_RANGE,
    max_files: int | None = None,
    max_scenes: int | None = None,
  ):
    """Initialises the reader.

    Args:
      root: directory holding `<dataset>/<train|test>/*.tfrecord`.
      dataset: GQN dataset name.
      source_split: the release's split folder to read scenes from ("test", as the authors).
      image_size: expected frame side length; frames of another size raise `DataError`.
      num_train_views: views [0, num_train_views) are "train", the rest "test".
      xy_range: allowed half-open [lo, hi) range of x and y.
      max_files: read only the first `max_files` files (None: all).
      max_scenes: stop after this many scenes (None: all).

    Raises:
      DataError: see `list_tfrecords`.
    """
    self.files = list_tfrecords(root, dataset, source_split)[:max_files]
    self.image_size = int(image_size)
    self.num_train_views = int(num_train_views)
    self.xy_range = tuple(float(v) for v in xy_range)
    self.max_scenes = max_scenes

  def _records(self) -> Iterator[tuple[str, int, bytes]]:
    n = 0
    for path in self.files:
      for index, data in enumerate(iter_tfrecord(path)):
        if self.max_scenes is not None and n >= self.max_scenes:
          return
        yield path, index, data
        n += 1

  def num_scenes(self, split: str) -> int:
    """Number of scenes (the same for both splits; counted from the TFRecord framing)."""
    if split not in SPLITS:
      raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    n = sum(count_records(p) for p in self.files)
    return n if self.max_scenes is None else min(n, self.max_scenes)

  def iter_views(self, split: str) -> Iterator[dict]:
    """Yields view records of `split`, scene by scene in file order.

    "view" is the view's index within its scene as stored (0..8 for "train", 9 for "test"), so
    a view keeps its index whichever split it is in.
    """
    if split not in SPLITS:
      raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    for scene, (path, index, data) in enumerate(self._records()):
      frames, cameras = parse_example(data, path, index)
      if len(frames) <= self.num_train_views:
        raise DataError(
          path,
          f"record {index}: {len(frames)} views, need more than num_train_views="
          f"{self.num_train_views} to hold out a test view",
        )
      poses = cameras_to_poses(cameras)
      check_xy_range(poses, path, index, xy_range=self.xy_range)
      views = (
        range(self.num_train_views)
        if split == "train"
        else range(self.num_train_views, len(frames))
      )
      for v in views:
        yield {
          "image": _decode_frame(frames[v], path, index, v, self.image_size),
          "pose": poses[v].copy(),
          "scene": scene,
          "view": v,
        }

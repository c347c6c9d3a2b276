"""Gibson rooms: the authors' own renders of square areas in 12 Gibson buildings.

On-disk format (the authors' code):

* `<root>/<Building>/<area>/` holds the images and `train_meta.json`, `test_meta.json`, which are
  PYTHON PICKLES despite the suffix (they are unpickled, so only read data you trust).
* train: dict {(gx, gy, gtheta) int grid key: (relative_image_file, (x_m, y_m, yaw_deg))};
  test: dict {key: list of (relative_image_file, (x_m, y_m, yaw_deg))}.
* x, y in metres within [0, 2] of the area; yaw in degrees [0, 360].

Image files are resolved relative to the area folder. Every `<Building>/<area>` folder holding a
`train_meta.json` is one scene (sorted). Pose: (x, y, yaw in radians wrapped to [0, 2 pi)).
Views are ordered by grid key (and list order within a test key). The grid keys are exposed
(`grid_keys`) so a pair sampler can pair grid neighbours, |dgx|, |dgy| <= 1 and |dgtheta| <= 2
as in the authors' code (`grid_neighbours`; gtheta does not wrap there, nor here). The key
resolution is undocumented; only neighbourhood is used.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Iterator, Sequence

import numpy as np

from camrep import settings
from camrep.data.errors import DataError
from camrep.data.readers.imageio import PathLike, crop_and_resize, read_image

SPLITS = ("train", "test")
META_FILES = {"train": "train_meta.json", "test": "test_meta.json"}
DEFAULT_XY_RANGE = (0.0, 2.0)
"""Closed range [lo, hi] of x and y in metres within an area."""

_TWO_PI = 2 * np.pi


def _check_split(split: str) -> None:
  if split not in SPLITS:
    raise ValueError(f"split must be one of {SPLITS}, got {split!r}")


def _parse_entry(entry, path: str, key) -> tuple[str, tuple[float, float, float]]:
  try:
    file, pos = entry
    if not isinstance(file, str):
      raise TypeError(f"file is {type(file).__name__}, not str")
    x, y, yaw = (float(v) for v in pos)
  except (TypeError, ValueError) as e:
    raise DataError(
      path, f"key {key}: expected (image_file, (x_m, y_m, yaw_deg)), got {entry!r} ({e})"
    ) from e
  return file, (x, y, yaw)


def read_meta(path: PathLike, split: str) -> dict:
  """Unpickles and validates a `train_meta.json` / `test_meta.json`.

  Args:
    path: the meta file (a pickle).
    split: "train" (key -> entry) or "test" (key -> list of entries).

  Returns:
    dict(keys=int64 (N, 3) grid keys, files=list[str] of N relative image files,
         poses=float64 (N, 3) (x_m, y_m, yaw_deg) as stored), ordered by key, then list order.

  Raises:
    DataError: if the file is missing, not a pickle, not a dict of the expected structure,
      or empty.
  """
  _check_split(split)
  path = os.fspath(path)
  try:
    with open(path, "rb") as f:
      meta = pickle.load(f)
  except OSError as e:
    raise DataError(path, f"cannot read meta file ({e.strerror or e})") from e
  except Exception as e:  # pickle raises many types on corrupt input.
    raise DataError(path, f"not a readable pickle ({type(e).__name__}: {e})") from e
  if not isinstance(meta, dict):
    raise DataError(path, f"expected a dict keyed by grid (gx, gy, gtheta), got {type(meta)}")
  if not meta:
    raise DataError(path, "meta dict is empty")
  keys, files, poses = [], [], []
  for key in meta:
    if not (isinstance(key, tuple) and len(key) == 3 and all(_is_int(k) for k in key)):
      raise DataError(path, f"grid key {key!r} is not a tuple of 3 ints")
  for key in sorted(meta):
    entries = meta[key]
    if split == "train":
      entries = [entries]
    elif not isinstance(entries, list | tuple) or not entries or isinstance(entries[0], str):
      raise DataError(
        path, f"key {key}: expected a non-empty list of (file, pose), got {entries!r}"
      )
    for entry in entries:
      file, pose = _parse_entry(entry, path, key)
      keys.append(key)
      files.append(file)
      poses.append(pose)
  return dict(
    keys=np.array(keys, dtype=np.int64).reshape(-1, 3),
    files=files,
    poses=np.array(poses, dtype=np.float64).reshape(-1, 3),
  )


def _is_int(v) -> bool:
  return isinstance(v, int | np.integer) and not isinstance(v, bool)


def meta_to_poses(poses_deg: np.ndarray) -> np.ndarray:
  """(x_m, y_m, yaw_deg) -> float32 (x_m, y_m, yaw_rad) with yaw wrapped to [0, 2 pi).

  Args:
    poses_deg: (N, 3) poses as stored.

  Returns:
    float32 (N, 3).
  """
  p = np.asarray(poses_deg, dtype=np.float64)
  yaw = np.mod(np.deg2rad(p[:, 2]), _TWO_PI)
  out = np.stack([p[:, 0], p[:, 1], yaw], axis=-1).astype(np.float32)
  out[out[:, 2] >= np.float32(_TWO_PI), 2] = 0.0
  return out


def grid_neighbours(
  keys: np.ndarray, *, max_dxy: int = 1, max_dtheta: int = 2, include_self: bool = False
) -> list[np.ndarray]:
  """Indices of the grid neighbours of every view (the authors' pair rule).

  Neighbours satisfy |dgx| <= max_dxy, |dgy| <= max_dxy and |dgtheta| <= max_dtheta (gtheta not
  wrapped, as in the authors' code).

  Args:
    keys: int (N, 3) grid keys of one scene and split, as from `read_meta`.
    max_dxy: largest grid step in x and y.
    max_dtheta: largest grid step in theta.
    include_self: whether a view is its own neighbour (also other views with the same key are
      always included).

  Returns:
    N int64 arrays of view indices.
  """
  k = np.asarray(keys, dtype=np.int64)
  lim = np.array([max_dxy, max_dxy, max_dtheta])
  out = []
  for i in range(k.shape[0]):
    near = np.all(np.abs(k - k[i]) <= lim, axis=-1)
    near[i] = include_self
    out.append(np.nonzero(near)[0])
  return out


def list_areas(root: PathLike) -> list[str]:
  """Sorted `<Building>/<area>` folders (holding a train_meta.json) under `root`.

  Raises:
    DataError: if `root` is missing or no area is found.
  """
  root = os.fspath(root)
  if not os.path.isdir(root):
    raise DataError(root, "Gibson root directory does not exist")
  areas = []
  for building in sorted(os.listdir(root)):
    bdir = os.path.join(root, building)
    if not os.path.isdir(bdir):
      continue
    for area in sorted(os.listdir(bdir)):
      if os.path.isfile(os.path.join(bdir, area, META_FILES["train"])):
        areas.append(f"{building}/{area}")
  if not areas:
    raise DataError(root, "no <Building>/<area>/train_meta.json found")
  return areas


class GibsonRooms:
  """Reader for the authors' Gibson rooms: scene = `<Building>/<area>` (sorted).

  Attributes:
    name: "gibson".
    pose_names: (x, y, yaw).
    image_size: side length of the records' images.
    areas: `<Building>/<area>` names in scene-index order.
  """

  name = "gibson"
  pose_names = settings.GIBSON.pose_columns
  splits = SPLITS

  def __init__(
    self,
    root: PathLike,
    *,
    areas: Sequence[str] | None = None,
    image_size: int = 128,
    xy_range: Sequence[float] = DEFAULT_XY_RANGE,
  ):
    """Initialises the reader.

    Args:
      root: directory holding the building folders.
      areas: `<Building>/<area>` names in scene-index order; default: all, sorted.
      image_size: output side length in pixels.
      xy_range: allowed closed [lo, hi] range of x and y in metres.

    Raises:
      DataError: if `root` or a named area is missing, or no area is found.
    """
    self.root = os.fspath(root)
    self.areas = list(areas) if areas is not None else list_areas(self.root)
    for a in self.areas:
      if not os.path.isdir(os.path.join(self.root, a)):
        raise DataError(os.path.join(self.root, a), "Gibson area directory does not exist")
    self.image_size = int(image_size)
    self.xy_range = tuple(float(v) for v in xy_range)

  def num_scenes(self, split: str) -> int:
    """Number of areas (the same for both splits)."""
    _check_split(split)
    return len(self.areas)

  def read_area(self, scene: int, split: str) -> dict:
    """Reads and checks the meta file of one area.

    Args:
      scene: area index.
      split: "train" or "test".

    Returns:
      dict(keys=int64 (N, 3), image_paths=list[str], poses=float32 (N, 3) (x, y, yaw_rad)).

    Raises:
      DataError: see `read_meta`; also for a non-finite or out-of-range pose (naming the meta
        file and grid key) or a missing image file.
    """
    _check_split(split)
    area_dir = os.path.join(self.root, self.areas[scene])
    meta_path = os.path.join(area_dir, META_FILES[split])
    meta = read_meta(meta_path, split)
    lo, hi = self.xy_range
    for key, pose in zip(meta["keys"], meta["poses"], strict=True):
      if not np.all(np.isfinite(pose)):
        raise DataError(meta_path, f"key {tuple(key.tolist())}: non-finite pose {pose.tolist()}")
      if np.any(pose[:2] < lo) or np.any(pose[:2] > hi):
        raise DataError(
          meta_path,
          f"key {tuple(key.tolist())}: position {pose[:2].tolist()} m outside [{lo}, {hi}]",
        )
    paths = [os.path.join(area_dir, f) for f in meta["files"]]
    for p in paths:
      if not os.path.isfile(p):
        raise DataError(p, f"image listed in {META_FILES[split]} does not exist")
    return dict(keys=meta["keys"], image_paths=paths, poses=meta_to_poses(meta["poses"]))

  def grid_keys(self, split: str) -> list[np.ndarray]:
    """Per scene, the int64 (N, 3) grid keys aligned with the records' "view" index."""
    _check_split(split)
    return [
      read_meta(os.path.join(self.root, a, META_FILES[split]), split)["keys"] for a in self.areas
    ]

  def iter_views(self, split: str) -> Iterator[dict]:
    """Yields view records of `split`: areas in sorted order, views in grid-key order."""
    _check_split(split)
    for scene in range(len(self.areas)):
      area = self.read_area(scene, split)
      for view, (path, pose) in enumerate(zip(area["image_paths"], area["poses"], strict=True)):
        yield {
          "image": crop_and_resize(read_image(path), self.image_size),
          "pose": pose.copy(),
          "scene": scene,
          "view": view,
        }

"""SRN cars (Sitzmann et al.): instance folders of posed renders.

On-disk format (shared/reference/datasets_and_conventions.md, section 2b), one folder per car:

* `<instance>/rgb/NNNNNN.png`: RGB(A) render, white background (alpha is dropped).
* `<instance>/pose/NNNNNN.txt`: camera-to-world 4x4 in OpenCV camera axes, 16 numbers on one
  line (row-major) or 4 lines of 4.
* `<instance>/intrinsics.txt`: `f cx cy 0.` / `0. 0. 0.` / `1.` / `H W` (an optional fifth line
  is a world-to-camera flag).

Pose (authors' car code, the authors' code): from the camera centre c (translation column),
azimuth = atan2(c_y, c_x) wrapped to [0, 2 pi) and polar = arccos(c_z / |c|) in [0, pi]; the
rotation is not used (all cameras look at the origin). Intrinsics are read, validated and
rescaled to the output size although the paper never uses them.

Splits: each split is a folder of instances (`split_dirs`). The defaults follow the authors'
re-split: "train" = `cars_train`, "test" = `cars_train_test`, held-out views of the SAME cars,
whose sorted instance list must equal the training one because the per-scene embedding is
indexed by position. A split of novel cars (e.g. "test_scenes" = `cars_test`) may be added and
is indexed on its own.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator, Mapping

import numpy as np

from camrep import settings
from camrep.data.errors import DataError
from camrep.data.readers import textio
from camrep.data.readers.imageio import PathLike, check_image_size, crop_and_resize, read_image

DEFAULT_SPLIT_DIRS = {"train": "cars_train", "test": "cars_train_test"}
_STEM_RE = re.compile(r"^(\d+)\.(png|txt)$")
_TWO_PI = 2 * np.pi


def read_intrinsics(path: PathLike, *, image_size: int | None = None) -> dict:
  """Reads and validates an SRN `intrinsics.txt`, optionally rescaled to a crop-and-resize.

  Args:
    path: the intrinsics file.
    image_size: if given, (f, cx, cy) are moved to the centred square crop and scaled by
      image_size / crop side, as `crop_and_resize` does to the image.

  Returns:
    dict(focal=float, cx=float, cy=float, height=int, width=int, world2cam=bool), in pixels of the
    (rescaled) image.

  Raises:
    DataError: for a missing file or a line that does not match the format.
  """
  try:
    with open(path) as f:
      lines = [ln.split() for ln in f.read().splitlines() if ln.strip()]
  except OSError as e:
    raise DataError(path, f"cannot read intrinsics ({e.strerror or e})") from e
  want = "4 lines: 'f cx cy 0.', '0. 0. 0.', '1.', 'H W' (optional 5th: world2cam flag)"
  if len(lines) not in (4, 5) or [len(ln) for ln in lines[:4]] != [4, 3, 1, 2]:
    raise DataError(path, f"bad intrinsics format, expected {want}")
  try:
    f_, cx, cy, _ = (float(v) for v in lines[0])
    height, width = (int(float(v)) for v in lines[3])
    for v in lines[1] + lines[2]:
      float(v)
    world2cam = bool(int(float(lines[4][0]))) if len(lines) == 5 else False
  except (ValueError, IndexError) as e:
    raise DataError(path, f"bad intrinsics format, expected {want} ({e})") from e
  if not (np.isfinite([f_, cx, cy]).all() and f_ > 0 and height > 0 and width > 0):
    raise DataError(path, f"invalid intrinsics f={f_}, cx={cx}, cy={cy}, H={height}, W={width}")
  if image_size is not None:
    side = min(height, width)
    scale = image_size / side
    cx = (cx - (width - side) / 2) * scale
    cy = (cy - (height - side) / 2) * scale
    f_ *= scale
    height = width = int(image_size)
  return dict(focal=f_, cx=cx, cy=cy, height=height, width=width, world2cam=world2cam)


def read_pose(path: PathLike) -> np.ndarray:
  """Reads one `pose/NNNNNN.txt`: 16 numbers (one line, or 4 lines of 4), camera-to-world.

  Returns:
    (4, 4) float64 matrix.

  Raises:
    DataError: for a missing file, a count other than 16, or non-finite values.
  """
  return textio.read_matrix_4x4(path)


def c2w_to_angles(poses_c2w: np.ndarray) -> np.ndarray:
  """Camera-to-world matrices -> (azimuth, polar) of the camera centre on a z-up sphere.

  azimuth = atan2(c_y, c_x) mod 2 pi in [0, 2 pi); polar = arccos(c_z / |c|) in [0, pi].

  Args:
    poses_c2w: (..., 4, 4) (or (..., 3, 4)) matrices; only the translation column is used.

  Returns:
    (..., 2) float64 angles (radians).
  """
  return settings.CAR.poses_from_c2w(poses_c2w)


def list_instances(split_dir: PathLike) -> list[str]:
  """Sorted instance folder names of a split directory (folders holding `rgb/`).

  Raises:
    DataError: if the directory is missing or holds no instance folder.
  """
  d = os.fspath(split_dir)
  if not os.path.isdir(d):
    raise DataError(d, "SRN split directory does not exist")
  names = sorted(n for n in os.listdir(d) if os.path.isdir(os.path.join(d, n, "rgb")))
  if not names:
    raise DataError(d, "no SRN instance folders (<instance>/rgb/) found")
  return names


def _stems(d: str, ext: str) -> dict[str, str]:
  out = {}
  for name in os.listdir(d):
    m = _STEM_RE.match(name)
    if m is not None and m.group(2) == ext:
      out[m.group(1)] = os.path.join(d, name)
  return out


def read_instance(instance_dir: PathLike) -> dict:
  """Lists the views of one SRN instance and reads their poses and the intrinsics.

  Args:
    instance_dir: `<split>/<instance>`.

  Returns:
    dict(image_paths=list[str] sorted by view number, pose_paths=list[str] likewise,
         poses_c2w=(N, 4, 4) float64,
         intrinsics=dict as `read_intrinsics` without rescaling).

  Raises:
    DataError: for a missing `rgb/`, `pose/` or `intrinsics.txt`, an empty `rgb/`, an image
      without a pose (or the reverse), or a bad pose / intrinsics file.
  """
  d = os.fspath(instance_dir)
  rgb_dir, pose_dir = os.path.join(d, "rgb"), os.path.join(d, "pose")
  for sub in (rgb_dir, pose_dir):
    if not os.path.isdir(sub):
      raise DataError(sub, "SRN instance sub-directory does not exist")
  intrinsics = read_intrinsics(os.path.join(d, "intrinsics.txt"))
  images, poses = _stems(rgb_dir, "png"), _stems(pose_dir, "txt")
  if not images:
    raise DataError(rgb_dir, "no NNNNNN.png images")
  for stem in sorted(images.keys() ^ poses.keys()):
    if stem in images:
      raise DataError(images[stem], f"image has no pose file pose/{stem}.txt")
    raise DataError(poses[stem], f"pose has no image rgb/{stem}.png")
  stems = sorted(images, key=lambda s: (int(s), s))
  return dict(
    image_paths=[images[s] for s in stems],
    pose_paths=[poses[s] for s in stems],
    poses_c2w=np.stack([read_pose(poses[s]) for s in stems]),
    intrinsics=intrinsics,
  )


class SRNCars:
  """Reader for SRN cars: scene = instance (sorted folder names), view = render (sorted stems).

  Attributes:
    name: "srn_cars".
    pose_names: (azimuth, polar).
    image_size: side length of the records' images.
    splits: the split names (keys of `split_dirs`).
  """

  name = "srn_cars"
  pose_names = settings.CAR.pose_columns

  def __init__(
    self,
    root: PathLike,
    *,
    split_dirs: Mapping[str, str] = DEFAULT_SPLIT_DIRS,
    image_size: int = 128,
  ):
    """Initialises the reader and checks the split folders.

    Args:
      root: directory holding the split folders.
      split_dirs: split name -> folder under `root`. "test" must hold the same instances as
        "train" (held-out views of the training cars).
      image_size: output side length in pixels.

    Raises:
      DataError: for a missing / empty split folder, or a "test" instance list that differs
        from the "train" one.
    """
    self.root = os.fspath(root)
    self.split_dirs = {k: os.path.join(self.root, v) for k, v in split_dirs.items()}
    self.splits = tuple(self.split_dirs)
    self.image_size = int(image_size)
    self.instances = {k: list_instances(v) for k, v in self.split_dirs.items()}
    if "train" in self.instances and "test" in self.instances:
      train, test = self.instances["train"], self.instances["test"]
      if train != test:
        diff = sorted(set(train) ^ set(test))[:3]
        raise DataError(
          self.split_dirs["test"],
          f"instances differ from {self.split_dirs['train']} ({len(test)} vs {len(train)}, "
          f"e.g. {diff}); held-out views must be of the same cars",
        )

  def _check_split(self, split: str) -> None:
    if split not in self.split_dirs:
      raise ValueError(f"split must be one of {self.splits}, got {split!r}")

  def num_scenes(self, split: str) -> int:
    """Number of car instances in `split`."""
    self._check_split(split)
    return len(self.instances[split])

  def iter_views(self, split: str) -> Iterator[dict]:
    """Yields view records of `split`: instances in sorted order, views by number.

    Images must have the size given in the instance's `intrinsics.txt`; they are centre-cropped
    and resized with INTER_AREA.
    """
    self._check_split(split)
    for scene, inst in enumerate(self.instances[split]):
      data = read_instance(os.path.join(self.split_dirs[split], inst))
      hw = (data["intrinsics"]["height"], data["intrinsics"]["width"])
      centres = np.linalg.norm(data["poses_c2w"][:, :3, 3], axis=-1)
      at_origin = np.nonzero(centres == 0.0)[0]
      if at_origin.size:
        raise DataError(
          data["pose_paths"][at_origin[0]], "camera at the origin: azimuth and polar undefined"
        )
      angles = c2w_to_angles(data["poses_c2w"]).astype(np.float32)
      # An azimuth just below 2 pi may round up to 2 pi in float32; keep [0, 2 pi).
      angles[angles[:, 0] >= np.float32(_TWO_PI), 0] = 0.0
      for view, path in enumerate(data["image_paths"]):
        img = read_image(path)
        check_image_size(img, hw, path)
        yield {
          "image": crop_and_resize(img, self.image_size),
          "pose": angles[view],
          "scene": scene,
          "view": view,
        }

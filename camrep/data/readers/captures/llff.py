"""LLFF captures: `poses_bounds.npy` plus `images/` and its down-scaled copies `images_N/`.

Format (Mildenhall et al. 2019, LLFF `imgs2poses.py`; NeRF's `load_llff.py`):

* `poses_bounds.npy`: float array (N, 17). Row i: 15 numbers, a 3x5 matrix row-major
  `[R | t | hwf]` of image i, then its near and far depth bounds. R's columns are the camera's
  axes in LLFF's **(down, right, backwards)** order, t the camera centre (camera-to-world), and
  the last column (height, width, focal) of the FULL-resolution image in pixels.
* `images/`: the N images; image i is the i-th by sorted file name. `images_N/` holds them at 1/N
  of the size, so h, w and f scale by 1/N (as NeRF's loader, camrep takes the folder's actual
  size and checks it is within a pixel of hw / N). Principal point: the image centre.
* Optional `masks/`, `masks_N/`: one mask per image, same file stem, white = object (the shared
  museum captures carry them).

Axes: OpenCV camera axes from LLFF's are (x right, y down, z forward) = (R[:, 1], R[:, 0],
-R[:, 2]) (NeRF's loader makes OpenGL axes (R[:, 1], -R[:, 0], R[:, 2]) the same way).
"""

from __future__ import annotations

import os
import re

import numpy as np

from camrep.data.readers.captures import cameras
from camrep.data.readers.captures.cameras import (
  Capture,
  CaptureError,
  CountMismatchError,
  Frame,
  NonFinitePoseError,
)
from camrep.data.readers.imageio import PathLike

POSES_FILE = "poses_bounds.npy"
_FACTOR_RE = re.compile(r"^images_(\d+)$")


def is_capture(root: PathLike) -> bool:
  """Whether `root` holds a poses_bounds.npy."""
  return os.path.isfile(os.path.join(os.fspath(root), POSES_FILE))


def llff_to_opencv(r_llff: np.ndarray) -> np.ndarray:
  """(..., 3, 3) rotation with (down, right, back) columns -> (right, down, forward) columns."""
  r = np.asarray(r_llff, np.float64)
  return np.stack([r[..., :, 1], r[..., :, 0], -r[..., :, 2]], axis=-1)


def opencv_to_llff(r_cv: np.ndarray) -> np.ndarray:
  """Inverse of `llff_to_opencv`."""
  r = np.asarray(r_cv, np.float64)
  return np.stack([r[..., :, 1], r[..., :, 0], -r[..., :, 2]], axis=-1)


def image_folders(root: str) -> dict[int, str]:
  """{factor: folder} of the capture's `images` (factor 1) and `images_N` folders."""
  out = {}
  for name in os.listdir(root):
    if not os.path.isdir(os.path.join(root, name)):
      continue
    if name == "images":
      out[1] = name
    elif m := _FACTOR_RE.match(name):
      out[int(m.group(1))] = name
  return out


def read_poses_bounds(path: PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Reads `poses_bounds.npy`.

  Returns:
    c2w: (N, 4, 4) camera-to-world in OpenCV axes.
    hwf: (N, 3) full-resolution (height, width, focal).
    bounds: (N, 2) near, far.

  Raises:
    CaptureError: unreadable, or not (N, 17).
    NonFinitePoseError: NaN / infinite numbers.
    NotRigidError: a rotation block that is not a rotation.
  """
  try:
    arr = np.load(os.fspath(path), allow_pickle=False)
  except (OSError, ValueError) as e:
    raise CaptureError(path, f"cannot read ({e})") from None
  if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0:
    raise CaptureError(
      path, f"expected an (N, 17) array (3x5 [R|t|hwf] + near, far), got {arr.shape}"
    )
  arr = arr.astype(np.float64)
  bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
  if bad.size:
    raise NonFinitePoseError(path, f"row {bad[0]} holds non-finite values: {arr[bad[0]].tolist()}")
  m = arr[:, :15].reshape(-1, 3, 5)
  c2w = np.zeros((len(arr), 4, 4))
  c2w[:, :3, :3] = llff_to_opencv(m[:, :, :3])
  c2w[:, :3, 3] = m[:, :, 3]
  c2w[:, 3, 3] = 1.0
  for i in range(len(arr)):
    cameras.check_pose(c2w[i], path, f"row {i}")
  return c2w, m[:, :, 4], arr[:, 15:17]


def read_capture(root: PathLike, *, factor: int | None = None) -> Capture:
  """Reads an LLFF capture folder.

  Args:
    root: the folder holding `poses_bounds.npy`.
    factor: which `images_N` folder to read (1: `images/`); None: `images/` when present,
      else the only `images_N`, else the largest N (the smallest images).

  Raises:
    CaptureError: missing poses file or image folder, or a wrong array shape.
    CountMismatchError: images (or masks) and poses differ in number, or an image whose size is
      not the poses' hw / N.
    NonFinitePoseError, NotRigidError: as `read_poses_bounds`.
  """
  root = os.fspath(root)
  if not os.path.isdir(root):
    raise CaptureError(root, "capture folder does not exist")
  poses_file = os.path.join(root, POSES_FILE)
  if not os.path.isfile(poses_file):
    raise CaptureError(root, f"no {POSES_FILE} (not an LLFF capture)")
  c2w, hwf, bounds = read_poses_bounds(poses_file)
  folders = image_folders(root)
  if factor is None:
    if not folders:
      raise CaptureError(root, "no images/ or images_N/ folder")
    factor = 1 if 1 in folders else max(folders)
  factor = int(factor)
  if factor not in folders:
    raise CaptureError(root, f"no image folder for factor {factor} (found {sorted(folders)})")
  img_dir = os.path.join(root, folders[factor])
  names = cameras.list_images(img_dir)
  if len(names) != len(c2w):
    raise CountMismatchError(img_dir, f"{len(names)} images but {POSES_FILE} has {len(c2w)} poses")
  mask_dir = os.path.join(root, "masks" if factor == 1 else f"masks_{factor}")
  masks: dict[str, str] = {}
  if os.path.isdir(mask_dir):
    masks = {os.path.splitext(n)[0]: n for n in cameras.list_images(mask_dir)}
    missing = [n for n in names if os.path.splitext(n)[0] not in masks]
    if missing or len(masks) != len(names):
      raise CountMismatchError(
        mask_dir,
        f"{len(masks)} masks for {len(names)} images"
        + (f"; no mask for {missing[0]}" if missing else ""),
      )
  frames = []
  for i, name in enumerate(names):
    path = os.path.join(img_dir, name)
    h, w = cameras.image_size_of(path)
    full_h, full_w, f = hwf[i]
    if abs(h - full_h / factor) > 1.0 or abs(w - full_w / factor) > 1.0:
      raise CountMismatchError(
        path,
        f"image is {h}x{w} but {POSES_FILE} row {i} says {full_h:g}x{full_w:g} at full size, "
        f"{full_h / factor:g}x{full_w / factor:g} in {folders[factor]}/",
      )
    stem = os.path.splitext(name)[0]
    frames.append(
      Frame(
        name=name,
        image_path=path,
        c2w=c2w[i],
        fx=f / factor,
        fy=f / factor,
        cx=w / 2.0,
        cy=h / 2.0,
        width=w,
        height=h,
        mask_path=os.path.join(mask_dir, masks[stem]) if masks else None,
      )
    )
  return Capture(
    name=os.path.basename(os.path.normpath(root)),
    root=root,
    format="llff",
    frames=frames,
    bounds=bounds,
  )

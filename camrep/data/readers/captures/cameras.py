"""What every capture reader returns: frames with a camera-to-world pose in OpenCV axes.

Conventions (the one frame every reader converts to, so that the normalisation and the view
records need not know the source format):

* `Frame.c2w` is camera-to-world, 4x4, in **OpenCV camera axes** (x right, y down, z forward),
  the convention of SRN cars (`camrep.data.readers.srn`) and COLMAP. A world point p_w seen by the
  camera is p_cam = R^T (p_w - t) with c2w = [R | t].
* Intrinsics are in pixels of the image file as read (after any `images_N` down-scaling):
  focal lengths `fx`, `fy`, principal point `cx`, `cy`, size `width` x `height`.
* Distortion is OpenCV's coefficient vector (k1, k2, p1, p2, k3, k4, k5, k6), zeros when none;
  `load_frame_image` undistorts with `cv2.undistort` to the same camera matrix, or refuses.

The readers are `camrep.data.readers.captures.nerf`, `.llff` and `.colmap`;
`camrep.data.readers.captures.collection`
turns captures into view records.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence

import cv2
import numpy as np

from camrep.data.errors import DataError
from camrep.data.readers.imageio import PathLike

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr", ".bmp", ".tif", ".tiff", ".webp")
"""Image file extensions the readers look for (case-insensitive)."""

RIGID_TOL = 1e-3
"""Largest |R^T R - I| entry and |det R - 1| accepted for a pose's rotation block."""

N_DIST = 8


# ---------------------------------------------------------------------------------------------
# Named errors: each a DataError (message starts with the offending file).


class CaptureError(DataError):
  """A capture cannot be read as published."""


class MissingImageError(CaptureError):
  """A frame names an image (or mask) file that does not exist."""


class NotRigidError(CaptureError):
  """A pose matrix is not a rigid transform (rotation block not orthonormal, or bad last row)."""


class NonFinitePoseError(CaptureError):
  """A pose holds NaN or infinity."""


class UnknownCameraModelError(CaptureError):
  """A COLMAP / nerfstudio camera model camrep does not handle (fisheye, ...)."""


class CountMismatchError(CaptureError):
  """Poses and images (or masks) differ in number or names."""


class DistortionError(CaptureError):
  """A distorted camera that the caller asked not to undistort."""


class DuplicateFrameError(CaptureError):
  """One image file listed in two frames: twice, under two poses, or in two splits."""


# ---------------------------------------------------------------------------------------------
# Records.


@dataclasses.dataclass
class Frame:
  """One posed image of a capture.

  Attributes:
    name: the image's name within the capture (file name or the transforms.json file_path).
    image_path: the image file.
    c2w: (4, 4) float64 camera-to-world, OpenCV camera axes.
    fx, fy, cx, cy: intrinsics in pixels of the image file.
    width, height: the image file's size in pixels.
    distortion: (8,) float64 OpenCV coefficients (k1, k2, p1, p2, k3, k4, k5, k6).
    mask_path: an object mask (white = object), or None.
    split: the capture's own split of this frame ("train", "val", "test"), or None.
  """

  name: str
  image_path: str
  c2w: np.ndarray
  fx: float
  fy: float
  cx: float
  cy: float
  width: int
  height: int
  distortion: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(N_DIST))
  mask_path: str | None = None
  split: str | None = None

  @property
  def distorted(self) -> bool:
    return bool(np.any(self.distortion != 0.0))

  def camera_matrix(self) -> np.ndarray:
    """(3, 3) K."""
    return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclasses.dataclass
class Capture:
  """A capture: frames in a stable order (by file name, or the order of the split files), each
  a distinct image file (checked on construction, `check_distinct_frames`).

  Attributes:
    name: the capture's folder name.
    root: its folder.
    format: "nerf", "llff" or "colmap".
    frames: the posed images.
    points: (M, 3) sparse points in the world frame (COLMAP), or None.
    bounds: (N, 2) near / far depths per frame (LLFF), or None.
  """

  name: str
  root: str
  format: str
  frames: list[Frame]
  points: np.ndarray | None = None
  bounds: np.ndarray | None = None

  def __post_init__(self):
    check_distinct_frames(self)

  def c2w(self) -> np.ndarray:
    """(N, 4, 4) camera-to-world matrices of the frames."""
    return np.stack([f.c2w for f in self.frames])


# ---------------------------------------------------------------------------------------------
# Checks and conversions.


def check_distinct_frames(capture: Capture) -> None:
  """Refuses a capture that lists one image file in two frames (compared by resolved path).

  The same image under two poses gives it two labels; in two splits (Blender's train and test
  files), a held-out view also trains; twice in one split, it is weighted twice.

  Raises:
    DuplicateFrameError: naming every image listed more than once (up to 5) and its frames.
  """
  seen: dict[str, list[int]] = {}
  for i, f in enumerate(capture.frames):
    seen.setdefault(os.path.realpath(f.image_path), []).append(i)
  dups = [idx for idx in seen.values() if len(idx) > 1]
  if not dups:
    return
  parts = []
  for idx in dups[:5]:
    frames = [capture.frames[i] for i in idx]
    where = ", ".join(f"{f.name!r}" + (f" ({f.split})" if f.split else "") for f in frames)
    splits = {f.split for f in frames}
    poses = {np.asarray(f.c2w, np.float64).round(9).tobytes() for f in frames}
    if len(splits) > 1:
      why = "in two splits: a held-out view would also train"
    elif len(poses) > 1:
      why = "under different poses"
    else:
      why = "twice"
    parts.append(f"{os.path.basename(frames[0].image_path)} as {where} ({why})")
  more = f" and {len(dups) - 5} more" if len(dups) > 5 else ""
  raise DuplicateFrameError(
    capture.root,
    f"{len(dups)} image(s) listed in more than one frame: "
    + "; ".join(parts)
    + more
    + "; list each image once, in one split",
  )


def check_pose(m: np.ndarray, where: PathLike, what: str = "pose") -> np.ndarray:
  """Validates a camera-to-world matrix and returns it as (4, 4) float64.

  Args:
    m: (4, 4) or (3, 4) matrix.
    where: file named in errors.
    what: the pose's name in errors (e.g. "frame 3 transform_matrix").

  Raises:
    NonFinitePoseError: NaN or infinity.
    NotRigidError: wrong shape, a rotation block that is not orthonormal with det +1 (within
      `RIGID_TOL`), or a last row other than (0, 0, 0, 1).
  """
  try:
    m = np.asarray(m, dtype=np.float64)
  except (TypeError, ValueError) as e:
    raise NotRigidError(where, f"{what} is not a numeric matrix ({e})") from None
  if m.shape == (3, 4):
    m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]])
  if m.shape != (4, 4):
    raise NotRigidError(where, f"{what} must be 4x4 (or 3x4), got shape {m.shape}")
  if not np.all(np.isfinite(m)):
    raise NonFinitePoseError(where, f"{what} holds non-finite values: {m.tolist()}")
  rot = m[:3, :3]
  ortho = np.abs(rot.T @ rot - np.eye(3)).max()
  det = np.linalg.det(rot)
  last = np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max()
  if ortho > RIGID_TOL or abs(det - 1.0) > RIGID_TOL or last > RIGID_TOL:
    raise NotRigidError(
      where,
      f"{what} is not a rigid transform: |R^T R - I| = {ortho:.3g}, det R = {det:.6g}, last row "
      f"{m[3].tolist()} (camrep takes rotation + translation only; a scaled or sheared "
      "matrix would mis-pose every view)",
    )
  return m


def opengl_to_opencv(c2w_gl: np.ndarray) -> np.ndarray:
  """Camera-to-world in OpenGL / Blender / NeRF camera axes (x right, y up, z back) -> OpenCV
  axes (x right, y down, z forward): c2w_cv = c2w_gl diag(1, -1, -1, 1). Works on (..., 4, 4)."""
  return np.asarray(c2w_gl, np.float64) * np.array([1.0, -1.0, -1.0, 1.0])


def find_image(base: str, rel: str) -> str | None:
  """The image file `rel` under `base`, trying the known extensions when `rel` has none (Blender
  transforms name `./train/r_0`); None when absent."""
  path = os.path.normpath(os.path.join(base, rel))
  if os.path.isfile(path):
    return path
  if os.path.splitext(path)[1].lower() not in IMAGE_EXTENSIONS:
    for ext in IMAGE_EXTENSIONS:
      for cand in (path + ext, path + ext.upper()):
        if os.path.isfile(cand):
          return cand
  return None


def list_images(folder: str) -> list[str]:
  """Image file names in `folder`, sorted (LLFF / COLMAP order)."""
  return sorted(
    n
    for n in os.listdir(folder)
    if os.path.splitext(n)[1].lower() in IMAGE_EXTENSIONS and not n.startswith(".")
  )


def image_size_of(path: str) -> tuple[int, int]:
  """(height, width) of an image file (decoded)."""
  img = _read(path)
  return int(img.shape[0]), int(img.shape[1])


def _read(path: PathLike) -> np.ndarray:
  try:
    with open(path, "rb") as f:
      data = f.read()
  except OSError as e:
    raise MissingImageError(path, f"cannot read image file ({e.strerror or e})") from None
  buf = np.frombuffer(data, np.uint8)
  img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
  if img is None:
    raise CaptureError(path, f"cannot decode image ({len(data)} bytes)")
  if img.dtype == np.uint16:
    img = (img.astype(np.float32) / 257.0).round().astype(np.uint8)
  elif img.dtype != np.uint8:
    raise CaptureError(path, f"expected an 8- or 16-bit image, got {img.dtype}")
  return img


def parse_background(background: str | Sequence[int] | int) -> np.ndarray:
  """The background colour as uint8 RGB (3,): "white", "black", a grey level, or (r, g, b)."""
  named = {"white": (255, 255, 255), "black": (0, 0, 0), "grey": (128, 128, 128)}
  if isinstance(background, str):
    if background not in named:
      raise ValueError(
        f"background must be one of {sorted(named)} or (r, g, b), got {background!r}"
      )
    rgb = named[background]
  elif np.isscalar(background):
    rgb = (int(background),) * 3
  else:
    rgb = tuple(int(v) for v in background)
  if len(rgb) != 3 or not all(0 <= v <= 255 for v in rgb):
    raise ValueError(f"background must be 3 values in [0, 255], got {background!r}")
  return np.asarray(rgb, np.float32)


def load_frame_image(
  frame: Frame,
  *,
  background: np.ndarray,
  undistort: bool = True,
  use_mask: bool = True,
) -> np.ndarray:
  """The frame's image as uint8 RGB (height, width, 3): alpha and mask composited on
  `background`, then undistorted.

  Compositing: an RGBA image is alpha-blended onto the background (Blender renders); a mask
  (white = object, grey levels blend) keeps the object and replaces the rest by the background.

  Args:
    frame: the frame.
    background: (3,) RGB in [0, 255].
    undistort: undistort a distorted camera with `cv2.undistort` (same camera matrix); False
      refuses a distorted camera.
    use_mask: composite `frame.mask_path` when the frame has one.

  Raises:
    MissingImageError, CaptureError: unreadable image or mask, or a size other than the frame's.
    DistortionError: a distorted camera with `undistort` False.
  """
  img = _read(frame.image_path)
  if img.ndim == 2:
    img = np.repeat(img[:, :, None], 3, axis=2)
  if img.shape[:2] != (frame.height, frame.width):
    raise CountMismatchError(
      frame.image_path,
      f"image is {img.shape[0]}x{img.shape[1]} (HxW) but its camera says "
      f"{frame.height}x{frame.width}",
    )
  rgb = img[:, :, 2::-1].astype(np.float32) if img.shape[2] >= 3 else np.repeat(img, 3, 2)
  bg = np.asarray(background, np.float32).reshape(1, 1, 3)
  if img.shape[2] == 4:
    alpha = img[:, :, 3:4].astype(np.float32) / 255.0
    rgb = rgb * alpha + bg * (1.0 - alpha)
  if use_mask and frame.mask_path is not None:
    mask = _read(frame.mask_path)
    if mask.ndim == 3:
      mask = mask[:, :, 3] if mask.shape[2] == 4 else mask[:, :, :3].max(axis=2)
    if mask.shape[:2] != rgb.shape[:2]:
      raise CountMismatchError(
        frame.mask_path, f"mask is {mask.shape[:2]} but its image is {rgb.shape[:2]}"
      )
    m = mask.astype(np.float32)[:, :, None] / 255.0
    rgb = rgb * m + bg * (1.0 - m)
  out = np.clip(np.round(rgb), 0, 255).astype(np.uint8)
  if frame.distorted:
    if not undistort:
      raise DistortionError(
        frame.image_path,
        f"camera has distortion {frame.distortion.tolist()} (k1, k2, p1, p2, k3, ...) and "
        "undistortion is off; pass --config.undistort=True",
      )
    k = frame.camera_matrix()
    # Pixels that come from outside the source image take the background colour.
    out = cv2.undistort(out, k, frame.distortion, None, k)
    valid = cv2.undistort(np.full(out.shape[:2], 255, np.uint8), k, frame.distortion, None, k)
    out = np.where(valid[:, :, None] > 127, out, np.asarray(background, np.uint8))
  return np.ascontiguousarray(out)


def distortion_vector(
  *, k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0, k4=0.0, k5=0.0, k6=0.0
) -> np.ndarray:
  """OpenCV's (k1, k2, p1, p2, k3, k4, k5, k6) as (8,) float64."""
  return np.array([k1, k2, p1, p2, k3, k4, k5, k6], np.float64)

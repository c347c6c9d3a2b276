"""NeRF / instant-ngp / nerfstudio `transforms.json` captures.

Layouts read (Mildenhall et al. 2020; instant-ngp; nerfstudio's `ns-process-data` output):

* `DIR/transforms.json`: one file, every frame (no split of its own), or
* `DIR/transforms_{train,val,test}.json` (Blender / NeRF-synthetic): the capture's own splits.

Each file is a JSON object with `frames`, a list of `{"file_path": ..., "transform_matrix": 4x4}`
(camera-to-world in **OpenGL / Blender camera axes**: x right, y up, z backwards; converted to
OpenCV axes by c2w diag(1, -1, -1, 1)). `file_path` is relative to the JSON file and may omit the
extension (Blender's `./train/r_0` means `train/r_0.png`).

Intrinsics, at the top level and overridable per frame (instant-ngp and nerfstudio allow both):
`camera_angle_x` (horizontal field of view, radians: fx = w / (2 tan(angle_x / 2))) and
optionally `camera_angle_y`, or `fl_x`, `fl_y`, `cx`, `cy` in pixels; `w`, `h` (else read from the
image); distortion `k1`, `k2`, `k3`, `k4`, `p1`, `p2` (OpenCV's model). Fisheye cameras
(`is_fisheye`, nerfstudio `camera_model` OPENCV_FISHEYE, EQUIRECTANGULAR) are refused by name.
A frame's `mask_path` (nerfstudio) is composited like an LLFF mask. RGBA images (Blender) are
alpha-composited on the source's background colour when their view records are made.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np

from camrep.data.readers.captures import cameras
from camrep.data.readers.captures.cameras import (
  Capture,
  CaptureError,
  Frame,
  MissingImageError,
  UnknownCameraModelError,
)
from camrep.data.readers.imageio import PathLike

SPLIT_FILES = {
  "train": "transforms_train.json",
  "val": "transforms_val.json",
  "test": "transforms_test.json",
}
SINGLE_FILE = "transforms.json"
_INTRINSIC_KEYS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")
_DIST_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")


def is_capture(root: PathLike) -> bool:
  """Whether `root` holds a transforms.json or Blender's transforms_train.json."""
  root = os.fspath(root)
  return any(os.path.isfile(os.path.join(root, f)) for f in (SINGLE_FILE, SPLIT_FILES["train"]))


def _load_json(path: str) -> dict:
  try:
    with open(path) as f:
      data = json.load(f)
  except OSError as e:
    raise CaptureError(path, f"cannot read ({e.strerror or e})") from None
  except json.JSONDecodeError as e:
    raise CaptureError(path, f"not valid JSON ({e})") from None
  if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
    raise CaptureError(path, "expected a JSON object with a 'frames' list")
  if not data["frames"]:
    raise CaptureError(path, "'frames' is empty")
  return data


def _field_of_view(cam: dict, key: str, path: str, where: str) -> float:
  """`cam[key]`, a field of view in radians, checked to lie in (0, pi).

  Raises:
    CaptureError: 0, negative, pi or more, or not finite (fx = w / (2 tan(angle / 2)) would
      divide by zero or be negative).
  """
  angle = float(cam[key])
  if not (math.isfinite(angle) and 0.0 < angle < math.pi):
    raise CaptureError(
      path,
      f"{where}: {key}={cam[key]!r} is not a field of view in (0, pi) radians; give the "
      "camera's angle (e.g. 0.69 for 40 degrees) or its focal length in pixels (fl_x, fl_y)",
    )
  return angle


def _frame(path: str, i: int, top: dict, fr: dict, split: str | None) -> Frame:
  """One frame of a transforms file: top-level camera keys overridden by the frame's own."""
  where = f"frame {i}"
  if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
    raise CaptureError(path, f"{where} needs 'file_path' and 'transform_matrix'")
  cam = {
    k: top[k] for k in (*_INTRINSIC_KEYS, *_DIST_KEYS, "camera_model", "is_fisheye") if k in top
  }
  cam.update(
    {k: fr[k] for k in (*_INTRINSIC_KEYS, *_DIST_KEYS, "camera_model", "is_fisheye") if k in fr}
  )
  model = str(cam.get("camera_model", "OPENCV")).upper()
  if cam.get("is_fisheye") or model not in _PINHOLE_MODELS:
    raise UnknownCameraModelError(
      path,
      f"{where}: camera model {model!r}{' (is_fisheye)' if cam.get('is_fisheye') else ''} is "
      f"not handled; camrep reads pinhole cameras with OpenCV distortion ({_PINHOLE_MODELS})",
    )
  base = os.path.dirname(path)
  image = cameras.find_image(base, str(fr["file_path"]))
  if image is None:
    raise MissingImageError(
      os.path.join(base, str(fr["file_path"])), f"image of {where} of {path} does not exist"
    )
  mask = None
  if fr.get("mask_path"):
    mask = cameras.find_image(base, str(fr["mask_path"]))
    if mask is None:
      raise MissingImageError(os.path.join(base, str(fr["mask_path"])), f"mask of {where}")
  c2w = cameras.check_pose(fr["transform_matrix"], path, f"{where} transform_matrix")
  try:
    if "w" in cam and "h" in cam:
      w, h = int(cam["w"]), int(cam["h"])
    else:
      h, w = cameras.image_size_of(image)
    if "fl_x" in cam:
      fx = float(cam["fl_x"])
    elif "camera_angle_x" in cam:
      fx = 0.5 * w / math.tan(0.5 * _field_of_view(cam, "camera_angle_x", path, where))
    else:
      raise CaptureError(path, f"{where}: no focal length (camera_angle_x or fl_x)")
    if "fl_y" in cam:
      fy = float(cam["fl_y"])
    elif "camera_angle_y" in cam:
      fy = 0.5 * h / math.tan(0.5 * _field_of_view(cam, "camera_angle_y", path, where))
    else:
      fy = fx
    cx = float(cam.get("cx", w / 2.0))
    cy = float(cam.get("cy", h / 2.0))
    dist = cameras.distortion_vector(**{k: float(cam.get(k, 0.0)) for k in _DIST_KEYS})
  except (TypeError, ValueError) as e:
    raise CaptureError(path, f"{where}: bad camera value ({e})") from None
  if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0 and w > 0 and h > 0):
    raise CaptureError(path, f"{where}: invalid intrinsics fx={fx} fy={fy} w={w} h={h}")
  return Frame(
    name=str(fr["file_path"]),
    image_path=image,
    c2w=cameras.opengl_to_opencv(c2w),
    fx=fx,
    fy=fy,
    cx=cx,
    cy=cy,
    width=w,
    height=h,
    distortion=dist,
    mask_path=mask,
    split=split,
  )


def read_transforms_file(path: PathLike, *, split: str | None = None) -> list[Frame]:
  """The frames of one transforms JSON file, in file order.

  Raises:
    CaptureError and its subclasses: bad JSON, a missing image, a non-rigid or non-finite
      transform_matrix, a fisheye camera, missing intrinsics.
  """
  path = os.fspath(path)
  data = _load_json(path)
  return [_frame(path, i, data, fr, split) for i, fr in enumerate(data["frames"])]


def read_capture(root: PathLike) -> Capture:
  """Reads a NeRF-format capture folder (see the module docstring).

  Returns:
    A `Capture`; frames of Blender's split files carry their split ("train", "val", "test"),
    in the order train, val, test and file order within each.

  Raises:
    CaptureError: neither transforms.json nor transforms_train.json in `root`, or as
      `read_transforms_file`.
  """
  root = os.fspath(root)
  if not os.path.isdir(root):
    raise CaptureError(root, "capture folder does not exist")
  single = os.path.join(root, SINGLE_FILE)
  frames: list[Frame] = []
  if os.path.isfile(os.path.join(root, SPLIT_FILES["train"])):
    for split, name in SPLIT_FILES.items():
      f = os.path.join(root, name)
      if os.path.isfile(f):
        frames += read_transforms_file(f, split=split)
  elif os.path.isfile(single):
    frames = read_transforms_file(single)
  else:
    raise CaptureError(root, f"no {SINGLE_FILE} or {SPLIT_FILES['train']} (not a NeRF capture)")
  return Capture(
    name=os.path.basename(os.path.normpath(root)), root=root, format="nerf", frames=frames
  )

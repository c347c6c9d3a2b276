"""COLMAP sparse models: `cameras`, `images`, `points3D` in `.bin` or `.txt`.

Layout: `DIR/images/` (the photos) and `DIR/sparse/0/` (or `DIR/sparse/`, or `DIR` itself)
holding `cameras.bin`, `images.bin`, `points3D.bin` (or the `.txt` versions; `.bin` is read when
both exist). Formats as COLMAP writes them (`src/colmap/scene/reconstruction_io.cc`,
`scripts/python/read_write_model.py`), little-endian:

* cameras.bin: uint64 count; per camera int32 id, int32 model id, uint64 width, uint64 height,
  float64 params[model's count]. cameras.txt: `ID MODEL WIDTH HEIGHT PARAMS...`.
* images.bin: uint64 count; per image int32 id, float64 qw qx qy qz, float64 tx ty tz, int32
  camera id, NUL-terminated name, uint64 n, n x (float64 x, float64 y, int64 point3D id).
  images.txt: two lines per image, `ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` then its 2-D points
  (possibly an empty line).
* points3D.bin: uint64 count; per point uint64 id, float64 xyz[3], uint8 rgb[3], float64 error,
  uint64 track length, length x (int32 image id, int32 point2D index). points3D.txt: `ID X Y Z R
  G B ERROR TRACK...`.

Poses are **world-to-camera** with OpenCV camera axes: p_cam = R(q) p_world + t, q scalar-first;
camera-to-world is [R^T | -R^T t]. Camera models read: SIMPLE_PINHOLE (f, cx, cy), PINHOLE (fx,
fy, cx, cy), SIMPLE_RADIAL (f, cx, cy, k), RADIAL (f, cx, cy, k1, k2), OPENCV (fx, fy, cx, cy, k1,
k2, p1, p2) and FULL_OPENCV (+ k3, k4, k5, k6); fisheye and the other models are refused by name.
"""

from __future__ import annotations

import os
import struct

import numpy as np

from camrep.data.readers.captures import cameras
from camrep.data.readers.captures.cameras import (
  Capture,
  CaptureError,
  CountMismatchError,
  DuplicateFrameError,
  Frame,
  MissingImageError,
  NonFinitePoseError,
  UnknownCameraModelError,
)
from camrep.data.readers.imageio import PathLike

CAMERA_MODELS = {
  0: ("SIMPLE_PINHOLE", 3),
  1: ("PINHOLE", 4),
  2: ("SIMPLE_RADIAL", 4),
  3: ("RADIAL", 5),
  4: ("OPENCV", 8),
  5: ("OPENCV_FISHEYE", 8),
  6: ("FULL_OPENCV", 12),
  7: ("FOV", 5),
  8: ("SIMPLE_RADIAL_FISHEYE", 4),
  9: ("RADIAL_FISHEYE", 5),
  10: ("THIN_PRISM_FISHEYE", 12),
  11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
"""COLMAP's model ids -> (name, number of parameters)."""
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
_N_PARAMS = {name: n for name, n in CAMERA_MODELS.values()}


class _Reader:
  """Little-endian reads from a bytes buffer; running off the end is a CaptureError."""

  def __init__(self, path: str):
    self.path = path
    with open(path, "rb") as f:
      self.buf = f.read()
    self.pos = 0

  def read(self, fmt: str) -> tuple:
    size = struct.calcsize("<" + fmt)
    if self.pos + size > len(self.buf):
      raise CaptureError(self.path, f"truncated at byte {self.pos} (file has {len(self.buf)})")
    out = struct.unpack_from("<" + fmt, self.buf, self.pos)
    self.pos += size
    return out

  def name(self) -> str:
    end = self.buf.find(b"\x00", self.pos)
    if end < 0:
      raise CaptureError(self.path, f"unterminated image name at byte {self.pos}")
    s = self.buf[self.pos : end].decode("utf-8")
    self.pos = end + 1
    return s


def _model(path: str, model: int | str) -> tuple[str, int]:
  if isinstance(model, str):
    name = model.upper()
    if name not in _N_PARAMS:
      raise UnknownCameraModelError(path, f"unknown COLMAP camera model {model!r}")
  else:
    if model not in CAMERA_MODELS:
      raise UnknownCameraModelError(path, f"unknown COLMAP camera model id {model}")
    name = CAMERA_MODELS[model][0]
  return name, _N_PARAMS[name]


def read_cameras_bin(path: PathLike) -> dict[int, dict]:
  """{camera id: dict(model=str, width=int, height=int, params=(n,) float64)}."""
  r = _Reader(os.fspath(path))
  out = {}
  for _ in range(r.read("Q")[0]):
    cam_id, model_id, width, height = r.read("iiQQ")
    name, n = _model(r.path, model_id)
    out[cam_id] = dict(model=name, width=width, height=height, params=np.array(r.read(f"{n}d")))
  return out


def read_cameras_txt(path: PathLike) -> dict[int, dict]:
  """As `read_cameras_bin`, from cameras.txt."""
  path = os.fspath(path)
  out = {}
  for line in _lines(path):
    parts = line.split()
    name, n = _model(path, parts[1]) if len(parts) > 1 else ("", 0)
    if len(parts) != 4 + n:
      raise CaptureError(path, f"camera line {line!r}: expected ID MODEL W H and {n} params")
    try:
      out[int(parts[0])] = dict(
        model=name,
        width=int(parts[2]),
        height=int(parts[3]),
        params=np.array([float(v) for v in parts[4:]]),
      )
    except ValueError as e:
      raise CaptureError(path, f"camera line {line!r}: {e}") from None
  return out


def read_images_bin(path: PathLike) -> dict[int, dict]:
  """{image id: dict(qvec=(4,) wxyz, tvec=(3,), camera_id=int, name=str, num_points2d=int)}."""
  r = _Reader(os.fspath(path))
  out = {}
  for _ in range(r.read("Q")[0]):
    image_id, *qt, cam_id = r.read("i7di")
    name = r.name()
    n2d = r.read("Q")[0]
    r.pos += n2d * 24
    if r.pos > len(r.buf):
      raise CaptureError(r.path, f"truncated in the 2-D points of image {name!r}")
    _check_new_id(r.path, out, image_id, name)
    out[image_id] = dict(
      qvec=np.array(qt[:4]), tvec=np.array(qt[4:]), camera_id=cam_id, name=name, num_points2d=n2d
    )
  return out


def _check_new_id(path: str, images: dict[int, dict], image_id: int, name: str) -> None:
  """Refuses an image id listed twice (the second would silently replace the first)."""
  if image_id in images:
    raise DuplicateFrameError(
      path,
      f"image id {image_id} is listed twice ({images[image_id]['name']!r} and {name!r}): one "
      "registration would silently replace the other",
    )


def read_images_txt(path: PathLike) -> dict[int, dict]:
  """As `read_images_bin`, from images.txt (two lines per image; the second may be empty)."""
  path = os.fspath(path)
  with open(path) as f:
    lines = [ln.rstrip("\r\n") for ln in f if not ln.startswith("#")]
  out = {}
  i = 0
  while i < len(lines):
    if not lines[i].strip():
      i += 1
      continue
    parts = lines[i].split(maxsplit=9)
    if len(parts) != 10:
      raise CaptureError(
        path, f"image line {lines[i]!r}: expected ID QW QX QY QZ TX TY TZ CAM NAME"
      )
    try:
      image_id = int(parts[0])
    except ValueError as e:
      raise CaptureError(path, f"image line {lines[i]!r}: {e}") from None
    _check_new_id(path, out, image_id, parts[9].strip())
    try:
      vals = [float(v) for v in parts[1:8]]
      out[image_id] = dict(
        qvec=np.array(vals[:4]),
        tvec=np.array(vals[4:]),
        camera_id=int(parts[8]),
        name=parts[9].strip(),
        num_points2d=len((lines[i + 1] if i + 1 < len(lines) else "").split()) // 3,
      )
    except ValueError as e:
      raise CaptureError(path, f"image line {lines[i]!r}: {e}") from None
    i += 2
  return out


def read_points3d_bin(path: PathLike) -> np.ndarray:
  """(M, 3) float64 point positions."""
  r = _Reader(os.fspath(path))
  n = r.read("Q")[0]
  pts = np.empty((n, 3))
  for k in range(n):
    _, x, y, z, _, _, _, _, track = r.read("Q3d3BdQ")
    r.pos += track * 8
    pts[k] = (x, y, z)
  if r.pos > len(r.buf):
    raise CaptureError(r.path, "truncated in a point track")
  return pts


def read_points3d_txt(path: PathLike) -> np.ndarray:
  """(M, 3) float64 point positions, from points3D.txt."""
  path = os.fspath(path)
  pts = []
  for line in _lines(path):
    parts = line.split()
    try:
      pts.append([float(v) for v in parts[1:4]])
    except (ValueError, IndexError) as e:
      raise CaptureError(path, f"point line {line!r}: {e}") from None
  return np.asarray(pts, np.float64).reshape(-1, 3)


def _lines(path: str) -> list[str]:
  try:
    with open(path) as f:
      return [ln.strip() for ln in f if ln.strip() and not ln.startswith("#")]
  except OSError as e:
    raise CaptureError(path, f"cannot read ({e.strerror or e})") from None


def model_dir(root: PathLike) -> str:
  """The folder holding the sparse model: `root/sparse/0`, `root/sparse` or `root`."""
  root = os.fspath(root)
  for d in (os.path.join(root, "sparse", "0"), os.path.join(root, "sparse"), root):
    if any(os.path.isfile(os.path.join(d, f"cameras.{e}")) for e in ("bin", "txt")):
      return d
  raise CaptureError(
    root, "no COLMAP model (cameras.bin / cameras.txt in sparse/0, sparse or here)"
  )


def is_capture(root: PathLike) -> bool:
  """Whether `root` holds a COLMAP sparse model."""
  try:
    model_dir(root)
  except CaptureError:
    return False
  return True


def read_model(folder: PathLike) -> tuple[dict, dict, np.ndarray]:
  """(cameras, images, points) of a model folder, `.bin` preferred over `.txt`.

  Raises:
    CaptureError: a missing file of the model.
  """
  folder = os.fspath(folder)
  ext = "bin" if os.path.isfile(os.path.join(folder, "cameras.bin")) else "txt"
  readers = {
    "bin": (read_cameras_bin, read_images_bin, read_points3d_bin),
    "txt": (read_cameras_txt, read_images_txt, read_points3d_txt),
  }[ext]
  out = []
  for stem, reader in zip(("cameras", "images", "points3D"), readers, strict=True):
    f = os.path.join(folder, f"{stem}.{ext}")
    if not os.path.isfile(f):
      raise CaptureError(f, f"COLMAP model file missing ({stem}.{ext})")
    out.append(reader(f))
  return tuple(out)


def intrinsics(path: str, cam: dict) -> tuple[float, float, float, float, np.ndarray]:
  """(fx, fy, cx, cy, distortion (8,)) of a COLMAP camera.

  Raises:
    UnknownCameraModelError: a model other than `SUPPORTED_MODELS`.
  """
  model, p = cam["model"], cam["params"]
  dv = cameras.distortion_vector
  if model == "SIMPLE_PINHOLE":
    return p[0], p[0], p[1], p[2], dv()
  if model == "PINHOLE":
    return p[0], p[1], p[2], p[3], dv()
  if model == "SIMPLE_RADIAL":
    return p[0], p[0], p[1], p[2], dv(k1=p[3])
  if model == "RADIAL":
    return p[0], p[0], p[1], p[2], dv(k1=p[3], k2=p[4])
  if model == "OPENCV":
    return p[0], p[1], p[2], p[3], dv(k1=p[4], k2=p[5], p1=p[6], p2=p[7])
  if model == "FULL_OPENCV":
    return p[0], p[1], p[2], p[3], np.asarray(p[4:12], np.float64)
  raise UnknownCameraModelError(
    path, f"COLMAP camera model {model} is not handled; camrep reads {SUPPORTED_MODELS}"
  )


def quat_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
  """(3, 3) rotation of a scalar-first quaternion (normalised first)."""
  w, x, y, z = np.asarray(q_wxyz, np.float64) / np.linalg.norm(q_wxyz)
  return np.array(
    [
      [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
  )


def read_capture(root: PathLike, *, images_dir: str = "images") -> Capture:
  """Reads a COLMAP capture folder (frames sorted by image name).

  Args:
    root: the folder holding `images/` and the sparse model.
    images_dir: the photos' folder, relative to `root`.

  Raises:
    CaptureError: no model, a missing or truncated model file.
    UnknownCameraModelError: a camera model other than `SUPPORTED_MODELS`.
    MissingImageError: a registered image absent from `images_dir`.
    NonFinitePoseError: a NaN / infinite or zero quaternion or translation.
    CountMismatchError: an image whose camera id is not in cameras, or whose file size differs
      from its camera's.
  """
  root = os.fspath(root)
  if not os.path.isdir(root):
    raise CaptureError(root, "capture folder does not exist")
  folder = model_dir(root)
  cams, images, points = read_model(folder)
  img_root = os.path.join(root, images_dir)
  images_file = os.path.join(
    folder, "images.bin" if os.path.isfile(os.path.join(folder, "images.bin")) else "images.txt"
  )
  if not images:
    raise CaptureError(images_file, "the model registers no image")
  frames = []
  for im in sorted(images.values(), key=lambda d: d["name"]):
    where = f"image {im['name']!r}"
    q, t = im["qvec"], im["tvec"]
    if not (np.isfinite(q).all() and np.isfinite(t).all()) or np.linalg.norm(q) == 0:
      raise NonFinitePoseError(images_file, f"{where} has a bad pose q={q.tolist()} t={t.tolist()}")
    if im["camera_id"] not in cams:
      raise CountMismatchError(
        images_file,
        f"{where} uses camera {im['camera_id']}, which cameras lacks (has {sorted(cams)})",
      )
    cam = cams[im["camera_id"]]
    fx, fy, cx, cy, dist = intrinsics(folder, cam)
    path = os.path.join(img_root, im["name"])
    if not os.path.isfile(path):
      raise MissingImageError(path, f"{where} of the COLMAP model has no file in {img_root}")
    r_w2c = quat_to_matrix(q)
    c2w = np.eye(4)
    c2w[:3, :3] = r_w2c.T
    c2w[:3, 3] = -r_w2c.T @ t
    frames.append(
      Frame(
        name=im["name"],
        image_path=path,
        c2w=cameras.check_pose(c2w, images_file, where),
        fx=float(fx),
        fy=float(fy),
        cx=float(cx),
        cy=float(cy),
        width=int(cam["width"]),
        height=int(cam["height"]),
        distortion=dist,
      )
    )
  return Capture(
    name=os.path.basename(os.path.normpath(root)),
    root=root,
    format="colmap",
    frames=frames,
    points=points,
  )

"""Posed captures: NeRF transforms.json, LLFF and COLMAP readers, the object-centric
normalisation, splits, `prepare --source nerf|llff|colmap`, and the real-data path end to end.

Fixtures are written by code here, each format by an independent writer (the COLMAP `.bin` files
with `struct`, quaternions from scipy), around a rig of cameras whose true centre and up are
known. The real captures in ../shared/data/captures and the 7-Scenes stairs sample in
../shared/fixtures are used when present (skipped otherwise, as in a clone without ../shared).
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import shutil
import struct

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from camrep.data import prepare, records
from camrep.data.errors import DataError
from camrep.data.feed import pipeline, storage
from camrep.data.readers import srn
from camrep.data.readers.captures import cameras, colmap, llff, nerf, normalize
from camrep.data.readers.captures.cameras import (
  CountMismatchError,
  DistortionError,
  DuplicateFrameError,
  MissingImageError,
  NonFinitePoseError,
  NotRigidError,
  UnknownCameraModelError,
)
from camrep.data.readers.captures.collection import CaptureSource
from experiments import table1

pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]

ROOT = pathlib.Path(__file__).resolve().parents[1]
_SHARED = pathlib.Path(os.environ.get("CAMREP_SHARED", ROOT.parent / "shared"))
CAPTURES = _SHARED / "data" / "captures"
STAIRS = _SHARED / "fixtures" / "7scenes_stairs_sample"
needs_captures = pytest.mark.skipif(
  not (CAPTURES / "chair").is_dir(), reason=f"shared captures not at {CAPTURES}"
)
needs_stairs = pytest.mark.skipif(
  not (STAIRS / "stairs").is_dir(), reason=f"real 7-Scenes sample not at {STAIRS}"
)

H, W = 24, 32  # fixture image size (rows, columns)
CENTRE = np.array([0.3, -0.2, 0.5])


# ------------------------------------------------------------------------------- the rig


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
  """(4, 4) camera-to-world, OpenCV axes (x right, y down, z forward), looking at `target`."""
  z = target - eye
  z = z / np.linalg.norm(z)
  x = np.cross(z, up)
  x = x / np.linalg.norm(x)
  y = np.cross(z, x)
  m = np.eye(4)
  m[:3, :3] = np.stack([x, y, z], axis=1)
  m[:3, 3] = eye
  return m


def rig(n: int = 12, *, tilt: np.ndarray | None = None, radius: float = 3.0):
  """n cameras on two rings around CENTRE (elevations 20 and 40 degrees, even azimuths), up +z,
  then the whole rig rotated by `tilt` about CENTRE. Returns (c2w (n, 4, 4), elevations (n,))."""
  az = np.arange(n) * 2 * np.pi / n
  elev = np.radians(np.where(np.arange(n) % 2, 40.0, 20.0))
  up = np.array([0.0, 0.0, 1.0])
  out = []
  for a, e in zip(az, elev, strict=True):
    eye = CENTRE + radius * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    out.append(look_at(eye, CENTRE, up))
  c2w = np.stack(out)
  if tilt is not None:
    c2w[:, :3, :3] = tilt @ c2w[:, :3, :3]
    c2w[:, :3, 3] = (c2w[:, :3, 3] - CENTRE) @ tilt.T + CENTRE
  return c2w, elev


def write_png(path: pathlib.Path, rgb: np.ndarray) -> None:
  path.parent.mkdir(parents=True, exist_ok=True)
  bgr = rgb[..., [2, 1, 0, 3]] if rgb.shape[-1] == 4 else rgb[..., ::-1]
  assert cv2.imwrite(str(path), np.ascontiguousarray(bgr))


def noise(rng, h=H, w=W, c=3) -> np.ndarray:
  return rng.integers(0, 256, (h, w, c), dtype=np.uint8)


def gl(c2w_cv: np.ndarray) -> np.ndarray:
  """OpenCV -> OpenGL camera axes, written out independently of the reader's helper."""
  m = c2w_cv.copy()
  m[..., :3, 1] *= -1
  m[..., :3, 2] *= -1
  return m


def write_nerf(root: pathlib.Path, c2w: np.ndarray, *, rng, blender=False, rgba=False, **top):
  """A transforms.json capture (or Blender's transforms_{train,test}.json: every 4th view test)."""
  root.mkdir(parents=True, exist_ok=True)
  frames = {"train": [], "test": []} if blender else {"": []}
  for i, m in enumerate(c2w):
    split = ("test" if i % 4 == 0 else "train") if blender else ""
    rel = f"{split or 'images'}/r_{i}"
    write_png(root / f"{rel}.png", noise(rng, c=4 if rgba else 3))
    frames[split].append({"file_path": f"./{rel}", "transform_matrix": gl(m).tolist()})
  for split, fr in frames.items():
    name = f"transforms_{split}.json" if split else "transforms.json"
    (root / name).write_text(json.dumps({"camera_angle_x": 0.8, **top, "frames": fr}))
  return root


def write_llff(root: pathlib.Path, c2w: np.ndarray, *, rng, factor=4, masks=True, focal=30.0):
  """An LLFF capture: poses_bounds.npy at full size (factor x the images), images_N, masks_N."""
  root.mkdir(parents=True, exist_ok=True)
  rows = []
  for m in c2w:
    x, y, z = m[:3, 0], m[:3, 1], m[:3, 2]
    r_llff = np.stack([y, x, -z], axis=1)  # (down, right, back) columns
    hwf = np.array([[H * factor], [W * factor], [focal * factor]])
    mat = np.concatenate([r_llff, m[:3, 3:4], hwf], axis=1)  # 3 x 5
    rows.append(np.concatenate([mat.reshape(-1), [0.5, 6.0]]))
  np.save(root / "poses_bounds.npy", np.asarray(rows))
  sub = "images" if factor == 1 else f"images_{factor}"
  for i in range(len(c2w)):
    write_png(root / sub / f"IMG_{i:04d}.jpg.png", noise(rng))
    if masks:
      m = np.zeros((H, W), np.uint8)
      m[4:20, 8:24] = 255
      (root / f"masks_{factor}").mkdir(exist_ok=True)
      assert cv2.imwrite(str(root / f"masks_{factor}" / f"IMG_{i:04d}.jpg.png"), m)
  return root


COLMAP_MODELS = {"SIMPLE_PINHOLE": (0, 3), "PINHOLE": (1, 4), "SIMPLE_RADIAL": (2, 4),
                 "OPENCV": (4, 8), "OPENCV_FISHEYE": (5, 8)}  # fmt: skip


def prepared_llff(tmp: pathlib.Path, n_views: int = 40) -> str:
  """An LLFF capture of `n_views` views on `rig`, prepared with --preset small (64 px; every 8th
  view test) under `tmp`; returns the dataset directory."""
  root = write_llff(tmp / "obj", rig(n_views)[0], rng=np.random.default_rng(3))
  data = tmp / "data"
  prepare.prepare_source("llff", data, input_path=str(root), preset="small", progress=False)
  return str(data)


def colmap_params(model: str) -> list[float]:
  return {
    "SIMPLE_PINHOLE": [30.0, 16.0, 12.0],
    "PINHOLE": [30.0, 28.0, 15.5, 11.5],
    "SIMPLE_RADIAL": [30.0, 16.0, 12.0, 0.05],
    "OPENCV": [30.0, 31.0, 16.0, 12.0, 0.05, -0.01, 0.001, 0.002],
    "OPENCV_FISHEYE": [30.0, 31.0, 16.0, 12.0, 0.1, 0.0, 0.0, 0.0],
  }[model]


def w2c_of(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """COLMAP (qvec wxyz, tvec) of a camera-to-world matrix, via scipy."""
  r = m[:3, :3].T
  t = -r @ m[:3, 3]
  x, y, z, w = Rotation.from_matrix(r).as_quat()
  return np.array([w, x, y, z]), t


def write_colmap(root, c2w, *, rng, models=("PINHOLE",), text=False, model_id=None):
  """A COLMAP capture: images/ and sparse/0/{cameras,images,points3D}.{bin,txt}; camera k of
  `models` serves images k, k + len(models), ...; a few 2-D points and 3-D points with tracks."""
  sparse = root / "sparse" / "0"
  sparse.mkdir(parents=True, exist_ok=True)
  names = [f"frame_{i:03d}.png" for i in range(len(c2w))]
  for n in names:
    write_png(root / "images" / n, noise(rng))
  cams = [(k + 1, m) for k, m in enumerate(models)]
  pts = rng.normal(size=(5, 3)) * 0.2 + CENTRE
  ims = [(i + 1, *w2c_of(m), 1 + i % len(models), names[i]) for i, m in enumerate(c2w)]
  # Write images in an order other than by name (the reader sorts by name).
  ims = ims[::-1]
  if text:
    lines = ["# Camera list", *(f"{cid} {m} {W} {H} " + " ".join(map(str, colmap_params(m)))
                                for cid, m in cams)]  # fmt: skip
    (sparse / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:"]
    for iid, q, t, cid, name in ims:
      lines.append(f"{iid} " + " ".join(repr(float(v)) for v in [*q, *t]) + f" {cid} {name}")
      lines.append("" if iid % 2 else "1.5 2.5 1 3.5 4.5 -1")  # an empty points line too
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    lines = [f"{k + 1} {p[0]} {p[1]} {p[2]} 10 20 30 0.5 1 0 2 1" for k, p in enumerate(pts)]
    (sparse / "points3D.txt").write_text("# 3D point list\n" + "\n".join(lines) + "\n")
    return root
  buf = struct.pack("<Q", len(cams))
  for cid, m in cams:
    mid, n = COLMAP_MODELS[m]
    buf += struct.pack("<iiQQ", cid, mid if model_id is None else model_id, W, H)
    buf += struct.pack(f"<{n}d", *colmap_params(m))
  (sparse / "cameras.bin").write_bytes(buf)
  buf = struct.pack("<Q", len(ims))
  for iid, q, t, cid, name in ims:
    buf += struct.pack("<i4d3di", iid, *q, *t, cid) + name.encode() + b"\x00"
    buf += struct.pack("<Q", 2) + struct.pack("<ddq", 1.5, 2.5, 1) + struct.pack("<ddq", 3, 4, -1)
  (sparse / "images.bin").write_bytes(buf)
  buf = struct.pack("<Q", len(pts))
  for k, p in enumerate(pts):
    buf += struct.pack("<Q3d3BdQ", k + 1, *p, 10, 20, 30, 0.5, 2) + struct.pack("<iiii", 1, 0, 2, 1)
  (sparse / "points3D.bin").write_bytes(buf)
  return root


# ------------------------------------------------------------------------------- readers


def test_nerf_conventions_and_per_frame_intrinsics(tmp_path):
  rng = np.random.default_rng(0)
  c2w, _ = rig(8)
  root = write_nerf(tmp_path / "cap", c2w, rng=rng)
  data = json.loads((root / "transforms.json").read_text())
  data["frames"][1].update(fl_x=55.0, fl_y=54.0, cx=15.0, cy=11.0)  # per-frame override
  (root / "transforms.json").write_text(json.dumps(data))
  cap = nerf.read_capture(root)
  assert len(cap.frames) == 8 and all(f.split is None for f in cap.frames)
  np.testing.assert_allclose(cap.c2w(), c2w, atol=1e-12)  # OpenGL file -> OpenCV axes
  f0, f1 = cap.frames[:2]
  assert f0.image_path.endswith("images/r_0.png")  # extension-less file_path resolved
  fx = 0.5 * W / math.tan(0.4)  # camera_angle_x = 0.8, width read from the image
  assert (f0.fx, f0.fy, f0.cx, f0.cy, f0.width, f0.height) == pytest.approx((fx, fx, 16, 12, W, H))
  assert (f1.fx, f1.fy, f1.cx, f1.cy) == (55.0, 54.0, 15.0, 11.0)


def test_nerf_blender_splits_rgba_background(tmp_path):
  rng = np.random.default_rng(1)
  c2w, _ = rig(8)
  root = write_nerf(tmp_path / "chair", c2w, rng=rng, blender=True, rgba=True)
  for bg, want in (("white", 255), ("black", 0), ((10, 20, 30), [10, 20, 30])):
    src = CaptureSource(root, format="nerf", image_size=H, background=bg)
    assert src.splits == ("train", "test")
    assert (src.num_views("train"), src.num_views("test")) == (6, 2)
    rec = next(src.iter_views("test"))
    rgba = cv2.imread(src.captures[0].frames[6].image_path, cv2.IMREAD_UNCHANGED)  # r_0.png
    assert src.captures[0].frames[6].name == "./test/r_0" and rec["view"] == 0
    a = rgba[..., 3:4].astype(np.float64) / 255
    comp = rgba[..., 2::-1] * a + np.asarray(want, np.float64) * (1 - a)
    crop = comp[:, (W - H) // 2 : (W - H) // 2 + H]
    np.testing.assert_allclose(rec["image"], np.round(crop), atol=1)


def test_nerf_distortion_undistorted_or_refused(tmp_path):
  rng = np.random.default_rng(2)
  c2w, _ = rig(4)
  root = write_nerf(tmp_path / "cap", c2w, rng=rng, fl_x=30.0, k1=0.2, p1=0.01)
  cap = nerf.read_capture(root)
  f = cap.frames[0]
  np.testing.assert_allclose(f.distortion, [0.2, 0, 0.01, 0, 0, 0, 0, 0])
  white = cameras.parse_background("white")
  img = cameras.load_frame_image(f, background=white)
  raw = cv2.imread(f.image_path)[..., ::-1]
  k = f.camera_matrix()
  want = cv2.undistort(np.ascontiguousarray(raw), k, f.distortion, None, k)
  centre = (slice(8, 16), slice(10, 22))  # away from the border that comes from outside
  np.testing.assert_array_equal(img[centre], want[centre])
  assert not np.array_equal(img, raw)
  with pytest.raises(DistortionError, match="undistortion is off"):
    cameras.load_frame_image(f, background=white, undistort=False)
  with pytest.raises(DistortionError, match="r_0.png: 4 frame"):
    CaptureSource(root, format="nerf", image_size=8, undistort=False)
  fish = write_nerf(tmp_path / "fish", c2w, rng=rng, camera_model="OPENCV_FISHEYE")
  with pytest.raises(UnknownCameraModelError, match="OPENCV_FISHEYE"):
    nerf.read_capture(fish)


def test_llff_images_n_scaling_axes_and_masks(tmp_path):
  rng = np.random.default_rng(3)
  c2w, _ = rig(9)
  root = write_llff(tmp_path / "obj", c2w, rng=rng, factor=4)
  cap = llff.read_capture(root)
  np.testing.assert_allclose(cap.c2w(), c2w, atol=1e-12)
  f = cap.frames[0]
  assert (f.fx, f.fy, f.cx, f.cy, f.width, f.height) == (30.0, 30.0, W / 2, H / 2, W, H)
  assert f.mask_path.endswith("masks_4/IMG_0000.jpg.png") and cap.bounds.shape == (9, 2)
  img = cameras.load_frame_image(f, background=np.array([0.0, 0.0, 0.0]))
  assert img[0, 0].tolist() == [0, 0, 0] and img[:4].max() == 0  # outside the mask: background
  raw = cv2.imread(f.image_path)[..., ::-1]
  np.testing.assert_array_equal(img[4:20, 8:24], raw[4:20, 8:24])
  # A second, full-size folder: read by default; factor= picks the small one.
  (root / "images").mkdir()
  with pytest.raises(CountMismatchError, match="0 images but poses_bounds.npy has 9"):
    llff.read_capture(root)
  assert llff.read_capture(root, factor=4).frames[0].fx == 30.0
  # images_N that is not hw / N.
  os.rename(root / "images_4", root / "images_2")
  os.rmdir(root / "images")
  with pytest.raises(CountMismatchError, match=r"says 96x128 at full size, 48x64 in images_2"):
    llff.read_capture(root)


def _colmap_check(cap, c2w, models):
  assert [f.name for f in cap.frames] == sorted(f.name for f in cap.frames)
  np.testing.assert_allclose(cap.c2w(), c2w, atol=1e-10)
  for i, f in enumerate(cap.frames):
    model = models[i % len(models)]
    p = colmap_params(model)
    zeros = [0.0] * 8
    if model == "SIMPLE_PINHOLE":
      want = (p[0], p[0], p[1], p[2], zeros)
    elif model == "PINHOLE":
      want = (p[0], p[1], p[2], p[3], zeros)
    elif model == "SIMPLE_RADIAL":
      want = (p[0], p[0], p[1], p[2], [p[3]] + zeros[1:])
    else:  # OPENCV
      want = (p[0], p[1], p[2], p[3], [*p[4:8], 0, 0, 0, 0])
    assert (f.fx, f.fy, f.cx, f.cy) == want[:4]
    np.testing.assert_array_equal(f.distortion, want[4])
    assert (f.width, f.height) == (W, H)
  assert cap.points.shape == (5, 3)


@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
def test_colmap_models_and_world_to_camera(tmp_path, text):
  rng = np.random.default_rng(4)
  c2w, _ = rig(8)
  models = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "OPENCV")
  root = write_colmap(tmp_path / "scene", c2w, rng=rng, models=models, text=text)
  _colmap_check(colmap.read_capture(root), c2w, models)


def test_colmap_bin_and_txt_agree(tmp_path):
  c2w, _ = rig(6)
  models = ("OPENCV", "PINHOLE")
  a = colmap.read_capture(write_colmap(tmp_path / "a", c2w, rng=np.random.default_rng(5),
                                       models=models))  # fmt: skip
  b = colmap.read_capture(write_colmap(tmp_path / "b", c2w, rng=np.random.default_rng(5),
                                       models=models, text=True))  # fmt: skip
  np.testing.assert_allclose(a.c2w(), b.c2w(), atol=1e-12)
  np.testing.assert_allclose(a.points, b.points)


def test_colmap_unknown_camera_models(tmp_path):
  c2w, _ = rig(4)
  rng = np.random.default_rng(6)
  fish = write_colmap(tmp_path / "fish", c2w, rng=rng, models=("OPENCV_FISHEYE",))
  with pytest.raises(UnknownCameraModelError, match="OPENCV_FISHEYE is not handled"):
    colmap.read_capture(fish)
  odd = write_colmap(tmp_path / "odd", c2w, rng=rng, models=("PINHOLE",), model_id=42)
  with pytest.raises(UnknownCameraModelError, match="unknown COLMAP camera model id 42"):
    colmap.read_capture(odd)
  txt = write_colmap(tmp_path / "txt", c2w, rng=rng, models=("PINHOLE",), text=True)
  cams = (txt / "sparse/0/cameras.txt").read_text().replace("PINHOLE", "KANNALA_BRANDT")
  (txt / "sparse/0/cameras.txt").write_text(cams)
  with pytest.raises(UnknownCameraModelError, match="KANNALA_BRANDT"):
    colmap.read_capture(txt)


def test_bad_inputs_have_named_errors(tmp_path):
  rng = np.random.default_rng(7)
  c2w, _ = rig(6)
  # Missing image.
  root = write_nerf(tmp_path / "missing", c2w, rng=rng)
  os.remove(root / "images" / "r_3.png")
  with pytest.raises(MissingImageError, match="r_3: image of frame 3"):
    nerf.read_capture(root)
  # A transform_matrix that is not rigid (scaled rotation), and a NaN one.
  root = write_nerf(tmp_path / "scaled", c2w, rng=rng)
  data = json.loads((root / "transforms.json").read_text())
  m = np.asarray(data["frames"][2]["transform_matrix"])
  m[:3, :3] *= 2.0
  data["frames"][2]["transform_matrix"] = m.tolist()
  (root / "transforms.json").write_text(json.dumps(data))
  with pytest.raises(NotRigidError, match="frame 2 transform_matrix is not a rigid transform"):
    nerf.read_capture(root)
  data["frames"][2]["transform_matrix"] = np.full((4, 4), np.nan).tolist()
  (root / "transforms.json").write_text(json.dumps(data))
  with pytest.raises(NonFinitePoseError, match="frame 2 transform_matrix holds non-finite"):
    nerf.read_capture(root)
  # LLFF: NaN row, wrong shape, images vs poses counts, masks vs images.
  root = write_llff(tmp_path / "llff", c2w, rng=rng)
  good = np.load(root / "poses_bounds.npy")
  bad = good.copy()
  bad[4, 3] = np.nan
  np.save(root / "poses_bounds.npy", bad)
  with pytest.raises(NonFinitePoseError, match="row 4 holds non-finite"):
    llff.read_capture(root)
  np.save(root / "poses_bounds.npy", good[:, :15])
  with pytest.raises(DataError, match=r"expected an \(N, 17\) array"):
    llff.read_capture(root)
  np.save(root / "poses_bounds.npy", good[:5])
  with pytest.raises(CountMismatchError, match="6 images but poses_bounds.npy has 5 poses"):
    llff.read_capture(root)
  np.save(root / "poses_bounds.npy", good)
  os.remove(root / "masks_4" / "IMG_0002.jpg.png")
  with pytest.raises(CountMismatchError, match="5 masks for 6 images; no mask for IMG_0002"):
    llff.read_capture(root)
  # COLMAP: a registered image without its file, an image of an unknown camera.
  root = write_colmap(tmp_path / "colmap", c2w, rng=rng)
  os.remove(root / "images" / "frame_001.png")
  with pytest.raises(MissingImageError, match="frame_001.png"):
    colmap.read_capture(root)
  root = write_colmap(tmp_path / "colmap2", c2w, rng=rng, text=True)
  txt = (root / "sparse/0/images.txt").read_text().replace(" 1 frame_002.png", " 7 frame_002.png")
  (root / "sparse/0/images.txt").write_text(txt)
  with pytest.raises(CountMismatchError, match="uses camera 7, which cameras lacks"):
    colmap.read_capture(root)


# ------------------------------------------------------------------------------- normalisation


def test_normalisation_recentres_and_orients_a_tilted_rig(tmp_path):
  tilt = Rotation.from_rotvec([0.4, -0.3, 0.2]).as_matrix()
  c2w, elev = rig(12, tilt=tilt)
  norm, report = normalize.object_centric(c2w)
  np.testing.assert_allclose(norm.centre, CENTRE, atol=1e-9)
  assert report["residuals"]["angle_deg_max"] < 1e-6
  moved = norm.apply(c2w)
  up = -moved[:, :3, 1].mean(0)
  np.testing.assert_allclose(up / np.linalg.norm(up), [0, 0, 1], atol=1e-9)
  np.testing.assert_allclose(np.median(np.linalg.norm(moved[:, :3, 3], axis=1)), 1.0)
  src = CaptureSource(write_llff(tmp_path / "t", c2w, rng=np.random.default_rng(8)),
                      format="llff", holdout_every=0)  # fmt: skip
  polar = src.poses(0)[:, 1]
  np.testing.assert_allclose(polar, np.pi / 2 - elev, atol=1e-5)  # the rig's own elevations
  az = np.unwrap(src.poses(0)[:, 0].astype(np.float64))
  np.testing.assert_allclose(np.diff(az), 2 * np.pi / 12, atol=1e-5)


def test_round_trip_to_the_source_positions(tmp_path):
  """The positions in the source file, read independently, are recovered to 1e-5 from the
  normalised cameras and the normalisation recorded in the prepared dataset's metadata."""
  rng = np.random.default_rng(9)
  c2w, _ = rig(10, tilt=Rotation.from_rotvec([0.1, 0.5, -0.2]).as_matrix())
  c2w[:, :3, 3] += rng.normal(scale=0.05, size=(10, 3))  # not exactly object-centric
  root = write_nerf(tmp_path / "obj", c2w, rng=rng)
  path = prepare.prepare_source("nerf", tmp_path / "data", input_path=str(root),
                                overrides={"image_size": 16}, progress=False)  # fmt: skip
  meta = storage.load_metadata(path)
  info = meta["source_info"]["captures"][0]
  norm = normalize.Normalization.from_json(info["normalization"])
  frames = json.loads((root / "transforms.json").read_text())["frames"]
  source_positions = np.array([np.asarray(f["transform_matrix"])[:3, 3] for f in frames])
  src = CaptureSource(str(root), format="nerf", image_size=16)
  normalised = src.normalizations[0].apply(src.captures[0].c2w())
  np.testing.assert_allclose(norm.undo(normalised)[:, :3, 3], source_positions, atol=1e-5)
  np.testing.assert_allclose(norm.undo_points(normalised[:, :3, 3]), source_positions, atol=1e-5)
  # The records' (azimuth, polar) are those of the normalised positions.
  p = normalised[:, :3, 3]
  stored = storage.StoredSplit(path, "train").index
  want = np.stack([np.mod(np.arctan2(p[:, 1], p[:, 0]), 2 * np.pi),
                   np.arccos(p[:, 2] / np.linalg.norm(p, axis=1))], axis=1)  # fmt: skip
  np.testing.assert_allclose(stored.pose, want[stored.view], atol=1e-5)
  res = info["residuals"]
  assert 0 < res["angle_deg_median"] < 5 and len(info["angle_deg"]) == 10
  assert info["normalization"]["up_rule"] == "plane" and norm.up_rule == "plane"
  assert "independent of camera roll" in info["normalization"]["up_found_by"]


def test_not_object_centric_is_refused_or_routed_to_6dof(tmp_path):
  rng = np.random.default_rng(10)
  c2w = []
  for i in range(12):  # a forward-facing capture: a 3 x 4 grid of cameras all looking along +y
    eye = np.array([0.2 * (i % 4), 0.0, 0.15 * (i // 4)])
    c2w.append(look_at(eye, eye + [0.02 * (i % 3), 1.0, 0.01 * (i % 2)], np.array([0, 0, 1.0])))
  root = write_llff(tmp_path / "ff", np.stack(c2w), rng=rng)
  with pytest.raises(normalize.NotObjectCentricError, match="llff_6dof"):
    CaptureSource(root, format="llff")
  with pytest.raises(normalize.NotObjectCentricError):
    prepare.prepare_source("llff", tmp_path / "d", input_path=str(root), progress=False)
  path = prepare.prepare_source("llff_6dof", tmp_path / "d", input_path=str(root),
                                overrides={"image_size": 16}, progress=False)  # fmt: skip
  meta = storage.load_metadata(path)
  assert meta["pose_names"] == ["x", "y", "z", "theta", "phi", "psi"]
  train = storage.StoredSplit(path, "train").index.pose
  assert train[:, :3].min() >= -1e-6 and (train[:, :3].max(0) <= [4.0, 1.5, 3.0]).all()
  assert train[:, 0].max() == pytest.approx(4.0, abs=1e-5)  # scaled into the 7-Scenes cuboid
  # Several captures in the 6-DOF setting: the regression's scene naming takes a list of inputs.
  from camrep.regression import views as views_lib

  root2 = write_llff(tmp_path / "ff2", np.stack(c2w)[::-1].copy(), rng=rng)
  path = prepare.prepare_source("llff_6dof", tmp_path / "d2", input_path=[str(root), str(root2)],
                                overrides={"image_size": 16}, progress=False)  # fmt: skip
  meta = storage.load_metadata(path)
  assert meta["splits"]["train"]["num_scenes"] == 2
  assert views_lib.scene_names(meta) == []


def roll(c2w: np.ndarray, angles) -> np.ndarray:
  """Each camera turned by angles[i] about its own optical axis (OpenCV z): c2w R_z(angle)."""
  out = np.array(c2w, np.float64, copy=True)
  for i, a in enumerate(np.broadcast_to(angles, (len(c2w),))):
    rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    out[i, :3, :3] = out[i, :3, :3] @ rz
  return out


def labels(c2w: np.ndarray) -> tuple[np.ndarray, normalize.Normalization]:
  """(N, 2) float64 (azimuth, polar) of the car setting, and the normalisation."""
  norm, _ = normalize.object_centric(c2w)
  return srn.c2w_to_angles(norm.apply(c2w)), norm


def assert_same_labels(a: np.ndarray, b: np.ndarray, atol_deg: float = 1e-6) -> None:
  diff = np.degrees((a - b + np.pi) % (2 * np.pi) - np.pi)  # azimuths wrap
  assert np.abs(diff).max() < atol_deg, np.abs(diff).max(axis=0)


@pytest.mark.parametrize("tilted", [False, True])
def test_labels_do_not_depend_on_camera_roll(tilted):
  """Rolling any camera by any angle about its optical axis changes no label: the up direction
  comes from the camera centres (the normal of their plane), not from the cameras' up vectors."""
  tilt = Rotation.from_rotvec([0.4, -0.3, 0.2]).as_matrix() if tilted else None
  c2w, elev = rig(12, tilt=tilt)
  base, norm = labels(c2w)
  assert norm.up_rule == "plane" and norm.to_json()["up_rule"] == "plane"
  np.testing.assert_allclose(base[:, 1], np.pi / 2 - elev, atol=1e-9)  # the rig's own elevations
  rng = np.random.default_rng(20)
  for angles in (rng.uniform(0, 2 * np.pi, 12), np.pi / 2, np.where(np.arange(12) % 2, np.pi, 0)):
    rolled, norm = labels(roll(c2w, angles))
    assert_same_labels(rolled, base, atol_deg=1e-9)
    assert norm.up_rule == "plane"


def test_portrait_and_landscape_mix_and_captures_from_above(tmp_path):
  """Portrait photos (rolled +-90 deg) among landscape ones, through the LLFF reader: the same
  labels as all-landscape; a capture taken from above, every other camera upside down, keeps
  polar angles under 90 deg (the cameras' side of the plane is up)."""
  n = 16
  az = np.arange(n) * 2 * np.pi / n
  elev = np.radians(np.where(np.arange(n) % 2, 60.0, 75.0))
  eye = np.stack([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)], 1)
  c2w = np.stack([look_at(CENTRE + 2.0 * e, CENTRE, np.array([0.0, 0.0, 1.0])) for e in eye])
  rng = np.random.default_rng(21)
  landscape = CaptureSource(write_llff(tmp_path / "l", c2w, rng=rng), format="llff")
  portrait = roll(c2w, rng.choice([np.pi / 2, -np.pi / 2, 0.0], n))
  mixed = CaptureSource(write_llff(tmp_path / "p", portrait, rng=rng), format="llff")
  np.testing.assert_allclose(landscape.poses(0)[:, 1], np.pi / 2 - elev, atol=1e-6)
  np.testing.assert_array_max_ulp(mixed.poses(0), landscape.poses(0), maxulp=2)
  flipped = CaptureSource(
    write_llff(tmp_path / "f", roll(c2w, np.where(np.arange(n) % 2, np.pi, 0.0)), rng=rng),
    format="llff",
  )
  assert np.degrees(flipped.poses(0)[:, 1]).max() < 31.0  # from above: polar 15 and 30 deg
  assert flipped.describe()["captures"][0]["normalization"]["up_rule"] == "plane"


def test_up_fallbacks_are_named():
  """A ring at the object's height: the plane's sign comes from the cameras' up vectors; a
  forward-facing capture: the cameras' mean up vector. Both are recorded by name."""
  c2w = np.stack([
    look_at(CENTRE + 3.0 * np.array([np.cos(a), np.sin(a), 0.0]), CENTRE, np.array([0, 0, 1.0]))
    for a in np.arange(10) * 2 * np.pi / 10])  # fmt: skip
  up, info = normalize.up_direction(c2w, CENTRE)
  assert info["rule"] == "plane_signed_by_camera_up"
  np.testing.assert_allclose(up, [0, 0, 1], atol=1e-9)
  np.testing.assert_allclose(normalize.up_direction(roll(c2w, np.pi), CENTRE)[0], [0, 0, -1],
                             atol=1e-9)  # fmt: skip
  grid = []
  for i in range(12):  # forward-facing: a 3 x 4 grid of cameras looking along +y
    eye = np.array([0.2 * (i % 4), 0.0, 0.15 * (i // 4)])
    grid.append(look_at(eye, eye + [0.0, 1.0, 0.0], np.array([0, 0, 1.0])))
  up, info = normalize.up_direction(np.stack(grid), np.array([0.3, 20.0, 0.15]))
  assert info["rule"] == "mean_camera_up" and info["cap_deg"] < normalize.FORWARD_CAP_DEG
  np.testing.assert_allclose(up, [0, 0, 1], atol=1e-9)
  assert "depends on roll" in normalize.UP_RULES[info["rule"]]


def _rolled_copy(src: pathlib.Path, dst: pathlib.Path, rng) -> pathlib.Path:
  """`src` (a shared capture) with every camera rolled by a random angle; images linked."""
  dst.mkdir()
  for entry in src.iterdir():
    if entry.is_dir():
      os.symlink(entry, dst / entry.name)
  if (src / "poses_bounds.npy").exists():
    pb = np.load(src / "poses_bounds.npy")
    mats = pb[:, :15].reshape(-1, 3, 5)
    cv = llff.llff_to_opencv(mats[:, :, :3])
    c2w = np.tile(np.eye(4), (len(pb), 1, 1))
    c2w[:, :3, :3], c2w[:, :3, 3] = cv, mats[:, :, 3]
    c2w = roll(c2w, rng.uniform(0, 2 * np.pi, len(pb)))
    mats[:, :, :3] = llff.opencv_to_llff(c2w[:, :3, :3])
    np.save(dst / "poses_bounds.npy", np.concatenate([mats.reshape(-1, 15), pb[:, 15:]], 1))
    return dst
  for f in src.glob("transforms_*.json"):
    data = json.loads(f.read_text())
    for fr in data["frames"]:  # OpenGL axes: z is the optical axis (backwards) too
      m = np.asarray(fr["transform_matrix"], np.float64)
      fr["transform_matrix"] = roll(m[None], rng.uniform(0, 2 * np.pi))[0].tolist()
    (dst / f.name).write_text(json.dumps(data))
  return dst


@needs_captures
@pytest.mark.parametrize("fmt,name", [("nerf", "chair"), ("llff", "ethiopianHead"),
                                      ("llff", "moldGoldCape")])  # fmt: skip
def test_shared_captures_labels_survive_random_rolls(tmp_path, fmt, name):
  rolled = _rolled_copy(CAPTURES / name, tmp_path / name, np.random.default_rng(22))
  a = CaptureSource(str(CAPTURES / name), format=fmt, image_size=16)
  b = CaptureSource(str(rolled), format=fmt, image_size=16)
  np.testing.assert_allclose(b.captures[0].c2w()[:, :3, 3], a.captures[0].c2w()[:, :3, 3])
  assert not np.allclose(b.captures[0].c2w()[:, :3, :2], a.captures[0].c2w()[:, :3, :2])
  for src in (a, b):
    assert src.normalizations[0].up_rule == "plane"
  assert_same_labels(labels(b.captures[0].c2w())[0], labels(a.captures[0].c2w())[0])
  np.testing.assert_array_max_ulp(b.poses(0), a.poses(0), maxulp=2)  # the prepared (float32)


# ------------------------------------------------------------------------------- splits, prepare


def test_splits_every_kth_held_out_and_unseen_captures(tmp_path, capsys):
  rng = np.random.default_rng(11)
  a = write_llff(tmp_path / "a", rig(10)[0], rng=rng)
  b = write_colmap(tmp_path / "b", rig(7)[0], rng=rng)  # another format is refused below
  c = write_llff(tmp_path / "c", rig(6)[0], rng=rng)
  with pytest.raises(DataError, match="poses_bounds.npy"):
    CaptureSource([a, b], format="llff")
  argv = ["--source", "llff", "--input", str(a), "--input", str(c), "--data_dir",
          str(tmp_path / "d"), "--preset", "small", "--config.holdout_every=3",
          "--config.unseen=['c']", "--no_progress"]  # fmt: skip
  assert prepare.main(argv) == 0
  path = prepare.target_dir(tmp_path / "d", "llff", "small", storage.DEFAULT_VERSION)
  out = capsys.readouterr().out
  assert "Downloading and preparing" not in out and "wrote" in out  # tfds' banner is quiet
  assert path == tmp_path / "d" / "llff" / "small" / "1.0.0"
  meta = storage.load_metadata(path)
  assert meta["image_shape"] == [64, 64] and meta["metadata"]["input"] == [str(a), str(c)]
  assert {k: (v["num_scenes"], v["num_views"]) for k, v in meta["splits"].items()} == {
    "train": (1, 6), "test": (1, 4), "test_scenes": (1, 6)}  # fmt: skip
  test = storage.StoredSplit(path, "test").index
  assert sorted(test.view.tolist()) == [0, 3, 6, 9] and set(test.scene.tolist()) == {0}
  novel = storage.StoredSplit(path, "test_scenes").index
  assert set(novel.scene.tolist()) == {0} and sorted(novel.view.tolist()) == list(range(6))
  roles = [(x["name"], x["role"], x["split_rule"]) for x in meta["source_info"]["captures"]]
  assert roles == [
    (
      "a",
      "seen",
      "every 3rd view held out (it has no splits of its own; --config.holdout_every=3)",
    ),
    ("c", "unseen", "whole capture held out (--config.unseen)"),
  ]
  assert "  a (seen): train 6, test 4; every 3rd view held out" in out  # the summary says why


def test_too_few_scenes_and_missing_config_errors_name_the_fix(tmp_path):
  rng = np.random.default_rng(12)
  root = write_llff(tmp_path / "a", rig(8)[0], rng=rng)
  path = prepare.prepare_source("llff", tmp_path / "d", input_path=str(root),
                                overrides={"image_size": 16}, progress=False)  # fmt: skip
  stored = storage.StoredSplit(path, "train")
  cfg = pipeline.PipelineConfig(num_devices=1, scenes_per_device=8, views_per_scene=2)
  with pytest.raises(DataError, match=r"pass --config\.data\.scenes_per_device=1$"):
    pipeline.BatchPipeline(stored.index, stored.read_images, cfg, where=path)
  with pytest.raises(DataError, match=r"no config 'small'; it holds default \(no config\) at "
                     r"16x16 px.*--preset small.*--config\.data\.preset=default"):  # fmt: skip
    storage.dataset_dir(tmp_path / "d", "llff", config="small")


def test_one_image_in_two_frames_is_refused_by_name(tmp_path):
  rng = np.random.default_rng(13)
  c2w, _ = rig(8)
  root = write_nerf(tmp_path / "twice", c2w, rng=rng)
  data = json.loads((root / "transforms.json").read_text())
  frames = data["frames"]
  (root / "transforms.json").write_text(json.dumps({**data, "frames": [*frames, frames[5]]}))
  with pytest.raises(
    DuplicateFrameError, match=r"r_5.png as './images/r_5', './images/r_5' \(twice\)"
  ):
    nerf.read_capture(root)
  other = {**frames[5], "transform_matrix": frames[6]["transform_matrix"]}
  (root / "transforms.json").write_text(json.dumps({**data, "frames": [*frames, other]}))
  with pytest.raises(DuplicateFrameError, match=r"r_5.png .*\(under different poses\)"):
    nerf.read_capture(root)
  # Blender: a training image listed in the test file too.
  root = write_nerf(tmp_path / "blender", c2w, rng=rng, blender=True)
  test = json.loads((root / "transforms_test.json").read_text())
  train = json.loads((root / "transforms_train.json").read_text())
  test["frames"].append(train["frames"][0])
  (root / "transforms_test.json").write_text(json.dumps(test))
  with pytest.raises(DuplicateFrameError, match=r"r_1.png as './train/r_1' \(train\), "
                     r"'./train/r_1' \(test\) \(in two splits"):  # fmt: skip
    CaptureSource(root, format="nerf")
  # COLMAP: one image name under two ids, and one id listed twice.
  root = write_colmap(tmp_path / "colmap", c2w, rng=rng, text=True)
  lines = (root / "sparse/0/images.txt").read_text().splitlines()
  first = next(i for i, line in enumerate(lines) if line.endswith("frame_002.png"))
  again = lines[first].replace(lines[first].split()[0], "99", 1)
  (root / "sparse/0/images.txt").write_text("\n".join([*lines, again, ""]) + "\n")
  with pytest.raises(
    DuplicateFrameError, match="frame_002.png as 'frame_002.png', 'frame_002.png'"
  ):
    colmap.read_capture(root)
  again = lines[first].replace("frame_002.png", "frame_003.png")
  (root / "sparse/0/images.txt").write_text("\n".join([*lines, again, ""]) + "\n")
  with pytest.raises(DuplicateFrameError, match="image id 3 is listed twice"):
    colmap.read_capture(root)


def test_a_changed_capture_is_refused_by_name_until_overwritten(tmp_path, capsys):
  rng = np.random.default_rng(14)
  root = write_nerf(tmp_path / "obj", rig(12)[0], rng=rng)
  argv = ["--source=nerf", f"--input={root}", f"--data_dir={tmp_path / 'd'}", "--no_progress",
          "--config.image_size=8"]  # fmt: skip
  assert prepare.main(argv) == 0
  assert prepare.main(argv) == 0 and "reused" in capsys.readouterr().out
  data = json.loads((root / "transforms.json").read_text())
  (root / "transforms.json").write_text(json.dumps({**data, "frames": data["frames"][:10]}))
  assert prepare.main(argv) == 2
  err = capsys.readouterr().err
  assert "its inputs changed since it was prepared: obj: 10 frames, was 12; 2 frame(s) removed " \
         "(images/r_10.png, images/r_11.png)" in err and "--overwrite" in err  # fmt: skip
  (root / "transforms.json").write_text(json.dumps(data))
  assert prepare.main(argv) == 0  # the same inputs again: reused
  os.utime(root / "images" / "r_3.png", ns=(1, 1))
  assert prepare.main(argv) == 2
  assert "1 frame(s) changed (images/r_3.png)" in capsys.readouterr().err
  assert prepare.main([*argv, "--overwrite"]) == 0 and "wrote" in capsys.readouterr().out
  assert prepare.main(argv) == 0
  # A dataset prepared before inputs were recorded: reused with a warning, not silently.
  path = prepare.target_dir(tmp_path / "d", "nerf", None, storage.DEFAULT_VERSION)
  meta = storage.load_metadata(path)
  assert set(meta["inputs"]) == {"digest", "captures"}
  del meta["inputs"]
  (path / storage.METADATA_FILE).write_text(json.dumps(meta))
  assert prepare.main(argv) == 0
  assert "prepared before camrep recorded its inputs" in capsys.readouterr().err


def test_a_capture_without_held_out_views_is_refused_for_evaluation(tmp_path):
  rng = np.random.default_rng(15)
  a = write_nerf(tmp_path / "a", rig(8)[0], rng=rng, blender=True)  # its own test split
  b = write_nerf(tmp_path / "b", rig(8)[0], rng=rng)  # no split files
  overrides = {"image_size": 8, "holdout_every": 0}
  path = prepare.prepare_source(
    "nerf", tmp_path / "d", input_path=[str(a), str(b)], overrides=overrides, progress=False
  )
  storage.StoredSplit(path, "train")
  with pytest.raises(DataError, match=r"1 seen capture\(s\) have no held-out view in it: b "
                     r"\(every view trains .*--config.holdout_every=K"):  # fmt: skip
    storage.StoredSplit(path, "test")
  meta = storage.load_metadata(path)
  facts = records.naming(meta, {"test": "prepared test split (cars_train_test: ...)"})
  assert facts["scene_names"] == {"0": "a", "1": "b"}
  assert facts["splits"]["test"].startswith(
    "held-out views of the training captures (a: 2 views, its own test split; b: 0 views, every "
    "view trains"
  )
  errs = records.scene_name_column(facts, "test", np.array([1, 0, 1]))
  assert errs["scene_name"].tolist() == ["b", "a", "b"]


@needs_captures
def test_a_blender_capture_with_only_its_training_split_holds_out_views(tmp_path, capsys):
  """The shared chair without its val and test files: every 8th training view is held out, and
  the summary says how the test split was made."""
  root = tmp_path / "chair"
  root.mkdir()
  shutil.copy(CAPTURES / "chair" / "transforms_train.json", root)
  os.symlink(CAPTURES / "chair" / "train", root / "train")
  argv = ["--source=nerf", f"--input={root}", f"--data_dir={tmp_path / 'd'}", "--no_progress",
          "--config.image_size=8"]  # fmt: skip
  assert prepare.main(argv) == 0
  out = capsys.readouterr().out
  assert "  chair (seen): train 87, test 13; every 8th view held out (it has a training split " \
         "but no test split; --config.holdout_every=8)" in out  # fmt: skip
  path = prepare.target_dir(tmp_path / "d", "nerf", None, storage.DEFAULT_VERSION)
  test = storage.StoredSplit(path, "test").index
  assert sorted(test.view.tolist()) == list(range(0, 100, 8))


# ------------------------------------------------------------------------------- real captures


@needs_captures
@pytest.mark.parametrize("fmt,name", [("nerf", "chair"), ("llff", "ethiopianHead"),
                                      ("llff", "moldGoldCape")])  # fmt: skip
def test_shared_captures_are_object_centric(fmt, name):
  src = CaptureSource(str(CAPTURES / name), format=fmt, image_size=16)
  res = src.reports[0]["residuals"]
  assert res["angle_deg_median"] < 3.0 and res["angle_deg_max"] < 10.0, res
  c2w = src.captures[0].c2w()
  if fmt == "llff":  # round trip against the file, read here on its own
    pb = np.load(CAPTURES / name / "poses_bounds.npy")
    want = pb[:, :15].reshape(-1, 3, 5)[:, :, 3]
    assert len(src.captures[0].frames) == len(pb)
    assert all(f.mask_path for f in src.captures[0].frames)
  else:
    want = np.concatenate([
      [np.asarray(f["transform_matrix"])[:3, 3] for f in
       json.loads((CAPTURES / name / f"transforms_{s}.json").read_text())["frames"]]
      for s in ("train", "val", "test")])  # fmt: skip
    assert src.splits == ("train", "val", "test")
  back = src.normalizations[0].undo(src.normalizations[0].apply(c2w))
  np.testing.assert_allclose(back[:, :3, 3], want, atol=1e-5)


@needs_captures
def test_shared_capture_end_to_end(tmp_path):
  """prepare -> camrep.main (car, smoke) -> camrep.regression (ours, quat) -> table1."""
  from camrep.configs import regression as regression_config
  from camrep.configs import shapenet_car
  from camrep.regression import driver
  from camrep.synthesis import train as synthesis_train

  data = tmp_path / "data"
  argv = ["--source", "llff", "--input", str(CAPTURES / "ethiopianHead"), "--data_dir",
          str(data), "--preset", "small", "--no_progress"]  # fmt: skip
  assert prepare.main(argv) == 0
  c = shapenet_car.get_config("smoke")
  c.data.source, c.data.dir = "llff", str(data)  # preset "small": found without a flag
  c.total_steps, c.eval_every_steps = 1, 0  # evaluation off, to stay fast
  with pytest.raises(DataError, match=r"--config\.data\.scenes_per_device=1"):
    synthesis_train.train_and_evaluate(c, str(tmp_path / "syn_bad"))
  c.data.scenes_per_device = 1
  synthesis_train.train_and_evaluate(c, str(tmp_path / "syn"))
  for rep in ("ours", "quat"):
    r = regression_config.get_config("smoke")
    r.setting, r.representation = "car", rep
    r.data.source, r.data.dir = "llff", str(data)
    if rep == "ours":
      r.synthesis_workdir = str(tmp_path / "syn")
    results = driver.run(r, str(tmp_path / f"reg_{rep}"), log=lambda s: None)
    assert results["data"]["source"] == "llff" and results["data"]["num_test_views"] == 9
    # Results name their data: the capture, and how its test views were chosen.
    assert results["data"]["scene_names"] == {"0": "ethiopianHead"}
    assert results["data"]["splits"]["test"].startswith(
      "held-out views of the training captures (ethiopianHead: 9 views, every 8th view held out"
    )
    with np.load(tmp_path / f"reg_{rep}" / "errors_test.npz") as z:
      assert set(z["scene_name"].tolist()) == {"ethiopianHead"} and len(z["scene_name"]) == 9
  text = table1.build([json.loads((tmp_path / f"reg_{x}" / "results.json").read_text())
                       for x in ("ours", "quat")])  # fmt: skip
  assert "Table 1: pose regression on real data" in text and "Procedural columns" not in text
  assert "prepared `llff`" in text and "instances: ethiopianHead (9 test views: every 8th" in text


def test_capture_config_reads_a_default_prepared_capture(tmp_path):
  """`shapenet_car.py:capture` (128 px, one instance per step) validates against a capture
  prepared without a preset (128 px), and names the fix for a 64 px `--preset small` one."""
  from camrep.configs import shapenet_car
  from camrep.runtime import runconfig
  from camrep.synthesis import config_schema

  root = write_llff(tmp_path / "obj", rig(8)[0], rng=np.random.default_rng(16))
  prepare.prepare_source("llff", tmp_path / "d", input_path=str(root), progress=False)
  c = shapenet_car.get_config("capture")
  c.data.source, c.data.dir = "llff", str(tmp_path / "d")
  assert (c.model.image_size, c.data.scenes_per_device, c.data.preset) == (128, 1, "default")
  config_schema.validate(c)
  prepare.prepare_source("llff", tmp_path / "s", input_path=str(root), preset="small",
                         progress=False)  # fmt: skip
  c.data.dir = str(tmp_path / "s")
  with pytest.raises((runconfig.ConfigError, DataError), match="small"):
    config_schema.validate(c)


@needs_stairs
def test_readme_seven_scenes_command_prepares_the_stairs_sample(tmp_path):
  """The README's 7-Scenes prepare command with its defaults (margin included), then a regression
  smoke run on it."""
  from camrep.configs import regression as regression_config
  from camrep.regression import driver

  assert prepare.main(["--source", "seven_scenes", "--input", str(STAIRS), "--data_dir",
                       str(tmp_path / "tfds"), "--no_progress"]) == 0  # fmt: skip
  path = prepare.target_dir(tmp_path / "tfds", "seven_scenes", None, storage.DEFAULT_VERSION)
  meta = storage.load_metadata(path)
  assert meta["splits"]["test"]["num_views"] == 6  # the test frames 0.10 m outside are kept
  r = regression_config.get_config("smoke")
  r.setting, r.representation = "seven_scenes", "quat"
  r.data.source, r.data.dir = "seven_scenes", str(tmp_path / "tfds")
  results = driver.run(r, str(tmp_path / "reg"), log=lambda s: None)
  assert results["data"]["num_test_views"] == 6
  assert np.isfinite(results["test"]["all"]["position_error"]["mean"])

"""Writers of small fixtures in the exact on-disk formats of the real datasets.

Used by tests/test_readers.py (and usable by storage-layer tests): GQN TFRecords (framed by the
`tfrecord` package's own writer, an independent implementation of the masked CRC32C), SRN cars
instance folders, and Gibson area folders with pickled `*_meta.json` files.
"""

from __future__ import annotations

import os
import pickle

import cv2
import numpy as np
from tfrecord.writer import TFRecordWriter


def random_image(rng: np.random.Generator, h: int, w: int, channels: int = 3) -> np.ndarray:
  """Smooth random uint8 image (H, W, C) that survives JPEG compression recognisably."""
  small = rng.integers(0, 256, (max(h // 8, 1), max(w // 8, 1), channels), dtype=np.uint8)
  return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR).reshape(h, w, channels)


def encode(img_rgb: np.ndarray, ext: str) -> bytes:
  """Encodes an RGB(A) uint8 image as ".png" or ".jpg" bytes (OpenCV wants BGR)."""
  if img_rgb.shape[2] == 4:
    bgr = img_rgb[:, :, [2, 1, 0, 3]]
  else:
    bgr = img_rgb[:, :, ::-1]
  ok, buf = cv2.imencode(ext, np.ascontiguousarray(bgr))
  assert ok
  return buf.tobytes()


# ---------------------------------------------------------------------------------------------
# GQN


def gqn_scene(
  rng: np.random.Generator, *, views: int = 10, size: int = 64
) -> tuple[np.ndarray, np.ndarray]:
  """A random GQN-rooms-like scene: frames uint8 (V, size, size, 3), cameras float32 (V, 5).

  x, y in [-1, 1), z ~ 0.2, yaw in [-2 pi, 0] (the authors' assumed range), pitch small.
  """
  frames = np.stack([random_image(rng, size, size) for _ in range(views)])
  cameras = np.stack(
    [
      rng.uniform(-1, 1, views),
      rng.uniform(-1, 1, views),
      np.full(views, 0.2),
      rng.uniform(-2 * np.pi, 0, views),
      rng.uniform(-0.3, 0.3, views),
    ],
    axis=-1,
  ).astype(np.float32)
  return frames, cameras


def write_gqn_tfrecord(path: str | os.PathLike, scenes, *, jpeg_frames=None) -> None:
  """Writes scenes [(frames (V,H,W,3) uint8 RGB, cameras (V,5)), ...] as GQN tf.train.Examples.

  Args:
    path: output .tfrecord file.
    scenes: list of (frames, cameras).
    jpeg_frames: optional list (one per scene) of lists of raw bytes to store instead of
      encoding `frames` (to write corrupt JPEGs).
  """
  writer = TFRecordWriter(os.fspath(path))
  try:
    for i, (frames, cameras) in enumerate(scenes):
      if jpeg_frames is not None and jpeg_frames[i] is not None:
        blobs = list(jpeg_frames[i])
      else:
        blobs = [encode(f, ".jpg") for f in frames]
      writer.write(
        {
          "frames": (blobs, "byte"),
          "cameras": (np.asarray(cameras, np.float32).reshape(-1).tolist(), "float"),
        }
      )
  finally:
    writer.close()


# ---------------------------------------------------------------------------------------------
# SRN cars


def srn_pose(azimuth: float, polar: float, radius: float = 1.3) -> np.ndarray:
  """Camera-to-world (OpenCV axes: x right, y down, z forward) looking at the origin, z up."""
  c = radius * np.array(
    [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)]
  )
  forward = -c / np.linalg.norm(c)
  up = np.array([0.0, 0.0, 1.0])
  right = np.cross(forward, up)
  if np.linalg.norm(right) < 1e-8:
    right = np.array([1.0, 0.0, 0.0])
  right /= np.linalg.norm(right)
  down = np.cross(forward, right)
  m = np.eye(4)
  m[:3, :3] = np.stack([right, down, forward], axis=1)
  m[:3, 3] = c
  return m


def write_srn_instance(
  instance_dir: str | os.PathLike,
  rng: np.random.Generator,
  angles: np.ndarray,
  *,
  size: int = 128,
  rgba: bool = True,
  four_lines: bool = False,
) -> list[np.ndarray]:
  """Writes one SRN instance folder: rgb/NNNNNN.png, pose/NNNNNN.txt, intrinsics.txt.

  Args:
    instance_dir: output folder.
    rng: image noise source.
    angles: (V, 2) (azimuth, polar) of the cameras.
    size: image side (H = W).
    rgba: write RGBA PNGs (as the SRN renders) instead of RGB.
    four_lines: write the pose as 4 lines of 4 instead of one line of 16.

  Returns:
    The V RGB images written (alpha removed).
  """
  d = os.fspath(instance_dir)
  os.makedirs(os.path.join(d, "rgb"), exist_ok=True)
  os.makedirs(os.path.join(d, "pose"), exist_ok=True)
  f = 525.0 / 512.0 * size
  with open(os.path.join(d, "intrinsics.txt"), "w") as fh:
    fh.write(f"{f} {size / 2} {size / 2} 0.\n0. 0. 0.\n1.\n{size} {size}\n")
  images = []
  for v, (az, po) in enumerate(np.asarray(angles)):
    img = random_image(rng, size, size, 4 if rgba else 3)
    if rgba:
      img[..., 3] = 255
    with open(os.path.join(d, "rgb", f"{v:06d}.png"), "wb") as fh:
      fh.write(encode(img, ".png"))
    m = srn_pose(az, po)
    text = (
      "\n".join(" ".join(f"{x:.9f}" for x in row) for row in m)
      if four_lines
      else " ".join(f"{x:.9f}" for x in m.reshape(-1))
    )
    with open(os.path.join(d, "pose", f"{v:06d}.txt"), "w") as fh:
      fh.write(text + "\n")
    images.append(img[..., :3])
  return images


# ---------------------------------------------------------------------------------------------
# Gibson rooms


def write_gibson_area(
  area_dir: str | os.PathLike,
  rng: np.random.Generator,
  *,
  size: int = 128,
  grid: int = 2,
  test_per_key: int = 2,
) -> dict:
  """Writes one Gibson area: images and pickled train_meta.json / test_meta.json.

  Train holds one view per grid key (gx, gy, gtheta) in [0, grid)^2 x [0, 3); test holds
  `test_per_key` views per key. Positions are 0.05 m per grid step, yaw 10 deg per step.

  Returns:
    dict(train=the train meta dict, test=the test meta dict) as pickled.
  """
  d = os.fspath(area_dir)
  os.makedirs(os.path.join(d, "images"), exist_ok=True)
  train, test = {}, {}
  n = 0

  def add(key):
    nonlocal n
    rel = os.path.join("images", f"{n:05d}.png")
    with open(os.path.join(d, rel), "wb") as fh:
      fh.write(encode(random_image(rng, size, size), ".png"))
    n += 1
    pos = (
      0.05 * key[0] + rng.uniform(0, 0.05),
      0.05 * key[1] + rng.uniform(0, 0.05),
      10.0 * key[2],
    )
    return rel, pos

  keys = [(gx, gy, gt) for gt in range(3) for gy in range(grid) for gx in range(grid)]
  for key in keys:  # deliberately not sorted: the reader sorts.
    train[key] = add(key)
    test[key] = [add(key) for _ in range(test_per_key)]
  for name, meta in (("train_meta.json", train), ("test_meta.json", test)):
    with open(os.path.join(d, name), "wb") as fh:
      pickle.dump(meta, fh)
  return dict(train=train, test=test)

"""Image decoding and resizing shared by the real-dataset readers.

All readers hand out uint8 RGB images of shape (H, W, 3). Decoding goes through OpenCV (which
returns BGR/BGRA); these helpers convert, check, centre-crop and resize, and turn every failure
into a `DataError` that names the file.
"""

from __future__ import annotations

import os

import cv2
import numpy as np

from camrep.data.errors import DataError

PathLike = str | os.PathLike


def decode_image(data: bytes, path: PathLike) -> np.ndarray:
  """Decodes encoded image bytes (PNG, JPEG, ...) into RGB.

  Grey images are repeated to three channels and an alpha channel is dropped (not composited),
  as the authors' loaders do.

  Args:
    data: the encoded file contents.
    path: the file (or record) the bytes came from, used in error messages.

  Returns:
    uint8 (H, W, 3) RGB image.

  Raises:
    DataError: if the bytes cannot be decoded or are not 8-bit.
  """
  buf = np.frombuffer(data, dtype=np.uint8)
  img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
  if img is None:
    raise DataError(path, f"cannot decode image ({len(data)} bytes, corrupt or unknown format)")
  if img.dtype != np.uint8:
    raise DataError(path, f"expected an 8-bit image, got dtype {img.dtype}")
  if img.ndim == 2:
    return np.repeat(img[:, :, None], 3, axis=2)
  if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
    raise DataError(path, f"unsupported image shape {img.shape}")
  if img.shape[2] == 1:
    return np.repeat(img, 3, axis=2)
  return np.ascontiguousarray(img[:, :, 2::-1])


def read_image(path: PathLike, *, expected_hw: tuple[int, int] | None = None) -> np.ndarray:
  """Reads and decodes an image file into RGB.

  Args:
    path: image file.
    expected_hw: if given, the (height, width) the image must have.

  Returns:
    uint8 (H, W, 3) RGB image.

  Raises:
    DataError: if the file is missing, undecodable, or has the wrong size.
  """
  try:
    with open(path, "rb") as f:
      data = f.read()
  except OSError as e:
    raise DataError(path, f"cannot read image file ({e.strerror or e})") from e
  img = decode_image(data, path)
  check_image_size(img, expected_hw, path)
  return img


def check_image_size(img: np.ndarray, expected_hw: tuple[int, int] | None, path: PathLike) -> None:
  """Raises `DataError` naming `path` if `img` (H, W, C) is not `expected_hw` (None: no check)."""
  if expected_hw is not None and tuple(img.shape[:2]) != tuple(expected_hw):
    raise DataError(
      path,
      f"image is {img.shape[0]}x{img.shape[1]} (HxW), expected {expected_hw[0]}x{expected_hw[1]}",
    )


def center_crop_square(img: np.ndarray) -> np.ndarray:
  """Crops the largest centred square, (H, W, C) -> (S, S, C) with S = min(H, W)."""
  h, w = img.shape[:2]
  s = min(h, w)
  top, left = (h - s) // 2, (w - s) // 2
  return img[top : top + s, left : left + s]


def crop_and_resize(img: np.ndarray, size: int) -> np.ndarray:
  """Centre-crops to a square and resizes with `cv2.INTER_AREA`, as the authors' loaders do.

  Args:
    img: uint8 (H, W, 3) image.
    size: output side length in pixels.

  Returns:
    uint8 (size, size, 3) image (a copy when no resizing is needed).
  """
  sq = center_crop_square(img)
  if sq.shape[0] == size:
    return np.ascontiguousarray(sq)
  return cv2.resize(sq, (size, size), interpolation=cv2.INTER_AREA)

"""Image grids for logs and figures: uint8 conversion, labelled grids, error maps and the
view-synthesis grid (context | target | prediction | error) the train loop writes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import cv2
import jax
import numpy as np

Array = jax.Array


def to_uint8(image: Any, *, value_range: tuple[float, float] = (-1.0, 1.0)) -> np.ndarray:
  """Converts an image to uint8 RGB.

  Args:
    image: (H, W), (H, W, 1) or (H, W, 3) array; uint8 is kept as is, floats are mapped linearly
      from `value_range` to [0, 255], clipped and rounded.
    value_range: (low, high) of float inputs; camrep images are in [-1, 1].

  Returns:
    (H, W, 3) uint8 array.
  """
  image = np.asarray(image)
  if image.ndim == 3 and image.shape[-1] == 1:
    image = image[..., 0]
  if image.ndim == 2:
    image = np.repeat(image[..., None], 3, axis=-1)
  if image.ndim != 3 or image.shape[-1] != 3:
    raise ValueError(f"expected an (H, W[, 1 or 3]) image, got {image.shape}")
  if image.dtype == np.uint8:
    return image
  lo, hi = value_range
  scaled = (np.asarray(image, np.float64) - lo) / (hi - lo) * 255.0
  return np.clip(np.round(np.nan_to_num(scaled, nan=0.0)), 0, 255).astype(np.uint8)


def _draw_label(canvas: np.ndarray, text: str, x: int, y: int, width: int, height: int) -> None:
  """Draws black text into the box (x, y, width, height) of an RGB uint8 canvas, cut to fit."""
  font, scale, thick = cv2.FONT_HERSHEY_SIMPLEX, max(0.3, height / 40.0), 1
  while text and cv2.getTextSize(text, font, scale, thick)[0][0] > width:
    text = text[:-1]
  if text:
    (_, th), _ = cv2.getTextSize(text, font, scale, thick)
    baseline_y = y + (height + th) // 2
    cv2.putText(canvas, text, (x, baseline_y), font, scale, (0, 0, 0), thick, cv2.LINE_AA)


def image_grid(
  rows: Sequence[Sequence[Any]],
  *,
  labels: Sequence[str] | None = None,
  pad: int = 2,
  value_range: tuple[float, float] = (-1.0, 1.0),
) -> np.ndarray:
  """Tiles images into one uint8 picture on a white background.

  Every cell has the size of the largest image; smaller images sit at its top left, short rows
  are left blank at the end.

  Args:
    rows: Rows of images, each (H, W[, 1 or 3]), uint8 or float in `value_range`.
    labels: Optional column titles, drawn in a header strip above the first row.
    pad: White pixels between cells and around the border.
    value_range: Range of float images (camrep images are in [-1, 1]).

  Returns:
    (H_grid, W_grid, 3) uint8 RGB image.
  """
  cells = [[to_uint8(im, value_range=value_range) for im in row] for row in rows]
  if not cells or not any(cells):
    raise ValueError("image_grid needs at least one image")
  h = max(im.shape[0] for row in cells for im in row)
  w = max(im.shape[1] for row in cells for im in row)
  n_cols = max(len(row) for row in cells)
  if labels is not None:
    n_cols = max(n_cols, len(labels))
  header = 0 if not labels else max(12, min(24, h // 4))
  grid = np.full(
    (header + len(cells) * (h + pad) + pad, n_cols * (w + pad) + pad, 3), 255, np.uint8
  )
  for j, text in enumerate(labels or ()):
    _draw_label(grid, str(text), pad + j * (w + pad), 0, w, header)
  for i, row in enumerate(cells):
    y = header + pad + i * (h + pad)
    for j, im in enumerate(row):
      x = pad + j * (w + pad)
      grid[y : y + im.shape[0], x : x + im.shape[1]] = im
  return grid


def error_image(pred: Any, target: Any, *, gain: float = 4.0) -> np.ndarray:
  """Colour-mapped absolute error of two [-1, 1] images.

  err = mean over RGB of |pred - target| / 2 (the error in [0, 1] units), times `gain`, clipped
  to [0, 1] and shown with the inferno colour map: black = exact, yellow-white = error >= 1/gain.
  The fixed gain keeps grids from different steps comparable.

  Args:
    pred: (H, W, 3) float image in [-1, 1].
    target: (H, W, 3) float image in [-1, 1].
    gain: Error amplification.

  Returns:
    (H, W, 3) uint8 RGB image.
  """
  pred = np.asarray(pred, np.float32)
  target = np.asarray(target, np.float32)
  err = np.mean(np.abs(pred - target), axis=-1) / 2.0
  gray = np.clip(np.nan_to_num(err * gain, nan=1.0) * 255.0, 0, 255).round().astype(np.uint8)
  return cv2.cvtColor(cv2.applyColorMap(gray, cv2.COLORMAP_INFERNO), cv2.COLOR_BGR2RGB)


def _as_float_images(x: Any) -> np.ndarray:
  x = np.asarray(x)
  if x.dtype == np.uint8:
    return x.astype(np.float32) / 127.5 - 1.0
  return x.astype(np.float32)


def view_synthesis_grid(
  context: Any,
  target: Any,
  prediction: Any,
  *,
  max_scenes: int = 4,
  error_gain: float = 4.0,
) -> np.ndarray:
  """Eval figure: one row per (scene, query): context views | target | prediction | |error|.

  Args:
    context: (S, C, H, W, 3) context images, float in [-1, 1] or uint8.
    target: (S, Q, H, W, 3) ground-truth query images.
    prediction: (S, Q, H, W, 3) synthesised query images.
    max_scenes: Show at most this many scenes (the first ones).
    error_gain: See `error_image`; the last column title says the gain.

  Returns:
    (H_grid, W_grid, 3) uint8 RGB image with S' * Q rows and C + 3 columns.
  """
  context = _as_float_images(context)
  target = _as_float_images(target)
  prediction = _as_float_images(prediction)
  if context.ndim != 5 or target.ndim != 5 or target.shape != prediction.shape:
    raise ValueError(
      f"expected context (S,C,H,W,3), target and prediction (S,Q,H,W,3); got "
      f"{context.shape}, {target.shape}, {prediction.shape}"
    )
  if context.shape[0] != target.shape[0]:
    raise ValueError(f"scene counts differ: {context.shape[0]} vs {target.shape[0]}")
  n_context = context.shape[1]
  rows = []
  for s in range(min(max_scenes, context.shape[0])):
    for q in range(target.shape[1]):
      err = error_image(prediction[s, q], target[s, q], gain=error_gain)
      rows.append([*context[s], target[s, q], prediction[s, q], err])
  labels = [f"ctx {i}" for i in range(n_context)]
  labels += ["target", "prediction", f"|err|x{error_gain:g}"]
  return image_grid(rows, labels=labels)

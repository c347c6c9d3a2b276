"""Plots drawn with OpenCV alone (no matplotlib): line plots with axes and legends, heat maps,
PNG output. Used by the noise-robustness figure, Gram maps and the experiments.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import cv2
import jax
import numpy as np

Array = jax.Array


_FONT = cv2.FONT_HERSHEY_SIMPLEX


_BLACK = (0, 0, 0)


def _text(img, text, org, *, scale=0.45, color=_BLACK, thickness=1, anchor="left"):
  """Draws text with its baseline at org[1]; anchor "left", "center" or "right" in x."""
  (w, _), _ = cv2.getTextSize(text, _FONT, scale, thickness)
  x, y = org
  if anchor == "center":
    x -= w // 2
  elif anchor == "right":
    x -= w
  cv2.putText(img, text, (int(x), int(y)), _FONT, scale, color, thickness, cv2.LINE_AA)


def _nice_ticks(lo: float, hi: float, n: int = 6) -> np.ndarray:
  """About n round tick values; the first <= lo, the last >= hi."""
  if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
    hi = lo + 1.0
  raw = (hi - lo) / max(n - 1, 1)
  mag = 10 ** math.floor(math.log10(raw))
  step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
  first, last = math.floor(lo / step + 1e-9), math.ceil(hi / step - 1e-9)
  return step * np.arange(first, last + 1)


def _fmt(v: float, step: float) -> str:
  decimals = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 0
  decimals += 1 if abs(round(step * 10**decimals) - step * 10**decimals) > 1e-6 else 0
  return f"{v:.{decimals}f}"


SERIES_COLORS = ((31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14))


def line_plot(
  x: Sequence[float] | np.ndarray,
  y: Sequence[float] | np.ndarray | Mapping[str, Sequence[float]],
  *,
  title: str,
  xlabel: str,
  ylabel: str,
  size: tuple[int, int] = (560, 420),
  color: tuple[int, int, int] = (31, 119, 180),
) -> np.ndarray:
  """A line plot with markers, axes, ticks, grid, labels and a title.

  Args:
    x: (n,) values.
    y: (n,) values, or {label: (n,) values} for several series with a legend (colours from
      `SERIES_COLORS`); non-finite values are left out.
    size: (width, height) in pixels.
    color: RGB line colour of a single series.

  Returns:
    (height, width, 3) uint8 RGB image.
  """
  x = np.asarray(x, np.float64)
  series = (
    {k: np.asarray(v, np.float64) for k, v in y.items()}
    if isinstance(y, Mapping)
    else {"": np.asarray(y, np.float64)}
  )
  colors = (
    dict(zip(series, SERIES_COLORS * 4, strict=False)) if isinstance(y, Mapping) else {"": color}
  )
  width, height = size
  img = np.full((height, width, 3), 255, np.uint8)
  left, right, top, bottom = 70, 20, 40, 55
  pw, ph = width - left - right, height - top - bottom
  every = np.concatenate(list(series.values()))
  ok = np.isfinite(every)
  ylo, yhi = (float(every[ok].min()), float(every[ok].max())) if ok.any() else (0.0, 1.0)
  pad = 0.08 * (yhi - ylo) if yhi > ylo else max(abs(yhi) * 0.05, 0.05)
  yt = _nice_ticks(ylo - pad, yhi + pad)
  xt = _nice_ticks(float(x.min()), float(x.max()))
  x0, x1 = min(xt[0], x.min()), max(xt[-1], x.max())
  y0, y1 = yt[0], yt[-1]
  px = lambda v: left + (v - x0) / (x1 - x0 or 1.0) * pw
  py = lambda v: top + ph - (v - y0) / (y1 - y0 or 1.0) * ph
  for v in xt:
    X = round(px(v))
    cv2.line(img, (X, top), (X, top + ph), (225, 225, 225), 1)
    cv2.line(img, (X, top + ph), (X, top + ph + 5), _BLACK, 1)
    _text(img, _fmt(v, xt[1] - xt[0]), (X, top + ph + 20), anchor="center")
  for v in yt:
    Y = round(py(v))
    cv2.line(img, (left, Y), (left + pw, Y), (225, 225, 225), 1)
    cv2.line(img, (left - 5, Y), (left, Y), _BLACK, 1)
    _text(img, _fmt(v, yt[1] - yt[0]), (left - 8, Y + 5), anchor="right")
  cv2.rectangle(img, (left, top), (left + pw, top + ph), _BLACK, 1)
  for i, (label, yv) in enumerate(series.items()):
    ok = np.isfinite(yv)
    c = colors[label]
    pts = np.array([[px(a), py(b)] for a, b in zip(x[ok], yv[ok], strict=True)])
    if len(pts):
      pts_i = np.round(pts).astype(np.int32)
      cv2.polylines(img, [pts_i.reshape(-1, 1, 2)], False, c, 2, cv2.LINE_AA)
      for p in pts_i:
        cv2.circle(img, (int(p[0]), int(p[1])), 4, c, -1, cv2.LINE_AA)
    if label:  # legend, top right inside the axes
      ly = top + 18 + 20 * i
      cv2.line(img, (left + pw - 150, ly - 4), (left + pw - 125, ly - 4), c, 2, cv2.LINE_AA)
      _text(img, label, (left + pw - 118, ly))
  _text(img, title, (width // 2, 25), scale=0.6, anchor="center")
  _text(img, xlabel, (left + pw // 2, height - 12), scale=0.5, anchor="center")
  # Rotated y label: draw horizontally on a strip, rotate, paste left of the tick labels.
  (tw, th), _ = cv2.getTextSize(ylabel, _FONT, 0.5, 1)
  strip = np.full((th + 8, min(tw + 4, ph)), 255, np.uint8)
  cv2.putText(strip, ylabel, (2, th + 2), _FONT, 0.5, 0, 1, cv2.LINE_AA)
  strip = cv2.rotate(strip, cv2.ROTATE_90_COUNTERCLOCKWISE)
  ys = top + (ph - strip.shape[0]) // 2
  img[ys : ys + strip.shape[0], 4 : 4 + strip.shape[1]] = strip[..., None]
  return img


def heat_map(
  m: np.ndarray,
  *,
  title: str,
  caption: str = "",
  min_size: int = 400,
  max_size: int = 1024,
  colormap: int = cv2.COLORMAP_VIRIDIS,
) -> np.ndarray:
  """A (K, K) matrix as a colour-mapped image with a title, caption and colour bar.

  Small matrices are upscaled by an integer factor (nearest neighbour, so cells stay sharp) to at
  least `min_size` pixels; larger than `max_size` ones are shrunk (area averaging).

  Returns:
    uint8 RGB image.
  """
  m = np.asarray(m, np.float64)
  lo, hi = float(np.nanmin(m)), float(np.nanmax(m))
  span = hi - lo if hi > lo else 1.0
  gray = np.clip(np.round((np.nan_to_num(m, nan=lo) - lo) / span * 255), 0, 255).astype(np.uint8)
  K = max(m.shape)
  if K > max_size:
    side = (max_size * m.shape[1] // K, max_size * m.shape[0] // K)
    gray = cv2.resize(gray, side, interpolation=cv2.INTER_AREA)
  else:
    f = max(1, math.ceil(min_size / K))
    gray = cv2.resize(gray, (m.shape[1] * f, m.shape[0] * f), interpolation=cv2.INTER_NEAREST)
  body = cv2.applyColorMap(gray, colormap)  # BGR
  h, w = body.shape[:2]
  top, bottom, bar_w, right = 40, 40 if caption else 16, 18, 80
  img = np.full((top + h + bottom, 16 + w + 16 + bar_w + right, 3), 255, np.uint8)
  img[top : top + h, 16 : 16 + w] = body
  ramp = np.linspace(255, 0, h).round().astype(np.uint8)[:, None].repeat(bar_w, axis=1)
  bx = 16 + w + 16
  img[top : top + h, bx : bx + bar_w] = cv2.applyColorMap(ramp, colormap)
  cv2.rectangle(img, (bx, top), (bx + bar_w - 1, top + h - 1), _BLACK, 1)
  ticks = _nice_ticks(lo, hi, 5)
  ticks = ticks[(ticks >= lo - 1e-9) & (ticks <= hi + 1e-9)]
  step = ticks[1] - ticks[0] if len(ticks) > 1 else span
  for v in ticks:
    Y = round(top + (hi - v) / span * (h - 1))
    cv2.line(img, (bx + bar_w, Y), (bx + bar_w + 4, Y), _BLACK, 1)
    _text(img, _fmt(v, step), (bx + bar_w + 7, min(max(Y + 5, top + 10), top + h)))
  rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
  _text(rgb, title, (16, 27), scale=0.6)
  if caption:
    _text(rgb, caption, (16, top + h + 26), scale=0.45)
  return rgb


def write_png(path: str, rgb: np.ndarray) -> None:
  ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
  if not ok:
    raise RuntimeError(f"PNG encoding of {path} failed")
  with open(path, "wb") as f:
    f.write(png.tobytes())

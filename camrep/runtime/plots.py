"""Figures drawn with matplotlib: curves with a band over seeds, and Gram maps with pose ticks,
written as PNG and PDF twins. Used by the noise-robustness figure, learning curves and Gram maps
(`camrep.synthesis.evaluate`, experiments/noise_figure.py, experiments/learning_curve.py).

matplotlib's object interface only (no pyplot, no global backend): `Figure` renders through Agg
for PNG and its PDF backend for PDF, in any process and thread. The training loop's image grids
stay OpenCV (`camrep.runtime.grids`).
"""

from __future__ import annotations

import math
import os
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

# Colours of successive series (matplotlib's tab10, so a label keeps its colour across panels);
# past the tenth series the colours repeat with the next line style and marker, so no two series
# of a panel look alike (Table 1 has nine representations, a noise figure more inputs).
COLORS = (
  "tab:blue", "tab:red", "tab:green", "tab:purple", "tab:orange",
  "tab:brown", "tab:gray", "tab:pink", "tab:olive", "tab:cyan",
)  # fmt: skip
LINESTYLES = ("-", "--", ":", "-.")
MARKERS = ("o", "s", "^", "D")
PANEL_SIZE = (4.6, 3.4)  # inches, one panel; PNGs at DPI dots per inch
DPI = 120


def series_style(i: int) -> dict[str, str]:
  """Colour, line style and marker of the i-th series of a panel (distinct for i < 40)."""
  k = (i // len(COLORS)) % len(LINESTYLES)
  return {"color": COLORS[i % len(COLORS)], "linestyle": LINESTYLES[k], "marker": MARKERS[k]}


@dataclass(frozen=True)
class Panel:
  """One panel of curves against a shared x.

  series: {label: (n,) values, or (seeds, n) values of several seeds}; several seeds are drawn
    as their mean with a band from their minimum to their maximum. Points where no seed is
    finite are left out (the line joins their neighbours).
  bands: {label: ((n,) low, (n,) high, seeds)}: a band given as it is (e.g. read back from a
    table of means and ranges, where `series` holds the (n,) means), drawn instead of the
    seeds' range and named "mean of <seeds> seeds".
  """

  title: str
  ylabel: str
  series: Mapping[str, np.ndarray]
  xlabel: str = ""
  bands: Mapping[str, tuple] = field(default_factory=dict)


def _as_seeds(values) -> np.ndarray:
  """(seeds, n) float64 from (n,) or (seeds, n) values."""
  a = np.asarray(values, np.float64)
  return a[None] if a.ndim == 1 else a


def mean_and_band(values) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
  """(mean, low, high, seeds) over the seeds axis, ignoring non-finite seeds per point.

  Args:
    values: (n,) or (seeds, n).

  Returns:
    mean, low (min over seeds), high (max over seeds), each (n,) (NaN where no seed is finite),
    and the number of seeds.
  """
  a = _as_seeds(values)
  ok = np.isfinite(a)
  count = ok.sum(axis=0)
  filled = np.where(ok, a, 0.0)
  with np.errstate(invalid="ignore", divide="ignore"):
    mean = np.where(count > 0, filled.sum(axis=0) / np.maximum(count, 1), np.nan)
  low = np.where(count > 0, np.where(ok, a, np.inf).min(axis=0), np.nan)
  high = np.where(count > 0, np.where(ok, a, -np.inf).max(axis=0), np.nan)
  return mean, low, high, a.shape[0]


def _series_name(label: str, values, seeds: int, ok: np.ndarray) -> str:
  """A series' legend entry: "<label> (mean of <seeds> seeds)", or "(mean of the <lo>-<seeds>
  seeds logged at each step)" where some seeds have no value at a drawn point (runs that stopped
  before the others)."""
  if seeds <= 1:
    return label
  logged = np.isfinite(_as_seeds(values)).sum(axis=0)[ok]
  lo = int(logged.min()) if logged.size else seeds
  if lo == seeds:
    return f"{label} (mean of {seeds} seeds)"
  return f"{label} (mean of the {lo}-{seeds} seeds logged at each step)"


def curves_figure(x, panels: Sequence[Panel], *, suptitle: str = "") -> Figure:
  """Panels side by side, one line per series (markers at the points), a band where a series
  has several seeds. Panels that plot the same series share one legend below them, where it
  cannot cover a curve; otherwise each panel has its own, placed where it covers the fewest
  points."""
  x = np.asarray(x, np.float64)
  w, h = PANEL_SIZE
  # A long title is wrapped to the figure's width (~13 characters an inch at its font size).
  width = max(20, int(13 * w * len(panels)))
  title = [t for line in suptitle.splitlines() for t in textwrap.wrap(line, width)]
  fig = Figure(figsize=(w * len(panels), h + 0.2 * len(title)), layout="constrained")
  axes = fig.subplots(1, len(panels), squeeze=False)[0]
  for ax, panel in zip(axes, panels, strict=True):
    for i, (label, values) in enumerate(panel.series.items()):
      mean, low, high, seeds = mean_and_band(values)
      ok = np.isfinite(mean)
      if label in panel.bands:
        low, high, seeds = panel.bands[label]
        low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
        name = f"{label} (mean of {seeds} seeds)" if seeds > 1 else label
      else:
        name = _series_name(label, values, seeds, ok)
      style = series_style(i)
      ax.plot(x[ok], mean[ok], markersize=3.5, linewidth=1.6, label=name or None, **style)
      if seeds > 1:
        ax.fill_between(x[ok], low[ok], high[ok], color=style["color"], alpha=0.2, linewidth=0)
    ax.set_title(panel.title, fontsize=10)
    ax.set_xlabel(panel.xlabel)
    ax.set_ylabel(panel.ylabel)
    ax.grid(True, color="0.9")
    ax.set_axisbelow(True)
    ax.xaxis.set_major_locator(MaxNLocator(nbins=7, steps=[1, 2, 2.5, 5, 10]))
  labels = [tuple(panel.series) for panel in panels]
  named = any(any(series) for series in labels)
  if named and len(panels) > 1 and len(set(labels)) == 1:
    handles, names = axes[0].get_legend_handles_labels()
    # As many columns as fit the figure's width (~12 characters an inch at 8 pt, plus the
    # marker), then spread evenly over the rows.
    fit = max(1, int(12 * w * len(panels)) // (max(map(len, names)) + 6))
    rows = math.ceil(len(names) / fit)
    fig.legend(
      handles,
      names,
      loc="outside lower center",
      ncol=math.ceil(len(names) / rows),
      fontsize=8,
      frameon=False,
    )
  elif named:
    for ax, series in zip(axes, labels, strict=True):
      if any(series):
        ax.legend(loc="best", fontsize=8, framealpha=0.85)
  if title:
    fig.suptitle("\n".join(title), fontsize=9 if len(title) > 1 else 11)
  return fig


@dataclass(frozen=True)
class GramAxis:
  """How a Gram map's index maps to pose: `values` (K,) in `unit`, or a flat 2-D grid."""

  label: str
  values: np.ndarray  # (K,) ticks in the DOF's units, or (K, 2) positions (flat index)
  unit: str = ""


def gram_axis(values, *, name: str, angular: bool) -> GramAxis:
  """The axis of a Gram map over a DOF's values: degrees for an angle (values in radians), the
  DOF's own unit otherwise; (K, 2) positions of a polar DOF keep their (x, y) pairs."""
  v = np.asarray(values, np.float64)
  if v.ndim == 2:
    return GramAxis(f"{name}: (x, y) grid point, x-major", v, "")
  if angular:
    return GramAxis(f"{name} (degrees)", np.degrees(v), "deg")
  return GramAxis(name, v, "")


def gram_figure(g, axis: GramAxis, *, title: str, caption: str = "") -> Figure:
  """A (K, K) Gram matrix as an image with pose ticks on both axes and a colour bar.

  Angles and linear DOFs: ticks at round values of the DOF (degrees, metres...). A polar DOF's
  flat (x, y) grid: a tick at the start of each x row, labelled with its x, every few rows.
  """
  g = np.asarray(g, np.float64)
  k = g.shape[0]
  fig = Figure(figsize=(5.0, 4.3 + (0.25 if caption else 0.0)), layout="constrained")
  ax = fig.subplots()
  im = ax.imshow(g, cmap="viridis", interpolation="nearest", origin="upper")
  fig.colorbar(im, ax=ax, shrink=0.85, label="inner product")
  v = axis.values
  if v.ndim == 2:  # flat grid: x changes every n_side entries
    n_side = int(round(math.sqrt(k)))
    starts = np.arange(0, k, n_side)
    step = max(1, len(starts) // 6)
    ticks = starts[::step]
    labels = [f"x={v[t, 0]:.2g}" for t in ticks]
  else:
    lo, hi = float(v[0]), float(v[-1])
    # Degrees at multiples of 90 / 45 / 30 / 15, other units at 1-2-5 steps.
    steps = [1, 1.5, 3, 4.5, 9, 10] if axis.unit == "deg" else [1, 2, 2.5, 5, 10]
    locs = MaxNLocator(nbins=7, steps=steps).tick_values(lo, hi)
    locs = locs[(locs >= min(lo, hi) - 1e-9) & (locs <= max(lo, hi) + 1e-9)]
    ticks = (locs - lo) / ((hi - lo) or 1.0) * (k - 1)
    labels = [f"{t:g}" for t in locs]
  rotation = 45 if v.ndim == 2 else 0
  ax.set_xticks(ticks, labels, rotation=rotation, fontsize=8)
  ax.set_yticks(ticks, labels, fontsize=8)
  ax.set_xlabel(axis.label)
  ax.set_ylabel(axis.label)
  ax.set_title(title, fontsize=10)
  if caption:
    fig.text(0.01, 0.005, caption, fontsize=8, color="0.3")
  return fig


def save(fig: Figure, path: str, *, formats: Sequence[str] = ("png", "pdf")) -> list[str]:
  """Writes `fig` as `path` (its extension dropped) in each format: a PNG at DPI and a vector
  PDF by default. Returns the paths written."""
  stem = os.path.splitext(path)[0]
  out = []
  for fmt in formats:
    p = f"{stem}.{fmt}"
    fig.savefig(p, dpi=DPI, format=fmt, metadata=_metadata(fmt))
    out.append(p)
  return out


def _metadata(fmt: str) -> dict:
  """No creation dates in the files: the same figure gives the same bytes."""
  if fmt == "png":
    return {"Software": None}
  if fmt == "pdf":
    return {"CreationDate": None, "Producer": None, "Creator": None}
  return {}


def to_rgb(fig: Figure, dpi: float = DPI) -> np.ndarray:
  """The figure rendered at `dpi`: (H, W, 3) uint8 RGB (for notebooks and tests)."""
  from matplotlib.backends.backend_agg import FigureCanvasAgg

  fig.set_dpi(dpi)
  canvas = FigureCanvasAgg(fig)
  canvas.draw()
  return np.asarray(canvas.buffer_rgba())[..., :3].copy()

"""Run logging into the workdir: metrics.jsonl, TensorBoard, PNG image grids, progress lines.

Layout written under `workdir`:

  config.json                 the run's config (`MetricWriter.write_config`).
  metrics.jsonl               one JSON object per logged step, {"step": s, "train/loss": ...};
                              the machine-readable record that experiments/ scripts read.
  tensorboard/events.*        the same scalars and the images, for TensorBoard (tensorboardX).
  images/{name}_{step:08d}.png  every logged image.

Non-finite values: JSON has no NaN or inf, so they are written as the strings "NaN",
"Infinity" and "-Infinity" (the spellings JavaScript and Python's `float()` accept);
`read_metrics` turns them back into floats. The file therefore stays strict JSON.

Only one process should own a MetricWriter (process 0 in a multi-host run).
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import cv2
import numpy as np

try:  # Optional: writes TensorBoard event files without TensorFlow.
  from tensorboardX import FileWriter as _TBFileWriter
  from tensorboardX.proto.event_pb2 import Event as _TBEvent
  from tensorboardX.proto.event_pb2 import SessionLog as _TBSessionLog
  from tensorboardX.proto.summary_pb2 import Summary as _TBSummary
except ImportError:  # pragma: no cover - depends on the environment
  _TBFileWriter = None

METRICS_FILE = "metrics.jsonl"
CONFIG_FILE = "config.json"
TENSORBOARD_DIR = "tensorboard"
IMAGES_DIR = "images"

_NONFINITE_TO_STR = {math.inf: "Infinity", -math.inf: "-Infinity"}
_STR_TO_NONFINITE = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}
_PNG_NAME = re.compile(r"^(?P<name>.+)_(?P<step>\d{8,})\.png$")


def tensorboard_available() -> bool:
  """Whether tensorboardX is importable (TensorBoard output is skipped otherwise)."""
  return _TBFileWriter is not None


def _to_float(name: str, value: Any) -> float:
  arr = np.asarray(value)
  if arr.size != 1:
    raise ValueError(f"scalar {name!r} has shape {arr.shape}; log one value per key")
  return float(arr.reshape(()))


def _encode_json_value(x: float) -> float | str:
  if math.isnan(x):
    return "NaN"
  return _NONFINITE_TO_STR.get(x, x)


def _decode_json_value(x: Any) -> Any:
  if isinstance(x, str) and x in _STR_TO_NONFINITE:
    return _STR_TO_NONFINITE[x]
  return x


def _parse_lines(text: str, path: str) -> list[dict[str, Any]]:
  """Parses metrics.jsonl text; a torn last line (crash mid-write) is dropped."""
  lines = text.split("\n")
  records = []
  for i, line in enumerate(lines):
    if not line.strip():
      continue
    try:
      record = json.loads(line)
    except json.JSONDecodeError:
      if i == len(lines) - 1:  # No newline after it: an interrupted write.
        break
      raise ValueError(f"{path}:{i + 1}: not a JSON line: {line[:80]!r}") from None
    records.append({k: _decode_json_value(v) for k, v in record.items()})
  return records


def read_metrics(workdir: str) -> list[dict[str, Any]]:
  """Reads workdir/metrics.jsonl back, with "NaN"/"Infinity"/"-Infinity" turned into floats.

  Args:
    workdir: Run directory.

  Returns:
    One dict per logged line, in file order, each with an int "step" and float values; an empty
    list if the file does not exist.
  """
  path = os.path.join(workdir, METRICS_FILE)
  if not os.path.exists(path):
    return []
  with open(path, encoding="utf-8") as f:
    return _parse_lines(f.read(), path)


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


def _safe_filename(name: str) -> str:
  return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


class MetricWriter:
  """Writes scalars, images and the config of one run into its workdir.

  Resuming is safe: metrics.jsonl is opened for appending (a torn last line left by a crash is
  removed first). After restoring a checkpoint at step s, call `truncate_after(s)` so that lines
  logged after s by the interrupted run are dropped and the resumed log equals an uninterrupted
  one.

  Usage:
    writer = MetricWriter(workdir)
    writer.write_config(config)
    writer.write_scalars(step, {"train/loss": loss, "train/lr": lr})
    writer.write_images(step, {"eval/test/grid": grid})
    writer.close()
  """

  def __init__(self, workdir: str, *, tensorboard: bool = True):
    """Creates the workdir if needed and opens the outputs.

    Args:
      workdir: Run directory.
      tensorboard: Also write TensorBoard event files to workdir/tensorboard (needs tensorboardX;
        silently skipped when it is not installed, see `tensorboard_available`).
    """
    self.workdir = workdir
    os.makedirs(workdir, exist_ok=True)
    self._path = os.path.join(workdir, METRICS_FILE)
    self._drop_torn_line()
    self._file = open(self._path, "a", encoding="utf-8")
    self._tb = None
    if tensorboard and tensorboard_available():
      self._tb = _TBFileWriter(os.path.join(workdir, TENSORBOARD_DIR), flush_secs=30)

  def _drop_torn_line(self) -> None:
    if not os.path.exists(self._path):
      return
    with open(self._path, "rb+") as f:
      data = f.read()
      if data and not data.endswith(b"\n"):
        f.truncate(data.rfind(b"\n") + 1)

  @property
  def tensorboard_dir(self) -> str | None:
    """Where event files go, or None when TensorBoard output is off."""
    return os.path.join(self.workdir, TENSORBOARD_DIR) if self._tb is not None else None

  def write_scalars(self, step: int, scalars: Mapping[str, Any]) -> None:
    """Appends one line {"step": step, **scalars} to metrics.jsonl and logs them to TensorBoard.

    Args:
      step: Global step (an int, or anything int() accepts, e.g. a 0-d array).
      scalars: name -> scalar (Python number or 0-d / size-1 array). Values are stored as Python
        floats; NaN and +-inf as the strings "NaN", "Infinity", "-Infinity".
    """
    step = int(step)
    if "step" in scalars:
      raise ValueError('"step" is reserved for the step number')
    values = {k: _to_float(k, v) for k, v in scalars.items()}
    record = {"step": step, **{k: _encode_json_value(v) for k, v in values.items()}}
    self._file.write(json.dumps(record, allow_nan=False) + "\n")
    self._file.flush()
    if self._tb is not None:
      summary = _TBSummary(
        value=[_TBSummary.Value(tag=k, simple_value=v) for k, v in values.items()]
      )
      self._tb.add_summary(summary, step)

  def write_images(
    self,
    step: int,
    images: Mapping[str, Any],
    *,
    value_range: tuple[float, float] = (-1.0, 1.0),
  ) -> None:
    """Writes PNG files and TensorBoard images.

    Files go to workdir/images/{name}_{step:08d}.png, with characters other than letters, digits,
    "_", "." and "-" in the name replaced by "_" (so "eval/test/grid" -> "eval_test_grid"); the
    TensorBoard tag is the name itself.

    Args:
      step: Global step.
      images: name -> (H, W[, 1 or 3]) image, uint8 or float (see `to_uint8`).
      value_range: Range of float images.
    """
    step = int(step)
    image_dir = os.path.join(self.workdir, IMAGES_DIR)
    os.makedirs(image_dir, exist_ok=True)
    tb_values = []
    for name, image in images.items():
      rgb = to_uint8(image, value_range=value_range)
      ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
      if not ok:
        raise RuntimeError(f"PNG encoding of {name!r} failed")
      png = png.tobytes()
      path = os.path.join(image_dir, f"{_safe_filename(name)}_{step:08d}.png")
      with open(path, "wb") as f:
        f.write(png)
      if self._tb is not None:
        tb_image = _TBSummary.Image(
          height=rgb.shape[0], width=rgb.shape[1], colorspace=3, encoded_image_string=png
        )
        tb_values.append(_TBSummary.Value(tag=name, image=tb_image))
    if tb_values:
      self._tb.add_summary(_TBSummary(value=tb_values), step)

  def write_config(self, config: Any) -> None:
    """Writes workdir/config.json.

    Args:
      config: An ml_collections ConfigDict / FrozenConfigDict (serialised with
        `to_json_best_effort`) or a JSON-serialisable mapping (other leaves become strings).
    """
    if hasattr(config, "to_json_best_effort"):
      text = config.to_json_best_effort(indent=2, sort_keys=True)
    else:
      text = json.dumps(dict(config), indent=2, sort_keys=True, default=str)
    path = os.path.join(self.workdir, CONFIG_FILE)
    with open(path + ".tmp", "w", encoding="utf-8") as f:
      f.write(text + "\n")
    os.replace(path + ".tmp", path)

  def truncate_after(self, step: int) -> None:
    """Drops everything logged after `step`, for a run resumed from a checkpoint at `step`.

    Removes metrics.jsonl lines with a larger step (atomically), lines cut short by a killed
    process, and image files with a larger step, and writes a TensorBoard "purge" marker so that
    TensorBoard hides the interrupted run's events after `step`.

    Args:
      step: Step of the restored checkpoint; lines with step <= it are kept.
    """
    step = int(step)
    self.flush()
    with open(self._path, encoding="utf-8") as f:
      text = f.read()
    kept = []
    for line in text.split("\n"):
      try:
        row = json.loads(line) if line.strip() else None
      except json.JSONDecodeError:  # a line cut short by a killed process
        row = None
      if row is not None and row["step"] <= step:
        kept.append(line)
    self._file.close()
    with open(self._path + ".tmp", "w", encoding="utf-8") as f:
      f.writelines(line + "\n" for line in kept)
    os.replace(self._path + ".tmp", self._path)
    self._file = open(self._path, "a", encoding="utf-8")
    image_dir = os.path.join(self.workdir, IMAGES_DIR)
    if os.path.isdir(image_dir):
      for fname in os.listdir(image_dir):
        match = _PNG_NAME.match(fname)
        if match and int(match["step"]) > step:
          os.remove(os.path.join(image_dir, fname))
    if self._tb is not None:
      # Same marker as tensorboardX's SummaryWriter(purge_step=step + 1).
      self._tb.add_event(_TBEvent(step=step + 1, file_version="brain.Event:2"))
      self._tb.add_event(
        _TBEvent(step=step + 1, session_log=_TBSessionLog(status=_TBSessionLog.START))
      )
      self._tb.flush()

  def flush(self) -> None:
    """Flushes metrics.jsonl and the TensorBoard queue."""
    self._file.flush()
    if self._tb is not None:
      self._tb.flush()

  def close(self) -> None:
    """Flushes and closes all outputs; the writer is unusable afterwards."""
    if self._file.closed:
      return
    self.flush()
    self._file.close()
    if self._tb is not None:
      self._tb.close()

  def __enter__(self) -> MetricWriter:
    return self

  def __exit__(self, *exc: object) -> None:
    self.close()


# --------------------------------------------------------------------------------------------
# Image grids.


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


# --------------------------------------------------------------------------------------------
# Progress and scheduling.


def format_duration(seconds: float) -> str:
  """Formats seconds as "12s", "4m44s" or "1h02m03s" ("--" when unknown or infinite)."""
  if not math.isfinite(seconds) or seconds < 0:
    return "--"
  s = round(seconds)
  h, rem = divmod(s, 3600)
  m, s = divmod(rem, 60)
  if h:
    return f"{h}h{m:02d}m{s:02d}s"
  if m:
    return f"{m}m{s:02d}s"
  return f"{s}s"


class NullWriter:
  """A `MetricWriter` that writes nothing: what processes other than 0 of a multi-process run
  use, so that one process owns the workdir's logs."""

  def write_scalars(self, step: int, scalars: Mapping[str, Any]) -> None:
    del step, scalars

  def write_images(self, step: int, images: Mapping[str, Any], **kwargs: Any) -> None:
    del step, images, kwargs

  def write_config(self, config: Any) -> None:
    del config

  def truncate_after(self, step: int) -> None:
    del step

  def flush(self) -> None:
    pass

  def close(self) -> None:
    pass


class Progress:
  """Rate-limited one-line progress reports, for logs that are not a terminal (CI, cluster).

  `update(step)` is cheap and meant to be called every step; it returns a line such as
  "step 120/1000 (12.0%) 3.1 steps/s ETA 4m44s" on the first call, on the last step, and
  otherwise at most once every `every_seconds`; else None. The rate is measured over the
  interval since the previous report (since the first update before that), so the time spent in
  the first step (compilation) and before it does not count.
  """

  def __init__(
    self,
    total_steps: int,
    *,
    start_step: int = 0,
    every_seconds: float = 30.0,
    log_fn: Callable[[str], None] | None = None,
    clock: Callable[[], float] = time.monotonic,
  ):
    """Sets up the reporter.

    Args:
      total_steps: Step number at which training ends.
      start_step: Step the run starts (or resumes) from.
      every_seconds: Minimum time between two reports.
      log_fn: Called with each report line (e.g. `logging.info` or `print`); none by default.
      clock: Time source in seconds (tests pass a fake one).
    """
    self.total_steps = int(total_steps)
    self.every_seconds = float(every_seconds)
    self._log_fn = log_fn
    self._clock = clock
    self._last_step = int(start_step)
    self._anchor: tuple[float, int] | None = None  # (time, step) where the window starts.
    self._last_report: float | None = None
    self._rate = math.nan

  @property
  def steps_per_second(self) -> float:
    """Steps/s over the latest measuring window (NaN before two updates)."""
    return self._rate

  def update(self, step: int) -> str | None:
    """Records that `step` is done; returns a report line when one is due, else None."""
    step = int(step)
    now = self._clock()
    self._last_step = step
    if self._anchor is None:
      self._anchor = (now, step)
    else:
      t0, s0 = self._anchor
      if now > t0 and step > s0:
        self._rate = (step - s0) / (now - t0)
    due = (
      self._last_report is None
      or step >= self.total_steps
      or now - self._last_report >= self.every_seconds
    )
    if not due:
      return None
    self._last_report = now
    if self._rate == self._rate:  # Once a rate exists, the next window starts here.
      self._anchor = (now, step)
    line = self.status()
    if self._log_fn is not None:
      self._log_fn(line)
    return line

  def status(self) -> str:
    """The current status line, whether or not a report is due."""
    total = max(self.total_steps, 1)
    pct = 100.0 * self._last_step / total
    rate = self._rate
    if math.isfinite(rate) and rate > 0:
      eta = format_duration(max(self.total_steps - self._last_step, 0) / rate)
      speed = f"{rate:.1f} steps/s" if rate >= 1 else f"{rate:.2g} steps/s"
    else:
      eta, speed = "--", "-- steps/s"
    return f"step {self._last_step}/{self.total_steps} ({pct:.1f}%) {speed} ETA {eta}"


def itstime(step: int, every: int, total: int, *, first: bool = False) -> bool:
  """Whether a periodic action (log, eval, checkpoint) runs at `step`.

  Steps count completed updates: 1 .. total. True when `step` is a positive multiple of
  `every`, when `step == total` (the last step, even if not a multiple), and with `first=True`
  also at step 1. `every <= 0` disables the action entirely (never true, not even at the last
  step). Follows big_vision `utils.py:itstime`.

  Args:
    step: Number of completed steps.
    every: Period in steps; <= 0 means never.
    total: Total number of steps of the run.
    first: Also fire at step 1.

  Returns:
    Whether to act at this step.
  """
  if every <= 0:
    return False
  return (step > 0 and step % every == 0) or step == total or (first and step == 1)

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
from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np

from camrep.runtime import grids

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


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
  """Writes `path` whole or not at all: a temporary file beside it, flushed to disk, then
  renamed over it, so a reader (or a run after a full disk or a kill) sees the old file or the
  whole new one, never a cut one; the temporary file is removed on any failure."""
  path = os.fspath(path)
  tmp = f"{path}.tmp.{os.getpid()}"
  try:
    with open(tmp, "w", encoding="utf-8") as f:
      f.write(text)
      f.flush()
      os.fsync(f.fileno())
    os.replace(tmp, path)
  finally:
    if os.path.lexists(tmp):
      os.remove(tmp)


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


class MetricsFileError(ValueError):
  """A metrics.jsonl line that is not a record this module wrote (not JSON, or without an
  integer "step")."""


def _bad_line(path: str, number: int, line: str, what: str) -> MetricsFileError:
  return MetricsFileError(
    f"{path}:{number}: {what}: {line[:80]!r}; a camrep metrics line is a JSON object with an "
    'integer "step". Remove that line (or put the file back) and start again; nothing was '
    "changed"
  )


def _parse_lines(text: str, path: str) -> list[dict[str, Any]]:
  """Parses metrics.jsonl text; a torn last line (crash mid-write) is dropped.

  Raises:
    MetricsFileError: another line is not JSON or has no integer "step".
  """
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
      raise _bad_line(path, i + 1, line, "not a JSON line") from None
    if not _has_step(record):
      raise _bad_line(path, i + 1, line, 'a line without an integer "step"')
    records.append({k: _decode_json_value(v) for k, v in record.items()})
  return records


def _has_step(record: Any) -> bool:
  return (
    isinstance(record, dict)
    and isinstance(record.get("step"), int)
    and not isinstance(record["step"], bool)
  )


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
      images: name -> (H, W[, 1 or 3]) image, uint8 or float (see `grids.to_uint8`).
      value_range: Range of float images.
    """
    step = int(step)
    image_dir = os.path.join(self.workdir, IMAGES_DIR)
    os.makedirs(image_dir, exist_ok=True)
    tb_values = []
    for name, image in images.items():
      rgb = grids.to_uint8(image, value_range=value_range)
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

    Raises:
      MetricsFileError: a complete line holds no integer "step" (nothing is changed).
    """
    step = int(step)
    self.flush()
    with open(self._path, encoding="utf-8") as f:
      text = f.read()
    kept = []
    for number, line in enumerate(text.split("\n"), 1):
      try:
        row = json.loads(line) if line.strip() else None
      except json.JSONDecodeError:  # a line cut short by a killed process
        row = None
      if row is not None and not _has_step(row):
        raise _bad_line(self._path, number, line, 'a line without an integer "step"')
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


# --------------------------------------------------------------------------------------------
# Progress and scheduling.


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

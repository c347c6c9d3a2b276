"""Tests for camrep.runtime.writers: metrics.jsonl, TensorBoard, PNG grids, Progress, itstime."""

from __future__ import annotations

import glob
import json
import math
import os
import re
import struct

import cv2
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from camrep.runtime import grids, writers
from camrep.runtime import progress as progress_lib


def _read_events(workdir):
  """All TensorBoard events under workdir/tensorboard (plain TFRecord framing, no TF needed)."""
  event_pb2 = pytest.importorskip("tensorboardX.proto.event_pb2")
  events = []
  for path in sorted(glob.glob(os.path.join(workdir, "tensorboard", "events.out.tfevents.*"))):
    data = open(path, "rb").read()
    i = 0
    while i < len(data):
      (n,) = struct.unpack("<Q", data[i : i + 8])
      i += 12  # length + its crc
      events.append(event_pb2.Event.FromString(data[i : i + n]))
      i += n + 4  # payload + its crc
  return events


def _strict_json(line):
  def reject(name):
    raise ValueError(f"non-standard JSON constant {name}")

  return json.loads(line, parse_constant=reject)


# ------------------------------------------------------------------------------------------
# metrics.jsonl


def test_scalars_round_trip_and_types(tmp_path):
  with writers.MetricWriter(str(tmp_path), tensorboard=False) as w:
    w.write_scalars(1, {"train/loss": np.float32(0.5), "train/lr": jnp.asarray(1e-3)})
    w.write_scalars(np.int64(2), {"train/loss": 0.25, "eval/test/psnr": jnp.ones((1,)) * 30})
    # Flushed at every write: readable before close.
    assert len(writers.read_metrics(str(tmp_path))) == 2
    with pytest.raises(ValueError):
      w.write_scalars(3, {"step": 1.0})
    with pytest.raises(ValueError):
      w.write_scalars(3, {"train/vec": np.ones(3)})
  records = writers.read_metrics(str(tmp_path))
  assert records == [
    {"step": 1, "train/loss": 0.5, "train/lr": pytest.approx(1e-3)},
    {"step": 2, "train/loss": 0.25, "eval/test/psnr": 30.0},
  ]
  assert all(type(r["step"]) is int for r in records)
  assert all(type(v) is float for r in records for k, v in r.items() if k != "step")
  assert not os.path.exists(tmp_path / "tensorboard")
  assert writers.read_metrics(str(tmp_path / "missing")) == []


def test_non_finite_values_are_strict_json_strings(tmp_path):
  with writers.MetricWriter(str(tmp_path), tensorboard=False) as w:
    w.write_scalars(5, {"a": math.nan, "b": np.float32(np.inf), "c": -math.inf, "d": 1.0})
  lines = (tmp_path / "metrics.jsonl").read_text().splitlines()
  assert _strict_json(lines[0]) == {
    "step": 5,
    "a": "NaN",
    "b": "Infinity",
    "c": "-Infinity",
    "d": 1.0,
  }
  (rec,) = writers.read_metrics(str(tmp_path))
  assert math.isnan(rec["a"]) and rec["b"] == math.inf and rec["c"] == -math.inf


def _log_run(workdir, steps, *, resume_from=None, tensorboard=False):
  with writers.MetricWriter(workdir, tensorboard=tensorboard) as w:
    if resume_from is not None:
      w.truncate_after(resume_from)
    for s in steps:
      w.write_scalars(s, {"train/loss": 1.0 / s, "train/bad": math.nan if s == 3 else 0.0})
      w.write_images(s, {"eval/grid": np.full((4, 4, 3), s, np.uint8)})


def test_resume_appends_and_truncate_after_gives_identical_log(tmp_path):
  ref, run = str(tmp_path / "ref"), str(tmp_path / "run")
  _log_run(ref, range(1, 9))
  # Interrupted run: logged up to step 6, the last checkpoint is at step 4.
  _log_run(run, range(1, 7))
  with open(os.path.join(run, "metrics.jsonl"), "a") as f:
    f.write('{"step": 7, "train/lo')  # Torn line from a crash mid-write.
  _log_run(run, range(5, 9), resume_from=4)
  ref_bytes = open(os.path.join(ref, "metrics.jsonl"), "rb").read()
  assert open(os.path.join(run, "metrics.jsonl"), "rb").read() == ref_bytes
  assert [r["step"] for r in writers.read_metrics(run)] == list(range(1, 9))
  assert sorted(os.listdir(os.path.join(run, "images"))) == sorted(
    os.listdir(os.path.join(ref, "images"))
  )


def test_plain_resume_appends(tmp_path):
  _log_run(str(tmp_path), [1, 2])
  _log_run(str(tmp_path), [3])
  assert [r["step"] for r in writers.read_metrics(str(tmp_path))] == [1, 2, 3]


def test_truncate_after_drops_images_and_keeps_others(tmp_path):
  with writers.MetricWriter(str(tmp_path), tensorboard=False) as w:
    for s in (10, 20, 30):
      w.write_scalars(s, {"x": s})
      w.write_images(s, {"g": np.zeros((2, 2, 3), np.uint8)})
    (tmp_path / "images" / "notes.txt").write_text("kept")
    w.truncate_after(20)
    w.write_scalars(25, {"x": 25})
  assert [r["step"] for r in writers.read_metrics(str(tmp_path))] == [10, 20, 25]
  assert sorted(os.listdir(tmp_path / "images")) == [
    "g_00000010.png",
    "g_00000020.png",
    "notes.txt",
  ]


# ------------------------------------------------------------------------------------------
# TensorBoard, images, config.


def test_tensorboard_event_files(tmp_path):
  if not writers.tensorboard_available():
    pytest.skip("tensorboardX not installed")
  with writers.MetricWriter(str(tmp_path)) as w:
    assert w.tensorboard_dir == str(tmp_path / "tensorboard")
    w.write_scalars(1, {"train/loss": 0.5, "train/nan": math.nan})
    w.write_images(1, {"eval/test/grid": np.zeros((6, 5, 3), np.uint8)})
    w.truncate_after(1)
  events = _read_events(str(tmp_path))
  scalars = {
    v.tag: v.simple_value for e in events for v in e.summary.value if v.HasField("simple_value")
  }
  assert scalars["train/loss"] == 0.5 and math.isnan(scalars["train/nan"])
  (image,) = [v.image for e in events for v in e.summary.value if v.HasField("image")]
  assert (image.height, image.width, image.colorspace) == (6, 5, 3)
  decoded = cv2.imdecode(np.frombuffer(image.encoded_image_string, np.uint8), cv2.IMREAD_UNCHANGED)
  assert decoded.shape == (6, 5, 3)
  assert any(e.session_log.status == e.session_log.START and e.step == 2 for e in events)


def test_write_images_png_rgb_order_and_names(tmp_path):
  red = np.zeros((3, 4, 3), np.float32) - 1.0
  red[..., 0] = 1.0  # [-1, 1] floats: pure red.
  gray = np.full((3, 4), 128, np.uint8)
  with writers.MetricWriter(str(tmp_path), tensorboard=False) as w:
    w.write_images(12, {"eval/test/red": red, "gray": gray})
  bgr = cv2.imread(str(tmp_path / "images" / "eval_test_red_00000012.png"), cv2.IMREAD_UNCHANGED)
  assert bgr.shape == (3, 4, 3)
  np.testing.assert_array_equal(bgr[0, 0], [0, 0, 255])
  g = cv2.imread(str(tmp_path / "images" / "gray_00000012.png"), cv2.IMREAD_UNCHANGED)
  assert g.shape == (3, 4, 3) and np.all(g == 128)


def test_write_config(tmp_path):
  config = ml_collections.ConfigDict({"seed": 3, "model": {"width": 8}, "total_steps": 10})
  with writers.MetricWriter(str(tmp_path), tensorboard=False) as w:
    w.write_config(config)
    assert json.loads((tmp_path / "config.json").read_text())["model"] == {"width": 8}
    w.write_config({"seed": 1, "shape": (2, 3), "obj": object()})
  loaded = json.loads((tmp_path / "config.json").read_text())
  assert loaded["seed"] == 1 and loaded["shape"] == [2, 3] and isinstance(loaded["obj"], str)


# ------------------------------------------------------------------------------------------
# Grids.


def test_to_uint8_ranges():
  np.testing.assert_array_equal(
    grids.to_uint8(np.array([[-1.0, 0.0, 1.0, 2.0]]))[0, :, 0], [0, 128, 255, 255]
  )
  np.testing.assert_array_equal(
    grids.to_uint8(np.array([[0.0, 1.0]]), value_range=(0.0, 1.0))[0, :, 0], [0, 255]
  )
  with pytest.raises(ValueError):
    grids.to_uint8(np.zeros((2, 2, 2)))


def test_image_grid_shape_and_layout():
  h, w, pad = 8, 10, 2
  rows = [[np.full((h, w, 3), -1.0)] * 3, [np.full((h, w, 3), 255, np.uint8)] * 2]
  grid = grids.image_grid(rows, pad=pad)
  assert grid.dtype == np.uint8
  assert grid.shape == (2 * (h + pad) + pad, 3 * (w + pad) + pad, 3)
  assert np.all(grid[pad : pad + h, pad : pad + w] == 0)  # First cell: -1 -> black.
  assert np.all(grid[:pad] == 255)  # White border.
  labelled = grids.image_grid(rows, labels=["a", "b", "c"], pad=pad)
  header = labelled.shape[0] - grid.shape[0]
  assert header > 0 and labelled.shape[1] == grid.shape[1]
  assert np.any(labelled[:header] < 255)  # Text was drawn.
  with pytest.raises(ValueError):
    grids.image_grid([])


def test_view_synthesis_grid_written_and_readable(tmp_path):
  rng = np.random.default_rng(0)
  s, c, q, h, w = 5, 3, 2, 16, 16
  context = rng.uniform(-1, 1, (s, c, h, w, 3)).astype(np.float32)
  target = rng.uniform(-1, 1, (s, q, h, w, 3)).astype(np.float32)
  prediction = target.copy()
  prediction[:, 1] = -target[:, 1]
  grid = grids.view_synthesis_grid(context, target, prediction, max_scenes=4)
  pad = 2
  assert grid.shape[1] == (c + 3) * (w + pad) + pad
  header = grid.shape[0] - (4 * q * (h + pad) + pad)
  assert header > 0
  err_x = pad + (c + 2) * (w + pad)

  def cell(row, x):
    y = header + pad + row * (h + pad)
    return grid[y : y + h, x : x + w]

  assert cell(0, err_x).max() < 10  # Exact prediction: near-black error map.
  assert cell(1, err_x).mean() > 100  # Wrong prediction: bright error map.
  np.testing.assert_array_equal(cell(0, pad + c * (w + pad)), grids.to_uint8(target[0, 0]))
  with writers.MetricWriter(str(tmp_path), tensorboard=False) as mw:
    mw.write_images(7, {"eval/test/views": grid})
  back = cv2.imread(str(tmp_path / "images" / "eval_test_views_00000007.png"), cv2.IMREAD_COLOR)
  np.testing.assert_array_equal(back[..., ::-1], grid)
  with pytest.raises(ValueError):
    grids.view_synthesis_grid(context, target, prediction[:, :1])


# ------------------------------------------------------------------------------------------
# Progress and itstime.


class FakeClock:
  def __init__(self):
    self.t = 0.0

  def __call__(self):
    return self.t


def test_progress_format_and_rate_limit():
  clock = FakeClock()
  p = progress_lib.Progress(1000, every_seconds=10.0, clock=clock)
  assert p.update(0) == "step 0/1000 (0.0%) -- steps/s ETA --"  # First call reports.
  assert math.isnan(p.steps_per_second)
  clock.t = 5.0
  assert p.update(15) is None  # Within every_seconds.
  clock.t = 120 / 3.1
  assert p.update(120) == "step 120/1000 (12.0%) 3.1 steps/s ETA 4m44s"
  assert p.steps_per_second == pytest.approx(3.1)
  clock.t += 1.0
  assert p.update(121) is None
  clock.t += 9.0
  line = p.update(150)  # Rate over the window since the last report: 30 steps / 10 s.
  assert line == "step 150/1000 (15.0%) 3.0 steps/s ETA 4m43s"
  clock.t += 0.1
  assert p.update(1000).startswith("step 1000/1000 (100.0%)")  # The last step always reports.


def test_progress_slow_rate_and_resume():
  clock = FakeClock()
  p = progress_lib.Progress(10_000, start_step=9000, every_seconds=1.0, clock=clock)
  assert p.status().startswith("step 9000/10000 (90.0%)")
  p.update(9000)
  clock.t = 40.0
  assert p.update(9002) == "step 9002/10000 (90.0%) 0.05 steps/s ETA 5h32m40s"


def test_progress_prints_plain_lines_when_not_a_tty(capsys):
  clock = FakeClock()
  p = progress_lib.Progress(4, every_seconds=60.0, log_fn=print, clock=clock)
  for step in range(1, 5):
    clock.t += 1.0
    p.update(step)
  out = capsys.readouterr().out
  assert "\r" not in out and "\x1b" not in out
  lines = out.splitlines()
  assert len(lines) == 2  # First call and last step only.
  assert re.fullmatch(r"step 4/4 \(100\.0%\) 1\.0 steps/s ETA 0s", lines[-1])


def test_format_duration():
  assert progress_lib.format_duration(0) == "0s"
  assert progress_lib.format_duration(59.4) == "59s"
  assert progress_lib.format_duration(284) == "4m44s"
  assert progress_lib.format_duration(3723) == "1h02m03s"
  assert progress_lib.format_duration(math.inf) == "--"


def test_itstime_periodic_and_last_step():
  fired = [s for s in range(1, 26) if progress_lib.itstime(s, 10, 25)]
  assert fired == [10, 20, 25]
  # The last step fires once, even when it is also a multiple.
  assert [s for s in range(1, 21) if progress_lib.itstime(s, 10, 20)] == [10, 20]
  assert not progress_lib.itstime(24, 10, 25) and not progress_lib.itstime(0, 10, 25)
  assert [s for s in range(1, 6) if progress_lib.itstime(s, 100, 5)] == [5]
  assert [s for s in range(1, 26) if progress_lib.itstime(s, 10, 25, first=True)] == [1, 10, 20, 25]
  assert [s for s in range(1, 3) if progress_lib.itstime(s, 1, 2)] == [1, 2]


def test_itstime_disabled():
  assert not any(progress_lib.itstime(s, 0, 10) for s in range(0, 11))
  assert not any(progress_lib.itstime(s, -1, 10, first=True) for s in range(0, 11))

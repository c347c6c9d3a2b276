"""tools/capture_sizes.py: a held-out view beside each run's prediction of it, on the session's
shared view-synthesis run (any workdir works alike; the README's picture used two capture runs)."""

from __future__ import annotations

import cv2
import pytest

from tools import capture_sizes


def test_the_picture_shows_the_target_and_each_runs_prediction(gqn_smoke_run, tmp_path, capsys):
  out = tmp_path / "sizes.png"
  assert capture_sizes.main(["--runs", gqn_smoke_run, gqn_smoke_run, "--out", str(out)]) == 0
  lines = capsys.readouterr().out.splitlines()
  assert sum("held-out view PSNR" in line and "step 4" in line for line in lines) == 2
  image = cv2.imread(str(out))
  size = 64  # configs/gqn.py:smoke renders 64 px
  assert image.shape[0] > size and image.shape[1] >= 3 * size  # target + two predictions


def test_a_missing_run_is_an_error_line(tmp_path, capsys):
  with pytest.raises(SystemExit) as e:
    capture_sizes.main(["--runs", str(tmp_path / "nope"), "--out", str(tmp_path / "x.png")])
  assert e.value.code == 2 and "not a directory" in capsys.readouterr().err

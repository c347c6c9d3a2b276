"""Text-file helpers shared by the real-dataset readers; every failure is a `DataError`."""

from __future__ import annotations

import os

import numpy as np

from camrep.data.errors import DataError


def read_matrix_4x4(path: str | os.PathLike) -> np.ndarray:
  """Reads a 4x4 matrix written as 16 whitespace-separated numbers (any line layout).

  Used for SRN `pose/NNNNNN.txt` (one line of 16) and 7-Scenes `frame-NNNNNN.pose.txt` (4 lines
  of 4, CRLF, tabs); both are camera-to-world.

  Returns:
    (4, 4) float64.

  Raises:
    DataError: unreadable file, a non-number, a count other than 16, or non-finite values.
  """
  try:
    with open(path) as f:
      text = f.read()
  except OSError as e:
    raise DataError(path, f"cannot read pose file ({e.strerror or e})") from e
  try:
    vals = [float(v) for v in text.split()]
  except ValueError as e:
    raise DataError(path, f"pose file holds a non-number ({e})") from e
  if len(vals) != 16:
    raise DataError(path, f"expected 16 numbers (4x4 camera-to-world), got {len(vals)}")
  m = np.array(vals, dtype=np.float64).reshape(4, 4)
  if not np.all(np.isfinite(m)):
    raise DataError(path, "non-finite pose")
  return m

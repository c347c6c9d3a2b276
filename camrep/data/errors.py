"""Errors raised on bad input data: always name the file (or directory) and the problem."""

from __future__ import annotations

import os


class DataError(ValueError):
  """Bad input data. The message starts with the offending path, then says what is wrong."""

  def __init__(self, path: str | os.PathLike | None, problem: str):
    self.path = None if path is None else os.fspath(path)
    self.problem = problem
    super().__init__(f"{self.path}: {problem}" if self.path else problem)

"""The workdir of a run: checked before any work starts, and its config read back."""

from __future__ import annotations

import json
import os
import tempfile

import jax
import ml_collections

from camrep.runtime import writers

Array = jax.Array


class WorkdirError(RuntimeError):
  """The workdir cannot be created or written to."""


def check_workdir(workdir: str) -> None:
  """Creates `workdir` and writes / removes a probe file there, so that a bad workdir fails at
  once with a message naming it, not after minutes of data loading and compilation.

  Raises:
    WorkdirError: the directory cannot be created or written (permissions, a file in the way,
      a read-only or full file system).
  """
  try:
    os.makedirs(workdir, exist_ok=True)
    fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=workdir)
    os.close(fd)
    os.remove(probe)
  except OSError as e:
    raise WorkdirError(f"workdir {workdir} cannot be written: {e.strerror or e}") from e


def read_config(workdir: str) -> ml_collections.ConfigDict:
  """workdir/config.json (written by `writers.MetricWriter.write_config`) as a ConfigDict.

  Raises:
    FileNotFoundError: no such workdir, or it has no config.json.
  """
  if not os.path.isdir(workdir):
    raise FileNotFoundError(f"workdir {workdir!r} does not exist")
  path = os.path.join(workdir, writers.CONFIG_FILE)
  if not os.path.exists(path):
    raise FileNotFoundError(
      f"{path} not found: {workdir!r} is not a camrep training workdir "
      "(`python -m camrep.main --config=... --workdir=DIR` writes it)"
    )
  with open(path, encoding="utf-8") as f:
    return ml_collections.ConfigDict(json.load(f))

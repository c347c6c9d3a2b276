"""A training workdir's records read back: final_metrics.json (whether and where its run
completed) and the latest logged scalars. The run frame (`camrep.runtime.frame`) writes them:
final_metrics.json atomically, marked `"complete": false` before an extended run writes anything
else, so a killed run never leaves a record that says it completed.
"""

from __future__ import annotations

import json
import os
from typing import Any

from camrep.runtime import writers
from camrep.runtime.checkpoint import CHECKPOINT_SUBDIR

FINAL_FILE = "final_metrics.json"


def has_checkpoints(workdir: str) -> bool:
  d = os.path.join(workdir, CHECKPOINT_SUBDIR)
  return os.path.isdir(d) and any(name.isdigit() for name in os.listdir(d))


def read_final(workdir: str) -> dict[str, Any] | None:
  """workdir/final_metrics.json, or None when there is none or it cannot be read."""
  try:
    with open(os.path.join(workdir, FINAL_FILE), encoding="utf-8") as f:
      final = json.load(f)
  except (OSError, json.JSONDecodeError):
    return None
  return final if isinstance(final, dict) else None


def is_complete(workdir: str, total_steps: int | None = None) -> bool:
  """Whether final_metrics.json records a completed run (at `total_steps`, when given)."""
  final = read_final(workdir)
  if not final or final.get("complete") is not True:
    return False
  return total_steps is None or final.get("step") == int(total_steps)


def last_logged(workdir: str) -> dict[str, float]:
  """The latest value of every train/ and eval/ scalar in metrics.jsonl."""
  last = {}
  for row in writers.read_metrics(workdir):
    last.update({k: v for k, v in row.items() if k.startswith(("train/", "eval/"))})
  return last

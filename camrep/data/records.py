"""The one record format every camrep data source produces.

A *view record* is one posed image:

  {"image": uint8 (H, W, 3) RGB,
   "pose":  float32 (P,), the source's pose in physical units (its columns:
            `camrep.data.sources.get(name).pose_names`),
   "scene": int, index of the scene / instance / area within the source,
   "view":  int, index of the view within its scene (stable, 0-based)}

Pose conventions (radians for angles, the dataset's own length unit for positions):

  rooms, gqn         (x, y, yaw)            x, y in [-1, 1]; yaw wrapped to [0, 2 pi)
  object, srn_cars   (azimuth, polar)       azimuth in [0, 2 pi), polar angle in [0, pi]
  area, gibson       (x, y, yaw)            x, y in metres within [0, 2]; yaw in [0, 2 pi)
  scene6dof, seven_scenes (x, y, z, theta, phi, psi)
                                            translation re-based by the training minimum (m);
                                            Euler angles shifted to be >= 0 (see seven_scenes.py)

Splits: "train"; "test" (held-out views of the training scenes); "test_scenes" (held-out whole
scenes, for the families that have them).

A prepared captures dataset also says what its instances are called and how its splits were made
(`naming`, `split_summary`): results name captures, not scene ids. `digest` is the one hash of
record metadata: a capture source's inputs and a run's data fingerprint
(`camrep.data.feed.fingerprint`).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Any

import numpy as np

RECORD_KEYS = ("image", "pose", "scene", "view")


def digest(value: Any) -> str:
  """ "sha256:<hex>" of `value` as canonical JSON (sorted keys, no spaces)."""
  text = json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)
  return "sha256:" + hashlib.sha256(text.encode("utf-8")).hexdigest()


# ---------------------------------------------------------------------------------------------
# What a prepared dataset's instances are called and how its splits were made (captures record
# both in camrep_source.json's "source_info"; other sources name nothing here).


def capture_facts(metadata: Mapping[str, Any]) -> list[dict[str, Any]]:
  """The per-capture facts of a prepared captures dataset (`CaptureSource.describe`), or []."""
  info = metadata.get("source_info") or {}
  return list(info.get("captures", [])) if info.get("kind") == "captures" else []


def validation_every(fraction: float) -> int:
  """k of a captures dataset's validation views (`validation_rows`): k = round(1 / fraction), at
  least 2."""
  return max(2, round(1.0 / fraction))


def validation_rows(scene: np.ndarray, view: np.ndarray, every: int) -> np.ndarray:
  """Which training views of a captures dataset validate: per capture every `every`-th view by
  view id from view every // 2 on, never the last one (so each lies between training views, as
  the held-out test views do); a capture with fewer views gives its middle view; one view alone
  stays in training. The one rule of both stages: the regression's validation split
  (`regression.views.split_validation`) and the held-out views of a view-synthesis run with
  `--config.evals.split=validation` (`synthesis.components.make_pipeline`), both carved from the
  prepared "train" split when it is read.

  Args:
    scene: int (N,) scene ids of the training views.
    view: int (N,) their view ids.
    every: k (`validation_every`).

  Returns:
    bool (N,): True for a validation view.
  """
  scene, view = np.asarray(scene), np.asarray(view)
  out = np.zeros(len(scene), bool)
  for s in np.unique(scene):
    rows = np.flatnonzero(scene == s)
    rows = rows[np.argsort(view[rows], kind="stable")]
    picked = rows[every // 2 : len(rows) - 1 : every]
    out[picked if len(picked) else rows[len(rows) // 2 :][:1]] = len(rows) > 1
  return out


def validation_description(fraction: float) -> str:
  """How `validation_rows` chooses a captures dataset's validation views, in words (results.json,
  record.json)."""
  k = validation_every(fraction)
  return (
    f"every {k}th training view of each capture by view id (views {k // 2}, {k // 2 + k}, ..., "
    "never the last), between training views as the held-out test views are; disjoint from test"
  )


def split_summary(metadata: Mapping[str, Any]) -> list[str]:
  """One line per capture: its role, views per split and the rule that made them (prepare's
  summary), e.g. "chair (seen): train 88, val 100, test 12; every 8th view held out (...)"."""
  lines = []
  for c in capture_facts(metadata):
    splits = c.get("splits", {})
    order = [s for s in ("train", "val", "test", "test_scenes") if s in splits]
    counts = ", ".join(f"{s} {splits[s]}" for s in order + sorted(set(splits) - set(order)))
    lines.append(f"{c.get('name')} ({c.get('role')}): {counts}; {c.get('split_rule')}")
  return lines


def naming(metadata: Mapping[str, Any], splits: Mapping[str, str]) -> dict[str, Any]:
  """What a run's record of its data says about a prepared dataset's instances and splits.

  For a captures dataset: "scene_names" {scene id: capture name} of the seen captures (the ids
  of train, val and test), "test_scene_names" the same for the unseen ones ("test_scenes" ids,
  from 0 on their own), "captures" (name, role, scene id, views per split, split rule), and
  "splits": `splits` with each description replaced by the source's own ("test": held-out
  views of the training captures, per capture how they were chosen). Other datasets: {}.

  Args:
    metadata: the dataset's camrep_source.json.
    splits: {evaluation split: description} as the run would record it.
  """
  caps = capture_facts(metadata)
  if not caps:
    return {}
  seen = [c for c in caps if c.get("role") == "seen"]
  unseen = [c for c in caps if c.get("role") != "seen"]

  def views(group: list[dict[str, Any]], split: str) -> str:
    return "; ".join(
      f"{c['name']}: {c.get('splits', {}).get(split, 0)} views, {c.get('split_rule')}"
      for c in group
    )

  described = {
    "train": f"training views of the seen captures ({views(seen, 'train')})",
    "val": f"the captures' own val views ({views(seen, 'val')})",
    "test": f"held-out views of the training captures ({views(seen, 'test')})",
    "test_scenes": f"whole captures held out as novel instances ({views(unseen, 'test_scenes')})",
  }
  out: dict[str, Any] = {
    "scene_names": {str(c["scene"]): c["name"] for c in seen},
    "captures": [
      {k: c.get(k) for k in ("name", "role", "scene", "splits", "split_rule")} for c in caps
    ],
    "splits": {name: described.get(name, text) for name, text in splits.items()},
  }
  if unseen:
    out["test_scene_names"] = {str(c["scene"]): c["name"] for c in unseen}
  return out


def scene_name_column(
  data_info: Mapping[str, Any], split: str, scene_ids: np.ndarray
) -> dict[str, np.ndarray]:
  """{"scene_name": (N,) str} for per-example files (errors_<split>.npz), from a run's record
  of its data (`naming`'s "scene_names" / "test_scene_names"); {} when it names no scenes.

  Args:
    data_info: results.json's "data".
    split: the evaluation split.
    scene_ids: (N,) int scene ids of the examples.
  """
  names = data_info.get("scene_names") or {}
  if split == "test_scenes" and "test_scene_names" in data_info:
    names = data_info["test_scene_names"]
  if not names:
    return {}
  ids = np.asarray(scene_ids).reshape(-1)
  return {"scene_name": np.asarray([str(names.get(str(int(i)), "")) for i in ids], dtype=str)}


def instances_clause(data_info: Mapping[str, Any]) -> str:
  """ "; instances: NAME (N test views: RULE), ..." for a table's data line, from a run's record
  of a captures dataset (`naming`); "" for other data (their tables read as before)."""
  caps = data_info.get("captures")
  if not caps:
    return ""
  split = data_info.get("test_split", "test")
  key = "test_scenes" if split == "test_scenes" else split
  parts = [
    f"{c['name']} ({c.get('splits', {}).get(key, 0)} {key} views: {c.get('split_rule')})"
    for c in caps
    if (c.get("role") == "seen") != (key == "test_scenes")
  ]
  return "; instances: " + ", ".join(parts)

"""Writes a PNG grid of procedural views (scenes as rows, views as columns) with their poses:
`python -m camrep.data.show --family=rooms --out=/tmp/rooms.png [--scenes=4 --views=6]`.

Lets a person look at the data. Each cell shows one view, upscaled to at least 128 px, with the
pose printed underneath (angles in degrees, marked "d"; positions in the family's units).

Usage:
  python -m camrep.data.show --family=rooms --out=/tmp/rooms.png
  python -m camrep.data.show --family=object --out=/tmp/object.png --scenes=4 --views=6 \
      --size=64 --split=test_scenes
  python -m camrep.data.show --family=scene6dof --out=/tmp/6dof.png --preset=small

Families: rooms, object, area, scene6dof (see `camrep.data.procedural`). For scene6dof the
views are spread evenly along the scene's trajectory; for the others they are the first ones.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

import cv2
import numpy as np
from absl import flags

from camrep.data import procedural
from camrep.runtime import cli

_ANGLES = {"yaw", "azimuth", "polar", "theta", "phi", "psi"}
_SHORT = {"azimuth": "az", "polar": "pol", "theta": "th", "phi": "ph", "psi": "ps"}


def pose_lines(pose: np.ndarray, names: Sequence[str]) -> list[str]:
  """Human-readable pose text, at most three components a line.

  Args:
    pose: (P,) pose.
    names: P component names.

  Returns:
    Lines such as ["x=0.12 y=-0.40 yaw=231d"].
  """
  parts = []
  for value, name in zip(pose, names, strict=True):
    label = _SHORT.get(name, name)
    parts.append(f"{label}={np.rad2deg(value):.0f}d" if name in _ANGLES else f"{label}={value:.2f}")
  return [" ".join(parts[i : i + 3]) for i in range(0, len(parts), 3)]


def make_grid(
  family: procedural.ProceduralFamily, *, split: str, num_scenes: int, num_views: int
) -> np.ndarray:
  """Renders the grid image.

  Args:
    family: a procedural family.
    split: split to show.
    num_scenes: rows (the split's first scenes).
    num_views: columns.

  Returns:
    (rows * (cell + caption), columns * cell, 3) uint8 RGB.
  """
  cell = max(128, family.image_size)
  lines = (len(family.pose_names) + 2) // 3
  caption = 14 * lines + 6
  rows = []
  for scene in list(family.scene_ids(split))[:num_scenes]:
    poses = family.poses(split, scene)
    if family.name == "scene6dof":
      poses = poses[np.linspace(0, len(poses) - 1, num_views).round().astype(int)]
    poses = poses[:num_views]
    images = family.render_views(scene, poses)
    cells = []
    for image, pose in zip(images, poses, strict=True):
      big = cv2.resize(image, (cell, cell), interpolation=cv2.INTER_NEAREST)
      band = np.full((caption, cell, 3), 255, np.uint8)
      for k, text in enumerate(pose_lines(pose, family.pose_names)):
        cv2.putText(
          band, text, (3, 13 + 14 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.32, (0, 0, 0), 1, cv2.LINE_AA
        )
      cells.append(np.concatenate([big, band], axis=0))
    cells += [np.full_like(cells[0], 255)] * (num_views - len(cells))
    rows.append(np.concatenate(cells, axis=1))
  return np.concatenate(rows, axis=0)


def define_flags(fv: flags.FlagValues, argv: Sequence[str] = ()) -> None:
  """The tool's flags (`camrep.runtime.cli.Define`)."""
  del argv
  flags.DEFINE_enum("family", None, procedural.FAMILIES, "Procedural family.", flag_values=fv)
  flags.DEFINE_string("out", None, "Output PNG path.", flag_values=fv)
  flags.DEFINE_integer(
    "scenes", 4, "Rows (the split's first scenes).", lower_bound=1, flag_values=fv
  )
  flags.DEFINE_integer("views", 6, "Columns.", lower_bound=1, flag_values=fv)
  flags.DEFINE_integer(
    "size", None, "Image size (default: the family's).", lower_bound=1, flag_values=fv
  )
  flags.DEFINE_enum("split", "train", ("train", "test", "test_scenes"), "Split.", flag_values=fv)
  flags.DEFINE_enum("preset", "default", procedural.PRESETS, "Family preset.", flag_values=fv)
  flags.DEFINE_integer("seed", 0, "Family seed.", lower_bound=0, flag_values=fv)
  flags.mark_flags_as_required(["family", "out"], flag_values=fv)


def run_cli(fv: flags.FlagValues) -> int:
  """The tool (`camrep.runtime.cli.Body`)."""
  overrides = dict(seed=fv.seed, batch_size=fv.views)
  if fv.size:
    overrides["image_size"] = fv.size
  try:
    family = procedural.make_family(fv.family, fv.preset, **overrides)
  except (TypeError, ValueError) as e:
    raise cli.UsageError(f"--family={fv.family}: {e}") from None
  if fv.split not in family.splits:
    raise cli.UsageError(f"--split={fv.split}: family {fv.family!r} has {list(family.splits)}")
  grid = make_grid(family, split=fv.split, num_scenes=fv.scenes, num_views=fv.views)
  ok, png = cv2.imencode(".png", cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
  if not ok:
    raise RuntimeError("cv2 could not encode the PNG")
  tmp = f"{fv.out}.tmp"
  try:  # written whole or not at all (a full disk leaves no cut PNG)
    with open(tmp, "wb") as f:
      f.write(png.tobytes())
    os.replace(tmp, fv.out)
  except OSError:
    if os.path.exists(tmp):
      os.remove(tmp)
    raise
  height, width = grid.shape[:2]
  print(f"wrote {fv.out}: {width}x{height} px, family {family.name}, split {fv.split}")
  return 0


def main(argv: Sequence[str] | None = None) -> int:
  """In-process entry (tests): `argv` are the flags; returns the exit status."""
  return cli.call(define_flags, run_cli, sys.argv[1:] if argv is None else argv, prog=__name__)


if __name__ == "__main__":
  cli.main(define_flags, run_cli)

"""Writes a PNG grid of procedural views (scenes as rows, views as columns) with their poses.

Lets a person look at the data. Each cell shows one view, upscaled to at least 128 px, with the
pose printed underneath (angles in degrees, marked "d"; positions in the family's units).

Usage:
  python -m camrep.data.show --family rooms --out /tmp/rooms.png
  python -m camrep.data.show --family object --out /tmp/object.png --scenes 4 --views 6 \
      --size 64 --split test_scenes
  python -m camrep.data.show --family scene6dof --out /tmp/6dof.png --preset small

Families: rooms, object, area, scene6dof (see `camrep.data.procedural`). For scene6dof the
views are spread evenly along the scene's trajectory; for the others they are the first ones.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import cv2
import numpy as np

from camrep.data import procedural

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


def main(argv: Sequence[str] | None = None) -> None:
  """Command-line entry point (see the module docstring)."""
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--family", required=True, choices=procedural.FAMILIES)
  parser.add_argument("--out", required=True, help="output PNG path")
  parser.add_argument("--scenes", type=int, default=4, help="rows")
  parser.add_argument("--views", type=int, default=6, help="columns")
  parser.add_argument("--size", type=int, default=None, help="image size (default: the family's)")
  parser.add_argument("--split", default="train")
  parser.add_argument("--preset", default="default", choices=procedural.PRESETS)
  parser.add_argument("--seed", type=int, default=0)
  args = parser.parse_args(argv)
  overrides = dict(seed=args.seed, batch_size=args.views)
  if args.size:
    overrides["image_size"] = args.size
  family = procedural.make_family(args.family, args.preset, **overrides)
  grid = make_grid(family, split=args.split, num_scenes=args.scenes, num_views=args.views)
  if not cv2.imwrite(args.out, cv2.cvtColor(grid, cv2.COLOR_RGB2BGR)):
    raise OSError(f"{args.out}: could not write the PNG")
  height, width = grid.shape[:2]
  print(f"wrote {args.out}: {width}x{height} px, family {family.name}, split {args.split}")


if __name__ == "__main__":
  main()

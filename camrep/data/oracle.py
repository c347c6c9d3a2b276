"""How observable a family's poses are: a nearest-neighbour oracle (issues 16 and 18).

For each query view, the reference view (of the same scene) with the smallest pixel distance
lends its pose. If images and pose labels agree, the oracle's errors fall far below chance once
the references are dense enough; if they are misaligned anywhere (a shuffled cache, a yaw sign),
it stays at chance whatever the density. The same numbers say how much a single view of a scene
tells about its pose at the density a run trains on: the floor a regressor has to beat without
geometry.

  python -m camrep.data.oracle --family rooms --scenes 30 --train_views 10 [--override k=v ...]
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence

import numpy as np

from camrep.data import procedural


def _wrap(d: np.ndarray) -> np.ndarray:
  return np.abs((d + np.pi) % (2 * np.pi) - np.pi)


def nearest_view_poses(
  queries: np.ndarray, references: np.ndarray, reference_poses: np.ndarray
) -> np.ndarray:
  """The pose of each query's nearest reference view in pixel L2.

  Args:
    queries: (Q, H, W, C) images (any dtype). references: (R, H, W, C). reference_poses: (R, P).

  Returns:
    (Q, P) poses.
  """
  q = queries.reshape(len(queries), -1).astype(np.float32)
  r = references.reshape(len(references), -1).astype(np.float32)
  d = (q * q).sum(1)[:, None] - 2 * q @ r.T + (r * r).sum(1)[None, :]
  return reference_poses[np.argmin(d, axis=1)]


def pose_errors(pred: np.ndarray, true: np.ndarray, angular: Sequence[bool]) -> np.ndarray:
  """|pred - true| per column, angles wrapped to [0, pi]: (N, P)."""
  d = np.abs(pred - true)
  ang = np.asarray(angular, bool)
  d[:, ang] = _wrap(pred[:, ang] - true[:, ang])
  return d


def run(
  family: procedural.ProceduralFamily,
  *,
  num_scenes: int,
  query_split: str = "test",
  seed: int = 0,
) -> dict:
  """The oracle on the first `num_scenes` training scenes: queries from `query_split`, references
  the scene's training views; beside it the chance level (a random reference view's pose) and the
  control (the oracle with the reference labels permuted within each scene: a misalignment).

  Returns:
    {"columns", "num_queries", and per column (angles in degrees) "oracle_mean",
     "oracle_median", "control_median", "chance_mean", "chance_median"}.
  """
  rng = np.random.default_rng(seed)
  names = family.pose_names
  angular = [n in ("yaw", "azimuth", "polar", "theta", "phi", "psi") for n in names]
  oracle, control, chance = [], [], []
  for s in range(num_scenes):
    ref_p, q_p = family.poses("train", s), family.poses(query_split, s)
    ref_i, q_i = family.render_views(s, ref_p), family.render_views(s, q_p)
    oracle.append(pose_errors(nearest_view_poses(q_i, ref_i, ref_p), q_p, angular))
    shuffled = rng.permutation(ref_p)
    control.append(pose_errors(nearest_view_poses(q_i, ref_i, shuffled), q_p, angular))
    chance.append(pose_errors(ref_p[rng.integers(len(ref_p), size=len(q_p))], q_p, angular))
  oracle, control, chance = (np.concatenate(x) for x in (oracle, control, chance))
  scale = np.where(angular, 180 / np.pi, 1.0)

  def stat(f, x):
    return {n: float(v) for n, v in zip(names, f(x, axis=0) * scale, strict=True)}

  return {
    "columns": list(names),
    "num_queries": len(oracle),
    "oracle_mean": stat(np.mean, oracle),
    "oracle_median": stat(np.median, oracle),
    "control_median": stat(np.median, control),
    "chance_mean": stat(np.mean, chance),
    "chance_median": stat(np.median, chance),
  }


def main(argv: Sequence[str] | None = None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--family", default="rooms", choices=sorted(procedural.FAMILIES))
  p.add_argument("--preset", default="small")
  p.add_argument("--scenes", type=int, default=30)
  p.add_argument("--train_views", type=int, default=10)
  p.add_argument("--test_views", type=int, default=2)
  p.add_argument("--override", action="append", default=[], help="family field=python literal")
  args = p.parse_args(argv)
  import ast

  fields = {k: ast.literal_eval(v) for k, v in (o.split("=", 1) for o in args.override)}
  if args.family != "scene6dof":  # the 7-Scenes trajectories fix their own views
    fields.update(train_views=args.train_views, test_views=args.test_views)
    fields.setdefault("num_train_scenes", args.scenes)
  fam = procedural.make_family(args.family, preset=args.preset, **fields)
  out = run(fam, num_scenes=args.scenes)
  print(json.dumps(out, indent=1))
  return 0


if __name__ == "__main__":
  raise SystemExit(main())

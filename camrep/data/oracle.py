"""How observable a family's poses are: a nearest-neighbour oracle:
`python -m camrep.data.oracle --family=rooms --scenes=30 --train_views=10 [--config.FIELD=VALUE]`.

For each query view, the reference view (of the same scene) with the smallest pixel distance
lends its pose. If images and pose labels agree, the oracle's errors fall far below chance once
the references are dense enough; if they are misaligned anywhere (a shuffled cache, a yaw sign),
it stays at chance whatever the density. The same numbers say how much a single view of a scene
tells about its pose at the density a run trains on: the floor a regressor has to beat without
geometry.

`--config.FIELD=VALUE` overrides a field of the family's config (`camrep.data.procedural`), typed
as the field's default (e.g. `--config.wall_style=compass`, `--config.texture_contrast=0,0.08`).
Prints the result as JSON. Exit status as every camrep tool (`camrep.runtime.cli`).
"""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Sequence

import numpy as np
from absl import flags

from camrep.data import procedural
from camrep.runtime import cli


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


def define_flags(fv: flags.FlagValues, argv: Sequence[str] = ()) -> None:
  """The tool's flags (`camrep.runtime.cli.Define`); `--config.` are the chosen family's fields."""
  flags.DEFINE_enum("family", "rooms", procedural.FAMILIES, "Procedural family.", flag_values=fv)
  flags.DEFINE_enum("preset", "small", procedural.PRESETS, "Family preset.", flag_values=fv)
  flags.DEFINE_integer("scenes", 30, "Training scenes queried.", lower_bound=1, flag_values=fv)
  flags.DEFINE_integer(
    "train_views", 10, "Reference views per scene.", lower_bound=1, flag_values=fv
  )
  flags.DEFINE_integer("test_views", 2, "Query views per scene.", lower_bound=1, flag_values=fv)
  family = cli.peek_flag(argv, "family", "rooms")
  if family in procedural.FAMILIES:
    cli.define_overrides(
      fv,
      argv,
      dataclasses.asdict(procedural.make_config(family)),
      f"A field of the {family!r} family's config.",
    )


def run_cli(fv: flags.FlagValues) -> int:
  """The tool (`camrep.runtime.cli.Body`)."""
  fields = cli.overrides(fv)
  if fv.family != "scene6dof":  # the 7-Scenes trajectories fix their own views
    fields.update(train_views=fv.train_views, test_views=fv.test_views)
    fields.setdefault("num_train_scenes", fv.scenes)
  try:
    fam = procedural.make_family(fv.family, preset=fv.preset, **fields)
  except (TypeError, ValueError) as e:
    raise cli.UsageError(f"--family={fv.family} with {fields}: {e}") from None
  out = run(fam, num_scenes=fv.scenes)
  print(json.dumps(out, indent=1))
  return 0


def main(argv: Sequence[str] | None = None) -> int:
  """In-process entry (tests): `argv` are the flags; returns the exit status."""
  return cli.call(define_flags, run_cli, sys.argv[1:] if argv is None else argv, prog=__name__)


if __name__ == "__main__":
  cli.main(define_flags, run_cli)

"""Normalising a capture's cameras to a camrep setting.

Car setting (object-centric captures, SRN-cars-like): the world is moved so that the origin is
the point nearest to every camera's optical axis (least squares) and rotated so that the mean
camera "up" (-y in OpenCV axes) is +z, then scaled so that the median camera distance is 1. The
car pose (azimuth, polar) of a view is then that of its camera centre on a z-up sphere, as for SRN
cars (`camrep.data.srn.c2w_to_angles`). How well the cameras look at one point is measured per
view: the distance from the centre to the optical axis (in the capture's units and after
scaling) and the angle between the axis and the ray to the centre (degrees). A capture whose
median angle exceeds `max_residual_deg` (or with a camera facing away from the centre) is not
object-centric: `NotObjectCentricError` says so and names the 6-DOF route.

6-DOF setting (forward-facing or walk-through captures, 7-Scenes-like): the capture's own world
frame, uniformly scaled so that the training cameras' positions span at most the 7-Scenes grid
cuboid, then `camrep.data.seven_scenes.c2w_to_dofs` (translation re-based by the training
minimum, Euler angles shifted to be >= 0).

Both are similarity transforms stored in the dataset metadata (`Normalization.to_json`), so
recovered camera positions can be mapped back to the source file's (`Normalization.undo`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from camrep.data.captures.cameras import CaptureError

DEFAULT_MAX_RESIDUAL_DEG = 10.0
"""Largest median angle (degrees) between a view's optical axis and the ray to the centre for an
object-centric capture."""


class NotObjectCentricError(CaptureError):
  """The cameras do not look at a common point: the car setting would mis-pose them."""


@dataclasses.dataclass(frozen=True)
class Normalization:
  """A similarity transform of the world: p_new = scale * R (p - centre).

  Attributes:
    centre: (3,) float64, in the source's world frame.
    rotation: (3, 3) float64 R, source world axes -> normalised axes.
    scale: float.
  """

  centre: np.ndarray
  rotation: np.ndarray
  scale: float

  def apply(self, c2w: np.ndarray) -> np.ndarray:
    """(..., 4, 4) camera-to-world in the source world -> in the normalised world."""
    c2w = np.asarray(c2w, np.float64)
    out = c2w.copy()
    out[..., :3, :3] = self.rotation @ c2w[..., :3, :3]
    out[..., :3, 3] = self.scale * (c2w[..., :3, 3] - self.centre) @ self.rotation.T
    return out

  def undo(self, c2w: np.ndarray) -> np.ndarray:
    """Inverse of `apply`."""
    c2w = np.asarray(c2w, np.float64)
    out = c2w.copy()
    out[..., :3, :3] = self.rotation.T @ c2w[..., :3, :3]
    out[..., :3, 3] = (c2w[..., :3, 3] / self.scale) @ self.rotation + self.centre
    return out

  def undo_points(self, p: np.ndarray) -> np.ndarray:
    """(..., 3) normalised positions -> source world positions."""
    return (np.asarray(p, np.float64) / self.scale) @ self.rotation + self.centre

  def to_json(self) -> dict[str, Any]:
    return {
      "centre": self.centre.tolist(),
      "rotation": self.rotation.tolist(),
      "scale": float(self.scale),
      "formula": "p_normalised = scale * rotation @ (p_source - centre)",
    }

  @classmethod
  def from_json(cls, d: dict[str, Any]) -> Normalization:
    return cls(
      np.asarray(d["centre"], np.float64), np.asarray(d["rotation"], np.float64), float(d["scale"])
    )


def nearest_point_to_axes(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
  """The point p minimising sum_i |(I - d_i d_i^T)(p - o_i)|^2 (distance to each line).

  Args:
    origins: (N, 3) camera centres.
    dirs: (N, 3) optical axes (any norm > 0).

  Returns:
    (3,) float64.

  Raises:
    CaptureError: the lines are (near) parallel, so no point is nearest to all of them.
  """
  d = np.asarray(dirs, np.float64)
  d = d / np.linalg.norm(d, axis=-1, keepdims=True)
  proj = np.eye(3) - d[:, :, None] * d[:, None, :]  # (N, 3, 3)
  a = proj.sum(0)
  b = np.einsum("nij,nj->i", proj, np.asarray(origins, np.float64))
  if np.linalg.cond(a) > 1e8:
    raise NotObjectCentricError(
      None, "the optical axes are (nearly) parallel: no point is nearest to all of them"
    )
  return np.linalg.solve(a, b)


def axis_residuals(
  centre: np.ndarray, origins: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
  """How far each optical axis passes from `centre`.

  Returns:
    distance: (N,) distance from the centre to the axis line.
    angle_deg: (N,) angle between the axis and the ray from the camera to the centre, in
      [0, 180] (over 90: the centre is behind the camera).
  """
  d = np.asarray(dirs, np.float64)
  d = d / np.linalg.norm(d, axis=-1, keepdims=True)
  v = np.asarray(centre, np.float64) - np.asarray(origins, np.float64)
  along = np.einsum("ni,ni->n", v, d)
  perp = np.linalg.norm(v - along[:, None] * d, axis=-1)
  return perp, np.degrees(np.arctan2(perp, along))


def rotation_to_z(up: np.ndarray) -> np.ndarray:
  """(3, 3) the smallest rotation taking the unit vector `up` to +z (Rodrigues)."""
  u = np.asarray(up, np.float64) / np.linalg.norm(up)
  z = np.array([0.0, 0.0, 1.0])
  c = float(u @ z)
  if c < -1.0 + 1e-12:
    return np.diag([1.0, -1.0, -1.0])  # half turn about x
  k = np.cross(u, z)
  kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
  return np.eye(3) + kx + kx @ kx / (1.0 + c)


def residual_summary(distance: np.ndarray, angle_deg: np.ndarray) -> dict[str, float]:
  """Median / mean / max of the residuals (JSON-ready)."""
  return {
    "angle_deg_median": float(np.median(angle_deg)),
    "angle_deg_mean": float(np.mean(angle_deg)),
    "angle_deg_max": float(np.max(angle_deg)),
    "distance_median": float(np.median(distance)),
    "distance_max": float(np.max(distance)),
  }


def object_centric(
  c2w: np.ndarray,
  *,
  max_residual_deg: float = DEFAULT_MAX_RESIDUAL_DEG,
  where: str | None = None,
) -> tuple[Normalization, dict[str, Any]]:
  """The car-setting normalisation of an object-centric capture (see the module docstring).

  Args:
    c2w: (N, 4, 4) camera-to-world, OpenCV axes, N >= 2.
    max_residual_deg: largest accepted median axis angle.
    where: the capture, for messages.

  Returns:
    The `Normalization` and a report: residuals before refusal (`residual_summary`, distances in
    normalised units), per-view angles, the mean-up alignment.

  Raises:
    NotObjectCentricError: parallel axes, a median angle above `max_residual_deg`, or a camera
      with the centre behind it.
  """
  c2w = np.asarray(c2w, np.float64)
  if c2w.ndim != 3 or c2w.shape[0] < 2:
    raise NotObjectCentricError(where, f"need at least 2 cameras, got {c2w.shape[:-2]}")
  origins, dirs = c2w[:, :3, 3], c2w[:, :3, 2]
  try:
    centre = nearest_point_to_axes(origins, dirs)
  except NotObjectCentricError as e:
    raise NotObjectCentricError(where, e.problem + _ROUTE) from None
  dist, angle = axis_residuals(centre, origins, dirs)
  radius = np.linalg.norm(origins - centre, axis=-1)
  scale = 1.0 / float(np.median(radius)) if np.median(radius) > 0 else 1.0
  up = -c2w[:, :3, 1].mean(0)  # OpenCV "up" is -y
  up_norm = float(np.linalg.norm(up))
  rot = rotation_to_z(up if up_norm > 1e-9 else np.array([0.0, 0.0, 1.0]))
  summary = residual_summary(dist * scale, angle)
  report = {
    "residuals": summary,
    "angle_deg": np.round(angle, 4).tolist(),
    "mean_up_length": up_norm,
    "max_residual_deg": float(max_residual_deg),
  }
  if summary["angle_deg_median"] > max_residual_deg or summary["angle_deg_max"] >= 90.0:
    worst = int(np.argmax(angle))
    raise NotObjectCentricError(
      where,
      f"optical axes pass {summary['angle_deg_median']:.1f} deg (median; max "
      f"{summary['angle_deg_max']:.1f} deg at view {worst}) from their nearest common point, more "
      f"than max_residual_deg={max_residual_deg:g}"
      + (" (a camera faces away from it)" if summary["angle_deg_max"] >= 90.0 else "")
      + _ROUTE,
    )
  return Normalization(centre, rot, scale), report


_ROUTE = (
  ": the capture does not look at one object, so the car setting (azimuth, polar around a "
  "centre) would mis-pose it; prepare it in the 6-DOF setting instead (--source "
  "nerf_6dof / llff_6dof / colmap_6dof), or accept it with --config.max_residual_deg=DEG"
)


def six_dof(c2w_train: np.ndarray, *, extent: Sequence[float]) -> Normalization:
  """The 6-DOF normalisation: the source world, scaled so the training positions span at most
  `extent` (no rotation; the re-basing by the minimum is `seven_scenes.c2w_to_dofs`'s).

  Args:
    c2w_train: (N, 4, 4) training cameras.
    extent: (3,) the grid cuboid.
  """
  p = np.asarray(c2w_train, np.float64)[:, :3, 3]
  span = p.max(0) - p.min(0)
  ext = np.asarray(extent, np.float64)
  ratios = np.where(span > 1e-12, ext / np.maximum(span, 1e-12), np.inf)
  scale = float(ratios.min()) if np.isfinite(ratios.min()) else 1.0
  return Normalization(np.zeros(3), np.eye(3), scale)

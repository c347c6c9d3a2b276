"""Normalising a capture's cameras to a camrep setting.

Car setting (object-centric captures, SRN-cars-like): the world is moved so that the origin is
the point nearest to every camera's optical axis (least squares) and rotated so that the
capture's up direction (`up_direction`) is +z, then scaled so that the median camera distance is
1. The car pose (azimuth, polar) of a view is then that of its camera centre on a z-up sphere, as
for SRN cars (`camrep.data.readers.srn.c2w_to_angles`). The centre and the up direction are found
from the camera positions and optical axes only, never from the cameras' own up vectors, so
rolling a camera about its optical axis (a portrait photo among landscape ones) changes no label,
except in the degenerate cases `up_direction` names. How well the cameras look at one point is
measured per view: the distance from the centre to the optical axis (in the capture's units and
after scaling) and the angle between the axis and the ray to the centre (degrees). A capture whose
median angle exceeds `max_residual_deg` (or with a camera facing away from the centre) is not
object-centric: `NotObjectCentricError` says so and names the 6-DOF route.

6-DOF setting (forward-facing or walk-through captures, 7-Scenes-like): the capture's own world
frame, uniformly scaled so that the training cameras' positions span at most the 7-Scenes grid
cuboid, then `camrep.data.readers.seven_scenes.c2w_to_dofs` (translation re-based by the training
minimum, Euler angles shifted to be >= 0).

Both are similarity transforms stored in the dataset metadata (`Normalization.to_json`), so
recovered camera positions can be mapped back to the source file's (`Normalization.undo`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from camrep.data.readers.captures.cameras import CaptureError

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
    up_rule: how R's +z (the up direction) was found (`up_direction`'s rule name), "" when R is
      not about up (the 6-DOF setting's identity).
  """

  centre: np.ndarray
  rotation: np.ndarray
  scale: float
  up_rule: str = ""

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
    out = {
      "centre": self.centre.tolist(),
      "rotation": self.rotation.tolist(),
      "scale": float(self.scale),
      "formula": "p_normalised = scale * rotation @ (p_source - centre)",
    }
    if self.up_rule:
      out["up_rule"] = self.up_rule
      out["up_found_by"] = UP_RULES[self.up_rule]
    return out

  @classmethod
  def from_json(cls, d: dict[str, Any]) -> Normalization:
    return cls(
      np.asarray(d["centre"], np.float64),
      np.asarray(d["rotation"], np.float64),
      float(d["scale"]),
      str(d.get("up_rule", "")),
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


# How `up_direction` found the up direction (recorded as the normalisation's "up_rule").
UP_RULES = {
  "plane": (
    "normal of the best-fit plane of the camera centres, on the side the cameras look from "
    "(independent of camera roll)"
  ),
  "plane_signed_by_camera_up": (
    "normal of the best-fit plane of the camera centres, its sign from the cameras' up vectors "
    "because the cameras sit on both sides of the object alike (the sign depends on roll)"
  ),
  "mean_camera_up": (
    "the cameras' mean up vector (-y), because the camera centres do not determine a plane "
    "(forward-facing, along a line, or all round a sphere; depends on roll)"
  ),
}
FORWARD_CAP_DEG = 15.0
"""Cameras all within this angle of their mean direction from the centre are forward-facing: the
plane of their centres is the image plane, not the horizon."""
PLANE_MIN_SPREAD = 0.05
"""The centres determine a plane when their second-largest spread (RMS, in units of the median
camera distance) is at least this..."""
PLANE_MAX_RATIO = 0.8
"""... and their smallest spread is at most this fraction of the second (else every direction is
about as flat as the normal: cameras all round a sphere)."""
SIDE_MIN = 0.05
"""The plane's normal points to the cameras' side when their mean unit direction from the centre
has at least this component along it; below, the cameras sit on both sides alike."""


def up_direction(c2w: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
  """The capture's up direction, from the camera centres and the object centre.

  Rule ("plane"): the normal n of the plane that best fits the camera centres o_i (the right
  singular vector of the smallest singular value of o_i - mean(o)), oriented to the side the
  cameras look from: n . mean_i((o_i - c) / |o_i - c|) > 0. A ring of cameras around an object,
  a dome above it, or an arc of photos taken walking round it all give their own axis; the
  cameras' up vectors, which a roll about the optical axis changes (portrait photos), are not
  used. Fallbacks, recorded by name (`UP_RULES`), both depending on roll:

  * "plane_signed_by_camera_up": the cameras sit on both sides of the plane through the centre
    alike (|n . mean direction| < `SIDE_MIN`, e.g. a ring at the object's height): the sign of n
    is that of sum_i n . up_i (up_i = -y_i, the camera's up vector).
  * "mean_camera_up": the centres do not determine a plane, either because they lie within
    `FORWARD_CAP_DEG` of one direction from the centre (a forward-facing capture: the plane of
    the centres is the image plane), or their second spread is under `PLANE_MIN_SPREAD` (along a
    line), or their smallest spread exceeds `PLANE_MAX_RATIO` of the second (all round a sphere).
    Up is then the cameras' mean up vector (the rule before plane fitting).

  Args:
    c2w: (N, 4, 4) camera-to-world, OpenCV axes.
    centre: (3,) the object centre (`nearest_point_to_axes`).

  Returns:
    up: (3,) unit vector in the source's world frame.
    info: JSON-ready: "rule" (a key of `UP_RULES`), "spreads" (the three RMS spreads of the
      centres in units of the median camera distance), "cap_deg" (largest angle of a camera from
      the mean direction), "side" (n . mean direction), "mean_up_length" (|mean camera up|).
  """
  c2w = np.asarray(c2w, np.float64)
  origins = c2w[:, :3, 3]
  offsets = origins - np.asarray(centre, np.float64)
  dist = np.linalg.norm(offsets, axis=-1)
  radius = float(np.median(dist)) if np.median(dist) > 0 else 1.0
  unit = offsets / np.maximum(dist, 1e-300)[:, None]
  mean_dir = unit.mean(0)
  mean_len = float(np.linalg.norm(mean_dir))
  if mean_len > 1e-9:
    cos = np.clip(unit @ (mean_dir / mean_len), -1.0, 1.0)
    cap = float(np.degrees(np.arccos(cos.min())))
  else:
    cap = 180.0
  _, sv, vt = np.linalg.svd(origins - origins.mean(0), full_matrices=True)
  spreads = np.zeros(3)
  spreads[: len(sv)] = sv / np.sqrt(len(origins)) / radius
  normal = vt[2]
  side = float(normal @ mean_dir)
  mean_up = -c2w[:, :3, 1].mean(0)
  mean_up_len = float(np.linalg.norm(mean_up))
  info = {
    "spreads": [round(float(x), 6) for x in spreads],
    "cap_deg": round(cap, 4),
    "side": round(abs(side), 6),
    "mean_up_length": mean_up_len,
  }
  flat = spreads[1] >= PLANE_MIN_SPREAD and spreads[2] <= PLANE_MAX_RATIO * spreads[1]
  if cap < FORWARD_CAP_DEG or not flat:
    up = mean_up / mean_up_len if mean_up_len > 1e-9 else np.array([0.0, 0.0, 1.0])
    return up, {"rule": "mean_camera_up", **info}
  if abs(side) >= SIDE_MIN:
    return normal * np.sign(side), {"rule": "plane", **info}
  vote = float((c2w[:, :3, 1] @ normal).sum())  # -sum_i n . up_i
  return normal * (-1.0 if vote > 0 else 1.0), {"rule": "plane_signed_by_camera_up", **info}


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
    normalised units), per-view angles, how the up direction was found (`up_direction`'s info).

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
  up, up_info = up_direction(c2w, centre)
  rot = rotation_to_z(up)
  summary = residual_summary(dist * scale, angle)
  report = {
    "residuals": summary,
    "angle_deg": np.round(angle, 4).tolist(),
    "up": up_info,
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
  return Normalization(centre, rot, scale, up_info["rule"]), report


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

"""The one record format every camrep data source produces.

A *view record* is one posed image:

  {"image": uint8 (H, W, 3) RGB,
   "pose":  float32 (P,), the family's pose in physical units (see `POSE_NAMES`),
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
"""

from __future__ import annotations

POSE_NAMES: dict[str, tuple[str, ...]] = {
  "rooms": ("x", "y", "yaw"),
  "gqn": ("x", "y", "yaw"),
  "object": ("azimuth", "polar"),
  "srn_cars": ("azimuth", "polar"),
  "area": ("x", "y", "yaw"),
  "gibson": ("x", "y", "yaw"),
  "scene6dof": ("x", "y", "z", "theta", "phi", "psi"),
  "seven_scenes": ("x", "y", "z", "theta", "phi", "psi"),
  # Posed captures (camrep.data.captures): object-centric (car) or 6-DOF.
  **{f: ("azimuth", "polar") for f in ("nerf", "llff", "colmap")},
  **{f"{f}_6dof": ("x", "y", "z", "theta", "phi", "psi") for f in ("nerf", "llff", "colmap")},
}

RECORD_KEYS = ("image", "pose", "scene", "view")


# The procedural family that stands in for each setting's real dataset.
SOURCE_OF_SETTING = {"gqn": "rooms", "car": "object", "gibson": "area", "seven_scenes": "scene6dof"}
SETTINGS = tuple(SOURCE_OF_SETTING)
PROCEDURAL = ("rooms", "object", "area", "scene6dof")


SETTING_OF_SOURCE = {
  "rooms": "gqn",
  "gqn": "gqn",
  "object": "car",
  "srn_cars": "car",
  "area": "gibson",
  "gibson": "gibson",
  "scene6dof": "seven_scenes",
  "seven_scenes": "seven_scenes",
  **{f: "car" for f in ("nerf", "llff", "colmap")},
  **{f"{f}_6dof": "seven_scenes" for f in ("nerf", "llff", "colmap")},
}


def setting_of_source(source: str) -> str:
  """The paper's setting (gqn, car, gibson, seven_scenes) of a data source, real or procedural."""
  try:
    return SETTING_OF_SOURCE[source]
  except KeyError:
    raise ValueError(
      f"unknown data source {source!r}; choose one of {sorted(SETTING_OF_SOURCE)}"
    ) from None

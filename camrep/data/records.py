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
"""

from __future__ import annotations

RECORD_KEYS = ("image", "pose", "scene", "view")

"""The camera conditionings of the multi-view transformer (task "mvt") by name, and the cameras
the geometric ones see: `CONDITIONINGS` is the one registry `config.model.camera` reads.

  none         NoCamera: no camera information (the control).
  raymap       (a) Pluecker raymap per pixel, absolute (LVSM).
  gta          (b) GTA, D = the world-to-camera SE(3) matrix, relative.
  gta_so3      (b) GTA on the rotation only (SO(3)), relative.
  prope        (c) PRoPE, D = lift(K) T_cam_world, relative.
  learned_abs  (d) the learned pose vector v(p) of Zhu et al. on every token, absolute.
  learned_rel  (e) M(p) = diag_l exp(B_l p_l) of the same learned generators, relative.

(`camrep.models.camera_conditioning` holds the conditionings and their equations.)

The learned pair (d), (e) share one pose system: the setting's (`components.pose_spec`, config
`rep`) with one DOF per pose column (`camera_conditioning.columnwise`): rooms' polar (x, y) DOF
becomes LinearDof x and y, because (e) needs one generator per coordinate (a polar DOF's
direction-dependent generators do not commute) and (d) then differs from (e) only in how the
same system enters the transformer. (e) needs an exact exponential (`rep.exp_method` "spectral"
or "expm"); the rotation loss of both is `loss.rot_weight` sum_l L_rot,l (eq. 9, extra pairs
`loss.n_pairs`), 0 by default in configs/lvsm.py.

Cameras of (a)-(c) (`cameras`): a procedural rooms or object family's own map from pose columns
to cameras (`camera_conditioning.cameras_of_family`, the family of config `data.preset` and
`data.family`, also for such data prepared to a directory); prepared data of the car setting
(SRN cars, a capture): a camera on the unit sphere looking at the origin, with a nominal field of
view (`NOMINAL_FOV_DEG`): the prepared records hold the pose columns (azimuth, polar) only, and a
capture is normalised to a median camera distance of 1
(`camrep.data.readers.captures.normalize`), so the rotation is exact and the distance and
intrinsics are nominal. Other prepared data is refused for (a)-(c): its pose columns do not give
the camera.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from camrep import pose as P
from camrep import settings
from camrep.data import sources
from camrep.models import camera_conditioning as cc

# Field of view of the car setting's prepared data (the procedural object family's default).
NOMINAL_FOV_DEG = 45.0


@dataclasses.dataclass(frozen=True)
class Inputs:
  """What a conditioning is built from.

  Attributes:
    spec: the setting's pose system (config `rep`).
    cameras: a function giving the setting's `PoseCameras` (raises ValueError where the poses
      do not give the camera); called by the geometric conditionings only.
    rot_weight: lambda_2 of the learned conditionings' rotation loss.
    n_pairs: extra pose pairs per DOF of that loss.
    init_scale: std of the learned relative generators at init.
  """

  spec: P.PoseSystemSpec
  cameras: Callable[[], cc.PoseCameras]
  rot_weight: float = 0.0
  n_pairs: int = 64
  init_scale: float = 2.0


def _learned_abs(i: Inputs) -> cc.CameraConditioning:
  return cc.LearnedAbsolute(cc.columnwise(i.spec), rotation_weight=i.rot_weight, n_pairs=i.n_pairs)


def _learned_rel(i: Inputs) -> cc.CameraConditioning:
  return cc.LearnedRelative(
    cc.columnwise(i.spec),
    init_scale=i.init_scale,
    rotation_weight=i.rot_weight,
    n_pairs=i.n_pairs,
  )


CONDITIONINGS: dict[str, Callable[[Inputs], cc.CameraConditioning]] = {
  "none": lambda i: cc.NoCamera(),
  "raymap": lambda i: cc.Raymap(i.cameras()),
  "gta": lambda i: cc.GTA(i.cameras(), group="se3"),
  "gta_so3": lambda i: cc.GTA(i.cameras(), group="so3"),
  "prope": lambda i: cc.PRoPE(i.cameras()),
  "learned_abs": _learned_abs,
  "learned_rel": _learned_rel,
}
"""config.model.camera -> its conditioning, built from `Inputs` (module docstring)."""


def cameras(data_config) -> cc.PoseCameras:
  """The pose-to-camera map of a run's data (module docstring).

  Raises:
    ValueError: data whose pose columns do not give the camera.
  """
  if sources.is_procedural(data_config.source):
    return cc.cameras_of_family(sources.family_of_config(data_config))
  setting = sources.setting_of(data_config.source)
  if isinstance(setting, settings.ShapeNetCar):
    return cc.ObjectCameras(camera_distance=1.0, fov_deg=NOMINAL_FOV_DEG)
  raise ValueError(
    f"prepared {data_config.source!r} data ({setting} setting) holds pose columns that do not "
    "give the camera: the geometric conditionings (raymap, gta, gta_so3, prope) need procedural "
    "rooms / object data or the car setting; use none, learned_abs or learned_rel"
  )


def from_config(config, spec: P.PoseSystemSpec) -> cc.CameraConditioning:
  """The conditioning `config.model.camera` names, on pose system `spec`.

  Raises:
    ValueError: an unknown name, or one the data or the pose system cannot feed.
  """
  name = config.model.camera
  if name not in CONDITIONINGS:
    raise ValueError(f"unknown model.camera {name!r}; choose one of {tuple(CONDITIONINGS)}")
  inputs = Inputs(
    spec=spec,
    cameras=lambda: cameras(config.data),
    rot_weight=float(config.loss.rot_weight),
    n_pairs=int(config.loss.n_pairs),
    init_scale=float(config.model.init_scale),
  )
  return CONDITIONINGS[name](inputs)

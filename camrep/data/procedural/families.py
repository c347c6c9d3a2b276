"""The four procedural families (`camrep.data.procedural` documents them and builds them):
`RoomsFamily` (GQN-rooms-like), `ObjectFamily` (ShapeNet-car-like toy cars), `AreaFamily`
(Gibson-like furnished rooms) and `Scene6DofFamily` (real 7-Scenes trajectories in procedural
rooms). Each builds its scenes with `camrep.data.procedural.scenery` and maps its poses to
cameras; the shared machinery is `camrep.data.procedural.family_base`.
"""

from __future__ import annotations

import os

import numpy as np

from camrep.data.procedural import render
from camrep.data.procedural.family_base import Layout, ProceduralFamily, SampledPoseFamily
from camrep.data.procedural.scenery import (
  add_light,
  furnish,
  hsv,
  object_material,
  surface_material,
)
from camrep.data.readers import seven_scenes

SEVEN_SCENES = ("chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs")
"""The 7-Scenes scene names (the scene6dof family's scenes)."""
_TWO_PI = 2.0 * np.pi


def default_pose_dir() -> str | None:
  """Directory of 7-Scenes pose tables given by $CAMREP_7SCENES_POSES, else None: the tables
  shipped with camrep (`seven_scenes.PACKED_POSES`)."""
  return os.environ.get("CAMREP_7SCENES_POSES") or None


def _free_position(
  rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, footprints: np.ndarray, clearance: float
) -> np.ndarray:
  """Uniform 2-D point in [lo, hi] outside every footprint disc grown by `clearance`."""
  for _ in range(1000):
    p = rng.uniform(lo, hi)
    if len(footprints) == 0:
      return p
    dist = np.hypot(*(footprints[:, :2] - p).T)
    if np.all(dist > footprints[:, 2] + clearance):
      return p
  raise RuntimeError("no free camera position after 1000 tries; the scene is too crowded")


# ---------------------------------------------------------------------------------------------
# rooms


class RoomsFamily(SampledPoseFamily):
  """GQN-rooms-like scenes: room [-1, 1]^2 x [0, room_height], 1-4 objects, planar camera.

  Pose (x, y, yaw): camera at (x, y, camera_height) with |x|, |y| <= position_range, outside
  every object footprint grown by camera_clearance; yaw uniform in [0, 2 pi) counter-clockwise
  from +x; fixed pitch.
  """

  name = "rooms"
  scene_independent_cameras = True
  splits = ("train", "test", "test_scenes")
  budgets = dict(max_boxes=4, max_spheres=4, max_cylinders=4, max_planes=1)

  def _build(self, scene: int) -> Layout:
    cfg = self.config
    rng = self._scene_rng(scene)
    b = render.SceneBuilder()
    wall_kw = dict(
      patterns=("checker", "stripes_u", "stripes_v", "noise", "tiles"),
      freq_range=(3.0, 9.0),
      sat=(0.2, 0.7),
      val=(0.45, 0.9),
      contrast=tuple(cfg.texture_contrast),
    )
    wall = surface_material(rng, **wall_kw)
    walls = []
    if cfg.wall_style == "tinted":
      for _ in range(4):  # each wall slightly tinted, so the four walls differ a little
        w = dict(wall)
        tint = rng.uniform(0.85, 1.1, size=3).astype(np.float32)
        w["color_a"] = np.clip(w["color_a"] * tint, 0, 1)
        w["color_b"] = np.clip(w["color_b"] * tint, 0, 1)
        walls.append(w)
    elif cfg.wall_style in ("distinct", "compass"):
      hue0 = rng.uniform()
      if cfg.wall_style == "compass":
        hue0 = 0.0  # the same in every room: -x wall red, +x yellow-green, -y cyan, +y violet
      for k in range(4):
        hue = hue0 + 0.25 * k + rng.uniform(-0.04, 0.04)
        walls.append(surface_material(rng, hue=hue, **{**wall_kw, "sat": (0.45, 0.8)}))
    else:
      raise ValueError(
        f"unknown wall_style {cfg.wall_style!r}; choose 'tinted', 'distinct' or 'compass'"
      )
    floor = surface_material(
      rng,
      patterns=("checker", "noise", "tiles", "stripes_u"),
      freq_range=(3.0, 8.0),
      sat=(0.1, 0.6),
      val=(0.35, 0.8),
      contrast=tuple(cfg.texture_contrast),
    )
    ceiling = render.material(hsv(rng.uniform(), 0.1, 0.9))
    b.set_room((-1.0, -1.0, 0.0), (1.0, 1.0, cfg.room_height), walls + [floor, ceiling])
    add_light(b, rng, azimuth_deg=cfg.light_azimuth_deg)
    footprints = []
    n = int(rng.integers(cfg.min_objects, cfg.max_objects + 1))
    kinds = {"box": 0, "sphere": 0, "cylinder": 0}
    for _ in range(n):
      kind = str(rng.choice(["box", "sphere", "cylinder"]))
      if kinds[kind] >= 4:
        kind = min(kinds, key=kinds.get)
      kinds[kind] += 1
      r = rng.uniform(0.1, 0.22)
      xy = _free_position(
        rng, np.full(2, -0.65), np.full(2, 0.65), np.array(footprints).reshape(-1, 3), r + 0.05
      )
      mat = object_material(rng)
      if kind == "box":
        h = rng.uniform(0.1, 0.25)
        half = (r / np.sqrt(2) * rng.uniform(0.8, 1.2), r / np.sqrt(2) * rng.uniform(0.8, 1.2), h)
        b.add_box((xy[0], xy[1], h), half, mat, yaw=rng.uniform(0, np.pi))
      elif kind == "sphere":
        b.add_sphere((xy[0], xy[1], r), r, mat)
      else:
        b.add_cylinder(xy, 0.0, rng.uniform(0.15, 0.45), r * 0.85, mat)
      footprints.append((xy[0], xy[1], r))
    return Layout(
      scene=b.build(**self.budgets),
      footprints=np.array(footprints, np.float32).reshape(-1, 3),
      origin=np.zeros(3),
    )

  def _sample_pose(self, rng: np.random.Generator, layout: Layout) -> np.ndarray:
    cfg = self.config
    lim = np.full(2, cfg.position_range)
    xy = _free_position(rng, -lim, lim, layout.footprints, cfg.camera_clearance)
    return np.array([xy[0], xy[1], rng.uniform(0, _TWO_PI)])

  def _poses_to_c2w(self, scene: int, poses: np.ndarray) -> np.ndarray:
    cfg = self.config
    pos = np.concatenate([poses[:, :2], np.full((len(poses), 1), cfg.camera_height)], axis=-1)
    return render.camera_from_yaw_pitch_roll(pos, poses[:, 2], np.full(len(poses), cfg.pitch))


# ---------------------------------------------------------------------------------------------
# object


class ObjectFamily(SampledPoseFamily):
  """ShapeNet-car-like toy cars, canonical frame: front towards +x, up +z, centred at 0.

  Each car: body box, a cabin set back towards the rear, a bright nose panel and two pale
  headlight spheres at the front (+x), two red tail-light boxes at the back, four dark wheel
  spheres and, for some cars, a rear spoiler. Pose (azimuth, polar): camera at
  camera_distance * (sin p cos a, sin p sin a, cos p) looking at the origin with +z up;
  azimuth uniform in [0, 2 pi), polar in polar_range_deg (uniform in cos p, i.e. uniform on the
  sphere band). Azimuth 0 views the front.
  """

  name = "object"
  scene_independent_cameras = True
  splits = ("train", "test", "test_scenes")
  budgets = dict(max_boxes=6, max_spheres=6, max_cylinders=1, max_planes=1)

  def _build(self, scene: int) -> Layout:
    rng = self._scene_rng(scene)
    b = render.SceneBuilder()
    b.background = np.ones(3, np.float32)
    # Light from above and the side: front and back faces get the same (ambient) light, so the
    # nose and tail lights keep their colours from both ends.
    b.light_dir = np.array([0.0, 0.5, 0.87], np.float32)
    b.ambient = 0.65
    length, width = rng.uniform(1.5, 1.9), rng.uniform(0.65, 0.85)
    h_body, r_wheel = rng.uniform(0.22, 0.32), rng.uniform(0.14, 0.19)
    h_cab = rng.uniform(0.18, 0.28)
    z_bot = 0.75 * r_wheel
    z_shift = -(z_bot + h_body + h_cab) / 2  # centre the car's height on z = 0
    zb = z_bot + h_body / 2 + z_shift
    # Body hues avoid red/orange/yellow: warm colours mark only the nose and the tail lights.
    hue, sat, val = rng.uniform(0.22, 0.9), rng.uniform(0.4, 0.9), rng.uniform(0.55, 0.95)
    body = render.material(
      hsv(hue, sat, val),
      hsv(hue, sat * 0.5, val * 0.7),
      pattern=str(rng.choice(["flat", "flat", "stripes_u", "stripes_v"])),
      freq=rng.uniform(3.0, 6.0),
    )
    b.add_box((0.0, 0.0, zb), (length / 2, width / 2, h_body / 2), body)
    cab_len = length * rng.uniform(0.4, 0.55)
    cab_x = -length * rng.uniform(0.06, 0.18)
    glass = render.material(hsv(rng.uniform(0.5, 0.7), 0.35, rng.uniform(0.2, 0.4)))
    b.add_box(
      (cab_x, 0.0, zb + h_body / 2 + h_cab / 2), (cab_len / 2, width * 0.42, h_cab / 2), glass
    )
    nose = render.material(hsv(rng.uniform(0.08, 0.18), 0.9, 1.0))  # orange-yellow, every car
    b.add_box((length / 2 + 0.015, 0.0, zb), (0.02, width * 0.38, h_body * 0.32), nose)
    tail = render.material((0.85, 0.05, 0.05))
    for side in (-1, 1):
      b.add_box(
        (-length / 2 - 0.01, side * width * 0.33, zb + h_body * 0.15),
        (0.02, width * 0.12, h_body * 0.22),
        tail,
      )
      b.add_sphere(
        (length / 2 - 0.02, side * width * 0.33, zb + h_body * 0.1),
        0.07,
        render.material((1.0, 1.0, 0.8)),
      )
    if rng.uniform() < 0.5:
      b.add_box(
        (-length / 2 + 0.08, 0.0, zb + h_body / 2 + 0.03), (0.06, width * 0.46, 0.025), body
      )
    tyre = render.material((0.12, 0.12, 0.12), (0.35, 0.35, 0.35), pattern="stripes_u", freq=12.0)
    for sx in (-1, 1):
      for sy in (-1, 1):
        b.add_sphere((sx * length * 0.31, sy * width * 0.45, r_wheel + z_shift), r_wheel, tyre)
    return Layout(
      scene=b.build(**self.budgets), footprints=np.zeros((0, 3), np.float32), origin=np.zeros(3)
    )

  def _sample_pose(self, rng: np.random.Generator, layout: Layout) -> np.ndarray:
    lo, hi = np.deg2rad(self.config.polar_range_deg)
    polar = np.arccos(rng.uniform(np.cos(hi), np.cos(lo)))
    return np.array([rng.uniform(0, _TWO_PI), polar])

  def _poses_to_c2w(self, scene: int, poses: np.ndarray) -> np.ndarray:
    az, pol = poses[:, 0], poses[:, 1]
    r = self.config.camera_distance
    eye = r * np.stack([np.sin(pol) * np.cos(az), np.sin(pol) * np.sin(az), np.cos(pol)], axis=-1)
    return render.look_at(eye, np.zeros_like(eye))


# ---------------------------------------------------------------------------------------------
# area


class AreaFamily(SampledPoseFamily):
  """Gibson-rooms-like: one furnished room per scene, cameras over a central 2 m x 2 m area.

  Pose (x, y, yaw): camera at origin + (x, y, camera_height) with x, y uniform in
  [0, area_size] metres, yaw uniform in [0, 2 pi), fixed pitch. Furniture stays outside the
  area grown by object_clearance; room sides are uniform in room_size_range (metres).
  """

  name = "area"
  splits = ("train", "test")
  budgets = dict(max_boxes=16, max_spheres=6, max_cylinders=6, max_planes=1)

  def _num_train_scenes(self) -> int:
    return self.config.num_scenes

  def _build(self, scene: int) -> Layout:
    cfg = self.config
    rng = self._scene_rng(scene)
    size = rng.uniform(*cfg.room_size_range, size=2)
    lo = np.array([0.0, 0.0, 0.0])
    hi = np.array([size[0], size[1], cfg.room_height])
    origin = np.zeros(3)
    origin[:2] = (size - cfg.area_size) / 2 + rng.uniform(-0.2, 0.2, size=2)
    a_lo, a_hi = (
      origin[:2] - cfg.object_clearance,
      origin[:2] + cfg.area_size + cfg.object_clearance,
    )

    def keep_out(x, y, r, top):
      return (a_lo[0] - r < x < a_hi[0] + r) and (a_lo[1] - r < y < a_hi[1] + r)

    b = render.SceneBuilder()
    n = int(rng.integers(cfg.min_objects, cfg.max_objects + 1))
    fp = furnish(b, rng, lo, hi, n, keep_out, self.budgets)
    return Layout(
      scene=b.build(**self.budgets),
      footprints=np.array(fp, np.float32).reshape(-1, 3),
      origin=origin,
    )

  def _sample_pose(self, rng: np.random.Generator, layout: Layout) -> np.ndarray:
    s = self.config.area_size
    return np.array([rng.uniform(0, s), rng.uniform(0, s), rng.uniform(0, _TWO_PI)])

  def _poses_to_c2w(self, scene: int, poses: np.ndarray) -> np.ndarray:
    cfg = self.config
    origin = self.layout(scene).origin
    pos = (
      np.concatenate([poses[:, :2], np.full((len(poses), 1), cfg.camera_height)], axis=-1) + origin
    )
    return render.camera_from_yaw_pitch_roll(pos, poses[:, 2], np.full(len(poses), cfg.pitch))


# ---------------------------------------------------------------------------------------------
# scene6dof


def _up_alignment(down: np.ndarray) -> np.ndarray:
  """Rotation A (3, 3), a signed axis permutation, taking the world axis nearest `-down` to +z."""
  k = int(np.argmax(np.abs(down)))
  z = np.zeros(3)
  z[k] = -np.sign(down[k])
  x = np.zeros(3)
  x[(k + 1) % 3] = 1.0
  return np.stack([x, np.cross(z, x), z])


class Scene6DofFamily(ProceduralFamily):
  """7-Scenes-like: real 7-Scenes camera trajectories inside procedural furnished rooms.

  Per scene, the training table's minimum translation (`seven_scenes.translation_min`) is the
  origin of the re-based frame, so pose translations are those of the real data set. The
  renderer works in a z-up "room frame": p_room = A (p_world - t_min), A a signed axis
  permutation taking the 7-Scenes world's mean camera "down" axis (+y) to -z. The room box
  spans the trajectories' (train + test) extent plus margin_xy horizontally, floor_drop below
  the lowest and ceiling_rise above the highest camera. Furniture reaching within 0.25 m of
  camera height stays object_clearance away from every camera horizontally.
  """

  name = "scene6dof"
  splits = ("train", "test")
  # Each scene's trajectory has its own length: `num_views` needs `scene`.
  fixed_view_count = False
  budgets = dict(max_boxes=16, max_spheres=6, max_cylinders=6, max_planes=1)

  def __init__(self, config):
    super().__init__(config)
    unknown = set(config.scenes) - set(SEVEN_SCENES)
    if unknown:
      raise ValueError(f"unknown 7-Scenes scenes {sorted(unknown)}; choose from {SEVEN_SCENES}")
    self._tables: dict[tuple[str, str], np.ndarray] = {}

  def _num_train_scenes(self) -> int:
    return len(self.config.scenes)

  def scene_name(self, scene: int) -> str:
    """The 7-Scenes name of a scene id."""
    return self.config.scenes[scene]

  def _table(self, scene: int, split: str) -> np.ndarray:
    """(N, 4, 4) float64 camera-to-world poses of the full pose table."""
    key = (self.scene_name(scene), split)
    if key not in self._tables:
      pose_dir = self.config.pose_dir or default_pose_dir()
      if pose_dir:
        _, c2w = seven_scenes.read_pose_table(os.path.join(pose_dir, f"{key[0]}_{split}.txt"))
      else:
        _, c2w = seven_scenes.packed_pose_table(*key)
      self._tables[key] = c2w
    return self._tables[key]

  def num_views(self, split: str, scene: int | None = None) -> int:
    """Frames of a scene's (subsampled) trajectory; needs `scene`."""
    self._check_split(split)
    if scene is None:
      raise ValueError("scene6dof: the number of views depends on the scene; pass scene=")
    return len(self.poses(split, scene))

  def t_min(self, scene: int) -> np.ndarray:
    """(3,) re-basing offset: minimum training camera position (metres, 7-Scenes world)."""
    return seven_scenes.translation_min(self._table(scene, "train"))

  def poses(self, split: str, scene: int) -> np.ndarray:
    """The 6-DOF poses of the scene's subsampled `split` trajectory (see `seven_scenes`)."""
    self._check_scene(split, scene)
    stride = self.config.train_stride if split == "train" else self.config.test_stride
    c2w = self._table(scene, split)[::stride]
    return seven_scenes.c2w_to_dofs(c2w, self.t_min(scene)).astype(np.float32)

  def _alignment(self, scene: int) -> np.ndarray:
    return _up_alignment(self._table(scene, "train")[:, :3, 1].mean(axis=0))

  def _build(self, scene: int) -> Layout:
    cfg = self.config
    rng = self._scene_rng(scene)
    a = self._alignment(scene)
    t_min = self.t_min(scene)
    centres = np.concatenate([self._table(scene, s)[:, :3, 3] for s in ("train", "test")]) - t_min
    cams = centres @ a.T
    c_lo, c_hi = cams.min(axis=0), cams.max(axis=0)
    lo = np.array([c_lo[0] - cfg.margin_xy, c_lo[1] - cfg.margin_xy, c_lo[2] - cfg.floor_drop])
    hi = np.array([c_hi[0] + cfg.margin_xy, c_hi[1] + cfg.margin_xy, c_hi[2] + cfg.ceiling_rise])
    sub = cams[:: max(1, len(cams) // 400)]

    def keep_out(x, y, r, top):
      near = np.hypot(sub[:, 0] - x, sub[:, 1] - y) < r + cfg.object_clearance
      return bool(np.any(near & (sub[:, 2] < top + 0.25)))

    # The point nearest (least squares) to all optical axes: where the cameras look.
    axes = np.einsum("ij,njk->nik", a, self._table(scene, "train")[:, :3, :3])[:, :, 2]
    proj = np.eye(3) - axes[:, :, None] * axes[:, None, :]
    focus = np.linalg.lstsq(
      proj.sum(0), np.einsum("nij,nj->i", proj, cams[: len(axes)]), rcond=None
    )[0]
    focus = np.clip(focus, lo + 0.7, hi - 0.7)
    b = render.SceneBuilder()
    n = int(rng.integers(cfg.min_objects, cfg.max_objects + 1))
    fp = furnish(b, rng, lo, hi, n, keep_out, self.budgets, focus=focus)
    return Layout(
      scene=b.build(**self.budgets),
      footprints=np.array(fp, np.float32).reshape(-1, 3),
      origin=np.zeros(3),
    )

  def _poses_to_c2w(self, scene: int, poses: np.ndarray) -> np.ndarray:
    """Room-frame camera-to-world matrices (OpenCV axes, as 7-Scenes) of 6-DOF poses."""
    dofs = np.asarray(poses, np.float64).reshape(-1, 6)
    c2w = seven_scenes.dofs_to_c2w(dofs, np.zeros(3))  # the re-based 7-Scenes frame
    a4 = np.eye(4)
    a4[:3, :3] = self._alignment(scene)
    return (a4 @ c2w).astype(np.float32)

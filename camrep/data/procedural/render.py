"""A small analytic ray caster in JAX: the renderer behind camrep's procedural datasets.

World frame: right-handed, +z up, lengths in the family's own unit (scene units or metres).

Camera: pinhole, OpenCV convention in the camera frame (x right, y down, z forward), given by a
camera-to-world matrix `T_world_cam` (4, 4): a camera-frame point p_cam maps to
p_world = R p_cam + t. `Camera.fov_deg` is the HORIZONTAL field of view; pixels are square and
the principal point is the image centre. `look_at` and `camera_from_yaw_pitch_roll` build
`T_world_cam`; yaw is measured counter-clockwise from +x about +z, positive pitch looks up.

Scene: a `Scene` pytree with a FIXED maximum number of primitives per kind (padding slots have
mask 0), so one compilation of the renderer serves every scene of a dataset family:

  room       an inside-out axis-aligned box (walls, floor, ceiling), one material per face in
             the order -x, +x, -y, +y, -z (floor), +z (ceiling); optional (mask)
  planes     infinite planes n . p = offset
  boxes      boxes rotated by a yaw about their vertical axis
  spheres
  cylinders  vertical capped cylinders

Each primitive carries a `Material`: two colours mixed by a procedural pattern (flat, checker,
stripes along u or v, value noise, tiles) evaluated at surface coordinates (u, v) in world
length units times a frequency, so walls and floors carry texture and position is visible.

Shading: Lambertian with one directional light plus ambient, and hard shadows cast by the
objects (boxes, spheres, cylinders; the room and planes do not cast shadows, otherwise a
closed room would be dark). Rays that hit nothing get the scene's background colour.
Output is float32 RGB in [0, 1], (H, W, 3); `to_uint8` converts for view records.

Everything here is a pure function of its inputs (the renderer has no randomness). The only
jitted entry points are the module-level `render_views` (many poses of one scene),
`render_batch` (one pose each of a batch of scenes), `render_scenes_views` (V poses each of S
scenes, the procedural training batches, optionally converted to uint8 on the device) and
`render_table_views` (the same for scenes gathered by row from a stacked table on the device):
compiling the whole ray caster once per (camera, primitive budget, batch shape) is the point of
this module. `render` is the plain,
un-jitted single-image function they wrap.

The module stays whole past the package's 700-line bound for modules : it
reads as one piece, the ray caster and its shading vmapped and compiled together.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

# Bumped whenever a change here (or in the procedural families' scenery) alters a rendered
# pixel: it is part of a procedural dataset's fingerprint (`camrep.data.feed.fingerprint`), so a
# workdir trained on the old images refuses to resume on the new ones.
RENDERER_VERSION = 1
_EPS = 1e-4
_INF = 1e10

PATTERNS = ("flat", "checker", "stripes_u", "stripes_v", "noise", "tiles")
"""Texture patterns; a material's `pattern` is an index into this tuple."""

ROOM_FACES = ("-x", "+x", "-y", "+y", "floor", "ceiling")
"""Order of the room's six face materials."""


# ---------------------------------------------------------------------------------------------
# Scene pytrees.


@struct.dataclass
class Material:
  """Surface appearance: colour = (1 - s) color_a + s color_b, s = pattern(u * freq, v * freq).

  Attributes:
    color_a: (*, 3) RGB in [0, 1].
    color_b: (*, 3) RGB in [0, 1].
    pattern: (*,) int32 index into `PATTERNS`.
    freq: (*,) pattern cells per length unit.
    seed: (*,) int32 seed of the value-noise pattern.
  """

  color_a: jax.Array
  color_b: jax.Array
  pattern: jax.Array
  freq: jax.Array
  seed: jax.Array


@struct.dataclass
class Room:
  """Inside-out axis-aligned box seen from inside.

  Attributes:
    lo: (3,) minimum corner.
    hi: (3,) maximum corner.
    mask: () 1.0 if the scene has a room, else 0.0.
    material: `Material` with leading axis (6,) in `ROOM_FACES` order.
  """

  lo: jax.Array
  hi: jax.Array
  mask: jax.Array
  material: Material


@struct.dataclass
class Planes:
  """Infinite planes {p : normal . p = offset}.

  Attributes:
    normal: (N, 3) unit normals.
    offset: (N,).
    mask: (N,) 1.0 for a real plane, 0.0 for padding.
    material: `Material` with leading axis (N,).
  """

  normal: jax.Array
  offset: jax.Array
  mask: jax.Array
  material: Material


@struct.dataclass
class Boxes:
  """Boxes rotated by `yaw` about the vertical axis through their centre.

  Attributes:
    center: (N, 3).
    half: (N, 3) half extents along the box's local x, y, z.
    yaw: (N,) radians, counter-clockwise about +z.
    mask: (N,).
    material: `Material` with leading axis (N,).
  """

  center: jax.Array
  half: jax.Array
  yaw: jax.Array
  mask: jax.Array
  material: Material


@struct.dataclass
class Spheres:
  """Spheres.

  Attributes:
    center: (N, 3).
    radius: (N,).
    mask: (N,).
    material: `Material` with leading axis (N,).
  """

  center: jax.Array
  radius: jax.Array
  mask: jax.Array
  material: Material


@struct.dataclass
class Cylinders:
  """Vertical capped cylinders {|p_xy - center| <= radius, z0 <= p_z <= z1}.

  Attributes:
    center: (N, 2) axis position (x, y).
    z_range: (N, 2) (z0, z1) with z0 < z1.
    radius: (N,).
    mask: (N,).
    material: `Material` with leading axis (N,).
  """

  center: jax.Array
  z_range: jax.Array
  radius: jax.Array
  mask: jax.Array
  material: Material


@struct.dataclass
class Scene:
  """A full scene with fixed per-kind primitive budgets (see `SceneBuilder`).

  Attributes:
    room: `Room`.
    planes: `Planes`.
    boxes: `Boxes`.
    spheres: `Spheres`.
    cylinders: `Cylinders`.
    light_dir: (3,) unit vector pointing TOWARDS the directional light.
    ambient: () ambient fraction in [0, 1]; lit = albedo (ambient + (1 - ambient) n.l shadow).
    background: (3,) RGB of rays that hit nothing.
  """

  room: Room
  planes: Planes
  boxes: Boxes
  spheres: Spheres
  cylinders: Cylinders
  light_dir: jax.Array
  ambient: jax.Array
  background: jax.Array


@dataclasses.dataclass(frozen=True)
class Camera:
  """Static pinhole camera intrinsics (hashable: a static argument of the jitted renderers).

  Attributes:
    height: image height in pixels.
    width: image width in pixels.
    fov_deg: horizontal field of view in degrees.
    supersample: rays per pixel along each axis (averaged; 1 = one ray through the centre).
  """

  height: int
  width: int
  fov_deg: float
  supersample: int = 1

  @property
  def focal(self) -> float:
    """Focal length in pixels of the output image."""
    return 0.5 * self.width / float(np.tan(np.deg2rad(self.fov_deg) / 2.0))


# ---------------------------------------------------------------------------------------------
# Building scenes (NumPy, outside jit).


def material(
  color_a: Sequence[float],
  color_b: Sequence[float] | None = None,
  *,
  pattern: str = "flat",
  freq: float = 1.0,
  seed: int = 0,
) -> dict:
  """One material as a dict of NumPy values (consumed by `SceneBuilder`).

  Args:
    color_a: (3,) RGB in [0, 1].
    color_b: (3,) second RGB colour of the pattern; defaults to `color_a`.
    pattern: one of `PATTERNS`.
    freq: pattern cells per length unit.
    seed: value-noise seed.

  Returns:
    Dict with the fields of `Material`.
  """
  if pattern not in PATTERNS:
    raise ValueError(f"pattern must be one of {PATTERNS}, got {pattern!r}")
  color_b = color_a if color_b is None else color_b
  return dict(
    color_a=np.asarray(color_a, np.float32).reshape(3),
    color_b=np.asarray(color_b, np.float32).reshape(3),
    pattern=np.int32(PATTERNS.index(pattern)),
    freq=np.float32(freq),
    seed=np.int32(seed),
  )


def _stack_materials(mats: list[dict], n: int) -> Material:
  pad = material((0.0, 0.0, 0.0))
  mats = list(mats) + [pad] * (n - len(mats))
  return Material(**{k: np.stack([m[k] for m in mats]) for k in pad})


class SceneBuilder:
  """Collects primitives in NumPy and pads them into a fixed-budget `Scene`.

  Example:
    b = SceneBuilder()
    b.set_room((-1, -1, 0), (1, 1, 1), [material((0.8, 0.7, 0.6))] * 6)
    b.add_sphere((0, 0, 0.2), 0.2, material((1, 0, 0)))
    scene = b.build(max_boxes=4, max_spheres=4, max_cylinders=4, max_planes=1)
  """

  def __init__(self):
    self._room = None
    self._planes, self._boxes, self._spheres, self._cylinders = [], [], [], []
    self.light_dir = np.array([0.3, 0.2, 0.93], np.float32)
    self.ambient = 0.4
    self.background = np.ones(3, np.float32)

  def set_room(self, lo: Sequence[float], hi: Sequence[float], face_materials: list[dict]):
    """Sets the inside-out room box [lo, hi] with 6 face materials (`ROOM_FACES` order)."""
    if len(face_materials) != 6:
      raise ValueError(f"a room needs 6 face materials, got {len(face_materials)}")
    self._room = (np.asarray(lo, np.float32), np.asarray(hi, np.float32), face_materials)
    return self

  def add_plane(self, normal: Sequence[float], offset: float, mat: dict):
    """Adds the plane {p : n . p = offset} (normal is normalised here)."""
    n = np.asarray(normal, np.float32)
    self._planes.append((n / np.linalg.norm(n), np.float32(offset), mat))
    return self

  def add_box(self, center: Sequence[float], half: Sequence[float], mat: dict, yaw: float = 0.0):
    """Adds a box with half extents `half`, rotated by `yaw` (radians) about +z."""
    self._boxes.append((np.asarray(center, np.float32), np.asarray(half, np.float32), yaw, mat))
    return self

  def add_sphere(self, center: Sequence[float], radius: float, mat: dict):
    """Adds a sphere."""
    self._spheres.append((np.asarray(center, np.float32), np.float32(radius), mat))
    return self

  def add_cylinder(self, center_xy: Sequence[float], z0: float, z1: float, radius: float, mat):
    """Adds a vertical cylinder with axis at `center_xy` spanning z0..z1."""
    if not z1 > z0:
      raise ValueError(f"cylinder needs z1 > z0, got {z0}, {z1}")
    self._cylinders.append((np.asarray(center_xy, np.float32), (z0, z1), radius, mat))
    return self

  @property
  def counts(self) -> dict[str, int]:
    """Number of primitives of each kind added so far."""
    return dict(
      planes=len(self._planes),
      boxes=len(self._boxes),
      spheres=len(self._spheres),
      cylinders=len(self._cylinders),
    )

  def build(
    self, *, max_boxes: int, max_spheres: int, max_cylinders: int, max_planes: int = 1
  ) -> Scene:
    """Pads every primitive list to its budget (at least 1 slot) and returns a `Scene`.

    Raises:
      ValueError: if a budget is exceeded.
    """
    budgets = dict(planes=max_planes, boxes=max_boxes, spheres=max_spheres, cylinders=max_cylinders)
    for kind, n in self.counts.items():
      if n > budgets[kind]:
        raise ValueError(f"{n} {kind} exceed the budget of {budgets[kind]}")
    f32 = functools.partial(np.asarray, dtype=np.float32)

    def mask(items, n):
      return f32([1.0] * len(items) + [0.0] * (n - len(items)))

    def col(items, i, n, fill):
      return f32([it[i] for it in items] + [fill] * (n - len(items)))

    nb, ns, nc, npl = (max(1, m) for m in (max_boxes, max_spheres, max_cylinders, max_planes))
    if self._room is None:
      grey = material((0.5, 0.5, 0.5))
      room = Room(
        lo=f32([-1, -1, -1]),
        hi=f32([1, 1, 1]),
        mask=f32(0.0),
        material=_stack_materials([grey] * 6, 6),
      )
    else:
      lo, hi, mats = self._room
      room = Room(lo=lo, hi=hi, mask=f32(1.0), material=_stack_materials(mats, 6))
    planes = Planes(
      normal=col(self._planes, 0, npl, [0.0, 0.0, 1.0]),
      offset=col(self._planes, 1, npl, 0.0),
      mask=mask(self._planes, npl),
      material=_stack_materials([p[2] for p in self._planes], npl),
    )
    boxes = Boxes(
      center=col(self._boxes, 0, nb, [0.0, 0.0, 0.0]),
      half=col(self._boxes, 1, nb, [0.1, 0.1, 0.1]),
      yaw=col(self._boxes, 2, nb, 0.0),
      mask=mask(self._boxes, nb),
      material=_stack_materials([b[3] for b in self._boxes], nb),
    )
    spheres = Spheres(
      center=col(self._spheres, 0, ns, [0.0, 0.0, 0.0]),
      radius=col(self._spheres, 1, ns, 0.1),
      mask=mask(self._spheres, ns),
      material=_stack_materials([s[2] for s in self._spheres], ns),
    )
    cylinders = Cylinders(
      center=col(self._cylinders, 0, nc, [0.0, 0.0]),
      z_range=col(self._cylinders, 1, nc, [0.0, 0.1]),
      radius=col(self._cylinders, 2, nc, 0.1),
      mask=mask(self._cylinders, nc),
      material=_stack_materials([c[3] for c in self._cylinders], nc),
    )
    light = f32(self.light_dir)
    return Scene(
      room=room,
      planes=planes,
      boxes=boxes,
      spheres=spheres,
      cylinders=cylinders,
      light_dir=light / np.linalg.norm(light),
      ambient=f32(self.ambient),
      background=f32(self.background).reshape(3),
    )


def stack_scenes(scenes: Sequence[Scene]) -> Scene:
  """Stacks scenes with identical budgets along a new leading axis (for `render_batch` and
  `render_scenes_views`)."""
  return jax.tree.map(lambda *xs: np.stack(xs), *scenes)


# ---------------------------------------------------------------------------------------------
# Cameras.


def look_at(eye: jax.Array, target: jax.Array, up: Sequence[float] = (0.0, 0.0, 1.0)) -> jax.Array:
  """Camera-to-world matrix of a camera at `eye` looking at `target` (OpenCV axes).

  Camera z = normalize(target - eye), x = normalize(z x up) (image right), y = z x x (down).

  Args:
    eye: (*, 3) camera centres.
    target: (*, 3) points to look at (not straight up or down from `eye`).
    up: (3,) world up direction.

  Returns:
    (*, 4, 4) float32 `T_world_cam`.
  """
  eye = jnp.asarray(eye, jnp.float32)
  target = jnp.asarray(target, jnp.float32)
  z = _normalize(target - eye)
  x = _normalize(jnp.cross(z, jnp.broadcast_to(jnp.asarray(up, jnp.float32), z.shape)))
  y = jnp.cross(z, x)
  return _pack_pose(jnp.stack([x, y, z], axis=-1), eye)


@jax.jit  # one program, not ~20 eager ops each compiled per pose count in every process
def camera_from_yaw_pitch_roll(
  position: jax.Array, yaw: jax.Array, pitch: jax.Array, roll: jax.Array | float = 0.0
) -> jax.Array:
  """Camera-to-world matrix from a position and z-up Tait-Bryan angles (OpenCV camera axes).

  The viewing direction is (cos pitch cos yaw, cos pitch sin yaw, sin pitch); yaw = 0 looks
  along +x, yaw = pi/2 along +y; pitch > 0 looks up; roll turns the image clockwise about the
  viewing direction (as seen by the camera).

  Args:
    position: (*, 3) camera centres.
    yaw: (*,) radians.
    pitch: (*,) radians in (-pi/2, pi/2).
    roll: (*,) radians.

  Returns:
    (*, 4, 4) float32 `T_world_cam`.
  """
  position = jnp.asarray(position, jnp.float32)
  yaw, pitch, roll = (jnp.asarray(a, jnp.float32) for a in (yaw, pitch, roll))
  yaw, pitch, roll = jnp.broadcast_arrays(yaw, pitch, roll)
  cy, sy, cp, sp = jnp.cos(yaw), jnp.sin(yaw), jnp.cos(pitch), jnp.sin(pitch)
  fwd = jnp.stack([cp * cy, cp * sy, sp], axis=-1)
  right = jnp.stack([sy, -cy, jnp.zeros_like(sy)], axis=-1)
  down = jnp.cross(fwd, right)
  cr, sr = jnp.cos(roll)[..., None], jnp.sin(roll)[..., None]
  x = cr * right + sr * down
  y = -sr * right + cr * down
  rot = jnp.stack([x, y, fwd], axis=-1)
  return _pack_pose(rot, jnp.broadcast_to(position, rot.shape[:-2] + (3,)))


def _pack_pose(rot: jax.Array, t: jax.Array) -> jax.Array:
  top = jnp.concatenate([rot, t[..., None]], axis=-1)
  bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], jnp.float32), top.shape[:-2] + (1, 4))
  return jnp.concatenate([top, bottom], axis=-2)


def _normalize(v: jax.Array) -> jax.Array:
  return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def camera_rays(T_world_cam: jax.Array, camera: Camera) -> tuple[jax.Array, jax.Array]:
  """World-space rays through the (super-sampled) pixel grid, row-major.

  Args:
    T_world_cam: (4, 4) camera-to-world matrix.
    camera: intrinsics.

  Returns:
    origins (R, 3) and unit directions (R, 3), R = (H s) (W s) with s = camera.supersample.
  """
  s = camera.supersample
  h, w = camera.height * s, camera.width * s
  f = camera.focal * s
  i, j = jnp.meshgrid(
    jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32), indexing="ij"
  )
  d_cam = jnp.stack([(j + 0.5 - w / 2) / f, (i + 0.5 - h / 2) / f, jnp.ones_like(i)], axis=-1)
  d_cam = d_cam.reshape(-1, 3)
  T = jnp.asarray(T_world_cam, jnp.float32)
  d = _normalize(d_cam @ T[:3, :3].T)
  o = jnp.broadcast_to(T[:3, 3], d.shape)
  return o, d


# ---------------------------------------------------------------------------------------------
# Ray / primitive intersections. Rays: o (R, 3), d (R, 3) unit. Each returns t (R, N), +inf-like
# `_INF` for a miss or a padding slot; only hits with t > _EPS count.


def _safe_inv(d: jax.Array) -> jax.Array:
  return 1.0 / jnp.where(jnp.abs(d) < 1e-9, jnp.where(d < 0, -1e-9, 1e-9), d)


def _valid(t: jax.Array, ok: jax.Array) -> jax.Array:
  return jnp.where(ok & (t > _EPS), t, _INF)


def intersect_room(o: jax.Array, d: jax.Array, room: Room) -> jax.Array:
  """Exit distance of rays from an inside-out box: (R, 1). Valid only from inside the box."""
  inv = _safe_inv(d)
  t1, t2 = (room.lo - o) * inv, (room.hi - o) * inv
  t_exit = jnp.min(jnp.maximum(t1, t2), axis=-1)
  inside = jnp.all((o > room.lo) & (o < room.hi), axis=-1)
  return _valid(t_exit, inside & (room.mask > 0))[:, None]


def intersect_planes(o: jax.Array, d: jax.Array, planes: Planes) -> jax.Array:
  """Ray-plane distances (R, N)."""
  nd = d @ planes.normal.T
  no = o @ planes.normal.T
  t = (planes.offset - no) / jnp.where(jnp.abs(nd) < 1e-9, 1e-9, nd)
  return _valid(t, (jnp.abs(nd) >= 1e-9) & (planes.mask > 0))


def _to_box_frame(p: jax.Array, boxes: Boxes, *, is_dir: bool) -> jax.Array:
  """(R, 3) world vectors -> (R, N, 3) in each box's local frame (inverse yaw rotation)."""
  c, s = jnp.cos(boxes.yaw), jnp.sin(boxes.yaw)
  q = p[:, None, :] if is_dir else p[:, None, :] - boxes.center
  x, y = q[..., 0], q[..., 1]
  xl, yl = c * x + s * y, -s * x + c * y
  return jnp.stack([xl, yl, jnp.broadcast_to(q[..., 2], xl.shape)], axis=-1)


def intersect_boxes(o: jax.Array, d: jax.Array, boxes: Boxes) -> jax.Array:
  """Ray-box (slab test in the box frame) distances (R, N); rays starting inside miss."""
  o_l = _to_box_frame(o, boxes, is_dir=False)
  inv = _safe_inv(_to_box_frame(d, boxes, is_dir=True))
  t1, t2 = (-boxes.half - o_l) * inv, (boxes.half - o_l) * inv
  t_near = jnp.max(jnp.minimum(t1, t2), axis=-1)
  t_far = jnp.min(jnp.maximum(t1, t2), axis=-1)
  return _valid(t_near, (t_near <= t_far) & (boxes.mask > 0))


def intersect_spheres(o: jax.Array, d: jax.Array, spheres: Spheres) -> jax.Array:
  """Ray-sphere distances to the first surface crossing in front of the origin (R, N)."""
  oc = o[:, None, :] - spheres.center
  b = jnp.sum(oc * d[:, None, :], axis=-1)
  c = jnp.sum(oc * oc, axis=-1) - spheres.radius**2
  disc = b * b - c
  sq = jnp.sqrt(jnp.maximum(disc, 0.0))
  t = jnp.where(-b - sq > _EPS, -b - sq, -b + sq)
  return _valid(t, (disc >= 0) & (spheres.mask > 0))


def intersect_cylinders(o: jax.Array, d: jax.Array, cyl: Cylinders) -> jax.Array:
  """Ray-capped-vertical-cylinder distances (R, N)."""
  ox = o[:, None, 0] - cyl.center[:, 0]
  oy = o[:, None, 1] - cyl.center[:, 1]
  dx, dy, dz, oz = d[:, None, 0], d[:, None, 1], d[:, None, 2], o[:, None, 2]
  z0, z1 = cyl.z_range[:, 0], cyl.z_range[:, 1]
  a = jnp.maximum(dx * dx + dy * dy, 1e-12)
  b = ox * dx + oy * dy
  c = ox * ox + oy * oy - cyl.radius**2
  disc = b * b - a * c
  t_side = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / a
  z_side = oz + t_side * dz
  t_side = _valid(t_side, (disc >= 0) & (z_side >= z0) & (z_side <= z1))
  inv_dz = _safe_inv(dz)
  t_caps = []
  for zc in (z0, z1):
    t = (zc - oz) * inv_dz
    px, py = ox + t * dx, oy + t * dy
    t_caps.append(_valid(t, px * px + py * py <= cyl.radius**2))
  t = jnp.minimum(t_side, jnp.minimum(*t_caps))
  return jnp.where(cyl.mask > 0, t, _INF)


# ---------------------------------------------------------------------------------------------
# Surface attributes at the nearest hit. Each takes hit points p (R, 3) and the per-ray gathered
# parameters of the hit primitive, and returns (normal (R, 3), uv (R, 2)).

_UV_AXES = np.array([[1, 2], [0, 2], [0, 1]])


def _face_uv(q: jax.Array, axis: jax.Array) -> jax.Array:
  idx = jnp.asarray(_UV_AXES)[axis]
  return jnp.take_along_axis(q, idx, axis=-1)


def _room_surface(p: jax.Array, room: Room) -> tuple[jax.Array, jax.Array, jax.Array]:
  center, half = (room.lo + room.hi) / 2, (room.hi - room.lo) / 2
  q = (p - center) / half
  axis = jnp.argmax(jnp.abs(q), axis=-1)
  pos = jnp.take_along_axis(q, axis[:, None], axis=-1)[:, 0] > 0
  normal = -jax.nn.one_hot(axis, 3) * jnp.where(pos, 1.0, -1.0)[:, None]
  face = 2 * axis + pos.astype(jnp.int32)
  return normal, _face_uv(p, axis), face


def _plane_surface(p: jax.Array, normal: jax.Array) -> tuple[jax.Array, jax.Array]:
  helper = jnp.where(
    jnp.abs(normal[:, 2:3]) < 0.9, jnp.array([0.0, 0.0, 1.0]), jnp.array([1.0, 0.0, 0.0])
  )
  t1 = _normalize(jnp.cross(normal, helper))
  t2 = jnp.cross(normal, t1)
  return normal, jnp.stack([jnp.sum(p * t1, -1), jnp.sum(p * t2, -1)], axis=-1)


def _box_surface(p, center, half, yaw) -> tuple[jax.Array, jax.Array]:
  c, s = jnp.cos(yaw), jnp.sin(yaw)
  q = p - center
  q = jnp.stack([c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1], q[:, 2]], axis=-1)
  axis = jnp.argmax(jnp.abs(q) / half, axis=-1)
  n_l = jax.nn.one_hot(axis, 3) * jnp.sign(jnp.take_along_axis(q, axis[:, None], axis=-1))
  normal = jnp.stack([c * n_l[:, 0] - s * n_l[:, 1], s * n_l[:, 0] + c * n_l[:, 1], n_l[:, 2]], -1)
  return normal, _face_uv(q, axis)


def _sphere_surface(p, center, radius) -> tuple[jax.Array, jax.Array]:
  q = p - center
  normal = q / radius[:, None]
  uv = jnp.stack([jnp.arctan2(q[:, 1], q[:, 0]) * radius, q[:, 2]], axis=-1)
  return normal, uv


def _cylinder_surface(p, center, z_range, radius) -> tuple[jax.Array, jax.Array]:
  q = p[:, :2] - center
  zc, hz = z_range.mean(-1), (z_range[:, 1] - z_range[:, 0]) / 2
  rad_n = jnp.linalg.norm(q, axis=-1) / radius
  dz = (p[:, 2] - zc) / hz
  cap = jnp.abs(dz) > rad_n
  side_n = jnp.concatenate([q / radius[:, None], jnp.zeros_like(dz)[:, None]], axis=-1)
  cap_n = jnp.zeros_like(side_n).at[:, 2].set(jnp.sign(dz))
  normal = jnp.where(cap[:, None], cap_n, side_n)
  side_uv = jnp.stack([jnp.arctan2(q[:, 1], q[:, 0]) * radius, p[:, 2]], axis=-1)
  uv = jnp.where(cap[:, None], q, side_uv)
  return normal, uv


# ---------------------------------------------------------------------------------------------
# Textures.


def _hash01(ix: jax.Array, iy: jax.Array, seed: jax.Array) -> jax.Array:
  """Integer lattice hash -> [0, 1) (uint32 arithmetic; identical on every backend)."""
  h = (
    ix.astype(jnp.uint32) * jnp.uint32(374761393)
    + iy.astype(jnp.uint32) * jnp.uint32(668265263)
    + seed.astype(jnp.uint32) * jnp.uint32(2246822519)
  )
  h = (h ^ (h >> 13)) * jnp.uint32(1274126177)
  h = h ^ (h >> 16)
  return (h >> 8).astype(jnp.float32) / float(1 << 24)


def _value_noise(u: jax.Array, v: jax.Array, seed: jax.Array) -> jax.Array:
  iu, iv = jnp.floor(u), jnp.floor(v)
  fu, fv = u - iu, v - iv
  fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
  iu, iv = iu.astype(jnp.int32), iv.astype(jnp.int32)
  n00, n10 = _hash01(iu, iv, seed), _hash01(iu + 1, iv, seed)
  n01, n11 = _hash01(iu, iv + 1, seed), _hash01(iu + 1, iv + 1, seed)
  return (n00 * (1 - fu) + n10 * fu) * (1 - fv) + (n01 * (1 - fu) + n11 * fu) * fv


def pattern_value(uv: jax.Array, pattern: jax.Array, freq: jax.Array, seed: jax.Array) -> jax.Array:
  """Mixing weight in [0, 1] of the material pattern at surface coordinates.

  Args:
    uv: (R, 2) surface coordinates in length units.
    pattern: (R,) int32 index into `PATTERNS`.
    freq: (R,) cells per length unit.
    seed: (R,) int32 noise seed.

  Returns:
    (R,) weights of `color_b`.
  """
  u, v = uv[:, 0] * freq, uv[:, 1] * freq
  fu, fv = jnp.floor(u), jnp.floor(v)
  checker = jnp.mod(fu + fv, 2.0)
  stripes_u = jnp.mod(fu, 2.0)
  stripes_v = jnp.mod(fv, 2.0)
  noise = 0.65 * _value_noise(u, v, seed) + 0.35 * _value_noise(3.1 * u, 3.1 * v, seed + 7)
  tiles = ((u - fu < 0.08) | (v - fv < 0.08)).astype(jnp.float32)
  options = jnp.stack([jnp.zeros_like(u), checker, stripes_u, stripes_v, noise, tiles], axis=-1)
  return jnp.take_along_axis(options, pattern[:, None], axis=-1)[:, 0]


# ---------------------------------------------------------------------------------------------
# The renderer.


def _take(tree, idx: jax.Array):
  return jax.tree.map(lambda x: x[idx], tree)


def _occluded(o: jax.Array, d: jax.Array, scene: Scene) -> jax.Array:
  """(R,) True where the ray hits an object (box, sphere, cylinder) at any t > eps."""
  t = jnp.minimum(
    jnp.min(intersect_boxes(o, d, scene.boxes), axis=-1),
    jnp.minimum(
      jnp.min(intersect_spheres(o, d, scene.spheres), axis=-1),
      jnp.min(intersect_cylinders(o, d, scene.cylinders), axis=-1),
    ),
  )
  return t < _INF


def trace(o: jax.Array, d: jax.Array, scene: Scene, *, shadows: bool = True) -> dict:
  """Nearest hit and shaded colour of each ray.

  Args:
    o: (R, 3) ray origins.
    d: (R, 3) unit ray directions.
    scene: the scene (unbatched).
    shadows: cast shadow rays towards the light.

  Returns:
    Dict with "rgb" (R, 3) in [0, 1], "t" (R,) hit distance (`_INF` for a miss), "normal"
    (R, 3) facing the ray, and "kind" (R,) int32 in {-1 miss, 0 room, 1 plane, 2 box,
    3 sphere, 4 cylinder}.
  """
  t_kinds = [
    intersect_room(o, d, scene.room),
    intersect_planes(o, d, scene.planes),
    intersect_boxes(o, d, scene.boxes),
    intersect_spheres(o, d, scene.spheres),
    intersect_cylinders(o, d, scene.cylinders),
  ]
  idx = [jnp.argmin(t, axis=-1) for t in t_kinds]
  t_min = jnp.stack([jnp.min(t, axis=-1) for t in t_kinds], axis=-1)
  kind = jnp.argmin(t_min, axis=-1)
  t = jnp.min(t_min, axis=-1)
  hit = t < _INF
  p = o + jnp.where(hit, t, 0.0)[:, None] * d

  n_room, uv_room, face = _room_surface(p, scene.room)
  pl = _take(scene.planes, idx[1])
  n_pl, uv_pl = _plane_surface(p, pl.normal)
  bx = _take(scene.boxes, idx[2])
  n_bx, uv_bx = _box_surface(p, bx.center, bx.half, bx.yaw)
  sp = _take(scene.spheres, idx[3])
  n_sp, uv_sp = _sphere_surface(p, sp.center, sp.radius)
  cy = _take(scene.cylinders, idx[4])
  n_cy, uv_cy = _cylinder_surface(p, cy.center, cy.z_range, cy.radius)
  mats = [_take(scene.room.material, face), pl.material, bx.material, sp.material, cy.material]

  def select(*xs):
    out = xs[0]
    for k in range(1, len(xs)):
      sel = kind == k
      out = jnp.where(sel.reshape(sel.shape + (1,) * (xs[k].ndim - 1)), xs[k], out)
    return out

  normal = select(n_room, n_pl, n_bx, n_sp, n_cy)
  normal = jnp.where(jnp.sum(normal * d, -1, keepdims=True) > 0, -normal, normal)
  uv = select(uv_room, uv_pl, uv_bx, uv_sp, uv_cy)
  mat = jax.tree.map(select, *mats)

  w = pattern_value(uv, mat.pattern, mat.freq, mat.seed)[:, None]
  albedo = (1 - w) * mat.color_a + w * mat.color_b
  light = scene.light_dir / jnp.linalg.norm(scene.light_dir)
  diffuse = jnp.maximum(normal @ light, 0.0)
  if shadows:
    lit = ~_occluded(p + normal * 1e-3, jnp.broadcast_to(light, p.shape), scene)
    diffuse = diffuse * lit
  shade = scene.ambient + (1 - scene.ambient) * diffuse
  rgb = jnp.where(hit[:, None], albedo * shade[:, None], scene.background)
  return dict(
    rgb=jnp.clip(rgb, 0.0, 1.0), t=t, normal=normal, kind=jnp.where(hit, kind, -1).astype(jnp.int32)
  )


def render(
  scene: Scene, T_world_cam: jax.Array, camera: Camera, *, shadows: bool = True
) -> jax.Array:
  """Renders one image (pure, not jitted; see `render_views` / `render_batch`).

  Args:
    scene: unbatched `Scene`.
    T_world_cam: (4, 4) camera-to-world matrix (OpenCV camera axes).
    camera: intrinsics.
    shadows: cast hard shadows from objects.

  Returns:
    (H, W, 3) float32 RGB in [0, 1].
  """
  o, d = camera_rays(T_world_cam, camera)
  rgb = trace(o, d, scene, shadows=shadows)["rgb"]
  s = camera.supersample
  rgb = rgb.reshape(camera.height, s, camera.width, s, 3)
  return rgb.mean(axis=(1, 3))


@functools.partial(jax.jit, static_argnames=("camera", "shadows"))
def render_views(
  scene: Scene, T_world_cam: jax.Array, camera: Camera, *, shadows: bool = True
) -> jax.Array:
  """Jitted: many views of ONE scene.

  Args:
    scene: unbatched `Scene`.
    T_world_cam: (V, 4, 4) camera-to-world matrices.
    camera: intrinsics (static).
    shadows: static.

  Returns:
    (V, H, W, 3) float32 in [0, 1].
  """
  return jax.vmap(lambda T: render(scene, T, camera, shadows=shadows))(T_world_cam)


@functools.partial(jax.jit, static_argnames=("camera", "shadows"))
def render_batch(
  scenes: Scene, T_world_cam: jax.Array, camera: Camera, *, shadows: bool = True
) -> jax.Array:
  """Jitted: one view each of a batch of scenes (scene leaves carry a leading (B,) axis).

  Args:
    scenes: `Scene` whose leaves have a leading batch axis B (see `stack_scenes`).
    T_world_cam: (B, 4, 4) camera-to-world matrices.
    camera: intrinsics (static).
    shadows: static.

  Returns:
    (B, H, W, 3) float32 in [0, 1].
  """
  return jax.vmap(lambda sc, T: render(sc, T, camera, shadows=shadows))(scenes, T_world_cam)


@functools.partial(jax.jit, static_argnames=("camera", "shadows", "uint8"))
def render_scenes_views(
  scenes: Scene,
  T_world_cam: jax.Array,
  camera: Camera,
  *,
  shadows: bool = True,
  uint8: bool = True,
) -> jax.Array:
  """Jitted: V views each of S scenes in one call (vmapped over scenes, then views).

  Args:
    scenes: `Scene` whose leaves have a leading scene axis S (see `stack_scenes`).
    T_world_cam: (S, V, 4, 4) camera-to-world matrices, row s for scene s.
    camera: intrinsics (static).
    shadows: static.
    uint8: static; True: convert on the device as `to_uint8` does (round to nearest), so only
      uint8 images leave it; False: float32 in [0, 1].

  Returns:
    (S, V, H, W, 3) uint8, or float32 in [0, 1].
  """
  return _scenes_views(scenes, T_world_cam, camera, shadows=shadows, uint8=uint8)


@functools.partial(jax.jit, static_argnames=("camera", "shadows", "uint8"))
def render_table_views(
  table: Scene,
  rows: jax.Array,
  T_world_cam: jax.Array,
  camera: Camera,
  *,
  shadows: bool = True,
  uint8: bool = True,
) -> jax.Array:
  """Jitted: `render_scenes_views` of the scenes at `rows` of a stacked table of scenes; the
  rows are gathered inside the call, so only indices and cameras cross to the device.

  Args:
    table: `Scene` whose leaves have a leading axis N
      (`camrep.data.procedural.scene_table.SceneTable`).
    rows: int32 (*L) rows of the table (any leading shape L; repeats allowed).
    T_world_cam: (*L, V, 4, 4) camera-to-world matrices of the scene at each row.
    camera: intrinsics (static).
    shadows: static.
    uint8: static; as `render_scenes_views`.

  Returns:
    (*L, V, H, W, 3) uint8, or float32 in [0, 1].
  """
  flat = rows.reshape(-1)
  scenes = jax.tree.map(lambda a: jnp.take(a, flat, axis=0), table)
  T = T_world_cam.reshape(-1, *T_world_cam.shape[rows.ndim :])
  images = _scenes_views(scenes, T, camera, shadows=shadows, uint8=uint8)
  return images.reshape(*rows.shape, *images.shape[1:])


def _scenes_views(scenes: Scene, T_world_cam, camera: Camera, *, shadows: bool, uint8: bool):
  def one_scene(scene, T):
    return jax.vmap(lambda t: render(scene, t, camera, shadows=shadows))(T)

  images = jax.vmap(one_scene)(scenes, T_world_cam)
  if uint8:
    images = jnp.round(jnp.clip(images, 0.0, 1.0) * 255.0).astype(jnp.uint8)
  return images


def to_uint8(images: jax.Array) -> np.ndarray:
  """Float images in [0, 1] -> uint8 (round to nearest), as NumPy."""
  return np.round(np.clip(np.asarray(images, np.float32), 0.0, 1.0) * 255.0).astype(np.uint8)

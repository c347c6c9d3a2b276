"""Procedural posed-image datasets rendered by `camrep.data.render`: camrep's default data.

Four families mirror the paper's four datasets (digest sections 1.7 and 6); each yields view
records (`camrep.data.records`) with the same pose conventions as its real counterpart:

  rooms      like GQN rooms: many square rooms [-1, 1]^2 (textured walls and floor, 1 to 4
             objects), camera free in 2-D at a fixed height and pitch; pose (x, y, yaw).
  object     like ShapeNet cars: many toy cars built from primitives, all facing +x with a bright
             nose, headlights, red tail lights and a rear cabin, so the front is visible; camera
             on a sphere looking at the centre, white background; pose (azimuth, polar).
  area       like Gibson rooms: a few furnished rooms; dense views over a 2 m x 2 m area in the
             middle of each; pose (x, y, yaw) with x, y in [0, 2] m area coordinates.
  scene6dof  like 7-Scenes: one furnished room per 7-Scenes scene, seen along the REAL 7-Scenes
             camera trajectories (`camrep.data.seven_scenes` pose tables); pose = the paper's
             six DOFs from `seven_scenes.c2w_to_dofs`.

Splits: "train"; "test" = different poses of the training scenes (a different random stream,
or the 7-Scenes test trajectories); "test_scenes" = whole held-out scenes (rooms and object),
whose scene ids continue after the training ids (num_train_scenes, num_train_scenes + 1, ...),
so a per-scene table indexed by id never aliases a held-out scene.

Determinism: scene `s` is built from `np.random.default_rng([seed, family, s])` and view `v`
of split `k` from `np.random.default_rng([seed, family, s, k, v])`, so any record can be
regenerated alone and a smaller config's views are a prefix of a larger one's. The renderer
is deterministic (one jit compile per family and image size: see `camrep.data.render`).

Usage:
  family = make_family("rooms", preset="small")
  for record in family.iter_views("train"): ...
  images = family.render_views(scene=0, poses=family.poses("test", 0))
"""

from __future__ import annotations

import abc
import colorsys
import dataclasses
import os
from collections.abc import Iterator
from typing import Any

import jax.numpy as jnp
import numpy as np

from camrep.data import render, seven_scenes, sources

FAMILIES = ("rooms", "object", "area", "scene6dof")
PRESETS = ("default", "small")

_FAMILY_CODE = {"rooms": 1, "object": 2, "area": 3, "scene6dof": 4}
_SPLIT_CODE = {"train": 0, "test": 1, "test_scenes": 2}
_TWO_PI = 2.0 * np.pi
_SEVEN_SCENES = ("chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs")


def default_pose_dir() -> str | None:
  """Directory of 7-Scenes pose tables given by $CAMREP_7SCENES_POSES, else None: the tables
  shipped with camrep (`seven_scenes.PACKED_POSES`)."""
  return os.environ.get("CAMREP_7SCENES_POSES") or None


# ---------------------------------------------------------------------------------------------
# Configs: the defaults are paper-like sizes; SMALL_OVERRIDES build in seconds (tests, smoke).


@dataclasses.dataclass(frozen=True)
class RoomsConfig:
  """GQN-rooms-like family. Lengths in scene units, angles in radians unless named *_deg."""

  seed: int = 0
  image_size: int = 64
  num_train_scenes: int = 200_000  # the paper samples 200k GQN scenes
  num_test_scenes: int = 10_000
  train_views: int = 10  # GQN records hold 10 views
  test_views: int = 10
  fov_deg: float = 60.0  # horizontal
  camera_height: float = 0.4
  pitch: float = -0.3  # looking down by about 17 degrees
  room_height: float = 1.0
  position_range: float = 0.8  # camera |x|, |y| <= this (walls at +-1)
  camera_clearance: float = 0.12  # from object footprints
  min_objects: int = 1
  max_objects: int = 4
  # Value contrast of the two colours of wall and floor textures (0: nearly flat colours, as
  # in most real GQN rooms; the draws are the same for any range, so scenes keep their layout).
  texture_contrast: tuple[float, float] = (0.25, 0.5)
  # "tinted": one wall material for the room, each wall slightly tinted (the walls look alike,
  # so a view of a wall says little about the yaw); "distinct": every wall its own pattern and a
  # hue a quarter turn from its neighbours', like DeepMind's rooms whose walls can be told apart.
  wall_style: str = "tinted"
  # The light's azimuth in degrees from +x, the same in every room (a fixed sun: shading and
  # shadows then tell the yaw), or None: a random azimuth per room.
  light_azimuth_deg: float | None = None
  supersample: int = 1
  shadows: bool = True
  batch_size: int = 32  # images per renderer call (one compile)


@dataclasses.dataclass(frozen=True)
class ObjectConfig:
  """ShapeNet-car-like family. Azimuth from +x towards +y; polar angle from the +z pole."""

  seed: int = 0
  image_size: int = 128
  num_train_scenes: int = 2_000
  num_test_scenes: int = 100
  train_views: int = 50
  test_views: int = 50
  fov_deg: float = 45.0
  camera_distance: float = 2.4
  polar_range_deg: tuple[float, float] = (30.0, 90.0)  # uniform in cos(polar) over this band
  supersample: int = 1
  shadows: bool = True
  batch_size: int = 16


@dataclasses.dataclass(frozen=True)
class AreaConfig:
  """Gibson-rooms-like family. Metres; the 2 m area is centred in a larger furnished room."""

  seed: int = 0
  image_size: int = 128
  num_scenes: int = 20  # the paper's 20 Gibson areas
  train_views: int = 14_000  # ~28k views an area, half train (paper)
  test_views: int = 14_000
  area_size: float = 2.0
  room_size_range: tuple[float, float] = (4.2, 5.2)
  room_height: float = 2.6
  camera_height: float = 1.2
  pitch: float = 0.0
  fov_deg: float = 75.0
  min_objects: int = 8
  max_objects: int = 12
  object_clearance: float = 0.3  # between furniture and the camera area
  supersample: int = 1
  shadows: bool = True
  batch_size: int = 16


@dataclasses.dataclass(frozen=True)
class Scene6DofConfig:
  """7-Scenes-like family: real trajectories inside procedural rooms. Metres."""

  seed: int = 0
  image_size: int = 128
  scenes: tuple[str, ...] = _SEVEN_SCENES
  pose_dir: str | None = None  # None: $CAMREP_7SCENES_POSES, else the shipped tables
  train_stride: int = 1  # keep every k-th frame of each table
  test_stride: int = 1
  fov_deg: float = 44.6  # 7-Scenes focal 585 px over the central 480 px crop
  margin_xy: float = 1.0  # room walls beyond the trajectory's horizontal extent
  floor_drop: float = 1.1  # floor below the lowest camera
  ceiling_rise: float = 0.9  # ceiling above the highest camera
  min_objects: int = 8
  max_objects: int = 12
  object_clearance: float = 0.3  # horizontal distance from cameras for objects reaching them
  supersample: int = 1
  shadows: bool = True
  batch_size: int = 16


SMALL_OVERRIDES: dict[str, dict[str, Any]] = {
  "rooms": dict(num_train_scenes=4, num_test_scenes=2, train_views=10, test_views=4),
  "object": dict(
    image_size=64, num_train_scenes=4, num_test_scenes=2, train_views=12, test_views=4
  ),
  "area": dict(image_size=64, num_scenes=2, train_views=24, test_views=8),
  "scene6dof": dict(image_size=64, scenes=("chess", "heads"), train_stride=200, test_stride=250),
}
"""Per family: overrides of the `small` preset (a few scenes and views)."""


# ---------------------------------------------------------------------------------------------
# Random appearance helpers.


def _rng(*keys: int) -> np.random.Generator:
  return np.random.default_rng([int(k) for k in keys])


def _hsv(h: float, s: float, v: float) -> np.ndarray:
  return np.asarray(colorsys.hsv_to_rgb(h % 1.0, float(np.clip(s, 0, 1)), float(np.clip(v, 0, 1))))


def _surface_material(
  rng: np.random.Generator,
  *,
  patterns: tuple[str, ...],
  freq_range: tuple[float, float],
  sat: tuple[float, float],
  val: tuple[float, float],
  hue: float | None = None,
  contrast: tuple[float, float] = (0.25, 0.5),
) -> dict:
  """A random two-colour material of one hue with a value contrast."""
  h = rng.uniform() if hue is None else hue
  s, v = rng.uniform(*sat), rng.uniform(*val)
  c = rng.uniform(*contrast)
  color_a = _hsv(h, s, v)
  color_b = _hsv(
    h + rng.uniform(-0.06, 0.06), s * rng.uniform(0.6, 1.2), v - c if v > 0.5 else v + c
  )
  return render.material(
    color_a,
    color_b,
    pattern=str(rng.choice(patterns)),
    freq=rng.uniform(*freq_range),
    seed=int(rng.integers(0, 2**31 - 1)),
  )


def _object_material(
  rng: np.random.Generator, *, textured_p: float = 0.3, freq=(6.0, 14.0)
) -> dict:
  """A saturated object colour, sometimes striped or checkered."""
  h = rng.uniform()
  color_a = _hsv(h, rng.uniform(0.55, 0.95), rng.uniform(0.6, 0.95))
  if rng.uniform() < textured_p:
    color_b = _hsv(h + 0.5, rng.uniform(0.3, 0.9), rng.uniform(0.5, 1.0))
    pattern = str(rng.choice(["stripes_u", "stripes_v", "checker"]))
    return render.material(color_a, color_b, pattern=pattern, freq=rng.uniform(*freq))
  return render.material(color_a)


def _light(
  b: render.SceneBuilder,
  rng: np.random.Generator,
  elevation_deg=(45.0, 70.0),
  ambient=(0.35, 0.5),
  azimuth_deg: float | None = None,
):
  """A directional light at a random elevation and ambient level; its azimuth is random, or
  `azimuth_deg` (the world's fixed sun) when given. The draws are the same either way."""
  az, el = rng.uniform(0, _TWO_PI), np.deg2rad(rng.uniform(*elevation_deg))
  if azimuth_deg is not None:
    az = np.deg2rad(azimuth_deg)
  b.light_dir = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], np.float32)
  b.ambient = float(rng.uniform(*ambient))


# ---------------------------------------------------------------------------------------------
# Shared family machinery.


@dataclasses.dataclass(frozen=True)
class Layout:
  """A built scene plus what pose sampling needs to know about it.

  Attributes:
    scene: the renderer's `Scene` (NumPy leaves).
    footprints: (K, 3) obstacle discs (x, y, radius) in the world frame, for camera rejection.
    origin: (3,) world position of the pose frame's origin (area family; zeros elsewhere).
  """

  scene: render.Scene
  footprints: np.ndarray
  origin: np.ndarray


class ProceduralFamily(abc.ABC):
  """Base class: splits, deterministic pose streams, chunked rendering and view records.

  Subclasses set `name`, `splits` and the primitive `budgets` of `render.SceneBuilder.build`,
  and implement `_build`, `_sample_pose` (or override `poses`) and `_poses_to_c2w`.
  """

  name: str
  splits: tuple[str, ...]
  budgets: dict[str, int]
  # Whether every scene of a split has the same number of views (`num_views(split)` alone).
  fixed_view_count: bool = True
  # Whether `_poses_to_c2w` ignores the scene (then a batch's cameras are one computation).
  scene_independent_cameras: bool = False

  def __init__(self, config):
    self.config = config
    self.camera = render.Camera(
      config.image_size, config.image_size, float(config.fov_deg), int(config.supersample)
    )
    self._layouts: dict[int, Layout] = {}

  # -- sizes and ids --------------------------------------------------------------------------

  @property
  def pose_names(self) -> tuple[str, ...]:
    """Names of the pose components (the registry's, `camrep.data.sources`)."""
    return sources.get(self.name).pose_names

  @property
  def image_size(self) -> int:
    """Square image side in pixels."""
    return self.config.image_size

  def _check_split(self, split: str) -> None:
    if split not in self.splits:
      raise ValueError(f"{self.name}: split must be one of {self.splits}, got {split!r}")

  def _num_train_scenes(self) -> int:
    return self.config.num_train_scenes

  def scene_ids(self, split: str) -> range:
    """Global scene ids of a split (test_scenes ids follow the training ids)."""
    self._check_split(split)
    n_train = self._num_train_scenes()
    if split == "test_scenes":
      return range(n_train, n_train + self.config.num_test_scenes)
    return range(n_train)

  def num_scenes(self, split: str) -> int:
    """Number of scenes in a split."""
    return len(self.scene_ids(split))

  def _check_scene(self, split: str, scene: int) -> None:
    if scene not in self.scene_ids(split):
      raise ValueError(
        f"{self.name}: scene {scene} is not in split {split!r} ({self.scene_ids(split)})"
      )

  @abc.abstractmethod
  def num_views(self, split: str, scene: int | None = None) -> int:
    """Number of views of a scene in a split (families with a fixed count ignore `scene`)."""

  # -- scenes and poses -----------------------------------------------------------------------

  def layout(self, scene: int) -> Layout:
    """The scene's `Layout` (built deterministically from (seed, family, scene); cached)."""
    if scene not in self._layouts:
      if len(self._layouts) >= 256:
        self._layouts.clear()
      self._layouts[scene] = self._build(int(scene))
    return self._layouts[scene]

  def scene(self, scene: int) -> render.Scene:
    """The renderer `Scene` of a scene id."""
    return self.layout(scene).scene

  def _scene_rng(self, scene: int) -> np.random.Generator:
    return _rng(self.config.seed, _FAMILY_CODE[self.name], scene)

  @abc.abstractmethod
  def poses(self, split: str, scene: int) -> np.ndarray:
    """Poses of a scene's views in a split.

    Args:
      split: "train", "test" or "test_scenes".
      scene: global scene id in that split.

    Returns:
      (V, P) float32 poses in the family's convention (`pose_names`).
    """

  def poses_to_c2w(self, scene: int, poses: np.ndarray) -> np.ndarray:
    """Camera-to-world matrices (renderer world frame, OpenCV camera axes) of poses.

    Args:
      scene: scene id.
      poses: (V, P) poses.

    Returns:
      (V, 4, 4) float32.
    """
    poses = np.asarray(poses, np.float32).reshape(-1, len(self.pose_names))
    return np.asarray(self._poses_to_c2w(scene, poses), np.float32)

  # -- rendering ------------------------------------------------------------------------------

  def _render_chunk(self, scene_ids: list[int], c2w: np.ndarray) -> np.ndarray:
    """Renders len(scene_ids) <= batch_size views, padded to one fixed batch shape."""
    bs, n = self.config.batch_size, len(scene_ids)
    ids = list(scene_ids) + [scene_ids[-1]] * (bs - n)
    c2w = np.concatenate([c2w, np.repeat(c2w[-1:], bs - n, axis=0)], axis=0)
    scenes = render.stack_scenes([self.scene(s) for s in ids])
    images = render.render_batch(scenes, c2w, self.camera, shadows=self.config.shadows)
    return render.to_uint8(images)[:n]

  def render_views(self, scene: int, poses: np.ndarray) -> np.ndarray:
    """Renders arbitrary poses of one scene.

    Args:
      scene: scene id (any id of any split).
      poses: (V, P) poses in the family's convention.

    Returns:
      (V, H, W, 3) uint8 RGB.
    """
    c2w = self.poses_to_c2w(scene, poses)
    bs = self.config.batch_size
    out = [
      self._render_chunk([scene] * len(c2w[i : i + bs]), c2w[i : i + bs])
      for i in range(0, len(c2w), bs)
    ]
    size = self.image_size
    return np.concatenate(out, axis=0) if out else np.zeros((0, size, size, 3), np.uint8)

  def render_batch(
    self,
    scene_ids: np.ndarray,
    poses: np.ndarray,
    *,
    max_images: int | None = None,
    on_device: bool = False,
  ):
    """Renders V poses each of S scenes in one jitted renderer call (`render.render_scenes_views`).

    The scenes' parameters and camera matrices go to the device as arrays, the renderer is
    vmapped over scenes and views, and the uint8 conversion runs there too. One compile serves
    every batch of the same (S, V). The images equal `render_views` of each scene within one
    grey level (the same ray caster, batched differently).

    Args:
      scene_ids: (S,) scene ids (any split; repeats allowed).
      poses: (S, V, P) poses in the family's convention, row s of scene `scene_ids[s]`.
      max_images: None (default): one call for the whole batch. Otherwise a bound on S V per
        call (memory): scenes go in chunks of max(1, max_images // V), the last chunk padded
        with copies of its last scene so one compile serves every chunk.
      on_device: return the `jax.Array` left on the default device instead of NumPy.

    Returns:
      (S, V, H, W, 3) uint8 RGB (NumPy, or a jax.Array with `on_device`).
    """
    ids = [int(s) for s in np.asarray(scene_ids).reshape(-1)]
    poses = np.asarray(poses, np.float32)
    p = len(self.pose_names)
    if poses.ndim != 3 or poses.shape[0] != len(ids) or poses.shape[2] != p:
      raise ValueError(f"poses must be (S={len(ids)}, V, {p}), got {poses.shape}")
    n_s, n_v = poses.shape[:2]
    size = self.image_size
    if n_s == 0 or n_v == 0:
      return np.zeros((n_s, n_v, size, size, 3), np.uint8)
    c2w = self._batch_c2w(ids, poses)
    per_call = n_s if max_images is None else max(1, min(n_s, int(max_images) // n_v))
    chunks = []
    for i in range(0, n_s, per_call):
      chunk_ids, chunk_c2w = ids[i : i + per_call], c2w[i : i + per_call]
      n, pad = len(chunk_ids), per_call - len(chunk_ids)
      if pad:
        chunk_ids = chunk_ids + [chunk_ids[-1]] * pad
        chunk_c2w = np.concatenate([chunk_c2w, np.repeat(chunk_c2w[-1:], pad, axis=0)])
      scenes = render.stack_scenes([self.scene(s) for s in chunk_ids])
      images = render.render_scenes_views(
        scenes, chunk_c2w, self.camera, shadows=self.config.shadows, uint8=True
      )
      chunks.append(images[:n] if pad else images)
    if on_device:
      return chunks[0] if len(chunks) == 1 else jnp.concatenate(chunks)
    return np.concatenate([np.asarray(c) for c in chunks])

  def _batch_c2w(self, scene_ids: list[int], poses: np.ndarray) -> np.ndarray:
    """(S, V, P) poses of scenes `scene_ids` -> (S, V, 4, 4) float32 camera-to-world."""
    if self.scene_independent_cameras:  # one call for the whole batch
      n_s, n_v, p = poses.shape
      return self.poses_to_c2w(scene_ids[0], poses.reshape(-1, p)).reshape(n_s, n_v, 4, 4)
    return np.stack([self.poses_to_c2w(s, q) for s, q in zip(scene_ids, poses, strict=True)])

  def iter_views(self, split: str) -> Iterator[dict]:
    """View records of a split, scene by scene, views in order.

    Yields:
      {"image": uint8 (H, W, 3), "pose": float32 (P,), "scene": int, "view": int}.
    """
    jobs = self._jobs(split)
    bs = self.config.batch_size
    while True:
      chunk = [job for _, job in zip(range(bs), jobs, strict=False)]
      if not chunk:
        return
      images = self._render_chunk([j[0] for j in chunk], np.stack([j[3] for j in chunk]))
      for (scene, view, pose, _), image in zip(chunk, images, strict=True):
        yield dict(image=image, pose=pose, scene=int(scene), view=int(view))

  def _jobs(self, split: str) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
    for scene in self.scene_ids(split):
      poses = self.poses(split, scene)
      c2w = self.poses_to_c2w(scene, poses)
      for view in range(len(poses)):
        yield scene, view, poses[view], c2w[view]

  # -- implemented by each family -------------------------------------------------------------

  @abc.abstractmethod
  def _build(self, scene: int) -> Layout:
    """Builds scene `scene` from `self._scene_rng(scene)`."""

  @abc.abstractmethod
  def _poses_to_c2w(self, scene: int, poses: np.ndarray) -> np.ndarray:
    """(V, P) poses -> (V, 4, 4) renderer camera-to-world matrices."""


class SampledPoseFamily(ProceduralFamily):
  """A family whose view `v` of a split is drawn from its own generator
  `default_rng([seed, family, scene, split, v])` by `_sample_pose`."""

  def num_views(self, split: str, scene: int | None = None) -> int:
    """Views per scene of a split (config train_views / test_views; `scene` is ignored)."""
    del scene
    self._check_split(split)
    return self.config.test_views if split == "test" else self.config.train_views

  def poses(self, split: str, scene: int) -> np.ndarray:
    """Poses of a scene's views in a split: (V, P) float32 (see `ProceduralFamily.poses`)."""
    self._check_scene(split, scene)
    layout = self.layout(scene)
    code = (self.config.seed, _FAMILY_CODE[self.name], scene, _SPLIT_CODE[split])
    out = [self._sample_pose(_rng(*code, v), layout) for v in range(self.num_views(split))]
    return np.asarray(out, np.float32).reshape(-1, len(self.pose_names))

  @abc.abstractmethod
  def _sample_pose(self, rng: np.random.Generator, layout: Layout) -> np.ndarray:
    """Draws one (P,) pose of the scene from a per-view generator."""


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
    wall = _surface_material(rng, **wall_kw)
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
        walls.append(_surface_material(rng, hue=hue, **{**wall_kw, "sat": (0.45, 0.8)}))
    else:
      raise ValueError(
        f"unknown wall_style {cfg.wall_style!r}; choose 'tinted', 'distinct' or 'compass'"
      )
    floor = _surface_material(
      rng,
      patterns=("checker", "noise", "tiles", "stripes_u"),
      freq_range=(3.0, 8.0),
      sat=(0.1, 0.6),
      val=(0.35, 0.8),
      contrast=tuple(cfg.texture_contrast),
    )
    ceiling = render.material(_hsv(rng.uniform(), 0.1, 0.9))
    b.set_room((-1.0, -1.0, 0.0), (1.0, 1.0, cfg.room_height), walls + [floor, ceiling])
    _light(b, rng, azimuth_deg=cfg.light_azimuth_deg)
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
      mat = _object_material(rng)
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
      _hsv(hue, sat, val),
      _hsv(hue, sat * 0.5, val * 0.7),
      pattern=str(rng.choice(["flat", "flat", "stripes_u", "stripes_v"])),
      freq=rng.uniform(3.0, 6.0),
    )
    b.add_box((0.0, 0.0, zb), (length / 2, width / 2, h_body / 2), body)
    cab_len = length * rng.uniform(0.4, 0.55)
    cab_x = -length * rng.uniform(0.06, 0.18)
    glass = render.material(_hsv(rng.uniform(0.5, 0.7), 0.35, rng.uniform(0.2, 0.4)))
    b.add_box(
      (cab_x, 0.0, zb + h_body / 2 + h_cab / 2), (cab_len / 2, width * 0.42, h_cab / 2), glass
    )
    nose = render.material(_hsv(rng.uniform(0.08, 0.18), 0.9, 1.0))  # orange-yellow, every car
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
# Furnished rooms (area and scene6dof).


def _furnish(
  b: render.SceneBuilder,
  rng: np.random.Generator,
  lo: np.ndarray,
  hi: np.ndarray,
  n_objects: int,
  keep_out,
  budgets: dict[str, int],
  focus: np.ndarray | None = None,
) -> list[tuple[float, float, float]]:
  """Adds walls/floor/ceiling, furniture and wall paintings to `b`; returns footprints.

  Args:
    b: builder to fill.
    rng: scene generator.
    lo: (3,) room minimum corner (metres, z up; floor at lo[2]).
    hi: (3,) room maximum corner.
    n_objects: furniture pieces to try to place.
    keep_out: f(x, y, radius, top_z) -> True where an object there would block the cameras.
    budgets: the primitive budgets of the family.
    focus: optional (3,) point the cameras look at: a table with two objects is put under it
      (when `keep_out` allows), like the desks of 7-Scenes.

  Returns:
    Footprints (x, y, radius) of the placed furniture.
  """
  wall_patterns = ("stripes_u", "stripes_v", "noise", "tiles", "checker", "flat")
  base_h = rng.uniform()
  walls = [
    _surface_material(
      rng,
      patterns=wall_patterns,
      freq_range=(1.0, 4.0),
      sat=(0.15, 0.6),
      val=(0.5, 0.9),
      hue=base_h + rng.uniform(-0.25, 0.25),
    )
    for _ in range(4)
  ]
  floor = _surface_material(
    rng,
    patterns=("stripes_u", "tiles", "checker", "noise"),
    freq_range=(1.5, 4.0),
    sat=(0.2, 0.6),
    val=(0.3, 0.7),
  )
  ceiling = render.material(_hsv(rng.uniform(), 0.05, 0.92))
  b.set_room(lo, hi, walls + [floor, ceiling])
  _light(b, rng, elevation_deg=(50.0, 75.0), ambient=(0.4, 0.55))
  z0 = float(lo[2])
  used = dict(boxes=0, spheres=0, cylinders=0)

  def room_for(**need) -> bool:
    return all(used[k] + v <= budgets["max_" + k] for k, v in need.items())

  footprints: list[tuple[float, float, float]] = []
  if focus is not None:
    top = float(np.clip(focus[2], z0 + 0.5, z0 + 1.0))
    for radius in (0.6, 0.45, 0.3):
      if not keep_out(focus[0], focus[1], radius, top):
        x, y = focus[:2]
        wood = _surface_material(
          rng,
          patterns=("stripes_u", "noise"),
          freq_range=(4.0, 9.0),
          sat=(0.3, 0.6),
          val=(0.4, 0.7),
        )
        b.add_box((x, y, top - 0.03), (radius, radius * 0.7, 0.03), wood)
        b.add_box(
          (x, y, z0 + (top - 0.06) / 2), (radius * 0.9, radius * 0.6, (top - 0.06) / 2), wood
        )
        r_obj = radius * 0.3
        b.add_sphere((x + radius * 0.4, y, top + r_obj), r_obj, _object_material(rng))
        b.add_box(
          (x - radius * 0.4, y, top + r_obj),
          (r_obj, r_obj, r_obj),
          _object_material(rng, textured_p=1.0),
          yaw=rng.uniform(0, np.pi),
        )
        used.update(boxes=3, spheres=1)
        footprints.append((x, y, radius))
        break
  for _ in range(n_objects):
    kind = str(rng.choice(["table", "shelf", "cabinet", "sofa", "pillar", "lamp", "plant", "ball"]))
    need = dict(
      table=dict(boxes=1),
      shelf=dict(boxes=1),
      cabinet=dict(boxes=1),
      sofa=dict(boxes=2),
      pillar=dict(cylinders=1),
      lamp=dict(cylinders=1, spheres=1),
      plant=dict(cylinders=1, spheres=1),
      ball=dict(spheres=1),
    )[kind]
    if not room_for(**need):
      continue
    size = dict(
      table=0.5, shelf=0.45, cabinet=0.4, sofa=0.6, pillar=0.2, lamp=0.2, plant=0.25, ball=0.25
    )[kind]
    radius = size * rng.uniform(0.8, 1.2)
    top = dict(
      table=0.75, shelf=1.9, cabinet=1.0, sofa=0.8, pillar=hi[2] - z0, lamp=1.7, plant=1.1, ball=0.5
    )[kind]
    placed = None
    for _ in range(200):
      xy = rng.uniform(lo[:2] + radius + 0.05, hi[:2] - radius - 0.05)
      clash = any(np.hypot(*(xy - f[:2])) < radius + f[2] + 0.05 for f in footprints)
      if not clash and not keep_out(xy[0], xy[1], radius, z0 + top):
        placed = xy
        break
    if placed is None:
      continue
    x, y = placed
    yaw = rng.uniform(0, np.pi)
    mat = _object_material(rng, textured_p=0.35, freq=(2.0, 8.0))
    hr = radius / np.sqrt(2)
    if kind == "table":
      b.add_box((x, y, z0 + 0.72), (hr * 1.3, hr * 0.9, 0.03), mat, yaw=yaw)
    elif kind == "shelf":
      shelf = render.material(mat["color_a"], mat["color_a"] * 0.4, pattern="stripes_v", freq=3.0)
      b.add_box((x, y, z0 + top / 2), (hr * 1.2, hr * 0.6, top / 2), shelf, yaw=yaw)
    elif kind == "cabinet":
      b.add_box((x, y, z0 + top / 2), (hr, hr, top / 2), mat, yaw=yaw)
    elif kind == "sofa":
      b.add_box((x, y, z0 + 0.22), (hr * 1.4, hr * 0.8, 0.22), mat, yaw=yaw)
      back = np.array([-np.sin(yaw), np.cos(yaw)]) * hr * 0.65
      b.add_box((x + back[0], y + back[1], z0 + 0.5), (hr * 1.4, hr * 0.15, 0.3), mat, yaw=yaw)
    elif kind == "pillar":
      b.add_cylinder((x, y), z0, hi[2], radius, mat)
    elif kind == "lamp":
      b.add_cylinder((x, y), z0, z0 + top - 0.2, 0.03, render.material((0.2, 0.2, 0.2)))
      b.add_sphere((x, y, z0 + top - 0.1), 0.18, render.material((1.0, 0.95, 0.7)))
    elif kind == "plant":
      b.add_cylinder((x, y), z0, z0 + 0.45, radius * 0.6, mat)
      leaf = render.material(
        (0.15, 0.5, 0.15), (0.3, 0.75, 0.2), pattern="noise", freq=8.0, seed=int(rng.integers(1e6))
      )
      b.add_sphere((x, y, z0 + 0.45 + radius * 1.1), radius * 1.2, leaf)
    else:
      b.add_sphere((x, y, z0 + radius), radius, mat)
    for k, v in need.items():
      used[k] += v
    footprints.append((x, y, radius))
  # Paintings: thin textured boxes on the walls, strong position and yaw cues.
  n_paint = budgets["max_boxes"] - used["boxes"]
  for i in range(min(n_paint, int(rng.integers(3, 7)))):
    wall = (i + int(rng.integers(4))) % 4
    axis, side = wall // 2, wall % 2
    w, h = rng.uniform(0.4, 1.0), rng.uniform(0.3, 0.7)
    zc = z0 + rng.uniform(1.1, 1.8)
    pos = np.zeros(3)
    pos[axis] = (hi if side else lo)[axis] + (-0.02 if side else 0.02)
    other = 1 - axis
    pos[other] = rng.uniform(lo[other] + w, hi[other] - w)
    pos[2] = zc
    half = np.zeros(3)
    half[axis], half[other], half[2] = 0.02, w / 2, h / 2
    art = _surface_material(
      rng,
      patterns=("noise", "checker", "stripes_u", "stripes_v"),
      freq_range=(3.0, 9.0),
      sat=(0.6, 1.0),
      val=(0.5, 1.0),
    )
    b.add_box(pos, half, art)
  return footprints


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
    fp = _furnish(b, rng, lo, hi, n, keep_out, self.budgets)
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
    unknown = set(config.scenes) - set(_SEVEN_SCENES)
    if unknown:
      raise ValueError(f"unknown 7-Scenes scenes {sorted(unknown)}; choose from {_SEVEN_SCENES}")
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
    fp = _furnish(b, rng, lo, hi, n, keep_out, self.budgets, focus=focus)
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


# ---------------------------------------------------------------------------------------------
# Factory.

_CLASSES = {
  "rooms": RoomsFamily,
  "object": ObjectFamily,
  "area": AreaFamily,
  "scene6dof": Scene6DofFamily,
}
_CONFIGS = {
  "rooms": RoomsConfig,
  "object": ObjectConfig,
  "area": AreaConfig,
  "scene6dof": Scene6DofConfig,
}


def make_config(name: str, preset: str = "default", **overrides):
  """The frozen config of a family: defaults, then the preset's overrides, then `overrides`.

  Args:
    name: one of `FAMILIES`.
    preset: "default" (paper-like sizes) or "small" (a few scenes and views).
    **overrides: config fields to replace.

  Returns:
    The family's config dataclass.
  """
  if name not in FAMILIES:
    raise ValueError(f"unknown procedural family {name!r}; choose from {FAMILIES}")
  if preset not in PRESETS:
    raise ValueError(f"preset must be one of {PRESETS}, got {preset!r}")
  fields = dict(SMALL_OVERRIDES[name]) if preset == "small" else {}
  fields.update(overrides)
  return _CONFIGS[name](**fields)


def make_family(name: str, preset: str = "default", **overrides) -> ProceduralFamily:
  """Builds a procedural family; see `make_config` for the arguments."""
  config = make_config(name, preset, **overrides)
  return _CLASSES[name](config)

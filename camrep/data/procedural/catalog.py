"""The procedural families' configs, presets and factory: `make_family(name, preset, **overrides)`.

One frozen config dataclass per family (`RoomsConfig`, `ObjectConfig`, `AreaConfig`,
`Scene6DofConfig`), the `small` preset's overrides (`SMALL_OVERRIDES`), the counts every config
must keep at least 1 (`check_counts`), and `make_config` / `make_family`, which apply defaults, then
the preset, then the caller's overrides. The families themselves are described in
`camrep.data.procedural`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from camrep.data.procedural.families import (
  SEVEN_SCENES,
  AreaFamily,
  ObjectFamily,
  RoomsFamily,
  Scene6DofFamily,
)
from camrep.data.procedural.family_base import ProceduralFamily

FAMILIES = ("rooms", "object", "area", "scene6dof")
PRESETS = ("default", "small")


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
  scenes: tuple[str, ...] = SEVEN_SCENES
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
  config = _CONFIGS[name](**fields)
  check_counts(config)
  return config


COUNTS = (
  "image_size",
  "num_train_scenes",
  "num_test_scenes",
  "num_scenes",
  "train_views",
  "test_views",
  "train_stride",
  "test_stride",
  "supersample",
  "batch_size",
)
"""Fields of the family configs that count something and must be at least 1: a split without
scenes or views cannot be stored or evaluated, and the others size or divide the rendering."""


def check_counts(config) -> None:
  """Refuses counts a family cannot render with, before anything is rendered or written.

  Args:
    config: a family's config dataclass.

  Raises:
    ValueError: a field of `COUNTS` that is not an integer >= 1, or min_objects below 0 or
      above max_objects.
  """
  for field in COUNTS:
    value = getattr(config, field, None)
    if field in {f.name for f in dataclasses.fields(config)} and (
      isinstance(value, bool) or not isinstance(value, int) or value < 1
    ):
      raise ValueError(f"{field}={value!r}: must be an integer >= 1")
  low, high = getattr(config, "min_objects", 0), getattr(config, "max_objects", 0)
  if low < 0 or low > high:
    raise ValueError(
      f"min_objects={low!r}, max_objects={high!r}: must satisfy 0 <= min_objects <= max_objects"
    )


def make_family(name: str, preset: str = "default", **overrides) -> ProceduralFamily:
  """Builds a procedural family; see `make_config` for the arguments."""
  config = make_config(name, preset, **overrides)
  return _CLASSES[name](config)

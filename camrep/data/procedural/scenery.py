"""Random scene content of the procedural families: two-colour surface and object materials,
the directional light, and furnished rooms (walls, floor, furniture, wall paintings) shared by
the area and scene6dof families. Every function draws from the scene generator it is given, in
a fixed order, so a scene is a pure function of its seed.
"""

from __future__ import annotations

import colorsys

import numpy as np

from camrep.data.procedural import render

_TWO_PI = 2.0 * np.pi


def hsv(h: float, s: float, v: float) -> np.ndarray:
  return np.asarray(colorsys.hsv_to_rgb(h % 1.0, float(np.clip(s, 0, 1)), float(np.clip(v, 0, 1))))


def surface_material(
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
  color_a = hsv(h, s, v)
  color_b = hsv(
    h + rng.uniform(-0.06, 0.06), s * rng.uniform(0.6, 1.2), v - c if v > 0.5 else v + c
  )
  return render.material(
    color_a,
    color_b,
    pattern=str(rng.choice(patterns)),
    freq=rng.uniform(*freq_range),
    seed=int(rng.integers(0, 2**31 - 1)),
  )


def object_material(rng: np.random.Generator, *, textured_p: float = 0.3, freq=(6.0, 14.0)) -> dict:
  """A saturated object colour, sometimes striped or checkered."""
  h = rng.uniform()
  color_a = hsv(h, rng.uniform(0.55, 0.95), rng.uniform(0.6, 0.95))
  if rng.uniform() < textured_p:
    color_b = hsv(h + 0.5, rng.uniform(0.3, 0.9), rng.uniform(0.5, 1.0))
    pattern = str(rng.choice(["stripes_u", "stripes_v", "checker"]))
    return render.material(color_a, color_b, pattern=pattern, freq=rng.uniform(*freq))
  return render.material(color_a)


def add_light(
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


def furnish(
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
    surface_material(
      rng,
      patterns=wall_patterns,
      freq_range=(1.0, 4.0),
      sat=(0.15, 0.6),
      val=(0.5, 0.9),
      hue=base_h + rng.uniform(-0.25, 0.25),
    )
    for _ in range(4)
  ]
  floor = surface_material(
    rng,
    patterns=("stripes_u", "tiles", "checker", "noise"),
    freq_range=(1.5, 4.0),
    sat=(0.2, 0.6),
    val=(0.3, 0.7),
  )
  ceiling = render.material(hsv(rng.uniform(), 0.05, 0.92))
  b.set_room(lo, hi, walls + [floor, ceiling])
  add_light(b, rng, elevation_deg=(50.0, 75.0), ambient=(0.4, 0.55))
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
        wood = surface_material(
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
        b.add_sphere((x + radius * 0.4, y, top + r_obj), r_obj, object_material(rng))
        b.add_box(
          (x - radius * 0.4, y, top + r_obj),
          (r_obj, r_obj, r_obj),
          object_material(rng, textured_p=1.0),
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
    mat = object_material(rng, textured_p=0.35, freq=(2.0, 8.0))
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
    art = surface_material(
      rng,
      patterns=("noise", "checker", "stripes_u", "stripes_v"),
      freq_range=(3.0, 9.0),
      sat=(0.6, 1.0),
      val=(0.5, 1.0),
    )
    b.add_box(pos, half, art)
  return footprints

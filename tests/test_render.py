"""Tests of camrep.data.procedural.render: ray/primitive intersections, camera conventions,
shading, jit."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from camrep.data.procedural import render

GREY = render.material((0.5, 0.5, 0.5))
_NUM_RAYS = 8  # trace() calls are padded to this many rays: one compile serves every test
_trace = jax.jit(render.trace, static_argnames="shadows")


def trace(o, d, scene, *, shadows=True) -> dict:
  """Jitted `render.trace` on rays padded to `_NUM_RAYS`; returns NumPy arrays."""
  n = len(o)
  pad = lambda x: np.concatenate([x, np.repeat(x[-1:], _NUM_RAYS - n, axis=0)])
  out = _trace(pad(o), pad(d), scene, shadows=shadows)
  return {k: np.asarray(v)[:n] for k, v in out.items()}


pytestmark = pytest.mark.usefixtures("fast_compile")


def _rays(origins, directions):
  o = np.asarray(origins, np.float32).reshape(-1, 3)
  d = np.asarray(directions, np.float32).reshape(-1, 3)
  return o, d / np.linalg.norm(d, axis=-1, keepdims=True)


def _scene(build) -> render.Scene:
  b = render.SceneBuilder()
  build(b)
  return b.build(max_boxes=2, max_spheres=2, max_cylinders=2, max_planes=2)


def test_sphere_straight_ahead_hits_at_known_depth():
  scene = _scene(lambda b: b.add_sphere((3.0, 0.0, 0.0), 1.0, GREY))
  o, d = _rays([[0, 0, 0], [0, 0, 0], [0, 5, 0]], [[1, 0, 0], [-1, 0, 0], [1, 0, 0]])
  t = np.asarray(render.intersect_spheres(o, d, scene.spheres))
  np.testing.assert_allclose(t[0, 0], 2.0, rtol=1e-6)
  assert t[1, 0] >= 1e9 and t[2, 0] >= 1e9  # behind the camera; passing beside it
  assert np.all(t[:, 1] >= 1e9)  # the padding slot never hits


def test_box_faces_and_yaw():
  scene = _scene(
    lambda b: b.add_box((0, 0, 0), (1.0, 2.0, 3.0), GREY).add_box(
      (10, 0, 0), (1.0, 2.0, 3.0), GREY, yaw=np.pi / 2
    )
  )
  o, d = _rays(
    [[5, 0, 0], [0, 0, 10], [0, -7, 0], [15, 0, 0]], [[-1, 0, 0], [0, 0, -1], [0, 1, 0], [-1, 0, 0]]
  )
  t = np.asarray(render.intersect_boxes(o, d, scene.boxes))
  np.testing.assert_allclose(t[:3, 0], [4.0, 7.0, 5.0], rtol=1e-6)
  np.testing.assert_allclose(t[3, 1], 3.0, rtol=1e-6)  # rotated: the 2.0 half extent faces +x
  hit = trace(o, d, scene, shadows=False)
  np.testing.assert_allclose(hit["normal"][:3], [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-6)
  np.testing.assert_array_equal(hit["kind"], [2, 2, 2, 2])


def test_plane_and_cylinder():
  scene = _scene(
    lambda b: b.add_plane((0, 0, 1), 0.0, GREY).add_cylinder((0.0, 0.0), 0.0, 1.0, 1.0, GREY)
  )
  o, d = _rays([[5, 0, 2]], [[1, 0, -1]])
  np.testing.assert_allclose(
    render.intersect_planes(o, d, scene.planes)[0, 0], 2 * np.sqrt(2), rtol=1e-6
  )
  o, d = _rays([[5, 0, 0.5], [0.2, 0, 5], [0, 5, 2]], [[-1, 0, 0], [0, 0, -1], [0, -1, 0]])
  t = np.asarray(render.intersect_cylinders(o, d, scene.cylinders))[:, 0]
  np.testing.assert_allclose(t[:2], [4.0, 4.0], rtol=1e-6)  # side, top cap
  assert t[2] >= 1e9  # passes above the cylinder
  normal = trace(o[:2], d[:2], scene, shadows=False)["normal"]
  np.testing.assert_allclose(normal, [[1, 0, 0], [0, 0, 1]], atol=1e-5)


def test_room_is_seen_from_inside():
  faces = [render.material((0.1 * k, 0.0, 0.0)) for k in range(6)]

  def build(b):
    b.set_room((-1, -2, 0), (1, 2, 3), faces)
    b.ambient = 1.0

  scene = _scene(build)
  o, d = _rays([[0, 0, 1]] * 4, [[1, 0, 0], [0, -1, 0], [0, 0, -1], [0, 0, 1]])
  np.testing.assert_allclose(render.intersect_room(o, d, scene.room)[:, 0], [1, 2, 1, 2], rtol=1e-6)
  hit = trace(o, d, scene)
  np.testing.assert_allclose(
    hit["normal"], [[-1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1]], atol=1e-6
  )
  # Face materials in ROOM_FACES order: +x -> 1, -y -> 2, floor -> 4, ceiling -> 5.
  np.testing.assert_allclose(hit["rgb"][:, 0], [0.1, 0.2, 0.4, 0.5], atol=1e-6)
  outside = render.intersect_room(*_rays([[5, 0, 1]], [[-1, 0, 0]]), scene.room)
  assert outside[0, 0] >= 1e9


def test_camera_conventions():
  T = np.asarray(render.camera_from_yaw_pitch_roll(np.zeros(3), 0.0, 0.0))
  np.testing.assert_allclose(T[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-6)
  T = np.asarray(render.camera_from_yaw_pitch_roll(np.array([1.0, 2.0, 3.0]), np.pi / 2, 0.3))
  np.testing.assert_allclose(T[:3, 2], [0, np.cos(0.3), np.sin(0.3)], atol=1e-6)
  np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
  np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
  T2 = np.asarray(
    render.look_at(np.array([1.0, 2.0, 3.0]), np.array([1.0, 3.0, 3.0 + np.tan(0.3)]))
  )
  np.testing.assert_allclose(T2, T, atol=1e-6)
  cam = render.Camera(5, 5, 90.0)
  o, d = render.camera_rays(T, cam)
  np.testing.assert_allclose(d[12], T[:3, 2], atol=1e-6)  # the centre pixel looks forward
  np.testing.assert_allclose(d[14] @ T[:3, 0], np.sin(np.arctan(0.8)), atol=1e-6)  # right edge


@pytest.mark.parametrize(
  "center, where", [((3, 0, 0), "centre"), ((3, -1.2, 0), "right"), ((3, 0, 1.2), "top")]
)
def test_objects_appear_where_the_camera_convention_says(center, where):
  scene = _scene(lambda b: b.add_sphere(center, 0.5, render.material((1.0, 0.0, 0.0))))
  T = render.camera_from_yaw_pitch_roll(np.zeros(3), 0.0, 0.0)
  image = np.asarray(render.render_views(scene, T[None], render.Camera(15, 15, 90.0)))[0]
  red = (image[..., 0] > 0.2) & (image[..., 1] < 0.1)
  rows, cols = np.nonzero(red)
  assert red.sum() > 0
  mean_r, mean_c = rows.mean(), cols.mean()
  if where == "centre":
    assert abs(mean_r - 7) < 1 and abs(mean_c - 7) < 1
  elif where == "right":
    assert mean_c > 9 and abs(mean_r - 7) < 1
  else:
    assert mean_r < 5 and abs(mean_c - 7) < 1


def test_shadows_and_background():
  def build(b):
    b.add_plane((0, 0, 1), 0.0, render.material((1.0, 1.0, 1.0)))
    b.add_sphere((0, 0, 1.0), 0.5, GREY)
    b.light_dir = np.array([0.0, 0.0, 1.0])
    b.ambient = 0.2
    b.background = np.array([0.0, 0.0, 1.0])

  scene = _scene(build)
  o, d = _rays([[0, 0, 0.2], [3, 0, 0.2], [0, 0, 3]], [[0, 0, -1], [0, 0, -1], [0, 0, 1]])
  rgb = trace(o, d, scene)["rgb"]
  np.testing.assert_allclose(rgb[0], [0.2] * 3, atol=1e-6)  # floor under the sphere: ambient
  np.testing.assert_allclose(rgb[1], [1.0] * 3, atol=1e-6)  # lit floor
  np.testing.assert_allclose(rgb[2], [0.0, 0.0, 1.0], atol=1e-6)  # sky: background
  rgb_no = trace(o, d, scene, shadows=False)["rgb"]
  np.testing.assert_allclose(rgb_no[0], [1.0] * 3, atol=1e-6)


def test_patterns_are_in_range_and_textured():
  u = np.linspace(0, 3, 200, dtype=np.float32)
  uv = np.stack([u, u * 0.7], axis=-1)
  for k, name in enumerate(render.PATTERNS):
    w = np.asarray(
      render.pattern_value(
        uv, np.full(200, k, np.int32), np.full(200, 2.0, np.float32), np.zeros(200, np.int32)
      )
    )
    assert np.all((w >= 0) & (w <= 1)), name
    assert (w.std() > 0.05) == (name != "flat"), name


def test_jitted_renderers_agree_and_are_deterministic():
  scene = _scene(
    lambda b: b.add_box(
      (3, 0, 0), (0.5, 0.5, 0.5), render.material((1, 0, 0), (0, 1, 0), pattern="checker", freq=4.0)
    )
  )
  cam = render.Camera(8, 8, 60.0, supersample=2)
  T = render.camera_from_yaw_pitch_roll(np.zeros((2, 3)), np.array([0.0, 0.3]), np.zeros(2))
  views = np.asarray(render.render_views(scene, T, cam))
  batch = np.asarray(render.render_batch(render.stack_scenes([scene, scene]), T, cam))
  assert views.shape == (2, 8, 8, 3) and views.dtype == np.float32
  np.testing.assert_allclose(views, batch, atol=1e-6)
  np.testing.assert_array_equal(views, np.asarray(render.render_views(scene, T, cam)))
  assert not np.array_equal(views[0], views[1])
  u8 = render.to_uint8(views)
  assert u8.dtype == np.uint8 and u8.shape == views.shape


def test_builder_checks_budgets_and_arguments():
  b = render.SceneBuilder().add_sphere((0, 0, 0), 1.0, GREY).add_sphere((0, 0, 3), 1.0, GREY)
  with pytest.raises(ValueError, match="budget"):
    b.build(max_boxes=1, max_spheres=1, max_cylinders=1)
  with pytest.raises(ValueError, match="pattern"):
    render.material((1, 1, 1), pattern="plaid")
  with pytest.raises(ValueError, match="z1 > z0"):
    render.SceneBuilder().add_cylinder((0, 0), 1.0, 0.5, 0.1, GREY)

"""A split's procedural scenes and view poses as arrays: built once, then gathered by index.

Building a procedural scene (`family.layout`) and drawing its views' poses (`family.poses`, one
generator per view, rejection sampling) is Python work of about 3 ms a scene; a batch of 30 rooms
built from scratch at every step makes training host-bound (paper-size rooms: 200,000 scenes, so
no cache of recent scenes ever hits). A `SceneTable` holds, for the scenes of a split (a process's
shard), what batches need:

  scenes     the renderer's `render.Scene` of every scene, stacked: leaves (N, ...);
  poses      float32 (N, V_max, P), each scene's view poses (rows past its count are zeros);
  num_views  int64 (N,);
  c2w        float32 (N, V_max, 4, 4) each view's camera-to-world matrix
             (`family.poses_to_c2w`, computed in chunks of many poses where the family's
             cameras do not depend on the scene: rooms, object).

Built from the family's own functions, so its values are the family's exactly. A batch then
gathers rows by index (no Python per scene) and `render` draws the views in one jitted call that
gathers the scenes on the device, where the table is kept after the first call.

Size: about 1.8 KiB a rooms scene (200,000 rooms: 0.35 GiB); `estimate_nbytes` says it before
building. Build time: about 3 ms a scene of one core (200,000 rooms: ~10 min on one core of the
2-core CPU machine), spread over `workers` spawned processes when given.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import multiprocessing
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from camrep.data.procedural import render

_CAMERAS_PER_CALL = 1 << 16
TABLE_MAX_BYTES = 4 * 2**30
"""Default bound on a table's size: a split whose table would be larger is rendered from
scenes built batch by batch instead (`RenderPipeline`)."""


def _scene_c2w(family: Any) -> bool:
  """Whether the family's camera matrices depend on the scene (then the table stores them)."""
  return not getattr(family, "scene_independent_cameras", False)


def _views_max(family: Any, split: str, scene_ids: Sequence[int]) -> int:
  if getattr(family, "fixed_view_count", True):
    return int(family.num_views(split))
  return max(int(family.num_views(split, int(s))) for s in scene_ids)


def _scene_nbytes(scene: render.Scene) -> int:
  return int(sum(np.asarray(x).nbytes for x in jax.tree.leaves(scene)))


def estimate_nbytes(family: Any, split: str, scene_ids: Sequence[int]) -> int:
  """Bytes of the table of `scene_ids` (one scene is built to measure a scene's parameters)."""
  scene_ids = list(scene_ids)
  if not scene_ids:
    return 0
  v = _views_max(family, split, scene_ids)
  per_view = 4 * len(family.pose_names) + 64
  return len(scene_ids) * (_scene_nbytes(family.scene(int(scene_ids[0]))) + v * per_view + 8)


def _build_rows(family: Any, split: str, scene_ids: Sequence[int], views_max: int) -> dict:
  """The scenes and poses of `scene_ids`, built by the family's own NumPy code (no JAX call, so
  a worker process computes exactly what this one would)."""
  n, p = len(scene_ids), len(family.pose_names)
  scenes, poses = [], np.zeros((n, views_max, p), np.float32)
  counts = np.zeros(n, np.int64)
  for i, s in enumerate(int(x) for x in scene_ids):
    scenes.append(family.scene(s))
    q = np.asarray(family.poses(split, s), np.float32)
    poses[i, : len(q)] = q
    counts[i] = len(q)
  return dict(scenes=render.stack_scenes(scenes), poses=poses, counts=counts)


def _worker_init() -> None:
  """Table-building processes stay off accelerators (they compute nothing with JAX)."""
  jax.config.update("jax_platforms", "cpu")


@dataclasses.dataclass
class SceneTable:
  """The scenes and view poses of some scenes of a split (see the module docstring).

  Attributes:
    scene_ids: int64 (N,) the scenes, in table row order.
    scenes: `render.Scene` with NumPy leaves (N, ...).
    poses: float32 (N, V_max, P).
    num_views: int64 (N,).
    c2w: float32 (N, V_max, 4, 4).
  """

  scene_ids: np.ndarray
  scenes: render.Scene
  poses: np.ndarray
  num_views: np.ndarray
  c2w: np.ndarray
  _device: Any = dataclasses.field(default=None, repr=False)

  @classmethod
  def build(
    cls, family: Any, split: str, scene_ids: Sequence[int], *, workers: int = 0, chunk: int = 2048
  ) -> SceneTable:
    """Builds the table of `scene_ids` (in that order) with the family's own functions.

    Args:
      family: a procedural family (`camrep.data.procedural`).
      split: its split.
      scene_ids: the scenes, any order (the rows follow it).
      workers: spawned processes that build chunks of scenes (0: this process).
      chunk: scenes per chunk.
    """
    ids = np.asarray(scene_ids, np.int64)
    views_max = _views_max(family, split, ids)
    chunks = [ids[i : i + chunk] for i in range(0, len(ids), chunk)] or [ids]
    if workers > 0 and len(chunks) > 1:
      ctx = multiprocessing.get_context("spawn")
      with concurrent.futures.ProcessPoolExecutor(
        workers, mp_context=ctx, initializer=_worker_init
      ) as pool:
        parts = list(
          pool.map(_build_rows, *zip(*[(family, split, c, views_max) for c in chunks], strict=True))
        )
    else:
      parts = [_build_rows(family, split, c, views_max) for c in chunks]
    cat = np.concatenate
    poses, counts = cat([p["poses"] for p in parts]), cat([p["counts"] for p in parts])
    # Cameras in this process, on its default backend, as the batch-by-batch path computes them.
    c2w = np.zeros((*poses.shape[:2], 4, 4), np.float32)
    if _scene_c2w(family):
      for i, s in enumerate(ids):
        c2w[i, : counts[i]] = family.poses_to_c2w(int(s), poses[i, : counts[i]])
    else:  # cameras from poses alone: many poses per call
      flat_p, flat_c = poses.reshape(-1, poses.shape[-1]), c2w.reshape(-1, 4, 4)
      for i in range(0, len(flat_p), _CAMERAS_PER_CALL):
        flat_c[i : i + _CAMERAS_PER_CALL] = family.poses_to_c2w(
          int(ids[0]), flat_p[i : i + _CAMERAS_PER_CALL]
        )
    return cls(
      scene_ids=ids,
      scenes=jax.tree.map(lambda *xs: cat(xs), *[p["scenes"] for p in parts]),
      poses=poses,
      num_views=counts,
      c2w=c2w,
    )

  @property
  def nbytes(self) -> int:
    """Bytes of the table's host arrays."""
    arrays = [*jax.tree.leaves(self.scenes), self.poses, self.num_views, self.c2w]
    return int(sum(a.nbytes for a in arrays))

  def device_scenes(self) -> render.Scene:
    """The stacked scenes on the default device (copied there on the first call)."""
    if self._device is None:
      self._device = jax.device_put(self.scenes)
    return self._device

  def render(
    self,
    rows: np.ndarray,
    T_world_cam: np.ndarray,
    camera: render.Camera,
    *,
    shadows: bool,
    max_images: int | None = None,
    on_device: bool = False,
  ):
    """Renders V views each of the scenes in table rows `rows` (`render.render_table_views`).

    Args:
      rows: int (*L) table rows (any leading shape L; repeats allowed).
      T_world_cam: (*L, V, 4, 4) camera-to-world matrices.
      camera: the family's camera.
      shadows: the family's shadow setting.
      max_images: None: one call; otherwise a bound on the images per call (the scenes in
        chunks, the last padded with its last row so one compile serves every chunk).
      on_device: return the `jax.Array` left on the device instead of NumPy.

    Returns:
      (*L, V, H, W, 3) uint8.
    """
    rows = np.asarray(rows, np.int32)
    lead, n_v = rows.shape, T_world_cam.shape[rows.ndim]
    n_s = rows.size
    if n_s == 0 or n_v == 0:
      return np.zeros((*lead, n_v, camera.height, camera.width, 3), np.uint8)
    table = self.device_scenes()
    T_world_cam = np.asarray(T_world_cam, np.float32)
    if max_images is None or n_s * n_v <= max_images:
      images = render.render_table_views(
        table, rows, T_world_cam, camera, shadows=shadows, uint8=True
      )
      return images if on_device else np.asarray(images)
    rows, T_world_cam = rows.reshape(-1), T_world_cam.reshape(n_s, n_v, 4, 4)
    per_call = max(1, int(max_images) // n_v)
    chunks = []
    for i in range(0, n_s, per_call):
      r, t = rows[i : i + per_call], T_world_cam[i : i + per_call]
      n, pad = len(r), per_call - len(r)
      if pad:
        r = np.concatenate([r, np.repeat(r[-1:], pad)])
        t = np.concatenate([t, np.repeat(t[-1:], pad, axis=0)])
      images = render.render_table_views(table, r, t, camera, shadows=shadows, uint8=True)
      chunks.append(images[:n] if pad else images)
    if on_device:
      images = jnp.concatenate(chunks)
    else:
      images = np.concatenate([np.asarray(c) for c in chunks])
    return images.reshape(*lead, *images.shape[1:])

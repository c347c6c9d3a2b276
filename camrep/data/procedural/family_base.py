"""Shared machinery of the procedural families (`camrep.data.procedural`): the `Layout` of a
built scene, the `ProceduralFamily` base class (splits, scene ids, deterministic pose streams,
chunked and batched rendering, view records) and `SampledPoseFamily`, whose views are drawn one
per generator `default_rng([seed, family, scene, split, view])`.
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Iterator

import jax.numpy as jnp
import numpy as np

from camrep.data import sources
from camrep.data.procedural import render

FAMILY_CODE = {"rooms": 1, "object": 2, "area": 3, "scene6dof": 4}
"""Per family: its key in every generator seed (`seeded_rng(seed, FAMILY_CODE[name], ...)`)."""
SPLIT_CODE = {"train": 0, "test": 1, "test_scenes": 2}
"""Per split: its key in the per-view generator seeds."""


def seeded_rng(*keys: int) -> np.random.Generator:
  """`np.random.default_rng` of the integer keys (scene and view generators)."""
  return np.random.default_rng([int(k) for k in keys])


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
    return seeded_rng(self.config.seed, FAMILY_CODE[self.name], scene)

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
    code = (self.config.seed, FAMILY_CODE[self.name], scene, SPLIT_CODE[split])
    out = [self._sample_pose(seeded_rng(*code, v), layout) for v in range(self.num_views(split))]
    return np.asarray(out, np.float32).reshape(-1, len(self.pose_names))

  @abc.abstractmethod
  def _sample_pose(self, rng: np.random.Generator, layout: Layout) -> np.ndarray:
    """Draws one (P,) pose of the scene from a per-view generator."""

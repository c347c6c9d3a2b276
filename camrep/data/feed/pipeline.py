"""Input pipeline: batches of posed views laid out for a pmapped train step (grain).

A batch is a `camrep.data.feed.batches.ViewBatch` of numpy arrays, D = `num_devices` (local
devices), S = `scenes_per_device`, V = `views_per_scene`: image uint8 (D, S, V, H, W, 3), pose
float32 (D, S, V, P), scene int32 (D, S), view int32 (D, S, V); `batches.dummy_batch` gives its
shapes without reading data.

View selection per scene (`PipelineConfig.mode`):

  "random"  V distinct views of the scene in random order (GQN style: the train step splits
            them into context and query views).
  "pairs"   V = 2 * n_pairs views laid out as pairs, views[2i] an anchor and views[2i + 1] a
            near neighbour in pose (reshape to (..., n_pairs, 2)). Anchors are distinct views
            drawn at random; the partner is drawn uniformly among the anchor's `pair_k`
            nearest views of the same scene by Euclidean distance in a per-DOF-normalised pose
            space: each pose difference is divided by that DOF's spread over the split (std,
            or the circular std for the periodic angles yaw, azimuth, theta, psi, whose
            differences are also wrapped to [-pi, pi)). This is the generic stand-in for the
            authors' per-dataset pair rules (car: fixed listed pairs; Gibson: grid-key
            neighbours; 7-Scenes: frame i and i + 2/3), which need metadata that not every
            source has; it gives the same kind of pair, a small pose shift within one scene.

Order and determinism: the batch at step k is a pure function of (seed, k, process_index,
process_count, the split's view index), so a run resumed at step k sees exactly the batches
the uninterrupted run would have seen (`BatchPipeline.iterator(start_step=k)`). Scenes are
drawn without replacement within an epoch: epoch e = k // steps_per_epoch uses the
permutation `default_rng([seed, 0, e])` of this process's scenes; views use
`default_rng([seed, 1, k, process_index])`.

Multi-host: the split's scenes (sorted by id) are dealt round-robin, process p reading scenes
p, p + process_count, ... only (disjoint, covering). Every process uses the same
steps_per_epoch, computed from the smallest shard, so all processes turn epochs together.

Backends share the batching code: `tfds_pipeline` reads the ArrayRecord files written by
`camrep.data.feed.storage.prepare` (grouping by scene comes from the sidecar index, only the
selected PNGs are decoded); `memory_pipeline` holds a source's split in memory (tests, quick
runs). `BatchPipeline.iterator` wraps `batch` in a `grain.MapDataset` over step numbers and
prefetches it: with `num_workers` > 0 in that many worker processes (grain's `mp_prefetch`: worker
w builds the batches of steps start + w, start + w + num_workers, ..., and the iterator hands them
out in step order), otherwise in grain reader threads of this process (cv2's PNG decoding releases
the GIL, but the rest of a batch does not). Either way element i is `batch(start_step + i)`, so the
data stays a pure function of (seed, step, process) whatever the number of workers or threads.
`default_num_workers` picks the number from the usable cores, and `prefetch_to_device` keeps the
next batches on their way to the accelerators while the step runs.

`RenderPipeline` (procedural families rendered on demand) renders each batch in one jitted call
(`family.render_batch`, vmapped over the batch's scenes and views); on an accelerator its "image"
stays there as a `jax.Array` (`prefetch_to_device` then moves it device to device, no host round
trip), so that field is the one exception to "numpy arrays" above.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Any

import grain
import jax
import numpy as np
from absl import flags as absl_flags

from camrep.data.errors import DataError
from camrep.data.feed import batches, draws, storage
from camrep.data.feed.storage import ViewIndex, ViewSource
from camrep.data.procedural import scene_table

MODES = ("random", "pairs")
PERIODIC_POSE_NAMES = frozenset({"yaw", "azimuth", "theta", "psi"})
"""Pose coordinates that are angles on a full circle (wrapped); see `camrep.data.records`."""

_NO_END = 2**62  # "Infinite" stream length for grain's MapDataset.range.

Batch = batches.ViewBatch
ImageReader = Callable[[np.ndarray], np.ndarray]
"""Maps record positions, int (...,), to images, uint8 (..., H, W, 3)."""


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
  """Batch layout, view selection and shuffling of a `BatchPipeline`.

  Attributes:
    num_devices: D, the leading (pmap) axis; the number of local devices.
    scenes_per_device: S, scenes per device per step.
    views_per_scene: V, views per scene ("pairs": 2 * number of pairs).
    mode: "random" or "pairs" (see the module docstring).
    pair_k: "pairs" mode: the partner is drawn among this many nearest views.
    seed: shuffling seed (>= 0).
    num_threads: grain reader threads for `BatchPipeline.iterator` (0: read in the caller);
      with `num_workers` > 0, the threads of each worker process.
    prefetch: batches grain keeps ready ahead of the consumer (per worker with `num_workers`).
    num_workers: worker processes that build the batches of `BatchPipeline.iterator` (PNG
      decoding of prepared datasets); 0: none, batches are built by this process's threads.
  """

  num_devices: int = 1
  scenes_per_device: int = 8
  views_per_scene: int = 9
  mode: str = "random"
  pair_k: int = 4
  seed: int = 0
  num_threads: int = 2
  prefetch: int = 4
  num_workers: int = 0

  @property
  def scenes_per_step(self) -> int:
    """D * S, the scenes in one step's batch on this process."""
    return self.num_devices * self.scenes_per_device

  @property
  def scene_views_needed(self) -> int:
    """Views every scene must have: V distinct views ("random"), or V / 2 anchors, at least
    2 ("pairs")."""
    if self.mode == "random":
      return self.views_per_scene
    return max(2, self.views_per_scene // 2)

  @classmethod
  def from_mapping(cls, cfg: Mapping[str, Any]) -> PipelineConfig:
    """Builds a config from the matching keys of a dict or ml_collections.ConfigDict."""
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: cfg[k] for k in cfg.keys() if k in names})

  def validate(self) -> None:
    """Raises ValueError on an inconsistent config."""
    for field in ("num_devices", "scenes_per_device", "views_per_scene", "pair_k"):
      if getattr(self, field) < 1:
        raise ValueError(f"PipelineConfig.{field} must be >= 1, got {getattr(self, field)}")
    if self.mode not in MODES:
      raise ValueError(f"PipelineConfig.mode must be one of {MODES}, got {self.mode!r}")
    if self.mode == "pairs" and self.views_per_scene % 2:
      raise ValueError(f"'pairs' mode needs an even views_per_scene, got {self.views_per_scene}")
    if self.seed < 0 or self.num_threads < 0 or self.prefetch < 0 or self.num_workers < 0:
      raise ValueError("PipelineConfig.seed, num_threads, prefetch and num_workers must be >= 0")


def usable_cores() -> int:
  """CPU cores this process may run on (its affinity mask; `os.cpu_count()` where there is none)."""
  try:
    return len(os.sched_getaffinity(0))
  except AttributeError:  # not on Linux
    return os.cpu_count() or 1


def default_num_workers(cores: int | None = None) -> int:
  """Worker processes for a prepared dataset's batches when `data.num_workers` is -1 ("auto").

  All usable cores but two (one for the training loop, which dispatches the step and feeds the
  device, one for the grain and XLA threads around it), at most 32: 14 on a 16-core GPU machine,
  0 on the 2-core CPU machine (no worker processes; reader threads, as before).
  """
  cores = usable_cores() if cores is None else cores
  return max(0, min(32, cores - 2))


def prefetch_to_device(
  batches: Iterable[Mapping[str, np.ndarray]],
  size: int = 2,
  *,
  keys: Sequence[str] = ("image", "pose", "scene"),
  devices: Sequence[Any] | None = None,
  device_axis: int = 0,
) -> Iterator[dict[str, jax.Array]]:
  """Copies batches to the local devices `size` batches ahead of the consumer.

  Each array is split along its device axis over `devices`, as the pmapped step takes it, by
  `jax.device_put`, which returns at once: the copies of the next batches run while the current
  step computes (flax.jax_utils.prefetch_to_device, with today's sharding API).

  Args:
    batches: host batches, arrays (D, ...) with D = len(devices), or (K, D, ...) with
      `device_axis=1` (K steps stacked, `BatchPipeline.batches`).
    size: batches in flight (2 is enough to hide one batch's copy behind a step).
    keys: the fields to copy (the others are dropped).
    devices: the devices of the device axis (default: `jax.local_devices()`).
    device_axis: the axis split over the devices.

  Returns:
    An iterator of {key: jax.Array} in the order of `batches`.
  """
  devices = list(jax.local_devices() if devices is None else devices)
  spec = jax.sharding.PartitionSpec(*([None] * device_axis), "devices")
  sharding = jax.sharding.NamedSharding(jax.sharding.Mesh(np.asarray(devices), ("devices",)), spec)
  queue: collections.deque = collections.deque()
  it = iter(batches)

  def enqueue(n: int) -> None:
    for b in it:
      # A field already on a device (RenderPipeline's images) moves device to device.
      queue.append({k: jax.device_put(_host_or_device(b[k]), sharding) for k in keys})
      n -= 1
      if n <= 0:
        break

  enqueue(max(1, size))
  while queue:
    out = queue.popleft()
    enqueue(1)
    yield out


def _fit_hint(scenes: int, num_devices: int) -> str:
  """The override that fits a split of `scenes` scenes per process on `num_devices` devices."""
  if scenes >= num_devices:
    return f": pass --config.data.scenes_per_device={scenes // num_devices}"
  return f": use at most {scenes} device(s) (e.g. CUDA_VISIBLE_DEVICES) or more scenes"


def _host_or_device(x: Any) -> Any:
  return x if isinstance(x, jax.Array) else np.asarray(x)


def wrap_angle(x: np.ndarray) -> np.ndarray:
  """Wraps angles (radians) to [-pi, pi)."""
  return (x + np.pi) % (2 * np.pi) - np.pi


def pose_scales(pose: np.ndarray, periodic: np.ndarray) -> np.ndarray:
  """Per-DOF spread used to normalise pose differences.

  Args:
    pose: float (N, P) poses.
    periodic: bool (P,), which DOFs are full-circle angles.

  Returns:
    float64 (P,): the std of each DOF; for periodic DOFs the RMS of the wrapped deviation from
    the circular mean. A DOF with (near-)zero spread gets 1.
  """
  pose = np.asarray(pose, np.float64)
  scale = pose.std(axis=0)
  if periodic.any():
    ang = pose[:, periodic]
    mean = np.arctan2(np.sin(ang).mean(0), np.cos(ang).mean(0))
    scale[periodic] = np.sqrt(np.mean(wrap_angle(ang - mean) ** 2, axis=0))
  return np.where(scale > 1e-8, scale, 1.0)


def pose_distance(
  a: np.ndarray, b: np.ndarray, scale: np.ndarray, periodic: np.ndarray
) -> np.ndarray:
  """Distance in the per-DOF-normalised pose space (periodic DOFs wrapped).

  Args:
    a: float (..., P).
    b: float (..., P), broadcast against `a`.
    scale: (P,) from `pose_scales`.
    periodic: bool (P,).

  Returns:
    float64 (...,): sqrt(sum_d (delta_d / scale_d)^2).
  """
  delta = np.asarray(a, np.float64) - np.asarray(b, np.float64)
  delta = np.where(periodic, wrap_angle(delta), delta) / scale
  return np.sqrt(np.sum(delta**2, axis=-1))


def pair_views(
  anchors: np.ndarray,
  picks: np.ndarray,
  poses: np.ndarray,
  counts: np.ndarray,
  pair_k: int,
  scale: np.ndarray,
  periodic: np.ndarray,
) -> np.ndarray:
  """In "pairs" mode, each anchor view followed by a partner among its nearest views.

  The partner of anchor a is `nearest[pick]`, where `nearest` are the positions of the
  min(pair_k, n - 1) views of the scene nearest to a by `pose_distance` (a itself left out), in
  the order `np.argpartition` gives them.

  Args:
    anchors: int (M, A) anchor views of M scenes (positions among each scene's views).
    picks: int (M, A) draws in [0, min(pair_k, n - 1)).
    poses: float (..., V_max, P), M scenes' view poses (scene m: its first counts[m] rows).
    counts: int (M,) views of each scene.
    pair_k: the neighbourhood size.
    scale: (P,) from `pose_scales`.
    periodic: bool (P,).

  Returns:
    int64 (M, 2 A): anchor, partner, anchor, partner, ...
  """
  m, n_anchors = anchors.shape
  poses = poses.reshape(m, *poses.shape[-2:])
  out = np.empty((m, n_anchors, 2), np.int64)
  out[:, :, 0] = anchors
  for n in np.unique(counts):  # scenes of one view count at a time (scene6dof's differ)
    sel = np.flatnonzero(counts == n)
    p, a = poses[sel, :n], anchors[sel]
    anchor_poses = np.take_along_axis(p, a[:, :, None], axis=1)
    dist = pose_distance(anchor_poses[:, :, None], p[:, None], scale, periodic)
    np.put_along_axis(dist, a[:, :, None], np.inf, axis=2)
    k = min(pair_k, int(n) - 1)
    nearest = np.argpartition(dist, k - 1, axis=2)[:, :, :k]
    out[sel, :, 1] = np.take_along_axis(nearest, picks[sel][:, :, None], axis=2)[:, :, 0]
  return out.reshape(m, 2 * n_anchors)


class BatchPipeline:
  """Deterministic, step-indexed batches over one split (see the module docstring).

  Attributes:
    config: the `PipelineConfig`.
    index: the split's `ViewIndex`.
    process_index: this process, in [0, process_count).
    process_count: number of processes sharing the split.
    scene_ids: int64 (n,), the scene ids this process reads (its shard), sorted.
    steps_per_epoch: steps after which every process has seen its scenes once.
  """

  def __init__(
    self,
    index: ViewIndex,
    read_images: ImageReader,
    config: PipelineConfig,
    *,
    process_index: int = 0,
    process_count: int = 1,
    where: str | os.PathLike | None = None,
  ):
    """Checks the layout against the split and groups its views by scene.

    Args:
      index: the split's views (ids and poses, no images).
      read_images: decodes images at `index.record` positions.
      config: batch layout and seed.
      process_index: this process.
      process_count: number of processes.
      where: path (or name) of the data, for error messages.

    Raises:
      ValueError: bad config or process arguments.
      DataError: the split has too few scenes or views for the layout.
    """
    config.validate()
    if not 0 <= process_index < process_count:
      raise ValueError(
        f"need 0 <= process_index < process_count, got {process_index}, {process_count}"
      )
    self.config = config
    self.index = index
    self.process_index = process_index
    self.process_count = process_count
    self._read_images = read_images
    if len(index) == 0:
      raise DataError(where, "the split holds no views")

    order = np.argsort(index.scene, kind="stable")
    all_ids, starts = np.unique(index.scene[order], return_index=True)
    rows = np.split(order, starts[1:])
    mine = np.arange(process_index, len(all_ids), process_count)
    self.all_scene_ids = all_ids
    self._all_rows = dict(zip(all_ids.tolist(), rows, strict=True))
    self.scene_ids = all_ids[mine]
    scene_rows = [rows[i] for i in mine]

    need = config.scenes_per_step
    shard = len(all_ids) // process_count
    self.steps_per_epoch = shard // need
    if self.steps_per_epoch == 0:
      raise DataError(
        where,
        f"batch layout needs {need} scenes per step ({config.num_devices} devices x "
        f"{config.scenes_per_device}) per process, but the split has {len(all_ids)} scenes "
        f"for {process_count} process(es)" + _fit_hint(shard, config.num_devices),
      )
    min_views = min(len(r) for r in rows)
    need_views = config.scene_views_needed
    if min_views < need_views:
      raise DataError(
        where,
        f"{config.mode!r} mode with views_per_scene={config.views_per_scene} needs {need_views} "
        f"views in every scene, but a scene has only {min_views}",
      )
    self._counts = np.array([len(r) for r in scene_rows], np.int64)
    # Each scene's rows, padded with its last row to the longest scene's count.
    self._rows_pad = np.stack(
      [np.pad(r, (0, self._counts.max() - len(r)), mode="edge") for r in scene_rows]
    )
    self._periodic = np.array([n in PERIODIC_POSE_NAMES for n in index.pose_names], bool)
    self._scale = pose_scales(index.pose, self._periodic)
    self._epoch_cache: dict[int, np.ndarray] = {}

  def _epoch_order(self, epoch: int) -> np.ndarray:
    """This process's scenes (positions in `scene_ids`) in the order of `epoch`."""
    perm = self._epoch_cache.get(epoch)
    if perm is None:
      rng = np.random.default_rng([self.config.seed, 0, epoch])
      perm = rng.permutation(len(self.scene_ids))
      if len(self._epoch_cache) >= 4:  # Reader threads only ever need the current epoch(s).
        self._epoch_cache.clear()
      self._epoch_cache[epoch] = perm
    return perm

  def _positions(self, steps: Sequence[int]) -> np.ndarray:
    """Positions in `scene_ids` of the scenes of each step's batch: int64 (K, D S)."""
    b = self.config.scenes_per_step
    out = np.empty((len(steps), b), np.int64)
    for i, step in enumerate(steps):
      if step < 0:
        raise ValueError(f"step must be >= 0, got {step}")
      epoch, pos = divmod(int(step), self.steps_per_epoch)
      out[i] = self._epoch_order(epoch)[pos * b : (pos + 1) * b]
    return out

  def _views(
    self, steps: Sequence[int], counts: np.ndarray, poses: Callable[[], np.ndarray]
  ) -> np.ndarray:
    """Positions of the chosen views among each scene's views: int64 (K, D S, V).

    Step k's scenes draw from one generator `default_rng([seed, 1, k, process_index])`, scene
    after scene: "random": `choice(n, V, replace=False)`; "pairs": `choice(n, V / 2,
    replace=False)` anchors, then `integers(min(pair_k, n - 1), size=V / 2)` picks among each
    anchor's nearest views (the module docstring). `draws.sequential_draws` computes these draws
    for all scenes at once; where it cannot (a rejected draw, about once in 10^8 steps), numpy
    draws them scene by scene, the same numbers.

    Args:
      steps: the K steps.
      counts: int (K, D S) views of each step's scenes.
      poses: "pairs" mode: returns the scenes' view poses, float (K D S, V_max, P).
    """
    cfg = self.config
    pairs = cfg.mode == "pairs"
    size = cfg.views_per_scene // 2 if pairs else cfg.views_per_scene
    pair_k = cfg.pair_k if pairs else None

    def rngs():
      return [np.random.default_rng([cfg.seed, 1, int(s), self.process_index]) for s in steps]

    drawn = draws.sequential_draws(rngs(), counts, size, pair_k=pair_k)
    if drawn is None:
      drawn = draws.numpy_draws(rngs(), counts, size, pair_k=pair_k)
    chosen, picks = drawn
    if not pairs:
      return chosen
    m = counts.size
    views = pair_views(
      chosen.reshape(m, size),
      picks.reshape(m, size),
      poses(),
      counts.reshape(-1),
      cfg.pair_k,
      self._scale,
      self._periodic,
    )
    return views.reshape(*counts.shape, cfg.views_per_scene)

  def plan(self, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Which views make up the batch at `step` (no image is read).

    Args:
      step: the global step, >= 0.

    Returns:
      rows: int64 (D, S, V), rows of `index`.
      scenes: int64 (D, S), scene ids.
    """
    rows, scenes = self._plans([step])
    return rows[0], scenes[0]

  def _plans(self, steps: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """`plan` of K steps: rows (K, D, S, V), scene ids (K, D, S)."""
    cfg = self.config
    pos = self._positions(steps)
    views = self._views(steps, self._counts[pos], lambda: self.index.pose[self._rows_pad[pos]])
    rows = self._rows_pad[pos[..., None], views]
    shape = (len(steps), cfg.num_devices, cfg.scenes_per_device)
    return rows.reshape(*shape, cfg.views_per_scene), self.scene_ids[pos].reshape(shape)

  def batch(self, step: int) -> Batch:
    """The batch at `step`: a pure function of (seed, step, process, split); a `ViewBatch`."""
    return self._read([step], stacked=False)

  def batches(self, start: int, k: int) -> Batch:
    """The batches of steps start .. start + k - 1 stacked on a new leading axis: a `ViewBatch`
    of (K, D, S, V, ...) arrays, element i equal to `batch(start + i)`, read in one go."""
    return self._read(range(start, start + k), stacked=True)

  def _read(self, steps: Sequence[int], *, stacked: bool) -> Batch:
    rows, scenes = self._plans(steps)
    if not stacked:
      rows, scenes = rows[0], scenes[0]
    return Batch(
      image=self._read_images(self.index.record[rows]),
      pose=self.index.pose[rows].astype(np.float32),
      scene=scenes.astype(np.int32),
      view=self.index.view[rows].astype(np.int32),
    )

  def dataset(
    self,
    *,
    start_step: int = 0,
    num_steps: int | None = None,
    steps_per_element: int = 1,
    spans: Sequence[tuple[int, int]] | None = None,
  ) -> grain.MapDataset:
    """A grain MapDataset whose i-th element is `batch(start_step + i)`, or with
    `steps_per_element` K > 1, `batches(start_step + i K, K)` (the last one shorter when K does
    not divide `num_steps`), or with `spans`, `batches(first, n)` of the i-th (first, n).

    Args:
      start_step: first step (resume point).
      num_steps: number of steps; None for an (effectively) endless stream.
      steps_per_element: K, consecutive steps stacked in each element.
      spans: (first step, number of steps) of each element, for a train loop whose dispatches
        run a varying number of steps (they end at evaluations and checkpoints); replaces the
        other arguments.
    """
    if spans is not None:
      spans = [(int(first), int(n)) for first, n in spans]
      if any(n < 1 for _, n in spans):
        raise ValueError(f"every span must hold at least one step, got {spans}")
      return grain.MapDataset.source(spans).map(self._span_batches)
    k = int(steps_per_element)
    if k < 1:
      raise ValueError(f"steps_per_element must be >= 1, got {steps_per_element}")
    stop = _NO_END if num_steps is None else start_step + num_steps
    if k == 1:
      return grain.MapDataset.range(start_step, stop).map(self.batch)
    n = -(-(stop - start_step) // k)
    return grain.MapDataset.range(0, n).map(
      lambda i: self.batches(start_step + i * k, min(k, stop - start_step - i * k))
    )

  def _span_batches(self, span: tuple[int, int]) -> Batch:
    return self.batches(*span)

  def iterator(
    self,
    *,
    start_step: int = 0,
    num_steps: int | None = None,
    steps_per_element: int = 1,
    spans: Sequence[tuple[int, int]] | None = None,
  ) -> Iterator[Batch]:
    """Batches from `start_step` on, prefetched by worker processes or reader threads.

    With `config.num_workers` > 0, grain's `mp_prefetch` runs that many (spawned) processes,
    each with a copy of this pipeline (the stored split reopens itself there) and
    `config.num_threads` reader threads; close the iterator (`.close()`) to stop them early.

    Args:
      start_step: first step (resume point).
      num_steps: number of steps; None for an endless stream.
      steps_per_element: K: each element stacks K consecutive steps (`dataset`), for a train
        loop that runs K steps per dispatch.
      spans: each element stacks the steps of one (first step, n) (`dataset`).

    Returns:
      A grain DatasetIterator (also supports `get_state`/`set_state`).
    """
    cfg = self.config
    ds = self.dataset(
      start_step=start_step, num_steps=num_steps, steps_per_element=steps_per_element, spans=spans
    )
    # num_threads 0: read in the consumer's thread (grain's default would be 16 threads and a
    # 500-batch buffer).
    threads = cfg.num_threads
    opts = grain.ReadOptions(
      num_threads=threads, prefetch_buffer_size=max(1, cfg.prefetch) if threads else 0
    )
    it_ds = ds.to_iter_dataset(opts)
    if cfg.num_workers > 0:
      # grain reads absl flags (its worker options) when it starts workers; outside an absl
      # program (tests, notebooks) they are unparsed: take their defaults.
      if not absl_flags.FLAGS.is_parsed():
        absl_flags.FLAGS.mark_as_parsed()
      it_ds = it_ds.mp_prefetch(
        grain.MultiprocessingOptions(
          num_workers=cfg.num_workers, per_worker_buffer_size=max(1, cfg.prefetch)
        )
      )
    return iter(it_ds)

  def __iter__(self) -> Iterator[Batch]:
    return self.iterator()

  def num_scene_views(self, scene: int) -> int:
    """Number of views of one scene of the split (0 for an unknown scene)."""
    rows = self._all_rows.get(int(scene))
    return 0 if rows is None else len(rows)

  def scene_views(self, scene: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The first `n` views (by view id) of one scene of the split, any process's shard.

    Returns:
      images uint8 (n, H, W, 3), poses float32 (n, P).

    Raises:
      DataError: unknown scene, or fewer than n views.
    """
    rows = self._all_rows.get(int(scene))
    if rows is None:
      raise DataError(None, f"scene {scene} is not in this split")
    if len(rows) < n:
      raise DataError(None, f"scene {scene} has {len(rows)} views, {n} requested")
    rows = rows[np.argsort(self.index.view[rows], kind="stable")[:n]]
    return self._read_images(self.index.record[rows]), self.index.pose[rows].astype(np.float32)


def memory_pipeline(
  source: ViewSource,
  split: str,
  config: PipelineConfig,
  *,
  process_index: int = 0,
  process_count: int = 1,
) -> BatchPipeline:
  """A `BatchPipeline` over a source's split held in memory (no tfds).

  Args:
    source: the view-record source.
    split: split name.
    config: batch layout and seed.
    process_index: this process.
    process_count: number of processes.
  """
  index, images = storage.views_in_memory(source, split)
  return BatchPipeline(
    index,
    lambda records: images[records],
    config,
    process_index=process_index,
    process_count=process_count,
    where=f"{source.name}/{split}",
  )


def tfds_pipeline(
  data_dir: str | os.PathLike,
  name: str,
  split: str,
  config: PipelineConfig,
  *,
  dataset_config: str | None = None,
  version: str | None = None,
  process_index: int = 0,
  process_count: int = 1,
  select: Callable[[storage.ViewIndex], np.ndarray] | None = None,
) -> BatchPipeline:
  """A `BatchPipeline` over a split prepared by `camrep.data.prepare`, or over the part of it
  `select` keeps.

  Args:
    data_dir: the tfds data directory.
    name: dataset name.
    split: split name.
    config: batch layout and seed.
    dataset_config: the dataset's builder-config name (e.g. the preset), if it has several.
    version: dataset version; defaults to the newest.
    process_index: this process.
    process_count: number of processes.
    select: the split's `ViewIndex` -> bool (N,), the views to keep (a part carved from the
      split when it is read, e.g. a captures dataset's validation views of its training split,
      `records.validation_rows`); None: every view.

  Raises:
    DataError: missing/empty data_dir, unknown dataset or split, layout too large, nothing
      selected.
  """
  stored = storage.load(data_dir, name, split, config=dataset_config, version=version)
  index = stored.index if select is None else stored.index.subset(select(stored.index))
  return BatchPipeline(
    index,
    stored.read_images,
    config,
    process_index=process_index,
    process_count=process_count,
    where=stored.path,
  )


class RenderPipeline(BatchPipeline):
  """`BatchPipeline` over a procedural family that renders each batch's views on demand.

  No index of all views is built (paper-size rooms have 200,000 scenes x 10 views). Batches
  follow the same rules as `BatchPipeline` (epoch permutations of this process's scenes,
  per-step view choice), so a resumed run sees the same data.

  Scenes and poses: with a table (`table`, default: when `scene_table.estimate_nbytes` is at
  most `max_table_bytes`), the scenes and view poses of this process's shard are built once, on
  the first batch, into a `scene_table.SceneTable` (about 3 ms of Python a scene, in
  `table_workers` processes; 1 KiB a rooms scene), and every batch after that gathers its
  scenes, poses and cameras by index: no Python per scene, no scene built twice. Without one (a
  split too large for memory, or `table=False`), each batch builds its own scenes and poses
  (about 3 ms a scene, every step): slower, the same batches.

  Rendering: the batch's scenes and their (D S, V) cameras go to the renderer in ONE jitted call
  (`render.render_table_views`: the scenes gathered by row on the device, vmapped over scenes and
  views, uint8 conversion on the device; one compile per batch layout). The images equal the
  family's per-scene `render_views` (the old path, `one_call=False`, one call per scene, each
  padded to the family's `batch_size`) within one grey level, in practice bit-identical. With
  `images_on_device` (default: when JAX's default backend is not the CPU) "image" is the
  `jax.Array` left where it was rendered, and `prefetch_to_device` hands it to the step
  without a round trip through the host; the other fields are NumPy either way.
  """

  def __init__(
    self,
    family: Any,
    split: str,
    config: PipelineConfig,
    *,
    process_index: int = 0,
    process_count: int = 1,
    one_call: bool = True,
    images_on_device: bool | None = None,
    max_images_per_call: int | None = None,
    table: bool | None = None,
    table_workers: int | None = None,
    max_table_bytes: int = scene_table.TABLE_MAX_BYTES,
  ):
    """Checks the layout against the family's split.

    Args:
      family: a `camrep.data.procedural` family (or any object with its interface).
      split: split name.
      config: batch layout and seed.
      process_index: this process.
      process_count: number of processes.
      one_call: render the batch in one call; False: one `family.render_views` call per scene
        (the old path, kept for benchmarks).
      images_on_device: leave "image" as a device `jax.Array` (None: unless the backend is CPU).
      max_images_per_call: bound on images per renderer call (memory); None: the whole batch.
      table: build this shard's scenes and poses once into a `SceneTable` (True), or build each
        batch's (False); None: a table when its estimate is at most `max_table_bytes`.
      table_workers: processes that build the table (None: `default_num_workers()`, the
        usable cores but two; 0: this process).
      max_table_bytes: the bound of `table=None`.
    """
    config.validate()
    if not 0 <= process_index < process_count:
      raise ValueError(
        f"need 0 <= process_index < process_count, got {process_index}, {process_count}"
      )
    if split not in tuple(getattr(family, "splits", ("train", "test"))):
      raise DataError(None, f"family {family.name!r} has no split {split!r}")
    self.config = config
    self.family = family
    self.split = split
    self.one_call = bool(one_call)
    if images_on_device is None:
      images_on_device = jax.default_backend() != "cpu"
    self.images_on_device = bool(images_on_device)
    self.max_images_per_call = max_images_per_call
    self.process_index = process_index
    self.process_count = process_count
    self.all_scene_ids = np.asarray(family.scene_ids(split), np.int64)
    self.scene_ids = self.all_scene_ids[process_index::process_count]
    need = config.scenes_per_step
    self.steps_per_epoch = (len(self.all_scene_ids) // process_count) // need
    where = f"{family.name}/{split}"
    if self.steps_per_epoch == 0:
      raise DataError(
        where,
        f"batch layout needs {need} scenes per step per process, but the split has "
        f"{len(self.all_scene_ids)} scenes for {process_count} process(es)",
      )
    if getattr(family, "fixed_view_count", True):
      self._counts = np.full(len(self.scene_ids), family.num_views(split), np.int64)
      views = family.num_views(split)
    else:  # per-scene trajectories (scene6dof): the shortest one bounds the batch layout
      self._counts = np.array([family.num_views(split, int(s)) for s in self.scene_ids])
      views = min(family.num_views(split, int(s)) for s in self.all_scene_ids)
    need_views = config.scene_views_needed
    if views < need_views:
      raise DataError(
        where, f"{config.mode!r} mode needs {need_views} views per scene, scenes have {views}"
      )
    names = tuple(family.pose_names)
    self._periodic = np.array([n in PERIODIC_POSE_NAMES for n in names], bool)
    sample = np.concatenate([family.poses(split, int(s)) for s in self.all_scene_ids[:16]])
    self._scale = pose_scales(sample, self._periodic)
    self._epoch_cache = {}
    self.index = None
    if table is None:
      estimate = scene_table.estimate_nbytes(family, split, self.scene_ids)
      table = estimate <= max_table_bytes
    self.uses_table = bool(table) and self.one_call
    self._table_workers = default_num_workers() if table_workers is None else table_workers
    self._table: scene_table.SceneTable | None = None
    self._table_lock = threading.Lock()

  def __getstate__(self) -> dict:
    state = dict(self.__dict__)
    state["_table_lock"] = None
    return state

  def __setstate__(self, state: dict) -> None:
    self.__dict__.update(state)
    self._table_lock = threading.Lock()

  @property
  def table(self) -> scene_table.SceneTable | None:
    """This shard's `SceneTable` (built on first use), or None without one."""
    if not self.uses_table:
      return None
    with self._table_lock:
      if self._table is None:
        self._table = scene_table.SceneTable.build(
          self.family, self.split, self.scene_ids, workers=self._table_workers
        )
    return self._table

  def _scene_poses(self, scene: int) -> np.ndarray:
    return np.asarray(self.family.poses(self.split, int(scene)), np.float32)

  def _tables(self, pos: np.ndarray) -> tuple[scene_table.SceneTable, np.ndarray]:
    """A table holding the scenes at positions `pos` of `scene_ids`, and their rows in it: the
    shard's table, or one built for these scenes alone."""
    table = self.table
    if table is not None:
      return table, pos
    ids, rows = np.unique(self.scene_ids[pos], return_inverse=True)
    return scene_table.SceneTable.build(self.family, self.split, ids), rows.reshape(pos.shape)

  def _plans_in(self, steps: Sequence[int]):
    """(table, rows (K, D S), views (K, D S, V)) of K steps."""
    pos = self._positions(steps)
    table, rows = self._tables(pos)
    views = self._views(steps, table.num_views[rows], lambda: table.poses[rows.reshape(-1)])
    return table, rows, views

  def _plans(self, steps: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """(view ids (K, D, S, V), scene ids (K, D, S)) of K steps."""
    table, rows, views = self._plans_in(steps)
    shape = (len(steps), self.config.num_devices, self.config.scenes_per_device)
    return views.reshape(*shape, -1), table.scene_ids[rows].reshape(shape)

  def _read(self, steps: Sequence[int], *, stacked: bool) -> Batch:
    """The batches of `steps` (`batch`, `batches`), rendered in one call: image NumPy, or a
    jax.Array with `images_on_device`."""
    cfg = self.config
    table, rows, views = self._plans_in(steps)
    lead = (len(steps), cfg.num_devices, cfg.scenes_per_device)
    if not stacked:
      lead = lead[1:]
    rows, views = rows.reshape(lead), views.reshape(*lead, cfg.views_per_scene)
    poses = table.poses[rows[..., None], views]
    scenes = table.scene_ids[rows]
    if not self.one_call:
      per_scene = zip(scenes.reshape(-1), poses.reshape(-1, *poses.shape[-2:]), strict=True)
      images = np.stack([self.family.render_views(int(s), p) for s, p in per_scene])
      images = images.reshape(*views.shape, *images.shape[2:])
    else:
      images = table.render(
        rows,
        table.c2w[rows[..., None], views],
        self.family.camera,
        shadows=self.family.config.shadows,
        max_images=self.max_images_per_call,
        on_device=self.images_on_device,
      )
    return Batch(
      image=images, pose=poses, scene=scenes.astype(np.int32), view=views.astype(np.int32)
    )

  def num_scene_views(self, scene: int) -> int:
    return len(self._scene_poses(scene))

  def scene_views(self, scene: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    poses = self._scene_poses(scene)
    if len(poses) < n:
      raise DataError(None, f"scene {scene} has {len(poses)} views, {n} requested")
    return self.family.render_views(int(scene), poses[:n]), poses[:n]


def render_pipeline(
  family: Any,
  split: str,
  config: PipelineConfig,
  *,
  process_index: int = 0,
  process_count: int = 1,
  **kwargs: Any,
) -> RenderPipeline:
  """A pipeline that renders a procedural family's views batch by batch, one renderer call per
  batch (paper-size runs); `kwargs` go to `RenderPipeline` (one_call, images_on_device,
  max_images_per_call)."""
  return RenderPipeline(
    family, split, config, process_index=process_index, process_count=process_count, **kwargs
  )

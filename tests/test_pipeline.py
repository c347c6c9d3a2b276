"""Tests of camrep.data.feed.pipeline: layout, determinism, resume, process shards, pairs, errors,
the view choice computed for all scenes at once, K stacked steps."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from camrep.data import procedural
from camrep.data.errors import DataError
from camrep.data.feed import draws, pipeline, storage
from camrep.data.feed.pipeline import PipelineConfig

NUM_YAWS = 8


class RingSource:
  """Scene s, view v: camera at x = 0.1 s, y = 0, yaw = 2 pi v / 8 (a ring of 8 headings).

  Pixels encode the ids (channel 0 = scene, channel 1 = view) so batches can be checked
  against their ids; the nearest neighbours of view v in pose are views v +- 1 (mod 8).
  """

  name = "ring"
  pose_names = ("x", "y", "yaw")
  image_size = 4
  _scenes = {"train": 7, "test": 3}

  def num_scenes(self, split: str) -> int:
    return self._scenes[split]

  def pose(self, scene: int, view: int) -> np.ndarray:
    return np.array([0.1 * scene, 0.0, 2 * np.pi * view / NUM_YAWS], np.float32)

  def iter_views(self, split: str):
    for scene in range(self._scenes[split]):
      for view in range(NUM_YAWS):
        image = np.zeros((4, 4, 3), np.uint8)
        image[..., 0], image[..., 1], image[..., 2] = scene, view, len(split)
        yield {"image": image, "pose": self.pose(scene, view), "scene": scene, "view": view}


def make(config: PipelineConfig, **kwargs) -> pipeline.BatchPipeline:
  return pipeline.memory_pipeline(RingSource(), "train", config, **kwargs)


def assert_batches_equal(a: dict, b: dict):
  assert a.keys() == b.keys()
  for k in a:
    np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
  d = tmp_path_factory.mktemp("tfds")
  storage.prepare(RingSource(), d, progress=False)
  return d


@pytest.mark.parametrize("num_devices", [1, 2])
@pytest.mark.parametrize("mode", ["random", "pairs"])
def test_layout_and_content(num_devices, mode):
  cfg = PipelineConfig(
    num_devices=num_devices, scenes_per_device=3 // num_devices or 1, views_per_scene=4, mode=mode
  )
  pipe = make(cfg)
  batch = pipe.batch(0)
  d, s = num_devices, cfg.scenes_per_device
  assert batch["image"].shape == (d, s, 4, 4, 4, 3) and batch["image"].dtype == np.uint8
  assert batch["pose"].shape == (d, s, 4, 3) and batch["pose"].dtype == np.float32
  assert batch["scene"].shape == (d, s) and batch["scene"].dtype == np.int32
  assert batch["view"].shape == (d, s, 4) and batch["view"].dtype == np.int32
  # Pixels, poses and ids all describe the same view.
  np.testing.assert_array_equal(
    batch["image"][..., 0, 0, 0], np.broadcast_to(batch["scene"][..., None], (d, s, 4))
  )
  np.testing.assert_array_equal(batch["image"][..., 0, 0, 1], batch["view"])
  src = RingSource()
  for idx in np.ndindex(d, s, 4):
    np.testing.assert_array_equal(
      batch["pose"][idx], src.pose(batch["scene"][idx[:2]], batch["view"][idx])
    )
  if mode == "random":
    for idx in np.ndindex(d, s):
      assert len(set(batch["view"][idx].tolist())) == 4


def test_tfds_and_memory_pipelines_agree(data_dir):
  cfg = PipelineConfig(num_devices=2, scenes_per_device=1, views_per_scene=4, mode="pairs")
  stored = pipeline.tfds_pipeline(data_dir, "ring", "train", cfg)
  memory = make(cfg)
  for step in (0, 1, 5):
    assert_batches_equal(stored.batch(step), memory.batch(step))


def test_determinism_by_seed():
  cfg = PipelineConfig(scenes_per_device=2, views_per_scene=3, seed=7)
  a, b = make(cfg), make(cfg)
  for step in range(6):
    assert_batches_equal(a.batch(step), b.batch(step))
  other = make(PipelineConfig(scenes_per_device=2, views_per_scene=3, seed=8))
  assert any(not np.array_equal(a.batch(k)["view"], other.batch(k)["view"]) for k in range(6))


def test_restart_at_step_matches_uninterrupted_stream():
  cfg = PipelineConfig(scenes_per_device=2, views_per_scene=3, seed=3, num_threads=2)
  full = list(make(cfg).iterator(num_steps=8))
  assert len(full) == 8
  resumed = list(make(cfg).iterator(start_step=5, num_steps=3))
  for a, b in zip(full[5:], resumed, strict=True):
    assert_batches_equal(a, b)
  unthreaded = make(PipelineConfig(scenes_per_device=2, views_per_scene=3, seed=3, num_threads=0))
  for k, batch in enumerate(itertools.islice(iter(unthreaded), 8)):
    assert_batches_equal(batch, full[k])


@pytest.mark.slow
def test_worker_processes_give_the_same_stream_and_resume(data_dir):
  """num_workers > 0 (grain mp_prefetch, spawned processes decoding the stored PNGs): the same
  batches in the same order as `batch(k)`, from any start step, on every process's shard."""
  for process_index in (0, 1):
    cfg = PipelineConfig(
      num_devices=2, scenes_per_device=1, views_per_scene=4, seed=5, num_threads=1, num_workers=2
    )
    kw = dict(process_index=process_index, process_count=2)
    stored = pipeline.tfds_pipeline(data_dir, "ring", "train", cfg, **kw)
    it = stored.iterator(start_step=3, num_steps=5)
    try:
      got = list(it)
    finally:
      it.close()
    assert len(got) == 5
    reference = pipeline.tfds_pipeline(
      data_dir, "ring", "train", PipelineConfig(**{**cfg.__dict__, "num_workers": 0}), **kw
    )
    for k, batch in enumerate(got):
      assert_batches_equal(batch, reference.batch(3 + k))


def test_num_workers_config():
  from camrep.configs import gqn
  from camrep.runtime.runconfig import ConfigError
  from camrep.synthesis import components

  c = gqn.get_config("smoke")
  assert c.data.num_workers == -1
  assert components.num_workers(c) == pipeline.default_num_workers()
  c.data.num_workers = 3
  assert components.num_workers(c) == 3
  c.data.num_workers = -2
  with pytest.raises(ConfigError, match="num_workers"):
    components.check_config(c)


def test_default_num_workers_from_cores():
  assert pipeline.default_num_workers(16) == 14
  assert pipeline.default_num_workers(2) == 0
  assert pipeline.default_num_workers(1) == 0
  assert pipeline.default_num_workers(128) == 32
  assert pipeline.default_num_workers() == max(0, min(32, pipeline.usable_cores() - 2))


def test_prefetch_to_device_keeps_order_and_values():
  import jax

  cfg = PipelineConfig(scenes_per_device=2, views_per_scene=3, seed=3, num_threads=0)
  pipe = make(cfg)
  host = [pipe.batch(k) for k in range(5)]
  for size in (1, 2, 8):
    got = list(pipeline.prefetch_to_device(iter(host), size))
    assert len(got) == 5
    for a, b in zip(got, host, strict=True):
      assert set(a) == {"image", "pose", "scene"}
      assert all(isinstance(v, jax.Array) for v in a.values())
      for k in a:
        np.testing.assert_array_equal(np.asarray(a[k]), b[k])


def _reference_views(pipe, step: int, scene_poses: list[np.ndarray]) -> np.ndarray:
  """The view choice of one step, scene by scene, as the pipeline made it before its draws were
  computed for all scenes at once: view positions (S, V)."""
  cfg = pipe.config
  rng = np.random.default_rng([cfg.seed, 1, step, pipe.process_index])
  out = []
  for poses in scene_poses:
    n, v = len(poses), cfg.views_per_scene
    if cfg.mode == "random":
      out.append(rng.choice(n, size=v, replace=False))
      continue
    n_pairs = v // 2
    anchors = rng.choice(n, size=n_pairs, replace=False)
    dist = pipeline.pose_distance(poses[anchors, None], poses[None], pipe._scale, pipe._periodic)
    dist[np.arange(n_pairs), anchors] = np.inf
    k = min(cfg.pair_k, n - 1)
    nearest = np.argpartition(dist, k - 1, axis=1)[:, :k]
    partners = nearest[np.arange(n_pairs), rng.integers(k, size=n_pairs)]
    out.append(np.stack([anchors, partners], axis=1).reshape(-1))
  return np.stack(out)


def test_sequential_draws_equal_numpys_own():
  """`draws.sequential_draws` gives, for many generators and scenes at once, numpy's own
  `choice(n, size, replace=False)` (and "pairs" `integers`) drawn scene after scene."""
  rs = np.random.default_rng(0)
  for trial in range(600):
    n_gen, n_scenes, size = int(rs.integers(1, 4)), int(rs.integers(1, 40)), int(rs.integers(1, 12))
    counts = rs.integers(size, size + rs.integers(1, 80), size=(n_gen, n_scenes))
    pair_k = None
    if trial % 2:
      counts, pair_k = np.maximum(counts, 2), int(rs.integers(1, 6))
    seeds = [[int(rs.integers(0, 1000)), 1, trial, g] for g in range(n_gen)]
    got = draws.sequential_draws(
      [np.random.default_rng(s) for s in seeds], counts, size, pair_k=pair_k
    )
    want = draws.numpy_draws([np.random.default_rng(s) for s in seeds], counts, size, pair_k=pair_k)
    assert got is not None
    np.testing.assert_array_equal(got[0], want[0])
    if pair_k is not None:
      np.testing.assert_array_equal(got[1], want[1])
  # A population past numpy's Floyd branch (n > 10,000 and size > n // 50) is left to numpy.
  big = np.array([[20_000]])
  assert draws.sequential_draws([np.random.default_rng(0)], big, 500) is None


class _ZeroWords(np.random.PCG64):
  """A PCG64 whose raw outputs are all 0: every bounded draw of range 2 is rejected (Lemire)."""

  def random_raw(self, size=None, output=True):
    return np.zeros(size, np.uint64)


def test_a_rejected_draw_leaves_the_choice_to_numpy(monkeypatch):
  # Range [0, 2]: threshold (2^32 - 3) mod 3 = 1 > the leftover 0 of a zero word.
  assert draws.sequential_draws([np.random.Generator(_ZeroWords(0))], np.array([[5]]), 3) is None
  cfg = PipelineConfig(scenes_per_device=3, views_per_scene=4, mode="pairs", seed=2)
  want = [make(cfg).plan(k) for k in range(6)]
  monkeypatch.setattr(draws, "sequential_draws", lambda *a, **k: None)
  for k in range(6):
    for a, b in zip(make(cfg).plan(k), want[k], strict=True):
      np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("mode", ["random", "pairs"])
def test_plans_are_the_scene_by_scene_choice(mode):
  """Batches keep their views: the plan of every step is the one numpy drew scene by scene
  (memory pipeline over the ring, and the four procedural families' render pipelines)."""
  cfg = PipelineConfig(scenes_per_device=3, views_per_scene=4, mode=mode, seed=5)
  pipe = make(cfg)
  for step in range(25):
    rows, _ = pipe.plan(step)
    pos = pipe._positions([step])[0]
    per_scene = [pipe._rows_pad[c, : pipe._counts[c]] for c in pos]
    want = _reference_views(pipe, step, [pipe.index.pose[r] for r in per_scene])
    np.testing.assert_array_equal(rows[0], [r[w] for r, w in zip(per_scene, want, strict=True)])
  for name in procedural.FAMILIES:
    family = procedural.make_family(name, preset="small", image_size=16)
    fcfg = PipelineConfig(scenes_per_device=2, views_per_scene=4, mode=mode, seed=5)
    render = pipeline.render_pipeline(family, "train", fcfg)
    for step in range(8):
      views, scenes = render.plan(step)
      want = _reference_views(render, step, [render._scene_poses(s) for s in scenes[0]])
      np.testing.assert_array_equal(views[0], want, err_msg=name)


def test_batches_stack_consecutive_steps():
  """`batches(start, k)` is `batch(start + i)` stacked; `iterator(steps_per_element=k)` hands
  them out k at a time (the last element shorter), and `prefetch_to_device(device_axis=1)`
  splits their device axis."""
  import jax

  cfg = PipelineConfig(num_devices=1, scenes_per_device=2, views_per_scene=3, seed=4)
  pipe = make(cfg)
  stacked = pipe.batches(3, 4)
  assert stacked["image"].shape == (4, 1, 2, 3, 4, 4, 3)
  for i in range(4):
    assert_batches_equal(jax.tree.map(lambda x, i=i: x[i], stacked), pipe.batch(3 + i))
  got = list(pipe.iterator(start_step=2, num_steps=7, steps_per_element=3))
  assert [len(b["scene"]) for b in got] == [3, 3, 1]
  for i, b in enumerate(got):
    assert_batches_equal(b, pipe.batches(2 + 3 * i, len(b["scene"])))
  (fed,) = pipeline.prefetch_to_device([stacked], 1, device_axis=1)
  assert fed["image"].sharding.spec == jax.sharding.PartitionSpec(None, "devices")
  np.testing.assert_array_equal(np.asarray(fed["pose"]), stacked["pose"])
  with pytest.raises(ValueError, match="steps_per_element"):
    pipe.dataset(steps_per_element=0)
  # Spans of varying length (a train loop's dispatches ending at evaluations and checkpoints).
  spans = [(0, 3), (3, 1), (4, 2)]
  got = list(pipe.iterator(spans=spans))
  assert [len(b["scene"]) for b in got] == [3, 1, 2]
  for (first, n), b in zip(spans, got, strict=True):
    assert_batches_equal(b, pipe.batches(first, n))
  with pytest.raises(ValueError, match="at least one step"):
    pipe.dataset(spans=[(0, 0)])


def test_epochs_draw_scenes_without_replacement():
  cfg = PipelineConfig(scenes_per_device=3, views_per_scene=2)
  pipe = make(cfg)
  assert pipe.steps_per_epoch == 2  # 7 scenes // 3.
  for epoch in range(3):
    scenes = np.concatenate([pipe.batch(2 * epoch + k)["scene"].ravel() for k in range(2)])
    assert len(set(scenes.tolist())) == 6
  first = [pipe.batch(k)["scene"].ravel().tolist() for k in range(2)]
  second = [pipe.batch(k)["scene"].ravel().tolist() for k in range(2, 4)]
  assert first != second  # A new permutation each epoch.


@pytest.mark.parametrize("process_count", [2, 3])
def test_process_shards_disjoint_and_covering(process_count):
  cfg = PipelineConfig(scenes_per_device=2, views_per_scene=2)
  pipes = [make(cfg, process_index=p, process_count=process_count) for p in range(process_count)]
  shards = [set(p.scene_ids.tolist()) for p in pipes]
  assert set().union(*shards) == set(range(7))
  assert sum(len(s) for s in shards) == 7
  assert len({p.steps_per_epoch for p in pipes}) == 1
  for p, shard in zip(pipes, shards, strict=True):
    seen = {int(s) for k in range(4) for s in p.batch(k)["scene"].ravel()}
    assert seen <= shard


def test_pairs_are_pose_neighbours_across_the_yaw_seam():
  cfg = PipelineConfig(scenes_per_device=3, views_per_scene=6, mode="pairs", pair_k=2)
  pipe = make(cfg)
  seam = False
  for step in range(12):
    views = pipe.batch(step)["view"].reshape(-1, 2)
    diff = (views[:, 1] - views[:, 0]) % NUM_YAWS
    assert set(diff.tolist()) <= {1, NUM_YAWS - 1}, views
    seam |= any({int(a), int(b)} == {0, NUM_YAWS - 1} for a, b in views)
  assert seam  # Yaw is wrapped: 0 and 7/4 pi are neighbours.


def test_pose_distance_wraps_and_normalises():
  periodic = np.array([False, True])
  scale = pipeline.pose_scales(np.array([[0.0, 0.1], [2.0, 6.2]]), periodic)
  np.testing.assert_allclose(scale[0], 1.0)
  d = pipeline.pose_distance(
    np.array([0.0, 0.05]), np.array([0.0, 2 * np.pi - 0.05]), scale, periodic
  )
  np.testing.assert_allclose(d, 0.1 / scale[1], rtol=1e-6)


def test_layout_errors():
  with pytest.raises(DataError, match="needs 8 scenes per step"):
    make(PipelineConfig(scenes_per_device=8, views_per_scene=2))
  with pytest.raises(DataError, match="needs 4 scenes per step"):
    make(PipelineConfig(scenes_per_device=4, views_per_scene=2), process_index=1, process_count=2)
  with pytest.raises(DataError, match="needs 9 views in every scene"):
    make(PipelineConfig(scenes_per_device=1, views_per_scene=9))
  with pytest.raises(DataError, match="needs 9 views in every scene"):
    make(PipelineConfig(scenes_per_device=1, views_per_scene=18, mode="pairs"))
  with pytest.raises(ValueError, match="even views_per_scene"):
    make(PipelineConfig(views_per_scene=3, mode="pairs"))
  with pytest.raises(ValueError, match="mode must be one of"):
    make(PipelineConfig(mode="nearest"))
  with pytest.raises(ValueError, match="process_index"):
    make(PipelineConfig(scenes_per_device=1), process_index=2, process_count=2)
  with pytest.raises(ValueError, match="step must be >= 0"):
    make(PipelineConfig(scenes_per_device=1, views_per_scene=2)).batch(-1)


def test_data_errors(data_dir, tmp_path):
  cfg = PipelineConfig(scenes_per_device=1, views_per_scene=2)
  with pytest.raises(DataError, match="does not exist"):
    pipeline.tfds_pipeline(tmp_path / "missing", "ring", "train", cfg)
  with pytest.raises(DataError, match="no prepared dataset 'ring'"):
    pipeline.tfds_pipeline(tmp_path, "ring", "train", cfg)
  with pytest.raises(DataError, match="unknown split 'test_scenes'"):
    pipeline.tfds_pipeline(data_dir, "ring", "test_scenes", cfg)
  with pytest.raises(DataError, match="no split 'test_scenes'"):
    pipeline.memory_pipeline(RingSource(), "test_scenes", cfg)
  with pytest.raises(DataError, match="needs 4 scenes per step"):
    pipeline.tfds_pipeline(data_dir, "ring", "test", PipelineConfig(scenes_per_device=4))


def test_config_from_mapping():
  cfg = PipelineConfig.from_mapping({"scenes_per_device": 5, "mode": "pairs", "other": 1})
  assert cfg.scenes_per_device == 5 and cfg.mode == "pairs" and cfg.num_devices == 1

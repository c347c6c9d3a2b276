"""RenderPipeline: batches rendered on demand match the family's records exactly."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from camrep.data import procedural
from camrep.data.errors import DataError
from camrep.data.feed import pipeline
from camrep.data.procedural import scene_table

pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]


def test_render_pipeline_matches_records_and_is_deterministic():
  family = procedural.make_family("rooms", preset="small")
  cfg = pipeline.PipelineConfig(
    num_devices=2, scenes_per_device=1, views_per_scene=3, seed=3, num_threads=0
  )
  pipe = pipeline.render_pipeline(family, "train", cfg)
  b = pipe.batch(1)
  assert b["image"].shape == (2, 1, 3, 64, 64, 3) and b["image"].dtype == np.uint8
  assert b["pose"].shape == (2, 1, 3, 3) and b["scene"].shape == (2, 1)
  records = {(r["scene"], r["view"]): r for r in family.iter_views("train")}
  for d in range(2):
    for v in range(3):
      rec = records[(int(b["scene"][d, 0]), int(b["view"][d, 0, v]))]
      np.testing.assert_array_equal(b["image"][d, 0, v], rec["image"])
      np.testing.assert_array_equal(b["pose"][d, 0, v], rec["pose"])
  again = pipeline.render_pipeline(family, "train", cfg).batch(1)
  for k in b:
    np.testing.assert_array_equal(again[k], b[k])
  images, poses = pipe.scene_views(0, 2)
  np.testing.assert_array_equal(images[1], records[(0, 1)]["image"])
  assert pipe.num_scene_views(0) == 10


def test_render_pipeline_pairs_and_shards():
  family = procedural.make_family("object", preset="small")
  cfg = pipeline.PipelineConfig(scenes_per_device=1, views_per_scene=4, mode="pairs", num_threads=0)
  shards = [
    pipeline.render_pipeline(family, "train", cfg, process_index=i, process_count=2)
    for i in range(2)
  ]
  assert set(shards[0].scene_ids).isdisjoint(shards[1].scene_ids)
  assert sorted({*shards[0].scene_ids, *shards[1].scene_ids}) == list(family.scene_ids("train"))
  b = shards[0].batch(0)
  pairs = b["pose"].reshape(2, 2, 2)  # (pairs, anchor/partner, (azimuth, polar))
  gap = np.abs((pairs[:, 0, 0] - pairs[:, 1, 0] + np.pi) % (2 * np.pi) - np.pi)
  assert np.all(gap < np.pi / 2)  # partners are near neighbours in azimuth
  with pytest.raises(DataError, match="scenes per step"):
    pipeline.render_pipeline(
      family, "train", pipeline.PipelineConfig(scenes_per_device=50, num_threads=0)
    )


def test_render_pipeline_on_per_scene_trajectories():
  """scene6dof scenes have trajectories of different lengths (the paper-size 7-Scenes config
  renders batch by batch through this pipeline)."""
  family = procedural.make_family("scene6dof", preset="small")
  lengths = [family.num_views("train", s) for s in family.scene_ids("train")]
  assert len(set(lengths)) > 1
  cfg = pipeline.PipelineConfig(scenes_per_device=2, views_per_scene=4, mode="pairs", num_threads=0)
  pipe = pipeline.render_pipeline(family, "train", cfg)
  b = pipe.batch(0)
  assert b["image"].shape == (1, 2, 4, 64, 64, 3)
  assert pipe.num_scene_views(1) == lengths[1]
  too_many = pipeline.PipelineConfig(
    scenes_per_device=2, views_per_scene=2 * min(lengths) + 2, mode="pairs", num_threads=0
  )
  with pytest.raises(DataError, match="views per scene"):
    pipeline.render_pipeline(family, "train", too_many)


@pytest.mark.parametrize("name", procedural.FAMILIES)
def test_render_batch_matches_render_views(name):
  """One renderer call for S scenes x V views gives each scene's `render_views` images (issue
  14: within one grey level; measured bit-identical), also when split into padded chunks."""
  family = procedural.make_family(name, preset="small", image_size=16, batch_size=4)
  ids = list(family.scene_ids("train"))[:2]
  poses = np.stack([family.poses("train", s)[:3] for s in ids])
  images = family.render_batch(ids, poses)
  assert images.shape == (2, 3, 16, 16, 3) and images.dtype == np.uint8
  for s, p, got in zip(ids, poses, images, strict=True):
    want = family.render_views(s, p)
    assert np.abs(got.astype(int) - want.astype(int)).max() <= 1
  np.testing.assert_array_equal(family.render_batch(ids, poses, max_images=4), images)
  with pytest.raises(ValueError, match="poses must be"):
    family.render_batch(ids, poses[0])


def test_one_call_batches_equal_the_per_scene_path():
  """RenderPipeline's one-call batches are the old per-scene batches (same views, images within
  one grey level), as NumPy or left on the device, so resume and shards keep their data."""
  family = procedural.make_family("rooms", preset="small", image_size=16, batch_size=4)
  cfg = pipeline.PipelineConfig(
    num_devices=2, scenes_per_device=1, views_per_scene=3, seed=3, num_threads=0
  )
  new = pipeline.render_pipeline(family, "train", cfg, images_on_device=False).batch(2)
  old = pipeline.render_pipeline(family, "train", cfg, one_call=False).batch(2)
  assert isinstance(new["image"], np.ndarray) and new["image"].shape == (2, 1, 3, 16, 16, 3)
  for k in ("pose", "scene", "view"):
    np.testing.assert_array_equal(new[k], old[k])
  assert np.abs(new["image"].astype(int) - old["image"].astype(int)).max() <= 1
  on_device = pipeline.render_pipeline(
    family, "train", cfg, images_on_device=True, max_images_per_call=3
  ).batch(2)
  assert isinstance(on_device["image"], jax.Array)
  np.testing.assert_array_equal(np.asarray(on_device["image"]), new["image"])
  (fed,) = pipeline.prefetch_to_device([on_device], 1)
  np.testing.assert_array_equal(np.asarray(fed["image"]), new["image"])


@pytest.mark.parametrize("name", procedural.FAMILIES)
def test_scene_table_batches_equal_batches_built_per_step(name):
  """The split's scenes, poses and cameras built once into a table give the batches of scenes
  built batch by batch (`table=False`, the path of splits too large for memory) and of the old
  per-scene renderer calls: same views and poses, identical images; `batches(start, k)` renders
  k steps in one call and equals them stacked."""
  family = procedural.make_family(name, preset="small", image_size=16)
  mode = "random" if name == "rooms" else "pairs"
  cfg = pipeline.PipelineConfig(scenes_per_device=2, views_per_scene=4, mode=mode, seed=1)
  kw = dict(images_on_device=False)
  table = pipeline.render_pipeline(family, "train", cfg, table=True, **kw)
  built = pipeline.render_pipeline(family, "train", cfg, max_table_bytes=0, **kw)
  assert table.uses_table and not built.uses_table and built.table is None
  per_scene = pipeline.render_pipeline(family, "train", cfg, one_call=False, table=False)
  stacked = table.batches(1, 2)
  assert stacked["image"].shape == (2, 1, 2, 4, 16, 16, 3)
  for step in (1, 2):
    want = built.batch(step)
    for got in (table.batch(step), per_scene.batch(step)):
      for k in ("image", "pose", "scene", "view"):
        np.testing.assert_array_equal(got[k], want[k], err_msg=f"{name} {k}")
    for k in ("image", "pose", "scene", "view"):
      np.testing.assert_array_equal(stacked[k][step - 1], want[k], err_msg=f"{name} {k}")
  assert table.table.nbytes > 0 and table.table.c2w.shape[:2] == table.table.poses.shape[:2]


def test_scene_table_built_by_worker_processes_is_the_same():
  family = procedural.make_family("area", preset="small", image_size=16)
  ids = list(family.scene_ids("train"))
  here = scene_table.SceneTable.build(family, "train", ids)
  spawned = scene_table.SceneTable.build(family, "train", ids, workers=2, chunk=1)

  def arrays(t):
    return [*jax.tree.leaves(t.scenes), t.poses, t.num_views, t.c2w, t.scene_ids]

  for a, b in zip(arrays(here), arrays(spawned), strict=True):
    np.testing.assert_array_equal(a, b)
  assert scene_table.estimate_nbytes(family, "train", ids) == here.nbytes

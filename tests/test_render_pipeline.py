"""RenderPipeline: batches rendered on demand match the family's records exactly."""

from __future__ import annotations

import numpy as np
import pytest

from camrep.data import pipeline, procedural
from camrep.data.errors import DataError

pytestmark = pytest.mark.usefixtures("fast_compile")


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

"""The held-out evaluation set (camrep/synthesis/heldout.eval_batches) on stand-in pipelines whose
views carry their (scene, view) in the pose: one target view a scene where the split has enough
scenes, several views of each where it has fewer (a one-scene capture), contexts the scene's first
training views."""

from __future__ import annotations

import types

import numpy as np
import pytest

from camrep.data.errors import DataError
from camrep.synthesis import heldout


class _Split:
  """Scenes {id: number of views}; view v of scene s: image filled with v, pose (s, v)."""

  def __init__(self, views: dict[int, int]):
    self.views = views
    self.all_scene_ids = np.array(sorted(views), np.int64)

  def num_scene_views(self, scene: int) -> int:
    return self.views.get(int(scene), 0)

  def scene_views(self, scene: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    assert n <= self.views[int(scene)]
    images = np.broadcast_to(np.arange(n, dtype=np.uint8)[:, None, None, None], (n, 2, 2, 3))
    poses = np.stack([np.full(n, scene), np.arange(n)], axis=1).astype(np.float32)
    return images.copy(), poses


def _model(num_scenes: int, batch_scenes: int, n_context: int | None = 2):
  evals = types.SimpleNamespace(num_scenes=num_scenes, batch_scenes=batch_scenes, baseline_views=3)
  return types.SimpleNamespace(config=types.SimpleNamespace(evals=evals), n_context=n_context)


def _targets(batches) -> list[tuple[int, int]]:
  poses = np.concatenate([b["target_pose"][:, 0] for b in batches])
  scenes = np.concatenate([b["scene"] for b in batches])
  np.testing.assert_array_equal(poses[:, 0], scenes)
  return [(int(s), int(v)) for s, v in poses]


def test_a_split_with_enough_scenes_gives_the_first_test_view_of_each():
  train, test = _Split({s: 5 for s in range(10)}), _Split({s: 4 for s in range(10)})
  batches = heldout.eval_batches(_model(6, 4), train, test)
  assert [len(b["scene"]) for b in batches] == [4, 2]
  assert _targets(batches) == [(s, 0) for s in range(6)]
  for b in batches:
    assert b["target_image"].shape == (len(b["scene"]), 1, 2, 2, 3)
    assert b["context_image"].shape == (len(b["scene"]), 2, 2, 2, 3)
    assert b["scene"].dtype == np.int32


def test_a_one_scene_capture_is_evaluated_on_num_scenes_of_its_views():
  train, test = _Split({0: 100}), _Split({0: 200})
  batches = heldout.eval_batches(_model(5, 2), train, test)
  assert [len(b["scene"]) for b in batches] == [2, 2, 1]
  assert _targets(batches) == [(0, v) for v in range(5)]
  images = np.concatenate([b["target_image"][:, 0, 0, 0, 0] for b in batches])
  np.testing.assert_array_equal(images, np.arange(5))  # each target its own view, not view 0
  for b in batches:  # every target sees the scene's first 2 training views
    np.testing.assert_array_equal(b["context_pose"][..., 1], np.tile([0, 1], (len(b["scene"]), 1)))


def test_fewer_scenes_give_each_the_same_number_of_views_bounded_by_the_fewest():
  train = _Split({0: 9, 1: 9, 2: 9})
  batches = heldout.eval_batches(_model(7, 16), train, _Split({0: 9, 1: 9, 2: 9}))
  assert _targets(batches) == [(s, v) for s in range(3) for v in range(3)]  # ceil(7 / 3) = 3
  batches = heldout.eval_batches(_model(7, 16), train, _Split({0: 9, 1: 2, 2: 9}))
  assert _targets(batches) == [(s, v) for s in range(3) for v in range(2)]


def test_the_baseline_context_is_bounded_by_the_fewest_training_views():
  batches = heldout.eval_batches(
    _model(4, 8, n_context=None), _Split({0: 2, 1: 7}), _Split({0: 3, 1: 3})
  )
  assert batches[0]["context_image"].shape[1] == 2
  assert _targets(batches) == [(0, 0), (0, 1), (1, 0), (1, 1)]


def test_no_scene_in_both_splits_is_refused():
  with pytest.raises(DataError, match="no scene has both"):
    heldout.eval_batches(_model(4, 2), _Split({0: 3}), _Split({1: 3}))

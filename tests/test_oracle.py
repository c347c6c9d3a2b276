"""The nearest-neighbour oracle (camrep.data.oracle): the test that would catch images and pose
labels misaligned on a family's path (a first suspect when a regressor does not learn)."""

from __future__ import annotations

import numpy as np
import pytest

from camrep.data import oracle, procedural
from camrep.regression import views as views_lib
from tests.utils import slow_except

pytestmark = pytest.mark.usefixtures("fast_compile")


def test_nearest_view_poses_hand_made():
  refs = np.zeros((3, 2, 2, 1), np.uint8)
  refs[1] += 100
  refs[2] += 200
  poses = np.array([[0.0], [1.0], [2.0]])
  q = np.stack([refs[2] + 10, refs[0] + 1])
  np.testing.assert_array_equal(oracle.nearest_view_poses(q, refs, poses), [[2.0], [0.0]])
  err = oracle.pose_errors(np.array([[0.1, 6.2]]), np.array([[0.0, 0.1]]), [False, True])
  np.testing.assert_allclose(err, [[0.1, 2 * np.pi - 6.1]], atol=1e-6)


@pytest.mark.parametrize("name", slow_except(["rooms", "area"], ["rooms"]))
def test_regression_views_are_their_labels_rendered(name, tmp_path):
  """Every image the regression reads (through the on-disk cache) is what the renderer draws
  from its pose label: images and labels cannot be misaligned on this path (the first
  candidate, ruled out)."""
  fam = procedural.make_family(name, preset="small")
  views_lib.load_split(fam, "train", cache_dir=str(tmp_path))  # renders and writes the cache
  views = views_lib.load_split(fam, "train", cache_dir=str(tmp_path))  # reads it back
  rows = np.flatnonzero(views.scenes == 1)[::3]
  np.testing.assert_array_equal(fam.render_views(1, views.poses[rows]), views.images(rows))


def test_the_oracle_sees_the_pose_only_where_labels_fit():
  """Dense same-room references: the oracle is well below chance in yaw; with the reference
  labels permuted (a misalignment) it is not."""
  fam = procedural.make_family("rooms", preset="small", train_views=96, test_views=6)
  got = oracle.run(fam, num_scenes=2)
  assert got["num_queries"] == 12
  assert got["oracle_median"]["yaw"] < 0.7 * got["chance_median"]["yaw"], got
  assert got["oracle_median"]["yaw"] < 0.7 * got["control_median"]["yaw"], got

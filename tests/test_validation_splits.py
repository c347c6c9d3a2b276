"""Validation splits that interpolate as the test split does: a capture's validation views are
every k-th of its training views (`views.split_validation(interleaved=True)`), disjoint from its
held-out test views, and a capture run trained with the old split refuses to resume."""

from __future__ import annotations

import json

import numpy as np
import pytest

from camrep import settings
from camrep.configs import regression as regression_config
from camrep.data import records
from camrep.regression import config_schema as reg_schema
from camrep.regression import driver
from camrep.regression import views as views_lib
from camrep.runtime import runconfig
from camrep.runtime import workdir as workdir_lib
from tests.test_captures import prepared_llff


def _views(n_scenes, n_views):
  n = n_scenes * n_views
  return views_lib.ViewSet.in_memory(
    images=np.zeros((n, 2, 2, 3), np.uint8),
    poses=np.zeros((n, 2), np.float32),
    scenes=np.repeat(np.arange(n_scenes), n_views),
    views=np.tile(np.arange(n_views)[::-1], n_scenes),  # stored in reverse view order
  )


def test_interleaved_validation_lies_between_training_views():
  views = _views(2, 25)
  train, val = views_lib.split_validation(settings.CAR, views, 0.1, interleaved=True)
  for s in range(2):
    assert sorted(val.views[val.scenes == s]) == [5, 15]  # every 10th from view 5
    kept = train.views[train.scenes == s]
    assert all(kept.min() < v < kept.max() for v in (5, 15))
  # The old rule: the last views, beyond every training view (extrapolated).
  _, last = views_lib.split_validation(settings.CAR, views, 0.1)
  assert sorted(last.views[last.scenes == 0]) == [22, 23, 24]
  # Small captures: the middle view; one view alone stays in training.
  train, val = views_lib.split_validation(settings.CAR, _views(1, 4), 0.1, interleaved=True)
  assert val.views.tolist() == [2] and len(train) == 3
  train, val = views_lib.split_validation(settings.CAR, _views(1, 1), 0.1, interleaved=True)
  assert len(val) == 0 and len(train) == 1


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
  return prepared_llff(tmp_path_factory.mktemp("capture"))


def _config(data):
  c = regression_config.get_config("car,smoke")
  c.representation = "quat"
  c.data.source, c.data.dir = "llff", data
  return c


def test_capture_validation_interpolates_and_is_disjoint_from_test(capture):
  c = _config(capture)
  d = views_lib.make_data(c, reg_schema.check(c).source)
  val, test = d.evals["validation"].queries, d.evals["test"].queries
  k = records.validation_every(c.data.validation_fraction)
  assert len(val) >= 2 and d.info["validation"].startswith(f"every {k}th training view")
  every = sorted(d.train.views.tolist() + val.views.tolist())
  assert sorted(val.views) == every[k // 2 : len(every) - 1 : k]

  # Disjoint from test and from training: no pose in two of them.
  def keys(v):
    return {tuple(np.round(p, 5)) for p in v.poses}

  assert not keys(val) & keys(test) and not keys(val) & keys(d.train)
  # Interpolated: every validation view has training views before and after it (by view id).
  kept = d.train.views
  assert all(kept.min() < v < kept.max() for v in val.views)


def test_a_capture_run_with_the_old_validation_split_refuses_to_resume(tmp_path, capture):
  wd = tmp_path / "run"
  wd.mkdir()
  c = _config(capture)
  now = driver.data_record(c, reg_schema.check(c).source)
  assert now["version"] == 2 and now["validation"] == "interleaved"
  workdir_lib.write_record(str(wd), {"version": 1, "data": {}})
  with pytest.raises(runconfig.ConfigError, match="old validation split of a capture"):
    driver.check_validation_record(str(wd), now)
  driver.check_validation_record(str(wd), {"version": 1})  # not a capture: nothing to say
  workdir_lib.write_record(str(wd), {"version": 2, "validation": "interleaved", "data": {}})
  driver.check_validation_record(str(wd), now)  # a run of the new split resumes
  # Through the driver: the refusal comes before anything is trained.
  (wd / "record.json").write_text(json.dumps({"version": 1, "data": {}}))
  c.total_steps = 1
  with pytest.raises(runconfig.ConfigError, match="old validation split"):
    driver.run(c, str(wd), log=lambda s: None)

"""A capture column's view synthesis with `--config.evals.split=validation`: its held-out views
are carved from the prepared training split when it is read (every k-th training view of each
capture, k = round(1 / data.validation_fraction), `records.validation_rows`), the same views the
regression validates on; training never sees them and nothing reads the test split."""

from __future__ import annotations

import json

import numpy as np
import pytest

from camrep.configs import regression as regression_config
from camrep.configs import shapenet_car
from camrep.data import records
from camrep.data.feed import pipeline as pipeline_lib
from camrep.data.feed import storage
from camrep.regression import config_schema as reg_schema
from camrep.regression import pose_system
from camrep.regression import views as views_lib
from camrep.runtime import runconfig
from camrep.synthesis import components, config_schema, train
from tests.test_captures import prepared_llff

pytestmark = [pytest.mark.usefixtures("fast_compile")]


class PoisonedSplitRead(Exception):
  """The poisoned test split was read."""


def poison(monkeypatch):
  """Opening a prepared dataset's "test" split raises from now on."""
  init = storage.StoredSplit.__init__

  def guarded(self, path, split):
    if split == "test":
      raise PoisonedSplitRead(f"test split of {path} opened")
    init(self, path, split)

  monkeypatch.setattr(storage.StoredSplit, "__init__", guarded)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
  """One LLFF capture of 40 views, prepared with --preset small (64 px; every 8th view test)."""
  return prepared_llff(tmp_path_factory.mktemp("capture"))


def _config(data, split="validation"):
  c = shapenet_car.get_config("smoke")
  c.data.source, c.data.dir = "llff", data
  c.data.scenes_per_device, c.data.num_workers = 1, 0
  c.total_steps, c.eval_every_steps, c.ckpt_every_steps = 4, 1, 4
  c.stop.min_improvement, c.stop.window, c.stop.min_steps = 0.5, 0.5, 2
  c.evals.split = split
  return c


def _regression(data):
  r = regression_config.get_config("car,smoke")
  r.representation = "quat"
  r.data.source, r.data.dir = "llff", data
  r.data.validation_fraction = 0.1
  return r


def _pairs(scenes, views) -> set[tuple[int, int]]:
  return set(zip(np.ravel(scenes).tolist(), np.ravel(views).tolist(), strict=True))


def test_held_out_views_are_the_regressions_validation_views(capture, monkeypatch):
  r = _regression(capture)
  d = views_lib.make_data(r, reg_schema.check(r).source)
  poison(monkeypatch)
  c = _config(capture)
  config_schema.validate(c)
  assert components.carved_validation(c) == 10
  train_pipe, held = components.make_pipelines(c)
  val = d.evals["validation"].queries
  assert len(val) == 3  # views 5, 15, 25 of the 35 training views
  assert _pairs(held.index.scene, held.index.view) == _pairs(val.scenes, val.views)
  assert _pairs(train_pipe.index.scene, train_pipe.index.view) == _pairs(
    d.train.scenes, d.train.views
  )
  # "test" as before: the prepared test split (poisoned here), the whole training split.
  t = _config(capture, "test")
  assert components.carved_validation(t) is None
  with pytest.raises(PoisonedSplitRead):
    components.make_pipelines(t)
  full = components.make_pipeline(t, "train", num_devices=1)
  assert len(full.index) == len(train_pipe.index) + len(held.index) == 35


@pytest.mark.slow  # one smoke run on the capture: ~30 s on the loaded 2-core CPU
def test_a_capture_run_never_trains_on_its_held_out_views_nor_reads_test(
  tmp_path, capture, monkeypatch
):
  poison(monkeypatch)
  c = _config(capture)
  read, drawn_from = [], []
  batch_read = pipeline_lib.BatchPipeline._read

  def recorded(self, steps, *, stacked):
    b = batch_read(self, steps, stacked=stacked)
    read.append(_pairs(np.broadcast_to(b.scene[..., None], b.view.shape), b.view))
    drawn_from.append(_pairs(self.index.scene, self.index.view))  # every view it could draw
    return b

  monkeypatch.setattr(pipeline_lib.BatchPipeline, "_read", recorded)
  wd = tmp_path / "val"
  train.train_and_evaluate(c, str(wd), log=lambda s: None)
  final = json.loads((wd / "final_metrics.json").read_text())
  assert final["complete"] and np.isfinite(final["eval/psnr"])
  curve = final["stopping"]["curve"]
  assert len(curve) >= 2 and all(np.isfinite(v) for _, v in curve)
  index = storage.load(capture, "llff", "train", config="small").index
  held = records.validation_rows(index.scene, index.view, 10)
  rest = _pairs(index.scene[~held], index.view[~held])
  assert len(read) >= c.total_steps and held.sum() == 3
  assert set().union(*read) <= rest and all(views == rest for views in drawn_from)


def test_what_cannot_be_carved_is_refused(capture):
  c = _config(capture)
  c.data.dir = ""
  with pytest.raises(runconfig.ConfigError, match="a prepared captures dataset holds out"):
    config_schema.check_data(c)
  # A regression reading the run must hold out the same views.
  syn = _config(capture)
  r = _regression(capture)
  pose_system.check_same_validation("syn", syn, r)
  r.data.validation_fraction = 0.25
  with pytest.raises(runconfig.ConfigError, match="held out every 10th training view"):
    pose_system.check_same_validation("syn", syn, r)
  syn.evals.split = "test"  # a run evaluated on test: nothing carved, nothing to compare
  pose_system.check_same_validation("syn", syn, r)
  # data.validation_fraction is used only by a prepared dataset's validation evaluation.
  p = shapenet_car.get_config("smoke")
  with pytest.raises(runconfig.ConfigError, match="data.validation_fraction"):
    config_schema.validate(p, overridden=["data.validation_fraction"])

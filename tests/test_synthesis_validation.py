"""View synthesis' plateau rule on a validation split of its own (`--config.evals.split=
validation`): held-out views of the training scenes drawn apart from "test", so that the first
stage never stops on the images a regression is tested on. The test split is poisoned (reading
it raises) and training and stopping go on unaffected."""

from __future__ import annotations

import json

import numpy as np
import pytest

from camrep.configs import seven_scenes, shapenet_car
from camrep.data import sources
from camrep.data.procedural import families
from camrep.runtime import runconfig
from camrep.synthesis import config_schema, train

pytestmark = [pytest.mark.usefixtures("fast_compile")]


class PoisonedSplitRead(Exception):
  """The poisoned test split was read."""


@pytest.fixture
def poisoned(monkeypatch):
  """Reading any view of the object family's "test" split raises."""
  poses = families.ObjectFamily.poses

  def guarded(self, split, scene):
    if split == "test":
      raise PoisonedSplitRead(f"test split read (scene {scene})")
    return poses(self, split, scene)

  monkeypatch.setattr(families.ObjectFamily, "poses", guarded)


def _config(split):
  c = shapenet_car.get_config("smoke")
  c.total_steps, c.eval_every_steps, c.ckpt_every_steps = 6, 1, 6
  c.stop.min_improvement, c.stop.window, c.stop.min_steps = 0.5, 0.5, 2
  c.evals.split = split
  return c


def _metrics(wd):
  rows = [json.loads(x) for x in open(f"{wd}/metrics.jsonl")]
  return [{k: v for k, v in r.items() if k.startswith("train/loss")} for r in rows]


@pytest.mark.slow  # two smoke runs: ~1 min on the loaded 2-core CPU
def test_the_plateau_rule_never_reads_test_images(tmp_path, poisoned):
  wd = tmp_path / "val"
  train.train_and_evaluate(_config("validation"), str(wd), log=lambda s: None)
  final = json.loads((wd / "final_metrics.json").read_text())
  assert final["complete"] and np.isfinite(final["eval/psnr"])
  curve = final["stopping"]["curve"]
  assert len(curve) >= 2 and all(np.isfinite(v) for _, v in curve)
  # The poison works: the same run evaluating on "test" reads it.
  with pytest.raises(PoisonedSplitRead):
    train.train_and_evaluate(_config("test"), str(tmp_path / "test"), log=lambda s: None)


@pytest.mark.slow  # two smoke runs
def test_training_does_not_depend_on_the_evaluation_split(tmp_path, monkeypatch):
  """Training is the same whichever split evaluates (only eval/ rows differ): the split moves
  the plateau rule's reading, nothing else."""
  a, b = tmp_path / "a", tmp_path / "b"
  for wd, split in ((a, "validation"), (b, "test")):
    c = _config(split)
    c.stop.min_improvement = 0.0  # both to the cap
    train.train_and_evaluate(c, str(wd), log=lambda s: None)
  assert _metrics(a) == _metrics(b)


def test_validation_views_are_neither_training_nor_test_views():
  car = sources.build("object", preset="small")
  for s in range(2):
    val = car.poses("validation", s)
    assert len(val) == car.num_views("test")
    for other in ("train", "test"):
      assert not np.isin(val.round(6), car.poses(other, s).round(6)).all(axis=1).any()
  seven = sources.build("scene6dof", preset="small")
  stride = seven.config.train_stride
  val, tr = seven.poses("validation", 0), seven.poses("train", 0)
  assert len(val) in (len(tr), len(tr) - 1) and stride >= 2
  assert not np.isin(val.round(6), tr.round(6)).all(axis=1).any()
  # At stride 1 every frame trains: no validation split.
  full = sources.build("scene6dof", preset="small", overrides={"train_stride": 1})
  assert "validation" not in full.splits


def test_a_source_without_a_validation_split_is_refused():
  c = seven_scenes.get_config("smoke")
  c.evals.split = "validation"
  config_schema.validate(c)  # the procedural scene6dof family has one
  c.data.source = "nerf"
  with pytest.raises(runconfig.ConfigError, match="has no 'validation' split"):
    config_schema.check_data(c)

"""Restoring a run reads no data: `batches.dummy_batch` stands in for a rendered batch.

Every way a view can be made (the ray-caster's two entry points, a pipeline's batch, a prepared
split's PNG decoding) is made to raise; a finished GQN :smoke run must still restore, with the
checkpoint's parameters, through `restore.load_run`, `train.restore_or_init` and the regression's
`load_pose_system`.
"""

from __future__ import annotations

import shutil

import jax
import numpy as np
import pytest

from camrep.data.feed import batches, pipeline, storage
from camrep.data.procedural import render
from camrep.regression import pose_system
from camrep.runtime import checkpoint as ckpt_lib
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import components, restore
from camrep.synthesis import step as step_lib

pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]


class Rendered(AssertionError):
  """Raised where a restore would make or read a view."""


def _refuse_views(monkeypatch) -> None:
  """Makes rendering, batching and decoding raise `Rendered` for the rest of the test."""
  for owner, name in (
    (render, "render_batch"),
    (render, "render_scenes_views"),
    (pipeline.BatchPipeline, "batch"),
    (pipeline.RenderPipeline, "batch"),
    (storage.StoredSplit, "read_images"),
    (storage, "views_in_memory"),
  ):
    monkeypatch.setattr(owner, name, _raise)


def _raise(*args, **kwargs):
  raise Rendered("a restore rendered or read a view")


def _assert_same_params(a, b):
  flat_a, tree_a = jax.tree.flatten(a)
  flat_b, tree_b = jax.tree.flatten(b)
  assert tree_a == tree_b
  for x, y in zip(flat_a, flat_b, strict=True):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_load_run_renders_nothing(gqn_smoke_run, monkeypatch):
  _refuse_views(monkeypatch)
  run = restore.load_run(gqn_smoke_run)
  assert run.step == 4
  # The pipelines are built on first use, and building the in-memory one renders: the patch
  # bites, so the restore above really made no view.
  with pytest.raises(Rendered):
    run.train_pipe  # noqa: B018


def test_restore_or_init_and_pose_system_render_nothing(gqn_smoke_run, tmp_path, monkeypatch):
  wd = str(tmp_path / "run")
  shutil.copytree(gqn_smoke_run, wd)
  reference = restore.load_run(wd)
  config = workdir_lib.read_config(wd)
  # The trainer's restore (train.train_and_evaluate): template from `step.init_fn`, whose batch is
  # `batches.dummy_batch`; the model's table size from `batches.describe`.
  model = components.make_model(
    components.resolve(config), int(batches.describe(config.data, "train").scene_ids.max()) + 1
  )
  init = step_lib.init_fn(config, model, step_lib.make_optimizers(config))
  _refuse_views(monkeypatch)
  with ckpt_lib.Checkpointer(wd, max_to_keep=config.max_to_keep) as ckpt:
    state_d, _, start = ckpt.restore_or_init(lambda: step_lib.state_dict(init()))
  state = step_lib.from_state_dict(init, state_d)
  assert start == 4
  _assert_same_params(state.params, reference.params)
  system = pose_system.load_pose_system(wd, "gqn")
  assert system["step"] == 4
  _assert_same_params(system["rep"], reference.params["rep"])


def test_dummy_batch_has_the_pipeline_layout_and_gives_the_same_init():
  from camrep.configs import gqn, shapenet_car

  for config in (gqn.get_config("smoke"), shapenet_car.get_config("smoke")):
    pipe = components.make_pipeline(config, "train", num_devices=1)
    real = pipe.batch(0)
    dummy = batches.dummy_batch(config, num_devices=1)
    assert isinstance(real, batches.ViewBatch) and real.keys() == dummy.keys()
    for k in real:
      assert (dummy[k].shape, dummy[k].dtype) == (real[k].shape, real[k].dtype), k
    info = batches.describe(config.data, "train")
    np.testing.assert_array_equal(info.scene_ids, pipe.all_scene_ids)
    # The init reads shapes only: a fresh start from the dummy equals one from batch 0.
    model = components.make_model(components.resolve(config), components.num_train_scenes(pipe))
    key = jax.random.key(config.seed)
    tx = step_lib.make_optimizers(config)
    from_real = step_lib.create_train_state(key, model, tx, real).params
    from_dummy = step_lib.create_train_state(key, model, tx, dummy).params
    _assert_same_params(from_real, from_dummy)

"""Tests of the regression driver (camrep.regression).

The driver runs end to end at configs/regression.py:smoke (tiny car data, a few steps); "ours"
regresses the pose system of a 1-step car :smoke view-synthesis run made here. The tables and the
comparison launcher are tested in test_tables.py and test_comparison.py.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from camrep import settings
from camrep.configs import regression as regression_config
from camrep.configs import shapenet_car
from camrep.regression import config_schema as reg_schema
from camrep.regression import driver as R
from camrep.regression import pose_system
from camrep.regression import views as views_lib
from camrep.runtime import runconfig
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import components
from tests.utils import snapshot

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
  return str(tmp_path_factory.mktemp("regression_cache"))


def _config(setting="car", representation="euler", **kw):
  c = regression_config.get_config(f"{setting},smoke")
  c.representation = representation
  for k, v in kw.items():
    node = c
    *path, last = k.split(".")
    for p in path:
      node = node[p]
    node[last] = v
  return c


def _checked(config):
  """The config, checked by the driver (`check_config`)."""
  reg_schema.check(config)
  return config


def _batching(config):
  """The batch layout the driver resolves from a config."""
  return views_lib.Batching.of(config, settings.get(config.setting))


# ------------------------------------------------------------------------------- the driver


def test_baseline_end_to_end(tmp_path, cache):
  wd = str(tmp_path / "run")
  config = _config(
    "car",
    "euler",
    **{
      "data.cache_dir": cache,
      "optax.lr": 3e-3,
      "seed": 1,
      "eval_every_steps": 2,
      "evals.periodic_all_splits": True,  # learning curves: every split at step 2 too
    },
  )
  results = R.run(config, wd, log=lambda s: None)
  with open(os.path.join(wd, "results.json")) as f:
    assert json.load(f) == json.loads(json.dumps(results))
  # record.json: the data's fingerprint (a baseline has no pose system to record).
  record = workdir_lib.read_record(wd)
  assert record["data"] == views_lib.data_record(config, reg_schema.check(config).source)
  assert "pose_spec" not in record
  assert (results["setting"], results["representation"], results["seed"]) == ("car", "euler", 1)
  assert results["lr"] == 3e-3 and results["steps"] == 3 and results["params"] > 0
  assert results["variant"] == "smoke" and results["representation_params"]["source"] == "none"
  assert results["machine"]["backend"] == "cpu" and results["machine"]["jax"]  # what ran it
  # small object family: 4 cars x 12 training views, the last quarter of each car for validation.
  assert results["data"]["train_views"] == 36 and results["data"]["test_split"] == "test"
  assert results["data"]["num_examples"] == {"validation": 12, "test": 16}
  for split in ("validation", "test"):
    summary = results[split]
    assert set(summary) == {"all", "0", "1", "2", "3"}
    for err in ("rotation_error_deg", "azimuth_error_deg", "polar_error_deg"):
      stats = summary["all"][err]
      assert set(stats) == {"mean", "median"} and 0 <= stats["median"] <= 180
  errs = np.load(os.path.join(wd, "errors_test.npz"))
  assert errs["rotation_error_deg"].shape == (16,) and errs["pred"].shape == (16, 2)
  np.testing.assert_allclose(
    errs["rotation_error_deg"].mean(), results["test"]["all"]["rotation_error_deg"]["mean"], 1e-5
  )
  lines = [json.loads(x) for x in open(os.path.join(wd, "metrics.jsonl"))]
  assert [r["step"] for r in lines if "train/loss" in r] == [2, 3]
  evals = {}
  for r in lines:
    evals.setdefault(r["step"], set()).update(k for k in r if k.startswith("eval/"))
  for step in (2, 3):
    assert {"eval/test/rotation_error_deg_mean", "eval/validation/rotation_error_deg_mean"} <= (
      evals[step]
    )
  with open(os.path.join(wd, "config.json")) as f:
    assert json.load(f)["total_steps"] == 3
  # The cache holds the family prepared as an ArrayRecord dataset; data read back from it has
  # the pixels a fresh render gives.
  assert os.path.isfile(os.path.join(cache, "object", os.listdir(os.path.join(cache, "object"))[0],
                                     "1.0.0", "camrep_source.json"))  # fmt: skip
  cached = views_lib.make_data(config, reg_schema.check(config).source).train
  config.data.cache_dir = ""
  rendered = views_lib.make_data(config, reg_schema.check(config).source).train
  rows = np.arange(len(rendered))
  np.testing.assert_array_equal(cached.images(rows), rendered.images(rows))
  np.testing.assert_array_equal(cached.poses, rendered.poses)
  config.data.cache_dir = cache
  # A rerun in this workdir with another config: refused unless allowed.
  _check_rerun_with_another_config(wd, config)


def _check_rerun_with_another_config(wd, config):
  before = snapshot(wd)
  other = copy.deepcopy(config)
  other.representation = "quat"
  with pytest.raises(runconfig.ConfigError, match="representation: 'euler' -> 'quat'"):
    R.run(other, wd, log=lambda s: None)
  assert snapshot(wd) == before
  other.allow_changes = "representation"
  assert R.run(other, wd, log=lambda s: None)["representation"] == "quat"
  start, rerun = workdir_lib.read_history(wd)
  assert (start["event"], rerun["event"]) == ("start", "rerun")
  assert rerun["changes"] == {"representation": ["euler", "quat"]}
  assert not os.path.exists(os.path.join(wd, workdir_lib.LOCK_FILE))


@pytest.fixture(scope="module")
def car_synthesis(car_smoke_run):
  """The session's shared car run (`conftest.car_smoke_run`: 2 steps)."""
  return car_smoke_run


def test_ours_from_a_synthesis_workdir(tmp_path, cache, car_synthesis):
  config = _config("car", "ours", synthesis_workdir=car_synthesis, **{"data.cache_dir": cache})
  results = R.run(config, str(tmp_path / "ours"), log=lambda s: None)
  info = results["representation_params"]
  assert info["source"] == "synthesis" and info["step"] == 2
  assert info["workdir"] == os.path.abspath(car_synthesis)
  assert results["lr"] == 1e-3  # the paper's car lr (configs/regression.py hparams.car)
  assert np.isfinite(results["test"]["all"]["rotation_error_deg"]["mean"])
  spec, rep, info = pose_system.representation_params(reg_schema.check(config))
  assert spec == components.pose_spec(shapenet_car.get_config("smoke")) and info["step"] == 2
  # The system it read, by content: the digest of the parameters it regressed.
  assert results["representation_params"]["digest"] == pose_system.params_digest(rep)
  # "mlp" with a learned-grid run: its pose spec, a frozen random MLP embedding.
  mlp = _config("car", "mlp", synthesis_workdir=car_synthesis, **{"data.cache_dir": cache})
  spec, params, info = pose_system.representation_params(reg_schema.check(mlp))
  assert info["source"] == "random_init" and set(params) == set(spec.names)
  # A synthesis run of another setting is refused.
  other = _config("gibson", "ours", synthesis_workdir=car_synthesis)
  with pytest.raises(runconfig.ConfigError, match="is a 'car' run"):
    R.run(other, str(tmp_path / "bad"), log=lambda s: None)


def test_config_errors(tmp_path):
  with pytest.raises(runconfig.ConfigError, match="synthesis_workdir"):
    _checked(_config("car", "ours"))
  with pytest.raises(runconfig.ConfigError, match="unknown representation"):
    _checked(_config("car", "quaternion"))
  with pytest.raises(ValueError, match="unknown config variant 'shapenet'"):
    _config("shapenet", "quat")
  bad = _config("car", "quat")
  bad.setting = "shapenet"
  with pytest.raises(runconfig.ConfigError, match="unknown setting 'shapenet'"):
    reg_schema.check(bad)
  with pytest.raises(runconfig.ConfigError, match="no checkpoint|config.json"):
    R.run(_config("car", "ours", synthesis_workdir=str(tmp_path)), str(tmp_path / "x"))
  # gqn: a context larger than a scene's views, on procedural and real data alike.
  with pytest.raises(runconfig.ConfigError, match="a scene has 10 views, 41 needed"):
    R.run(_config("gqn", "quat", **{"data.n_context": 40}), str(tmp_path / "y"))
  c = _checked(_config("gqn", "quat"))
  assert (c.total_steps, c.data.batch_size, c.evals.test_split) == (3, 2, "test_scenes")
  assert c.optax.lr == 1e-4 and c.model.width == 1 / 32
  paper = regression_config.get_config("seven_scenes")
  paper.representation = "logq"
  paper = _checked(paper)
  assert (paper.total_steps, paper.data.batch_size, paper.optax.lr) == (24_000, 64, 5e-5)


def test_a_workdir_of_the_old_config_layout_is_refused(tmp_path):
  """A config.json with every setting's tables (written before the per-setting configs) is
  refused with the way out, before anything is written."""
  wd = tmp_path / "old"
  wd.mkdir()
  old = {**_config("car", "quat").to_dict(), "settings": {"car": {"total_steps": 3}}}
  (wd / "config.json").write_text(json.dumps(old))
  before = snapshot(str(wd))
  with pytest.raises(runconfig.ConfigError, match="rerun in a new workdir"):
    R.run(_config("car", "quat"), str(wd), log=lambda s: None)
  assert snapshot(str(wd)) == before


def test_the_setting_is_the_config_argument(tmp_path):
  base = [sys.executable, "-m", "camrep.regression", "--config=configs/regression.py:smoke"]
  out = subprocess.run(
    base + [f"--workdir={tmp_path / 'cli'}", "--config.setting=gqn"],
    cwd=ROOT,
    capture_output=True,
    text=True,
  )
  assert out.returncode == 2 and "Traceback" not in out.stderr
  assert "--config=configs/regression.py:gqn[,quick|,medium|,smoke]" in out.stderr
  assert not (tmp_path / "cli").exists()
  # Each setting's config holds its own fields only.
  gqn, seven, car = (
    regression_config.get_config(f"{s},smoke") for s in ("gqn", "seven_scenes", "car")
  )
  assert "n_context" in gqn.data and "n_context" not in car.data and "n_context" not in seven.data
  assert "resnet_stages" in seven.model and "resnet_stages" not in gqn.model
  assert "settings" not in car and set(car.hparams) == {"ours", "baselines"}
  assert regression_config.get_config("quick").setting == "car"  # the default setting
  assert regression_config.get_config("quick,gibson").data.family.num_scenes == 4
  with pytest.raises(ValueError, match="at most one setting"):
    regression_config.get_config("car,gqn")


def test_command_line_errors(tmp_path):
  base = [sys.executable, "-m", "camrep.regression", "--config=configs/regression.py:smoke"]
  base.append(f"--workdir={tmp_path / 'cli'}")
  out = subprocess.run(
    base + ["--config.representation=ours"], cwd=ROOT, capture_output=True, text=True
  )
  assert out.returncode == 2 and "--config.synthesis_workdir=DIR" in out.stderr
  out = subprocess.run(
    base + ["--config.representation=quaternion"], cwd=ROOT, capture_output=True, text=True
  )
  assert out.returncode == 2 and "Traceback" not in out.stderr
  assert "error: --config.representation='quaternion': must be one of [" in out.stderr


def _views(n_scenes, n_views, p=3, size=4):
  rng = np.random.default_rng(0)
  n = n_scenes * n_views
  return views_lib.ViewSet.in_memory(
    images=rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8),
    poses=rng.uniform(size=(n, p)).astype(np.float32),
    scenes=np.repeat(np.arange(n_scenes), n_views),
    views=np.tile(np.arange(n_views)[::-1], n_scenes),  # stored in reverse view order
  )


def test_validation_split_and_batches():
  views = _views(5, 10)
  train_v, val = views_lib.split_validation(settings.CAR, views, 0.2)
  assert len(val) == 10 and len(train_v) == 40
  for s in range(5):  # the two last views by id of every scene
    assert sorted(val.views[val.scenes == s]) == [8, 9]
  train_v, val = views_lib.split_validation(settings.GQN, views, 0.2)
  assert set(val.scenes) == {4} and set(train_v.scenes) == {0, 1, 2, 3}

  config = _batching(_checked(_config("gqn", "quat", **{"evals.batch_size": 7})))
  batch = next(views_lib.train_batches(config, train_v))
  assert batch["context_image"].shape == (2, 3, 4, 4, 3) and batch["image"].shape == (2, 2, 4, 4, 3)
  assert batch["pose"].shape == (2, 2, 3) and batch["scene"].shape == (2,)
  # Held-out scenes: context = views 0..2 of each scene, queries = the other 7, one scene a batch.
  ev = list(views_lib.eval_batches(config, views_lib.EvalSet(views, views)))
  assert len(ev) == 5 and ev[0]["image"].shape == (1, 7, 4, 4, 3) and ev[0]["mask"].all()
  b = ev[1]
  rows = views.scene_rows(1)
  np.testing.assert_array_equal(b["context_pose"][0], views.poses[rows[:3]])
  np.testing.assert_array_equal(b["pose"][0], views.poses[rows[3:]])

  config = _batching(_checked(_config("car", "quat", **{"evals.batch_size": 16})))
  ev = list(views_lib.eval_batches(config, views_lib.EvalSet(_views(5, 5, p=2))))
  assert [b["mask"].sum() for b in ev] == [16, 9] and ev[1]["image"].shape[0] == 16
  b0, b1 = (next(views_lib.train_batches(config, _views(5, 5, p=2))) for _ in range(2))
  np.testing.assert_array_equal(b0["pose"], b1["pose"])  # a pure function of (seed, step)


def _reference_batch(config, views, step):
  """The regression's training batch at `step` as the stage drew it before it read through
  `pipeline.BatchPipeline`: epoch permutations default_rng([seed, 0, epoch]) of the scenes (gqn)
  or views, views of a scene from default_rng([seed, 1, step])."""
  bs, seed = config.data.batch_size, config.seed
  if config.setting == "gqn":
    ids = views.scene_ids()
    epoch, pos = divmod(step, len(ids) // bs)
    chosen = np.random.default_rng([seed, 0, epoch]).permutation(len(ids))[
      pos * bs : (pos + 1) * bs
    ]
    rng = np.random.default_rng([seed, 1, step])
    c, q = config.data.n_context, config.data.n_query
    picked = np.stack([rng.choice(views.scene_rows(ids[i]), c + q, replace=False) for i in chosen])
    return {
      "context_image": views.images(picked[:, :c]),
      "context_pose": views.poses[picked[:, :c]],
      "image": views.images(picked[:, c:]),
      "pose": views.poses[picked[:, c:]],
      "scene": ids[chosen].astype(np.int32),
    }
  epoch, pos = divmod(step, len(views) // bs)
  rows = np.random.default_rng([seed, 0, epoch]).permutation(len(views))[pos * bs : (pos + 1) * bs]
  return {"image": views.images(rows), "pose": views.poses[rows], "scene": views.scenes[rows]}


@pytest.mark.parametrize("setting", ["gqn", "car"])
def test_training_batches_keep_the_stages_draws(setting):
  views = _views(6, 10)
  config = _checked(_config(setting, "quat", **{"data.batch_size": 2, "seed": 3}))
  got = views_lib.train_batches(_batching(config), views)
  steps = 3 * len(views.scene_ids()) // 2 if setting == "gqn" else len(views)  # 3 epochs, 2
  for step in range(steps):
    want, batch = _reference_batch(config, views, step), next(got)
    assert batch.keys() == want.keys()
    for k, v in want.items():
      np.testing.assert_array_equal(batch[k], v, err_msg=f"{k} at step {step}")

"""Pose regression on prepared real data: `camrep.regression` with data.source /
data.dir, end to end at configs/regression.py:smoke.

Data: the real 7-Scenes stairs sample in ../shared/fixtures (skipped when absent, as in CI), and
SRN-layout, GQN-TFRecord and Gibson-layout fixtures written by tests/readers_fixtures.py; each is
prepared with `camrep.data.prepare` into a module-scoped directory. "ours" regresses the pose
system of a 1-step view-synthesis run on the same prepared data (evaluation off, to stay fast).
Also: the refusals (source vs setting, missing dir, absent / empty split, a synthesis run on other
data or with another pose system), the ResNet-34 ImageNet weights (a synthetic torchvision-named
.npz), and `python -m camrep.comparison --dry_run --data`.
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest

from camrep.configs import gibson as gibson_config
from camrep.configs import gqn as gqn_config
from camrep.configs import regression as regression_config
from camrep.configs import seven_scenes as seven_scenes_config
from camrep.configs import shapenet_car
from camrep.data import prepare
from camrep.models import pose_regressor
from camrep.regression import config_schema, learner
from camrep.regression import driver as R
from camrep.regression import views as views_lib
from camrep.runtime import runconfig
from camrep.synthesis import train as synthesis_train
from experiments import table1, table2
from tests import readers_fixtures as fx

# One worker for the module: each source's prepared data and view-synthesis run (module
# fixtures, made on first use) are then made once.
pytestmark = [
  pytest.mark.usefixtures("fast_compile"),
  pytest.mark.slow,
  pytest.mark.xdist_group("regression_real"),
]

ROOT = pathlib.Path(__file__).resolve().parents[1]
_SHARED = pathlib.Path(os.environ.get("CAMREP_SHARED", ROOT.parent / "shared"))
STAIRS = _SHARED / "fixtures" / "7scenes_stairs_sample"
needs_stairs = pytest.mark.skipif(
  not (STAIRS / "stairs").is_dir(), reason=f"real 7-Scenes sample not at {STAIRS}"
)
ConfigError = runconfig.ConfigError

SYNTHESIS_CONFIGS = {
  "seven_scenes": seven_scenes_config,
  "srn_cars": shapenet_car,
  "gqn": gqn_config,
  "gibson": gibson_config,
}
SETTING = {"seven_scenes": "seven_scenes", "srn_cars": "car", "gqn": "gqn", "gibson": "gibson"}
BASELINES = {
  "seven_scenes": ("quat", "logq"),
  "srn_cars": ("euler", "quat"),
  "gqn": ("sincos", "quat"),
  "gibson": ("euler", "logq"),
}


# ------------------------------------------------------------------------------- fixtures


def _write_raw(source: str, root: pathlib.Path) -> tuple[str, dict]:
  """Raw data of `source` under root: (input path, prepare overrides)."""
  rng = np.random.default_rng(0)
  if source == "seven_scenes":
    # The test sequences leave the training cuboid by 0.1 m: margin, as tests/test_readers.py.
    return str(STAIRS), {"image_size": 64, "margin": 0.5}
  if source == "srn_cars":
    layout = {  # split folder: instance names, views each
      "cars_train": (("car0", "car1", "car2"), 8),
      "cars_train_test": (("car0", "car1", "car2"), 3),
      "cars_test": (("novel0", "novel1"), 4),
    }
    for split, (names, n_views) in layout.items():
      for name in names:
        angles = np.stack(
          [rng.uniform(0, 2 * np.pi, n_views), rng.uniform(0.3, 1.4, n_views)], axis=-1
        )
        fx.write_srn_instance(root / split / name, rng, angles, size=64)
    dirs = {"train": "cars_train", "test": "cars_train_test", "test_scenes": "cars_test"}
    return str(root), {"image_size": 64, "split_dirs": dirs}
  if source == "gqn":
    d = root / "rooms_free_camera_no_object_rotations" / "test"
    d.mkdir(parents=True)
    scenes = [fx.gqn_scene(rng, views=10, size=64) for _ in range(12)]
    fx.write_gqn_tfrecord(d / "1-of-1.tfrecord", scenes)
    return str(root), {}
  for area in ("area0", "area1"):
    fx.write_gibson_area(root / "Building" / area, rng, size=64, grid=2)
  return str(root), {"image_size": 64}


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
  """source -> its prepared data directory (made on first use)."""
  base = tmp_path_factory.mktemp("real")
  made = {}

  def get(source: str) -> str:
    if source not in made:
      if source == "seven_scenes" and not (STAIRS / "stairs").is_dir():
        pytest.skip(f"real 7-Scenes sample not at {STAIRS}")
      raw = base / f"raw_{source}"
      raw.mkdir()
      input_path, overrides = _write_raw(source, raw)
      data_dir = base / f"data_{source}"
      prepare.prepare_source(
        source, data_dir, input_path=input_path, overrides=overrides, progress=False
      )
      made[source] = str(data_dir)
    return made[source]

  return get


@pytest.fixture(scope="module")
def synthesis(tmp_path_factory, prepared):
  """source -> a 1-step view-synthesis workdir trained on its prepared data (made on first use)."""
  base = tmp_path_factory.mktemp("synthesis")
  made = {}

  def get(source: str) -> str:
    if source not in made:
      c = SYNTHESIS_CONFIGS[source].get_config("smoke")
      c.data.source, c.data.dir, c.data.preset = source, prepared(source), "default"
      c.total_steps, c.eval_every_steps = 1, 0
      if source in ("seven_scenes", "gibson"):
        c.data.scenes_per_device = 1  # one stairs scene; two areas
      wd = str(base / source)
      synthesis_train.train_and_evaluate(c, wd)
      made[source] = wd
    return made[source]

  return get


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
  return str(tmp_path_factory.mktemp("real_cache"))


def _checked(config):
  """The config, checked by the driver (`check_config`)."""
  config_schema.check(config)
  return config


def _config(source: str, data_dir: str, representation: str, cache: str = "", **kw):
  c = regression_config.get_config(f"{SETTING.get(source, 'car')},smoke")
  c.representation = representation
  c.data.source, c.data.dir, c.data.cache_dir = source, data_dir, cache
  for k, v in kw.items():
    node = c
    *path, last = k.split(".")
    for p in path:
      node = node[p]
    node[last] = v
  return c


def _check_results(wd: str, results: dict, source: str, data_dir: str, test_split: str):
  with open(os.path.join(wd, "results.json")) as f:
    stored = json.load(f)
  assert stored == json.loads(json.dumps(results))
  d = stored["data"]
  assert d["source"] == source and d["dir"] == os.path.abspath(data_dir)
  assert d["test_split"] == test_split and d["dataset_path"].startswith(os.path.abspath(data_dir))
  assert d["num_test_views"] == d["num_examples"][test_split] > 0
  with np.load(os.path.join(wd, f"errors_{test_split}.npz")) as z:
    assert len(z["scene"]) == len(z["view"]) == d["num_test_views"]
  assert set(stored["test"]) >= {"all"} and len(stored["test"]) >= 2  # all + per scene
  return stored


# ------------------------------------------------------------------------------- end to end

CASES = [
  # (source, test split, the test views the fixture holds)
  pytest.param("seven_scenes", "test", 6, marks=needs_stairs, id="seven_scenes"),
  pytest.param("srn_cars", "test", 9, id="srn_cars"),
  pytest.param("gqn", "test_scenes", 2 * 6, id="gqn"),  # 2 held-out scenes x (9 - 3 context)
  pytest.param("gibson", "test", 48, id="gibson"),
]


@pytest.mark.parametrize("source,test_split,n_test", CASES)
def test_baselines_end_to_end(tmp_path, prepared, cache, source, test_split, n_test):
  data_dir = prepared(source)
  for rep in BASELINES[source]:
    wd = str(tmp_path / rep)
    results = R.run(_config(source, data_dir, rep, cache), wd, log=lambda s: None)
    stored = _check_results(wd, results, source, data_dir, test_split)
    assert stored["data"]["num_test_views"] == n_test
    assert stored["representation"] == rep and stored["representation_params"]["source"] == "none"
  if source == "srn_cars":  # novel cars (cars_test) are scored too, as an extra split
    assert stored["data"]["num_examples"]["test_scenes"] == 8
    assert "test_scenes" in stored["extra"]
  if source == "seven_scenes":
    assert stored["data"]["scene_names"] == {"0": "stairs"}
    assert "TestSplit" in stored["data"]["splits"]["test"]
  if source == "gqn":  # validation and test scenes are disjoint from the training scenes
    assert stored["data"]["train_scenes"] == 12 - 2 - 3


@pytest.mark.parametrize("source,test_split,n_test", CASES)
def test_ours_end_to_end(tmp_path, synthesis, prepared, cache, source, test_split, n_test):
  data_dir = prepared(source)
  syn = synthesis(source)
  wd = str(tmp_path / "ours")
  config = _config(source, data_dir, "ours", cache, synthesis_workdir=syn)
  results = R.run(config, wd, log=lambda s: None)
  stored = _check_results(wd, results, source, data_dir, test_split)
  assert stored["data"]["num_test_views"] == n_test
  info = stored["representation_params"]
  assert info["source"] == "synthesis" and info["workdir"] == os.path.abspath(syn)


def test_decoded_splits_are_resized_and_streamed_alike(tmp_path, prepared):
  data_dir = prepared("gibson")
  config = _checked(_config("gibson", data_dir, "euler", **{"data.image_size": 16}))
  data = views_lib.make_data(config, config_schema.check(config).source)
  rows = np.arange(len(data.train))
  assert data.train.image_shape == (16, 16) and data.train.images(rows).shape[1:] == (16, 16, 3)
  config.data.stream = True
  streamed = views_lib.make_data(config, config_schema.check(config).source)
  np.testing.assert_array_equal(streamed.train.images(rows), data.train.images(rows))
  np.testing.assert_array_equal(streamed.train.images(rows[:4].reshape(2, 2))[1, 0],
                                data.train.images(rows[2]))  # fmt: skip


@pytest.mark.parametrize("source", ["gibson", "gqn"])
def test_streamed_run_matches_in_memory(tmp_path, prepared, cache, source):
  """data.stream decodes batches on the fly (grain reader threads); same batches, same errors."""
  data_dir = prepared(source)
  rep = BASELINES[source][0]
  kw = {"data.image_size": 32}
  memory = R.run(
    _config(source, data_dir, rep, cache, **kw), str(tmp_path / "m"), log=lambda s: None
  )
  streamed_config = _config(
    source, data_dir, rep, str(tmp_path / "c"), **kw, **{"data.stream": True}
  )
  streamed = R.run(streamed_config, str(tmp_path / "s"), log=lambda s: None)
  assert streamed["data"]["streamed"] and not memory["data"]["streamed"]
  assert not os.path.exists(tmp_path / "c")  # nothing decoded into the cache
  for split in ("validation", "test"):
    for name, v in memory[split]["all"].items():
      np.testing.assert_allclose(streamed[split]["all"][name]["mean"], v["mean"], rtol=1e-5)


# ------------------------------------------------------------------------------- refusals


def test_refusals(tmp_path, prepared):
  data_dir = prepared("gibson")
  with pytest.raises(ConfigError, match="--config=configs/regression.py:gibson"):
    config_schema.check(_config("gibson", data_dir, "euler", setting="car"))
  with pytest.raises(ConfigError, match="does not exist"):
    _checked(_config("gibson", str(tmp_path / "absent"), "euler"))
  with pytest.raises(ConfigError, match="--config.data.dir=DIR"):
    _checked(_config("gibson", "", "euler"))
  with pytest.raises(ConfigError, match="unknown data source"):
    _checked(_config("nope", data_dir, "euler"))
  with pytest.raises(ConfigError, match="no prepared dataset 'srn_cars'"):
    R.run(_config("srn_cars", data_dir, "euler"), str(tmp_path / "a"), log=lambda s: None)
  with pytest.raises(ConfigError, match="cannot provide evaluation split 'test_scenes'"):
    extra = _config("gibson", data_dir, "euler", **{"evals.extra_splits": "test_scenes"})
    R.run(extra, str(tmp_path / "b"), log=lambda s: None)
  assert not os.path.exists(tmp_path / "a") and not os.path.exists(tmp_path / "b")
  path, meta = views_lib.open_dataset(_checked(_config("gibson", data_dir, "euler")))
  meta = json.loads(json.dumps(meta))
  meta["splits"]["test"]["num_views"] = 0
  with pytest.raises(ConfigError, match="holds no views"):
    views_lib.load_real_split(path, meta, "test", image_size=None)
  with pytest.raises(ConfigError, match="--config.data.stream=True"):
    views_lib.load_real_split(path, meta, "train", image_size=None, max_bytes=1000)


def test_ours_refuses_a_synthesis_run_on_other_data(tmp_path, prepared, synthesis):
  data_dir = prepared("srn_cars")
  syn = synthesis("srn_cars")
  # The procedural car family, not the prepared SRN cars.
  procedural = regression_config.get_config("car,smoke")
  procedural.representation = "ours"
  procedural.synthesis_workdir = syn
  with pytest.raises(ConfigError, match="same data"):
    R.run(procedural, str(tmp_path / "a"), log=lambda s: None)
  # The same files prepared into another directory.
  copy = str(tmp_path / "copy")
  shutil.copytree(data_dir, copy)
  with pytest.raises(ConfigError, match="same data"):
    R.run(_config("srn_cars", copy, "ours", synthesis_workdir=syn), str(tmp_path / "b"))
  # Another pose system: the run's config says rep.kind=mlp.
  other = str(tmp_path / "mlp_run")
  shutil.copytree(syn, other)
  cfg_path = os.path.join(other, "config.json")
  with open(cfg_path) as f:
    cfg = json.load(f)
  cfg["rep"]["kind"] = "mlp"
  with open(cfg_path, "w") as f:
    json.dump(cfg, f)
  with pytest.raises(ConfigError, match="another pose system"):
    R.run(_config("srn_cars", data_dir, "ours", synthesis_workdir=other), str(tmp_path / "c"))


# ------------------------------------------------------------------------------- ResNet weights


def _torchvision_npz(path, stages, *, seed=0, width=1.0):
  """A torchvision-named ResNet state dict with random values (+ the fc and counters that the
  loader ignores), shapes of a ResNet of `stages` at `width`."""
  rng = np.random.default_rng(seed)
  sd = {}
  ch = [int(c * width) for c in pose_regressor.RESNET_CHANNELS]

  def conv(key, o, i, k):
    sd[key] = rng.normal(size=(o, i, k, k)).astype(np.float32)

  def bn(key, c):
    for name in ("weight", "bias", "running_mean"):
      sd[f"{key}.{name}"] = rng.normal(size=(c,)).astype(np.float32)
    sd[f"{key}.running_var"] = rng.uniform(0.5, 2, size=(c,)).astype(np.float32)
    sd[f"{key}.num_batches_tracked"] = np.array(7)

  conv("conv1.weight", ch[0], 3, 7)
  bn("bn1", ch[0])
  in_ch = ch[0]
  for i, n in enumerate(stages):
    for j in range(n):
      t = f"layer{i + 1}.{j}"
      conv(f"{t}.conv1.weight", ch[i], in_ch, 3)
      bn(f"{t}.bn1", ch[i])
      conv(f"{t}.conv2.weight", ch[i], ch[i], 3)
      bn(f"{t}.bn2", ch[i])
      if i > 0 and j == 0:
        conv(f"{t}.downsample.0.weight", ch[i], in_ch, 1)
        bn(f"{t}.downsample.1", ch[i])
      in_ch = ch[i]
  sd["fc.weight"] = rng.normal(size=(1000, in_ch)).astype(np.float32)
  sd["fc.bias"] = np.zeros(1000, np.float32)
  np.savez(path, **sd)
  return sd


def _resnet_state(config):
  reg = R.make_regressor(config_schema.check(config), None, 1)
  batch = {
    "image": np.zeros((2, 32, 32, 3), np.uint8),
    "pose": np.zeros((2, 6), np.float32),
    "scene": np.zeros(2, np.int32),
  }
  import jax

  return config, reg, learner.init(jax.random.key(0), reg, batch)


def test_resnet_weights_are_loaded(tmp_path):
  path = str(tmp_path / "resnet34.npz")
  sd = _torchvision_npz(path, (1,))
  c = regression_config.get_config("seven_scenes,smoke")
  c.representation = "quat"
  c.model.width, c.model.resnet_stages, c.model.resnet_weights = 1.0, (1,), path
  config, reg, state = _resnet_state(c)
  assert reg.image_norm == "imagenet"
  loaded = R.load_resnet_weights(config, state)
  net, stats = loaded.params["net"], loaded.batch_stats
  np.testing.assert_array_equal(net["conv1"]["kernel"], sd["conv1.weight"].transpose(2, 3, 1, 0))
  np.testing.assert_array_equal(
    net["layer1_0"]["conv2"]["kernel"], sd["layer1.0.conv2.weight"].transpose(2, 3, 1, 0)
  )
  np.testing.assert_array_equal(net["layer1_0"]["bn1"]["scale"], sd["layer1.0.bn1.weight"])
  np.testing.assert_array_equal(stats["bn1"]["var"], sd["bn1.running_var"])
  # fc and heads keep their initial values.
  np.testing.assert_array_equal(net["fc"]["kernel"], state.params["net"]["fc"]["kernel"])
  # A training step from the loaded state is finite.
  batch = {
    "image": np.full((2, 32, 32, 3), 128, np.uint8),
    "pose": np.full((2, 6), 0.5, np.float32),
    "scene": np.zeros(2, np.int32),
  }
  _, m = learner.train_step(loaded, batch)
  assert np.isfinite(float(m["loss"]))


def test_resnet_weights_refusals(tmp_path):
  path = str(tmp_path / "resnet34.npz")
  _torchvision_npz(path, (1,))
  c = regression_config.get_config("seven_scenes,smoke")
  c.representation = "quat"
  c.model.resnet_stages, c.model.resnet_weights = (1,), path  # smoke width 1/32: shapes differ
  config, _, state = _resnet_state(c)
  with pytest.raises(ConfigError, match="model.width=1"):
    R.load_resnet_weights(config, state)
  c.model.width, c.model.resnet_stages = 1.0, (2,)  # the file has one block in layer1
  config, _, state = _resnet_state(c)
  with pytest.raises(ConfigError, match="lacks"):
    R.load_resnet_weights(config, state)
  c.model.resnet_weights = str(tmp_path / "absent.npz")
  with pytest.raises(ConfigError, match="does not exist"):
    config_schema.check(c)
  # Only the 7-Scenes config has a ResNet: another setting's has no such field.
  assert "resnet_weights" not in regression_config.get_config("car,smoke").model


# ------------------------------------------------------------------------------- tables


def _fake(setting, rep, seed, data, errs, scenes=("0",)):
  one = {e: {"mean": 1.0, "median": 1.0} for e in errs}
  summary = {"all": one, **{s: one for s in scenes}}
  return dict(setting=setting, representation=rep, lr=1e-3, seed=seed, steps=3, params=5,
              variant="quick", validation=summary, test=summary, data=data)  # fmt: skip


def test_tables_state_the_data_of_each_column():
  srn = {"source": "srn_cars", "dataset": "srn_cars", "dataset_path": "/d/srn_cars/1.0.0",
         "test_split": "test", "num_test_views": 9}  # fmt: skip
  look = {"num_train_scenes": 400, "train_views": 10, "image_size": 32,
          "wall_style": "compass", "texture_contrast": [0.0, 0.08]}  # fmt: skip
  rooms = {"family": "rooms", "preset": "small", "test_split": "test_scenes",
           "family_overrides": look}  # fmt: skip
  area = {"family": "area", "preset": "small", "test_split": "test"}
  gib = {"source": "gibson", "dataset_path": "/d/gibson/1.0.0", "test_split": "test"}
  gg = ("x_error", "y_error", "yaw_error_deg")
  results = [
    _fake("car", "quat", 0, srn, ("rotation_error_deg",)),
    _fake("gqn", "euler", 0, rooms, gg),
    _fake("gibson", "euler", 0, area, gg),
    _fake("gibson", "euler", 1, gib, gg),
  ]
  text = table1.build(results)
  assert "# Table 1: pose regression on mixed data" in text
  assert (
    "- car: prepared `srn_cars` (source srn_cars) at /d/srn_cars/1.0.0, test split `test` "
    "(9 test views)" in text
  )
  assert (
    "- rooms: procedural `rooms` family (preset small, texture_contrast=(0.0, 0.08), "
    "wall_style=compass), test split `test_scenes`" in text
  )
  # Two looks of one family are two datasets: pooling them is flagged.
  tinted = {**rooms, "family_overrides": {**rooms["family_overrides"], "wall_style": "tinted"}}
  text = table1.build(results + [_fake("gqn", "euler", 1, tinted, gg)])
  assert "- rooms: MIXED DATA" in text and "wall_style=tinted" in text
  assert "- area: MIXED DATA" in text
  seven = {"source": "seven_scenes", "dataset_path": "/d/7s/1.0.0", "test_split": "test",
           "num_test_views": 6, "scene_names": {"0": "stairs"}}  # fmt: skip
  errs = ("position_error", "rotation_error_deg")
  text = table2.build([_fake("seven_scenes", "quat", 0, seven, errs)])
  assert text.startswith("# Table 2: 6-DOF regression on 7-Scenes (prepared real images)")
  assert "- all columns: prepared `seven_scenes` (source seven_scenes) at /d/7s/1.0.0" in text
  assert "- ResNet initialisation: none (from scratch)" in text


# ------------------------------------------------------------------------------- launcher


def test_run_comparison_dry_run_with_data(tmp_path):
  data = tmp_path / "seven"
  data.mkdir()
  out = subprocess.run(
    [
      sys.executable,
      "-m",
      "camrep.comparison",
      "--size",
      "quick",
      "--settings",
      "seven_scenes",
      "--data",
      f"seven_scenes={data}",
      "--out",
      str(tmp_path / "cmp"),
      "--dry_run",
      "--skip_figures",
    ],
    cwd=ROOT,
    capture_output=True,
    text=True,
    check=True,
  )
  text = out.stdout
  assert f"data of seven_scenes: prepared seven_scenes data in {data}" in text
  lines = [ln for ln in text.splitlines() if "camrep." in ln]
  assert lines and all(
    f"--config.data.source=seven_scenes --config.data.dir={data}" in ln for ln in lines
  )
  assert "experiments/table2.py" in text
  bad = subprocess.run(
    [sys.executable, "-m", "camrep.comparison", "--out", str(tmp_path), "--data", "x=y"],
    cwd=ROOT,
    capture_output=True,
    text=True,
  )
  assert bad.returncode == 2 and "--data expects SETTING=DIR" in bad.stderr

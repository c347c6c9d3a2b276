"""Tests of the regression driver (camrep.regression), the Table 1 / 2 scripts and the launcher.

The driver runs end to end at configs/regression.py:smoke (tiny car data, a few steps); "ours"
regresses the pose system of a 1-step car :smoke view-synthesis run made here. The tables are
built from fabricated results.json files.
"""

from __future__ import annotations

import copy
import importlib
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
from camrep.regression import tables as C
from camrep.regression import views as views_lib
from camrep.runtime import runconfig
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import components, config_schema, train
from tests.utils import load_experiment, snapshot

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
  assert record["data"] == views_lib.data_record(_checked(config))
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
  cached = views_lib.make_data(_checked(config)).train
  config.data.cache_dir = ""
  rendered = views_lib.make_data(_checked(config)).train
  rows = np.arange(len(rendered))
  np.testing.assert_array_equal(cached.images(rows), rendered.images(rows))
  np.testing.assert_array_equal(cached.poses, rendered.poses)
  config.data.cache_dir = cache
  # (issue 19) A rerun in this workdir with another config: refused unless allowed.
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
def car_synthesis(tmp_path_factory):
  config = shapenet_car.get_config("smoke")
  config.total_steps = 1
  config.evals.num_scenes = 1
  wd = str(tmp_path_factory.mktemp("synthesis") / "car")
  train.train_and_evaluate(config, wd)
  return wd


def test_ours_from_a_synthesis_workdir(tmp_path, cache, car_synthesis):
  config = _config("car", "ours", synthesis_workdir=car_synthesis, **{"data.cache_dir": cache})
  results = R.run(config, str(tmp_path / "ours"), log=lambda s: None)
  info = results["representation_params"]
  assert info["source"] == "synthesis" and info["step"] == 1
  assert info["workdir"] == os.path.abspath(car_synthesis)
  assert results["lr"] == 1e-3  # the paper's car lr (configs/regression.py hparams.car)
  assert np.isfinite(results["test"]["all"]["rotation_error_deg"]["mean"])
  spec, rep, info = pose_system.representation_params(_checked(config))
  assert spec == components.pose_spec(shapenet_car.get_config("smoke")) and info["step"] == 1
  # The system it read, by content: the digest of the parameters it regressed.
  assert results["representation_params"]["digest"] == pose_system.params_digest(rep)
  # "mlp" with a learned-grid run: its pose spec, a frozen random MLP embedding.
  mlp = _config("car", "mlp", synthesis_workdir=car_synthesis, **{"data.cache_dir": cache})
  spec, params, info = pose_system.representation_params(_checked(mlp))
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

  config = _checked(_config("gqn", "quat", **{"evals.batch_size": 7}))
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

  config = _checked(_config("car", "quat", **{"evals.batch_size": 16}))
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
  got = views_lib.train_batches(config, views)
  steps = 3 * len(views.scene_ids()) // 2 if setting == "gqn" else len(views)  # 3 epochs, 2
  for step in range(steps):
    want, batch = _reference_batch(config, views, step), next(got)
    assert batch.keys() == want.keys()
    for k, v in want.items():
      np.testing.assert_array_equal(batch[k], v, err_msg=f"{k} at step {step}")


# ------------------------------------------------------------------------------- the tables


def _summary(setting, scale, scenes=("0",)):
  errs = {
    "car": ("rotation_error_deg",),
    "gqn": ("x_error", "y_error", "yaw_error_deg"),
    "gibson": ("x_error", "y_error", "yaw_error_deg"),
    "seven_scenes": ("position_error", "rotation_error_deg"),
  }[setting]
  one = lambda s: {e: {"mean": s * (1 + i), "median": s * (0.5 + i)} for i, e in enumerate(errs)}
  out = {"all": one(scale)}
  for k, sc in enumerate(scenes):
    out[sc] = one(scale * (k + 1))
  return out


def _write(root, setting, rep, lr, seed, val, test, **extra):
  wd = os.path.join(root, setting, rep, f"lr{lr:g}_seed{seed}")
  os.makedirs(wd)
  r = dict(setting=setting, representation=rep, lr=lr, seed=seed, steps=10, params=5)
  r.update(variant="quick", validation=val, test=test, **extra)
  with open(os.path.join(wd, "results.json"), "w") as f:
    json.dump(r, f)


def test_table1_selects_lr_on_validation(tmp_path):
  root = str(tmp_path / "runs")
  # car ours: lr 1e-3 has the lower validation error on both seeds, the worse test error.
  for seed, test in ((0, 2.0), (1, 4.0)):
    _write(root, "car", "ours", 1e-3, seed, _summary("car", 1.0), _summary("car", test))
    _write(root, "car", "ours", 3e-3, seed, _summary("car", 2.0), _summary("car", 0.5))
  # car quat: lr 3e-3 is better on seed 0 (the only seed both lrs have), worse on seed 1.
  _write(root, "car", "quat", 1e-3, 0, _summary("car", 5.0), _summary("car", 9.0))
  _write(root, "car", "quat", 3e-3, 0, _summary("car", 4.0), _summary("car", 7.0))
  _write(root, "car", "quat", 3e-3, 1, _summary("car", 40.0), _summary("car", 8.0))
  _write(root, "gqn", "euler", 1e-4, 0, _summary("gqn", 0.1), _summary("gqn", 0.2))
  sel = C.select(C.load_results([os.path.join(root, "*", "*", "*")]))
  assert sel["car", "ours"].lr == 1e-3 and sel["car", "ours"].seeds == (0, 1)
  assert sel["car", "quat"].lr == 3e-3 and sel["car", "quat"].scores[1e-3][1] == (0,)
  assert C.seed_stats(sel["car", "ours"].runs, "rotation_error_deg") == (3.0, np.sqrt(2), 2)

  out = str(tmp_path / "results" / "table1.md")
  assert (
    load_experiment("table1").main(["--runs", os.path.join(root, "*", "*", "*"), "--out", out]) == 0
  )
  text = open(out).read()
  assert "| ours | 3.00 ± 1.41 | – | – | – | – | – | – |" in text
  assert "| (x, y, q) | 7.50 ± 0.71 |" in text
  # gqn euler (one seed): x = 0.2, y = 0.4, yaw = 0.6; the paper's Table 1 is labelled as such.
  assert "| (x, y, α) Euler | – | 0.200 | 0.400 | 0.600 | – | – | – |" in text
  assert "Paper's Table 1" in text and "| ours | 2.85 | 0.053 | 0.053 | 4.07 |" in text
  assert "| car | ours | 1e-3: 0.351 (seeds 0,1), 3e-3: 0.702 (seeds 0,1) | 1e-3 |" in text


def test_table2_medians_per_scene(tmp_path):
  root = str(tmp_path / "runs")
  names = {"0": "chess", "1": "stairs"}
  for rep, scale in (("ours", 0.1), ("quat", 0.2)):
    for seed in (0, 1):
      test = _summary("seven_scenes", scale * (1 + 2 * seed), scenes=("0", "1"))
      val = _summary("seven_scenes", scale)
      _write(root, "seven_scenes", rep, 1e-3, seed, val, test, data={"scene_names": names})
  out = str(tmp_path / "table2.md")
  assert (
    load_experiment("table2").main(["--runs", os.path.join(root, "*", "*", "*"), "--out", out]) == 0
  )
  text = open(out).read()
  # ours, chess: position medians 0.05 / 0.15, rotation medians 0.15 / 0.45 over the seeds.
  assert "| chess | 0.10 ± 0.07 m, 0.3 ± 0.2° | 0.20 ± 0.14 m, 0.6 ± 0.4° | 0.12 m, 4.83° |" in text
  assert "| stairs | 0.20 ± 0.14 m, 0.6 ± 0.4° |" in text
  assert "| average | 0.15 ± 0.11 m, 0.5 ± 0.3° |" in text and "0.21 m, 7.92° (7 scenes)" in text
  assert "real 7-Scenes" in text


def test_run_comparison_dry_run(tmp_path, capsys):
  rc = load_experiment("run_comparison")
  assert rc.main(["--size", "quick", "--out", str(tmp_path), "--dry_run"]) == 0
  text = capsys.readouterr().out
  first = text.splitlines()[0]
  assert "regression runs" in first and "estimated" in first and "2 CPU cores" in first
  assert (
    "--config=configs/gqn.py:quick" in text and "--config=configs/seven_scenes.py:quick" in text
  )
  assert "--config.representation=axis_angle" in text and "experiments/table2.py" in text
  assert f"--config.synthesis_workdir={tmp_path}/synthesis/car\n" in text
  assert "--config.optax.lr=<LR>" in text  # phase 2: other seeds at the chosen lr
  # Phase 2 reads the lr that seed 0's validation chose.
  plan = rc.PLANS["quick"]
  reg = os.path.join(str(tmp_path), "regression")
  _write(reg, "car", "quat", 1e-3, 0, _summary("car", 3.0), _summary("car", 1.0))
  _write(reg, "car", "quat", 3e-3, 0, _summary("car", 2.0), _summary("car", 9.0))
  assert rc.chosen_lr(str(tmp_path), "car", "quat", plan) == 3e-3
  assert rc.main(["--size", "paper", "--out", str(tmp_path), "--dry_run", "--settings", "car"]) == 0
  assert "--config=configs/regression.py:car " in capsys.readouterr().out
  args = ["--size", "medium", "--out", str(tmp_path), "--dry_run", "--jobs", "4"]
  assert rc.main(args) == 0
  text = capsys.readouterr().out
  assert "4 jobs at a time" in text.splitlines()[0] and "derived, not measured" in text
  assert "--config=configs/gqn.py:medium" in text
  assert "--config=configs/regression.py:car,medium" in text
  # --noise_runs: the GQN noise figure's other pose inputs and GQN's own generator (not medium).
  noise = ["--out", str(tmp_path), "--dry_run", "--settings", "gqn", "--noise_runs"]
  assert rc.main(["--size", "quick", *noise]) == 0
  text = capsys.readouterr().out
  for name in ("gqn_lowdim", "gqn_mlp", "gqn_convdraw"):
    assert f"--workdir={tmp_path}/synthesis/{name}" in text
  assert "--config=configs/gqn_convdraw.py:quick" in text and "noise_figure.py" in text
  assert rc.main(["--size", "medium", *noise, "--noise_kinds", "lowdim,convdraw"]) == 0
  text = capsys.readouterr().out
  assert "synthesis/gqn_lowdim" in text and "gqn_mlp" not in text and "convdraw" not in text


def test_run_comparison_runs_jobs_at_once(tmp_path, monkeypatch):
  """--jobs N: N subprocesses at a time, each told its share of GPU memory; failures named."""
  rc = load_experiment("run_comparison")
  monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION", raising=False)
  assert rc.job_env(1) is None and rc.job_env(3)["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.300"
  marks = tmp_path / "marks"
  marks.mkdir()
  # Each job waits (up to 20 s) until the other has started: only passes if both run at once.
  code = (
    "import os, sys, time; m, me, other, frac = sys.argv[1:]; open(os.path.join(m, me), 'w');"
    "t = time.time()\nwhile not os.path.exists(os.path.join(m, other)) and time.time() - t < 20:"
    " time.sleep(0.05)\nassert os.path.exists(os.path.join(m, other));"
    "assert os.environ['XLA_PYTHON_CLIENT_MEM_FRACTION'] == frac"
  )
  jobs = [
    rc.Job(me, [sys.executable, "-c", code, str(marks), me, other, "0.450"], "", 1)
    for me, other in (("a", "b"), ("b", "a"))
  ]
  fail = rc.Job("fails", [sys.executable, "-c", "raise SystemExit(3)"], "", 1)
  assert rc.run_jobs(jobs + [fail], str(tmp_path / "logs"), at_once=2, label="") == ["fails"]
  assert sorted(os.listdir(marks)) == ["a", "b"]


def test_run_comparison_converge_plan(tmp_path, capsys):
  """--size converge (issue 29): >= 3 seeds per cell, the stopping rule on every regression, one
  synthesis run per seed paired with ours' regression seed, capture columns, an estimate; the
  lr grid extends while a choice is at its edge; --max_hours starts nothing after the deadline."""
  rc = load_experiment("run_comparison")
  cap = tmp_path / "chair"
  cap.mkdir()
  out = str(tmp_path / "cmp")
  args = ["--size", "converge", "--out", out, "--dry_run", "--data", f"car_chair=nerf:{cap}"]
  assert rc.main(args) == 0
  text = capsys.readouterr().out
  first = text.splitlines()[0]
  assert first.startswith("converge comparison") and "estimated" in first
  assert "phase-1 runs" in first and "edge" in first
  launch = rc.make_launch(rc._parse_args(args))
  plan = launch.plan
  assert len(plan.seeds) >= 3 and all(len(g) >= 3 for g in plan.lrs.values())
  cells = {}
  for j in launch.first:
    cells.setdefault(rc._group(j), set()).add(j.argv[j.argv.index("-m") + 5])
  for col, rep, seed in launch.later:
    cells[col, rep].add(f"--config.seed={seed}")
  assert ("car_chair", "ours") in cells and ("seven_scenes", "ours") in cells
  assert all(len(seeds) >= 3 for seeds in cells.values())
  for j in launch.first:
    assert "--config.stop.min_improvement=0.02" in j.argv and "--config.eval_every_steps=" in (
      " ".join(j.argv)
    )
  ours = [j for j in launch.first if "--config.representation=ours" in j.argv]
  for j in ours:
    seed = next(a for a in j.argv if a.startswith("--config.seed=")).split("=")[1]
    assert any(a.endswith(f"_seed{seed}") for a in j.argv if a.startswith("--config.synthesis_"))
  syn = {j.name for j in launch.synth}
  assert {f"synthesis_car_chair_seed{k}" for k in range(3)} <= syn
  chair = next(j for j in launch.synth if j.name == "synthesis_car_chair_seed1")
  assert f"--config.data.dir={cap}" in chair.argv and "--config.seed=1" in chair.argv
  assert any("table1_car_chair.md" in " ".join(j.argv) for j in launch.tables)
  # The capture's MLP embedding has its own synthesis runs, which its mlp regressions read.
  mlp = next(j for j in launch.synth if j.name == "synthesis_car_chair_mlp_seed2")
  assert "--config.rep.kind=mlp" in mlp.argv and f"--config.data.dir={cap}" in mlp.argv
  assert "--config.data.scenes_per_device=1" in mlp.argv
  assert mlp.estimate_s == plan.synthesis_s["capture"] < plan.synthesis_s["car"]
  mlp_reg = [j for j in launch.first if j.name.startswith("regression_car_chair_mlp_")]
  wd = os.path.join(out, "synthesis", "car_chair_mlp_seed0")
  assert mlp_reg and all(f"--config.synthesis_workdir={wd}" in j.argv for j in mlp_reg)
  assert rc.synthesis_column("car_chair_mlp_seed0", launch.data) == "car_chair"
  assert rc.synthesis_column("car_mlp_seed0", launch.data) == "car"
  noise = next(j for j in launch.figures if j.name == "noise_figure_car_chair")
  assert os.path.join(out, "synthesis", "car_chair_mlp_seed1") in noise.argv
  assert noise.argv[noise.argv.index("--column") + 1] == "chair, car setting"  # not "(car)"
  # The grid extends: car quat chose the highest lr of (3e-4, 1e-3, 3e-3) -> 1e-2 next.
  reg = os.path.join(out, "regression")

  def write(lr, val):  # named as the launcher names its workdirs (lr3e-3_seed0)
    _write(reg, "car", "quat", lr, 0, _summary("car", val), _summary("car", 1.0))
    wd = os.path.join(reg, "car", "quat", f"lr{lr:g}_seed0")
    os.rename(wd, os.path.join(reg, "car", "quat", f"{rc.lr_tag(lr)}_seed0"))

  for lr, val in ((3e-4, 3.0), (1e-3, 2.0), (3e-3, 1.0)):
    write(lr, val)
  assert rc.extension_lr(out, "car", "quat", plan) == 1e-2
  write(1e-2, 2.0)
  assert rc.extension_lr(out, "car", "quat", plan) is None  # 3e-3 now inside the grid
  assert rc.chosen_lr(out, "car", "quat", plan) == 3e-3
  curves = [j for j in rc.curve_jobs(launch) if j.name == "curve_car"]
  assert len(curves) == 1 and "--bands" in curves[0].argv
  title = curves[0].argv[curves[0].argv.index("--title") + 1]  # says what the score is
  assert title.startswith("car: validation score = rotation_error_deg mean / 2.85")
  assert os.path.join(reg, "car", "quat", "lr3e-3_seed0") in curves[0].argv
  assert os.path.join(reg, "car", "quat", "lr1e-3_seed0") not in curves[0].argv
  assert [rc.half_decade(x, up=u) for x, u in ((1e-3, True), (3e-4, False), (1e-4, False))] == [
    3e-3,
    1e-4,
    3e-5,
  ]
  # --max_hours: past the deadline nothing starts, and that is not a failure.
  job = rc.Job("never", [sys.executable, "-c", "raise SystemExit(3)"], "", 1)
  assert rc.run_jobs([job], str(tmp_path / "logs"), at_once=1, label="", deadline=0.0) == []
  assert "not started (--max_hours)" in capsys.readouterr().out
  assert not os.path.exists(tmp_path / "logs" / "never.log")


def _synthesis_quick(rc, setting):
  module = rc.SYNTHESIS_CONFIGS[setting].removeprefix("configs/").removesuffix(".py")
  return importlib.import_module(f"camrep.configs.{module}").get_config("quick")


def test_run_comparison_converge_synthesis_to_its_plateau(tmp_path, capsys):
  """--size converge (issue 29 part 3): every view-synthesis run but GQN's ConvDRAW gets a cap
  of 4x its quick steps and the plateau rule, flags its config accepts (ConvDRAW: 4x its quick
  length with its schedules stretched, no rule); the held-out PSNR
  curves of each column's synthesis runs are drawn with bands over seeds."""
  rc = load_experiment("run_comparison")
  out = str(tmp_path / "cmp")
  args = ["--size", "converge", "--out", out, "--dry_run", "--noise_runs"]
  assert rc.main(args) == 0
  assert "curve_synthesis_<column>" in capsys.readouterr().out
  launch = rc.make_launch(rc._parse_args(args))
  flags = {j.name: {a.split("=")[0]: a.split("=")[1] for a in j.argv[4:]} for j in launch.synth}
  assert flags["synthesis_car_seed2"]["--config.total_steps"] == "4800"
  assert flags["synthesis_car_mlp_seed0"]["--config.stop.min_steps"] == "1200"
  g = flags["synthesis_gqn_lowdim_seed1"]
  assert g["--config.total_steps"] == "8000" and g["--config.eval_every_steps"] == "400"
  assert g["--config.stop.min_improvement"] == "0.02" and g["--config.seed"] == "1"
  # GQN's generator: 4x its quick length, its schedules stretched to it, no plateau rule.
  draw = flags["synthesis_gqn_convdraw_seed0"]
  assert draw["--config.total_steps"] == "8000" and draw["--config.optax.anneal_steps"] == "6400"
  assert "--config.stop.window" not in draw
  quick = importlib.import_module("camrep.configs.gqn_convdraw").get_config("quick")
  assert quick.optax.anneal_steps == 2000 * 8 // 10  # the fractions the stretch keeps
  # The flags fit the configs they go with: caps 4x their quick steps (the car 8x), the rule
  # and the permission to raise a cap accepted.
  for name in rc.SETTINGS:
    c = _synthesis_quick(rc, name)
    assert rc.CONVERGE_SYNTHESIS_CAPS[name] == (8 if name == "car" else 4) * c.total_steps
    plateau = dict(
      a.removeprefix("--config.").split("=") for a in rc.synthesis_flags(launch.plan, name)
    )
    for k, v in plateau.items():
      section, _, field = k.rpartition(".")
      node = c[section] if section else c
      kind = type(node[field])
      node[field] = v if kind is str else float(v) if kind is float else int(v)
    config_schema.validate(c, overridden=set(plateau))
    assert components.stopping_rule(c).active
  # Curves: one job per column over its synthesis workdirs that exist.
  for name in ("car_seed0", "car_seed1", "car_mlp_seed0", "gqn_seed0"):
    os.makedirs(os.path.join(out, "synthesis", name))
  jobs = {j.name: j.argv for j in rc.curve_jobs(launch)}
  car = jobs["curve_synthesis_car"]
  assert "eval/psnr" in car and "--bands" in car
  assert sum(a.startswith(os.path.join(out, "synthesis", "car")) for a in car) == 3
  assert "curve_synthesis_gqn" in jobs and "curve_synthesis_gibson" not in jobs


def test_run_comparison_crossed_seeds(tmp_path, capsys):
  """--crossed COLUMN (issue 29 part 3): every regression seed of ours on every other synthesis
  seed, outside regression/ (never tabled), then experiments/seed_spread.py; off by default."""
  rc = load_experiment("run_comparison")
  out = str(tmp_path / "cmp")
  args = ["--size", "converge", "--out", out, "--dry_run", "--settings", "car,gqn"]
  assert rc.main([*args, "--crossed", "car"]) == 0
  text = capsys.readouterr().out
  assert "crossed seeds of car's ours: 6 more regression runs" in text
  launch = rc.make_launch(rc._parse_args([*args, "--crossed", "car"]))
  jobs = rc.crossed_jobs(launch, 1e-3)
  assert len(jobs) == 6 and len({j.name for j in jobs}) == 6
  job = next(j for j in jobs if j.name == "crossed_car_lr1e-3_seed0_syn2")
  assert f"--workdir={os.path.join(out, 'crossed', 'car', 'lr1e-3_seed0_syn2')}" in job.argv
  assert f"--config.synthesis_workdir={os.path.join(out, 'synthesis', 'car_seed2')}" in job.argv
  assert "--config.seed=0" in job.argv and "--config.representation=ours" in job.argv
  assert "--config.optax.lr=0.001" in job.argv and "--config.stop.min_improvement=0.02" in job.argv
  spread = rc.seed_spread_job(launch, 1e-3)
  assert "experiments/seed_spread.py" in spread.argv and "--decode" in spread.argv
  assert os.path.join(out, "regression", "car", "ours", "lr1e-3_seed*") in spread.argv
  # Off by default; refused where the sizes do not pair seeds or the column is not launched.
  assert rc.crossed_jobs(rc.make_launch(rc._parse_args(args)), 1e-3) == []
  for bad in (["--size", "quick", "--crossed", "car"], [*args, "--crossed", "gibson"]):
    with pytest.raises(SystemExit) as e:
      rc._parse_args([*bad, "--out", out] if bad[1] == "quick" else bad)
    assert e.value.code == 2

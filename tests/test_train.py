"""End-to-end tests of view-synthesis training (camrep.synthesis, camrep.main), :smoke configs."""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest

from camrep import pose as P
from camrep.configs import gibson, gqn, gqn_convdraw, seven_scenes, shapenet_car
from camrep.configs import regression as regression_config
from camrep.models.composite import GQNSynthesis, TableSynthesis
from camrep.runtime import runconfig, writers
from camrep.synthesis import components, train
from camrep.synthesis import step as step_lib

ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIGS = {"gqn": gqn, "shapenet_car": shapenet_car, "gibson": gibson, "seven_scenes": seven_scenes}


pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]


@pytest.mark.parametrize("name", sorted(CONFIGS))
@pytest.mark.parametrize("variant", [None, "quick", "medium", "smoke"])
def test_configs_build(name, variant):
  config = CONFIGS[name].get_config(variant)
  components.check_config(config)
  spec = components.pose_spec(config)
  assert spec.pose_dim == {"gqn": 3, "shapenet_car": 2, "gibson": 3, "seven_scenes": 6}[name]
  for key in ("total_steps", "ckpt_every_steps", "eval_every_steps", "log_every_steps"):
    assert config[key] > 0
  model = components.make_model(components.resolve(config), 7)
  expected = GQNSynthesis if name == "gqn" else TableSynthesis
  assert isinstance(model.module, expected) and config.task == ("gqn" if name == "gqn" else "table")
  if variant is None:  # paper settings (digest 3)
    assert config.optax.lr_model == 1e-4
    assert (
      config.optax.pose_steps == {"gqn": 0, "shapenet_car": 3, "gibson": 2, "seven_scenes": 2}[name]
    )


def test_config_variant_errors():
  with pytest.raises(ValueError, match="variant"):
    gqn.get_config("huge")
  with pytest.raises(ValueError, match="variant 'medium'"):  # no medium size for the generator
    gqn_convdraw.get_config("medium")


def test_medium_variant_sits_between_quick_and_paper():
  for name, module in CONFIGS.items():
    quick, medium, paper = (module.get_config(v) for v in ("quick", "medium", None))
    assert quick.model.width < medium.model.width < paper.model.width, name
    assert quick.total_steps < medium.total_steps < paper.total_steps, name
    assert medium.data.in_memory and medium.model.image_size == quick.model.image_size, name
  for setting in regression_config.RECIPES:
    q, m = (regression_config.get_config(f"{setting},{v}") for v in ("quick", "medium"))
    assert q.model.width < m.model.width and q.total_steps < m.total_steps
    assert q.data.batch_size < m.data.batch_size


def test_check_config_rejects_layouts_the_step_cannot_run(tmp_path):
  c = gqn.get_config("smoke")
  c.data.n_context = c.data.views_per_scene  # no query views left
  with pytest.raises(runconfig.ConfigError, match="n_context"):
    components.check_config(c)
  c = gqn.get_config("smoke")
  c.loss.data_pairs = True  # GQN batches hold random views, not (anchor, partner) pairs
  with pytest.raises(runconfig.ConfigError, match="data.mode='pairs'"):
    train.train_and_evaluate(c, str(tmp_path / "run"))
  assert not (tmp_path / "run").exists()  # refused before the workdir was touched
  c.rep.kind = "lowdim"  # no generators, no rotation loss: data_pairs is moot
  components.check_config(c)
  c = shapenet_car.get_config("smoke")
  c.total_steps = 0
  with pytest.raises(runconfig.ConfigError, match="total_steps"):
    components.check_config(c)
  c = shapenet_car.get_config("smoke")
  c.data.source = "nowhere"
  with pytest.raises(runconfig.ConfigError, match="unknown data.source"):
    components.check_config(c)


def test_gqn_smoke_trains_evaluates_and_resumes(tmp_path, gqn_smoke_run):
  """The session's shared 4-step run (conftest.gqn_smoke_run), then resumed here to step 6."""
  config = gqn.get_config("smoke")
  workdir = str(tmp_path / "w")
  shutil.copytree(gqn_smoke_run, workdir)
  last = json.load(open(os.path.join(workdir, "final_metrics.json")))
  for f in ("config.json", "metrics.jsonl", "final_metrics.json"):
    assert os.path.exists(os.path.join(workdir, f)), f
  assert sorted(os.listdir(os.path.join(workdir, "checkpoints")))[-1] == "4"
  rows = writers.read_metrics(workdir)
  train_rows = [r for r in rows if "train/loss" in r]
  assert [r["step"] for r in train_rows] == [2, 4]
  for key in (
    "train/rec",
    "train/rot_xy",
    "train/rot_yaw",
    "train/dir_xy",
    "train/grad_norm_model",
    "train/steps_per_sec",
  ):
    assert np.isfinite(train_rows[-1][key]), key
  evals = [r for r in rows if "eval/psnr" in r]
  assert evals and {"eval/ssim", "eval/psnr_baseline"} <= set(evals[-1])
  assert last["eval/psnr"] == evals[-1]["eval/psnr"]
  assert any(f.endswith(".png") for f in os.listdir(os.path.join(workdir, "images")))
  assert json.load(open(os.path.join(workdir, "config.json")))["task"] == "gqn"
  # Resume: the same command with more steps continues from the checkpoint at step 4.
  config.total_steps, config.allow_changes = 6, "total_steps"
  train.train_and_evaluate(config, workdir)
  steps = [r["step"] for r in writers.read_metrics(workdir) if "train/loss" in r]
  assert steps == [2, 4, 6]


def test_prepared_data_with_worker_processes_trains_on_the_same_batches(tmp_path, gqn_smoke_run):
  """`data.dir` read by 2 worker processes (grain mp_prefetch) + device prefetch: the batches,
  hence the step-2 metrics, are those of the shared in-memory run (same seed, same views)."""
  from camrep.data import prepare

  data_dir = tmp_path / "tfds"
  assert prepare.main(["--source", "rooms", "--data_dir", str(data_dir), "--preset", "small"]) == 0
  config = gqn.get_config("smoke")
  config.data.dir = str(data_dir)
  config.data.num_workers, config.data.num_threads = 2, 1
  config.total_steps = 2
  train.train_and_evaluate(config, str(tmp_path / "w"))
  got = [r for r in writers.read_metrics(str(tmp_path / "w")) if "train/loss" in r]
  want = [r for r in writers.read_metrics(gqn_smoke_run) if "train/loss" in r and r["step"] == 2]
  assert [r["step"] for r in got] == [2]
  for key in ("train/loss", "train/rec", "train/rot_xy", "train/rot_yaw"):
    np.testing.assert_allclose(got[0][key], want[0][key], rtol=1e-5, err_msg=key)


@pytest.mark.parametrize("name", ["shapenet_car", "seven_scenes"])
def test_table_settings_smoke(name, tmp_path, request):
  """Pose steps then a decoder step, per-scene tables, rotation losses with data pairs.

  Trained by the CLI in a fresh process (the car: the session's shared run,
  `conftest.car_smoke_run`, 2 steps too): in two whole-suite runs on 2 cores the xdist worker
  that compiled this step in-process, after ~900 other tests, died inside XLA (an abort while
  serialising the executable for the compilation cache, then a segfault in the compile itself;
  BUILD_NOTES "A crash in the CI rehearsal"), while the test passes alone."""
  config = CONFIGS[name].get_config("smoke")
  if name == "shapenet_car":
    workdir = pathlib.Path(request.getfixturevalue("car_smoke_run"))
  else:
    workdir = tmp_path
    r = subprocess.run(
      [
        sys.executable,
        "-m",
        "camrep.main",
        f"--config={name}:smoke",
        f"--workdir={workdir}",
        "--config.total_steps=2",
        "--config.eval_every_steps=2",
      ],
      capture_output=True,
      text=True,
      cwd=ROOT,
      env={**os.environ, "JAX_DISABLE_MOST_OPTIMIZATIONS": "1"},  # as this module's fast_compile
      timeout=600,
    )
    assert r.returncode == 0, r.stderr[-3000:]
  with open(workdir / "final_metrics.json", encoding="utf-8") as f:
    last = json.load(f)
  assert last["complete"] is True and last["step"] == 2
  assert last["train/finite"] == 1.0
  spec = components.pose_spec(config)
  for d in spec.dofs:
    assert np.isfinite(last[f"train/rot_{d.name}"])
  assert np.isfinite(last["eval/psnr"]) and np.isfinite(last["eval/psnr_baseline"])


def test_two_host_devices_match_one(tmp_path):
  """The pmapped step on 2 forced host devices trains exactly as 1 device with the same global
  batch: same losses and gradient norms (a pmean/psum mix-up would double them), same parameters
  up to round-off (entries with zero true gradient, e.g. biases before instance norm, get
  round-off gradients that Adam normalises to +-lr)."""
  out = {}
  for n in (1, 2):
    path = tmp_path / f"d{n}.npz"
    r = subprocess.run(
      [sys.executable, "-m", "tests.two_devices_script", str(n), "2", str(path)],
      capture_output=True,
      text=True,
      cwd=ROOT,
      timeout=600,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    out[n] = dict(np.load(path))
  a, b = out[1], out[2]
  assert set(a) == set(b)
  for k in a:
    if k.startswith("metric/") and "steps_per_sec" not in k:
      np.testing.assert_allclose(a[k], b[k], rtol=2e-4, err_msg=k)
  params = [k for k in a if k.startswith("param/")]
  close = np.concatenate([np.isclose(a[k], b[k], rtol=1e-4, atol=1e-6).ravel() for k in params])
  assert close.mean() > 0.99
  config = gqn.get_config("smoke")
  bound = 2 * 2 * max(config.optax.lr_model, config.optax.lr_rep)
  for k in params:
    assert np.abs(a[k] - b[k]).max() <= bound, k


def test_non_finite_stops_and_keeps_last_good_checkpoint(tmp_path, gqn_smoke_run):
  config = gqn.get_config("smoke")
  workdir = str(tmp_path / "w")
  shutil.copytree(gqn_smoke_run, workdir)  # good checkpoint at step 4
  config.total_steps = 8
  # A diverging run: step 5's update overflows the parameters (their norm is not finite).
  config.optax.lr_model = 1e38
  config.allow_changes = "total_steps,optax.lr_model"
  # The message names the first bad step and whether the checkpoint it began from was verified.
  with pytest.raises(FloatingPointError, match="step 5 .*restored from step 4, checksum verified"):
    train.train_and_evaluate(config, workdir)
  assert sorted(os.listdir(os.path.join(workdir, "checkpoints")))[-1] == "4"


def _main(*args, timeout=300):
  return subprocess.run(
    [sys.executable, "-m", "camrep.main", "--config=configs/gqn.py:smoke", *args],
    capture_output=True,
    text=True,
    cwd=ROOT,
    timeout=timeout,
  )


def test_cli_rejects_wrong_override_type(tmp_path):
  r = _main(f"--workdir={tmp_path}", "--config.total_steps=abc")
  assert r.returncode == 2  # a user's mistake (camrep.runtime.cli), not absl's exit 1
  assert "error: --config.total_steps=abc: invalid literal for int()" in r.stderr
  assert "Traceback" not in r.stderr
  assert not os.listdir(tmp_path)  # refused before anything was written


def test_cli_unwritable_workdir_is_a_clear_error(tmp_path):
  blocker = tmp_path / "a_file"
  blocker.write_text("not a directory")
  r = _main(f"--workdir={blocker}/run")
  assert r.returncode == 2, r.stderr[-2000:]
  assert f"error: workdir {blocker}/run cannot be written: Not a directory" in r.stderr
  assert "Traceback" not in r.stderr


def test_pose_spec_matches_paper_grids():
  spec = components.pose_spec(gqn.get_config())
  assert spec.dof("xy").n_grid == 441 and spec.dof("xy").n_directions == 144
  assert spec.dim == 96 and spec.dof("yaw").n_grid == 36
  s7 = components.pose_spec(seven_scenes.get_config())
  assert [d.n_grid for d in s7.dofs] == [41, 16, 31, 36, 19, 36] and s7.dim == 32
  car = components.pose_spec(shapenet_car.get_config())
  assert isinstance(car.dof("polar"), P.AngularDof) and car.dof("polar").n_grid == 19


def test_learning_rate_schedules():
  config = gqn.get_config("smoke")
  assert step_lib.learning_rate(config, 1e-3) == 1e-3  # the paper's constant rate
  config.optax.schedule = "cosine"
  config.total_steps = 100
  lr = step_lib.learning_rate(config, 1e-3)
  assert float(lr(0)) == pytest.approx(1e-3) and float(lr(100)) == pytest.approx(1e-5)
  assert float(lr(50)) == pytest.approx(1e-3 * (0.01 + 0.99 * 0.5), rel=1e-5)
  config.optax.schedule = "linear"  # GQN's generator (configs/gqn_convdraw.py)
  config.optax.final_scale, config.optax.anneal_steps = 0.1, 100
  lr = step_lib.learning_rate(config, 1e-3)
  assert float(lr(0)) == pytest.approx(1e-3) and float(lr(50)) == pytest.approx(5.5e-4)
  assert float(lr(100)) == pytest.approx(1e-4) and float(lr(1000)) == pytest.approx(1e-4)
  config.optax.schedule = "exponential"
  with pytest.raises(ValueError, match="unknown optax.schedule 'exponential'"):
    step_lib.make_optimizers(config)

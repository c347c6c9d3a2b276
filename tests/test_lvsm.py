"""The multi-view transformer through camrep's entry points (task "mvt", configs/lvsm.py): every
camera conditioning trains and evaluates, on procedural rooms and on a prepared capture; the noise
test where it applies; config errors as `error:` lines."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from ml_collections import config_flags

from camrep import pose as P
from camrep.configs import lvsm
from camrep.data import prepare
from camrep.models import camera_conditioning as cc
from camrep.regression import pose_system
from camrep.runtime import cli
from camrep.runtime.runconfig import ConfigError
from camrep.synthesis import components, conditionings, config_schema, evaluate, restore, train
from camrep.synthesis import noise as noise_lib
from camrep.synthesis import step as step_lib
from tests.utils import slow_except

pytestmark = pytest.mark.usefixtures("fast_compile")

CAMERAS = tuple(conditionings.CONDITIONINGS)
# The fast tier trains one of each kind: absolute geometric, relative geometric, absolute
# learned (with the noise test), relative learned; the whole suite all seven.
FAST = ("raymap", "prope", "learned_abs", "learned_rel")


def _config(camera: str, **data):
  c = lvsm.get_config("smoke")
  c.model.camera = camera
  c.total_steps = c.eval_every_steps = c.ckpt_every_steps = 2
  c.evals.num_scenes = 2
  for k, v in data.items():
    setattr(c.data, k, v)
  return c


def test_the_registry_builds_each_conditioning_on_its_pose_system():
  spec = components.pose_spec(_config("none"))  # rooms: polar (x, y) + yaw
  assert spec.names == ("xy", "yaw")
  for name in CAMERAS:
    model = components.make_model(components.resolve(_config(name)), 4)
    learned = isinstance(model.conditioning, cc.LearnedAbsolute | cc.LearnedRelative)
    # The learned pair share one system with one DOF per column; the others keep the setting's.
    assert model.spec.names == (("x", "y", "yaw") if learned else ("xy", "yaw")), name
    assert model.reads_pose_vectors == isinstance(model.conditioning, cc.LearnedAbsolute)
  x, y, yaw = cc.columnwise(spec).dofs
  assert (x, y) == (P.LinearDof("x", -1.0, 1.0, 0.1), P.LinearDof("y", -1.0, 1.0, 0.1))
  assert yaw == spec.dofs[1]


def test_predict_is_the_posed_transformer_on_the_heldout_layout():
  """The synthesizer's training split (views [:C] context, [C:] queries) and held-out predict
  feed `PosedMVT` the same way; "rep" comes from the conditioning's own init (learned_rel's
  generators at init_scale, not the pose system's 1e-3)."""
  config = _config("learned_rel")
  model = components.make_model(components.resolve(config), 4)
  rng = np.random.default_rng(0)
  batch = {
    "image": rng.integers(0, 256, (2, 4, 64, 64, 3), dtype=np.uint8),
    "pose": np.concatenate(
      [rng.uniform(-0.9, 0.9, (2, 4, 2)), rng.uniform(0, 6, (2, 4, 1))], -1
    ).astype(np.float32),
    "scene": np.arange(2, dtype=np.int32),
  }
  params = model.init(jax.random.key(0), batch)
  gen = params["rep"]["x"][P.GENERATOR]
  assert float(jnp.std(gen)) > 0.5  # init_scale 2, not the pose system's 1e-3
  # The synthesizers' one `init`: "rep" is `init_pose`'s (the conditioning's, as the regression's
  # "untrained" control reads it), "model" the posed transformer's on the cameras' codes.
  images = batch["image"].astype(np.float32) / 127.5 - 1.0
  poses = batch["pose"]
  posed = jax.jit(model.posed.init)(jax.random.key(0), images[:, :2], poses[:, :2], poses[:, 2:])
  rep = jax.jit(model.init_pose)(jax.random.key(0))
  for want, got in ((posed, params), (posed["rep"], rep)):
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, atol=1e-6), want, got)
  heldout = {
    "context_image": batch["image"][:, :2],
    "context_pose": batch["pose"][:, :2],
    "target_image": batch["image"][:, 2:],
    "target_pose": batch["pose"][:, 2:],
  }
  pred = jax.jit(model.predict)(params, heldout)
  ctx = batch["image"][:, :2].astype(np.float32) / 127.5 - 1.0
  ref, _ = jax.jit(model.posed.apply)(params, ctx, batch["pose"][:, :2], batch["pose"][:, 2:])
  np.testing.assert_allclose(np.asarray(pred), np.asarray(ref), atol=1e-5)
  loss = jax.pmap(lambda p, b: model.loss(p, b, jax.random.key(1), 0), axis_name="batch")
  rec, terms = loss(*jax.tree.map(lambda a: jnp.asarray(a)[None], (params, batch)))
  target = batch["image"][:, 2:].astype(np.float32) / 127.5 - 1.0
  want = np.mean(np.sum((np.asarray(ref) - target) ** 2, axis=(-3, -2, -1)))
  np.testing.assert_allclose(float(rec[0]), want, rtol=1e-4)
  assert set(terms) == {"rec", "mse"}


@pytest.mark.parametrize("camera", slow_except(CAMERAS, FAST))
def test_each_conditioning_trains_and_evaluates(camera, tmp_path, capsys):
  config = _config(camera)
  workdir = str(tmp_path / camera)
  final = train.train_and_evaluate(config, workdir, log=lambda line: None)
  assert np.isfinite(final["eval/psnr"]) and np.isfinite(final["eval/psnr_baseline"])
  run = restore.load_run(workdir)
  fresh = step_lib.init_fn(config, run.model, step_lib.make_optimizers(config))()
  moved = jax.tree.map(lambda a, b: float(np.max(np.abs(np.asarray(a) - b))), fresh.params,
                       run.params)  # fmt: skip
  assert max(jax.tree.leaves(moved["model"])) > 0
  if run.model.conditioning.learns:  # the "rep" group trains the learned pose system
    gens = [moved["rep"][n][P.GENERATOR] for n in run.model.spec.names]
    assert max(gens) > 0
  else:
    assert run.params["rep"] == {}
  # Pose regression's "ours" reads a decoder run's pose system, not the transformer's.
  with pytest.raises(ConfigError, match="MVTSynthesizer run"):
    pose_system.load_pose_system(workdir, "gqn")
  # Generalisation to other context counts (evals.context_counts (1, 3); trained with 2).
  for n in (1, 3):
    assert np.isfinite(final[f"eval/psnr_context{n}"]), n
    assert np.isfinite(final[f"eval/ssim_context{n}"]), n
  assert "eval/psnr_context2" not in final  # the trained count is eval/psnr itself
  # The noise test on the query pose, before conditioning: every conditioning takes it.
  rc = evaluate.main(
    ["--workdir", workdir, "--what=noise", "--alphas=0,1", "--quantisation=nearest"]
  )
  assert rc == 0, capsys.readouterr().err
  noise = json.loads((tmp_path / camera / "eval" / "noise.json").read_text())
  assert noise["noise_on"] == "pose" and sorted(noise["beta"]) == ["x", "y", "yaw"]
  np.testing.assert_allclose(noise["psnr"][0], final["eval/psnr"], atol=1e-4)
  if isinstance(run.model.conditioning, cc.NoCamera):
    assert noise["psnr"][0] == noise["psnr"][1]  # the control reads no pose: noise cannot reach
  else:
    assert noise["psnr"][0] != noise["psnr"][1]  # the noise reaches the prediction
  # The paper's test on the vectors v(p), and the Gram maps, where the model reads them.
  for what in ("--what=noise", "--what=gram"):
    rc = evaluate.main(["--workdir", workdir, what, "--noise_on=vectors", "--alphas=0,1"])
    err = capsys.readouterr().err
    if run.model.reads_pose_vectors:
      assert rc == 0, err
    else:
      assert rc == 2 and "no per-DOF pose vectors v(p)" in err, err


@pytest.mark.slow
def test_a_capture_trains_and_evaluates_in_the_car_setting(tmp_path):
  """A tiny LLFF capture prepared at 64 px: the geometric conditioning sees the car setting's
  nominal cameras, the learned one its (azimuth, polar) system."""
  from tests.test_captures import rig, write_llff

  c2w, _ = rig(24)
  write_llff(tmp_path / "cap", c2w, rng=np.random.default_rng(0))
  argv = ["--source", "llff", "--input", str(tmp_path / "cap"), "--data_dir",
          str(tmp_path / "data"), "--preset", "small", "--no_progress"]  # fmt: skip
  assert prepare.main(argv) == 0
  for camera in ("prope", "learned_rel"):
    config = _config(camera, source="llff", dir=str(tmp_path / "data"), scenes_per_device=1)
    config.evals.num_scenes = 1
    config_schema.validate(config)
    final = train.train_and_evaluate(config, str(tmp_path / camera), log=lambda line: None)
    assert np.isfinite(final["eval/psnr"])
    model = components.make_model(components.resolve(config), 1)
    assert model.spec.names == ("azimuth", "polar")
    if camera == "prope":
      assert model.conditioning.cameras == cc.ObjectCameras(
        camera_distance=1.0, fov_deg=conditionings.NOMINAL_FOV_DEG
      )


def _validate_tool():
  def define(fv, argv):
    config_flags.DEFINE_config_file(
      "config", None, "config", flag_values=fv, lock_config=True, sys_argv=list(argv)
    )

  def body(fv):
    config_schema.validate(fv.config, overridden=cli.overridden(fv))
    return 0

  return define, body


@pytest.mark.parametrize(
  "flag, fragment",
  [
    ("--config.model.camera=plucker", "--config.model.camera='plucker': must be one of"),
    ("--config.model.size=huge", "--config.model.size='huge': must be one of"),
    ("--config.model.init_scale=0", "--config.model.init_scale=0.0: must be a number > 0"),
    ("--config.model.width=0.5", "this run does not use config.model.width"),
    # learned_rel: 3 DOFs x 8 blocks x 2 = 48 dims in MVTTiny's 16-dim heads.
    ("--config.rep.n_blocks=8", "needs 48 dims per head"),
    # The truncated series breaks M(a)^T M(b) = M(b - a).
    ("--config.rep.exp_method=taylor2", "needs an exact exponential"),
    ("--config.rep.kind=lowdim", "rep.kind must be 'grid'"),
  ],
)
def test_config_errors_are_one_error_line(flag, fragment, capsys):
  define, body = _validate_tool()
  base = ["--config=configs/lvsm.py:smoke", "--config.model.camera=learned_rel"]
  assert cli.call(define, body, [*base, flag]) == 2
  err = capsys.readouterr().err
  assert "Traceback" not in err
  lines = [line for line in err.splitlines() if line.startswith("error: ")]
  assert len(lines) == 1 and fragment in lines[0], err


def test_geometric_conditionings_refuse_data_without_cameras(tmp_path):
  config = _config("gta", source="area")
  config.task = "mvt"
  with pytest.raises(ConfigError, match="gta.: no pose-to-camera map for the .area. family"):
    config_schema.validate(config)
  with pytest.raises(ValueError, match="no paper size"):
    lvsm.get_config(None)


def test_pose_noise_is_the_same_for_every_pose_system():
  """The noise test on the pose: betas per column are the std over the column's grid, the same
  for the setting's polar system and the learned pair's one-column system; alpha 0 is exact; the
  draws come from the image keys only."""
  spec = components.pose_spec(_config("none"))
  betas = noise_lib.pose_betas(spec)
  np.testing.assert_allclose(betas, noise_lib.pose_betas(cc.columnwise(spec)))
  grid = np.arange(-1.0, 1.0 + 1e-9, 0.1)
  yaw = np.arange(36) * (2 * np.pi / 36)
  np.testing.assert_allclose(betas, [grid.std(), grid.std(), yaw.std()], rtol=1e-6)
  poses = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (4, 1, 3)), jnp.float32)
  keys = jax.random.split(jax.random.key(3), 4)
  np.testing.assert_array_equal(
    noise_lib.add_pose_noise(poses, keys, alpha=0.0, betas=betas), poses
  )
  a = noise_lib.add_pose_noise(poses, keys, alpha=0.2, betas=betas)
  b = noise_lib.add_pose_noise(poses + 1.0, keys, alpha=0.2, betas=betas)
  np.testing.assert_allclose(np.asarray(b - a), 1.0, atol=1e-6)  # the same draws
  z = np.asarray(a - poses) / (0.2 * betas)
  assert np.all(np.abs(z) > 0) and np.all(np.abs(z) < 6)

"""Tests of camrep.settings: the paper's settings as types in one registry, their pose systems,
orientation conventions, cameras and scores, and a setting added by one class.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typing_extensions import override

from camrep import metrics, settings
from camrep import pose as P
from camrep.data import sources
from tests.utils import assert_close, x64

TWO_PI = 2 * math.pi
PAPER = (settings.GQN, settings.CAR, settings.GIBSON, settings.SEVEN_SCENES)


def _wxyz(rot: Rotation) -> np.ndarray:
  """scipy (x, y, z, w) -> (w, x, y, z) with w >= 0."""
  q = np.roll(rot.as_quat(), 1, axis=-1)
  return np.where(q[..., :1] < 0, -q, q)


def test_one_registry_names_each_setting_once():
  assert settings.names()[:4] == ("gqn", "car", "gibson", "seven_scenes")
  for s in PAPER:
    assert settings.get(s.name) is s and settings.get(s) is s and str(s) == s.name
  with pytest.raises(ValueError, match="unknown setting 'kitti'"):
    settings.get("kitti")
  with pytest.raises(ValueError, match="already registered"):
    settings.register(settings.GqnRooms())


def test_the_columns_and_ranges_the_tables_held():
  """What `targets.POSE_COLUMNS`, `POSITION_DIM`, `_ANGLE_PERIODIC` and `sources.pose_names`
  stated, now derived from each setting's one pose system."""
  assert {s.name: s.pose_columns for s in PAPER} == {
    "gqn": ("x", "y", "yaw"),
    "car": ("azimuth", "polar"),
    "gibson": ("x", "y", "yaw"),
    "seven_scenes": ("x", "y", "z", "theta", "phi", "psi"),
  }
  assert {s.name: s.position_dim for s in PAPER} == {
    "gqn": 2,
    "car": 0,
    "gibson": 2,
    "seven_scenes": 3,
  }
  assert {s.name: tuple(d.periodic for d in s.angle_dofs) for s in PAPER} == {
    "gqn": (True,),
    "car": (True, False),
    "gibson": (True,),
    "seven_scenes": (True, False, True),
  }
  assert [s.has_polar_dof for s in PAPER] == [True, False, True, False]


def test_the_paper_size_pose_systems():
  """`pose_spec()` is the spec `targets.default_spec` built: gqn polar (x, y) on [-1, 1] at 0.1
  + yaw; gibson polar on [0, 2] m at 0.05 + yaw; car azimuth + polar angle (0..pi,
  non-periodic); seven_scenes x, y, z on [0, 4] x [0, 1.5] x [0, 3] m at 0.1 + theta, phi
  (0..pi), psi, with 4 x 8 blocks. Angles at 10 degrees."""
  ang = math.pi / 18

  def angle(name, high=TWO_PI, per=True):
    return P.AngularDof(name, spacing=ang, high=high, periodic=per)

  def spec(dofs, nb=6, bs=16):
    return P.PoseSystemSpec(dofs=dofs, n_blocks=nb, block_size=bs, exp_method="taylor2")

  assert settings.GQN.pose_spec() == spec(
    (P.BinnedPolarDof("xy", -1.0, 1.0, 0.1, pair_radius=2.0), angle("yaw"))
  )
  assert settings.GIBSON.pose_spec() == spec(
    (P.BinnedPolarDof("xy", 0.0, 2.0, 0.05, pair_radius=2.2), angle("yaw"))
  )
  assert settings.CAR.pose_spec() == spec((angle("azimuth"), angle("polar", math.pi, False)))
  linear = (P.LinearDof("x", 0.0, 4.0, 0.1), P.LinearDof("y", 0.0, 1.5, 0.1))
  assert settings.SEVEN_SCENES.pose_spec() == spec(
    linear
    + (P.LinearDof("z", 0.0, 3.0, 0.1), angle("theta"), angle("phi", math.pi, False))
    + (angle("psi"),),
    nb=4,
    bs=8,
  )
  # camrep's options reach every DOF; the ranges stay the setting's.
  cont = settings.GQN.pose_spec(polar_variant="continuous", position_spacing=0.2, periodic=False)
  assert isinstance(cont.dofs[0], P.ContinuousPolarDof) and cont.dofs[0].spacing == 0.2
  assert (cont.dofs[0].low, cont.dofs[0].high) == (-1.0, 1.0) and not cont.dofs[1].periodic


def test_car_rotation_is_intrinsic_zxz_and_inverts():
  rng = np.random.default_rng(3)
  az = rng.uniform(0, TWO_PI, 100)
  pol = rng.uniform(0.01, math.pi - 0.01, 100)
  with x64():
    R = settings.car_rotation(jnp.asarray(az), jnp.asarray(pol))
    ref = Rotation.from_euler(
      "ZXZ", np.stack([az - math.pi / 2, math.pi - pol, np.full(100, math.pi)], -1)
    )
    assert_close(R, ref.as_matrix(), atol=1e-12)
    # The optical axis points at the centre from the camera on the z-up sphere.
    centre = np.stack([np.sin(pol) * np.cos(az), np.sin(pol) * np.sin(az), np.cos(pol)], -1)
    assert_close(np.asarray(R)[:, :, 2], -centre, atol=1e-12)
    assert_close(settings.car_angles(R), np.stack([az, pol], -1), atol=1e-9)


def test_orientation_quat_seven_scenes_matches_dofs_to_c2w():
  from camrep.data.readers import seven_scenes

  rng = np.random.default_rng(4)
  poses = np.stack(
    [rng.uniform(0.1, 3.9, 16), rng.uniform(0.1, 1.4, 16), rng.uniform(0.1, 2.9, 16)]
    + [rng.uniform(0, TWO_PI, 16), rng.uniform(0.2, 2.9, 16), rng.uniform(0, TWO_PI, 16)],
    -1,
  )
  with x64():
    c2w = seven_scenes.dofs_to_c2w(poses, np.zeros(3))
    q = settings.SEVEN_SCENES.orientation_quat(jnp.asarray(poses))
    assert_close(q, _wxyz(Rotation.from_matrix(c2w[:, :3, :3])), atol=1e-12)
    # Back from the quaternion: the same angles (phi inside (0, pi): no gimbal lock).
    assert_close(settings.SEVEN_SCENES.angles_from_quat(q), poses[:, 3:], atol=1e-9)


@pytest.mark.parametrize("family", ["rooms", "area", "object", "scene6dof"])
def test_poses_from_the_renderers_cameras(family):
  """Each setting reads back the pose its procedural family rendered a camera at (the rooms:
  position and yaw, less the area's origin; the car: the centre's angles; 6-DOF: the sxyz
  angles)."""
  fam = sources.build(family, preset="small")
  setting = sources.setting_of(family)
  scene = fam.scene_ids("train")[0]
  poses = np.asarray(fam.poses("train", scene), np.float64)
  c2w = np.asarray(fam.poses_to_c2w(scene, poses), np.float64)
  if family == "area":  # the renderer's world is the area's, offset by its origin
    c2w[:, :3, 3] -= fam.layout(scene).origin
  if family == "scene6dof":  # the renderer's room frame is the re-based frame turned by A
    a4 = np.eye(4)
    a4[:3, :3] = fam._alignment(scene)
    c2w = np.einsum("ji,njk->nik", a4, c2w)
  got = setting.poses_from_c2w(c2w)
  k = setting.position_dim
  assert_close(got[:, :k], poses[:, :k], atol=1e-5)
  d = np.mod(got[:, k:] - poses[:, k:] + math.pi, TWO_PI) - math.pi
  assert np.abs(d).max() < 1e-4


def test_wrap_angles_and_the_selection_score():
  ang = jnp.asarray([[-0.5, 4.0]], jnp.float32)
  assert_close(settings.CAR.wrap_angles(ang), [[TWO_PI - 0.5, math.pi]], atol=1e-6)
  summary = {"all": {"x_error": {"mean": 0.106}, "y_error": {"mean": 0.053}}}
  summary["all"]["yaw_error_deg"] = {"mean": 4.07}
  assert settings.GQN.validation_score(summary) == pytest.approx((2 + 1 + 1) / 3)
  assert settings.SEVEN_SCENES.validation_score_text() == (
    "mean of (position_error median / 0.21, rotation_error_deg median / 7.92)"
  )
  assert settings.CAR.validation_score_text() == "rotation_error_deg mean / 2.85"


# ---------------------------------------------------------------------------- a new setting


class Turntable(settings.Setting):
  """A camera on a sphere around an object, scored on azimuth only: what adding a setting takes
  (here, in a test: one class; a data source of it; nothing else)."""

  name = "turntable"
  network = "conv5"
  selection_metric = (("azimuth_error_deg", "mean", 1.0),)

  @override
  def _dofs(self, o):
    return (o.angle("azimuth"), o.angle("polar", high=math.pi, periodic=False))

  @override
  def angles_to_quat(self, angles):
    return settings.CAR.angles_to_quat(angles)

  @override
  def angles_from_quat(self, q):
    return settings.CAR.angles_from_quat(q)

  @override
  def pose_errors(self, pred, true):
    return {"azimuth_error_deg": metrics.wrapped_angle_error_deg(pred[..., 0], true[..., 0])}


def turntable_objects(name, **kwargs):
  """The procedural object family, as the turntable setting's data."""
  from camrep.data import procedural

  del name
  return procedural.make_family("object", **kwargs)


@pytest.fixture
def turntable():
  setting = settings.register(Turntable())
  source = sources.register(
    sources.Source(
      "turntable_objects", "tests.test_settings", "turntable_objects", True, setting, None,
      ("train", "test", "test_scenes"), "the object family, turntable setting",
    )
  )  # fmt: skip
  yield setting
  sources.unregister(source.name)
  settings.unregister(setting)


def test_a_setting_is_one_class(turntable):
  """The encodings, the regressor and the regression config take a new setting unchanged."""
  from camrep.configs import regression as regression_config
  from camrep.regression import config_schema, driver
  from camrep.regression import targets as T

  assert turntable.pose_columns == ("azimuth", "polar") and turntable.position_dim == 0
  assert sources.procedural_of(turntable) == "turntable_objects"
  poses = jnp.asarray([[0.3, 1.0], [5.0, 2.0]], jnp.float32)
  for rep in ("quat", "sincos", "rot6d"):
    back = T.decode(rep, turntable, T.encode(rep, turntable, poses))
    assert_close(back, poses, atol=1e-4)
  c = regression_config.get_config("turntable,smoke")
  assert c.setting == "turntable" and c.evals.test_split == "test" and "hparams" in c
  c.representation = "mlp"
  run = config_schema.check(c)
  reg = driver.make_regressor(run, turntable.pose_spec(), 1)
  assert reg.setting is turntable and [h.name for h in reg.heads] == ["azimuth", "polar"]
  assert run.hparams.lr == c.optax.lr


@pytest.mark.slow
@pytest.mark.usefixtures("fast_compile")  # plumbing, not numbers: compile time dominates
def test_both_stages_run_a_new_setting(turntable, tmp_path):
  """View synthesis learns the new setting's pose system from its data source, and a
  regression regresses it, with no edit outside this file."""
  from camrep.configs import regression as regression_config
  from camrep.configs import shapenet_car
  from camrep.regression import driver
  from camrep.synthesis import train

  c = shapenet_car.get_config("smoke")
  c.data.source = "turntable_objects"
  c.total_steps, c.evals.num_scenes = 1, 1
  train.train_and_evaluate(c, str(tmp_path / "syn"))
  r = regression_config.get_config("turntable,smoke")
  r.representation, r.synthesis_workdir = "ours", str(tmp_path / "syn")
  results = driver.run(r, str(tmp_path / "reg"), log=lambda s: None)
  assert results["setting"] == "turntable"
  assert np.isfinite(results["test"]["all"]["azimuth_error_deg"]["mean"])
  assert results["representation_params"]["source"] == "synthesis"
  assert jax.tree.leaves(results)  # results.json content

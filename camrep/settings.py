"""The paper's settings (Table 1's columns and Table 2) as types, in one registry.

A `Setting` is what the paper means by "GQN rooms", "ShapeNet car", "Gibson area" or "7-Scenes":
the camera's pose columns and their ranges (its pose system: the one source of the ranges both
stages use), how its angles give a camera orientation, how a camera-to-world matrix gives its
pose, the errors a regressor is scored by and the score that picks its learning rate, the
regressor network, and how its views are split. The interface is documented once, on `Setting`;
each setting overrides only what differs. Code takes a `Setting`, never compares a name: the
names appear here (the registry) and where a config or a record names one (`get`).

  name          pose columns (radians; positions in the dataset's unit)
  gqn           (x, y, yaw)                 position (x, y) in [-1, 1]^2; yaw about +z
  car           (azimuth, polar)            no position; the camera rotation
                                            R = Rz(azimuth - pi/2) Rx(pi - polar) Rz(pi)
  gibson        (x, y, yaw)                 as gqn, position in [0, 2]^2 m
  seven_scenes  (x, y, z, theta, phi, psi)  position in [0, 4] x [0, 1.5] x [0, 3] m; orientation
                                            R = Rz(psi - pi) Ry(phi - pi/2) Rx(theta - pi)
                                            (static Euler "sxyz", shifted)

Adding a setting is one class here or in any module imported before use: subclass `Setting`,
give it a `name`, its DOFs (`_dofs`), its orientation maps and errors, and `register` an
instance. A data source of that setting (`camrep.data.sources.register`) then feeds both stages;
`camrep.configs.regression` gives a setting without its own recipe the base one.

Rotation conventions are `camrep.rotations`' (quaternions scalar first, (w, x, y, z)).
"""

from __future__ import annotations

import abc
import dataclasses
import functools
import math
from collections.abc import Mapping
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from typing_extensions import override

from camrep import dofs, metrics, rotations

Array = jax.Array

TWO_PI = 2.0 * math.pi


@dataclasses.dataclass(frozen=True)
class PoseOptions:
  """camrep's options of a pose system (a synthesis config's `rep` section), resolved.

  Attributes:
    angle_spacing: grid spacing of angles, radians.
    periodic: periodic angle grids (camrep's fix) or the authors' separate end vectors (non-
      periodic angles such as a polar angle stay non-periodic).
    position_spacing: grid spacing of positions, the dataset's length unit.
    polar_variant: a key of `dofs.POLAR_VARIANTS`.
    n_directions, block_norm, pair_radius: of a polar (x, y) DOF (`dofs.PolarDof`).
  """

  angle_spacing: float
  periodic: bool
  position_spacing: float
  polar_variant: str
  n_directions: int
  block_norm: bool
  pair_radius: float

  def angle(self, name: str, *, high: float = TWO_PI, periodic: bool | None = None) -> dofs.Dof:
    """An angle DOF on [0, high] at `angle_spacing`; periodic as the options unless given."""
    return dofs.AngularDof(
      name,
      spacing=self.angle_spacing,
      low=0.0,
      high=high,
      periodic=self.periodic if periodic is None else periodic,
    )

  def polar(self, low: float, high: float) -> dofs.Dof:
    """The polar (x, y) DOF "xy" on [low, high]^2 at `position_spacing`."""
    return dofs.polar_dof(
      self.polar_variant,
      name="xy",
      low=low,
      high=high,
      spacing=self.position_spacing,
      n_directions=self.n_directions,
      block_norm=self.block_norm,
      pair_radius=self.pair_radius,
    )

  def linear(self, name: str, low: float, high: float) -> dofs.Dof:
    """A linear DOF on [low, high] at `position_spacing`."""
    return dofs.LinearDof(name, low, high, self.position_spacing)


class Setting(abc.ABC):
  """One setting of the paper: its poses, their geometry and scoring, and its data's splits.

  Implementations are stateless singletons (compared and hashed by identity, so a `Setting` is
  a static argument of jitted functions), registered by `register`.

  Attributes:
    name: registry key, as configs and records name the setting.
    network: the regressor network, a key of `camrep.models.pose_regressor.NETWORKS`.
    context_views: True when a regression example is a scene (GQN): an encoder reads the
      scene's first `n_context` views and the regressor predicts the poses of its other views;
      validation and test then hold out whole scenes. False: an example is one view;
      validation holds out the last views of every training scene.
    test_split: the split the paper's protocol tests a regressor on.
    real_test_description: what a prepared real dataset's "test" split holds for this setting.
    validation_note: appended to the description of a real dataset's validation part.
    selection_metric: the score that picks a learning rate (`validation_score`): per term
      (error name, statistic, the paper's error of "ours"); the score is the mean over terms of
      validation error / paper error, so that position and angle errors count alike.
    noise_quantisation: the quantisation of the noise test's poses (the authors': a random
      neighbour for GQN and the car, rounding otherwise).
    gqn_pose_vector: GQN's low-dimensional pose input is its 7-D vector (x, y, z, sin yaw,
      cos yaw, sin pitch, cos pitch) with the rooms' constant camera height and pitch; False:
      raw positions and (sin, cos) of the angles.
    default_position_spacing, default_pair_radius, default_blocks: the paper-size pose
      system's position grid spacing, polar pair radius and (n_blocks, block_size).
  """

  name: ClassVar[str]
  network: ClassVar[str]
  context_views: ClassVar[bool] = False
  test_split: ClassVar[str] = "test"
  real_test_description: ClassVar[str] = "prepared test split"
  validation_note: ClassVar[str] = ""
  selection_metric: ClassVar[tuple[tuple[str, str, float], ...]]
  noise_quantisation: ClassVar[str] = "nearest"
  gqn_pose_vector: ClassVar[bool] = False
  default_position_spacing: ClassVar[float] = 0.1
  default_pair_radius: ClassVar[float] = 2.0
  default_blocks: ClassVar[tuple[int, int]] = (6, 16)

  def __repr__(self) -> str:
    return f"<setting {self.name}>"

  def __str__(self) -> str:
    return self.name

  # -- the pose system -------------------------------------------------------------------------

  @abc.abstractmethod
  def _dofs(self, o: PoseOptions) -> tuple[dofs.Dof, ...]:
    """The DOFs, in pose-column order, on the setting's ranges at the spacings of `o`."""

  def pose_spec(
    self,
    *,
    angle_spacing: float = math.pi / 18,
    periodic: bool = True,
    position_spacing: float | None = None,
    polar_variant: str = "binned",
    n_directions: int = 144,
    block_norm: bool = True,
    pair_radius: float | None = None,
    n_blocks: int | None = None,
    block_size: int | None = None,
    exp_method: str = "taylor2",
    n_steps: int = 1,
  ) -> dofs.PoseSystemSpec:
    """The setting's pose system: its DOFs on its ranges, with camrep's options.

    The defaults are the paper's sizes (angles at 10 degrees; positions at
    `default_position_spacing`; `default_blocks` blocks; the authors' "taylor2" exponential).
    View synthesis passes its config's `rep` options (`camrep.synthesis.components.pose_spec`);
    a regression without a view-synthesis run uses the defaults.
    """
    o = PoseOptions(
      angle_spacing=angle_spacing,
      periodic=periodic,
      position_spacing=self.default_position_spacing
      if position_spacing is None
      else position_spacing,
      polar_variant=polar_variant,
      n_directions=n_directions,
      block_norm=block_norm,
      pair_radius=self.default_pair_radius if pair_radius is None else pair_radius,
    )
    nb, bs = self.default_blocks
    return dofs.PoseSystemSpec(
      dofs=self._dofs(o),
      n_blocks=n_blocks or nb,
      block_size=block_size or bs,
      exp_method=exp_method,
      n_steps=n_steps,
    )

  @functools.cached_property
  def _default_dofs(self) -> tuple[dofs.Dof, ...]:
    return self.pose_spec().dofs

  @property
  def pose_columns(self) -> tuple[str, ...]:
    """The P pose columns of the setting's records, in order."""
    return tuple(c for d in self._default_dofs for c in d.column_names)

  @property
  def position_dim(self) -> int:
    """How many leading pose columns are a position (0, 2 or 3)."""
    return sum(d.width for d in self._default_dofs if not d.is_angle)

  @property
  def angle_dofs(self) -> tuple[dofs.Dof, ...]:
    """The angle DOFs (the trailing pose columns), in order."""
    return tuple(d for d in self._default_dofs if d.is_angle)

  @property
  def has_polar_dof(self) -> bool:
    """Whether the pose system has a polar (x, y) DOF, the one DOF of two columns (its options
    then apply)."""
    return any(d.width == 2 for d in self._default_dofs)

  def check_poses(self, poses: Array) -> Array:
    """poses as an array (..., P), checked for the setting's P columns.

    Raises:
      ValueError: another number of columns.
    """
    poses = jnp.asarray(poses)
    n = len(self.pose_columns)
    if poses.ndim < 1 or poses.shape[-1] != n:
      raise ValueError(f"{self.name} poses have {n} columns {self.pose_columns}, got {poses.shape}")
    return poses

  def check_spec(self, spec: dofs.PoseSystemSpec) -> None:
    """Raises ValueError when `spec`'s columns are not the setting's."""
    cols = tuple(c for d in spec.dofs for c in d.column_names)
    if len(cols) != len(self.pose_columns):
      raise ValueError(
        f"spec DOFs {spec.names} do not match {self.name} columns {self.pose_columns}"
      )

  # -- orientation ------------------------------------------------------------------------------

  def split_pose(self, poses: Array) -> tuple[Array, Array]:
    """(positions (..., position_dim), angles (..., n_angles)) of poses (..., P)."""
    poses = self.check_poses(poses)
    k = self.position_dim
    return poses[..., :k], poses[..., k:]

  @abc.abstractmethod
  def angles_to_quat(self, angles: Array) -> Array:
    """Quaternions (..., 4), w >= 0, of the camera orientation of angle columns (..., n_angles)."""

  @abc.abstractmethod
  def angles_from_quat(self, q: Array) -> Array:
    """Inverse of `angles_to_quat`: angle columns (..., n_angles) of quaternions (..., 4).

    q is normalised first; a rotation outside the setting's family decodes to the closest member.
    """

  def orientation_quat(self, poses: Array) -> Array:
    """The camera orientation of poses (..., P) as quaternions (..., 4), w >= 0."""
    return self.angles_to_quat(self.split_pose(poses)[1])

  def wrap_angles(self, angles: Array) -> Array:
    """Angle columns (..., n_angles) mapped into their ranges: periodic ones modulo their range,
    bounded ones clipped to it."""
    ds = self.angle_dofs
    periodic = jnp.asarray([d.periodic for d in ds])
    low = jnp.asarray([d.low for d in ds], angles.dtype)
    high = jnp.asarray([d.high for d in ds], angles.dtype)
    return jnp.where(periodic, low + jnp.mod(angles - low, high - low), jnp.clip(angles, low, high))

  # -- cameras ----------------------------------------------------------------------------------

  def poses_from_c2w(self, c2w: np.ndarray) -> np.ndarray:
    """Host-side: poses (..., P) float64 of camera-to-world matrices (..., 4, 4) (OpenCV camera
    axes: x right, y down, z the viewing direction), in the setting's world frame.

    Raises:
      NotImplementedError: the setting's poses are not a function of the camera alone.
    """
    raise NotImplementedError(f"setting {self.name!r} reads no camera-to-world matrices")

  # -- scoring ----------------------------------------------------------------------------------

  @abc.abstractmethod
  def pose_errors(self, pred: Array, true: Array) -> dict[str, Array]:
    """Per-example errors of predicted poses (the authors' code), via `camrep.metrics`.

    Args:
      pred, true: (..., P) poses.

    Returns:
      {error name: (...)}; angles in degrees ("*_deg"), positions in the dataset's unit.
    """

  def validation_score(self, summary: Mapping[str, Any]) -> float:
    """The learning-rate selection score of a summary (lower is better; see `selection_metric`).

    Args:
      summary: {"all": {error: {"mean", "median"}}, ...} (`scoring.summarise_errors`).
    """
    terms = [summary["all"][err][stat] / ref for err, stat, ref in self.selection_metric]
    return float(np.mean(terms))

  def validation_score_text(self) -> str:
    """The selection score in words, e.g. "mean of (x_error mean / 0.053, ...)"."""
    terms = [f"{err} {stat} / {ref:g}" for err, stat, ref in self.selection_metric]
    return terms[0] if len(terms) == 1 else f"mean of ({', '.join(terms)})"


# ----------------------------------------------------------------------------------------------
# The car setting's camera rotation.


def car_rotation(azimuth: Array, polar: Array) -> Array:
  """Camera rotation of a car view: intrinsic "rzxz" (az - pi/2, pi - polar, pi).

  R = Rz(az - pi/2) Rx(pi - polar) Rz(pi); its third column (the optical axis) is
  -(sin p cos a, sin p sin a, cos p): the camera on the z-up sphere looks at the centre.
  (scipy: `Rotation.from_euler("ZXZ", [az - pi/2, pi - polar, pi])`.)

  Args:
    azimuth, polar: (...) angles in radians.

  Returns:
    (..., 3, 3).
  """
  rz, rx = rotations.rot_z, rotations.rot_x
  return rz(azimuth - math.pi / 2) @ rx(math.pi - polar) @ rz(jnp.full_like(azimuth, math.pi))


def car_angles(R: Array) -> Array:
  """(azimuth, polar) of the camera whose rotation is closest to R in viewing direction.

  Inverse of `car_rotation`, read from the optical axis only, so any predicted rotation decodes
  (its roll is ignored): c = -R[:, 2], azimuth = atan2(c_y, c_x) mod 2 pi,
  polar = atan2(hypot(c_x, c_y), c_z) in [0, pi].

  Args:
    R: (..., 3, 3).

  Returns:
    (..., 2).
  """
  c = -R[..., :, 2]
  azimuth = jnp.mod(jnp.arctan2(c[..., 1], c[..., 0]), TWO_PI)
  polar = jnp.arctan2(jnp.hypot(c[..., 0], c[..., 1]), c[..., 2])
  return jnp.stack([azimuth, polar], axis=-1)


def sphere_angles(c2w: np.ndarray) -> np.ndarray:
  """Host-side (azimuth, polar) of camera centres on a z-up sphere: azimuth = atan2(c_y, c_x)
  mod 2 pi in [0, 2 pi), polar = arccos(c_z / |c|) in [0, pi]; (..., 4, 4) or (..., 3, 4) ->
  (..., 2) float64 (only the translation column is read)."""
  c = np.asarray(c2w, dtype=np.float64)[..., :3, 3]
  r = np.linalg.norm(c, axis=-1)
  azimuth = np.mod(np.arctan2(c[..., 1], c[..., 0]), TWO_PI)
  azimuth = np.where(azimuth >= TWO_PI, 0.0, azimuth)
  polar = np.arccos(np.clip(c[..., 2] / np.where(r > 0, r, 1.0), -1.0, 1.0))
  return np.stack([azimuth, polar], axis=-1)


# ----------------------------------------------------------------------------------------------
# The settings.


class _Rooms(Setting):
  """A camera moving in a plane at a fixed height and pitch: position (x, y) as one polar DOF,
  orientation a yaw about +z."""

  _range: ClassVar[tuple[float, float]]

  @override
  def _dofs(self, o):
    return (o.polar(*self._range), o.angle("yaw"))

  @override
  def angles_to_quat(self, angles):
    return rotations.yaw_to_quat(angles[..., 0])

  @override
  def angles_from_quat(self, q):
    return rotations.quat_to_yaw(rotations.standardise_quat(q))[..., None]

  @override
  def poses_from_c2w(self, c2w):
    """(x, y) of the camera centre and the yaw of its viewing direction (the third column)."""
    c2w = np.asarray(c2w, np.float64)
    fwd = c2w[..., :3, 2]
    yaw = np.mod(np.arctan2(fwd[..., 1], fwd[..., 0]), TWO_PI)
    return np.concatenate([c2w[..., :2, 3], yaw[..., None]], axis=-1)

  @override
  def pose_errors(self, pred, true):
    """ "x_error", "y_error" (|.|), "position_error" (Euclidean), "yaw_error_deg" (wrapped to
    [0, 180])."""
    pos_hat, ang_hat = self.split_pose(pred)
    pos, ang = self.split_pose(true)
    err = metrics.abs_error(pos_hat, pos)
    return {
      "x_error": err[..., 0],
      "y_error": err[..., 1],
      "position_error": metrics.translation_error(pos_hat, pos),
      "yaw_error_deg": metrics.wrapped_angle_error_deg(ang_hat[..., 0], ang[..., 0]),
    }


class GqnRooms(_Rooms):
  """GQN rooms (Eslami et al. 2018): scenes of a few views each, position in [-1, 1]^2 scene
  units; the regressor reads each scene's context views (`context_views`)."""

  name = "gqn"
  network = "adain_context"
  context_views = True
  test_split = "test_scenes"
  noise_quantisation = "random"
  gqn_pose_vector = True
  selection_metric = (
    ("x_error", "mean", 0.053),
    ("y_error", "mean", 0.053),
    ("yaw_error_deg", "mean", 4.07),
  )
  _range = (-1.0, 1.0)


class GibsonArea(_Rooms):
  """Gibson rooms (the authors' renders): cameras over a 2 m x 2 m area of each room, position in
  [0, 2]^2 m at 0.05 m; the regressor normalises per area."""

  name = "gibson"
  network = "conv5_area_norm"
  real_test_description = "prepared test split (held-out views of the training areas)"
  default_position_spacing = 0.05
  default_pair_radius = 2.2
  selection_metric = (
    ("x_error", "mean", 0.021),
    ("y_error", "mean", 0.020),
    ("yaw_error_deg", "mean", 0.87),
  )
  _range = (0.0, 2.0)


class ShapeNetCar(Setting):
  """ShapeNet cars (SRN renders): a camera on a sphere around the object looking at its centre,
  pose (azimuth, polar angle); no position."""

  name = "car"
  network = "conv5"
  real_test_description = (
    "prepared test split (cars_train_test: held-out views of the training cars)"
  )
  noise_quantisation = "random"
  selection_metric = (("rotation_error_deg", "mean", 2.85),)

  @override
  def _dofs(self, o):
    return (o.angle("azimuth"), o.angle("polar", high=math.pi, periodic=False))

  @override
  def angles_to_quat(self, angles):
    """The quaternion of `car_rotation`."""
    return rotations.matrix_to_quat(car_rotation(angles[..., 0], angles[..., 1]))

  @override
  def angles_from_quat(self, q):
    """`car_angles` of the rotation: by its optical axis, ignoring roll."""
    return car_angles(rotations.quat_to_matrix(rotations.standardise_quat(q)))

  @override
  def poses_from_c2w(self, c2w):
    """`sphere_angles` of the camera centre (the camera is assumed to look at the origin)."""
    return sphere_angles(c2w)

  @override
  def pose_errors(self, pred, true):
    """ "rotation_error_deg" = 2 arccos|<q_hat, q>| of the `car_rotation`s, "azimuth_error_deg"
    (wrapped), "polar_error_deg"."""
    _, ang_hat = self.split_pose(pred)
    _, ang = self.split_pose(true)
    q_hat, q = self.orientation_quat(pred), self.orientation_quat(true)
    return {
      "rotation_error_deg": metrics.rotation_error_deg(q_hat, q),
      "azimuth_error_deg": metrics.wrapped_angle_error_deg(ang_hat[..., 0], ang[..., 0]),
      "polar_error_deg": jnp.rad2deg(metrics.abs_error(ang_hat[..., 1], ang[..., 1])),
    }


class SevenScenes(Setting):
  """Microsoft 7-Scenes: a hand-held camera in 6 DOF, position in [0, 4] x [0, 1.5] x [0, 3] m
  after re-basing, orientation as shifted static Euler angles; the regressor is a ResNet."""

  name = "seven_scenes"
  network = "resnet"
  real_test_description = "prepared test split (TestSplit sequences)"
  validation_note = "; the end of the TrainSplit trajectory"
  default_blocks = (4, 8)
  selection_metric = (("position_error", "median", 0.21), ("rotation_error_deg", "median", 7.92))

  ANGLE_SHIFT = (math.pi, math.pi / 2, math.pi)
  """(theta, phi, psi) minus the sxyz Euler angles of the camera rotation (the authors')."""

  @override
  def _dofs(self, o):
    return (
      o.linear("x", 0.0, 4.0),
      o.linear("y", 0.0, 1.5),
      o.linear("z", 0.0, 3.0),
      o.angle("theta"),
      o.angle("phi", high=math.pi, periodic=False),
      o.angle("psi"),
    )

  @override
  def angles_to_quat(self, angles):
    """The sxyz Euler rotation of the unshifted angles."""
    unshifted = angles - jnp.asarray(self.ANGLE_SHIFT, angles.dtype)
    return rotations.matrix_to_quat(rotations.euler_sxyz_to_matrix(unshifted))

  @override
  def angles_from_quat(self, q):
    q = rotations.standardise_quat(q)
    R = rotations.quat_to_matrix(q)
    return rotations.matrix_to_euler_sxyz(R) + jnp.asarray(self.ANGLE_SHIFT, q.dtype)

  @override
  def poses_from_c2w(self, c2w):
    """Translation (not re-based) and the shifted sxyz angles of the rotation projected onto
    SO(3), theta, psi in [0, 2 pi], phi in [0, pi] (the authors' `compress_dataset.py`)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    angles = rotations.matrix_to_euler_sxyz(rotations.orthonormalize(c2w[..., :3, :3]))
    return np.concatenate([c2w[..., :3, 3], angles + np.asarray(self.ANGLE_SHIFT)], axis=-1)

  def c2w_from_poses(self, poses: np.ndarray) -> np.ndarray:
    """Inverse of `poses_from_c2w`: (..., 6) -> (..., 4, 4) float64."""
    d = np.asarray(poses, dtype=np.float64)
    out = np.zeros(d.shape[:-1] + (4, 4))
    out[..., :3, :3] = rotations.euler_sxyz_to_matrix(d[..., 3:] - np.asarray(self.ANGLE_SHIFT))
    out[..., :3, 3] = d[..., :3]
    out[..., 3, 3] = 1.0
    return out

  @override
  def pose_errors(self, pred, true):
    """ "position_error" (m) and "rotation_error_deg" of the sxyz rotations."""
    pos_hat, _ = self.split_pose(pred)
    pos, _ = self.split_pose(true)
    q_hat, q = self.orientation_quat(pred), self.orientation_quat(true)
    return {
      "position_error": metrics.translation_error(pos_hat, pos),
      "rotation_error_deg": metrics.rotation_error_deg(q_hat, q),
    }


# ----------------------------------------------------------------------------------------------
# The registry.

SETTINGS: dict[str, Setting] = {}
"""name -> `Setting`, in registration order."""


def register(setting: Setting) -> Setting:
  """Adds a setting to `SETTINGS` (and returns it).

  Raises:
    ValueError: the name is taken.
  """
  if setting.name in SETTINGS:
    raise ValueError(f"a setting named {setting.name!r} is already registered")
  SETTINGS[setting.name] = setting
  return setting


def unregister(setting: Setting) -> None:
  """Removes a registered setting (a test's own)."""
  if SETTINGS.get(setting.name) is setting:
    del SETTINGS[setting.name]


GQN = register(GqnRooms())
CAR = register(ShapeNetCar())
GIBSON = register(GibsonArea())
SEVEN_SCENES = register(SevenScenes())


def names() -> tuple[str, ...]:
  """The registered settings' names."""
  return tuple(SETTINGS)


def get(setting: str | Setting) -> Setting:
  """The setting a config or a record names (a `Setting` is returned as it is).

  Raises:
    ValueError: no setting has that name.
  """
  if isinstance(setting, Setting):
    return setting
  try:
    return SETTINGS[setting]
  except (KeyError, TypeError):
    raise ValueError(f"unknown setting {setting!r}; choose one of {names()}") from None

"""Camera conditioning of a multi-view transformer, as interchangeable pieces.

A `CameraConditioning` maps the poses of views (..., V, P) (a setting's pose columns) to
`ViewCodes`: per-token features that join the token's input (absolute encodings) and/or per-view
transforms of attention (relative encodings, `camrep.models.relative_attention` eqs. R1-R2):

  NoCamera         no camera information (a control).
  Raymap           (a) absolute: the Pluecker coordinates (d, o x d) of every pixel's ray,
                   patchified (LVSM, Jin et al., ICLR 2025).
  GTA              (b) relative: D = the world-to-camera SE(3) matrix (4 x 4), or its rotation
                   (SO(3), 3 x 3) (Miyato et al., ICLR 2024).
  PRoPE            (c) relative: D = lift(K) T_cam_world, the camera's projective matrix (Li et
                   al., NeurIPS 2025, "Cameras as Relative Positional Encoding").
  LearnedAbsolute  (d) absolute: v(p), the learned pose vector of Zhu et al. (CVPR 2021, eqs.
                   1-6), on every token of the view.
  LearnedRelative  (e) relative: D = M(p)^T with M(p) = diag_l exp(B_l p_l), the learned
                   generators B_l of the same pose system (eq. 6) on the DOF coordinates.

Fixed encodings have no parameters; the learned ones keep theirs in a `camrep.pose` pytree (the
"rep" group, trained with the transformer; `pose_loss` adds the paper's rotation loss, eq. 9, when
its weight is set). The geometric encodings (a-c) see cameras through a `PoseCameras`, the
setting's map from pose columns to camera-to-world matrices and intrinsics (`RoomsCameras`,
`ObjectCameras`; `cameras_of_family`).

Images are (..., H, W, 3); a `PatchGrid` cuts them into N = (H / p) (W / p) patches of p x p
pixels in row-major order (`patchify`), the token order of every per-token array here.

Example: camrep's learned relative encoding in one's own attention layer. Its generators are
parameters to train with the layer's (`rep` below); the transform wraps any softmax attention.

  >>> import jax, jax.numpy as jnp
  >>> from camrep import pose as P
  >>> from camrep.models import camera_conditioning as cc, relative_attention as ra
  >>> spec = P.PoseSystemSpec(
  ...   dofs=(P.LinearDof("x", -1.0, 1.0, 0.1), P.LinearDof("y", -1.0, 1.0, 0.1),
  ...         P.AngularDof("yaw")), n_blocks=2, block_size=2)
  >>> enc = cc.LearnedRelative(spec)
  >>> rep = enc.init(jax.random.key(0))
  >>> poses = jnp.zeros((2, 3, 3))  # (batch, views, (x, y, yaw))
  >>> t = enc.view_codes(rep, poses, cc.PatchGrid(32, 32, 8)).transform
  >>> q = k = v = jnp.ones((2, 3, 16, 4, 32))  # (batch, views, patches, heads, head dim)
  >>> q, k, v = ra.encode_qkv(q, k, v, t, grid=(4, 4))
  >>> o = jax.nn.dot_product_attention(*(x.reshape(2, 48, 4, 32) for x in (q, k, v)))
  >>> o = ra.decode_out(o.reshape(2, 3, 16, 4, 32), t, grid=(4, 4))
  >>> o.shape
  (2, 3, 16, 4, 32)
"""

from __future__ import annotations

import abc
import dataclasses
import math

import flax.struct
import jax
import jax.numpy as jnp
from typing_extensions import override

from camrep import lie
from camrep import pose as P
from camrep.data.procedural import render
from camrep.models.relative_attention import ViewTransform

Array = jax.Array
Params = dict


# --------------------------------------------------------------------------------------------
# Patches.


@dataclasses.dataclass(frozen=True)
class PatchGrid:
  """Images of height x width pixels cut into patch x patch tiles.

  Attributes:
    height, width: image size in pixels (each a multiple of `patch`).
    patch: tile side p in pixels.
  """

  height: int
  width: int
  patch: int

  def __post_init__(self):
    if self.patch < 1 or self.height % self.patch or self.width % self.patch:
      raise ValueError(
        f"images of {self.height} x {self.width} pixels do not split into {self.patch} x "
        f"{self.patch} patches"
      )

  @property
  def rows(self) -> int:
    return self.height // self.patch

  @property
  def cols(self) -> int:
    return self.width // self.patch

  @property
  def shape(self) -> tuple[int, int]:
    """(rows, cols) of patches."""
    return (self.rows, self.cols)

  @property
  def n(self) -> int:
    """N, patches per image."""
    return self.rows * self.cols


def patchify(x: Array, grid: PatchGrid) -> Array:
  """(..., H, W, c) -> (..., N, p p c), patches row-major, pixels row-major inside a patch."""
  p, r, c = grid.patch, grid.rows, grid.cols
  x = x.reshape(*x.shape[:-3], r, p, c, p, x.shape[-1])
  x = jnp.swapaxes(x, -4, -3)  # (..., r, c, p, p, ch)
  return x.reshape(*x.shape[:-5], r * c, p * p * x.shape[-1])


def unpatchify(x: Array, grid: PatchGrid) -> Array:
  """Inverse of `patchify`: (..., N, p p c) -> (..., H, W, c)."""
  p, r, c = grid.patch, grid.rows, grid.cols
  ch = x.shape[-1] // (p * p)
  x = x.reshape(*x.shape[:-2], r, c, p, p, ch)
  x = jnp.swapaxes(x, -4, -3)  # (..., r, p, c, p, ch)
  return x.reshape(*x.shape[:-5], r * p, c * p, ch)


# --------------------------------------------------------------------------------------------
# Cameras of a setting's poses.


def intrinsics(grid: PatchGrid, fov_deg: float) -> Array:
  """K (3, 3) of the procedural renderer's camera (`render.Camera`): horizontal field of view
  `fov_deg`, square pixels, principal point at the image centre; pixel (i, j)'s centre is at
  (u, v) = (j + 1/2, i + 1/2)."""
  f = 0.5 * grid.width / math.tan(math.radians(fov_deg) / 2)
  return jnp.array(
    [[f, 0.0, grid.width / 2], [0.0, f, grid.height / 2], [0.0, 0.0, 1.0]], jnp.float32
  )


def invert_rigid(T: Array) -> Array:
  """Inverse of rigid transforms (..., 4, 4): [R^T, -R^T t; 0, 1]."""
  R, t = T[..., :3, :3], T[..., :3, 3]
  Rt = jnp.swapaxes(R, -1, -2)
  top = jnp.concatenate([Rt, -jnp.einsum("...ij,...j->...i", Rt, t)[..., None]], axis=-1)
  bottom = jnp.broadcast_to(jnp.eye(4, dtype=T.dtype)[3:], (*T.shape[:-2], 1, 4))
  return jnp.concatenate([top, bottom], axis=-2)


class PoseCameras(abc.ABC):
  """A setting's poses as pinhole cameras (the renderer's conventions,
  `camrep.data.procedural.render`: z-up world, OpenCV camera axes x right, y down, z forward).

  Implementations are frozen dataclasses (hashable: static arguments of jitted code) holding the
  setting's constants; `cameras_of_family` builds one from a procedural family.

  Attributes:
    fov_deg: horizontal field of view in degrees.
  """

  fov_deg: float

  @abc.abstractmethod
  def T_world_cam(self, poses: Array) -> Array:
    """Camera-to-world matrices (..., 4, 4) of poses (..., P)."""

  def K(self, grid: PatchGrid) -> Array:
    """Intrinsics (3, 3) in pixels of images of the grid's size (`intrinsics`)."""
    return intrinsics(grid, self.fov_deg)


@dataclasses.dataclass(frozen=True)
class RoomsCameras(PoseCameras):
  """Rooms poses (x, y, yaw): camera at (x, y, camera_height), yaw counter-clockwise from +x,
  fixed pitch (`camrep.data.procedural.families.RoomsFamily`)."""

  camera_height: float = 0.4
  pitch: float = -0.3
  fov_deg: float = 60.0

  @override
  def T_world_cam(self, poses):
    poses = jnp.asarray(poses, jnp.float32)
    h = jnp.full(poses.shape[:-1] + (1,), self.camera_height, poses.dtype)
    position = jnp.concatenate([poses[..., :2], h], axis=-1)
    return render.camera_from_yaw_pitch_roll(position, poses[..., 2], self.pitch)


@dataclasses.dataclass(frozen=True)
class ObjectCameras(PoseCameras):
  """Object (car) poses (azimuth, polar): camera at camera_distance (sin p cos a, sin p sin a,
  cos p) looking at the origin, +z up (`camrep.data.procedural.families.ObjectFamily`)."""

  camera_distance: float = 2.4
  fov_deg: float = 45.0

  @override
  def T_world_cam(self, poses):
    poses = jnp.asarray(poses, jnp.float32)
    az, pol = poses[..., 0], poses[..., 1]
    eye = self.camera_distance * jnp.stack(
      [jnp.sin(pol) * jnp.cos(az), jnp.sin(pol) * jnp.sin(az), jnp.cos(pol)], axis=-1
    )
    return render.look_at(eye, jnp.zeros_like(eye))


def cameras_of_family(family) -> PoseCameras:
  """The `PoseCameras` of a procedural family (`camrep.data.procedural.make_family`) from its
  config: rooms and object families.

  Raises:
    ValueError: another family (area cameras sit at a per-scene origin, scene6dof cameras in a
      per-scene aligned frame: their poses alone do not give the camera).
  """
  from camrep.data.procedural import families

  cfg = family.config
  if isinstance(family, families.RoomsFamily):
    return RoomsCameras(camera_height=cfg.camera_height, pitch=cfg.pitch, fov_deg=cfg.fov_deg)
  if isinstance(family, families.ObjectFamily):
    return ObjectCameras(camera_distance=cfg.camera_distance, fov_deg=cfg.fov_deg)
  raise ValueError(
    f"no pose-to-camera map for the {family.name!r} family: its cameras depend on the scene "
    "(rooms and object families only)"
  )


def plucker_rays(T_world_cam: Array, K: Array, grid: PatchGrid) -> Array:
  """Pluecker coordinates of the ray through every pixel centre: (..., H, W, 6) = (d, o x d).

  d = R K^{-1} (j + 1/2, i + 1/2, 1)^T / |.| (unit, world frame), o = t, the camera centre
  (T_world_cam = [R, t; 0, 1]). Independent of where o sits on the ray (o x d is the moment).

  Args:
    T_world_cam: (..., 4, 4) camera-to-world matrices.
    K: (..., 3, 3) intrinsics in pixels.
    grid: the image size.
  """
  i, j = jnp.meshgrid(
    jnp.arange(grid.height, dtype=T_world_cam.dtype),
    jnp.arange(grid.width, dtype=T_world_cam.dtype),
    indexing="ij",
  )
  uv1 = jnp.stack([j + 0.5, i + 0.5, jnp.ones_like(i)], axis=-1)  # (H, W, 3)
  d_cam = jnp.einsum("...ij,hwj->...hwi", jnp.linalg.inv(K.astype(T_world_cam.dtype)), uv1)
  d = jnp.einsum("...ij,...hwj->...hwi", T_world_cam[..., :3, :3], d_cam)
  d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
  o = jnp.broadcast_to(T_world_cam[..., None, None, :3, 3], d.shape)
  return jnp.concatenate([d, jnp.cross(o, d)], axis=-1)


# --------------------------------------------------------------------------------------------
# Conditionings.


@flax.struct.dataclass
class ViewCodes:
  """What a transformer receives about the cameras of V views.

  Attributes:
    features: (..., V, N, F) per-token features joined to the token's input (absolute
      encodings), or None.
    transform: per-view blocks of a relative encoding (..., V, k, b, b), or None.
    values: whether the relative encoding also transforms values and outputs (eq. R1).
  """

  features: Array | None = None
  transform: ViewTransform | None = None
  values: bool = flax.struct.field(pytree_node=False, default=True)


class CameraConditioning(abc.ABC):
  """How a multi-view transformer binds cameras to tokens: poses (..., V, P) -> `ViewCodes`.

  Implementations are frozen dataclasses (hashable: a static field of a Flax module or a static
  argument of jitted code).

  Attributes:
    learns: True when it has parameters (the learned pose system, the "rep" group).
    spec: the learned pose system it trains (None for the fixed encodings).
    vector_input: True when its codes are the pose system's per-DOF vectors v(p) on every token
      (`LearnedAbsolute.codes_of_vectors`): what the noise test of paper section 4.3 perturbs.
    relative: True when it acts inside attention (a `ViewTransform`), False when it adds token
      features (or nothing).
  """

  learns = False
  relative = False
  vector_input = False
  spec: P.PoseSystemSpec | None = None

  def init(self, key: Array) -> Params:
    """Initial parameters ({} for fixed encodings)."""
    del key
    return {}

  @abc.abstractmethod
  def view_codes(self, params: Params, poses: Array, grid: PatchGrid) -> ViewCodes:
    """The codes of views with poses (..., V, P) in images cut by `grid`.

    Args:
      params: what `init` returned.
      poses: (..., V, P) pose columns of the setting (radians, the dataset's length unit).
      grid: image size and patch size.
    """

  def pose_loss(self, key: Array, params: Params) -> tuple[Array, dict[str, Array]]:
    """The parameters' own loss and its terms (the learned encodings' rotation loss); zero."""
    del key, params
    return jnp.zeros((), jnp.float32), {}


@dataclasses.dataclass(frozen=True)
class NoCamera(CameraConditioning):
  """No camera information: zero-width token features, so context tokens carry their pixels and
  query tokens a learned constant (a control: what the transformer makes of the context alone)."""

  @override
  def view_codes(self, params, poses, grid):
    return ViewCodes(features=jnp.zeros((*poses.shape[:-1], grid.n, 0), jnp.float32))


@dataclasses.dataclass(frozen=True)
class Raymap(CameraConditioning):
  """(a) Pluecker raymap, absolute: token features = the patch's p x p Pluecker vectors
  (`plucker_rays`), F = 6 p^2 (LVSM's camera input).

  Attributes:
    cameras: the setting's pose-to-camera map.
  """

  cameras: PoseCameras

  def codes_from_cameras(self, T_world_cam: Array, K: Array, grid: PatchGrid) -> ViewCodes:
    """Codes of cameras (..., V, 4, 4) with intrinsics K (3, 3) or (..., V, 3, 3)."""
    return ViewCodes(features=patchify(plucker_rays(T_world_cam, K, grid), grid))

  @override
  def view_codes(self, params, poses, grid):
    return self.codes_from_cameras(self.cameras.T_world_cam(poses), self.cameras.K(grid), grid)


GTA_GROUPS = ("se3", "so3")


@dataclasses.dataclass(frozen=True)
class GTA(CameraConditioning):
  """(b) Geometric transform attention, relative, with a fixed representation of the camera:

    group="se3": D = T_cam_world (4 x 4), so D_i D_j^{-1} = T_cam_i,cam_j, camera j's pose in
      camera i's frame (PRoPE's "GTA" baseline);
    group="so3": D = R_cam_world (3 x 3), so D_i D_j^{-1} = R_i^T R_j (orthogonal; blind to
      translation).

  Scores and messages (eq. R2) are invariant to any rigid transform G of the world applied to
  all cameras (T_world_cam -> G T_world_cam). Translations enter in the world's length unit.

  Attributes:
    cameras: the setting's pose-to-camera map.
    group: "se3" or "so3".
    values: also transform values and outputs (eq. R1; GTA does).
  """

  cameras: PoseCameras
  group: str = "se3"
  values: bool = True

  relative = True

  def __post_init__(self):
    if self.group not in GTA_GROUPS:
      raise ValueError(f"GTA group must be one of {GTA_GROUPS}, got {self.group!r}")

  def codes_from_cameras(self, T_world_cam: Array, K: Array | None = None) -> ViewCodes:
    """Codes of cameras (..., V, 4, 4) (K unused)."""
    del K
    if self.group == "so3":
      R = T_world_cam[..., :3, :3]
      t = ViewTransform.orthogonal(jnp.swapaxes(R, -1, -2)[..., None, :, :])
    else:
      t = ViewTransform(
        D=invert_rigid(T_world_cam)[..., None, :, :], D_inv=T_world_cam[..., None, :, :]
      )
    return ViewCodes(transform=t, values=self.values)

  @override
  def view_codes(self, params, poses, grid):
    return self.codes_from_cameras(self.cameras.T_world_cam(poses))


def normalised_intrinsics(K: Array, grid: PatchGrid) -> Array:
  """PRoPE's image-size-free intrinsics: fx / W, fy / H, cx / W - 1/2, cy / H - 1/2 (..., 3, 3)."""
  W, H = grid.width, grid.height
  zero = jnp.zeros_like(K[..., 0, 0])
  one = jnp.ones_like(zero)
  rows = [
    jnp.stack([K[..., 0, 0] / W, zero, K[..., 0, 2] / W - 0.5], -1),
    jnp.stack([zero, K[..., 1, 1] / H, K[..., 1, 2] / H - 0.5], -1),
    jnp.stack([zero, zero, one], -1),
  ]
  return jnp.stack(rows, axis=-2)


def _lift(K: Array) -> Array:
  """(..., 3, 3) -> (..., 4, 4) diag(K, 1)."""
  out = jnp.zeros((*K.shape[:-2], 4, 4), K.dtype)
  return out.at[..., :3, :3].set(K).at[..., 3, 3].set(1.0)


@dataclasses.dataclass(frozen=True)
class PRoPE(CameraConditioning):
  """(c) PRoPE, relative: D = P = lift(K~) T_cam_world, the camera's image-from-world projective
  matrix with PRoPE's normalised intrinsics K~ (`normalised_intrinsics`), so

    s_ij = q_i^T (P_i P_j^{-1} (+) RoPE(patch_i - patch_j)) k_j                     (PRoPE eq. 8)

  with P_i P_j^{-1} = lift(K~_i) T_cam_i,cam_j lift(K~_j)^{-1}, the relative projective
  transformation between the two frustums; a 4 x 4 block tiled over half of each head, the
  patch RoPE on the other half (`relative_attention`). Invariant to any rigid transform of the
  world applied to all cameras.

  Attributes:
    cameras: the setting's pose-to-camera map.
    values: also transform values and outputs (eq. R1; PRoPE does).
  """

  cameras: PoseCameras
  values: bool = True

  relative = True

  def codes_from_cameras(self, T_world_cam: Array, K: Array, grid: PatchGrid) -> ViewCodes:
    """Codes of cameras (..., V, 4, 4) with pixel intrinsics K (3, 3) or (..., V, 3, 3)."""
    Kn = jnp.broadcast_to(
      normalised_intrinsics(K.astype(T_world_cam.dtype), grid), (*T_world_cam.shape[:-2], 3, 3)
    )
    Kn_inv = jnp.linalg.inv(Kn)
    D = _lift(Kn) @ invert_rigid(T_world_cam)
    D_inv = T_world_cam @ _lift(Kn_inv)
    return ViewCodes(
      transform=ViewTransform(D=D[..., None, :, :], D_inv=D_inv[..., None, :, :]),
      values=self.values,
    )

  @override
  def view_codes(self, params, poses, grid):
    return self.codes_from_cameras(self.cameras.T_world_cam(poses), self.cameras.K(grid), grid)


class _Learned(CameraConditioning):
  """The learned pose system of `spec` (`camrep.pose`) as parameters, with the rotation loss."""

  spec: P.PoseSystemSpec
  rotation_weight: float
  n_pairs: int

  learns = True

  @override
  def init(self, key):
    return P.init(key, self.spec)

  @override
  def pose_loss(self, key, params):
    """rotation_weight * sum_l L_rot,l (eq. 9; `camrep.pose.rotation_losses`, extra pairs
    only), and the terms {"rot_<dof>"}; zero when the weight is 0."""
    if not self.rotation_weight:
      return jnp.zeros((), jnp.float32), {}
    losses = P.rotation_losses(key, params, self.spec, n_pairs=self.n_pairs)
    terms = {f"rot_{name}": value for name, value in losses.items()}
    return self.rotation_weight * sum(losses.values()), terms


@dataclasses.dataclass(frozen=True)
class LearnedAbsolute(_Learned):
  """(d) camrep's learned representation, absolute: token features = v(p), the concatenated
  per-DOF vectors of the view's pose (eqs. 1-6, section 3.5: grid vector rotated by
  exp(B_l rest)), F = n_dofs d, the same on every token of the view.

  Attributes:
    spec: the pose system.
    mode: grid quantisation of `camrep.pose.embed` ("nearest"; "random" needs keys, left to the
      caller of `camrep.pose.embed`).
    rotation_weight: lambda_2 of eq. 9 (0: no rotation loss).
    n_pairs: extra pose pairs per DOF of the rotation loss.
  """

  spec: P.PoseSystemSpec
  mode: str = "nearest"
  rotation_weight: float = 0.0
  n_pairs: int = 64

  vector_input = True

  @override
  def view_codes(self, params, poses, grid):
    return self.codes_of_vectors(
      P.concat(P.embed(params, self.spec, poses, mode=self.mode), self.spec), grid
    )

  def codes_of_vectors(self, vectors: Array, grid: PatchGrid) -> ViewCodes:
    """Codes of views whose concatenated pose vectors are `vectors` (..., V, n_dofs d): the same
    vector on each of the view's N tokens (for vectors quantised or perturbed by the caller)."""
    return ViewCodes(
      features=jnp.broadcast_to(
        vectors[..., None, :], (*vectors.shape[:-1], grid.n, vectors.shape[-1])
      )
    )


@dataclasses.dataclass(frozen=True)
class LearnedRelative(_Learned):
  """(e) camrep's learned representation as a relative encoding: D = M(p)^T, with

    M(p) = diag_l exp(B_l p_l),    so    s_ij = q_i^T M(p_i)^T M(p_j) k_j
                                              = q_i^T diag_l exp(B_l (p_j,l - p_i,l)) k_j,

  B_l the DOF's learned skew-symmetric block-diagonal generator (eq. 6), p_l its pose column in
  physical units; k = n_dofs n_blocks blocks of block_size (DOF-major), orthogonal.

  Where the relative form is exact: always in the DOF coordinates. Each DOF's generator acts on
  its own sub-space and exp(B a)^T exp(B b) = exp(B (b - a)) (a one-parameter group commutes
  with itself), so scores and messages depend on the pose pair only through the coordinate
  differences p_j - p_i, and are unchanged by a global shift of all cameras along any DOF. That
  is invariance to the cameras' relative pose where the DOFs' motions commute: the translations
  x, y, z, and one rotation about a fixed axis (the car's azimuth, a rotation of the world about
  +z).

  Where it is an approximation: where the DOFs' motions do not commute, the coordinate
  difference is not the relative pose. Rooms: a rigid rotation of the world turns (x, y) and
  shifts yaw, which changes (dx, dy); car: the polar angle is a rotation about an axis that turns
  with the azimuth (R_i^T R_j = R_y(-pol_i) R_z(az_j - az_i) R_y(pol_j) is not a function of
  pol_j - pol_i); 6-DOF Euler angles likewise. Two camera pairs with the same relative pose then
  get different scores; GTA and PRoPE, built on the SE(3) matrices, do not have this defect.
  The polar (x, y) system (`camrep.dofs.PolarDof`) has direction-dependent generators B(theta)
  that do not commute, so it has no M(p) at all and is refused.

  Periodic angles: exp(B a) has period 2 pi only when every rotation frequency of B (the
  eigenvalues of i B) is an integer; learned generators need not be, so cameras on either side
  of the 0 / 2 pi seam are encoded as if nearly 2 pi apart unless training makes the spectrum
  integral. The rotation loss (eq. 9) ties the generators to a periodic grid of vectors and so
  pushes them that way (`rotation_weight`).

  Up to a fixed orthogonal change of basis, which the query and key projections absorb, M(p) is
  RoPE over the DOF coordinates with learned frequencies (B = Q Lambda Q^T, `lie.skew_schur`):
  what the transformer learns here is the frequencies.

  Attributes:
    spec: the pose system (its n_dofs * n_blocks * block_size dims must fit in a head; an exact
      exp_method, "spectral" or "expm", since the relative form needs M orthogonal).
    init_scale: std of the generators' free coefficients at init (N(0, init_scale^2): a 2 x 2
      block's frequency is its coefficient), in radians per unit of the DOF; the pose
      system's own init (1e-3) would start with no camera information at all.
    rotation_weight: lambda_2 of eq. 9 (0: no rotation loss).
    n_pairs: extra pose pairs per DOF of the rotation loss.
    values: also transform values and outputs (eq. R1).
  """

  spec: P.PoseSystemSpec
  init_scale: float = 2.0
  rotation_weight: float = 0.0
  n_pairs: int = 64
  values: bool = True

  relative = True

  def __post_init__(self):
    if self.spec.exp_method == "taylor2":
      raise ValueError(
        "LearnedRelative needs an exact exponential (exp_method 'spectral' or 'expm'): the "
        "relative form M(a)^T M(b) = M(b - a) fails for the truncated Taylor series 'taylor2'"
      )
    polar = [d.name for d in self.spec.dofs if d.width != 1]
    if polar:
      raise ValueError(
        f"LearnedRelative needs one generator per pose column; the polar DOF(s) {polar} have "
        "direction-dependent generators B(theta) that do not commute (use LinearDof x and y)"
      )

  @override
  def init(self, key):
    params = P.init(key, self.spec)
    for i, d in enumerate(self.spec.dofs):
      k = jax.random.fold_in(jax.random.fold_in(key, 1_000_003), i)
      params[d.name][P.GENERATOR] = lie.init_generator(
        k, (self.spec.n_blocks,), self.spec.block_size, stddev=self.init_scale
      )
    return params

  def rotations(self, params: Params, poses: Array) -> Array:
    """M(p) as blocks (..., n_dofs n_blocks, s, s), DOF-major."""
    blocks = []
    for d in self.spec.dofs:
      B = lie.skew(params[d.name][P.GENERATOR], block_size=self.spec.block_size)
      value = d.values(poses[..., self.spec.columns(d.name)])
      blocks.append(lie.exp_blocks(B, value, method=self.spec.exp_method))
    return jnp.concatenate(blocks, axis=-3)

  @override
  def view_codes(self, params, poses, grid):
    M = self.rotations(params, jnp.asarray(poses))
    return ViewCodes(
      transform=ViewTransform(D=jnp.swapaxes(M, -1, -2), D_inv=M), values=self.values
    )


def columnwise(spec: P.PoseSystemSpec) -> P.PoseSystemSpec:
  """The pose system with one DOF per pose column: each DOF of several columns (the polar (x, y)
  DOF of rooms) becomes one `LinearDof` per column on its range at its spacing; the others are
  kept. `LearnedRelative` needs this form (one generator per coordinate)."""
  out = []
  for d in spec.dofs:
    if d.width == 1:
      out.append(d)
    else:
      out.extend(P.LinearDof(c, d.low, d.high, d.spacing) for c in d.column_names)
  return dataclasses.replace(spec, dofs=tuple(out))

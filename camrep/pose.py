"""The pose representation system of Zhu et al. (CVPR 2021), section 3, as pure parameter pytrees.

Every degree of freedom (DOF) of the camera gets learned d-dimensional vectors on a grid over its
range (d = n_blocks * block_size). The vector of a continuous value is the nearest (or, during
training, a random neighbouring) grid vector rotated by exp(B * rest), where B is the DOF's
skew-symmetric block-diagonal generator and rest the offset from the grid point in physical units
(sections 3.1, 3.3, 3.5). 2-D position may instead use the polar system of section 3.2: one vector
for (x, y) and a generator B(theta) that depends on the direction of the move.

A system is described by a static, hashable `PoseSystemSpec` (a tuple of DOF specs) and its
parameters are a plain nested dict of arrays:

  {dof.name: {"grid": (n_grid_points, d), "B": generator params, ...}}

Poses are arrays (..., pose_dim) whose columns follow the spec's DOFs in order (a polar DOF takes
two columns, x then y); angles are in radians, positions in the dataset's unit.

Entry points: `init`, `embed` (pose -> vectors), `rotation_losses` (eqs. 9 and 9.2),
`direction_loss` (L_rot,theta of eq. 9.2), `decode` (eq. 12 plus sub-grid refinement), `gram`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from camrep import lie

Array = jax.Array
Params = dict

QUANTISATION_MODES = ("nearest", "random", "floor")
TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------------------------
# Specs.


@dataclasses.dataclass(frozen=True)
class LinearDof:
  """A translation-like DOF on a non-periodic grid low, low + spacing, ..., high.

  Values beyond the range use the end grid point and extrapolate (the authors' clipping).
  """

  name: str
  low: float
  high: float
  spacing: float

  @property
  def width(self) -> int:
    return 1

  @property
  def n_grid(self) -> int:
    return int(round((self.high - self.low) / self.spacing)) + 1

  @property
  def periodic(self) -> bool:
    return False


@dataclasses.dataclass(frozen=True)
class AngularDof:
  """An angle DOF (radians).

  periodic=True (default, camrep's fix): N = (high - low) / spacing grid vectors with index
  taken mod N, so 0 and 360 degrees share one vector and moves across the seam wrap.
  periodic=False: the authors' grid with separate vectors at both ends (37 for 0..360 degrees at
  10 degrees), clipped at the ends; `n_grid_override` reproduces their 7-Scenes grids (36 vectors
  for 0..360, the last 10 degrees extrapolated).
  """

  name: str
  spacing: float = math.pi / 18
  low: float = 0.0
  high: float = TWO_PI
  periodic: bool = True
  n_grid_override: int | None = None

  @property
  def width(self) -> int:
    return 1

  @property
  def n_grid(self) -> int:
    if self.n_grid_override is not None:
      return self.n_grid_override
    n = int(round((self.high - self.low) / self.spacing))
    return n if self.periodic else n + 1


@dataclasses.dataclass(frozen=True)
class PolarDof:
  """2-D position with the polar generator B(theta) of section 3.2 (eqs. 4-5).

  Grid: (L + 1) x (L + 1) vectors over [low, high]^2 with L = (high - low) / spacing, flat index
  gx * (L + 1) + gy (digest 1.4).

  variant="binned" (the authors' code): B(theta) is a table of `n_directions` free generators,
  theta rounded to the nearest bin (mod n_directions: the authors' index could reach
  n_directions, out of range), softly tied by `direction_loss` (B_{j+D} ~ exp(C D dtheta) B_j).
  variant="continuous" (camrep): B(theta) = exp(C theta) B0 exp(-C theta), exact conjugation, so
  no bins and no direction loss.

  block_norm=True: each block of a grid vector has norm 1 / n_blocks as in the authors' code
  (whole vector 1/sqrt(n_blocks)); False: unit vectors like the other DOFs (the paper's text).
  pair_radius: the largest extra-pair move for the rotation loss, in grid units (GQN 2.0,
  Gibson 2.2).
  """

  name: str = "xy"
  low: float = -1.0
  high: float = 1.0
  spacing: float = 0.1
  n_directions: int = 144
  variant: str = "binned"
  block_norm: bool = True
  pair_radius: float = 2.0

  @property
  def width(self) -> int:
    return 2

  @property
  def n_side(self) -> int:
    return int(round((self.high - self.low) / self.spacing)) + 1

  @property
  def n_grid(self) -> int:
    return self.n_side**2

  @property
  def periodic(self) -> bool:
    return False


Dof = LinearDof | AngularDof | PolarDof


@dataclasses.dataclass(frozen=True)
class PoseSystemSpec:
  """A whole pose system: its DOFs, vector size and how exp(B t) is computed.

  Attributes:
    dofs: the DOF specs, in pose-column order.
    n_blocks, block_size: d = n_blocks * block_size (GQN/car/Gibson 6 x 16, 7-Scenes 4 x 8).
    exp_method: one of `lie.EXP_METHODS` ("taylor2" is the authors').
    n_steps: Taylor steps for exp_method="taylor2" (paper eq. 6; authors 1).
    init_stddev: std of the N(0, s^2) initialisation of grid vectors and generators (0.001).
    direction_loss_scale: factor of L_rot,theta (the authors' code multiplies by 36 / 720).
  """

  dofs: tuple[Dof, ...]
  n_blocks: int = 6
  block_size: int = 16
  exp_method: str = "spectral"
  n_steps: int = 1
  init_stddev: float = 1e-3
  direction_loss_scale: float = 36.0 / 720.0

  def __post_init__(self):
    names = [d.name for d in self.dofs]
    if len(set(names)) != len(names):
      raise ValueError(f"DOF names must be unique, got {names}")
    if self.exp_method not in lie.EXP_METHODS:
      raise ValueError(f"exp_method must be one of {lie.EXP_METHODS}, got {self.exp_method!r}")
    for d in self.dofs:
      if not isinstance(d, LinearDof | AngularDof | PolarDof):
        raise TypeError(f"unknown DOF spec {d!r}")
      if d.n_grid < 2:
        raise ValueError(f"DOF {d.name!r} needs at least 2 grid points, has {d.n_grid}")
      if isinstance(d, PolarDof) and d.variant not in ("binned", "continuous"):
        raise ValueError(f"PolarDof.variant must be 'binned' or 'continuous', got {d.variant!r}")

  @property
  def dim(self) -> int:
    """d, the size of one DOF's vector."""
    return self.n_blocks * self.block_size

  @property
  def pose_dim(self) -> int:
    """Number of pose columns."""
    return sum(d.width for d in self.dofs)

  @property
  def names(self) -> tuple[str, ...]:
    return tuple(d.name for d in self.dofs)

  def dof(self, name: str) -> Dof:
    for d in self.dofs:
      if d.name == name:
        return d
    raise KeyError(f"no DOF named {name!r}; this system has {self.names}")

  def columns(self, name: str) -> slice:
    """The pose columns of DOF `name`."""
    start = 0
    for d in self.dofs:
      if d.name == name:
        return slice(start, start + d.width)
      start += d.width
    raise KeyError(f"no DOF named {name!r}; this system has {self.names}")


# --------------------------------------------------------------------------------------------
# Parameters.


def init(key: Array, spec: PoseSystemSpec, *, dtype=jnp.float32) -> Params:
  """Initial parameters: grid vectors and generators i.i.d. N(0, init_stddev^2) (digest 1.1-1.2).

  Returns:
    {name: {"grid": (n_grid, d), "B": (n_blocks, s(s-1)/2)}} for linear and angular DOFs;
    polar binned: {"grid", "B": (n_directions, n_blocks, s(s-1)/2), "C": (n_blocks, ...)};
    polar continuous: {"grid", "B0": (n_blocks, ...), "C": (n_blocks, ...)}.
  """
  params = {}
  std = spec.init_stddev
  for i, d in enumerate(spec.dofs):
    kg, kb, kc = jax.random.split(jax.random.fold_in(key, i), 3)
    grid = std * jax.random.normal(kg, (d.n_grid, spec.dim), dtype)
    gen = lambda k, shape: lie.init_generator(k, shape, spec.block_size, stddev=std, dtype=dtype)
    if isinstance(d, PolarDof):
      if d.variant == "binned":
        p = {
          "grid": grid,
          "B": gen(kb, (d.n_directions, spec.n_blocks)),
          "C": gen(kc, (spec.n_blocks,)),
        }
      else:
        p = {"grid": grid, "B0": gen(kb, (spec.n_blocks,)), "C": gen(kc, (spec.n_blocks,))}
    else:
      p = {"grid": grid, "B": gen(kb, (spec.n_blocks,))}
    params[d.name] = p
  return params


def grid_vectors(params: Params, spec: PoseSystemSpec, name: str) -> Array:
  """The normalised grid vectors of one DOF, (n_grid, d) (normalised in every forward pass).

  Unit norm, or for a polar DOF with block_norm each block scaled to norm 1 / n_blocks.
  """
  d = spec.dof(name)
  return _normalise(params[name]["grid"], spec, block_norm=isinstance(d, PolarDof) and d.block_norm)


def _normalise(v: Array, spec: PoseSystemSpec, *, block_norm: bool) -> Array:
  eps = 1e-12
  if block_norm:
    vb = v.reshape(*v.shape[:-1], spec.n_blocks, spec.block_size)
    nb = jnp.sqrt(jnp.sum(vb * vb, axis=-1, keepdims=True) + eps)
    return (vb / (nb * spec.n_blocks)).reshape(v.shape)
  return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True) + eps)


def generator_blocks(params: Params, spec: PoseSystemSpec, name: str) -> dict[str, Array]:
  """The DOF's generators as skew blocks: {"B": (..., n_blocks, s, s), ...} for each generator."""
  return {
    k: lie.skew(v, block_size=spec.block_size) for k, v in params[name].items() if k != "grid"
  }


# --------------------------------------------------------------------------------------------
# Embedding continuous poses (section 3.5).


def _quantise(g: Array, mode: str, key: Array | None) -> Array:
  """Grid index (float, before clipping/wrapping) for grid coordinates g (digest 1.3)."""
  if mode == "nearest":
    return jnp.round(g)
  if mode == "floor":
    return jnp.floor(g)
  if mode == "random":
    if key is None:
      raise ValueError("mode='random' (random lower/upper neighbour) needs a PRNG key")
    return jnp.floor(g) + jax.random.bernoulli(key, 0.5, g.shape).astype(g.dtype)
  raise ValueError(f"unknown quantisation mode {mode!r}; choose one of {QUANTISATION_MODES}")


def _safe_polar(disp: Array) -> tuple[Array, Array]:
  """(..., 2) displacement -> (r, direction in [0, 2 pi)), with finite gradients at 0."""
  sq = jnp.sum(disp * disp, axis=-1)
  tiny = sq < jnp.finfo(disp.dtype).tiny ** 0.5
  dx = jnp.where(tiny, 1.0, disp[..., 0])
  dy = jnp.where(tiny, 0.0, disp[..., 1])
  r = jnp.where(tiny, 0.0, jnp.sqrt(jnp.where(tiny, 1.0, sq)))
  return r, jnp.mod(jnp.arctan2(dy, dx), TWO_PI)


def _rotate_polar(params: Params, spec: PoseSystemSpec, d: PolarDof, disp: Array, v: Array):
  """exp(B(theta) r) v for displacements (..., 2) in physical units (eq. 4, exp form)."""
  r, theta = _safe_polar(disp)
  method, n_steps = spec.exp_method, spec.n_steps
  if d.variant == "binned":
    B = lie.skew(params[d.name]["B"], block_size=spec.block_size)  # (n_dir, n_b, s, s)
    j = jnp.mod(jnp.round(theta / (TWO_PI / d.n_directions)).astype(jnp.int32), d.n_directions)
    return lie.apply_exp_blocks(B, r, v, method=method, n_steps=n_steps, index=j)
  C = lie.skew(params[d.name]["C"], block_size=spec.block_size)
  B0 = lie.skew(params[d.name]["B0"], block_size=spec.block_size)
  # exp(r e^{C th} B0 e^{-C th}) = e^{C th} e^{r B0} e^{-C th}.
  u = lie.apply_exp_blocks(C, -theta, v, method=method, n_steps=n_steps)
  u = lie.apply_exp_blocks(B0, r, u, method=method, n_steps=n_steps)
  return lie.apply_exp_blocks(C, theta, u, method=method, n_steps=n_steps)


def rotate(params: Params, spec: PoseSystemSpec, name: str, delta: Array, v: Array) -> Array:
  """Move DOF vectors by a pose shift: exp(B_l delta) v (eq. 6), or the polar eq. 4.

  Args:
    delta: (...) shift in physical units, or (..., 2) displacement for a polar DOF.
    v: (..., d) vectors of DOF `name`.

  Returns:
    (..., d).
  """
  d = spec.dof(name)
  if isinstance(d, PolarDof):
    return _rotate_polar(params, spec, d, delta, v)
  B = lie.skew(params[name]["B"], block_size=spec.block_size)
  return lie.apply_exp_blocks(B, delta, v, method=spec.exp_method, n_steps=spec.n_steps)


def embed_dof(
  params: Params,
  spec: PoseSystemSpec,
  name: str,
  value: Array,
  *,
  mode: str = "nearest",
  key: Array | None = None,
) -> Array:
  """Vector of one DOF at continuous values: exp(B rest) v_grid[k] (section 3.5, digest 1.3).

  Args:
    value: (...) values, or (..., 2) positions for a polar DOF, in physical units.
    mode: "nearest" (the paper), "random" (random lower/upper neighbour, the authors' training
      rule; needs `key`) or "floor" (the authors' inference rule).

  Returns:
    (..., d) vectors.
  """
  d = spec.dof(name)
  value = jnp.asarray(value, params[name]["grid"].dtype)
  grid = grid_vectors(params, spec, name)
  g = (value - d.low) / d.spacing
  if isinstance(d, PolarDof):
    if value.shape[-1] != 2:
      raise ValueError(f"polar DOF {name!r} takes (..., 2) positions, got {value.shape}")
    k = jnp.clip(_quantise(g, mode, key), 0, d.n_side - 1)
    rest = (g - k) * d.spacing
    ki = k.astype(jnp.int32)
    v = grid[ki[..., 0] * d.n_side + ki[..., 1]]
    return _rotate_polar(params, spec, d, rest, v)
  if d.periodic:
    n = d.n_grid
    g = jnp.mod(g, n)
    k = _quantise(g, mode, key)
    rest = (g - k) * d.spacing
    ki = jnp.mod(k.astype(jnp.int32), n)
  else:
    k = jnp.clip(_quantise(g, mode, key), 0, d.n_grid - 1)
    rest = (g - k) * d.spacing
    ki = k.astype(jnp.int32)
  return rotate(params, spec, name, rest, grid[ki])


def embed(
  params: Params,
  spec: PoseSystemSpec,
  pose: Array,
  *,
  mode: str = "nearest",
  key: Array | None = None,
) -> dict[str, Array]:
  """Vectors of every DOF for poses (..., pose_dim): {name: (..., d)}.

  With mode="random" each DOF (and each pose) draws its own lower/upper neighbour.
  """
  pose = jnp.asarray(pose)
  if pose.shape[-1] != spec.pose_dim:
    raise ValueError(f"pose has {pose.shape[-1]} columns, this system takes {spec.pose_dim}")
  out = {}
  for i, d in enumerate(spec.dofs):
    cols = pose[..., spec.columns(d.name)]
    value = cols if isinstance(d, PolarDof) else cols[..., 0]
    k = None if key is None else jax.random.fold_in(key, i)
    out[d.name] = embed_dof(params, spec, d.name, value, mode=mode, key=k)
  return out


def concat(vectors: Mapping[str, Array], spec: PoseSystemSpec) -> Array:
  """Concatenate per-DOF vectors in spec order: (..., n_dofs * d), the decoder's pose input."""
  return jnp.concatenate([vectors[n] for n in spec.names], axis=-1)


def split(v: Array, spec: PoseSystemSpec) -> dict[str, Array]:
  """Inverse of `concat`: (..., n_dofs * d) -> {name: (..., d)}."""
  if v.shape[-1] != len(spec.dofs) * spec.dim:
    raise ValueError(f"expected {len(spec.dofs) * spec.dim} columns, got {v.shape[-1]}")
  return {n: v[..., i * spec.dim : (i + 1) * spec.dim] for i, n in enumerate(spec.names)}


# --------------------------------------------------------------------------------------------
# Rotation losses (eqs. 9 and 9.2) and pair sampling (digest 1.5).


def wrap_angle(x: Array) -> Array:
  """Wrap angles to [-pi, pi)."""
  return jnp.mod(x + math.pi, TWO_PI) - math.pi


def pose_delta(spec: PoseSystemSpec, pose0: Array, pose1: Array) -> Array:
  """pose1 - pose0 per column, with periodic angles wrapped to [-pi, pi) (camrep's fix: the
  authors' raw difference turns a pair straddling 0/360 degrees into a ~2 pi move)."""
  delta = pose1 - pose0
  cols = []
  for d in spec.dofs:
    c = delta[..., spec.columns(d.name)]
    cols.append(wrap_angle(c) if isinstance(d, AngularDof) and d.periodic else c)
  return jnp.concatenate(cols, axis=-1)


def sample_pairs(key: Array, spec: PoseSystemSpec, name: str, n: int) -> tuple[Array, Array]:
  """Extra pose pairs for the rotation loss of DOF `name`, in physical units (digest 1.5).

  Non-periodic DOFs (the authors' recipe, A = n_grid - 1 intervals): a0 ~ U(0, A - 1),
  a1 = min(a0 + U(0.5, 1), A) grid units. Periodic angles: a0 ~ U(0, N), a1 = a0 +/- U(0.5, 1),
  wrapped (so the seam is trained too). Polar: p0 ~ U(1, L - 1)^2, direction uniform (binned
  variant: one of n_directions bins, fixed to exclude the out-of-range index), r ~
  U(0, pair_radius), p1 = clip(p0 + r (cos, sin), 0, L).

  Returns:
    (value0, value1): (n,) each, or (n, 2) for a polar DOF.
  """
  d = spec.dof(name)
  k0, k1, k2 = jax.random.split(key, 3)
  if isinstance(d, PolarDof):
    L = d.n_side - 1
    p0 = jax.random.uniform(k0, (n, 2), minval=1.0, maxval=L - 1.0)
    if d.variant == "binned":
      direction = jax.random.randint(k1, (n,), 0, d.n_directions) * (TWO_PI / d.n_directions)
    else:
      direction = jax.random.uniform(k1, (n,), maxval=TWO_PI)
    r = jax.random.uniform(k2, (n,), maxval=d.pair_radius)
    step = r[:, None] * jnp.stack([jnp.cos(direction), jnp.sin(direction)], -1)
    p1 = jnp.clip(p0 + step, 0.0, L)
    return d.low + p0 * d.spacing, d.low + p1 * d.spacing
  step = jax.random.uniform(k1, (n,), minval=0.5, maxval=1.0)
  if d.periodic:
    a0 = jax.random.uniform(k0, (n,), maxval=d.n_grid)
    sign = jnp.where(jax.random.bernoulli(k2, 0.5, (n,)), 1.0, -1.0)
    a1 = a0 + sign * step
  else:
    A = d.n_grid - 1
    a0 = jax.random.uniform(k0, (n,), maxval=A - 1.0)
    a1 = jnp.minimum(a0 + step, A)
  return d.low + a0 * d.spacing, d.low + a1 * d.spacing


def dof_rotation_loss(
  params: Params,
  spec: PoseSystemSpec,
  name: str,
  value0: Array,
  value1: Array,
  *,
  mode: str = "random",
  key: Array | None = None,
) -> Array:
  """L_rot for one DOF over given pairs (eq. 9; polar: L_rot,x of eq. 9.2).

  mean over pairs of ||v(l1) - exp(B (l1 - l0)) v(l0)||^2, with the move wrapped for periodic
  angles and taken after clipping for polar pairs.

  Args:
    value0, value1: (n,) values, or (n, 2) positions for a polar DOF.

  Returns:
    scalar loss.
  """
  d = spec.dof(name)
  k0 = k1 = None
  if key is not None:
    k0, k1 = jax.random.split(key)
  v0 = embed_dof(params, spec, name, value0, mode=mode, key=k0)
  v1 = embed_dof(params, spec, name, value1, mode=mode, key=k1)
  delta = value1 - value0
  if isinstance(d, AngularDof) and d.periodic:
    delta = wrap_angle(delta)
  moved = rotate(params, spec, name, delta, v0)
  return jnp.mean(jnp.sum((moved - v1) ** 2, axis=-1))


def rotation_losses(
  key: Array,
  params: Params,
  spec: PoseSystemSpec,
  *,
  n_pairs: int,
  mode: str = "random",
  data_pairs: tuple[Array, Array] | None = None,
) -> dict[str, Array]:
  """The rotation loss of every DOF, {name: scalar} (eqs. 9 and 9.2).

  Each DOF gets `n_pairs` sampled extra pairs (`sample_pairs`). With `data_pairs` (poses of real
  image pairs, (m, pose_dim) each), the loss is 0.5 (data-pair term) + 0.5 (extra-pair term), as
  in the authors' car, Gibson and 7-Scenes code; GQN uses extra pairs only. Weights (lambda_2,
  lambda_3) are applied by the caller.
  """
  losses = {}
  for i, d in enumerate(spec.dofs):
    kd = jax.random.fold_in(key, i)
    ks, ke, kdata = jax.random.split(kd, 3)
    value0, value1 = sample_pairs(ks, spec, d.name, n_pairs)
    loss = dof_rotation_loss(params, spec, d.name, value0, value1, mode=mode, key=ke)
    if data_pairs is not None:
      p0, p1 = data_pairs
      cols = spec.columns(d.name)
      x0, x1 = p0[..., cols], p1[..., cols]
      if not isinstance(d, PolarDof):
        x0, x1 = x0[..., 0], x1[..., 0]
      loss = 0.5 * loss + 0.5 * dof_rotation_loss(
        params, spec, d.name, x0, x1, mode=mode, key=kdata
      )
    losses[d.name] = loss
  return losses


def direction_loss(params: Params, spec: PoseSystemSpec, name: str, *, max_shift: int = 5):
  """L_rot,theta of eq. 9.2 for a binned polar DOF: B(theta + D) ~ exp(C D) B(theta).

  As the authors' code (digest 1.4): every bin j and shift D in 1..max_shift (720 combinations),
  left multiplication exp(C D dtheta) B_j - B_{(j + D) mod n}, squared and summed over matrix
  entries, averaged over combinations, times `spec.direction_loss_scale` (their 36 / 720).
  Blocks are multiplied block-wise. The continuous variant satisfies the relation exactly, so
  there is no such loss for it (returns 0).
  """
  d = spec.dof(name)
  if not isinstance(d, PolarDof):
    raise ValueError(f"direction_loss is for polar DOFs; {name!r} is {type(d).__name__}")
  if d.variant == "continuous":
    return jnp.zeros((), params[name]["grid"].dtype)
  B = lie.skew(params[name]["B"], block_size=spec.block_size)  # (n, n_b, s, s)
  C = lie.skew(params[name]["C"], block_size=spec.block_size)  # (n_b, s, s)
  shifts = jnp.arange(1, max_shift + 1)
  dtheta = TWO_PI / d.n_directions
  R = lie.exp_blocks(C, shifts * dtheta, method=spec.exp_method, n_steps=spec.n_steps)
  RB = jnp.einsum("kbij,nbjl->nkbil", R, B)  # (n, max_shift, n_b, s, s)
  target = B[(jnp.arange(d.n_directions)[:, None] + shifts[None, :]) % d.n_directions]
  sq = jnp.sum((RB - target) ** 2, axis=(-3, -2, -1))
  return spec.direction_loss_scale * jnp.mean(sq)


# --------------------------------------------------------------------------------------------
# Decoding (eq. 12) with sub-grid refinement.


def candidates(spec: PoseSystemSpec, name: str, resolution: float | None = None) -> Array:
  """A dense candidate list over the DOF's range for arg-min decoding.

  Default resolution: spacing / 40 for angles (0.25 degrees at 10 degree spacing, the authors'
  test setting), spacing / 4 for positions (their 0.25 grid-unit position list).

  Returns:
    (K,) values, or (K, 2) positions for a polar DOF.
  """
  d = spec.dof(name)
  if resolution is None:
    resolution = d.spacing / (40.0 if isinstance(d, AngularDof) else 4.0)
  if isinstance(d, AngularDof) and d.periodic:
    n = int(round((d.high - d.low) / resolution))
    return jnp.asarray(d.low + resolution * np.arange(n), jnp.float32)
  n = int(math.floor((d.high - d.low) / resolution + 1e-6)) + 1
  axis = d.low + resolution * np.arange(n)
  if isinstance(d, AngularDof):
    # The authors decode non-periodic angles over [low, high) (360 is 0 degrees).
    axis = axis[axis < d.high - 1e-9] if math.isclose(d.high - d.low, TWO_PI) else axis
  if isinstance(d, PolarDof):
    gx, gy = np.meshgrid(axis, axis, indexing="ij")
    return jnp.asarray(np.stack([gx.ravel(), gy.ravel()], -1), jnp.float32)
  return jnp.asarray(axis, jnp.float32)


def decode_dof(
  params: Params,
  spec: PoseSystemSpec,
  name: str,
  v_hat: Array,
  *,
  resolution: float | None = None,
  refine_steps: int = 4,
  mode: str = "nearest",
  cands: Array | None = None,
) -> Array:
  """Decode vectors of one DOF back to values (eq. 12), then refine below the candidate spacing.

  1. arg-min over candidates of ||v(l) - v_hat||^2 = |c|^2 - 2 <v_hat, c> + const.
  2. `refine_steps` damped Gauss-Newton steps on ||v(l) - v_hat||^2 from the arg-min, each move
     limited to the candidate spacing; the refined value is kept only where it lowers the
     residual. So decoding error is not bounded by the candidate spacing.

  Args:
    v_hat: (..., d) predicted vectors.
    cands: optional candidate values (K,) / (K, 2); default `candidates(spec, name, resolution)`.

  Returns:
    (...) values, or (..., 2) positions for a polar DOF.
  """
  d = spec.dof(name)
  if cands is None:
    cands = candidates(spec, name, resolution)
  if resolution is None:
    resolution = d.spacing / (40.0 if isinstance(d, AngularDof) else 4.0)
  cvec = embed_dof(params, spec, name, cands, mode=mode)  # (K, d)
  score = jnp.sum(cvec * cvec, -1) - 2.0 * jnp.einsum("...d,kd->...k", v_hat, cvec)
  best = cands[jnp.argmin(score, axis=-1)]
  if refine_steps == 0:
    return best
  f = lambda x: embed_dof(params, spec, name, x, mode=mode)
  polar = isinstance(d, PolarDof)

  def residual(x, vh):
    return jnp.sum((f(x) - vh) ** 2)

  def refine_one(x0, vh):
    def body(_, x):
      r = f(x) - vh
      if polar:
        J = jax.jacfwd(f)(x)  # (d, 2)
        H = J.T @ J + 1e-9 * jnp.eye(2, dtype=J.dtype)
        step = -jnp.linalg.solve(H, J.T @ r)
      else:
        J = jax.jacfwd(f)(x)  # (d,)
        step = -(J @ r) / (J @ J + 1e-9)
      return x + jnp.clip(step, -resolution, resolution)

    x = jax.lax.fori_loop(0, refine_steps, body, x0)
    x = jnp.clip(x, x0 - resolution, x0 + resolution)
    better = residual(x, vh) < residual(x0, vh)
    return jnp.where(better, x, x0)

  batch = v_hat.shape[:-1]
  flat_best = best.reshape(-1, *best.shape[len(batch) :])
  flat_v = v_hat.reshape(-1, v_hat.shape[-1])
  out = jax.vmap(refine_one)(flat_best, flat_v).reshape(best.shape)
  if isinstance(d, AngularDof) and d.periodic:
    out = d.low + jnp.mod(out - d.low, d.high - d.low)
  return out


def decode(
  params: Params,
  spec: PoseSystemSpec,
  vectors: Mapping[str, Array] | Array,
  *,
  refine_steps: int = 4,
  mode: str = "nearest",
  resolution: Mapping[str, float] | None = None,
) -> Array:
  """Decode pose vectors to poses (..., pose_dim): every DOF independently, as eq. 12.

  Args:
    vectors: {name: (..., d)} or the concatenated (..., n_dofs * d).
    refine_steps: Gauss-Newton refinement steps (0: plain arg-min, the authors' decoder).
    resolution: optional candidate spacing per DOF name.
  """
  if not isinstance(vectors, Mapping):
    vectors = split(jnp.asarray(vectors), spec)
  cols = []
  for d in spec.dofs:
    res = None if resolution is None else resolution.get(d.name)
    x = decode_dof(
      params, spec, d.name, vectors[d.name], resolution=res, refine_steps=refine_steps, mode=mode
    )
    cols.append(x if isinstance(d, PolarDof) else x[..., None])
  return jnp.concatenate(cols, axis=-1)


# --------------------------------------------------------------------------------------------
# Inspection.


def gram(params: Params, spec: PoseSystemSpec, name: str, *, values: Array | None = None) -> Array:
  """Inner-product (Gram) matrix V V^T of a DOF's vectors over its range (supplement figure).

  Args:
    values: (K,) values (or (K, 2) positions); default: candidates at 1 degree for angles, the
      grid points for positions.

  Returns:
    (K, K).
  """
  d = spec.dof(name)
  if values is None:
    res = math.pi / 180 if isinstance(d, AngularDof) else d.spacing
    values = candidates(spec, name, res)
  V = embed_dof(params, spec, name, values, mode="nearest")
  return V @ V.T


def grid_std(params: Params, spec: PoseSystemSpec, name: str) -> Array:
  """beta_i: the std of element i over the DOF's normalised grid vectors, (d,) (section 4.3)."""
  return jnp.std(grid_vectors(params, spec, name), axis=0)

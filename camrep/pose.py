"""The pose representation system of Zhu et al. (CVPR 2021), section 3, as pure parameter pytrees.

Every degree of freedom (DOF) of the camera gets learned d-dimensional vectors on a grid over its
range (d = n_blocks * block_size). The vector of a continuous value is the nearest (or, during
training, a random neighbouring) grid vector rotated by exp(B * rest), where B is the DOF's
skew-symmetric block-diagonal generator and rest the offset from the grid point in physical units
(sections 3.1, 3.3, 3.5). 2-D position may instead use the polar system of section 3.2: one vector
for (x, y) and a generator B(theta) that depends on the direction of the move.

A system is described by a static, hashable `PoseSystemSpec` (a tuple of DOF specs) and its
parameters are a plain nested dict of arrays:

  {dof.name: {"grid": (n_grid_points, d), "generator_coeffs": (n_blocks, s(s-1)/2), ...}}

where "*_coeffs" entries are the free coefficients of skew-symmetric blocks (`lie.skew` makes
the matrices B, C of the paper). Each DOF kind (`LinearDof`, `AngularDof`, `PolarDof`)
implements the `Dof` interface: its columns, grid index, rotation, range policy and decoding
candidates.

Poses are arrays (..., pose_dim) whose columns follow the spec's DOFs in order (a polar DOF takes
two columns, x then y); angles are in radians, positions in the dataset's unit.

Entry points: `init`, `embed` (pose -> vectors), `rotation_losses` (eqs. 9 and 9.2),
`direction_loss` (L_rot,theta of eq. 9.2), `decode` (eq. 12 plus sub-grid refinement), `gram`,
and `check_range` (host-side check of poses before the jitted path).
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np
from typing_extensions import override

from camrep import lie

Array = jax.Array
Params = dict

QUANTISATION_MODES = ("nearest", "random", "floor")
TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------------------------
# Degrees of freedom: one interface (`Dof`), documented once, implemented per kind.

# Keys of a DOF's parameters (see `init`). The generator keys hold the free coefficients (strict
# upper triangles, `lie.skew`) of skew-symmetric blocks, not the matrices `lie` calls B and C.
GRID = "grid"
GENERATOR = "generator_coeffs"
GENERATOR0 = "generator0_coeffs"
DIRECTION = "direction_coeffs"


def _require(ok: bool, dof, field: str, message: str):
  if not ok:
    raise ValueError(
      f"{type(dof).__name__} {getattr(dof, 'name', '?')!r}: {field} {message}, "
      f"got {field}={getattr(dof, field)!r}"
    )


class Dof(abc.ABC):
  """One degree of freedom of the camera and its learned grid (paper sections 3.1-3.3, 3.5).

  A DOF owns `width` pose columns (1, or 2 for the polar (x, y) system) and a grid of
  `n_grid` learned vectors over [low, high] at `spacing` (physical units: radians or the
  dataset's length unit). Its value v(l) is the vector of a grid point rotated by
  exp(B (l - grid point)) (eq. 6). Implementations are frozen dataclasses (hashable, so a
  `PoseSystemSpec` is a static jit argument) whose constructors refuse impossible fields with a
  ValueError naming the field.

  Values outside [low, high] (`out_of_range`):
    "clamp": the grid index is clipped to the end grid point and the vector extrapolated from it
      by exp(B rest) (the authors' rule); `decode` answers within about a candidate step of the
      range. `check_range` reports such values.
    "wrap": periodic angles are taken mod (high - low); nothing is out of range.
  NaN values embed to NaN vectors, and NaN vectors decode to NaN values.
  """

  name: str
  low: float
  high: float
  spacing: float

  width = 1  # pose columns
  is_angle = False  # an angle in radians (GQN's low-dim input and regressors use (sin, cos))
  block_norm = False  # True: each block of a grid vector has norm 1 / n_blocks (polar only)
  has_direction_loss = False  # a table of generators tied by `direction_loss` (eq. 9.2)

  def _validate(self):
    _require(
      isinstance(self.name, str) and bool(self.name), self, "name", "must be a non-empty str"
    )
    for field in ("low", "high", "spacing"):
      _require(math.isfinite(getattr(self, field)), self, field, "must be finite")
    _require(self.spacing > 0, self, "spacing", "must be > 0")
    _require(self.low < self.high, self, "high", f"must be > low={self.low!r}")

  @property
  @abc.abstractmethod
  def n_grid(self) -> int:
    """Number of grid vectors."""

  @property
  def periodic(self) -> bool:
    """True when values wrap mod (high - low) (one shared vector at low and high)."""
    return False

  @property
  def out_of_range(self) -> str:
    """What embedding does beyond [low, high]: "clamp" or "wrap" (see the class docstring)."""
    return "wrap" if self.periodic else "clamp"

  @property
  def column_names(self) -> tuple[str, ...]:
    """Names of the DOF's pose columns."""
    return (self.name,)

  @property
  def default_resolution(self) -> float:
    """Candidate spacing of arg-min decoding: spacing / 40 for angles (0.25 degrees at 10 degree
    spacing, the authors' test setting), spacing / 4 for positions (their 0.25 grid units)."""
    return self.spacing / (40.0 if self.is_angle else 4.0)

  @property
  def gram_resolution(self) -> float:
    """Value step of Gram maps: 1 degree for angles, the grid spacing for positions."""
    return math.pi / 180 if self.is_angle else self.spacing

  def values(self, cols: Array) -> Array:
    """The DOF's values from its pose columns: (..., width) -> (...) or (..., 2) for width 2."""
    return cols[..., 0]

  def columns(self, values: Array) -> Array:
    """Inverse of `values`: (...) or (..., 2) -> (..., width)."""
    return values[..., None]

  def init_params(self, key: Array, spec: PoseSystemSpec, *, dtype) -> Params:
    """Initial parameters of this DOF, i.i.d. N(0, init_stddev^2) (digest 1.1-1.2):
    {"grid": (n_grid, d), "generator_coeffs": (n_blocks, s(s-1)/2)} (polar: see `PolarDof`)."""
    kg, kb, _ = jax.random.split(key, 3)
    return {
      GRID: _init_grid(kg, self, spec, dtype),
      GENERATOR: _init_gen(kb, (spec.n_blocks,), spec, dtype),
    }

  def grid_index(self, g: Array, mode: str, key: Array | None) -> tuple[Array, Array]:
    """Grid index and offset of grid coordinates g = (value - low) / spacing (section 3.5).

    Returns:
      (flat int32 index into the grid (...), rest: offset from that grid point in physical
      units, the shift of exp(B rest); same shape as the values).
    """
    k = jnp.clip(_quantise(g, mode, key), 0, self.n_grid - 1)
    rest = (g - k) * self.spacing
    return k.astype(jnp.int32), rest

  def rotate(self, params: Params, spec: PoseSystemSpec, delta: Array, v: Array) -> Array:
    """exp(B delta) v (eq. 6) for this DOF's parameters `params`; delta (...) in physical units
    (polar: (..., 2) displacements, eq. 4), v (..., d)."""
    B = lie.skew(params[GENERATOR], block_size=spec.block_size)
    return lie.apply_exp_blocks(B, delta, v, method=spec.exp_method, n_steps=spec.n_steps)

  def wrap_delta(self, delta: Array) -> Array:
    """A difference of values as a move: wrapped to [-pi, pi) for periodic angles (camrep's fix:
    the authors' raw difference turns a pair straddling 0/360 degrees into a ~2 pi move)."""
    return delta

  def wrap_value(self, x: Array) -> Array:
    """Values mapped into the DOF's range where it is periodic ([low, high)); others unchanged."""
    return x

  def sample_pairs(self, key: Array, n: int) -> tuple[Array, Array]:
    """Extra pairs of values for the rotation loss (digest 1.5), (n,) each (polar (n, 2)).

    Non-periodic (the authors' recipe, A = n_grid - 1 intervals): a0 ~ U(0, A - 1),
    a1 = min(a0 + U(0.5, 1), A) grid units. Periodic: a0 ~ U(0, N), a1 = a0 +/- U(0.5, 1)
    (values past `high` are wrapped by `embed`, so the seam is trained too).
    """
    k0, k1, k2 = jax.random.split(key, 3)
    step = jax.random.uniform(k1, (n,), minval=0.5, maxval=1.0)
    if self.periodic:
      a0 = jax.random.uniform(k0, (n,), maxval=self.n_grid)
      sign = jnp.where(jax.random.bernoulli(k2, 0.5, (n,)), 1.0, -1.0)
      a1 = a0 + sign * step
    else:
      A = self.n_grid - 1
      a0 = jax.random.uniform(k0, (n,), maxval=A - 1.0)
      a1 = jnp.minimum(a0 + step, A)
    return self.low + a0 * self.spacing, self.low + a1 * self.spacing

  def candidates(self, resolution: float | None = None) -> Array:
    """Candidate values over the range for arg-min decoding, (K,) float32 (polar (K, 2))."""
    res = self.default_resolution if resolution is None else resolution
    return jnp.asarray(self._axis(res), jnp.float32)

  def _axis(self, resolution: float) -> np.ndarray:
    n = int(math.floor((self.high - self.low) / resolution + 1e-6)) + 1
    return self.low + resolution * np.arange(n)

  def direction_loss(self, params: Params, spec: PoseSystemSpec, *, max_shift: int) -> Array:
    """L_rot,theta of eq. 9.2 (`direction_loss`); only polar DOFs have one."""
    raise ValueError(f"direction_loss is for polar DOFs; {self.name!r} is {type(self).__name__}")

  def describe_grid(self, k: int) -> str:
    """One line describing a Gram map over k values of this DOF (figure captions)."""
    return f"{k} grid points, {self.low:g} to {self.high:g} step {self.spacing:g}"

  def range_problems(self, values: np.ndarray, *, atol: float) -> list[str]:
    """Host-side: what is wrong with `values` (numpy, from `values`): non-finite entries, and
    (for "clamp" DOFs) entries beyond [low - atol, high + atol]. Empty when all is well."""
    values = np.asarray(values, np.float64)
    problems = []
    bad = ~np.isfinite(values)
    if bad.any():
      problems.append(f"DOF {self.name!r}: {int(bad.sum())} non-finite value(s)")
    if self.out_of_range == "clamp":
      with np.errstate(invalid="ignore"):
        out = ~bad & ((values < self.low - atol) | (values > self.high + atol))
      if out.any():
        worst = values[out][np.argmax(np.abs(values[out] - (self.low + self.high) / 2))]
        problems.append(
          f"DOF {self.name!r}: {int(out.sum())} value(s) outside [{self.low:g}, {self.high:g}] "
          f"(e.g. {worst:g}), which embed clamps to the end grid point and extrapolates"
        )
    return problems


@dataclasses.dataclass(frozen=True)
class LinearDof(Dof):
  """A translation-like DOF on a non-periodic grid low, low + spacing, ..., high.

  Values beyond the range use the end grid point and extrapolate (the authors' clipping).
  """

  name: str
  low: float
  high: float
  spacing: float

  def __post_init__(self):
    self._validate()
    _require(self.n_grid >= 2, self, "spacing", "must leave at least 2 grid points on the range")

  @property
  def n_grid(self) -> int:
    return int(round((self.high - self.low) / self.spacing)) + 1


@dataclasses.dataclass(frozen=True)
class AngularDof(Dof):
  """An angle DOF (radians).

  periodic=True (default, camrep's fix): N = (high - low) / spacing grid vectors with index
  taken mod N, so 0 and 360 degrees share one vector and moves across the seam wrap; the
  spacing must divide the range. periodic=False: the authors' grid with separate vectors at both
  ends (37 for 0..360 degrees at 10 degrees), clipped at the ends; `n_grid_override` reproduces
  their 7-Scenes grids (36 vectors for 0..360, the last 10 degrees extrapolated).
  """

  name: str
  spacing: float = math.pi / 18
  low: float = 0.0
  high: float = TWO_PI
  periodic: bool = True
  n_grid_override: int | None = None

  is_angle = True

  def __post_init__(self):
    self._validate()
    if self.periodic:
      n = (self.high - self.low) / self.spacing
      _require(
        abs(n - round(n)) <= 1e-6 * max(1.0, n),
        self,
        "spacing",
        f"must divide the periodic range high - low = {self.high - self.low!r}",
      )
    if self.n_grid_override is not None:
      _require(
        isinstance(self.n_grid_override, int) and self.n_grid_override >= 2,
        self,
        "n_grid_override",
        "must be None or an int >= 2",
      )
    _require(self.n_grid >= 2, self, "spacing", "must leave at least 2 grid points on the range")

  @property
  def n_grid(self) -> int:
    if self.n_grid_override is not None:
      return self.n_grid_override
    n = int(round((self.high - self.low) / self.spacing))
    return n if self.periodic else n + 1

  @override
  def grid_index(self, g, mode, key):
    if not self.periodic:
      return super().grid_index(g, mode, key)
    n = self.n_grid
    g = jnp.mod(g, n)
    k = _quantise(g, mode, key)
    rest = (g - k) * self.spacing
    return jnp.mod(k.astype(jnp.int32), n), rest

  @override
  def wrap_delta(self, delta):
    return wrap_angle(delta) if self.periodic else delta

  @override
  def wrap_value(self, x):
    return self.low + jnp.mod(x - self.low, self.high - self.low) if self.periodic else x

  @override
  def _axis(self, resolution):
    if self.periodic:
      n = int(round((self.high - self.low) / resolution))
      return self.low + resolution * np.arange(n)
    axis = super()._axis(resolution)
    # The authors decode non-periodic angles over [low, high) (360 is 0 degrees).
    return axis[axis < self.high - 1e-9] if math.isclose(self.high - self.low, TWO_PI) else axis

  @override
  def describe_grid(self, k):
    return f"{k} values, 1-degree steps from {math.degrees(self.low):.0f} deg"


@dataclasses.dataclass(frozen=True)
class PolarDof(Dof):
  """2-D position with the polar generator B(theta) of section 3.2 (eqs. 4-5).

  Grid: (L + 1) x (L + 1) vectors over [low, high]^2 with L = (high - low) / spacing, flat index
  gx * (L + 1) + gy (digest 1.4). Out-of-range positions are clamped per axis.

  variant="binned" (the authors' code): B(theta) is a table of `n_directions` free generators,
  theta rounded to the nearest bin (mod n_directions: the authors' index could reach
  n_directions, out of range), softly tied by `direction_loss` (B_{j+D} ~ exp(C D dtheta) B_j).
  Parameters {"grid", "generator_coeffs": (n_directions, n_blocks, s(s-1)/2),
  "direction_coeffs": (n_blocks, s(s-1)/2)} (B_j and C).
  variant="continuous" (camrep): B(theta) = exp(C theta) B0 exp(-C theta), exact conjugation, so
  no bins and no direction loss. Parameters {"grid", "generator0_coeffs", "direction_coeffs"}
  (B0 and C, (n_blocks, s(s-1)/2) each).

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

  width = 2

  def __post_init__(self):
    self._validate()
    _require(
      self.variant in ("binned", "continuous"), self, "variant", "must be 'binned' or 'continuous'"
    )
    _require(
      isinstance(self.n_directions, int) and self.n_directions >= 1,
      self,
      "n_directions",
      "must be an int >= 1",
    )
    _require(self.pair_radius > 0, self, "pair_radius", "must be > 0")
    _require(self.n_side >= 2, self, "spacing", "must leave at least 2 grid points per axis")

  @property
  def has_direction_loss(self) -> bool:
    return self.variant == "binned"

  @property
  def n_side(self) -> int:
    return int(round((self.high - self.low) / self.spacing)) + 1

  @property
  def n_grid(self) -> int:
    return self.n_side**2

  @property
  @override
  def column_names(self):
    return ("x", "y")

  @override
  def values(self, cols):
    return cols

  @override
  def columns(self, values):
    return values

  @override
  def init_params(self, key, spec, *, dtype):
    kg, kb, kc = jax.random.split(key, 3)
    grid = _init_grid(kg, self, spec, dtype)
    if self.variant == "binned":
      return {
        GRID: grid,
        GENERATOR: _init_gen(kb, (self.n_directions, spec.n_blocks), spec, dtype),
        DIRECTION: _init_gen(kc, (spec.n_blocks,), spec, dtype),
      }
    return {
      GRID: grid,
      GENERATOR0: _init_gen(kb, (spec.n_blocks,), spec, dtype),
      DIRECTION: _init_gen(kc, (spec.n_blocks,), spec, dtype),
    }

  @override
  def grid_index(self, g, mode, key):
    if g.shape[-1] != 2:
      raise ValueError(f"polar DOF {self.name!r} takes (..., 2) positions, got {g.shape}")
    k = jnp.clip(_quantise(g, mode, key), 0, self.n_side - 1)
    rest = (g - k) * self.spacing
    ki = k.astype(jnp.int32)
    return ki[..., 0] * self.n_side + ki[..., 1], rest

  @override
  def rotate(self, params, spec, delta, v):
    """exp(B(theta) r) v for displacements (..., 2) in physical units (eq. 4, exp form)."""
    r, theta = _safe_polar(delta)
    method, n_steps = spec.exp_method, spec.n_steps
    if self.variant == "binned":
      B = lie.skew(params[GENERATOR], block_size=spec.block_size)  # (n_dir, n_b, s, s)
      bins = jnp.round(theta / (TWO_PI / self.n_directions)).astype(jnp.int32)
      j = jnp.mod(bins, self.n_directions)
      return lie.apply_exp_blocks(B, r, v, method=method, n_steps=n_steps, index=j)
    C = lie.skew(params[DIRECTION], block_size=spec.block_size)
    B0 = lie.skew(params[GENERATOR0], block_size=spec.block_size)
    # exp(r e^{C th} B0 e^{-C th}) = e^{C th} e^{r B0} e^{-C th}.
    u = lie.apply_exp_blocks(C, -theta, v, method=method, n_steps=n_steps)
    u = lie.apply_exp_blocks(B0, r, u, method=method, n_steps=n_steps)
    return lie.apply_exp_blocks(C, theta, u, method=method, n_steps=n_steps)

  @override
  def sample_pairs(self, key, n):
    """Polar: p0 ~ U(1, L - 1)^2 grid units, direction uniform (binned variant: one of
    n_directions bins, fixed to exclude the out-of-range index), r ~ U(0, pair_radius),
    p1 = clip(p0 + r (cos, sin), 0, L); (n, 2) each."""
    k0, k1, k2 = jax.random.split(key, 3)
    L = self.n_side - 1
    p0 = jax.random.uniform(k0, (n, 2), minval=1.0, maxval=L - 1.0)
    if self.variant == "binned":
      direction = jax.random.randint(k1, (n,), 0, self.n_directions) * (TWO_PI / self.n_directions)
    else:
      direction = jax.random.uniform(k1, (n,), maxval=TWO_PI)
    r = jax.random.uniform(k2, (n,), maxval=self.pair_radius)
    step = r[:, None] * jnp.stack([jnp.cos(direction), jnp.sin(direction)], -1)
    p1 = jnp.clip(p0 + step, 0.0, L)
    return self.low + p0 * self.spacing, self.low + p1 * self.spacing

  @override
  def _axis(self, resolution):
    axis = super()._axis(resolution)
    gx, gy = np.meshgrid(axis, axis, indexing="ij")
    return np.stack([gx.ravel(), gy.ravel()], -1)

  @override
  def direction_loss(self, params, spec, *, max_shift):
    if self.variant == "continuous":
      return jnp.zeros((), params[GRID].dtype)
    B = lie.skew(params[GENERATOR], block_size=spec.block_size)  # (n, n_b, s, s)
    C = lie.skew(params[DIRECTION], block_size=spec.block_size)  # (n_b, s, s)
    shifts = jnp.arange(1, max_shift + 1)
    dtheta = TWO_PI / self.n_directions
    R = lie.exp_blocks(C, shifts * dtheta, method=spec.exp_method, n_steps=spec.n_steps)
    RB = jnp.einsum("kbij,nbjl->nkbil", R, B)  # (n, max_shift, n_b, s, s)
    target = B[(jnp.arange(self.n_directions)[:, None] + shifts[None, :]) % self.n_directions]
    sq = jnp.sum((RB - target) ** 2, axis=(-3, -2, -1))
    return spec.direction_loss_scale * jnp.mean(sq)

  @override
  def describe_grid(self, k):
    return f"{self.n_side} x {self.n_side} grid points, flat index gx * {self.n_side} + gy"


def _init_grid(key: Array, d: Dof, spec: PoseSystemSpec, dtype) -> Array:
  return spec.init_stddev * jax.random.normal(key, (d.n_grid, spec.dim), dtype)


def _init_gen(key: Array, shape: tuple[int, ...], spec: PoseSystemSpec, dtype) -> Array:
  return lie.init_generator(key, shape, spec.block_size, stddev=spec.init_stddev, dtype=dtype)


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
    if not isinstance(self.dofs, tuple) or not self.dofs:
      raise ValueError(f"PoseSystemSpec: dofs must be a non-empty tuple of DOFs, got {self.dofs!r}")
    for d in self.dofs:
      if not isinstance(d, Dof):
        raise TypeError(f"unknown DOF spec {d!r}")
    names = [d.name for d in self.dofs]
    if len(set(names)) != len(names):
      raise ValueError(f"DOF names must be unique, got {names}")
    if self.exp_method not in lie.EXP_METHODS:
      raise ValueError(f"exp_method must be one of {lie.EXP_METHODS}, got {self.exp_method!r}")
    for field, low in (("n_blocks", 1), ("block_size", 2), ("n_steps", 1)):
      v = getattr(self, field)
      if not isinstance(v, int) or isinstance(v, bool) or v < low:
        raise ValueError(f"PoseSystemSpec: {field} must be an int >= {low}, got {field}={v!r}")
    if self.n_steps != 1 and self.exp_method != "taylor2":
      raise ValueError(
        f"PoseSystemSpec: n_steps={self.n_steps} splits moves for exp_method='taylor2' only"
      )
    for field in ("init_stddev", "direction_loss_scale"):
      v = getattr(self, field)
      if not (math.isfinite(v) and (v > 0 if field == "init_stddev" else v >= 0)):
        bound = "> 0" if field == "init_stddev" else ">= 0"
        raise ValueError(f"PoseSystemSpec: {field} must be finite and {bound}, got {v!r}")

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


def check_range(spec: PoseSystemSpec, poses, *, atol: float = 1e-6) -> None:
  """Host-side check of poses before they enter the jitted path (which never checks).

  Raises ValueError naming every DOF with non-finite values (they would embed to NaN) or, for
  DOFs whose `out_of_range` is "clamp", values outside [low - atol, high + atol] (they would be
  embedded by extrapolation from the end grid point). Periodic angles may take any finite value.

  Args:
    poses: (..., pose_dim) array-like.
  """
  poses = np.asarray(poses)
  if poses.ndim < 1 or poses.shape[-1] != spec.pose_dim:
    raise ValueError(f"poses must have shape (..., {spec.pose_dim}), got {poses.shape}")
  problems = []
  for d in spec.dofs:
    problems += d.range_problems(d.values(poses[..., spec.columns(d.name)]), atol=atol)
  if problems:
    raise ValueError("poses out of the pose system's range: " + "; ".join(problems))


# --------------------------------------------------------------------------------------------
# Parameters.


def init(key: Array, spec: PoseSystemSpec, *, dtype=jnp.float32) -> Params:
  """Initial parameters: grid vectors and generators i.i.d. N(0, init_stddev^2) (digest 1.1-1.2).

  Returns:
    {name: {"grid": (n_grid, d), "generator_coeffs": (n_blocks, s(s-1)/2)}} for linear and
    angular DOFs; polar DOFs as `PolarDof` documents. The "*_coeffs" entries are the free
    coefficients of skew blocks: `lie.skew` (or `generator_blocks`) turns them into matrices.
  """
  return {
    d.name: d.init_params(jax.random.fold_in(key, i), spec, dtype=dtype)
    for i, d in enumerate(spec.dofs)
  }


def grid_vectors(params: Params, spec: PoseSystemSpec, name: str) -> Array:
  """The normalised grid vectors of one DOF, (n_grid, d) (normalised in every forward pass).

  Unit norm, or for a polar DOF with block_norm each block scaled to norm 1 / n_blocks.
  """
  return _normalise(params[name][GRID], spec, block_norm=spec.dof(name).block_norm)


def _normalise(v: Array, spec: PoseSystemSpec, *, block_norm: bool) -> Array:
  eps = 1e-12
  if block_norm:
    vb = v.reshape(*v.shape[:-1], spec.n_blocks, spec.block_size)
    nb = jnp.sqrt(jnp.sum(vb * vb, axis=-1, keepdims=True) + eps)
    return (vb / (nb * spec.n_blocks)).reshape(v.shape)
  return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True) + eps)


def generator_blocks(params: Params, spec: PoseSystemSpec, name: str) -> dict[str, Array]:
  """The DOF's generators as skew blocks, {parameter key: (..., n_blocks, s, s)}, one entry per
  "*_coeffs" parameter (e.g. {"generator_coeffs": B})."""
  return {k: lie.skew(v, block_size=spec.block_size) for k, v in params[name].items() if k != GRID}


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


def rotate(params: Params, spec: PoseSystemSpec, name: str, delta: Array, v: Array) -> Array:
  """Move DOF vectors by a pose shift: exp(B_l delta) v (eq. 6), or the polar eq. 4.

  Args:
    delta: (...) shift in physical units, or (..., 2) displacement for a polar DOF.
    v: (..., d) vectors of DOF `name`.

  Returns:
    (..., d).
  """
  return spec.dof(name).rotate(params[name], spec, delta, v)


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

  Out-of-range values are clamped or wrapped as the DOF's `out_of_range` says; NaN values give
  NaN vectors.

  Args:
    value: (...) values, or (..., 2) positions for a polar DOF, in physical units.
    mode: "nearest" (the paper), "random" (random lower/upper neighbour, the authors' training
      rule; needs `key`) or "floor" (the authors' inference rule).

  Returns:
    (..., d) vectors.
  """
  d = spec.dof(name)
  value = jnp.asarray(value, params[name][GRID].dtype)
  grid = grid_vectors(params, spec, name)
  index, rest = d.grid_index((value - d.low) / d.spacing, mode, key)
  return d.rotate(params[name], spec, rest, grid[index])


def embed(
  params: Params,
  spec: PoseSystemSpec,
  pose: Array,
  *,
  mode: str = "nearest",
  key: Array | None = None,
) -> dict[str, Array]:
  """Vectors of every DOF for poses (..., pose_dim): {name: (..., d)}.

  With mode="random" each DOF (and each pose) draws its own lower/upper neighbour. Not checked
  here (jitted callers): `check_range` reports NaN and out-of-range poses on the host.
  """
  pose = jnp.asarray(pose)
  if pose.shape[-1] != spec.pose_dim:
    raise ValueError(f"pose has {pose.shape[-1]} columns, this system takes {spec.pose_dim}")
  out = {}
  for i, d in enumerate(spec.dofs):
    value = d.values(pose[..., spec.columns(d.name)])
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
  cols = [d.wrap_delta(delta[..., spec.columns(d.name)]) for d in spec.dofs]
  return jnp.concatenate(cols, axis=-1)


def sample_pairs(key: Array, spec: PoseSystemSpec, name: str, n: int) -> tuple[Array, Array]:
  """Extra pose pairs for the rotation loss of DOF `name`, in physical units (digest 1.5).

  As `Dof.sample_pairs` (and `PolarDof.sample_pairs`) describe.

  Returns:
    (value0, value1): (n,) each, or (n, 2) for a polar DOF.
  """
  return spec.dof(name).sample_pairs(key, n)


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
  moved = d.rotate(params[name], spec, d.wrap_delta(value1 - value0), v0)
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
    value0, value1 = d.sample_pairs(ks, n_pairs)
    loss = dof_rotation_loss(params, spec, d.name, value0, value1, mode=mode, key=ke)
    if data_pairs is not None:
      p0, p1 = data_pairs
      cols = spec.columns(d.name)
      x0, x1 = d.values(p0[..., cols]), d.values(p1[..., cols])
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
  there is no such loss for it (returns 0). Raises ValueError for a DOF that is not polar.
  """
  return spec.dof(name).direction_loss(params[name], spec, max_shift=max_shift)


# --------------------------------------------------------------------------------------------
# Decoding (eq. 12) with sub-grid refinement.


def candidates(spec: PoseSystemSpec, name: str, resolution: float | None = None) -> Array:
  """A dense candidate list over the DOF's range for arg-min decoding.

  Default resolution: `Dof.default_resolution` (spacing / 40 for angles, 0.25 degrees at 10
  degree spacing, the authors' test setting; spacing / 4 for positions, their 0.25 grid-unit
  position list).

  Returns:
    (K,) values, or (K, 2) positions for a polar DOF.
  """
  return spec.dof(name).candidates(resolution)


def _nan_where_nan(v_hat: Array, x: Array) -> Array:
  """x with NaN wherever the vector v_hat (..., d) has a NaN (x: (...) or (..., 2))."""
  bad = jnp.isnan(jnp.sum(v_hat, axis=-1))
  bad = bad.reshape(bad.shape + (1,) * (x.ndim - bad.ndim))
  return jnp.where(bad, jnp.asarray(jnp.nan, x.dtype), x)


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
  Vectors with a NaN decode to NaN (not to the first candidate). Results lie within about one
  candidate step of the range (periodic angles: in [low, high)).

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
    resolution = d.default_resolution
  cvec = embed_dof(params, spec, name, cands, mode=mode)  # (K, d)
  score = jnp.sum(cvec * cvec, -1) - 2.0 * jnp.einsum("...d,kd->...k", v_hat, cvec)
  best = cands[jnp.argmin(score, axis=-1)]
  if refine_steps == 0:
    return _nan_where_nan(v_hat, best)
  f = lambda x: embed_dof(params, spec, name, x, mode=mode)

  def residual(x, vh):
    return jnp.sum((f(x) - vh) ** 2)

  def refine_one(x0, vh):
    def body(_, x):
      r = f(x) - vh
      J = jax.jacfwd(f)(x)  # (d,), or (d, 2) for a polar DOF
      if d.width > 1:
        H = J.T @ J + 1e-9 * jnp.eye(d.width, dtype=J.dtype)
        step = -jnp.linalg.solve(H, J.T @ r)
      else:
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
  return _nan_where_nan(v_hat, d.wrap_value(out))


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

  A DOF whose vector holds a NaN decodes to NaN.

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
    cols.append(d.columns(x))
  return jnp.concatenate(cols, axis=-1)


# --------------------------------------------------------------------------------------------
# Inspection.


def gram(params: Params, spec: PoseSystemSpec, name: str, *, values: Array | None = None) -> Array:
  """Inner-product (Gram) matrix V V^T of a DOF's vectors over its range (supplement figure).

  Args:
    values: (K,) values (or (K, 2) positions); default: candidates at `Dof.gram_resolution` (1
      degree for angles, the grid points for positions).

  Returns:
    (K, K).
  """
  if values is None:
    values = candidates(spec, name, spec.dof(name).gram_resolution)
  V = embed_dof(params, spec, name, values, mode="nearest")
  return V @ V.T


def grid_std(params: Params, spec: PoseSystemSpec, name: str) -> Array:
  """beta_i: the std of element i over the DOF's normalised grid vectors, (d,) (section 4.3)."""
  return jnp.std(grid_vectors(params, spec, name), axis=0)

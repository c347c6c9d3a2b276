"""The degrees of freedom of a pose system and its spec (Zhu et al., CVPR 2021, section 3).

`Dof` is the interface of one degree of freedom (documented once), implemented by `LinearDof`,
`AngularDof` and the polar DOFs `BinnedPolarDof` and `ContinuousPolarDof`: its pose columns,
grid, grid index, rotation exp(B delta), range policy, pair sampling and decoding candidates.
`PoseSystemSpec` groups them with the vector size and exp method; `check_range` checks poses on
the host. `camrep.pose` builds the parameters, embedding, losses and decoding on these and
re-exports every public name here.
"""

from __future__ import annotations

import abc
import dataclasses
import math

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
    """Initial parameters of this DOF, i.i.d. N(0, init_stddev^2) (the authors' code):
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

  def stacking(self) -> Stacking | None:
    """The constants that make this DOF one case of the shared 1-D rule, or None.

    The rule: one pose column, parameters {"grid": (n_grid, d), "generator_coeffs": (n_blocks,
    s(s-1)/2)}, unit grid vectors, `grid_index`, `rotate`, `wrap_delta` and `sample_pairs` as
    `Dof` defines them, or as `AngularDof` does where `periodic`. `camrep.pose` traces the DOFs
    of a system that follow it as one program (their grids in one table, their generators
    stacked); a DOF that returns None (the polar DOFs, and any subclass that changes one of
    those methods) is traced on its own.
    """
    if self.width != 1 or self.block_norm:
      return None
    return Stacking(self.low, self.spacing, self.n_grid, self.periodic)

  def wrap_delta(self, delta: Array) -> Array:
    """A difference of values as a move: wrapped to [-pi, pi) for periodic angles (camrep's fix:
    the authors' raw difference turns a pair straddling 0/360 degrees into a ~2 pi move)."""
    return delta

  def wrap_value(self, x: Array) -> Array:
    """Values mapped into the DOF's range where it is periodic ([low, high)); others unchanged."""
    return x

  def sample_pairs(self, key: Array, n: int) -> tuple[Array, Array]:
    """Extra pairs of values for the rotation loss (the authors' code), (n,) each (polar (n, 2)).

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

  def record(self) -> dict:
    """The DOF as JSON values for a run's record.json: its class ("kind") and its fields."""
    return {"kind": type(self).__name__, **dataclasses.asdict(self)}

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
class Stacking:
  """The constants of a DOF that follows the shared 1-D rule (`Dof.stacking`).

  Attributes:
    low, spacing: the grid's start and step, physical units.
    n_grid: number of grid vectors.
    periodic: grid index taken mod n_grid and moves wrapped to [-pi, pi) (`AngularDof`).
  """

  low: float
  spacing: float
  n_grid: int
  periodic: bool


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


# The fields of the one polar class these replaced, in its order (positional arguments of
# `PolarDof(...)`).
_POLAR_FIELDS = (
  "name", "low", "high", "spacing", "n_directions", "variant", "block_norm", "pair_radius"
)  # fmt: skip


class _PolarMeta(abc.ABCMeta):
  """`PolarDof(..., variant="binned" | "continuous")` builds that variant's class (`polar_dof`),
  as the single polar class before them was built; the variants' own classes build as usual."""

  def __call__(cls, *args, **kwargs):
    if cls is not PolarDof:
      return super().__call__(*args, **kwargs)
    fields = {**dict(zip(_POLAR_FIELDS[: len(args)], args, strict=True)), **kwargs}
    return polar_dof(fields.pop("variant", "binned"), **fields)


class PolarDof(Dof, metaclass=_PolarMeta):
  """2-D position with the polar generator B(theta) of section 3.2 (eqs. 4-5).

  Grid: (L + 1) x (L + 1) vectors over [low, high]^2 with L = (high - low) / spacing, flat index
  gx * (L + 1) + gy (the authors' code). Out-of-range positions are clamped per axis. Two
  implementations differ in how B depends on the direction theta of a move:
  `BinnedPolarDof` (the authors': a table of generators) and `ContinuousPolarDof` (camrep's:
  one conjugated generator). `POLAR_VARIANTS` names them for `config.rep.polar_variant`;
  `PolarDof(..., variant=NAME)` builds one.

  block_norm=True: each block of a grid vector has norm 1 / n_blocks as in the authors' code
  (whole vector 1/sqrt(n_blocks)); False: unit vectors like the other DOFs (the paper's text).
  pair_radius: the largest extra-pair move for the rotation loss, in grid units (GQN 2.0,
  Gibson 2.2).
  """

  name: str
  low: float
  high: float
  spacing: float
  block_norm: bool
  pair_radius: float

  width = 2
  variant = ""  # the key of `POLAR_VARIANTS` (config.rep.polar_variant) and of the records

  def _validate(self):
    super()._validate()
    _require(self.pair_radius > 0, self, "pair_radius", "must be > 0")
    _require(self.n_side >= 2, self, "spacing", "must leave at least 2 grid points per axis")

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
  def stacking(self):
    """None: the polar grid index, rotation and pairs are their own (two columns)."""
    return None

  @override
  def grid_index(self, g, mode, key):
    if g.shape[-1] != 2:
      raise ValueError(f"polar DOF {self.name!r} takes (..., 2) positions, got {g.shape}")
    k = jnp.clip(_quantise(g, mode, key), 0, self.n_side - 1)
    rest = (g - k) * self.spacing
    ki = k.astype(jnp.int32)
    return ki[..., 0] * self.n_side + ki[..., 1], rest

  @abc.abstractmethod
  def _directions(self, key: Array, n: int) -> Array:
    """Directions (n,) in radians of the extra pairs' moves (`sample_pairs`)."""

  @override
  def sample_pairs(self, key, n):
    """Polar: p0 ~ U(1, L - 1)^2 grid units, direction from `_directions`,
    r ~ U(0, pair_radius), p1 = clip(p0 + r (cos, sin), 0, L); (n, 2) each."""
    k0, k1, k2 = jax.random.split(key, 3)
    L = self.n_side - 1
    p0 = jax.random.uniform(k0, (n, 2), minval=1.0, maxval=L - 1.0)
    direction = self._directions(k1, n)
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
  def describe_grid(self, k):
    return f"{self.n_side} x {self.n_side} grid points, flat index gx * {self.n_side} + gy"

  @override
  def record(self):
    """The layout of the single polar class these two replaced (kind "PolarDof" with its
    `variant` and `n_directions`), so that records written before compare equal."""
    fields = dataclasses.asdict(self)
    return {
      "kind": "PolarDof",
      **{k: fields[k] for k in ("name", "low", "high", "spacing")},
      "n_directions": self.n_directions,
      "variant": self.variant,
      "block_norm": self.block_norm,
      "pair_radius": self.pair_radius,
    }


@dataclasses.dataclass(frozen=True)
class BinnedPolarDof(PolarDof):
  """The authors' polar DOF: B(theta) is a table of `n_directions` free generators, theta rounded
  to the nearest bin (mod n_directions: the authors' index could reach n_directions, out of
  range), softly tied by `direction_loss` (B_{j+D} ~ exp(C D dtheta) B_j).

  Parameters {"grid", "generator_coeffs": (n_directions, n_blocks, s(s-1)/2),
  "direction_coeffs": (n_blocks, s(s-1)/2)} (B_j and C).
  """

  name: str = "xy"
  low: float = -1.0
  high: float = 1.0
  spacing: float = 0.1
  n_directions: int = 144
  block_norm: bool = True
  pair_radius: float = 2.0

  variant = "binned"
  has_direction_loss = True

  def __post_init__(self):
    self._validate()
    _require(
      isinstance(self.n_directions, int) and self.n_directions >= 1,
      self,
      "n_directions",
      "must be an int >= 1",
    )

  @override
  def init_params(self, key, spec, *, dtype):
    kg, kb, kc = jax.random.split(key, 3)
    return {
      GRID: _init_grid(kg, self, spec, dtype),
      GENERATOR: _init_gen(kb, (self.n_directions, spec.n_blocks), spec, dtype),
      DIRECTION: _init_gen(kc, (spec.n_blocks,), spec, dtype),
    }

  @override
  def rotate(self, params, spec, delta, v):
    """exp(B_j r) v for displacements (..., 2) in physical units, j the bin of their direction
    (eq. 4, exp form)."""
    r, theta = _safe_polar(delta)
    B = lie.skew(params[GENERATOR], block_size=spec.block_size)  # (n_dir, n_b, s, s)
    bins = jnp.round(theta / (TWO_PI / self.n_directions)).astype(jnp.int32)
    j = jnp.mod(bins, self.n_directions)
    return lie.apply_exp_blocks(B, r, v, method=spec.exp_method, n_steps=spec.n_steps, index=j)

  @override
  def _directions(self, key, n):
    """One of the n_directions bins (which excludes the out-of-range index)."""
    return jax.random.randint(key, (n,), 0, self.n_directions) * (TWO_PI / self.n_directions)

  @override
  def direction_loss(self, params, spec, *, max_shift):
    B = lie.skew(params[GENERATOR], block_size=spec.block_size)  # (n, n_b, s, s)
    C = lie.skew(params[DIRECTION], block_size=spec.block_size)  # (n_b, s, s)
    shifts = jnp.arange(1, max_shift + 1)
    dtheta = TWO_PI / self.n_directions
    R = lie.exp_blocks(C, shifts * dtheta, method=spec.exp_method, n_steps=spec.n_steps)
    RB = jnp.einsum("kbij,nbjl->nkbil", R, B)  # (n, max_shift, n_b, s, s)
    target = B[(jnp.arange(self.n_directions)[:, None] + shifts[None, :]) % self.n_directions]
    sq = jnp.sum((RB - target) ** 2, axis=(-3, -2, -1))
    return spec.direction_loss_scale * jnp.mean(sq)


@dataclasses.dataclass(frozen=True)
class ContinuousPolarDof(PolarDof):
  """camrep's polar DOF: B(theta) = exp(C theta) B0 exp(-C theta), exact conjugation, so no bins
  and no direction loss (it holds exactly).

  Parameters {"grid", "generator0_coeffs", "direction_coeffs"} (B0 and C, (n_blocks, s(s-1)/2)
  each).

  Attributes:
    n_directions: unused (no bins): the config's `rep.n_directions`, kept in the DOF and its
      record as the single polar class kept it, so that a workdir's record.json compares equal.
  """

  name: str = "xy"
  low: float = -1.0
  high: float = 1.0
  spacing: float = 0.1
  n_directions: int = 144
  block_norm: bool = True
  pair_radius: float = 2.0

  variant = "continuous"

  def __post_init__(self):
    self._validate()

  @override
  def init_params(self, key, spec, *, dtype):
    kg, kb, kc = jax.random.split(key, 3)
    return {
      GRID: _init_grid(kg, self, spec, dtype),
      GENERATOR0: _init_gen(kb, (spec.n_blocks,), spec, dtype),
      DIRECTION: _init_gen(kc, (spec.n_blocks,), spec, dtype),
    }

  @override
  def rotate(self, params, spec, delta, v):
    """exp(B(theta) r) v for displacements (..., 2) in physical units (eq. 4, exp form)."""
    r, theta = _safe_polar(delta)
    method, n_steps = spec.exp_method, spec.n_steps
    C = lie.skew(params[DIRECTION], block_size=spec.block_size)
    B0 = lie.skew(params[GENERATOR0], block_size=spec.block_size)
    # exp(r e^{C th} B0 e^{-C th}) = e^{C th} e^{r B0} e^{-C th}.
    u = lie.apply_exp_blocks(C, -theta, v, method=method, n_steps=n_steps)
    u = lie.apply_exp_blocks(B0, r, u, method=method, n_steps=n_steps)
    return lie.apply_exp_blocks(C, theta, u, method=method, n_steps=n_steps)

  @override
  def _directions(self, key, n):
    """Uniform on [0, 2 pi)."""
    return jax.random.uniform(key, (n,), maxval=TWO_PI)

  @override
  def direction_loss(self, params, spec, *, max_shift):
    """0: the conjugated generator satisfies the relation exactly."""
    return jnp.zeros((), params[GRID].dtype)


POLAR_VARIANTS: dict[str, type[PolarDof]] = {
  cls.variant: cls for cls in (BinnedPolarDof, ContinuousPolarDof)
}
"""`config.rep.polar_variant` -> its polar DOF class."""


def polar_dof(variant: str, **fields) -> PolarDof:
  """The polar DOF of a variant (a key of `POLAR_VARIANTS`) with `fields`.

  Raises:
    ValueError: an unknown variant, or fields the DOF refuses.
  """
  if variant not in POLAR_VARIANTS:
    raise ValueError(f"unknown polar variant {variant!r}; choose one of {tuple(POLAR_VARIANTS)}")
  return POLAR_VARIANTS[variant](**fields)


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


def wrap_angle(x: Array) -> Array:
  """Wrap angles to [-pi, pi)."""
  return jnp.mod(x + math.pi, TWO_PI) - math.pi


def _quantise(g: Array, mode: str, key: Array | None) -> Array:
  """Grid index (float, before clipping/wrapping) for grid coordinates g (the authors' code)."""
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

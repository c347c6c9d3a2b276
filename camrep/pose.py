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
the matrices B, C of the paper). Each DOF kind (`LinearDof`, `AngularDof`, the `PolarDof`s,
defined in `camrep.dofs` with `PoseSystemSpec` and re-exported here) implements the `Dof`
interface: its columns, grid index, rotation, range policy and decoding candidates.

Poses are arrays (..., pose_dim) whose columns follow the spec's DOFs in order (a polar DOF takes
two columns, x then y); angles are in radians, positions in the dataset's unit.

`embed` and the rotation losses trace the DOFs that follow the shared 1-D rule (`Dof.stacking`:
linear and angular DOFs) as one program: their normalised grids concatenated into one table,
their generators stacked into (G, n_blocks, s, s), one gather and one exp(B t) v for all of them;
random draws stay per DOF, from the same keys as `embed_dof` and `dof_rotation_loss` (the per-DOF
functions), so the numbers are theirs up to float32 round-off. Polar DOFs take the per-DOF path.

Entry points: `init`, `embed` (pose -> vectors), `rotation_losses` (eqs. 9 and 9.2),
`direction_loss` (L_rot,theta of eq. 9.2), `decode` (eq. 12 plus sub-grid refinement), `gram`,
and `check_range` (host-side check of poses before the jitted path).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from camrep import lie
from camrep.dofs import DIRECTION as DIRECTION
from camrep.dofs import GENERATOR as GENERATOR
from camrep.dofs import GENERATOR0 as GENERATOR0
from camrep.dofs import GRID as GRID
from camrep.dofs import POLAR_VARIANTS as POLAR_VARIANTS
from camrep.dofs import QUANTISATION_MODES as QUANTISATION_MODES
from camrep.dofs import TWO_PI as TWO_PI
from camrep.dofs import AngularDof as AngularDof
from camrep.dofs import BinnedPolarDof as BinnedPolarDof
from camrep.dofs import ContinuousPolarDof as ContinuousPolarDof
from camrep.dofs import Dof as Dof
from camrep.dofs import LinearDof as LinearDof
from camrep.dofs import PolarDof as PolarDof
from camrep.dofs import PoseSystemSpec as PoseSystemSpec
from camrep.dofs import Stacking as Stacking
from camrep.dofs import _quantise
from camrep.dofs import check_range as check_range
from camrep.dofs import polar_dof as polar_dof
from camrep.dofs import wrap_angle as wrap_angle

Array = jax.Array
Params = dict

# --------------------------------------------------------------------------------------------
# Parameters.


def init(key: Array, spec: PoseSystemSpec, *, dtype=jnp.float32) -> Params:
  """Initial parameters: grid vectors and generators i.i.d. N(0, init_stddev^2) (the authors' code).

  Returns:
    {name: {"grid": (n_grid, d), "generator_coeffs": (n_blocks, s(s-1)/2)}} for linear and
    angular DOFs; polar DOFs as `BinnedPolarDof` and `ContinuousPolarDof` document. The
    "*_coeffs" entries are the free coefficients of skew blocks: `lie.skew` (or
    `generator_blocks`) turns them into matrices.
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
  """Vector of one DOF at continuous values: exp(B rest) v_grid[k] (section 3.5, the authors' code).

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
  g = _group(spec)
  if g is not None:
    value = _group_values(g, pose)
    coin = None
    if mode == "random" and key is not None:
      coin = _coins(_fold_in(key, g.index), 1, value.shape[1:], value.dtype)
    vectors = _group_embed(spec, g, _group_tables(params, spec, g), value, mode, coin)
    out.update(zip(g.names, vectors, strict=True))
  for i, d in enumerate(spec.dofs):
    if d.stacking() is None:
      value = d.values(pose[..., spec.columns(d.name)])
      k = None if key is None else jax.random.fold_in(key, i)
      out[d.name] = embed_dof(params, spec, d.name, value, mode=mode, key=k)
  return {n: out[n] for n in spec.names}


def concat(vectors: Mapping[str, Array], spec: PoseSystemSpec) -> Array:
  """Concatenate per-DOF vectors in spec order: (..., n_dofs * d), the decoder's pose input."""
  return jnp.concatenate([vectors[n] for n in spec.names], axis=-1)


def split(v: Array, spec: PoseSystemSpec) -> dict[str, Array]:
  """Inverse of `concat`: (..., n_dofs * d) -> {name: (..., d)}."""
  if v.shape[-1] != len(spec.dofs) * spec.dim:
    raise ValueError(f"expected {len(spec.dofs) * spec.dim} columns, got {v.shape[-1]}")
  return {n: v[..., i * spec.dim : (i + 1) * spec.dim] for i, n in enumerate(spec.names)}


# --------------------------------------------------------------------------------------------
# The DOFs of the shared 1-D rule (`Dof.stacking`) traced as one program: a leading DOF axis G.


@dataclasses.dataclass(frozen=True)
class _Group:
  """The DOFs of a system whose `Dof.stacking` is not None, in spec order.

  Attributes:
    index: their positions in spec.dofs (their keys are fold_in(key, position)).
    names: their names.
    cols: their pose columns.
    low, spacing, n_grid, periodic: (G,) numpy arrays of their `Stacking` constants (float64,
      cast to the values' dtype where used, as a Python float would be).
    offset: (G,) first row of each DOF's grid in the concatenated table.
  """

  index: tuple[int, ...]
  names: tuple[str, ...]
  cols: tuple[int, ...]
  low: np.ndarray
  spacing: np.ndarray
  n_grid: np.ndarray
  periodic: np.ndarray
  offset: np.ndarray

  def per_dof(self, field: np.ndarray, ndim: int) -> np.ndarray:
    """A (G,) constant shaped (G, 1, ...) to broadcast against (G, ...) arrays of `ndim` axes."""
    return field.reshape((len(self.index),) + (1,) * (ndim - 1))


@functools.lru_cache(maxsize=64)
def _group(spec: PoseSystemSpec) -> _Group | None:
  """The system's DOFs of the shared 1-D rule, or None when it has none."""
  members = [(i, d, d.stacking()) for i, d in enumerate(spec.dofs) if d.stacking() is not None]
  if not members:
    return None
  n_grid = np.array([c.n_grid for _, _, c in members], np.int32)
  return _Group(
    index=tuple(i for i, _, _ in members),
    names=tuple(d.name for _, d, _ in members),
    cols=tuple(spec.columns(d.name).start for _, d, _ in members),
    low=np.array([c.low for _, _, c in members], np.float64),
    spacing=np.array([c.spacing for _, _, c in members], np.float64),
    n_grid=n_grid,
    periodic=np.array([c.periodic for _, _, c in members], bool),
    offset=np.concatenate([[0], np.cumsum(n_grid)[:-1]]).astype(np.int32),
  )


def _group_tables(params: Params, spec: PoseSystemSpec, g: _Group) -> tuple[Array, Array]:
  """(the normalised grids concatenated, (sum n_grid, d); the generators' skew blocks stacked,
  (G, n_blocks, s, s)). Normalisation is per row, so it equals `grid_vectors` of each DOF."""
  grid = _normalise(jnp.concatenate([params[n][GRID] for n in g.names], 0), spec, block_norm=False)
  coeffs = jnp.stack([params[n][GENERATOR] for n in g.names], 0)
  return grid, lie.skew(coeffs, block_size=spec.block_size)


def _group_values(g: _Group, pose: Array) -> Array:
  """The group's values of poses (..., pose_dim): (G, ...)."""
  return jnp.moveaxis(jnp.take(pose, np.asarray(g.cols), axis=-1), -1, 0)


def _vmap_n(fn: Callable, n: int) -> Callable:
  """fn mapped over n leading axes of every argument."""
  for _ in range(n):
    fn = jax.vmap(fn)
  return fn


def _fold_in(key: Array, index: tuple[int, ...]) -> Array:
  """fold_in(key, i) for every i of `index`: (G,) keys."""
  return jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.asarray(index, jnp.int32))


def _coins(keys: Array, lead: int, shape: tuple[int, ...], dtype) -> Array:
  """Random lower/upper neighbour draws (0 or 1) of shape `shape` per key of the `lead` leading
  axes of `keys`: (*keys' leading shape, *shape), the draws `_quantise` makes from each key."""
  draw = lambda k: jax.random.bernoulli(k, 0.5, shape).astype(dtype)
  return _vmap_n(draw, lead)(keys)


def _group_embed(
  spec: PoseSystemSpec, g: _Group, tables, value: Array, mode: str, coin: Array | None
) -> Array:
  """`embed_dof` of every group DOF: values (G, ...) -> vectors (G, ..., d).

  As `Dof.grid_index` (clipped index) or, where periodic, `AngularDof.grid_index` (coordinate
  and index mod n_grid); `coin` (G, ...): the random neighbour draws of mode "random".
  """
  grid, B = tables
  value = value.astype(grid.dtype)
  per = lambda field: g.per_dof(field, value.ndim)
  periodic, n_grid = per(g.periodic), per(g.n_grid)
  low, spacing = (per(f).astype(value.dtype) for f in (g.low, g.spacing))
  x = (value - low) / spacing
  x = jnp.where(periodic, jnp.mod(x, n_grid.astype(x.dtype)), x)
  k = _quantise(x, mode, None) if coin is None else jnp.floor(x) + coin
  k = jnp.where(periodic, k, jnp.clip(k, 0, n_grid - 1))
  rest = (x - k) * spacing
  index = k.astype(jnp.int32)
  index = jnp.where(periodic, jnp.mod(index, n_grid), index) + per(g.offset)
  return _group_rotate(spec, B, rest, grid[index])


def _group_rotate(spec: PoseSystemSpec, B: Array, t: Array, v: Array) -> Array:
  """exp(B_i t) v (eq. 6) with the DOF axis first: B (G, n_blocks, s, s), t (G, ...),
  v (G, ..., d) -> (G, ..., d)."""
  B = B.reshape(B.shape[:1] + (1,) * (t.ndim - 1) + B.shape[1:])
  return lie.apply_exp_blocks(B, t, v, method=spec.exp_method, n_steps=spec.n_steps)


def _group_sample_pairs(g: _Group, keys: Array, n: int) -> tuple[Array, Array]:
  """`Dof.sample_pairs` of every group DOF from its key: (G, n) each. Both recipes' draws are
  made (split into the same three keys); `periodic` selects."""
  periodic = g.per_dof(g.periodic, 2)
  maxval = np.where(g.periodic, g.n_grid, g.n_grid - 2).astype(np.float64)

  def draw(key, maxval):
    k0, k1, k2 = jax.random.split(key, 3)
    step = jax.random.uniform(k1, (n,), minval=0.5, maxval=1.0)
    a0 = jax.random.uniform(k0, (n,), maxval=maxval)
    sign = jnp.where(jax.random.bernoulli(k2, 0.5, (n,)), 1.0, -1.0)
    return a0, step, sign

  a0, step, sign = jax.vmap(draw)(keys, jnp.asarray(maxval))
  end = g.per_dof(g.n_grid - 1, 2).astype(np.float64)
  a1 = jnp.where(periodic, a0 + sign * step, jnp.minimum(a0 + step, end))
  low, spacing = g.per_dof(g.low, 2), g.per_dof(g.spacing, 2)
  return low + a0 * spacing, low + a1 * spacing


def _group_pair_sq(
  spec: PoseSystemSpec, g: _Group, tables, x0: Array, x1: Array, mode: str, coins: tuple | None
) -> Array:
  """||v(x1) - exp(B (x1 - x0)) v(x0)||^2 per pair (eq. 9 before its mean), x0, x1 (G, N) ->
  (G, N), both ends in one embedding; moves wrapped to [-pi, pi) where periodic."""
  coin = None if coins is None else jnp.stack(coins, 1)
  v = _group_embed(spec, g, tables, jnp.stack([x0, x1], 1), mode, coin)  # (G, 2, N, d)
  delta = x1 - x0
  delta = jnp.where(g.per_dof(g.periodic, 2), wrap_angle(delta), delta)
  moved = _group_rotate(spec, tables[1], delta.astype(v.dtype), v[:, 0])
  return jnp.sum((moved - v[:, 1]) ** 2, axis=-1)


def _group_rotation_losses(
  key, params, spec, g: _Group, n_pairs, mode, data_pairs, data_keys
) -> dict[str, Array]:
  """`data_rotation_losses` of the group DOFs: extra pairs and data pairs of every group DOF in
  one embedding, from the keys `dof_rotation_loss` would get."""
  index = jnp.asarray(g.index, jnp.int32)
  ks, ke, _ = jax.vmap(lambda k: tuple(jax.random.split(k, 3)))(_fold_in(key, g.index))
  x0, x1 = _group_sample_pairs(g, ks, n_pairs)  # (G, n)
  ends = [(x0, x1, ke, 1)]
  lead = None
  if data_pairs is not None:
    p0, p1 = data_pairs
    lead = p0.shape[:-2]
    y0, y1 = _group_values(g, p0), _group_values(g, p1)  # (G, ..., m)
    ends.append((y0, y1, jax.vmap(data_keys)(index), 1 + len(lead)))
  random = mode == "random"
  a, b, c0, c1 = [], [], [], []
  for v0, v1, keys, n_lead in ends:
    a.append(v0.reshape(len(g.index), -1))
    b.append(v1.reshape(len(g.index), -1))
    if random:
      k0, k1 = _vmap_n(lambda k: tuple(jax.random.split(k)), n_lead)(keys)
      c0.append(_coins(k0, n_lead, v0.shape[n_lead:], a[-1].dtype).reshape(a[-1].shape))
      c1.append(_coins(k1, n_lead, v1.shape[n_lead:], b[-1].dtype).reshape(b[-1].shape))
  coins = (jnp.concatenate(c0, -1), jnp.concatenate(c1, -1)) if random else None
  tables = _group_tables(params, spec, g)
  sq = _group_pair_sq(spec, g, tables, jnp.concatenate(a, -1), jnp.concatenate(b, -1), mode, coins)
  loss = jnp.mean(sq[:, :n_pairs], axis=-1)  # (G,)
  if data_pairs is not None:
    per_lead = jnp.mean(sq[:, n_pairs:].reshape((len(g.index),) + y0.shape[1:]), axis=-1)
    loss = 0.5 * loss + 0.5 * jnp.mean(per_lead.reshape(len(g.index), -1), axis=-1)
  return dict(zip(g.names, loss, strict=True))


# --------------------------------------------------------------------------------------------
# Rotation losses (eqs. 9 and 9.2) and pair sampling (the authors' code).


def dof_poses(spec: PoseSystemSpec, name: str, values: Array) -> Array:
  """Poses (K, pose_dim) whose DOF `name` takes `values` ((K,) or (K, 2)), other columns 0."""
  values = jnp.asarray(values, jnp.float32)
  cols = values if values.ndim == 2 else values[:, None]
  poses = jnp.zeros((cols.shape[0], spec.pose_dim), jnp.float32)
  return poses.at[:, spec.columns(name)].set(cols)


def pose_delta(spec: PoseSystemSpec, pose0: Array, pose1: Array) -> Array:
  """pose1 - pose0 per column, with periodic angles wrapped to [-pi, pi) (camrep's fix: the
  authors' raw difference turns a pair straddling 0/360 degrees into a ~2 pi move)."""
  delta = pose1 - pose0
  cols = [d.wrap_delta(delta[..., spec.columns(d.name)]) for d in spec.dofs]
  return jnp.concatenate(cols, axis=-1)


def sample_pairs(key: Array, spec: PoseSystemSpec, name: str, n: int) -> tuple[Array, Array]:
  """Extra pose pairs for the rotation loss of DOF `name`, in physical units (the authors' code).

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
  # Both ends in one embedding, mapped over the two ends (the grid is normalised and the
  # generators are built once); end 0 and end 1 draw from the two halves of split(key).
  ends = jnp.stack(jnp.broadcast_arrays(jnp.asarray(value0), jnp.asarray(value1)))
  if key is None:
    v0, v1 = jax.vmap(lambda x: embed_dof(params, spec, name, x, mode=mode))(ends)
  else:
    one = lambda x, k: embed_dof(params, spec, name, x, mode=mode, key=k)
    v0, v1 = jax.vmap(one)(ends, jax.random.split(key))
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

  Per DOF (position i in the spec): kd = fold_in(key, i), split into three keys for the extra
  pairs' values, their two ends' neighbours and the data pairs' (`dof_rotation_loss`).
  """
  return data_rotation_losses(
    key,
    params,
    spec,
    n_pairs=n_pairs,
    mode=mode,
    data_pairs=data_pairs,
    data_keys=lambda i: jax.random.split(jax.random.fold_in(key, i), 3)[2],
  )


def data_rotation_losses(
  key: Array,
  params: Params,
  spec: PoseSystemSpec,
  *,
  n_pairs: int,
  mode: str = "random",
  data_pairs: tuple[Array, Array] | None = None,
  data_keys: Callable[[Array], Array] | None = None,
) -> dict[str, Array]:
  """`rotation_losses` with data pairs over leading axes (e.g. scenes), each with its own keys.

  Args:
    data_pairs: (pose0, pose1), (..., m, pose_dim) each: m pairs per leading index; None: extra
      pairs only.
    data_keys: the DOF's position i in the spec (int32 scalar, traced) -> keys of the leading
      shape (...): the data pairs of DOF i at a leading index are `dof_rotation_loss`'s pairs
      with that key (split into their two ends' keys). Needed with `data_pairs`.

  Returns:
    {name: scalar}: the extra-pair loss, or with `data_pairs` 0.5 (extra) + 0.5 (mean over the
    leading indices of the data-pair loss).
  """
  losses = {}
  g = _group(spec)
  if g is not None:
    losses.update(
      _group_rotation_losses(key, params, spec, g, n_pairs, mode, data_pairs, data_keys)
    )
  for i, d in enumerate(spec.dofs):
    if d.stacking() is not None:
      continue
    ks, ke, _ = jax.random.split(jax.random.fold_in(key, i), 3)
    value0, value1 = d.sample_pairs(ks, n_pairs)
    loss = dof_rotation_loss(params, spec, d.name, value0, value1, mode=mode, key=ke)
    if data_pairs is not None:
      p0, p1 = data_pairs
      cols = spec.columns(d.name)
      x0, x1 = d.values(p0[..., cols]), d.values(p1[..., cols])
      one = lambda a, b, k, n=d.name: dof_rotation_loss(params, spec, n, a, b, mode=mode, key=k)
      per_lead = _vmap_n(one, p0.ndim - 2)(x0, x1, data_keys(i))
      loss = 0.5 * loss + 0.5 * jnp.mean(per_lead)
    losses[d.name] = loss
  return {n: losses[n] for n in spec.names}


def direction_loss(params: Params, spec: PoseSystemSpec, name: str, *, max_shift: int = 5):
  """L_rot,theta of eq. 9.2 for a binned polar DOF: B(theta + D) ~ exp(C D) B(theta).

  As the authors' code: every bin j and shift D in 1..max_shift (720 combinations),
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

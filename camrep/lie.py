"""Lie operators for the pose-shift generators of Zhu et al. (CVPR 2021).

A pose shift Delta along one degree of freedom acts on a pose sub-vector as the matrix
M(Delta) = exp(B Delta) (paper eq. 6), where B is a learned skew-symmetric, block-diagonal
generator (an element of the Lie algebra so(d); exp maps it into SO(d)). Following the authors'
code B is parameterised by the strict upper triangles of its blocks and is
kept as a stack of blocks (..., n_blocks, s, s): the full d x d matrix is never formed on hot paths.

All functions are pure and batched over leading axes; callers jit. Three ways to compute the
exponential are offered (`EXP_METHODS`):

  "expm"      jax.scipy.linalg.expm under vmap: the reference path of the design card.
  "taylor2"   I + tB + t^2 B^2 / 2 (paper eq. 7, the authors' code); `n_steps=N` splits a large
              move into N small ones and multiplies them (paper eq. 6).
  "spectral"  exact, via one decomposition per generator that serves any number of shifts t.
              Even s: the real Schur form B = Q Lam Q^T (`skew_schur`; Q orthogonal, Lam =
              s/2 plane rotations theta_k J), so exp(tB) v = Q R(t theta) Q^T v in real
              arithmetic: two s x s products and s/2 plane rotations per vector, the cost of
              "taylor2". Odd s: the complex eigenbasis of the Hermitian iB = V diag(w) V^H,
              exp(tB) = V diag(exp(-i t w)) V^H (`skew_eig`). Either way the derivative is a
              custom JVP through the fixed basis (Daleckii-Krein divided differences), never
              through the eigenvectors, so it is finite at B = 0 and at degenerate spectra
              (where eigh's own gradient is NaN), and per vector it is again only s x s
              products with per-generator matrices.

Conventions: generator blocks `B` have shape (..., s, s); shifts `t` broadcast against B's leading
axes; vectors `v` have shape (..., s). Functions whose name contains `blocks` take a block stack
(..., n_blocks, s, s) and flat vectors (..., n_blocks * s).

Every generator B must be skew-symmetric (B^T = -B), as `skew` builds it from free coefficients.
The functions here do not check it (they run inside jitted code, where a check would cost a
reduction or a host round trip): given a B that is not skew, "spectral" silently uses its skew
part (B - B^T) / 2 (a symmetric B gives the identity) while "expm" and "taylor2" use B as given,
and none of them is then a rotation. Callers holding a B from elsewhere check it once on the
host with `check_skew`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from camrep import spectral
from camrep.spectral import plane_pq_split, skew_eig, skew_schur  # noqa: F401  (public here)

EXP_METHODS = ("expm", "taylor2", "spectral")

Array = jax.Array


# --------------------------------------------------------------------------------------------
# Generators from free parameters.


def num_skew_params(block_size: int) -> int:
  """Number of free parameters of one s x s skew-symmetric block: s (s - 1) / 2."""
  return block_size * (block_size - 1) // 2


def block_size_from_num_params(num_params: int) -> int:
  """Inverse of `num_skew_params`; raises ValueError if `num_params` is not triangular."""
  s = int(round((1 + np.sqrt(1 + 8 * num_params)) / 2))
  if num_skew_params(s) != num_params:
    raise ValueError(f"{num_params} is not s(s-1)/2 for any block size s")
  return s


@functools.lru_cache(maxsize=64)
def _skew_gather_index(s: int) -> np.ndarray:
  """(s, s) indices into [0, u_1..u_n, -u_1..-u_n] that assemble U - U^T (row-major triangle)."""
  n = num_skew_params(s)
  iu, ju = np.triu_indices(s, 1)
  idx = np.zeros((s, s), np.int32)
  idx[iu, ju] = 1 + np.arange(n)
  idx[ju, iu] = 1 + n + np.arange(n)
  return idx


def skew(params: Array, *, block_size: int | None = None) -> Array:
  """Skew-symmetric blocks from their strict upper triangles ("hat").

  Block = U - U^T with U the row-major strict upper triangle filled from `params`
  (as the authors' code).

  Args:
    params: (..., s (s - 1) / 2) free parameters.
    block_size: s; inferred from the last axis when None.

  Returns:
    (..., s, s) skew-symmetric matrices.
  """
  params = jnp.asarray(params)
  n = params.shape[-1]
  s = block_size_from_num_params(n) if block_size is None else block_size
  if num_skew_params(s) != n:
    raise ValueError(f"params has {n} entries on its last axis, expected {num_skew_params(s)}")
  flat = jnp.concatenate([jnp.zeros_like(params[..., :1]), params, -params], axis=-1)
  return flat[..., _skew_gather_index(s)]


def check_skew(B: Array, *, atol: float | None = None) -> None:
  """Host-side check that generators are skew-symmetric: max |B + B^T| <= atol.

  Cheap (one pass over B) but not for jitted code: it reads the values back (a traced B raises
  jax's ConcretizationTypeError).

  Args:
    B: (..., s, s) generators.
    atol: tolerance; default 1e-5 (float32 and lower) or 1e-12 (float64) times max(1, max |B|).

  Raises:
    ValueError: B is not (..., s, s), holds non-finite values, or is not skew-symmetric (the
      message gives the largest |B + B^T|).
  """
  B = np.asarray(B)
  _check_square(B, "B")
  if not np.all(np.isfinite(B)):
    raise ValueError("B holds non-finite values")
  if atol is None:
    rel = 1e-12 if B.dtype == np.float64 else 1e-5
    atol = rel * max(1.0, float(np.max(np.abs(B), initial=0.0)))
  err = float(np.max(np.abs(B + np.swapaxes(B, -1, -2)), initial=0.0))
  if err > atol:
    raise ValueError(
      f"B must be skew-symmetric (B^T = -B); max |B + B^T| = {err:.3g} > atol = {atol:.3g} "
      "(build generators with `skew` from free coefficients)"
    )


def vee(B: Array) -> Array:
  """Inverse of `skew`: (..., s, s) -> (..., s (s - 1) / 2), reading the strict upper triangle."""
  B = jnp.asarray(B)
  _check_square(B, "B")
  iu, ju = np.triu_indices(B.shape[-1], 1)
  return B[..., iu, ju]


def init_generator(
  key: Array,
  shape: tuple[int, ...],
  block_size: int,
  *,
  stddev: float = 1e-3,
  dtype=jnp.float32,
) -> Array:
  """Free parameters of generators, i.i.d. N(0, stddev^2) as in the authors' code.

  Args:
    key: PRNG key.
    shape: leading shape, e.g. (n_blocks,) or (n_directions, n_blocks).
    block_size: s.
    stddev: standard deviation (authors: 0.001).
    dtype: float dtype.

  Returns:
    (*shape, s (s - 1) / 2) parameters; `skew` turns them into blocks.
  """
  return stddev * jax.random.normal(key, (*shape, num_skew_params(block_size)), dtype)


def block_diag(blocks: Array) -> Array:
  """(..., n, s, s) block stack -> (..., n s, n s) block-diagonal matrix (tests and plots only)."""
  blocks = jnp.asarray(blocks)
  n, s = blocks.shape[-3], blocks.shape[-1]
  eye = jnp.eye(n, dtype=blocks.dtype)
  full = jnp.einsum("...aij,ab->...aibj", blocks, eye)
  return full.reshape(*blocks.shape[:-3], n * s, n * s)


def matvec_blocks(B: Array, v: Array) -> Array:
  """Block-diagonal matrix-vector product.

  Args:
    B: (..., n, s, s) block stack.
    v: (..., n s) flat vectors.

  Returns:
    (..., n s), the product diag(B_1..B_n) v without forming the full matrix.
  """
  n, s = B.shape[-3], B.shape[-1]
  vb = _split_blocks(v, n, s)
  out = jnp.einsum("...bij,...bj->...bi", B, vb)
  return out.reshape(*out.shape[:-2], n * s)


# --------------------------------------------------------------------------------------------
# The exponential.


def exp_skew(B: Array, t: Array | float, *, method: str = "spectral", n_steps: int = 1) -> Array:
  """exp(t B) for skew-symmetric generators (paper eqs. 6-7).

  Args:
    B: (..., s, s) skew-symmetric generators, not checked (`check_skew`): only the skew part
      (B - B^T)/2 is used by "spectral"; "expm" and "taylor2" use B as given.
    t: shifts, broadcastable against B.shape[:-2]; e.g. t of shape (4, 1) with B of shape
      (6, s, s) gives (4, 6, s, s).
    method: one of `EXP_METHODS`.
    n_steps: for "taylor2" only: split the move into this many equal steps and multiply their
      Taylor approximations (paper eq. 6); 1 is the authors' single step.

  Returns:
    (*broadcast(t.shape, B.shape[:-2]), s, s) matrices; orthogonal with det +1 for the exact
    methods.
  """
  B, t = _check_B_t(B, t, method, n_steps)
  s = B.shape[-1]
  batch = jnp.broadcast_shapes(t.shape, B.shape[:-2])
  if method == "expm":
    A = t[..., None, None] * B
    A = jnp.broadcast_to(A, (*batch, s, s)).reshape(-1, s, s)
    return jax.vmap(jax.scipy.linalg.expm)(A).reshape(*batch, s, s)
  if method == "taylor2":
    eye = jnp.eye(s, dtype=B.dtype)
    h = (t / n_steps)[..., None, None]
    M = eye + h * B + (0.5 * h * h) * (B @ B)
    M = jnp.broadcast_to(M, (*batch, s, s))
    return M if n_steps == 1 else jnp.linalg.matrix_power(M, n_steps)
  # spectral: apply to the basis vectors; row k of the result is exp(tB) e_k.
  eye = jnp.eye(s, dtype=B.dtype)
  cols = spectral.apply(B[..., None, :, :], t[..., None], eye, None)
  return jnp.swapaxes(cols, -1, -2)


def apply_exp_skew(
  B: Array,
  t: Array | float,
  v: Array,
  *,
  method: str = "spectral",
  n_steps: int = 1,
  index: Array | None = None,
) -> Array:
  """exp(t B) v without forming matrices where that is cheaper.

  "taylor2" computes v + tBv + t^2 B(Bv)/2 (repeated `n_steps` times with t / n_steps, eq. 6);
  "spectral" rotates the planes of B's real Schur form (even s; the eigenbasis of iB for odd s);
  "expm" forms the matrices.

  Args:
    B: (..., s, s) skew-symmetric generators, not checked (`check_skew`); with `index`, a table
      (K, ..., s, s) indexed by `index`.
    t: shifts, broadcastable against the (indexed) generator's leading axes and v's.
    v: (..., s) vectors.
    method: one of `EXP_METHODS`.
    n_steps: Taylor steps for "taylor2" (paper eq. 6).
    index: optional int array (N...) selecting table entries: the generator of element n is
      B[index[n]]. With "spectral" the table is decomposed once, not once per element, which
      is what makes the 144-direction polar system cheap.

  Returns:
    (*broadcast, s) rotated vectors.
  """
  B, t = _check_B_t(B, t, method, n_steps)
  v = jnp.asarray(v, B.dtype)
  if v.shape[-1] != B.shape[-1]:
    raise ValueError(f"v has size {v.shape[-1]} on its last axis, B blocks are {B.shape[-1]}")
  if method == "spectral":
    return spectral.apply(B, t, v, None if index is None else jnp.asarray(index))
  if index is not None:
    B = B[index]
  if method == "expm":
    M = exp_skew(B, t, method="expm")
    return jnp.einsum("...ij,...j->...i", M, v)
  h = (t / n_steps)[..., None]

  def step(u):
    Bu = jnp.einsum("...ij,...j->...i", B, u)
    BBu = jnp.einsum("...ij,...j->...i", B, Bu)
    return u + h * Bu + (0.5 * h * h) * BBu

  shape = jnp.broadcast_shapes(B.shape[:-1], t.shape + (1,), v.shape)
  u = jnp.broadcast_to(v, shape)
  if n_steps == 1:
    return step(u)
  return jax.lax.fori_loop(0, n_steps, lambda _, u: step(u), u)


def exp_blocks(B: Array, t: Array | float, *, method: str = "spectral", n_steps: int = 1) -> Array:
  """exp(t B) for a block stack: B (..., n, s, s), t (...) -> (..., n, s, s).

  The same shift acts on every block (the blocks of one block-diagonal generator). The blocks
  must be skew-symmetric, as in `exp_skew`.
  """
  t = jnp.asarray(t, jnp.asarray(B).dtype)
  return exp_skew(B, t[..., None], method=method, n_steps=n_steps)


def apply_exp_blocks(
  B: Array,
  t: Array | float,
  v: Array,
  *,
  method: str = "spectral",
  n_steps: int = 1,
  index: Array | None = None,
) -> Array:
  """exp(t B) v for a block-diagonal generator kept as blocks.

  Args:
    B: (..., n, s, s) block stack of skew-symmetric blocks, not checked (`check_skew`); with
      `index`, a table (K, n, s, s).
    t: (...) shifts, one per flat vector.
    v: (..., n s) flat vectors.
    method, n_steps, index: as in `apply_exp_skew`.

  Returns:
    (..., n s) rotated vectors.
  """
  B = jnp.asarray(B)
  n, s = B.shape[-3], B.shape[-1]
  t = jnp.asarray(t, B.dtype)
  vb = _split_blocks(jnp.asarray(v, B.dtype), n, s)
  idx = None if index is None else jnp.asarray(index)[..., None]
  if idx is not None:
    # Index the table's leading axis per element, keeping the block axis: B[index][..., b].
    B = jnp.moveaxis(B, -3, 0)  # (n, K, s, s)
    out = jax.vmap(
      lambda Bb, vbb: apply_exp_skew(Bb, t, vbb, method=method, n_steps=n_steps, index=index),
      in_axes=(0, -2),
      out_axes=-2,
    )(B, vb)
  else:
    out = apply_exp_skew(B, t[..., None], vb, method=method, n_steps=n_steps)
  return out.reshape(*out.shape[:-2], n * s)


# --------------------------------------------------------------------------------------------
# Helpers.


def _split_blocks(v: Array, n: int, s: int) -> Array:
  if v.shape[-1] != n * s:
    raise ValueError(f"vector size {v.shape[-1]} != n_blocks * block_size = {n} * {s}")
  return v.reshape(*v.shape[:-1], n, s)


def _check_square(B: Array, name: str):
  if B.ndim < 2 or B.shape[-1] != B.shape[-2]:
    raise ValueError(f"{name} must have shape (..., s, s), got {B.shape}")


def _check_B_t(B, t, method, n_steps):
  B = jnp.asarray(B)
  if not jnp.issubdtype(B.dtype, jnp.floating):
    B = B.astype(jnp.float32)
  _check_square(B, "B")
  if method not in EXP_METHODS:
    raise ValueError(f"unknown exp method {method!r}; choose one of {EXP_METHODS}")
  if n_steps < 1 or int(n_steps) != n_steps:
    raise ValueError(f"n_steps must be a positive integer, got {n_steps}")
  if n_steps != 1 and method != "taylor2":
    raise ValueError("n_steps splits moves for method='taylor2' only (the others are exact)")
  return B, jnp.asarray(t, B.dtype)

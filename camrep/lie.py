"""Lie operators for the pose-shift generators of Zhu et al. (CVPR 2021).

A pose shift Delta along one degree of freedom acts on a pose sub-vector as the matrix
M(Delta) = exp(B Delta) (paper eq. 6), where B is a learned skew-symmetric, block-diagonal
generator (an element of the Lie algebra so(d); exp maps it into SO(d)). Following the authors'
code (digest section 1.1) B is parameterised by the strict upper triangles of its blocks and is
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

  Block = U - U^T with U the row-major strict upper triangle filled from `params` (digest 1.1).

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
  """Free parameters of generators, i.i.d. N(0, stddev^2) as in the authors' code (digest 1.1).

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
  cols = _spectral(B[..., None, :, :], t[..., None], eye, None)
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
    return _spectral(B, t, v, None if index is None else jnp.asarray(index))
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
# Spectral method. Odd s: eigenbasis of iB and its custom JVP (`_spectral_apply`).


def _spectral(B, t, v, index):
  """Real Schur planes for even s (`_plane_apply`), the complex eigenbasis for odd s."""
  return (_plane_apply if B.shape[-1] % 2 == 0 else _spectral_apply)(B, t, v, index)


def _complex_dtype(dtype):
  return jnp.complex128 if jnp.dtype(dtype) == jnp.float64 else jnp.complex64


def skew_eig(B: Array) -> tuple[Array, Array]:
  """Eigendecomposition of iB for skew-symmetric B: iB = V diag(w) V^H.

  Args:
    B: (..., s, s) real; its skew part is used.

  Returns:
    w: (..., s) real eigenvalues (ascending), V: (..., s, s) complex unitary eigenvectors.
    Then exp(tB) = V diag(exp(-i t w)) V^H.
  """
  B = jnp.asarray(B)
  Bs = 0.5 * (B - jnp.swapaxes(B, -1, -2))
  H = 1j * Bs.astype(_complex_dtype(B.dtype))
  return jnp.linalg.eigh(H, symmetrize_input=False)


def _near_threshold(dtype) -> float:
  # Eigenvalue gaps below this use the second-order expansion of the divided difference
  # (relative error ~ (t gap)^4 / 1920), above it the exact quotient (relative rounding error
  # ~ eps / (t gap)); the balance point for |t| ~ 1.
  return 1e-4 if jnp.dtype(dtype) == jnp.float64 else 3e-2


@jax.custom_jvp
def _spectral_apply(B, t, v, index):
  """exp(t B[index]) v via the eigenbasis of iB. B, t, v broadcast as in `apply_exp_skew`."""
  w, V = skew_eig(B)
  if index is not None:
    w, V = w[index], V[index]
  cdt = V.dtype
  a = jnp.einsum("...ji,...j->...i", V.conj(), v.astype(cdt))
  e = jnp.exp(-1j * t[..., None].astype(cdt) * w.astype(cdt))
  return jnp.einsum("...ij,...j->...i", V, e * a).real.astype(v.dtype)


def _is_zero(x) -> bool:
  return isinstance(x, jax.custom_derivatives.SymbolicZero)


def _spectral_apply_jvp(primals, tangents):
  """Daleckii-Krein: d exp(tB) = V (F o (V^H dB V)) V^H, F_ij = (e_i - e_j) / (w_i - w_j).

  With e_k = exp(-i t w_k) the divided differences split into table-level matrices so that the
  per-element work is matrix-vector products only:
    far pairs  (|w_i - w_j| >= tau):  (F o X) a = e o (Y a) - Y (e o a),  Y = X o 1/(w_i - w_j);
    near pairs (|w_i - w_j| <  tau):  F_ij ~ -i t h_i h_j (1 - t^2 (w_i - w_j)^2 / 24),
                                      h_k = exp(-i t w_k / 2)  (exact at equal eigenvalues).
  Nothing divides by an eigenvalue gap below tau, so the tangent is finite for every B.
  """
  B, t, v, index = primals
  dB, dt, dv, _ = tangents
  w, V = skew_eig(B)
  cdt = V.dtype
  tau = _near_threshold(B.dtype)
  gap = w[..., :, None] - w[..., None, :]
  near = jnp.abs(gap) < tau
  if index is not None:
    wg, Vg = w[index], V[index]
  else:
    wg, Vg = w, V
  tc = t[..., None].astype(cdt)
  a = jnp.einsum("...ji,...j->...i", Vg.conj(), v.astype(cdt))
  e = jnp.exp(-1j * tc * wg.astype(cdt))
  c = e * a
  y = jnp.einsum("...ij,...j->...i", Vg, c).real.astype(v.dtype)

  dc = jnp.zeros(jnp.broadcast_shapes(c.shape, v.shape), cdt)
  if not _is_zero(dv):
    da = jnp.einsum("...ji,...j->...i", Vg.conj(), dv.astype(cdt))
    dc = dc + e * da
  if not _is_zero(dt):
    dc = dc + (-1j * wg.astype(cdt)) * c * dt[..., None].astype(cdt)
  if not _is_zero(dB):
    dBs = 0.5 * (dB - jnp.swapaxes(dB, -1, -2))
    X = V.conj().swapaxes(-1, -2) @ (1j * dBs.astype(cdt)) @ V
    safe_gap = jnp.where(near, 1.0, gap)
    Y = jnp.where(near, 0.0, X / safe_gap.astype(cdt))
    Z = jnp.where(near, X, 0.0)
    Z2 = Z * (gap * gap).astype(cdt)
    if index is not None:
      Y, Z, Z2 = Y[index], Z[index], Z2[index]
    h = jnp.exp(-0.5j * tc * wg.astype(cdt))
    mv = lambda M, x: jnp.einsum("...ij,...j->...i", M, x)
    ha = h * a
    dc = dc + e * mv(Y, a) - mv(Y, c)
    dc = dc - 1j * tc * h * (mv(Z, ha) - (tc * tc / 24.0) * mv(Z2, ha))
  dy = jnp.einsum("...ij,...j->...i", Vg, dc).real.astype(v.dtype)
  return y, jnp.broadcast_to(dy, y.shape)


_spectral_apply.defjvp(_spectral_apply_jvp, symbolic_zeros=True)


# --------------------------------------------------------------------------------------------
# Spectral method, even s: real Schur planes and their custom JVP (`_plane_apply`).


def skew_schur(B: Array) -> tuple[Array, Array]:
  """Real Schur form of skew-symmetric B of even size s: B = Q Lam Q^T (to rounding).

  Q is orthogonal and its columns are in "plane" layout: plane k (k < s/2) is spanned by
  columns k and s/2 + k, and Lam acts on it as theta_k J, J = [[0, -1], [1, 0]], i.e.
  Lam[s/2 + k, k] = theta_k = -Lam[k, s/2 + k] and Lam is zero elsewhere. In complex plane
  coordinates xi_k = c_k + i c_{s/2+k} (c = Q^T v), exp(tB) multiplies xi_k by exp(i t theta_k).

  Built from `skew_eig`: for the s/2 eigenpairs (w, z) of iB with the largest w, B z = -i w z,
  so sqrt(2) (Re z, Im z) spans an invariant plane. Where eigenvectors are not separated from
  their conjugates (w ~ 0, e.g. B = 0, where z may be real) those columns are rank deficient or
  not orthonormal, so Q is taken as the orthogonal polar factor U V^T of their SVD (which
  completes the null space) and theta is read off Q^T B Q, not from w. theta may be negative.
  Not differentiable in any useful sense (eigh's gradient is NaN at degenerate spectra); the
  spectral JVP never differentiates it.

  Args:
    B: (..., s, s) real, s even; its skew part is used.

  Returns:
    Q: (..., s, s) orthogonal, theta: (..., s/2) real.
  """
  Q, _, theta2 = _schur_planes(B)
  return Q, theta2[..., : B.shape[-1] // 2]


@functools.lru_cache(maxsize=16)
def _theta_selector(s: int) -> np.ndarray:
  """(s, s, s) S with sum_ij L_ij S_mij = (L[h+k, k] - L[k, h+k]) / 2, k = m mod h."""
  h = s // 2
  S = np.zeros((s, s, s))
  for m in range(s):
    k = m % h
    S[m, h + k, k], S[m, k, h + k] = 0.5, -0.5
  return S


def _schur_planes(B: Array) -> tuple[Array, Array, Array]:
  """`skew_schur` as (Q, Q^T, theta2) with theta2 = [theta, theta] (..., s), as `_rot` wants it.

  Q^T is formed as its own product V U^T so that XLA's CPU backend sees a plain row-major
  operand for the per-element GEMMs (it folds a transpose into the dot and then falls back from
  its fast GEMM path)."""
  B = jnp.asarray(B)
  _check_square(B, "B")
  s = B.shape[-1]
  if s % 2:
    raise ValueError(f"skew_schur needs an even block size, got {s}")
  h = s // 2
  Bs = 0.5 * (B - jnp.swapaxes(B, -1, -2))
  _, V = skew_eig(Bs)
  Z = V[..., h:]  # eigenvalues ascending: the w >= 0 half
  W = 2.0**0.5 * jnp.concatenate([Z.real, Z.imag], axis=-1).astype(B.dtype)
  U, _, Vh = jnp.linalg.svd(W)
  Q = U @ Vh
  Qt = jnp.swapaxes(Vh, -1, -2) @ jnp.swapaxes(U, -1, -2)
  L = Qt @ Bs @ Q
  # A contraction rather than diagonal + concatenate: XLA then materialises theta instead of
  # fusing the gathers into (and de-vectorising) the per-element rotation loop.
  theta2 = jnp.einsum("...ij,mij->...m", L, _theta_selector(s).astype(B.dtype))
  return Q, Qt, theta2


def plane_pq_split(X: Array) -> tuple[Array, Array]:
  """Complex-linear and anti-linear parts of a real (..., s, s) matrix in plane layout.

  With xi_l = c_l + i c_{h+l} (h = s/2), the 2 x 2 sub-block of X from plane l to plane k,
  [[a, b], [c, d]] = X[[k, h+k]][:, [l, h+l]], maps xi_l to p_kl xi_l + q_kl conj(xi_l) with
  p = (a + d + i (c - b)) / 2 and q = (a - d + i (c + b)) / 2.

  Returns:
    p, q: (..., h, h) complex.
  """
  h = X.shape[-1] // 2
  a, b = X[..., :h, :h], X[..., :h, h:]
  c, d = X[..., h:, :h], X[..., h:, h:]
  return jax.lax.complex(0.5 * (a + d), 0.5 * (c - b)), jax.lax.complex(
    0.5 * (a - d), 0.5 * (c + b)
  )


def _real_linear(P: Array) -> Array:
  """Real (s, s) matrix of xi -> P xi in plane layout."""
  re, im = P.real, P.imag
  return jnp.concatenate([jnp.concatenate([re, -im], -1), jnp.concatenate([im, re], -1)], -2)


def _real_antilinear(P: Array) -> Array:
  """Real (s, s) matrix of xi -> P conj(xi) in plane layout."""
  re, im = P.real, P.imag
  return jnp.concatenate([jnp.concatenate([re, im], -1), jnp.concatenate([im, -re], -1)], -2)


def _rot(c: Array, cos: Array, sin: Array) -> Array:
  """Rotate each plane of c (T, s, E) (plane layout on axis -2) by its angle; cos, sin (T, s, E)
  hold each plane's cosine and sine twice (rows k and s/2 + k). Full-height factors keep this
  one vectorised elementwise loop (slicing them per half made XLA's CPU fusion recompute the
  sines per output, ~4x slower)."""
  h = c.shape[-2] // 2
  return c * cos + jnp.concatenate([-c[..., h:, :], c[..., :h, :]], -2) * sin


def _sincos(x: Array) -> tuple[Array, Array]:
  """(sin x, cos x). float32: Cody-Waite reduction by pi/2 and the Cephes minimax polynomials on
  [-pi/4, pi/4] (abs error <~ 1e-7 for |x| <~ 1e4), as plain fused arithmetic: XLA's CPU sin and
  cos cost ~10x more and dominated the spectral method. Other dtypes: jnp.sin, jnp.cos."""
  if x.dtype != jnp.float32:
    return jnp.sin(x), jnp.cos(x)
  f = np.float32
  k = jnp.round(x * f(2 / np.pi))
  r = ((x - k * f(1.5703125)) - k * f(4.837512969970703125e-4)) - k * f(7.54978995489188216e-8)
  z = r * r
  s = r + r * z * (f(-1.6666654611e-1) + z * (f(8.3321608736e-3) + z * f(-1.9515295891e-4)))
  c = (
    1
    - 0.5 * z
    + z
    * z
    * (f(4.166664568298827e-2) + z * (f(-1.388731625493765e-3) + z * f(2.443315711809948e-5)))
  )
  q = k.astype(jnp.int32) & 3  # quadrant
  odd = (q & 1) == 1
  s, c = jnp.where(odd, c, s), jnp.where(odd, s, c)
  return jnp.where(q >= 2, -s, s), jnp.where((q == 1) | (q == 2), -c, c)


def _plane_apply(B, t, v, index):
  """exp(t B[index]) v for even s via the real Schur planes (`_plane_core`).

  Rearranges the broadcast problem into the column layout the core wants: T "table rows" (the
  axes along which the generator varies: B's batch axes, or `index`'s) x E elements sharing a
  generator, vectors as (T, s, E). Matrix-vector products are then plain batched GEMMs and the
  elementwise work runs along the contiguous element axis; XLA's CPU backend otherwise spends
  most of the time in strided transposes between (elements, blocks, s) and block-major dots.
  """
  s = B.shape[-1]
  sel = B.shape[:-2] if index is None else index.shape
  full = jnp.broadcast_shapes(sel, t.shape, v.shape[:-1])
  r = len(full)
  sel_al = (1,) * (r - len(sel)) + tuple(sel)
  tdims = [i for i in range(r) if sel_al[i] != 1]
  edims = [i for i in range(r) if sel_al[i] == 1]
  tsh, esh = [full[i] for i in tdims], [full[i] for i in edims]
  T, E = int(np.prod(tsh, dtype=int)), int(np.prod(esh, dtype=int))
  t3 = jnp.broadcast_to(t, full).transpose(tdims + edims).reshape(T, E)
  v3 = jnp.broadcast_to(v, (*full, s)).transpose(tdims + [r] + edims).reshape(T, s, E)
  if index is None:
    tab, idx = B.reshape(T, s, s), None
  else:
    tab, idx = B, index.reshape(T)
  y3 = _plane_core(tab, t3, v3, idx)
  y = y3.reshape(*tsh, s, *esh)
  inv = np.argsort(tdims + [r] + edims)
  return y.transpose(*inv)


@jax.custom_jvp
def _plane_core(B, t, v, index):
  """exp(t B[index]) v in column layout: B (K, s, s) table, t (T, E), v (T, s, E), index (T,)
  selecting table rows (None: K = T)."""
  Q, Qt, theta2 = _schur_planes(B)
  if index is not None:
    Q, Qt, theta2 = Q[index], Qt[index], theta2[index]
  sin, cos = _sincos(theta2[..., None] * t[..., None, :])
  return Q @ _rot(Qt @ v, cos, sin)


def _plane_tables(Q, Qt, theta, dB, tau):
  """Table-level matrices of the dB tangent (see `_plane_core_jvp`), linear in dB: A (K, s, s)
  and N (K, 2 s, s) = [N; N2] stacked on rows."""
  dBs = 0.5 * (dB - jnp.swapaxes(dB, -1, -2))
  X = Qt @ dBs @ Q
  p, q = plane_pq_split(X)
  gp = theta[..., None, :] - theta[..., :, None]  # th_l - th_k
  gm = theta[..., :, None] + theta[..., None, :]  # th_k + th_l
  nearp, nearm = jnp.abs(gp) < tau, jnp.abs(gm) < tau
  Pp = jnp.where(nearp, 0.0, -1j * p / jnp.where(nearp, 1.0, gp))
  Pm = jnp.where(nearm, 0.0, -1j * q / jnp.where(nearm, 1.0, gm))
  Zp, Zm = jnp.where(nearp, p, 0.0), jnp.where(nearm, q, 0.0)
  A = _real_linear(Pp) - _real_antilinear(Pm)
  N = _real_linear(Zp) + _real_antilinear(Zm)
  N2 = _real_linear(Zp * gp * gp) + _real_antilinear(Zm * gm * gm)
  return A, jnp.concatenate([N, N2], -2)


def _plane_core_jvp(primals, tangents):
  """Daleckii-Krein in the real Schur planes (`skew_schur`: B = Q Lam Q^T).

  With c = Q^T v, xi_k its complex plane coordinates, eps_k = exp(i t theta_k) and
  X = Q^T dB Q split per plane pair into p_kl xi_l + q_kl conj(xi_l) (`plane_pq_split`),
    d[exp(tB) v]_k = sum_l p_kl F+_kl xi_l + q_kl F-_kl conj(xi_l)  (then mapped back by Q),
    F+_kl = int_0^t e^{i((t-s) th_k + s th_l)} ds = (eps_l - eps_k) / (i (th_l - th_k)),
    F-_kl = int_0^t e^{i((t-s) th_k - s th_l)} ds = (eps_k - conj(eps_l)) / (i (th_k + th_l)).
  Factorised so that the per-element work is real s x s GEMMs with table-level matrices
  (e = eps - 1, h = exp(i t theta / 2), w = h o xi; "o" acts per plane as a complex product):
    far pairs  (|gap| >= tau):  A(e o xi) - e o A(xi),  A(z) = P+ z - P- conj(z),
                                P+ = p / (i (th_l - th_k)),  P- = q / (i (th_k + th_l));
                                (eps_l - eps_k = e_l - e_k keeps the cancellation relative to
                                |t theta| instead of 1, which matters in float32 for small t);
    near pairs (|gap| <  tau):  F+ ~ t h_k h_l (1 - t^2 gap^2 / 24), F- ~ t h_k conj(h_l) (...)
                                -> h o (t N(w) - t^3 / 24 N2(w))  (N, N2 real forms of the
                                near p, q and of p gap^2, q gap^2; exact at gap = 0, so the
                                diagonal, always near, is exact).
  Nothing divides by a gap below tau, so the tangent is finite for every B. dt: i theta eps xi;
  dv: exp(tB) dv. Only (T, s, E) arrays are per element; everything (s, s) is per table row
  (with `index`, gathered per element, as in `_spectral_apply_jvp`).
  """
  B, t, v, index = primals
  dB, dt, dv, _ = tangents
  Q, Qt, theta2 = _schur_planes(B)
  Qg, Qtg, thg = (Q[index], Qt[index], theta2[index]) if index is not None else (Q, Qt, theta2)
  tt = t[..., None, :]
  phi = thg[..., None] * tt
  # Half-angle rotation h = exp(i t theta / 2) for the near pairs; the full one from it.
  hsin, hcos = _sincos(0.5 * phi)
  sin, cos = 2 * hsin * hcos, 1 - 2 * hsin * hsin
  c = Qtg @ v
  u = _rot(c, cos, sin)
  y = Qg @ u

  # Tangent-side products are written with the transposed factor so that their transposes (what
  # reverse mode runs) are the row-major GEMMs Q @ x and Q^T @ x (see `_schur_planes`).
  du = jnp.zeros_like(u)
  if not _is_zero(dv):
    du = du + _rot(jnp.swapaxes(Qg, -1, -2) @ dv, cos, sin)
  if not _is_zero(dt):
    du = du + _rot(u, 0.0, thg[..., None] * dt[..., None, :])  # i theta u dt per plane
  if not _is_zero(dB):
    tau = _plane_near_threshold(t)
    A, N = _plane_tables(Q, Qt, theta2[..., : B.shape[-1] // 2], dB, tau)
    if index is not None:
      A, N = A[index], N[index]
    s = c.shape[-2]
    Nw = N @ _rot(c, hcos, hsin)
    near = tt * Nw[..., :s, :] - (tt * tt * tt / 24.0) * Nw[..., s:, :]
    # eps_l - eps_k = (eps_l - 1) - (eps_k - 1): the far pairs' cancellation is then relative to
    # |eps - 1| ~ |t theta| rather than 1 (cos - 1 = -2 sin^2 of the half angle, no cancellation).
    cm1 = -2 * hsin * hsin
    du = du + A @ _rot(c, cm1, sin) - _rot(A @ c, cm1, sin) + _rot(near, hcos, hsin)
  return y, jnp.swapaxes(Qtg, -1, -2) @ du


_plane_core.defjvp(_plane_core_jvp, symbolic_zeros=True)


def _plane_near_threshold(t: Array) -> Array:
  """Gap threshold tau = kappa / max |t| of the near-pair expansion, so that |t gap| < kappa on
  every near pair whatever the shifts: the expansion's relative error is below
  (t gap)^4 / 1920 <= kappa^4 / 1920, and the far quotient's relative rounding error is about
  eps max(|theta|, 2 / |t|) / gap <= eps max(|t theta|, 2) / kappa. kappa balances the two:
  0.2 in float32 (4e-7 / 8e-7; the bench's gradient is then within ~2e-6 of float64, against
  ~6e-6 with a fixed tau = 3e-2), 3e-3 in float64 (~4e-14 / ~1e-13)."""
  kappa = 3e-3 if t.dtype == jnp.float64 else 0.2
  tmax = jnp.max(jnp.abs(t), initial=0.0)
  return kappa / jnp.maximum(tmax, jnp.finfo(t.dtype).tiny)


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

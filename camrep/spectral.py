"""The exact exponential of `camrep.lie` ("spectral"): exp(t B) v for skew-symmetric B through one
decomposition per generator, with custom JVPs that never differentiate the eigenvectors.

Even block size s: the real Schur form B = Q Lam Q^T (`skew_schur`), exp(t B) v = Q R(t theta)
Q^T v, and the Daleckii-Krein derivative in those planes (`_plane_apply`). Odd s: the complex
eigenbasis of the Hermitian iB (`skew_eig`) and the same derivative there (`_spectral_apply`).
Both are finite at B = 0 and at degenerate spectra. `camrep.lie.apply_exp_skew(...,
method="spectral")` calls `apply`; shapes and broadcasting are as documented there.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array


# --------------------------------------------------------------------------------------------
# Odd s: eigenbasis of iB and its custom JVP (`_spectral_apply`).


def apply(B, t, v, index):
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
  return per_matrix(functools.partial(jnp.linalg.eigh, symmetrize_input=False), H)


def per_matrix(fn, X: Array):
  """fn applied to one (s, s) matrix of X (..., s, s) at a time, outputs restacked on X's batch.

  A batched LAPACK decomposition (eigh, svd) would be one call over the whole batch, but jaxlib
  0.10's CPU kernels split a batch above ~2e5 FLOP (five 16 x 16 complex eigh) into tasks on
  XLA:CPU's intra-op thread pool and block the calling pool thread until those tasks end. The
  generator tables of the DOFs are independent, so XLA runs their decompositions at the same
  time; once every pool thread (2 on a 2-core machine) blocks in such a call, no thread is left
  to run the queued tasks and the program never returns. A call with one matrix never splits.
  Each matrix goes through the same LAPACK routine either way, so results are bit-identical,
  and the loop costs ~3% of the decompositions' time (6 x 144 generators of size 16).

  Args:
    fn: (s, s) -> pytree of arrays (e.g. `jnp.linalg.eigh`).
    X: (..., s, s).

  Returns:
    fn's pytree, each leaf with X's batch axes in front of its own.
  """
  batch = X.shape[:-2]
  if int(np.prod(batch, dtype=int)) <= 1:
    return fn(X)
  out = jax.lax.map(fn, X.reshape(-1, *X.shape[-2:]))
  return jax.tree.map(lambda y: y.reshape(*batch, *y.shape[1:]), out)


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
  if B.ndim < 2 or B.shape[-1] != B.shape[-2]:
    raise ValueError(f"B must have shape (..., s, s), got {B.shape}")
  s = B.shape[-1]
  if s % 2:
    raise ValueError(f"skew_schur needs an even block size, got {s}")
  h = s // 2
  Bs = 0.5 * (B - jnp.swapaxes(B, -1, -2))
  _, V = skew_eig(Bs)
  Z = V[..., h:]  # eigenvalues ascending: the w >= 0 half
  W = 2.0**0.5 * jnp.concatenate([Z.real, Z.imag], axis=-1).astype(B.dtype)
  U, _, Vh = per_matrix(jnp.linalg.svd, W)
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

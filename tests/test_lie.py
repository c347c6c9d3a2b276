"""Property tests of camrep.lie against scipy.linalg.expm, in float64 (jaxlie style)."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from camrep import lie, spectral
from tests.utils import (
  assert_close,
  general_lie_test,
  jac_numerical,
  sample_generator,
  stable_seed,
  x64,
)

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]

# Compilation (expm, eigh, decode) dominates these small shapes; numerics are unchanged.
pytestmark = pytest.mark.usefixtures("fast_compile")


def _expm_ref(B, t):
  """scipy oracle: exp(t B) over broadcast batch axes."""
  B = np.asarray(B)
  t = np.asarray(t)
  batch = np.broadcast_shapes(t.shape, B.shape[:-2])
  Bb = np.broadcast_to(B, (*batch, *B.shape[-2:])).reshape(-1, *B.shape[-2:])
  tb = np.broadcast_to(t, batch).reshape(-1)
  out = np.stack([scipy.linalg.expm(ti * Bi) for ti, Bi in zip(tb, Bb, strict=True)])
  return out.reshape(*batch, *B.shape[-2:])


def _tol(method, regime):
  # taylor2 is compared with the exponential only where its truncation error is negligible.
  return 1e-10 if method != "taylor2" else (1e-12 if regime == "near_zero" else None)


# ---------------------------------------------------------------------------- generators


def test_skew_vee_roundtrip():
  with x64():
    _skew_vee_roundtrip()


def _skew_vee_roundtrip():
  rng = np.random.default_rng(0)
  for s in (2, 3, 8, 16):
    p = rng.normal(size=(4, 5, lie.num_skew_params(s)))
    B = lie.skew(p)
    assert B.shape == (4, 5, s, s)
    assert_close(B, -np.swapaxes(B, -1, -2), atol=0)
    assert_close(lie.vee(B), p, atol=0)
    assert_close(np.triu(B[0, 0], 1)[np.triu_indices(s, 1)], p[0, 0], atol=0)


def test_skew_rejects_wrong_size():
  with pytest.raises(ValueError, match="not s\\(s-1\\)/2"):
    lie.skew(np.zeros(7))
  with pytest.raises(ValueError, match="expected 6"):
    lie.skew(np.zeros(7), block_size=4)


def test_init_generator_shape_and_scale():
  p = lie.init_generator(jax.random.key(0), (144, 6), 16)
  assert p.shape == (144, 6, 120) and p.dtype == jnp.float32
  assert 0.0008 < float(jnp.std(p)) < 0.0012


def test_block_diag_and_matvec_blocks():
  with x64():
    _block_diag_and_matvec_blocks()


def _block_diag_and_matvec_blocks():
  rng = np.random.default_rng(1)
  B = sample_generator(rng, (2, 3), 4, "normal")  # (2, n=3, 4, 4)
  v = rng.normal(size=(2, 12))
  full = lie.block_diag(B)
  assert full.shape == (2, 12, 12)
  assert_close(full[0], scipy.linalg.block_diag(*B[0]), atol=0)
  assert_close(lie.matvec_blocks(B, v), np.einsum("bij,bj->bi", full, v), atol=1e-12)


# ---------------------------------------------------------------------------- exp vs oracle


def test_seeds_are_fixed_across_processes():
  """The property tests' seeds must not come from the salted `hash` of strings: the same
  (method, batch, regime) gives the same seed in every process, so a failure replays."""
  assert stable_seed("spectral", (3, 1, 2), "near_zero") == 914256524
  assert stable_seed("expm", (), "normal") == 3703809839
  assert stable_seed("expm", (), "normal") != stable_seed("expm", (1,), "normal")


@general_lie_test
def test_exp_matches_scipy(method, batch, regime):
  rng = np.random.default_rng(stable_seed(method, batch, regime))
  for s in (2, 3, 8):
    B = sample_generator(rng, batch, s, regime)
    t = rng.uniform(-1.5, 1.5, size=batch)
    out = lie.exp_skew(B, t, method=method)
    assert out.shape == (*batch, s, s) and out.dtype == jnp.float64
    tol = _tol(method, regime)
    if tol is None:  # taylor2 at finite t: compare with its own formula
      tb = np.asarray(t)[..., None, None]
      ref = np.eye(s) + tb * B + 0.5 * tb**2 * (B @ B)
      assert_close(out, ref, atol=1e-12)
    else:
      assert_close(out, _expm_ref(B, t), atol=tol)


@general_lie_test
def test_exact_methods_orthogonal_det_one(method, batch, regime):
  if method == "taylor2":
    pytest.skip("taylor2 is not orthogonal: M^T M = I + t^4 B^4 / 4")
  rng = np.random.default_rng(1)
  B = sample_generator(rng, batch, 16, regime)
  M = np.asarray(lie.exp_skew(B, 0.7, method=method))
  assert_close(np.swapaxes(M, -1, -2) @ M, np.broadcast_to(np.eye(16), M.shape), atol=1e-12)
  assert_close(np.linalg.det(M), np.ones(batch), atol=1e-12)


@general_lie_test
def test_group_law_and_identity(method, batch, regime):
  if method == "taylor2":
    pytest.skip("taylor2 satisfies the group law only to O(t^3)")
  rng = np.random.default_rng(2)
  B = sample_generator(rng, batch, 8, regime)
  s, t = 0.3, -1.1
  Ms, Mt, Mst = (np.asarray(lie.exp_skew(B, x, method=method)) for x in (s, t, s + t))
  assert_close(Ms @ Mt, Mst, atol=1e-12)
  assert_close(
    lie.exp_skew(B, 0.0, method=method), np.broadcast_to(np.eye(8), Ms.shape), atol=1e-14
  )
  M_neg = np.asarray(lie.exp_skew(B, -t, method=method))
  assert_close(M_neg, np.swapaxes(Mt, -1, -2), atol=1e-12)
  assert_close(M_neg @ Mt, np.broadcast_to(np.eye(8), Mt.shape), atol=1e-12)


@general_lie_test
def test_apply_equals_matrix_product(method, batch, regime):
  rng = np.random.default_rng(3)
  B = sample_generator(rng, batch, 8, regime)
  t = rng.uniform(-1, 1, size=batch)
  v = rng.normal(size=(*batch, 8))
  M = np.asarray(lie.exp_skew(B, t, method=method))
  out = lie.apply_exp_skew(B, t, v, method=method)
  assert out.shape == (*batch, 8)
  assert_close(out, np.einsum("...ij,...j->...i", M, v), atol=1e-12)
  # Rotation preserves norms (exact methods).
  if method != "taylor2":
    assert_close(np.linalg.norm(out, axis=-1), np.linalg.norm(v, axis=-1), atol=1e-12)


def test_broadcasting_shapes():
  """t (4, 1) with B (6, s, s) gives (4, 6, s, s), for every method (the issue's example)."""
  rng = np.random.default_rng(4)
  B = sample_generator(rng, (6,), 5, "normal").astype(np.float32)
  t = rng.uniform(size=(4, 1)).astype(np.float32)
  exp = jax.jit(lie.exp_skew, static_argnames="method")  # as the runs call them
  apply = jax.jit(lie.apply_exp_skew, static_argnames="method")
  for method in lie.EXP_METHODS:
    M = exp(B, t, method=method)
    assert M.shape == (4, 6, 5, 5) and M.dtype == jnp.float32
    v = rng.normal(size=(5,)).astype(np.float32)
    assert apply(B, t, v, method=method).shape == (4, 6, 5)


def test_blocks_match_full_block_diagonal_expm():
  with x64():
    rng = np.random.default_rng(5)
    B = sample_generator(rng, (3, 6), 4, "normal")  # 3 generators of 6 blocks of 4 x 4
    t = rng.uniform(-1, 1, size=(3,))
    v = rng.normal(size=(3, 24))
    ref = np.stack(
      [scipy.linalg.expm(t[i] * scipy.linalg.block_diag(*B[i])) @ v[i] for i in range(3)]
    )
    apply = jax.jit(lie.apply_exp_blocks, static_argnames="method")  # as the runs call them
    exp = jax.jit(lie.exp_blocks, static_argnames="method")
    for method in ("expm", "spectral"):
      assert_close(apply(B, t, v, method=method), ref, atol=1e-12)
      full = lie.block_diag(exp(B, t, method=method))
      assert_close(np.einsum("bij,bj->bi", full, v), ref, atol=1e-12)


def test_indexed_table_equals_gather():
  with x64():
    rng = np.random.default_rng(6)
    table = sample_generator(rng, (10, 3), 4, "normal")  # (K=10, n_blocks=3, 4, 4)
    idx = rng.integers(0, 10, size=(7,))
    t = rng.uniform(-1, 1, size=(7,))
    v = rng.normal(size=(7, 12))
    apply = jax.jit(lie.apply_exp_blocks, static_argnames="method")  # as the runs call it
    for method in lie.EXP_METHODS:
      ref = apply(table[idx], t, v, method=method)
      out = apply(table, t, v, method=method, index=idx)
      assert_close(out, ref, atol=1e-12)


def test_taylor2_error_grows_like_t_cubed():
  with x64():
    B = sample_generator(np.random.default_rng(7), (), 16, "normal")
    ts = np.array([1e-3, 1e-2, 1e-1])
    errs = [
      np.abs(lie.exp_skew(B, t, method="taylor2") - scipy.linalg.expm(t * B)).max() for t in ts
    ]
    slopes = np.diff(np.log(errs)) / np.diff(np.log(ts))
    np.testing.assert_allclose(slopes, 3.0, atol=0.1)


def test_taylor2_split_converges_to_exp():
  """Paper eq. 6: (I + B t/N + (B t/N)^2 / 2)^N -> exp(B t); error ~ N^-2 per the local t^3."""
  with x64():
    B = sample_generator(np.random.default_rng(8), (2,), 8, "normal")
    ref = _expm_ref(B, 2.0)
    v = np.random.default_rng(9).normal(size=(2, 8))
    errs = []
    for n in (1, 4, 16, 64):
      M = lie.exp_skew(B, 2.0, method="taylor2", n_steps=n)
      errs.append(np.abs(M - ref).max())
      assert_close(
        lie.apply_exp_skew(B, 2.0, v, method="taylor2", n_steps=n),
        np.einsum("bij,bj->bi", M, v),
        atol=1e-12,
      )
    assert errs[-1] < 5e-4
    slopes = np.diff(np.log(errs[1:])) / np.diff(np.log([4, 16, 64]))
    np.testing.assert_allclose(slopes, -2.0, atol=0.15)


def test_bad_arguments():
  B = np.zeros((3, 4, 4))
  with pytest.raises(ValueError, match="unknown exp method"):
    lie.exp_skew(B, 1.0, method="pade")
  with pytest.raises(ValueError, match="n_steps"):
    lie.exp_skew(B, 1.0, method="expm", n_steps=4)
  with pytest.raises(ValueError, match="shape"):
    lie.exp_skew(np.zeros((3, 4)), 1.0)
  with pytest.raises(ValueError, match="last axis"):
    lie.apply_exp_skew(B, 1.0, np.zeros(5))


# ---------------------------------------------------------------------------- transformations


def _loss(params, t, v, method, s):
  B = lie.skew(params, block_size=s)
  return jnp.sum(jnp.sin(lie.apply_exp_skew(B, t, v, method=method)) * jnp.arange(1, s + 1))


@pytest.mark.slow
@pytest.mark.parametrize("method", lie.EXP_METHODS)
def test_jit_vmap_grad_agree_with_eager(method):
  with x64():
    rng = np.random.default_rng(10)
    s = 6
    P = rng.normal(size=(5, lie.num_skew_params(s))) * 0.5
    t = rng.uniform(-1, 1, size=(5,))
    v = rng.normal(size=(5, s))
    f = lambda P, t, v: lie.apply_exp_skew(lie.skew(P, block_size=s), t, v, method=method)
    eager = f(P, t, v)
    assert_close(jax.jit(f)(P, t, v), eager, atol=1e-12)
    assert_close(jax.vmap(f)(P, t, v), eager, atol=1e-12)
    g = jax.grad(_loss, argnums=(0, 1, 2))(P, t, v, method, s)
    gj = jax.jit(jax.grad(_loss, argnums=(0, 1, 2)), static_argnums=(3, 4))(P, t, v, method, s)
    for a, b in zip(g, gj, strict=True):
      assert_close(a, b, atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("method", lie.EXP_METHODS)
@pytest.mark.parametrize("point", ["random", "near_zero"])
def test_jacfwd_jacrev_numerical(method, point):
  with x64():
    rng = np.random.default_rng(11)
    s = 5
    scale = 0.6 if point == "random" else 1e-7
    P = rng.normal(size=(2, lie.num_skew_params(s))) * scale
    t = rng.uniform(-1, 1, size=(2,))
    v = rng.normal(size=(2, s))
    f = lambda P, t: lie.apply_exp_skew(lie.skew(P, block_size=s), t, v, method=method).ravel()
    for argnum, x in ((0, P), (1, t)):
      g = jax.jit((lambda x: f(x, t)) if argnum == 0 else (lambda x: f(P, x)))
      jf = np.asarray(jax.jit(jax.jacfwd(g))(x)).reshape(-1, x.size)
      jr = np.asarray(jax.jit(jax.jacrev(g))(x)).reshape(-1, x.size)
      jn = jac_numerical(g, x)
      assert_close(jf, jr, atol=1e-10)
      assert_close(jf, jn, atol=1e-7)


@pytest.mark.slow
@pytest.mark.parametrize("method", lie.EXP_METHODS)
@pytest.mark.parametrize("case", ["B_zero", "t_zero", "degenerate", "near_degenerate"])
def test_no_nan_gradient_and_matches_expm(method, case):
  """Regression: eigh's own gradient is NaN at B = 0 and at degenerate spectra (jax_stack_notes
  section 3); the spectral method's custom JVP must stay finite and equal expm's gradient."""
  with x64():
    s = 8
    rng = np.random.default_rng(12)
    if case == "B_zero":
      B = np.zeros((s, s))
    else:
      B = np.zeros((s, s))
      theta = {"degenerate": [1.3] * 4, "near_degenerate": [1.3, 1.3 + 1e-6, 1.3 - 1e-7, 0.0]}.get(
        case, [0.4, 0.9, 1.6, 2.2]
      )
      for k, th in enumerate(theta):
        B[2 * k, 2 * k + 1], B[2 * k + 1, 2 * k] = -th, th
    P = lie.vee(B)[None]
    t = np.array([0.0 if case == "t_zero" else 0.8])
    v = rng.normal(size=(1, s))
    grad = jax.jit(jax.grad(_loss, argnums=(0, 1, 2)), static_argnums=(3, 4))
    g = grad(P, t, v, method, s)
    for x in g:
      assert np.all(np.isfinite(np.asarray(x)))
    if method != "taylor2":
      ge = grad(P, t, v, "expm", s)
      for a, b in zip(g, ge, strict=True):
        assert_close(a, b, atol=1e-9)


def test_spectral_float32_accuracy():
  """The fast exact method in float32 stays within 1e-5 of scipy (bench: within 1e-6 of expm)."""
  rng = np.random.default_rng(13)
  B = sample_generator(rng, (6,), 16, "normal")
  t = rng.uniform(-1, 1, size=(50, 1))
  exp = jax.jit(lie.exp_skew, static_argnames="method")  # as the runs call it
  out = exp(B.astype(np.float32), t.astype(np.float32), method="spectral")
  assert np.abs(np.asarray(out, np.float64) - _expm_ref(B, t)).max() < 1e-5


# ---------------------------------------------------------------------------- real Schur planes


def _rotated_planes(rng, thetas, s):
  """O diag(theta_k J) O^T for a random orthogonal O (padded with zero planes / a zero row)."""
  L = np.zeros((s, s))
  for k, th in enumerate(thetas):
    L[2 * k, 2 * k + 1], L[2 * k + 1, 2 * k] = -th, th
  O, _ = np.linalg.qr(rng.normal(size=(s, s)))
  return O @ L @ O.T


_SCHUR_CASES = {
  "B_zero": [],
  "random": None,
  "degenerate": [1.3, 1.3, 1.3, 1.3],
  "near_degenerate": [1.3, 1.3 + 1e-6, 1.3 - 1e-7, 0.0],
  "opposite": [0.7, -0.7, 0.7 + 1e-9, 0.2],
  "tiny": [1e-9, -1e-12, 0.5, 0.0],
  "null_space": [0.0, 0.0, 0.7, 0.0],
}


def _schur_case(case, s, rng):
  if _SCHUR_CASES[case] is None:
    return sample_generator(rng, (), s, "normal")
  return _rotated_planes(rng, _SCHUR_CASES[case], s)


def _plane_lambda(theta):
  h = theta.shape[-1]
  L = np.zeros((*theta.shape[:-1], 2 * h, 2 * h))
  L[..., np.arange(h) + h, np.arange(h)] = theta
  L[..., np.arange(h), np.arange(h) + h] = -theta
  return L


@pytest.mark.parametrize("case", list(_SCHUR_CASES))
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_skew_schur_factorisation(case, dtype):
  """Q orthogonal and B = Q Lam Q^T to rounding, including B = 0 (eigh returns real
  eigenvectors), degenerate and near-degenerate spectra and (near-)null spaces."""
  with x64():
    rng = np.random.default_rng(20)
    tol = 1e-13 if dtype == "float64" else 2e-6
    for s in (8, 16):
      B = _schur_case(case, s, rng)
      Q, theta = lie.skew_schur(B.astype(dtype))
      assert Q.dtype == dtype and Q.shape == (s, s) and theta.shape == (s // 2,)
      Q, theta = np.asarray(Q, np.float64), np.asarray(theta, np.float64)
      assert_close(Q.T @ Q, np.eye(s), atol=tol)
      assert_close(Q @ _plane_lambda(theta) @ Q.T, B, atol=tol * max(1.0, np.abs(B).max()))
      if _SCHUR_CASES[case] is not None:  # the plane angles, up to sign and order
        ref = np.sort(np.abs(np.pad(_SCHUR_CASES[case], (0, s // 2 - len(_SCHUR_CASES[case])))))
        assert_close(np.sort(np.abs(theta)), ref, atol=10 * tol)


def test_skew_schur_batched_and_odd_size():
  with x64():
    rng = np.random.default_rng(21)
    B = sample_generator(rng, (3, 2), 6, "normal")
    Q, theta = lie.skew_schur(B)
    assert Q.shape == (3, 2, 6, 6) and theta.shape == (3, 2, 3)
    assert_close(Q @ _plane_lambda(np.asarray(theta)) @ np.swapaxes(Q, -1, -2), B, atol=1e-13)
  with pytest.raises(ValueError, match="even"):
    lie.skew_schur(np.zeros((5, 5)))


def test_plane_pq_split():
  """X acting on plane l (coordinates l, s/2 + l) is p xi + q conj(xi), xi_l = c_l + i c_{h+l}."""
  with x64():
    rng = np.random.default_rng(22)
    s, h = 10, 5
    X = rng.normal(size=(2, s, s))
    c = rng.normal(size=(2, s))
    p, q = lie.plane_pq_split(X)
    assert p.shape == q.shape == (2, h, h)
    xi = c[..., :h] + 1j * c[..., h:]
    out = np.einsum("bij,bj->bi", X, c)
    ref = np.einsum("bkl,bl->bk", p, xi) + np.einsum("bkl,bl->bk", q, xi.conj())
    assert_close(out[..., :h] + 1j * out[..., h:], ref, atol=1e-13)
    # J = [[0, -1], [1, 0]] on every plane is multiplication by i: p = i I, q = 0.
    J = np.zeros((s, s))
    J[np.arange(h) + h, np.arange(h)], J[np.arange(h), np.arange(h) + h] = 1.0, -1.0
    p, q = lie.plane_pq_split(J)
    assert_close(p, 1j * np.eye(h), atol=0)
    assert_close(q, np.zeros((h, h)), atol=0)


@pytest.mark.slow
@pytest.mark.parametrize("s", [7, 8])
@pytest.mark.parametrize("case", ["random", "degenerate", "near_degenerate", "B_zero"])
def test_spectral_even_planes_and_odd_fallback_match_expm(s, case):
  """Even s runs the real-plane path, odd s the complex-eigenbasis fallback: both must give
  expm's value and gradient (in B, t and v) in float64, with and without `index`."""
  with x64():
    rng = np.random.default_rng(23)
    if case == "random":
      B = sample_generator(rng, (3,), s, "normal")
    else:
      th = {"degenerate": [0.9] * 3, "near_degenerate": [0.9, 0.9 + 1e-7, 0.0], "B_zero": []}
      B = np.stack([_rotated_planes(rng, th[case], s) for _ in range(3)])
    P = np.asarray(lie.vee(B))
    idx = np.array([2, 0, 0, 1, 2])
    t = rng.uniform(-2, 2, size=(5,))
    v = rng.normal(size=(5, s))
    w = rng.normal(size=(5, s))

    def loss(P, t, v, method, index):
      Bt = lie.skew(P, block_size=s)
      if index is None:
        Bt = Bt[idx]
      return jnp.sum(lie.apply_exp_skew(Bt, t, v, method=method, index=index) * w)

    out = jax.jit(lambda P, t, v: lie.apply_exp_skew(lie.skew(P, block_size=s), t, v, index=idx))
    assert_close(out(P, t, v), np.einsum("nij,nj->ni", _expm_ref(B[idx], t), v), atol=1e-12)
    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2)), static_argnums=3)
    ge = grad(P, t, v, "expm", None)
    for index in (None, idx):
      g = grad(P, t, v, "spectral", index)
      for a, b in zip(g, ge, strict=True):
        assert_close(a, b, atol=1e-10)


def test_spectral_broadcast_layouts():
  """The real-plane path rearranges (table rows x elements); mixed broadcasting must agree with
  expm, e.g. B (3, 1, s, s) with t (1, 4) and v (4, s), and t (2, 3, 1) with B (3, 1, s, s)."""
  with x64():
    rng = np.random.default_rng(24)
    s = 6
    B = sample_generator(rng, (3, 1), s, "normal")
    apply = jax.jit(lie.apply_exp_skew, static_argnames="method")  # as the runs call it
    for t_shape, v_shape in [((1, 4), (4, s)), ((2, 3, 1), (s,)), ((), (3, 5, s))]:
      t = rng.uniform(-1, 1, size=t_shape)
      v = rng.normal(size=v_shape)
      out = apply(B, t, v, method="spectral")
      ref = apply(B, t, v, method="expm")
      assert out.shape == ref.shape
      assert_close(out, ref, atol=1e-12)


@pytest.mark.slow
def test_spectral_float32_bench_workload():
  """The bench's shape (6 blocks of 16 x 16, |B dl| <= 1, float32; fewer pairs): value within
  2e-6 of float64 and gradient (generator parameters and vectors) within 1e-5 relative."""
  rng = np.random.default_rng(25)
  n_blocks, s, pairs = 6, 16, 300
  B = sample_generator(rng, (n_blocks,), s, "normal")
  P = np.asarray(lie.vee(B))
  dl = rng.uniform(-1, 1, size=pairs)
  v0 = rng.normal(size=(pairs, n_blocks * s))
  v0 /= np.linalg.norm(v0, axis=-1, keepdims=True)
  v1 = rng.normal(size=(pairs, n_blocks * s))
  v1 /= np.linalg.norm(v1, axis=-1, keepdims=True)

  def loss(P, dl, v0, v1, method):
    moved = lie.apply_exp_blocks(lie.skew(P, block_size=s), dl, v0, method=method)
    return jnp.mean(jnp.sum((moved - v1) ** 2, -1)), moved

  f32 = [x.astype(np.float32) for x in (P, dl, v0, v1)]
  value_and_grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 2), has_aux=True), static_argnums=4)
  (_, y), g = value_and_grad(*f32, "spectral")
  assert y.dtype == jnp.float32
  with x64():
    (_, y64), g64 = value_and_grad(P, dl, v0, v1, "expm")
  assert np.abs(np.asarray(y, np.float64) - np.asarray(y64)).max() < 2e-6
  for a, b in zip(g, g64, strict=True):
    b = np.asarray(b)
    assert np.abs(np.asarray(a, np.float64) - b).max() / np.abs(b).max() < 1e-5


def test_spectral_gradient_has_no_per_element_matrices():
  """Design goal: reverse mode through the real-plane path keeps per-element arrays at
  (..., s) size; (s, s) arrays exist only per generator (no `index`)."""
  n_blocks, s, pairs = 3, 16, 64
  P = jnp.zeros((n_blocks, lie.num_skew_params(s)))
  v = jnp.ones((pairs, n_blocks * s))
  dl = jnp.linspace(-1, 1, pairs)

  def loss(P, v):
    return jnp.sum(lie.apply_exp_blocks(lie.skew(P, block_size=s), dl, v) ** 2)

  jaxpr = jax.make_jaxpr(jax.grad(loss, argnums=(0, 1)))(P, v)
  sizes = []

  def walk(jx):
    for eqn in jx.eqns:
      sizes.extend(int(np.prod(o.aval.shape)) for o in eqn.outvars if hasattr(o.aval, "shape"))
      for sub in jax.extend.core.jaxprs_in_params(eqn.params):
        walk(sub)

  walk(jaxpr.jaxpr)
  # Per-element vectors: pairs * n_blocks * s (x2 for the stacked near products); a per-element
  # matrix would be pairs * n_blocks * s * s.
  assert max(sizes) <= 2 * pairs * n_blocks * s


def test_per_matrix_is_the_batched_decomposition():
  """`spectral.per_matrix` (one LAPACK call per matrix) returns the batched call's values bit
  for bit, with the batch axes restored; a single matrix passes straight through."""
  rng = np.random.default_rng(stable_seed("per_matrix"))
  X = jnp.asarray(rng.standard_normal((2, 3, 5, 5)), jnp.float32)
  H = X + jnp.swapaxes(X, -1, -2)
  for fn, A in ((jnp.linalg.eigh, H), (jnp.linalg.svd, X)):
    got, want = spectral.per_matrix(fn, A), fn(A)
    for g, w in zip(got, want, strict=True):
      assert g.shape == w.shape and bool(jnp.all(g == w))
  w1 = spectral.per_matrix(jnp.linalg.eigh, H[0, 0])[0]
  assert bool(jnp.all(w1 == jnp.linalg.eigh(H[0, 0])[0]))


def test_spectral_gradient_of_polar_system_returns_on_two_threads():
  """The jitted gradient of a binned-polar + angular system (spectral, 6 x 16, 144 directions)
  returns on a 2-thread XLA:CPU pool, 30 calls in a row, and equals expm's to 1e-4 per parameter.

  Batched eigh/svd over the two independent generator tables used to deadlock that pool (both
  threads blocked in jaxlib's LAPACK batch splitting; see `spectral.per_matrix`): a hang within
  the first few calls, hence a subprocess with a timeout."""
  env = {**os.environ, "NPROC": "2"}
  try:
    proc = subprocess.run(
      [sys.executable, "-m", "tests.spectral_threads_script", "30"],
      cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=150,
    )  # fmt: skip
  except subprocess.TimeoutExpired:
    pytest.fail("the jitted spectral gradient did not return within 150 s (XLA:CPU deadlock)")
  assert proc.returncode == 0, proc.stderr[-3000:]
  out = json.loads(proc.stdout.strip().splitlines()[-1])
  assert out["calls"] == 30
  assert "['xy']['generator_coeffs']" in out["rel_err"], out
  assert max(out["rel_err"].values()) < 1e-4, out


# ---------------------------------------------------------------------------- skew check


def test_check_skew():
  """Generators must be skew; `check_skew` says so on the host (the jitted functions do not
  check: "spectral" would silently use the skew part, e.g. the identity for a symmetric B)."""
  rng = np.random.default_rng(7)
  B = lie.skew(rng.normal(size=(3, 6)).astype(np.float32))
  assert lie.check_skew(B) is None
  assert lie.check_skew(np.zeros((2, 2))) is None
  sym = np.asarray(B) + np.swapaxes(np.asarray(B), -1, -2) + np.eye(4, dtype=np.float32)
  with pytest.raises(ValueError, match="skew-symmetric"):
    lie.check_skew(sym)
  with pytest.raises(ValueError, match="skew-symmetric"):
    lie.check_skew(np.asarray(B) + 1e-3 * np.eye(4))
  lie.check_skew(np.asarray(B) + 1e-3 * np.eye(4), atol=1e-2)
  with pytest.raises(ValueError, match="non-finite"):
    lie.check_skew(np.full((4, 4), np.nan))
  with pytest.raises(ValueError, match=r"\(\.\.\., s, s\)"):
    lie.check_skew(np.zeros((3, 4)))
  with x64():
    B64 = lie.skew(rng.normal(size=(6,)))
    lie.check_skew(B64)
    with pytest.raises(ValueError, match="skew-symmetric"):
      lie.check_skew(np.asarray(B64) + 1e-9 * np.eye(4))


def test_exp_functions_document_the_skew_requirement():
  for f in (lie.exp_skew, lie.apply_exp_skew, lie.apply_exp_blocks):
    assert "check_skew" in f.__doc__, f.__name__
  assert "must be skew-symmetric" in lie.__doc__

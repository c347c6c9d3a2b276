"""Property tests of camrep.lie against scipy.linalg.expm, in float64 (jaxlie style)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from camrep import lie
from tests.utils import assert_close, general_lie_test, jac_numerical, sample_generator, x64


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


@general_lie_test
def test_exp_matches_scipy(method, batch, regime):
  rng = np.random.default_rng(hash((method, batch, regime)) % 2**32)
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
  for method in lie.EXP_METHODS:
    M = lie.exp_skew(B, t, method=method)
    assert M.shape == (4, 6, 5, 5) and M.dtype == jnp.float32
    v = rng.normal(size=(5,)).astype(np.float32)
    assert lie.apply_exp_skew(B, t, v, method=method).shape == (4, 6, 5)


def test_blocks_match_full_block_diagonal_expm():
  with x64():
    rng = np.random.default_rng(5)
    B = sample_generator(rng, (3, 6), 4, "normal")  # 3 generators of 6 blocks of 4 x 4
    t = rng.uniform(-1, 1, size=(3,))
    v = rng.normal(size=(3, 24))
    ref = np.stack(
      [scipy.linalg.expm(t[i] * scipy.linalg.block_diag(*B[i])) @ v[i] for i in range(3)]
    )
    for method in ("expm", "spectral"):
      assert_close(lie.apply_exp_blocks(B, t, v, method=method), ref, atol=1e-12)
      full = lie.block_diag(lie.exp_blocks(B, t, method=method))
      assert_close(np.einsum("bij,bj->bi", full, v), ref, atol=1e-12)


def test_indexed_table_equals_gather():
  with x64():
    rng = np.random.default_rng(6)
    table = sample_generator(rng, (10, 3), 4, "normal")  # (K=10, n_blocks=3, 4, 4)
    idx = rng.integers(0, 10, size=(7,))
    t = rng.uniform(-1, 1, size=(7,))
    v = rng.normal(size=(7, 12))
    for method in lie.EXP_METHODS:
      ref = lie.apply_exp_blocks(table[idx], t, v, method=method)
      out = lie.apply_exp_blocks(table, t, v, method=method, index=idx)
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
      g = (lambda x: f(x, t)) if argnum == 0 else (lambda x: f(P, x))
      jf = np.asarray(jax.jacfwd(g)(x)).reshape(-1, x.size)
      jr = np.asarray(jax.jacrev(g)(x)).reshape(-1, x.size)
      jn = jac_numerical(g, x)
      assert_close(jf, jr, atol=1e-10)
      assert_close(jf, jn, atol=1e-7)


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
    g = jax.grad(_loss, argnums=(0, 1, 2))(P, t, v, method, s)
    for x in g:
      assert np.all(np.isfinite(np.asarray(x)))
    if method != "taylor2":
      ge = jax.grad(_loss, argnums=(0, 1, 2))(P, t, v, "expm", s)
      for a, b in zip(g, ge, strict=True):
        assert_close(a, b, atol=1e-9)


def test_spectral_float32_accuracy():
  """The fast exact method in float32 stays within 1e-5 of scipy (bench: within 1e-6 of expm)."""
  rng = np.random.default_rng(13)
  B = sample_generator(rng, (6,), 16, "normal")
  t = rng.uniform(-1, 1, size=(50, 1))
  out = lie.exp_skew(B.astype(np.float32), t.astype(np.float32), method="spectral")
  assert np.abs(np.asarray(out, np.float64) - _expm_ref(B, t)).max() < 1e-5

"""Tests for camrep.metrics against references (skimage, scipy, float64 NumPy) and invariances."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from camrep import metrics
from tests.utils import x64

# Compilation dominates these small shapes; the numerics are checked to the same tolerances.
pytestmark = pytest.mark.usefixtures("fast_compile")

VARIANTS = ("eager", "jit")


def _variant(fn, variant):
  return jax.jit(fn) if variant == "jit" else fn


def _image_pair(rng, batch=(), h=24, w=28, noise=0.2):
  """Target in [-1, 1] and a noisy prediction that partly leaves [-1, 1] (exercises the clip)."""
  target = rng.uniform(-1, 1, (*batch, h, w, 3))
  pred = target + noise * rng.normal(size=target.shape)
  return pred.astype(np.float32), target.astype(np.float32)


# ------------------------------------------------------------------------------------------
# Float64 NumPy references, written independently of the implementation.


def _ref_psnr(pred, target):
  p = np.clip(np.asarray(pred, np.float64) / 2 + 0.5, 0, 1)
  t = np.clip(np.asarray(target, np.float64) / 2 + 0.5, 0, 1)
  return 10 * np.log10(1.0 / np.mean((p - t) ** 2))


def _ref_ssim(pred, target, size=11, sigma=1.5):
  """Direct 2-D Gaussian-window SSIM (Wang et al. 2004) over every valid window position."""
  x = np.clip(np.asarray(pred, np.float64) / 2 + 0.5, 0, 1)
  y = np.clip(np.asarray(target, np.float64) / 2 + 0.5, 0, 1)
  r = np.arange(size) - size // 2
  g = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma**2))
  g /= g.sum()
  c1, c2 = 0.01**2, 0.03**2
  h, w, _ = x.shape
  vals = []
  for i in range(h - size + 1):
    for j in range(w - size + 1):
      px, py = x[i : i + size, j : j + size], y[i : i + size, j : j + size]
      mx = np.einsum("ab,abc->c", g, px)
      my = np.einsum("ab,abc->c", g, py)
      vx = np.einsum("ab,abc->c", g, (px - mx) ** 2)
      vy = np.einsum("ab,abc->c", g, (py - my) ** 2)
      cxy = np.einsum("ab,abc->c", g, (px - mx) * (py - my))
      vals.append((2 * mx * my + c1) * (2 * cxy + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
  return np.mean(vals)


# ------------------------------------------------------------------------------------------
# PSNR.


@pytest.mark.parametrize("variant", VARIANTS)
def test_psnr_matches_references(variant):
  rng = np.random.default_rng(0)
  pred, target = _image_pair(rng, (3,))
  got = _variant(metrics.psnr, variant)(pred, target)
  assert got.shape == (3,)
  np.testing.assert_allclose(
    got, [_ref_psnr(p, t) for p, t in zip(pred, target, strict=True)], rtol=1e-5
  )
  skm = pytest.importorskip("skimage.metrics")
  to01 = lambda z: np.clip(z.astype(np.float64) / 2 + 0.5, 0, 1)
  expect = [
    skm.peak_signal_noise_ratio(to01(t), to01(p), data_range=1)
    for p, t in zip(pred, target, strict=True)
  ]
  np.testing.assert_allclose(got, expect, rtol=1e-5)


def test_psnr_is_per_image_then_averaged():
  """Mean of per-image PSNRs (the paper) differs from the PSNR of the pooled MSE."""
  rng = np.random.default_rng(1)
  t = rng.uniform(-1, 1, (2, 8, 8, 3)).astype(np.float32)
  p = t.copy()
  p[0] += 0.01
  p[1] += 0.3
  per_image = metrics.psnr(p, t)
  pooled = _ref_psnr(p, t)
  assert abs(float(per_image.mean()) - pooled) > 1.0


def test_psnr_identical_is_inf_with_zero_grad():
  rng = np.random.default_rng(2)
  t = rng.uniform(-1, 1, (2, 8, 8, 3)).astype(np.float32)
  assert np.all(np.isposinf(metrics.psnr(t, t)))
  # Out-of-range values that clip to the same image also count as identical.
  assert np.isposinf(metrics.psnr(t[0] * 0 + 3.0, t[0] * 0 + 1.0))
  g = jax.jit(jax.grad(lambda p: metrics.psnr(p, t).sum()))(t)
  assert np.all(np.isfinite(g)) and np.all(g == 0)


@pytest.mark.parametrize("variant", VARIANTS)
def test_psnr_finite_grad(variant):
  rng = np.random.default_rng(3)
  pred, target = _image_pair(rng, (2,))
  g = _variant(jax.grad(lambda p: metrics.psnr(p, target).sum()), variant)(pred)
  assert np.all(np.isfinite(g)) and np.any(g != 0)


# ------------------------------------------------------------------------------------------
# SSIM.


# SSIM tests share one image shape so that eager op compilations are reused.
_SSIM_SHAPE = dict(h=16, w=16)


@pytest.mark.parametrize("variant", VARIANTS)
def test_ssim_matches_direct_window_reference(variant):
  rng = np.random.default_rng(4)
  pred, target = _image_pair(rng, (2,), **_SSIM_SHAPE)
  got = _variant(metrics.ssim, variant)(pred, target)
  assert got.shape == (2,)
  expect = [_ref_ssim(p, t) for p, t in zip(pred, target, strict=True)]
  np.testing.assert_allclose(got, expect, atol=2e-6)


def test_ssim_matches_skimage():
  skm = pytest.importorskip("skimage.metrics")
  rng = np.random.default_rng(5)
  pred, target = _image_pair(rng, (2,), noise=0.3, **_SSIM_SHAPE)
  to01 = lambda z: np.clip(z.astype(np.float64) / 2 + 0.5, 0, 1)
  expect = [
    skm.structural_similarity(
      to01(t),
      to01(p),
      data_range=1,
      channel_axis=-1,
      gaussian_weights=True,
      sigma=1.5,
      use_sample_covariance=False,
    )
    for p, t in zip(pred, target, strict=True)
  ]
  np.testing.assert_allclose(metrics.ssim(pred, target), expect, atol=2e-6)
  with x64():
    got64 = jax.jit(metrics.ssim)(pred.astype(np.float64), target.astype(np.float64))
    np.testing.assert_allclose(got64, expect, atol=1e-12)


def test_ssim_batch_axes_and_vmap():
  rng = np.random.default_rng(6)
  pred, target = _image_pair(rng, (2, 3), **_SSIM_SHAPE)
  got = jax.jit(metrics.ssim)(pred, target)
  assert got.shape == (2, 3)
  flat = jax.jit(jax.vmap(metrics.ssim))(pred.reshape(-1, 16, 16, 3), target.reshape(-1, 16, 16, 3))
  np.testing.assert_allclose(np.asarray(got).reshape(-1), flat, rtol=1e-6)
  np.testing.assert_allclose(jax.jit(metrics.ssim)(pred[1, 2], target[1, 2]), got[1, 2], rtol=1e-6)


def test_ssim_properties():
  rng = np.random.default_rng(7)
  pred, target = _image_pair(rng, (2,), **_SSIM_SHAPE)
  np.testing.assert_allclose(metrics.ssim(pred, target), metrics.ssim(target, pred), rtol=1e-6)
  np.testing.assert_allclose(metrics.ssim(target, target), 1.0, atol=1e-6)
  assert np.all(metrics.ssim(pred, target) < 1.0)


@pytest.mark.parametrize("variant", VARIANTS)
def test_ssim_finite_grad(variant):
  """Random, identical and flat (zero-variance) pairs, batched: all gradients finite."""
  rng = np.random.default_rng(8)
  pred, target = _image_pair(rng, (3,), **_SSIM_SHAPE)
  pred[1] = target[1]
  pred[2], target[2] = 0.0, 0.5
  g = _variant(jax.grad(lambda p: metrics.ssim(p, target).sum()), variant)(pred)
  assert np.all(np.isfinite(g))
  assert np.any(g[0] != 0)


def test_image_metrics_check_shapes():
  a = np.zeros((16, 16, 3), np.float32)
  with pytest.raises(ValueError):
    metrics.psnr(a, a[:8])
  with pytest.raises(ValueError):
    metrics.ssim(a[..., :1], a[..., :1])
  with pytest.raises(ValueError):
    metrics.ssim(a[:8, :8], a[:8, :8])


# ------------------------------------------------------------------------------------------
# Pose errors.


def _random_quats(rng, n):
  """(n, 4) unit quaternions (w, x, y, z) and the matching scipy rotations."""
  rot = Rotation.random(n, random_state=rng.integers(1 << 31))
  return np.roll(rot.as_quat(), 1, axis=-1), rot


@pytest.mark.parametrize("variant", VARIANTS)
def test_rotation_error_matches_scipy_magnitude(variant):
  rng = np.random.default_rng(9)
  q1, r1 = _random_quats(rng, 64)
  q2, r2 = _random_quats(rng, 64)
  expect = np.degrees((r1.inv() * r2).magnitude())
  with x64():
    got = _variant(metrics.rotation_error_deg, variant)(q1, q2)
    np.testing.assert_allclose(got, expect, atol=1e-9)
    # The documented closed form 2 arccos|<q_hat, q>|.
    closed = np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(q1 * q2, -1)), 0, 1)))
    np.testing.assert_allclose(got, closed, atol=1e-6)
  got32 = _variant(metrics.rotation_error_deg, variant)(
    q1.astype(np.float32), q2.astype(np.float32)
  )
  np.testing.assert_allclose(got32, expect, atol=1e-3)


def test_rotation_error_invariances():
  rng = np.random.default_rng(10)
  q1, _ = _random_quats(rng, 16)
  q2, _ = _random_quats(rng, 16)
  e = metrics.rotation_error_deg(q1, q2)
  np.testing.assert_allclose(metrics.rotation_error_deg(q1, -q2), e, atol=1e-4)
  np.testing.assert_allclose(metrics.rotation_error_deg(-q1, q2), e, atol=1e-4)
  np.testing.assert_allclose(metrics.rotation_error_deg(q2, q1), e, atol=1e-4)
  # Unnormalised regressor outputs are normalised first.
  np.testing.assert_allclose(metrics.rotation_error_deg(3.0 * q1, 0.2 * q2), e, atol=1e-4)
  assert np.all((e >= 0) & (e <= 180))
  np.testing.assert_allclose(metrics.rotation_error_deg(q1, q1), 0.0, atol=1e-5)
  np.testing.assert_allclose(metrics.rotation_error_deg(q1, -q1), 0.0, atol=1e-5)


def test_rotation_error_known_angles_and_small_angle_precision():
  for deg in [1e-3, 0.5, 90.0, 179.9, 180.0]:
    r = Rotation.from_rotvec(np.radians(deg) * np.array([0.0, 0.6, 0.8]))
    q = np.roll(r.as_quat(), 1).astype(np.float32)
    ident = np.array([1.0, 0.0, 0.0, 0.0], np.float32)
    # float32 arccos of the dot product would return 0 below ~0.04 degrees.
    np.testing.assert_allclose(metrics.rotation_error_deg(q, ident), deg, rtol=1e-3, atol=1e-5)


def test_rotation_error_grad_finite_at_zero_and_batch_axes():
  q = np.array([0.5, 0.5, 0.5, 0.5], np.float32)
  g = jax.jit(jax.grad(lambda a: metrics.rotation_error_deg(a, q)))(q)
  assert np.all(np.isfinite(g))
  rng = np.random.default_rng(11)
  qa = rng.normal(size=(2, 3, 4)).astype(np.float32)
  qb = rng.normal(size=(2, 3, 4)).astype(np.float32)
  assert metrics.rotation_error_deg(qa, qb).shape == (2, 3)
  with pytest.raises(ValueError):
    metrics.rotation_error_deg(qa[..., :3], qb[..., :3])


@pytest.mark.parametrize("variant", VARIANTS)
def test_translation_error(variant):
  rng = np.random.default_rng(12)
  a, b = rng.normal(size=(2, 5, 3)).astype(np.float32)
  fn = _variant(metrics.translation_error, variant)
  np.testing.assert_allclose(fn(a, b), np.linalg.norm(a - b, axis=-1), rtol=1e-6)
  np.testing.assert_allclose(fn(a, b), fn(b, a), rtol=1e-6)
  assert np.all(fn(a, a) == 0)
  g = jax.jit(jax.grad(lambda x: metrics.translation_error(x, a).sum()))(a)
  assert np.all(np.isfinite(g))


@pytest.mark.parametrize("variant", VARIANTS)
def test_wrapped_angle_error(variant):
  fn = _variant(metrics.wrapped_angle_error_deg, variant)
  a_hat = np.radians(np.array([359.0, 1.0, 10.0, 190.0, -170.0, 720.5, 180.0]))
  a = np.radians(np.array([1.0, 359.0, 10.0, 10.0, 170.0, 0.0, 0.0]))
  np.testing.assert_allclose(fn(a_hat, a), [2.0, 2.0, 0.0, 180.0, 20.0, 0.5, 180.0], atol=1e-4)
  rng = np.random.default_rng(13)
  x, y = rng.uniform(-10, 10, (2, 100))
  got = np.asarray(fn(x, y))
  assert np.all((got >= 0) & (got <= 180 + 1e-4))
  np.testing.assert_allclose(got, fn(y, x), atol=1e-4)


def test_abs_error():
  np.testing.assert_allclose(
    metrics.abs_error(jnp.array([1.0, -2.0]), jnp.array([0.5, 1.0])), [0.5, 3.0]
  )


# ------------------------------------------------------------------------------------------
# masked_mean.


@pytest.mark.parametrize("variant", VARIANTS)
def test_masked_mean_ignores_padding(variant):
  fn = _variant(metrics.masked_mean, variant)
  values = jnp.array([1.0, 2.0, 3.0, jnp.inf, jnp.nan])
  mask = jnp.array([True, True, True, False, False])
  assert float(fn(values, mask)) == pytest.approx(2.0)
  assert float(fn(values, mask.astype(jnp.float32))) == pytest.approx(2.0)
  # A (B,) mask broadcast over per-example (B, K) values.
  v2 = jnp.array([[1.0, 3.0], [5.0, 7.0], [jnp.nan, 0.0]])
  assert float(fn(v2, jnp.array([1, 1, 0]))) == pytest.approx(4.0)
  assert np.isnan(fn(values, jnp.zeros(5, bool)))


def test_masked_mean_with_padded_psnr():
  """Zero-padded eval batches give inf PSNR on the padding; the mask removes it."""
  rng = np.random.default_rng(14)
  pred, target = _image_pair(rng, (2,), h=8, w=8)
  pred = np.concatenate([pred, np.zeros_like(pred)])
  target = np.concatenate([target, np.zeros_like(target)])
  per_image = metrics.psnr(pred, target)
  assert np.isinf(per_image[2:]).all()
  got = metrics.masked_mean(per_image, jnp.array([1, 1, 0, 0]))
  np.testing.assert_allclose(got, np.mean(per_image[:2]), rtol=1e-6)
  with pytest.raises(ValueError):
    metrics.masked_mean(per_image, jnp.ones(3))

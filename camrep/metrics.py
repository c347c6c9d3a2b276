"""Per-example evaluation metrics: view synthesis (PSNR, SSIM) and pose regression errors.

Every function is pure, returns one value per example and reduces nothing across examples: the
caller averages (use `masked_mean` for zero-padded eval batches). Nothing is jitted here; all
functions work under `jax.jit` and `jax.vmap` and over any leading batch axes.

Image convention: images are float arrays (..., H, W, 3) in [-1, 1], as the models produce and
the data pipeline stores them. PSNR and SSIM first map them to [0, 1] by x / 2 + 0.5 and clip, as
the authors' evaluation does (the authors' code), and then use max value 1.

Quaternion convention: (..., 4) with the scalar first, (w, x, y, z), as in jaxlie/transforms3d and
the 7-Scenes pose tables. scipy's `Rotation.as_quat()` is (x, y, z, w): roll it before comparing.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# Degrees per radian.
_DEG = 180.0 / np.pi


def _check_images(pred: jax.Array, target: jax.Array) -> None:
  if pred.shape != target.shape:
    raise ValueError(f"pred and target shapes differ: {pred.shape} vs {target.shape}")
  if pred.ndim < 3 or pred.shape[-1] != 3:
    raise ValueError(f"images must be (..., H, W, 3), got {pred.shape}")


def _check_same_shape(a: jax.Array, b: jax.Array, *, last: int | None = None) -> None:
  if a.shape != b.shape:
    raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
  if last is not None and (a.ndim < 1 or a.shape[-1] != last):
    raise ValueError(f"expected a trailing axis of size {last}, got {a.shape}")


def to_unit_range(images: jax.Array) -> jax.Array:
  """Maps images from [-1, 1] to [0, 1] by x / 2 + 0.5 and clips (the authors' code).

  Args:
    images: (...) array with values nominally in [-1, 1].

  Returns:
    (...) array in [0, 1], same dtype (float inputs).
  """
  return jnp.clip(images / 2 + 0.5, 0.0, 1.0)


def _safe_norm(x: jax.Array) -> jax.Array:
  """L2 norm over the last axis with a zero (not NaN) gradient at x = 0."""
  sq = jnp.sum(x * x, axis=-1)
  pos = sq > 0
  return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def psnr(pred: jax.Array, target: jax.Array) -> jax.Array:
  """Peak signal-to-noise ratio of each image, as the paper computes it.

  Both images are mapped [-1, 1] -> [0, 1] and clipped, then
  PSNR = 10 log10(1 / MSE) with the MSE over all H * W * 3 values of one image. The paper reports
  the mean of these per-image values (the caller averages). Equals
  `skimage.metrics.peak_signal_noise_ratio(target01, pred01, data_range=1)` and `dm_pix.psnr`.

  Identical images (MSE = 0 after clipping) give +inf, as skimage and dm_pix do; the gradient
  there is zero rather than NaN. Averaging an eval set that contains such a pair gives inf, which
  is the honest answer; padded examples must be removed with `masked_mean`.

  Args:
    pred: (..., H, W, 3) predicted images in [-1, 1].
    target: (..., H, W, 3) ground-truth images in [-1, 1].

  Returns:
    (...) PSNR in dB.
  """
  _check_images(pred, target)
  diff = to_unit_range(pred) - to_unit_range(target)
  mse = jnp.mean(diff * diff, axis=(-3, -2, -1))
  pos = mse > 0
  value = -10.0 * jnp.log10(jnp.where(pos, mse, 1.0))
  return jnp.where(pos, value, jnp.inf)


def _gaussian_filter_1d(filter_size: int, sigma: float) -> np.ndarray:
  """Normalised 1-D Gaussian taps, laid out exactly as dm_pix.ssim builds them."""
  hw = filter_size // 2
  shift = (2 * hw - filter_size + 1) / 2
  f = np.exp(-0.5 * ((np.arange(filter_size) - hw + shift) / sigma) ** 2)
  return f / f.sum()


def _valid_filter_matrix(n: int, taps: np.ndarray) -> np.ndarray:
  """(n - k + 1, n) banded matrix whose product with a length-n signal is its 'valid' filtering."""
  k = len(taps)
  m = np.zeros((n - k + 1, n), np.float64)
  for i in range(n - k + 1):
    m[i, i : i + k] = taps
  return m


def _valid_filter(z: jax.Array, taps: np.ndarray) -> jax.Array:
  """Separable 'valid' filtering of (..., H, W, C) along H then W.

  Done as two products with banded matrices at full float32 precision (the default matmul
  precision on GPU/TPU would round to tf32/bf16): few ops, so eager mode and compilation stay
  fast, and jit/vmap friendly. Output is (..., H - k + 1, W - k + 1, C) for k taps.
  """
  my = jnp.asarray(_valid_filter_matrix(z.shape[-3], taps), z.dtype)
  mx = jnp.asarray(_valid_filter_matrix(z.shape[-2], taps), z.dtype)
  hi = jax.lax.Precision.HIGHEST
  z = jnp.einsum("ih,...hwc->...iwc", my, z, precision=hi)
  return jnp.einsum("jw,...iwc->...ijc", mx, z, precision=hi)


def ssim(
  pred: jax.Array,
  target: jax.Array,
  *,
  filter_size: int = 11,
  filter_sigma: float = 1.5,
  k1: float = 0.01,
  k2: float = 0.03,
) -> jax.Array:
  """Structural similarity of each image (Wang et al. 2004), dm_pix.ssim's definition.

  Both images are mapped [-1, 1] -> [0, 1] and clipped (max value 1). Local means, variances and
  the covariance come from a separable 11x11 Gaussian window (sigma 1.5, taps normalised to sum 1)
  applied with 'valid' filtering (the dm_pix default); the SSIM map
    ((2 mu_p mu_t + c1)(2 sigma_pt + c2)) / ((mu_p^2 + mu_t^2 + c1)(sigma_p^2 + sigma_t^2 + c2)),
  c1 = k1^2, c2 = k2^2, is averaged over the valid H' x W' x 3 values. As in dm_pix the variances
  are floored at float32-eps^2 and |sigma_pt| is capped at sigma_p sigma_t, which keeps gradients
  finite for flat or identical images. Follows `dm_pix/_src/metrics.py:ssim` and equals
  `skimage.metrics.structural_similarity(t, p, data_range=1, channel_axis=-1,
  gaussian_weights=True, sigma=1.5, use_sample_covariance=False)` (whose reflect padding is
  cropped away).

  Args:
    pred: (..., H, W, 3) predicted images in [-1, 1], H and W >= filter_size.
    target: (..., H, W, 3) ground-truth images in [-1, 1].
    filter_size: Gaussian window size.
    filter_sigma: Gaussian standard deviation in pixels.
    k1: Luminance stabiliser constant.
    k2: Contrast stabiliser constant.

  Returns:
    (...) SSIM, at most 1.
  """
  _check_images(pred, target)
  if min(pred.shape[-3], pred.shape[-2]) < filter_size:
    raise ValueError(f"images {pred.shape} are smaller than the {filter_size}-pixel window")
  taps = _gaussian_filter_1d(filter_size, filter_sigma)
  a, b = to_unit_range(pred), to_unit_range(target)
  # One filtering pass over the five stacked local moments.
  moments = _valid_filter(jnp.concatenate([a, b, a * a, b * b, a * b], axis=-1), taps)
  mu0, mu1, e00, e11, e01 = jnp.split(moments, 5, axis=-1)
  mu00, mu11, mu01 = mu0 * mu0, mu1 * mu1, mu0 * mu1
  sigma00 = e00 - mu00
  sigma11 = e11 - mu11
  sigma01 = e01 - mu01
  # Rounding can make the variances slightly negative and |cov| exceed sqrt(var0 var1).
  eps = float(np.finfo(np.float32).eps) ** 2
  sigma00 = jnp.maximum(eps, sigma00)
  sigma11 = jnp.maximum(eps, sigma11)
  sigma01 = jnp.sign(sigma01) * jnp.minimum(jnp.sqrt(sigma00 * sigma11), jnp.abs(sigma01))
  c1, c2 = k1**2, k2**2
  numer = (2 * mu01 + c1) * (2 * sigma01 + c2)
  denom = (mu00 + mu11 + c1) * (sigma00 + sigma11 + c2)
  return jnp.mean(numer / denom, axis=(-3, -2, -1))


def translation_error(t_hat: jax.Array, t: jax.Array) -> jax.Array:
  """Euclidean distance between predicted and true positions, ||t_hat - t||_2.

  Args:
    t_hat: (..., D) predicted positions (D = 3 for 7-Scenes, 2 for GQN x-y), in scene units.
    t: (..., D) true positions.

  Returns:
    (...) distance, same units; zero (with zero gradient) when they coincide.
  """
  _check_same_shape(t_hat, t)
  return _safe_norm(t_hat - t)


def rotation_error_deg(q_hat: jax.Array, q: jax.Array) -> jax.Array:
  """Angle of the relative rotation between two quaternions, in degrees (PoseNet metric).

  Both inputs are normalised first (a regressor's raw output is fine). The value is
  2 arccos(clip(|<q_hat, q>|, 0, 1)), so q and -q give the same rotation (sign invariant) and the
  result is symmetric and lies in [0, 180]. It is evaluated in the equivalent, well-conditioned
  form 4 atan2(||q_hat - s q||, ||q_hat + s q||) with s = sign<q_hat, q>: arccos near 1 loses
  about 0.04 degrees to float32 rounding, atan2 does not, and its gradient stays finite at zero
  error. The formula does not depend on the component order as long as both inputs use the same
  one; camrep's convention is scalar first (w, x, y, z).

  Args:
    q_hat: (..., 4) predicted quaternion (w, x, y, z), any nonzero norm.
    q: (..., 4) true quaternion (w, x, y, z).

  Returns:
    (...) rotation error in degrees.
  """
  _check_same_shape(q_hat, q, last=4)
  tiny = jnp.finfo(jnp.result_type(q_hat, q, jnp.float32)).tiny
  a = q_hat / jnp.maximum(_safe_norm(q_hat), tiny)[..., None]
  b = q / jnp.maximum(_safe_norm(q), tiny)[..., None]
  b = jnp.where(jnp.sum(a * b, axis=-1, keepdims=True) < 0, -b, b)
  return 4.0 * jnp.arctan2(_safe_norm(a - b), _safe_norm(a + b)) * _DEG


def wrapped_angle_error_deg(a_hat: jax.Array, a: jax.Array) -> jax.Array:
  """Absolute angle difference on the circle, |wrap(a_hat - a)|, in degrees.

  wrap maps to [-pi, pi), so 359 degrees apart counts as 1 degree (yaw wrap-around). Elementwise:
  each entry is one angle.

  Args:
    a_hat: (...) predicted angles in radians.
    a: (...) true angles in radians.

  Returns:
    (...) error in degrees, in [0, 180].
  """
  _check_same_shape(a_hat, a)
  d = jnp.mod(a_hat - a + jnp.pi, 2 * jnp.pi) - jnp.pi
  return jnp.abs(d) * _DEG


def abs_error(x_hat: jax.Array, x: jax.Array) -> jax.Array:
  """Elementwise absolute error |x_hat - x|.

  Args:
    x_hat: (...) predictions.
    x: (...) targets.

  Returns:
    (...) absolute error.
  """
  _check_same_shape(x_hat, x)
  return jnp.abs(x_hat - x)


def masked_mean(values: jax.Array, mask: jax.Array) -> jax.Array:
  """Mean of the valid entries of a padded eval batch.

  Padded entries are excluded with `where`, so an inf or NaN there (e.g. the inf PSNR of two
  all-zero padding images) does not leak into the result. With no valid entry the mean is NaN.

  Args:
    values: (B, ...) per-example values.
    mask: (B,) or any leading prefix of `values`' shape; bool or 0/1, true where the example is
      real. It is broadcast over the trailing axes of `values`.

  Returns:
    () mean over all valid entries.
  """
  values = jnp.asarray(values)
  mask = jnp.asarray(mask)
  if mask.shape != values.shape[: mask.ndim]:
    raise ValueError(f"mask {mask.shape} is not a leading prefix of values {values.shape}")
  mask = jnp.broadcast_to(
    mask.reshape(mask.shape + (1,) * (values.ndim - mask.ndim)) != 0, values.shape
  )
  total = jnp.sum(jnp.where(mask, values, 0), dtype=jnp.result_type(values, jnp.float32))
  return total / jnp.sum(mask)

"""Building blocks shared by the generative models (the authors' code).

The authors' TF1 models use a few conventions that differ from Flax defaults; they are fixed here
once so that every model follows them:

- leaky ReLU with slope 0.2 (`tf.nn.leaky_relu`), not Flax's 0.01;
- convolution kernels initialised glorot_uniform (= `nn.initializers.xavier_uniform`), biases 0;
- TF 'SAME' padding (for even kernels TF pads one more row/column after than before, as XLA does);
- nearest-neighbour x2 upsampling (`UpSampling2D`);
- instance norm computed by hand, per sample and channel over (H, W), with the biased variance,
  eps = 1e-7 inside the square root and the AdaIN scale gamma used raw (no "1 + gamma").

Images are NHWC with any number of leading batch axes: (..., H, W, C).

Mixed precision (`model.dtype`): the layer helpers take `dtype`, the dtype of the computation;
parameters stay float32 (Flax's `param_dtype`) and are cast when used. Instance-norm statistics
and the AdaIN affine are computed in float32 whatever the activations' dtype, and their result is
cast back to it.

Three convolutions are computed by cheaper, exactly equivalent arrangements (`ConvMean`,
`UpConv`, `ConcatConstantConv`; see "Equivalent rewrites" below); their parameters are those of
the plain `nn.Conv` they replace, so checkpoints and initial values do not change. `rewrites(False)`
(around tracing, like `fastconv.weight_grad`) computes them as written instead.

Also here: `SceneTable`, the learned per-scene code u of the car, Gibson and 7-Scenes models
(the authors' code), and `param_count` / `intermediate_shapes` helpers for logging.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from camrep.models import fastconv

Array = jax.Array

LRELU_SLOPE = 0.2
IN_EPS = 1e-7

kernel_init = nn.initializers.xavier_uniform()  # TF1 glorot_uniform.
bias_init = nn.initializers.zeros_init()


def lrelu(x: Array) -> Array:
  """Leaky ReLU with the TF slope 0.2: max(x, 0.2 x). Shape-preserving."""
  return nn.leaky_relu(x, negative_slope=LRELU_SLOPE)


def scaled(channels: int, width: float) -> int:
  """Channel count `channels * width`, rounded, at least 1 (width multipliers of quick configs)."""
  return max(1, int(round(channels * width)))


def at_least_f32(x: Array) -> Array:
  """x in float32 when its dtype is narrower (bfloat16, float16); unchanged otherwise."""
  return x.astype(jnp.promote_types(x.dtype, jnp.float32))


def _normalise(x: Array, eps: float) -> Array:
  """(x - mu) / sqrt(var + eps) per sample and channel over (H, W), in at least float32."""
  x = at_least_f32(x)
  mu = jnp.mean(x, axis=(-3, -2), keepdims=True)
  var = jnp.mean(jnp.square(x - mu), axis=(-3, -2), keepdims=True)
  return (x - mu) / jnp.sqrt(var + eps)


def instance_norm(x: Array, eps: float = IN_EPS) -> Array:
  """Instance normalisation without affine terms, as the authors' TF code.

  Args:
    x: (..., H, W, C) activations.
    eps: added to the variance inside the square root.

  Returns:
    (..., H, W, C) in x's dtype: (x - mu) / sqrt(var + eps), with mu and the biased variance var
    taken per sample and channel over (H, W) (in float32 when x is bfloat16).
  """
  return _normalise(x, eps).astype(x.dtype)


def adain(x: Array, gamma: Array, beta: Array, eps: float = IN_EPS) -> Array:
  """Adaptive instance norm: gamma * instance_norm(x) + beta, gamma used raw.

  Args:
    x: (..., H, W, C) activations.
    gamma: (..., C) scale, one per sample (broadcast against x's leading axes).
    beta: (..., C) shift.
    eps: instance-norm epsilon inside the square root.

  Returns:
    (..., H, W, C) in x's dtype (normalised and scaled in float32 when x is bfloat16).
  """
  y = gamma[..., None, None, :] * _normalise(x, eps) + beta[..., None, None, :]
  return y.astype(x.dtype)


def upsample2(x: Array) -> Array:
  """Nearest-neighbour x2 upsampling: (..., H, W, C) -> (..., 2H, 2W, C)."""
  return jnp.repeat(jnp.repeat(x, 2, axis=-3), 2, axis=-2)


def global_avg_pool(x: Array) -> Array:
  """Mean over (H, W): (..., H, W, C) -> (..., C)."""
  return jnp.mean(x, axis=(-3, -2))


def conv(
  features: int,
  kernel: int,
  *,
  strides: int = 1,
  name: str,
  dtype: Any = None,
  kind: type[nn.Conv] = nn.Conv,
) -> nn.Conv:
  """TF-style conv: k x k kernel, 'SAME' padding, glorot_uniform kernel, zero bias; computed in
  `dtype` (inputs and the float32 parameters are cast to it; None: Flax infers it, float32).

  Also stands in for the authors' stride-1 `conv2d_transpose` layers: with stride 1 a transposed
  conv is a conv with a flipped kernel, which does not matter when training from scratch.
  On CPU its kernel gradient is computed as matmuls (`camrep.models.fastconv`). `kind` is
  `nn.Conv` or one of the rewritten forms with its parameters (`ConvMean`, `UpConv`,
  `ConcatConstantConv`).
  """
  return kind(
    features,
    (kernel, kernel),
    strides=(strides, strides),
    padding="SAME",
    kernel_init=kernel_init,
    bias_init=bias_init,
    conv_general_dilated=fastconv.conv_general_dilated,
    dtype=dtype,
    name=name,
  )


def conv_transpose(
  features: int, kernel: int, *, strides: int, name: str, dtype: Any = None
) -> nn.ConvTranspose:
  """TF-style `conv2d_transpose`: 'SAME' padding (output = input * strides), glorot, zero bias;
  computed in `dtype`."""
  return nn.ConvTranspose(
    features,
    (kernel, kernel),
    strides=(strides, strides),
    padding="SAME",
    kernel_init=kernel_init,
    bias_init=bias_init,
    dtype=dtype,
    name=name,
  )


# ---------------------------------------------------------------------------------------------
# Equivalent rewrites.
#
# Each module below holds the parameters of one `nn.Conv` (k x k, stride 1, TF 'SAME' padding,
# "kernel" (k, k, Cin, Cout) and "bias" (Cout,), created in nn.Conv's order) and computes what
# the plain layers compute, with fewer multiply-adds:
#
#   ConvMean            mean_{H, W} conv(x): the mean of a k x k conv is sum over taps (i, j) of
#                       W_ij^T (sum of x over the window tap (i, j) reads) / HW + b, window sums
#                       then one (N, k^2 Cin) x (k^2 Cin, Cout) matmul, HW times fewer FLOPs.
#   UpConv              conv(upsample2(x)) (nearest x2): output pixel (2h + a, 2w + b) reads
#                       upsampled rows 2h + a - p + i = source rows h + floor((a - p + i) / 2), so
#                       each of the four output parities is a small conv of x whose taps are sums
#                       of W's taps (sub-pixel convolution): 3 x 3 -> four 2 x 2 convs at the low
#                       resolution (16 / 36 of the FLOPs), 1 x 1 -> upsample2(conv(x)) (1 / 4).
#   ConcatConstantConv  conv(concat(x, v tiled over H, W)): the kernel splits over the input
#                       channels, conv(x, W_x) + the tiled part, which is v^T (sum of W_v over the
#                       taps that fall inside the image at (h, w)): constant inside, different
#                       only on the border rows and columns (zero padding), one small matmul per
#                       border class instead of a conv over HW copies of v.
#
# The rewrites change only the order of float additions (values and gradients agree with the
# plain layers to float32 round-off; tests/test_models.py checks them in float64).

_rewrites = True


def set_rewrites(on: bool) -> None:
  """Whether `ConvMean`, `UpConv` and `ConcatConstantConv` traced from now on use their
  rewrites (True, the default) or compute as written (False)."""
  global _rewrites
  _rewrites = bool(on)


def get_rewrites() -> bool:
  """The setting of `set_rewrites`."""
  return _rewrites


@contextlib.contextmanager
def rewrites(on: bool):
  """Context manager form of `set_rewrites` (restores the previous setting on exit)."""
  old = _rewrites
  set_rewrites(on)
  try:
    yield
  finally:
    set_rewrites(old)


class _SameConv(nn.Conv):
  """`nn.Conv` (stride 1, 'SAME', square odd or even kernel) with helpers for the rewrites."""

  def _params(self, in_features: int) -> tuple[Array, Array]:
    """The kernel and bias nn.Conv would create, in its order, shapes and initialisers."""
    k = tuple(self.kernel_size)
    kernel = self.param(
      "kernel", self.kernel_init, (*k, in_features, self.features), self.param_dtype
    )
    bias = self.param("bias", self.bias_init, (self.features,), self.param_dtype)
    return kernel, bias

  def _check(self) -> int:
    k = tuple(self.kernel_size)
    if len(k) != 2 or k[0] != k[1] or self.padding != "SAME":
      raise ValueError(f"{type(self).__name__}: square 'SAME' kernels only, got {k} {self.padding}")
    if tuple(np.broadcast_to(self.strides or 1, (2,))) != (1, 1):
      raise ValueError(f"{type(self).__name__}: stride 1 only, got {self.strides}")
    return int(k[0])

  def _conv(self, x: Array, kernel: Array, pads) -> Array:
    """The layer's conv function (fastconv's on the CPU) with explicit padding, NHWC / HWIO."""
    conv = self.conv_general_dilated or jax.lax.conv_general_dilated
    return conv(x, kernel, (1, 1), pads, dimension_numbers=("NHWC", "HWIO", "NHWC"))


def _same_pads(k: int) -> tuple[int, int]:
  """TF / XLA 'SAME' padding of a stride-1 kernel of size k: (before, after)."""
  return (k - 1) // 2, k // 2


def _tap_windows(size: int, k: int) -> list[tuple[int, int]]:
  """For each tap i of a stride-1 'SAME' kernel of size k over `size` positions: the [lo, hi)
  input positions it reads (positions in the padding read zeros)."""
  before = _same_pads(k)[0]
  return [(max(0, i - before), min(size, size + i - before)) for i in range(k)]


class ConvMean(_SameConv):
  """mean over (H, W) of a k x k 'SAME' conv of x: (..., H, W, Cin) -> (..., Cout), in at least
  float32 (as `global_avg_pool(at_least_f32(conv(x)))`); see "Equivalent rewrites"."""

  @nn.compact
  def __call__(self, x: Array) -> Array:
    if not _rewrites:
      return global_avg_pool(at_least_f32(super().__call__(x)))
    k = self._check()
    kernel, bias = self._params(x.shape[-1])
    h, w = x.shape[-3:-1]
    xf = at_least_f32(x)
    rows = [jnp.sum(xf[..., a:b, :, :], axis=-3) for a, b in _tap_windows(h, k)]
    cols = _tap_windows(w, k)
    sums = jnp.stack(
      [jnp.stack([jnp.sum(r[..., a:b, :], axis=-2) for a, b in cols], axis=-2) for r in rows], -3
    )  # (..., k, k, Cin): the window sum of each tap
    sums, kernel, bias = self.promote_dtype(sums, kernel, bias, dtype=self.dtype)
    y = jnp.einsum(
      "...ijc,ijcd->...d",
      sums,
      kernel,
      preferred_element_type=jnp.promote_types(sums.dtype, jnp.float32),
    )
    return y / (h * w) + at_least_f32(bias)


def _subpixel_groups(k: int, parity: int) -> tuple[np.ndarray, tuple[int, int]]:
  """Taps of a k-tap 'SAME' kernel applied after nearest x2 upsampling, grouped for one output
  parity: (G (n, k) 0/1, G[d, i] = 1 when tap i reads source offset d_min + d; the padding
  (before, after) of the n-tap conv at the source resolution)."""
  before = _same_pads(k)[0]
  offsets = [(parity - before + i) // 2 for i in range(k)]
  lo, hi = min(offsets), max(offsets)
  groups = np.zeros((hi - lo + 1, k), np.float32)
  for i, d in enumerate(offsets):
    groups[d - lo, i] = 1.0
  return groups, (-lo, hi)


class UpConv(_SameConv):
  """conv(upsample2(x)): a k x k 'SAME' conv of the nearest x2 upsampling of x,
  (N, H, W, Cin) -> (N, 2H, 2W, Cout); see "Equivalent rewrites"."""

  @nn.compact
  def __call__(self, x: Array) -> Array:
    if not _rewrites:
      return super().__call__(upsample2(x))
    k = self._check()
    kernel, bias = self._params(x.shape[-1])
    x, kernel, bias = self.promote_dtype(x, kernel, bias, dtype=self.dtype)
    if k == 1:  # a 1 x 1 conv commutes with the upsampling
      return upsample2(self._conv(x, kernel, ((0, 0), (0, 0))) + bias)
    out = []
    for a in (0, 1):
      g_a, pad_a = _subpixel_groups(k, a)
      row = []
      for b in (0, 1):
        g_b, pad_b = _subpixel_groups(k, b)
        sub = jnp.einsum("di,ej,ijco->deco", g_a, g_b, kernel).astype(kernel.dtype)
        row.append(self._conv(x, sub, (pad_a, pad_b)))
      out.append(jnp.stack(row, axis=-2))  # (N, H, W, 2, Cout): columns 2w + b
    y = jnp.stack(out, axis=-4)  # (N, H, 2, W, 2, Cout): rows 2h + a
    n, hh, _, ww, _, c = y.shape
    return y.reshape(n, 2 * hh, 2 * ww, c) + bias


class ConcatConstantConv(_SameConv):
  """conv(concat([x, v tiled over (H, W)], -1)): x (N, H, W, C), v (N, P) -> (N, H, W, Cout), a
  k x k 'SAME' conv over C + P input channels; see "Equivalent rewrites"."""

  @nn.compact
  def __call__(self, x: Array, v: Array) -> Array:
    if not _rewrites:
      tiled = jnp.broadcast_to(v[:, None, None, :], (*x.shape[:3], v.shape[-1])).astype(x.dtype)
      return super().__call__(jnp.concatenate([x, tiled], axis=-1))
    k = self._check()
    c = x.shape[-1]
    kernel, bias = self._params(c + v.shape[-1])
    x, v, kernel, bias = self.promote_dtype(x, v.astype(x.dtype), kernel, bias, dtype=self.dtype)
    y = self._conv(x, kernel[:, :, :c], (_same_pads(k), _same_pads(k)))
    # The tiled v: at (h, w) the taps inside the image sum their kernels; positions with the
    # same taps inside (the border classes) share one sum.
    h, w = x.shape[1:3]
    row_cls, row_taps = _border_classes(h, k)
    col_cls, col_taps = _border_classes(w, k)
    summed = jnp.einsum("ri,sj,ijpo->rspo", row_taps, col_taps, kernel[:, :, c:]).astype(x.dtype)
    per_class = jnp.einsum("np,rspo->nrso", v, summed)  # (N, classes_h, classes_w, Cout)
    tiled = per_class[:, row_cls][:, :, col_cls]
    return y + tiled + bias


def _border_classes(size: int, k: int) -> tuple[np.ndarray, np.ndarray]:
  """Positions of a stride-1 'SAME' k-tap conv grouped by which taps fall inside [0, size):
  (class of each position (size,), taps inside per class (classes, k) 0/1)."""
  inside = np.array(
    [[0 <= p + i - _same_pads(k)[0] < size for i in range(k)] for p in range(size)], np.float32
  )
  taps, cls = np.unique(inside, axis=0, return_inverse=True)
  return cls.reshape(-1), taps


def dense(features: int, *, name: str, dtype: Any = None) -> nn.Dense:
  """Dense layer with glorot_uniform kernel and zero bias (TF1 `tf.layers.dense` defaults);
  computed in `dtype`."""
  return nn.Dense(features, kernel_init=kernel_init, bias_init=bias_init, dtype=dtype, name=name)


def rms(x: Array) -> Array:
  """Root mean square of all entries (a scalar), for activation logging."""
  return jnp.sqrt(jnp.mean(jnp.square(x.astype(jnp.float32))))


def flatten_leading(x: Array, n_trailing: int) -> tuple[Array, tuple[int, ...]]:
  """Merge the leading axes of x into one: (*lead, *trail) -> (prod(lead), *trail), lead."""
  lead = x.shape[: x.ndim - n_trailing]
  return x.reshape((-1, *x.shape[x.ndim - n_trailing :])), lead


class SceneTable(nn.Module):
  """Learned per-scene code u (the authors' code), looked up by integer scene index.

  The table is initialised N(0, init_stddev^2) (the authors' 0.001) and, when `normalise`, each
  looked-up row is divided by its L2 norm on every lookup (projection, not a penalty); the table
  itself keeps the raw values. `norm_eps` is added to the norm: 0 for the car and Gibson models
  (the norm is then floored at 1e-6 only to keep an all-zero row finite), 1e-6 for 7-Scenes.

  The parameter is called "table", shape (num_scenes, dim).
  """

  num_scenes: int
  dim: int
  normalise: bool = True
  norm_eps: float = 0.0
  init_stddev: float = 1e-3

  @nn.compact
  def __call__(self, scene_index: Array) -> tuple[Array, dict[str, Array]]:
    """Looks up scene codes.

    Args:
      scene_index: (...) integer scene indices in [0, num_scenes).

    Returns:
      u: (..., dim) scene codes, unit-norm when `normalise`.
      aux: {"raw_norm": (...) norm of the stored rows before normalisation}.
    """
    table = self.param(
      "table", nn.initializers.normal(stddev=self.init_stddev), (self.num_scenes, self.dim)
    )
    u = jnp.take(table, scene_index, axis=0)
    norm = jnp.linalg.norm(u, axis=-1, keepdims=True)
    if self.normalise:
      denom = norm + self.norm_eps if self.norm_eps > 0 else jnp.maximum(norm, 1e-6)
      u = u / denom
    return u, {"raw_norm": norm[..., 0]}


def param_count(tree: Any) -> int:
  """Number of scalars in a pytree of arrays or `jax.ShapeDtypeStruct`s (e.g. from eval_shape)."""
  return int(sum(int(x.size) for x in jax.tree_util.tree_leaves(tree)))


def intermediate_shapes(
  module: nn.Module, *args: Any, method: Callable[..., Any] | str | None = None
) -> dict[str, tuple[int, ...]]:
  """Shapes of the activations a model records with `sow("intermediates", ...)`, at no cost.

  Runs `module.init` under `jax.eval_shape`, so nothing is computed or allocated.

  Args:
    module: a Linen module whose `__call__` (or `method`) sows into "intermediates".
    *args: example inputs (arrays or `jax.ShapeDtypeStruct`s).
    method: optional method to run instead of `__call__`.

  Returns:
    {"path/name": shape} for every sown value (sorted by path, as Flax stores collections).
  """

  def run(*inputs):
    return module.init(jax.random.key(0), *inputs, method=method, mutable=True)

  variables = jax.eval_shape(run, *args)
  flat = jax.tree_util.tree_flatten_with_path(variables.get("intermediates", {}))[0]
  out = {}
  for path, leaf in flat:
    keys = [str(getattr(k, "key", getattr(k, "idx", k))) for k in path]
    # sow stores a tuple per name; drop its index.
    if keys and keys[-1].isdigit():
      keys = keys[:-1]
    out["/".join(keys)] = tuple(leaf.shape)
  return out


def check_channels(name: str, got: Sequence[int], expected: int) -> None:
  """Raises ValueError when a style vector's last axis does not match the layer it modulates."""
  if got[-1] != expected:
    raise ValueError(f"{name}: expected {expected} channels, got shape {tuple(got)}")

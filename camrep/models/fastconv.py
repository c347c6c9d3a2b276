"""2-D convolution whose weight gradient is computed as matmuls (a speed fix for XLA:CPU).

XLA:CPU runs the weight-gradient convolution of a conv layer 5-7x slower than the forward one
(~20-50 GFLOP/s against a ~110-146 GFLOP/s fp32 matmul peak on the project's 2-core machine;
BUILD_NOTES "Performance"), and in the GQN-rooms train step it is most of
the time. `conv_general_dilated` here has `lax.conv_general_dilated`'s signature (Flax's
`nn.Conv(conv_general_dilated=...)` takes it) and the same forward pass and input gradient, but a
custom VJP computes the kernel gradient of a k x k conv as k^2 matmuls, one per kernel tap:

  dW[i, j] = P_ij^T dY,   P_ij = (rows, Cin) input pixels seen by tap (i, j),   dY (rows, Cout),

with rows = N * Ho * Wo, P_ij a strided slice of the padded input. Same FLOPs as the convolution
(2 * rows * Cin * Cout per tap), run by XLA's dot emitter instead of its conv emitter. The result
equals XLA's own gradient up to float round-off (summation order; tests/test_models.py).

Which weight gradient is used is decided when the step is traced:
  "auto" (default): matmuls on the CPU backend, XLA's own conv gradient elsewhere (GPU/TPU conv
    libraries compute it well);
  "by_channels": per layer, matmuls on the CPU backend for convs with at least
    `MATMUL_MIN_CHANNELS` output channels, XLA's gradient for narrower ones and on other backends.
    With few output channels the k^2 strided input copies P_ij cost more than the tap matmuls
    (a copy of rows x Cin floats per rows x Cin x Cout multiply-adds), and XLA's own gradient is
    faster: the pose-regression step at the quick width (eighth width, 8-32 channels) ran 2.3x
    faster with it, while at paper width (128-256 channels) the matmuls stay 1.4x faster
    (BUILD_NOTES "The regression step's speed"). The regression learner traces its step so;
  "matmul" / "xla": forced, e.g. by `python -m camrep.bench.train_step` to compare the two.
Set it with `weight_grad("xla")` as a context manager around tracing, or `set_weight_grad`.
Layouts other than NHWC / HWIO, dilations and feature groups fall back to XLA's conv.

A strided conv's input gradient on XLA:CPU is a convolution over the cotangent dilated with
zeros (s^2 - 1 of every s^2 products are with zeros at stride s). With k divisible by s, a k x k
stride-s conv equals a (k/s) x (k/s) stride-1 conv over the space-to-depth(s) of its padded input
(`s2d_conv`): its input gradient is a stride-1 transposed conv, and a forward over few input
channels (an RGB image: 3 x 4 = 12 after the rearrangement) runs faster too. Decided when traced,
like the kernel gradient (`strided_input_grad`):
  "auto" (default): "s2d" on the CPU backend, "xla" elsewhere;
  "s2d": such convs' input gradients through the space-to-depth form, and their forward pass too
    where the input has at most `S2D_MAX_FORWARD_CHANNELS` channels;
  "xla": XLA's own.
The same function to float round-off (summation order; tests/test_models.py). The car regressor's
step on one thread: BUILD_NOTES "The regression step's speed".

bfloat16 (`model.dtype`): the forward conv and the input gradient run in the inputs' dtype, as
XLA's; the tap matmuls of the kernel gradient accumulate in float32 (`preferred_element_type`)
and their result is cast to the kernel's dtype (tests/test_mixed_precision.py).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
from jax import lax

Array = jax.Array

WEIGHT_GRAD_MODES = ("auto", "by_channels", "matmul", "xla")
MATMUL_MIN_CHANNELS = 128
"""Output channels from which "by_channels" computes a conv's kernel gradient as matmuls."""
_mode = "auto"


def set_weight_grad(mode: str) -> None:
  """Chooses the kernel gradient of convs traced from now on: "auto", "by_channels", "matmul" or
  "xla"."""
  global _mode
  if mode not in WEIGHT_GRAD_MODES:
    raise ValueError(f"weight_grad must be one of {WEIGHT_GRAD_MODES}, got {mode!r}")
  _mode = mode


STRIDED_INPUT_GRAD_MODES = ("auto", "s2d", "xla")
S2D_MAX_FORWARD_CHANNELS = 4
"""Input channels up to which "s2d" also computes a strided conv's forward pass in the
space-to-depth form (measured: 3 channels 1.7x faster, 8 channels 2x slower)."""
_strided = "auto"


def get_strided_input_grad() -> str:
  """The strided convs' input gradient in force, resolved for the default backend: "s2d" or
  "xla"."""
  if _strided == "auto":
    return "s2d" if jax.default_backend() == "cpu" else "xla"
  return _strided


@contextlib.contextmanager
def strided_input_grad(mode: str):
  """Chooses the input gradient of strided convs traced inside: "auto", "s2d" or "xla"
  (restored on exit)."""
  global _strided
  if mode not in STRIDED_INPUT_GRAD_MODES:
    raise ValueError(f"strided_input_grad must be one of {STRIDED_INPUT_GRAD_MODES}, got {mode!r}")
  old, _strided = _strided, mode
  try:
    yield
  finally:
    _strided = old


def get_weight_grad(out_channels: int | None = None) -> str:
  """The mode in force, resolved for the default backend: "matmul" or "xla".

  "by_channels" needs the conv's `out_channels` to resolve; without them it is returned as is.
  """
  if _mode == "by_channels":
    if jax.default_backend() != "cpu":
      return "xla"
    if out_channels is None:
      return _mode
    return "matmul" if out_channels >= MATMUL_MIN_CHANNELS else "xla"
  if _mode == "auto":
    return "matmul" if jax.default_backend() == "cpu" else "xla"
  return _mode


@contextlib.contextmanager
def weight_grad(mode: str):
  """Context manager form of `set_weight_grad` (restores the previous mode on exit)."""
  old = _mode
  set_weight_grad(mode)
  try:
    yield
  finally:
    set_weight_grad(old)


def _xla_conv(x: Array, w: Array, strides, pads, precision) -> Array:
  return lax.conv_general_dilated(
    x, w, strides, pads, dimension_numbers=("NHWC", "HWIO", "NHWC"), precision=precision
  )


def kernel_grad_matmul(x: Array, dy: Array, kernel_hw: tuple[int, int], strides, pads) -> Array:
  """Kernel gradient of an NHWC / HWIO conv as one matmul per kernel tap.

  Args:
    x: (N, H, W, Cin) conv input.
    dy: (N, Ho, Wo, Cout) cotangent of the conv output.
    kernel_hw: (kh, kw).
    strides: (sh, sw).
    pads: ((top, bottom), (left, right)) explicit padding of the forward conv.

  Returns:
    (kh, kw, Cin, Cout) dW = sum over n, h, w of x_pad[n, sh*h + i, sw*w + j, :] dy[n, h, w, :],
    accumulated and returned in float32 (or wider, for float64 inputs).
  """
  (kh, kw), (sh, sw) = kernel_hw, strides
  n, ho, wo, cout = dy.shape
  cin = x.shape[-1]
  xp = jnp.pad(x, ((0, 0), tuple(pads[0]), tuple(pads[1]), (0, 0)))
  g = dy.reshape(n * ho * wo, cout)
  taps = []
  for i in range(kh):
    for j in range(kw):
      patch = lax.slice(
        xp, (0, i, j, 0), (n, i + sh * (ho - 1) + 1, j + sw * (wo - 1) + 1, cin), (1, sh, sw, 1)
      )
      p = patch.reshape(n * ho * wo, cin).T
      taps.append(jnp.dot(p, g, preferred_element_type=jnp.promote_types(p.dtype, jnp.float32)))
  return jnp.stack(taps).reshape(kh, kw, cin, cout)


def s2d_applies(kernel_hw: tuple[int, int], strides, pads) -> bool:
  """Whether `s2d_conv` computes this conv: some stride above 1, each kernel side divisible by
  its stride, no negative padding."""
  return (
    any(s > 1 for s in strides)
    and all(k % s == 0 for k, s in zip(kernel_hw, strides, strict=True))
    and all(p >= 0 for side in pads for p in side)
  )


def s2d_conv(x: Array, w: Array, strides, pads, precision=None) -> Array:
  """An NHWC / HWIO conv with kernel sides divisible by the strides (`s2d_applies`), as a
  stride-1 conv over the space-to-depth of its padded input.

  Args:
    x: (N, H, W, Cin).
    w: (kh, kw, Cin, Cout).
    strides: (sh, sw).
    pads: ((top, bottom), (left, right)), explicit and non-negative.
    precision: as `lax.conv_general_dilated`'s.

  Returns:
    (N, Ho, Wo, Cout), the conv `_xla_conv(x, w, strides, pads)` to float round-off: with
    z[n, y, x, (p, q, c)] = x_pad[n, sh*y + p, sw*x + q, c] and
    w2[a, b, (p, q, c), o] = w[sh*a + p, sw*b + q, c, o], out[n, y, x] = sum over a, b of
    z[n, y + a, x + b] . w2[a, b] (a < kh / sh, b < kw / sw).
  """
  n, h, wd, c = x.shape
  (kh, kw), (sh, sw) = w.shape[:2], strides
  ho = (h + pads[0][0] + pads[0][1] - kh) // sh + 1
  wo = (wd + pads[1][0] + pads[1][1] - kw) // sw + 1
  lh, lw = sh * (ho - 1) + kh, sw * (wo - 1) + kw  # the rows and columns some window reads
  xp = jnp.pad(x, ((0, 0), tuple(pads[0]), tuple(pads[1]), (0, 0)))[:, :lh, :lw]
  z = xp.reshape(n, lh // sh, sh, lw // sw, sw, c).transpose(0, 1, 3, 2, 4, 5)
  z = z.reshape(n, lh // sh, lw // sw, sh * sw * c)
  o = w.shape[-1]
  w2 = w.reshape(kh // sh, sh, kw // sw, sw, c, o).transpose(0, 2, 1, 3, 4, 5)
  w2 = w2.reshape(kh // sh, kw // sw, sh * sw * c, o)
  return _xla_conv(z, w2, (1, 1), ((0, 0), (0, 0)), precision)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3, 4, 5, 6))
def _conv_cpu(x: Array, w: Array, strides, pads, precision, kernel_grad: str, s2d: bool) -> Array:
  """The conv with the kernel gradient `kernel_grad` ("matmul" or "xla") and, with `s2d`, the
  input gradient (and for few input channels the forward pass) in the space-to-depth form."""
  return _conv_cpu_fwd(x, w, strides, pads, precision, kernel_grad, s2d)[0]


def _conv_cpu_fwd(x, w, strides, pads, precision, kernel_grad, s2d):
  if s2d and x.shape[-1] <= S2D_MAX_FORWARD_CHANNELS:
    y = s2d_conv(x, w, strides, pads, precision)
  else:
    y = _xla_conv(x, w, strides, pads, precision)
  return y, (x, w)


def _conv_cpu_bwd(strides, pads, precision, kernel_grad, s2d, res, dy):
  x, w = res
  # The gradients are transposes of the conv, linear in x and in w: `linear_transpose` gives them
  # without tracing the forward conv again (a `vjp` would, as dead code in the jaxpr).
  conv = s2d_conv if s2d else _xla_conv
  (dx,) = jax.linear_transpose(lambda x_: conv(x_, w, strides, pads, precision), x)(dy)
  if kernel_grad == "matmul":
    dw = kernel_grad_matmul(x, dy, w.shape[:2], strides, pads).astype(w.dtype)
  else:
    (dw,) = jax.linear_transpose(lambda w_: _xla_conv(x, w_, strides, pads, precision), w)(dy)
  return dx, dw


_conv_cpu.defvjp(_conv_cpu_fwd, _conv_cpu_bwd)


def _is_nhwc(dimension_numbers, ndim: int) -> bool:
  if ndim != 4:
    return False
  if dimension_numbers is None:  # lax's default is NCHW / OIHW
    return False
  if isinstance(dimension_numbers, lax.ConvDimensionNumbers):
    return tuple(dimension_numbers) == ((0, 3, 1, 2), (3, 2, 0, 1), (0, 3, 1, 2))
  return tuple(dimension_numbers) == ("NHWC", "HWIO", "NHWC")


def conv_general_dilated(
  lhs: Array,
  rhs: Array,
  window_strides: Sequence[int],
  padding,
  lhs_dilation: Sequence[int] | None = None,
  rhs_dilation: Sequence[int] | None = None,
  dimension_numbers=None,
  feature_group_count: int = 1,
  batch_group_count: int = 1,
  precision=None,
  preferred_element_type=None,
) -> Array:
  """`lax.conv_general_dilated` with the matmul kernel gradient and the space-to-depth input
  gradient of strided convs, each where its mode chooses it (see the module docstring).

  Args, returns: as `jax.lax.conv_general_dilated`.
  """
  plain = (
    _is_nhwc(dimension_numbers, lhs.ndim)
    and all(d == 1 for d in (lhs_dilation or (1, 1)))
    and all(d == 1 for d in (rhs_dilation or (1, 1)))
    and feature_group_count == 1
    and batch_group_count == 1
    and preferred_element_type is None
  )
  strides = tuple(int(s) for s in window_strides)
  if plain:
    if isinstance(padding, str):
      pads = lax.padtype_to_pads(lhs.shape[1:3], rhs.shape[:2], strides, padding)
    else:
      pads = padding
    pads = tuple((int(a), int(b)) for a, b in pads)
    kernel_grad = get_weight_grad(rhs.shape[-1])
    s2d = get_strided_input_grad() == "s2d" and s2d_applies(rhs.shape[:2], strides, pads)
  if not plain or (kernel_grad == "xla" and not s2d):
    return lax.conv_general_dilated(
      lhs,
      rhs,
      window_strides,
      padding,
      lhs_dilation=lhs_dilation,
      rhs_dilation=rhs_dilation,
      dimension_numbers=dimension_numbers,
      feature_group_count=feature_group_count,
      batch_group_count=batch_group_count,
      precision=precision,
      preferred_element_type=preferred_element_type,
    )
  return _conv_cpu(lhs, rhs, strides, pads, precision, kernel_grad, s2d)

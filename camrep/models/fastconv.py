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


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3, 4))
def _conv_mm(x: Array, w: Array, strides, pads, precision) -> Array:
  return _xla_conv(x, w, strides, pads, precision)


def _conv_mm_fwd(x, w, strides, pads, precision):
  return _xla_conv(x, w, strides, pads, precision), (x, w)


def _conv_mm_bwd(strides, pads, precision, res, dy):
  x, w = res
  # The input gradient is the transpose of the (linear in x) conv: `linear_transpose` gives it
  # without tracing the forward conv again (a `vjp` would, as dead code in the jaxpr).
  transpose = jax.linear_transpose(lambda x_: _xla_conv(x_, w, strides, pads, precision), x)
  (dx,) = transpose(dy)
  dw = kernel_grad_matmul(x, dy, w.shape[:2], strides, pads).astype(w.dtype)
  return dx, dw


_conv_mm.defvjp(_conv_mm_fwd, _conv_mm_bwd)


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
  """`lax.conv_general_dilated` with the matmul kernel gradient (see the module docstring).

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
  if not plain or get_weight_grad(rhs.shape[-1]) == "xla":
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
  strides = tuple(int(s) for s in window_strides)
  if isinstance(padding, str):
    pads = lax.padtype_to_pads(lhs.shape[1:3], rhs.shape[:2], strides, padding)
  else:
    pads = padding
  pads = tuple((int(a), int(b)) for a, b in pads)
  return _conv_mm(lhs, rhs, strides, pads, precision)

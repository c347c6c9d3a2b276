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

Also here: `SceneTable`, the learned per-scene code u of the car, Gibson and 7-Scenes models
(the authors' code), and `param_count` / `intermediate_shapes` helpers for logging.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

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


def conv(features: int, kernel: int, *, strides: int = 1, name: str, dtype: Any = None) -> nn.Conv:
  """TF-style conv: k x k kernel, 'SAME' padding, glorot_uniform kernel, zero bias; computed in
  `dtype` (inputs and the float32 parameters are cast to it; None: Flax infers it, float32).

  Also stands in for the authors' stride-1 `conv2d_transpose` layers: with stride 1 a transposed
  conv is a conv with a flipped kernel, which does not matter when training from scratch.
  On CPU its kernel gradient is computed as matmuls (`camrep.models.fastconv`).
  """
  return nn.Conv(
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

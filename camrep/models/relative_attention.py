"""Relative camera encodings inside attention: per-view transforms of queries, keys, values and
outputs (GTA, Miyato et al., ICLR 2024; PRoPE, Li et al., NeurIPS 2025), with 2-D RoPE of the
patch positions.

A relative encoding gives every token t an invertible block-diagonal matrix D_t acting on each
head's features, and attention runs on

  q'_t = D_t^T q_t,    k'_t = D_t^{-1} k_t,    v'_t = D_t^{-1} v_t,    o_t = D_t o'_t,      (R1)

where o'_t is ordinary softmax attention over (q', k', v'). The score and the message from
token j to token i are then

  s_ij = q_i^T D_i D_j^{-1} k_j,          o_i = sum_j a_ij D_i D_j^{-1} v_j,                  (R2)

so they see the tokens' cameras only through the relative transform D_i D_j^{-1} (GTA's eq. 6
with rho(g) = D; PRoPE's eq. 8 with D = its projective matrix). For orthogonal D (RoPE, SO(3),
camrep's learned M(p)) D^T = D^{-1} and queries and keys are transformed alike.

Head-feature layout (head_dim h), in this order:

  camera     the view's blocks D^cam (k chunks of b x b matrices, each chunk its own matrix: a
             `ViewTransform`), the whole set repeated reps = max(1, (h // 2) // (k b)) times
             (PRoPE and GTA: one 4 x 4 matrix tiled over half of the head);
  rope_x     r / 2 dims: RoPE of the patch column c, D = R(c omega_f) on planes
             (x_f, x_{F + f}) (the "split" layout), omega_f = base^(-f / F), F = r / 4;
  rope_y     r / 2 dims: the same for the patch row;
  identity   the h - camera - r < 4 leftover dims, untouched;

with r = 4 floor((h - camera) / 4). Tokens of one view share D^cam; tokens at the same patch
position share the RoPE part, so for two tokens of one view the relative transform is the RoPE
of their patch offset, and across views it is D^cam_i (D^cam_j)^{-1} on the camera dims.

Token layout: q, k, v, o are (..., V, N, heads, h) with N = rows * cols patches in row-major
order, and a `ViewTransform` is (..., V, k, b, b) over the same leading axes.

Using a relative encoding in one's own attention layer takes two calls around it:

  q, k, v = relative_attention.encode_qkv(q, k, v, transform, grid=(rows, cols))
  o = my_attention(q, k, v)            # any softmax attention over the V * N tokens
  o = relative_attention.decode_out(o, transform, grid=(rows, cols))

(`attention` does exactly this with plain softmax attention; `camrep.models.camera_conditioning`
builds the transforms from poses.)
"""

from __future__ import annotations

import dataclasses

import flax.struct
import jax
import jax.numpy as jnp

Array = jax.Array

ROPE_BASE = 100.0  # PRoPE's patch RoPE: omega_f = 100^(-f / F)


@flax.struct.dataclass
class ViewTransform:
  """The camera part D^cam of a relative encoding, per view, and its inverse.

  Attributes:
    D: (..., V, k, b, b) k chunks of b x b blocks per view: D^cam = diag(D[..., 0, :, :], ...).
    D_inv: (..., V, k, b, b) their inverses (the transposes for orthogonal blocks).
  """

  D: Array
  D_inv: Array

  @property
  def chunks(self) -> int:
    """k, the number of distinct blocks per view."""
    return self.D.shape[-3]

  @property
  def block(self) -> int:
    """b, the block size."""
    return self.D.shape[-1]

  @classmethod
  def orthogonal(cls, D: Array) -> ViewTransform:
    """A transform of orthogonal blocks D (..., V, k, b, b): D^{-1} = D^T."""
    return cls(D=D, D_inv=jnp.swapaxes(D, -1, -2))

  @classmethod
  def concat_views(cls, transforms: list[ViewTransform]) -> ViewTransform:
    """Transforms of several view groups joined along the view axis (their leading axes must
    broadcast)."""
    lead = jnp.broadcast_shapes(*(t.D.shape[:-4] for t in transforms))

    def cat(xs):
      return jnp.concatenate([jnp.broadcast_to(x, (*lead, *x.shape[-4:])) for x in xs], axis=-4)

    return cls(D=cat([t.D for t in transforms]), D_inv=cat([t.D_inv for t in transforms]))


@dataclasses.dataclass(frozen=True)
class HeadLayout:
  """How a relative encoding splits one head's h features (see the module docstring).

  Attributes:
    camera: dims carrying D^cam (reps * k * b).
    reps: repetitions of the k chunks.
    rope: dims carrying the patch RoPE (half for columns, half for rows; a multiple of 4).
  """

  camera: int
  reps: int
  rope: int

  @classmethod
  def of(cls, head_dim: int, chunks: int, block: int) -> HeadLayout:
    """The layout for k = `chunks` blocks of size b = `block` in a head of `head_dim`.

    Raises:
      ValueError: the k b camera dims do not fit in the head.
    """
    width = chunks * block
    if width > head_dim:
      raise ValueError(
        f"the camera transform needs {width} dims per head ({chunks} blocks of {block}), the "
        f"head has {head_dim}: raise the width or the head size, or use smaller blocks"
      )
    reps = max(1, (head_dim // 2) // width)
    camera = reps * width
    return cls(camera=camera, reps=reps, rope=4 * ((head_dim - camera) // 4))


def rope_angles(
  grid: tuple[int, int], n_freqs: int, *, base: float = ROPE_BASE, dtype=jnp.float32
) -> tuple[Array, Array]:
  """Angles of the patch RoPE: (N, F) for columns and for rows.

  theta_x[n, f] = col(n) omega_f, theta_y[n, f] = row(n) omega_f, omega_f = base^(-f / F),
  patches n = row * cols + col (PRoPE's coefficients).
  """
  rows, cols = grid
  omega = base ** (-jnp.arange(n_freqs, dtype=dtype) / max(n_freqs, 1))
  n = jnp.arange(rows * cols)
  col, row = (n % cols).astype(dtype), (n // cols).astype(dtype)
  return col[:, None] * omega, row[:, None] * omega


def _rotate_split(x: Array, angles: Array, sign: float) -> Array:
  """R(sign * angle) on the planes (x_f, x_{F + f}) of x (..., N, heads, 2F); angles (N, F)."""
  f = x.shape[-1] // 2
  cos = jnp.cos(angles)[:, None, :].astype(x.dtype)
  sin = (sign * jnp.sin(angles))[:, None, :].astype(x.dtype)
  a, b = x[..., :f], x[..., f:]
  return jnp.concatenate([cos * a - sin * b, sin * a + cos * b], axis=-1)


def _apply_blocks(x: Array, M: Array, reps: int) -> Array:
  """Per-view blocks on the camera dims: x (..., V, N, heads, reps k b), M (..., V, k, b, b)."""
  k, b = M.shape[-3], M.shape[-1]
  xs = x.reshape(*x.shape[:-1], reps, k, b)
  y = jnp.einsum("...vcij,...vnhrcj->...vnhrci", M.astype(x.dtype), xs)
  return y.reshape(x.shape)


def _transform(x: Array, M: Array | None, grid, sign: float, base: float) -> Array:
  """x (..., V, N, heads, h) through camera blocks M (or none) and the patch RoPE R(sign theta)."""
  h = x.shape[-1]
  if M is None:
    layout = HeadLayout(camera=0, reps=1, rope=4 * (h // 4))
  else:
    layout = HeadLayout.of(h, M.shape[-3], M.shape[-1])
  parts = []
  if layout.camera:
    parts.append(_apply_blocks(x[..., : layout.camera], M, layout.reps))
  if layout.rope:
    r2 = layout.rope // 2
    theta_x, theta_y = rope_angles(
      grid, r2 // 2, base=base, dtype=jnp.promote_types(x.dtype, jnp.float32)
    )
    start = layout.camera
    parts.append(_rotate_split(x[..., start : start + r2], theta_x, sign))
    parts.append(_rotate_split(x[..., start + r2 : start + 2 * r2], theta_y, sign))
  if layout.camera + layout.rope < h:
    parts.append(x[..., layout.camera + layout.rope :])
  return jnp.concatenate(parts, axis=-1)


def _check(x: Array, transform: ViewTransform | None, grid) -> None:
  rows, cols = grid
  if x.ndim < 4 or x.shape[-3] != rows * cols:
    raise ValueError(f"features must be (..., V, N={rows * cols}, heads, h), got {x.shape}")
  if transform is not None and transform.D.shape[-4] != x.shape[-4]:
    raise ValueError(f"the transform has {transform.D.shape[-4]} views, the features {x.shape[-4]}")


def encode_qkv(
  q: Array,
  k: Array,
  v: Array,
  transform: ViewTransform | None,
  *,
  grid: tuple[int, int],
  base: float = ROPE_BASE,
  values: bool = True,
) -> tuple[Array, Array, Array]:
  """Queries, keys and values of eq. R1: D^T q, D^{-1} k, D^{-1} v per token.

  Args:
    q, k, v: (..., V, N, heads, h) features, N = rows * cols patches per view (row-major).
    transform: per-view camera blocks (..., V, k, b, b); None: the patch RoPE only.
    grid: (rows, cols) of patches.
    base: RoPE frequency base.
    values: transform the values too (GTA and PRoPE do); False leaves v (and `decode_out`
      must then be called with values=False).

  Returns:
    (q', k', v'), shapes unchanged.
  """
  for x in (q, k, v):
    _check(x, transform, grid)
  Dq = None if transform is None else jnp.swapaxes(transform.D, -1, -2)
  Dk = None if transform is None else transform.D_inv
  # RoPE blocks are orthogonal: D^T = D^{-1} = R(-theta) for queries, keys and values alike.
  q2 = _transform(q, Dq, grid, -1.0, base)
  k2 = _transform(k, Dk, grid, -1.0, base)
  v2 = _transform(v, Dk, grid, -1.0, base) if values else v
  return q2, k2, v2


def decode_out(
  o: Array,
  transform: ViewTransform | None,
  *,
  grid: tuple[int, int],
  base: float = ROPE_BASE,
  values: bool = True,
) -> Array:
  """Attention output back in each token's frame (eq. R1): D o'; identity when values=False."""
  _check(o, transform, grid)
  if not values:
    return o
  return _transform(o, None if transform is None else transform.D, grid, 1.0, base)


def scores(
  q: Array, k: Array, transform: ViewTransform | None, *, grid, base: float = ROPE_BASE
) -> Array:
  """Attention logits s_ij / sqrt(h) of eq. R2 between all V N tokens: (..., heads, T, T)."""
  q2, k2, _ = encode_qkv(q, k, k, transform, grid=grid, base=base, values=False)
  return _logits(q2, k2)


def _logits(q: Array, k: Array) -> Array:
  h = q.shape[-1]
  qf = q.reshape(*q.shape[:-4], -1, *q.shape[-2:])
  kf = k.reshape(*k.shape[:-4], -1, *k.shape[-2:])
  return jnp.einsum("...thd,...shd->...hts", qf, kf) / jnp.sqrt(jnp.asarray(h, q.dtype))


def attention(
  q: Array,
  k: Array,
  v: Array,
  transform: ViewTransform | None,
  *,
  grid: tuple[int, int],
  base: float = ROPE_BASE,
  values: bool = True,
) -> Array:
  """Softmax attention of every token over every token of every view with a relative encoding
  (eqs. R1-R2).

  Args:
    q, k, v: (..., V, N, heads, h).
    transform: per-view camera blocks (..., V, k, b, b), or None for the patch RoPE only.
    grid, base, values: as in `encode_qkv`.

  Returns:
    (..., V, N, heads, h).
  """
  q2, k2, v2 = encode_qkv(q, k, v, transform, grid=grid, base=base, values=values)
  logits = _logits(q2, k2)
  a = jax.nn.softmax(logits.astype(jnp.promote_types(logits.dtype, jnp.float32)), axis=-1)
  a = a.astype(v2.dtype)
  vf = v2.reshape(*v2.shape[:-4], -1, *v2.shape[-2:])
  o = jnp.einsum("...hts,...shd->...thd", a, vf).reshape(v2.shape)
  return decode_out(o, transform, grid=grid, base=base, values=values)

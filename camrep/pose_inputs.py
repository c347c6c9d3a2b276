"""Every pose input a view-synthesis decoder can take (paper sections 3.1-3.3; supplement).

`config.rep.kind` picks one:

  grid    camrep's learned pose system (`camrep.pose`: grid vectors rotated by exp(B delta)),
          the paper's method;
  lowdim  GQN's low-dimensional pose vector (Eslami et al. 2018): raw positions and (sin, cos) of
          angles, the paper's view-synthesis baseline;
  mlp     the supplement's MLP embedding: per DOF a 2-layer MLP (hidden 128, leaky ReLU) of the
          pose, trained with the decoder (also a regression target, `camrep.regression.targets`).

All return per-DOF vectors {name: (..., k)} from poses (..., P), so decoders and regressors take
any of them unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import flax.linen as nn
import jax
import jax.numpy as jnp

from camrep import pose as P
from camrep.data import sources

Array = jax.Array


# The decoder's pose input (config.rep.kind): camrep's learned system (the paper's method), or a
# comparison input for the noise-robustness figure (issue 5): GQN's low-dimensional pose vector,
# or the supplement's MLP embedding (one 128 -> d MLP per DOF, trained with the decoder).
REP_KINDS = ("grid", "lowdim", "mlp")


def rep_kind(config) -> str:
  kind = config.rep.get("kind", "grid")
  if kind not in REP_KINDS:
    raise ValueError(f"unknown rep.kind {kind!r}; choose one of {REP_KINDS}")
  return kind


def lowdim_constants(config) -> tuple[float, float]:
  """(camera height, pitch) of the GQN-rooms procedural family: the constant z and pitch of GQN's
  low-dimensional pose vector."""
  from camrep.data import procedural

  rooms = procedural.RoomsConfig()
  fam = config.data.family
  return float(fam.get("camera_height", rooms.camera_height)), float(fam.get("pitch", rooms.pitch))


def lowdim_vectors(config, spec: P.PoseSystemSpec, poses: Array) -> dict[str, Array]:
  """GQN's low-dimensional pose input, split by DOF: {name: (..., k)}.

  GQN rooms (Eslami et al. 2018): (x, y, z, sin yaw, cos yaw, sin pitch, cos pitch), with the
  procedural rooms' constant camera height and pitch: "xy" -> (x, y, z), "yaw" -> (sin yaw,
  cos yaw, sin pitch, cos pitch). Other settings: polar / linear DOFs raw, angles (sin, cos).
  """
  gqn = sources.setting_of(config.data.source) == "gqn"
  z, pitch = lowdim_constants(config) if gqn else (0.0, 0.0)
  out = {}
  for d in spec.dofs:
    cols = poses[..., spec.columns(d.name)]
    ones = jnp.ones(cols.shape[:-1] + (1,), cols.dtype)
    if isinstance(d, P.AngularDof):
      v = jnp.concatenate([jnp.sin(cols), jnp.cos(cols)], -1)
      if gqn:
        v = jnp.concatenate([v, math.sin(pitch) * ones, math.cos(pitch) * ones], -1)
    else:
      v = jnp.concatenate([cols, z * ones], -1) if gqn and isinstance(d, P.PolarDof) else cols
    out[d.name] = v
  return out


def init_rep(key: Array, config, spec: P.PoseSystemSpec) -> dict:
  """Parameters of the pose-input group ("rep"): the learned system, the MLPs, or none."""
  kind = rep_kind(config)
  if kind == "grid":
    return P.init(key, spec)
  if kind == "mlp":
    return init_mlp(key, spec)
  return {}


def pose_vectors(
  config, spec: P.PoseSystemSpec, rep, poses: Array, *, mode: str = "nearest", key=None
) -> dict[str, Array]:
  """Per-DOF decoder inputs of poses (..., P) for the config's `rep.kind`: {name: (..., k)}.

  `mode` and `key` (quantisation of the learned system) are ignored by the other kinds.
  """
  kind = rep_kind(config)
  if kind == "grid":
    return P.embed(rep, spec, poses, mode=mode, key=key)
  if kind == "mlp":
    return mlp_embed(rep, spec, poses)
  return lowdim_vectors(config, spec, poses)


class MlpEmbedding(nn.Module):
  """Supplement baseline: v(l) = normalise(W2 lrelu(W1 l + b1) + b2) for one DOF.

  The input is the DOF value mapped linearly from [low, high] to [-1, 1] (two inputs for a polar
  DOF). The supplement gives no initialisation; here W1, b1 ~ N(0, 1) so that the 128 kinks of
  the leaky ReLU fall across the input range (with zero biases every kink would sit at 0 and the
  normalised output would take only two values), W2 glorot, b2 = 0. The output is unit-normalised
  like the learned system's angle vectors.

  Attributes:
    dim: output size d (96).
    hidden: hidden units (128).
  """

  dim: int = 96
  hidden: int = 128

  @nn.compact
  def __call__(self, x: Array) -> Array:
    """(..., n_in) inputs in [-1, 1] -> (..., dim) unit vectors."""
    normal = nn.initializers.normal(1.0)
    h = nn.Dense(self.hidden, kernel_init=normal, bias_init=normal, name="hidden")(x)
    h = nn.leaky_relu(h, negative_slope=0.2)  # TF slope, as camrep.models.layers.lrelu
    v = nn.Dense(self.dim, kernel_init=nn.initializers.xavier_uniform(), name="out")(h)
    return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True) + 1e-12)


def _mlp_input(d: P.Dof, value: Array) -> Array:
  x = 2.0 * (value - d.low) / (d.high - d.low) - 1.0
  return x if isinstance(d, P.PolarDof) else x[..., None]


def init_mlp(key: Array, spec: P.PoseSystemSpec, *, hidden: int = 128) -> dict:
  """Parameters of one `MlpEmbedding` per DOF of `spec`: {dof name: flax params}."""
  out = {}
  for i, d in enumerate(spec.dofs):
    x = jnp.zeros((1, d.width), jnp.float32)
    out[d.name] = MlpEmbedding(spec.dim, hidden).init(jax.random.fold_in(key, i), x)["params"]
  return out


def mlp_embed(
  mlp_params: Mapping, spec: P.PoseSystemSpec, poses: Array, *, hidden: int = 128
) -> dict[str, Array]:
  """MLP vectors of every DOF for poses (..., pose_dim): {name: (..., d)}."""
  out = {}
  for d in spec.dofs:
    cols = poses[..., spec.columns(d.name)]
    value = cols if isinstance(d, P.PolarDof) else cols[..., 0]
    module = MlpEmbedding(spec.dim, hidden)
    out[d.name] = module.apply({"params": mlp_params[d.name]}, _mlp_input(d, value))
  return out


def mlp_decode(
  mlp_params: Mapping, spec: P.PoseSystemSpec, heads: Mapping[str, Array], hidden: int
) -> Array:
  cols = []
  for d in spec.dofs:
    cands = P.candidates(spec, d.name)
    module = MlpEmbedding(spec.dim, hidden)
    cvec = module.apply({"params": mlp_params[d.name]}, _mlp_input(d, cands))  # (K, d)
    score = jnp.sum(cvec * cvec, -1) - 2.0 * jnp.einsum("...d,kd->...k", heads[d.name], cvec)
    best = cands[jnp.argmin(score, axis=-1)]
    cols.append(best if isinstance(d, P.PolarDof) else best[..., None])
  return jnp.concatenate(cols, axis=-1)

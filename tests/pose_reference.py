"""Stored outputs of camrep.pose and camrep.pose_encodings, to prove a refactor changes no number.

`outputs()` computes init, embed (three quantisation modes, in and out of range), rotate, the
rotation and direction losses, pair sampling, decode (with and without refinement), candidates,
Gram maps and the lowdim / MLP pose inputs for small systems of every DOF kind and exp method.
tests/data/pose_reference.npz holds what it returned at commit "tests: stored pose reference"
(before the DOF classes and the pose-input interface, with the parameter keys of then: "B",
"B0", "C"); test_pose.py compares bit for bit.

Regenerate (only when a change of numbers is intended, and say so in BUILD_NOTES):
  PYTHONPATH=$PWD python -m tests.pose_reference
"""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from camrep import pose as P
from camrep import pose_encodings
from camrep.configs import gqn
from camrep.synthesis import components, synthesizers

PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "pose_reference.npz")


def _specs() -> dict[str, P.PoseSystemSpec]:
  dofs_1d = (
    P.AngularDof("yaw"),
    P.LinearDof("x", -0.5, 1.5, 0.25),
    P.AngularDof("pitch", spacing=math.pi / 6, high=math.pi, periodic=False),
    P.AngularDof("roll", spacing=math.pi / 4, periodic=False, n_grid_override=8),
  )
  out = {}
  for method in ("taylor2", "spectral"):
    out[f"1d_{method}"] = P.PoseSystemSpec(
      dofs=dofs_1d, n_blocks=2, block_size=4, exp_method=method
    )
  polar = P.BinnedPolarDof(spacing=0.25, n_directions=12)
  for method in ("spectral",):
    out[f"binned_{method}"] = P.PoseSystemSpec(
      dofs=(polar, P.AngularDof("yaw", spacing=math.pi / 6)),
      n_blocks=2,
      block_size=4,
      exp_method=method,
    )
  cont = P.ContinuousPolarDof(spacing=0.25, block_norm=False, pair_radius=2.2)
  for method in ("expm",):
    out[f"continuous_{method}"] = P.PoseSystemSpec(
      dofs=(cont,), n_blocks=2, block_size=4, exp_method=method
    )
  return out


def _poses(spec: P.PoseSystemSpec) -> np.ndarray:
  """(12, pose_dim): random in-range poses, range ends, and poses beyond both ends."""
  rng = np.random.default_rng(20261125)
  cols = []
  for d in spec.dofs:
    lo, hi = d.low, d.high
    extra = np.array([lo, hi, lo - 0.6 * (hi - lo), hi + 0.7 * (hi - lo)])
    x = np.concatenate([rng.uniform(lo, hi, 8), extra])
    if d.width == 2:
      cols.append(np.stack([x, np.roll(x[::-1], 3)], -1))
    else:
      cols.append(x[:, None])
  return np.concatenate(cols, -1).astype(np.float32)


def _dof_values(spec: P.PoseSystemSpec, poses: np.ndarray, name: str) -> np.ndarray:
  cols = poses[:, spec.columns(name)]
  return cols if cols.shape[-1] == 2 else cols[:, 0]


def _flat(prefix: str, tree) -> dict:
  out = {}
  for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
    keys = "/".join(str(getattr(k, "key", k)) for k in path)
    out[f"{prefix}/{keys}"] = leaf
  return out


def _lowdim_input(source: str, spec: P.PoseSystemSpec) -> pose_encodings.LowDimEncoding:
  """The view-synthesis low-dim input of a run on `source` whose rooms have camera height 0.3 and
  pitch -0.2 (`synthesizers.pose_input`; GQN's 7-D vector on the rooms setting only)."""
  c = gqn.get_config("smoke")
  c.rep.kind = "lowdim"
  c.data.source = source
  c.data.family = {"camera_height": 0.3, "pitch": -0.2}
  return synthesizers.pose_input(components.resolve(c), spec)


def _params_and_noisy(spec: P.PoseSystemSpec, seed: jax.Array, poses: jax.Array):
  """The system's parameters and the noisy pose vectors its decodes start from."""
  key = lambda i: jax.random.fold_in(jax.random.key(seed), i)
  params = P.init(key(0), spec)
  vectors = P.embed(params, spec, poses)
  noisy = {
    n: v + 0.02 * jax.random.normal(key(10 + i), v.shape)
    for i, (n, v) in enumerate(sorted(vectors.items()))
  }
  return params, noisy


def _decode_residuals(spec, seed, poses, decoded) -> jax.Array:
  """(N, n_dofs): per DOF, the objective decoding minimises, ||v(decoded) - v_hat||^2 (eq. 12)."""
  params, noisy = _params_and_noisy(spec, seed, poses)
  cols = []
  for d in spec.dofs:
    x = _dof_values(spec, decoded, d.name)
    cols.append(jnp.sum((P.embed_dof(params, spec, d.name, x) - noisy[d.name]) ** 2, -1))
  return jnp.stack(cols, -1)


def _mlp_decode_residuals(spec, seed, poses, decoded) -> jax.Array:
  """(N, n_dofs): per DOF, the objective the MLP input's decode minimises over its candidates,
  ||f(decoded) - f(pose)||^2 (`MlpEncoding.decode`, of the vectors `_spec_outputs` decodes)."""
  mlp_input = pose_encodings.MlpEncoding(spec)
  mlp = mlp_input.init(jax.random.fold_in(jax.random.key(seed), 4))
  target, got = mlp_input.embed(mlp, poses), mlp_input.embed(mlp, decoded)
  return jnp.stack([jnp.sum((got[d.name] - target[d.name]) ** 2, -1) for d in spec.dofs], -1)


DECODES = ("decode_0", "decode_2", "mlp_decode")
"""The outputs that are an argmin over candidates (`decode_residuals` measures them)."""


def decode_residuals(decoded: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
  """{"<system>/<decode>": (N, n_dofs) residuals} of the decodes in `decoded` (same keys as
  `outputs`, a decode one of `DECODES`): two decodes that find equally good candidates have
  equal residuals, whichever of two near-tied candidates each picked."""
  out = {}
  for i, (sname, spec) in enumerate(_specs().items()):
    # One jitted objective a system (the grid's decodes share theirs: one compile for both).
    fns = {
      of: jax.jit(lambda seed, p, dec, spec=spec, of=of: of(spec, seed, p, dec))
      for of in (_decode_residuals, _mlp_decode_residuals)
    }
    for k in DECODES:
      name = f"{sname}/{k}"
      if name in decoded:
        fn = fns[_mlp_decode_residuals if k == "mlp_decode" else _decode_residuals]
        res = fn(jnp.uint32(100 + i), _poses(spec), jnp.asarray(decoded[name]))
        out[name] = np.asarray(res)
  return out


def _spec_outputs(
  spec: P.PoseSystemSpec, seed: jax.Array, poses: jax.Array
) -> dict[str, jax.Array]:
  """Every stored number of one system (jitted by `outputs`, so that XLA cannot fold it)."""
  out = {}
  key = lambda i: jax.random.fold_in(jax.random.key(seed), i)
  params, noisy = _params_and_noisy(spec, seed, poses)
  out.update(_flat("init", params))
  for mode in ("nearest", "floor", "random"):
    k = key(1) if mode == "random" else None
    out.update(_flat(f"embed_{mode}", P.embed(params, spec, poses, mode=mode, key=k)))
  out["decode_0"] = P.decode(params, spec, noisy, refine_steps=0)
  out["decode_2"] = P.decode(params, spec, P.concat(noisy, spec), refine_steps=2)
  out.update(_flat("rot", P.rotation_losses(key(2), params, spec, n_pairs=16)))
  shifted = poses[::-1] + 0.05
  rot_data = P.rotation_losses(
    key(3), params, spec, n_pairs=8, data_pairs=(poses, shifted), mode="nearest"
  )
  out.update(_flat("rot_data", rot_data))
  out["pose_delta"] = P.pose_delta(spec, poses, shifted)
  for i, d in enumerate(spec.dofs):
    values = _dof_values(spec, poses, d.name)
    v = P.embed_dof(params, spec, d.name, values)
    delta = jnp.linspace(-0.4, 0.3, len(values), dtype=jnp.float32)
    if d.width == 2:
      delta = jnp.stack([delta, delta[::-1] * 0.5], -1)
    out[f"{d.name}/rotate"] = P.rotate(params, spec, d.name, delta, v)
    out[f"{d.name}/pairs0"], out[f"{d.name}/pairs1"] = P.sample_pairs(key(20 + i), spec, d.name, 6)
    cands = P.candidates(spec, d.name)
    out[f"{d.name}/candidates"] = cands
    out[f"{d.name}/candidates_coarse"] = P.candidates(spec, d.name, d.spacing / 2)
    out[f"{d.name}/gram"] = P.gram(params, spec, d.name, values=cands[:: max(1, len(cands) // 24)])
    out[f"{d.name}/grid_std"] = P.grid_std(params, spec, d.name)
    if d.width == 2:
      out[f"{d.name}/direction"] = P.direction_loss(params, spec, d.name, max_shift=3)
  # The other pose inputs.
  for source in ("rooms", "object"):
    vecs = _lowdim_input(source, spec).embed({}, poses)
    out.update(_flat(f"lowdim_{source}", vecs))
  mlp_input = pose_encodings.MlpEncoding(spec)
  mlp = mlp_input.init(key(4))
  out.update(_flat("mlp_init", mlp))
  mlp_vectors = mlp_input.embed(mlp, poses)
  out.update(_flat("mlp_embed", mlp_vectors))
  out["mlp_decode"] = mlp_input.decode(mlp, mlp_vectors)
  return out


def outputs() -> dict[str, np.ndarray]:
  """Every stored number, {system name/output name: array}."""
  out = {}
  for i, (sname, spec) in enumerate(_specs().items()):
    poses = _poses(spec)
    fn = jax.jit(lambda seed, p, spec=spec: _spec_outputs(spec, seed, p))
    res = fn(jnp.uint32(100 + i), poses)
    out[f"{sname}/poses"] = poses
    out.update({f"{sname}/{k}": np.asarray(v) for k, v in res.items()})
  return out


def main():
  jax.config.update("jax_disable_most_optimizations", True)  # as test_pose.py's fast_compile
  os.makedirs(os.path.dirname(PATH), exist_ok=True)
  out = outputs()
  np.savez_compressed(PATH, **out)
  print(f"wrote {len(out)} arrays to {PATH} ({os.path.getsize(PATH)} bytes)")


if __name__ == "__main__":
  main()

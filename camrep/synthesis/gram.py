"""Gram maps V V^T of the learned pose vectors over each DOF's range (paper section 4.3,
the kernel figures): how similar the vectors of two poses are.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import jax
import numpy as np

from camrep import pose as P
from camrep.runtime import plots
from camrep.synthesis.restore import Run

Array = jax.Array


def gram_values(spec: P.PoseSystemSpec, name: str) -> Array:
  """The values of a Gram map: 1-degree steps for angles, the grid points otherwise.

  Returns:
    (K,) values, or (K, 2) positions for a polar DOF (flat index gx * n_side + gy).
  """
  return P.candidates(spec, name, spec.dof(name).gram_resolution)


def gram_maps(run: Run) -> dict[str, np.ndarray]:
  """{dof name: (K, K) Gram matrix V V^T} of the run's pose vectors over `gram_values`.

  Unit-norm DOFs have ones on the diagonal (up to the norm error of exp_method "taylor2" between
  grid points); a polar DOF with block_norm has 1 / n_blocks. Another pose input than the
  learned grid gives the same map of its vectors (`PoseEncoding.gram`).
  """
  rep, encoding = run.params["rep"], run.model.pose_encoding
  return {n: np.asarray(encoding.gram(rep, n, gram_values(run.spec, n))) for n in run.spec.names}


def _gram_caption(spec: P.PoseSystemSpec, name: str, k: int) -> str:
  return spec.dof(name).describe_grid(k)


def write_grams(out: str, run: Run, grams: Mapping[str, np.ndarray]) -> list[str]:
  """Writes out/gram_<dof>.png (and its PDF twin) and out/gram.npz ({dof}: Gram, {dof}_values:
  values)."""
  paths = []
  arrays = {}
  for name, g in grams.items():
    arrays[name] = g
    values = np.asarray(gram_values(run.spec, name))
    arrays[f"{name}_values"] = values
    angular = run.spec.dof(name).is_angle
    title = f"Gram V V^T of {name} ({g.shape[0]} x {g.shape[1]}), step {run.step}"
    fig = plots.gram_figure(
      g,
      plots.gram_axis(values, name=name, angular=angular),
      title=title,
      caption=_gram_caption(run.spec, name, g.shape[0]),
    )
    paths += plots.save(fig, os.path.join(out, f"gram_{name}.png"))
  npz = os.path.join(out, "gram.npz")
  np.savez(npz, **arrays)
  return [*paths, npz]

"""Helper for tests/test_lie.py: the jitted gradient of a polar + angular pose system's embedding,
exp_method="spectral", called CALLS times on a 2-thread XLA:CPU pool, then compared with
exp_method="expm". Prints one JSON line {"calls": CALLS, "rel_err": {parameter: max |spectral -
expm| / max |expm|}} (parameters with a zero gradient left out).

Usage (from the repository root): python -m tests.spectral_threads_script CALLS
"""

import json
import os
import sys

# XLA:CPU sizes its intra-op thread pool from NPROC; 2 threads whatever the machine.
os.environ["NPROC"] = "2"

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from camrep import pose as P  # noqa: E402

calls = int(sys.argv[1])
rng = np.random.default_rng(0)
# Both generator tables are big enough for a batched LAPACK call to split into pool tasks:
# polar 6 blocks x 144 directions, yaw 6 blocks, each 16 x 16.
dofs = (P.BinnedPolarDof("xy"), P.AngularDof("yaw"))
poses = np.concatenate([rng.uniform(-0.8, 0.8, (4, 3, 2)), rng.uniform(0, 6, (4, 3, 1))], -1)
poses = jnp.asarray(poses, jnp.float32)


def grad_fn(method):
  spec = P.PoseSystemSpec(dofs=dofs, n_blocks=6, block_size=16, exp_method=method)
  loss = lambda p: jnp.sum(P.concat(P.embed(p, spec, poses), spec) ** 3)
  return spec, jax.jit(jax.grad(loss))


spec, grad = grad_fn("spectral")
# Generators well away from zero (init's 0.001 leaves them near the identity).
params = jax.tree.map(lambda x: 300.0 * x, P.init(jax.random.key(0), spec))
for _ in range(calls):
  g = jax.block_until_ready(grad(params))
jax.config.update("jax_disable_most_optimizations", True)  # the reference: compile time only
g_ref = grad_fn("expm")[1](params)
rel_err = {}
leaves = jax.tree_util.tree_flatten_with_path(g)[0]
for (path, a), b in zip(leaves, jax.tree.leaves(g_ref), strict=True):
  scale = float(jnp.max(jnp.abs(b)))
  if scale > 0:
    rel_err[jax.tree_util.keystr(path)] = float(jnp.max(jnp.abs(a - b))) / scale
print(json.dumps({"calls": calls, "rel_err": rel_err}))

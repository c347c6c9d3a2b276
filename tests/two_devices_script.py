"""Helper for tests/test_train.py: train N steps on D forced host devices, save the parameters.

Usage (from the repository root): python -m tests.two_devices_script DEVICES STEPS OUT.npz
"""

import os
import sys

n_dev, steps, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
os.environ["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={n_dev}"

import jax  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_disable_most_optimizations", True)

from camrep.configs import gqn  # noqa: E402
from camrep.synthesis import components, train  # noqa: E402
from camrep.synthesis import step as step_lib  # noqa: E402

assert jax.local_device_count() == n_dev, jax.devices()
config = gqn.get_config("smoke")
config.data.scenes_per_device = 2 // n_dev  # the same global batch of 2 scenes
pipe = components.make_pipeline(config, "train", num_devices=n_dev)
spec = components.pose_spec(config)
model = components.make_model(config, components.num_train_scenes(pipe))
init_key, loop_key = jax.random.split(jax.random.key(config.seed))
state = step_lib.create_train_state(init_key, config, model, spec, pipe.batch(0))
pstate = train._replicate(state, n_dev)
keys = jax.vmap(jax.random.wrap_key_data)(train._replicate(jax.random.key_data(loop_key), n_dev))
p_step = step_lib.make_p_train_step(config, model, spec)
logged = {}
for step in range(steps):
  b = pipe.batch(step)
  pstate, m = p_step(pstate, {k: b[k] for k in ("image", "pose", "scene")}, keys)
  for k, v in train._to_host(m).items():
    logged[f"metric/{step}/{k}"] = np.asarray(v)
flat = jax.tree_util.tree_flatten_with_path(train._unreplicate(pstate.params))[0]
params = {"param/" + jax.tree_util.keystr(k): np.asarray(v) for k, v in flat}
np.savez(out, **params, **logged)

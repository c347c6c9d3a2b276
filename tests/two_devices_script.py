"""Helper for tests/test_train.py: train N steps on D forced host devices, save the parameters.

Usage (from the repository root): python -m tests.two_devices_script DEVICES STEPS OUT.npz
"""

import os
import sys

n_dev, steps, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
flags = os.environ.get("XLA_FLAGS", "")  # the suite's compile options, then the devices
os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={n_dev}".strip()

import jax  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_disable_most_optimizations", True)

from camrep.configs import gqn  # noqa: E402
from camrep.synthesis import components  # noqa: E402
from camrep.synthesis import step as step_lib  # noqa: E402

assert jax.local_device_count() == n_dev, jax.devices()
config = gqn.get_config("smoke")
config.data.scenes_per_device = 2 // n_dev  # the same global batch of 2 scenes
pipe = components.make_pipeline(config, "train", num_devices=n_dev)
model = components.make_model(components.resolve(config), components.num_train_scenes(pipe))
tx = step_lib.make_optimizers(config)
init_key, loop_key = step_lib.root_keys(config)
state = step_lib.create_train_state(init_key, model, tx, pipe.batch(0))
pstate = step_lib.replicate(state, n_dev)
p_step = step_lib.make_p_train_step(model, tx, pose_steps=config.optax.pose_steps)
logged = {}
for step in range(steps):
  b = pipe.batch(step)
  pstate, m = p_step(pstate, {k: b[k] for k in ("image", "pose", "scene")}, loop_key)
  for k, v in step_lib.to_host(m).items():
    logged[f"metric/{step}/{k}"] = np.asarray(v)
flat = jax.tree_util.tree_flatten_with_path(step_lib.unreplicate(pstate.params))[0]
params = {"param/" + jax.tree_util.keystr(k): np.asarray(v) for k, v in flat}
np.savez(out, **params, **logged)

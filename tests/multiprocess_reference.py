"""Helper for tests/test_multiprocess.py: what a 2-process run computes, in ONE process.

Two forced host devices; device p gets the batch that process p of a 2-process run reads (its
shard of the scenes), and the loop repeats `train_and_evaluate`'s keys and order.

Usage (from the repository root):
  python -m tests.multiprocess_reference STEPS OUT.npz [--config.key=value ...]
"""

import os
import sys

flags = os.environ.get("XLA_FLAGS", "")  # the suite's compile options, then the devices
os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count=2".strip()

import jax  # noqa: E402
import numpy as np  # noqa: E402

from camrep.configs import gqn  # noqa: E402
from camrep.synthesis import components  # noqa: E402
from camrep.synthesis import step as step_lib  # noqa: E402

steps, out = int(sys.argv[1]), sys.argv[2]
config = gqn.get_config("smoke")
for arg in sys.argv[3:]:
  key, value = arg.removeprefix("--config.").split("=")
  config[key] = type(config[key])(value)
assert jax.local_device_count() == 2, jax.devices()
pipes = [
  components.make_pipeline(config, "train", num_devices=1, process_index=p, process_count=2)
  for p in range(2)
]
model = components.make_model(components.resolve(config), components.num_train_scenes(pipes[0]))
tx = step_lib.make_optimizers(config)
state = step_lib.init_fn(config, model, tx)()
pstate = step_lib.replicate(state, 2)
loop_key = step_lib.root_keys(config)[1]
p_step = step_lib.make_p_train_step(model, tx, pose_steps=config.optax.pose_steps)
logged = {}
for step in range(1, steps + 1):
  parts = [p.batch(step - 1) for p in pipes]
  batch = {k: np.concatenate([b[k] for b in parts]) for k in ("image", "pose", "scene")}
  pstate, m = p_step(pstate, batch, loop_key)
  for k, v in step_lib.to_host(m).items():
    logged[f"metric/{step}/{k}"] = np.asarray(v)
flat = jax.tree_util.tree_flatten_with_path(step_lib.unreplicate(pstate.params))[0]
params = {"param/" + jax.tree_util.keystr(k): np.asarray(v) for k, v in flat}
np.savez(out, **params, **logged)

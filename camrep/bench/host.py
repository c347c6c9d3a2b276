"""The train loop as `camrep.synthesis.train` runs it, timed; and the host's share of it.

`train_loop` times the loop a user runs: batches from `components.device_batches` (the pipeline's
iterator, copied to the devices ahead of the step), one step dispatched per batch, the step's
metrics read on the host only at log steps (the non-finite check), the device waited for at
the end. Nothing is read per step, so the device runs ahead as it does in training.

`host_loop` is that loop with the step and the renderer replaced by near-free stubs: what is left
is the host's work per step (drawing scenes and poses, assembling the batch, copying it to the
device, dispatching). At the paper layout it must stay well under the step's time, or the loop
is host-bound. `python -m camrep.bench.pipeline --stubbed` and the GPU report's `host` phase both
call it.

  .venv/bin/python -m camrep.bench.pipeline --config=configs/gqn.py --stubbed --bench_steps 50
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from camrep.data.procedural import scene_table
from camrep.runtime import progress as progress_lib
from camrep.synthesis import components


def train_loop(
  p_step: Callable,
  pstate: Any,
  batches: Iterable[dict],
  key: jax.Array,
  *,
  steps: int,
  warmup: int = 2,
  log_every: int = 100,
) -> tuple[dict[str, float], Any]:
  """Runs `warmup` then `steps` steps of the training loop and times the latter.

  Args:
    p_step: the pmapped step, `p_step(pstate, batch, key) -> (pstate, metrics)`.
    pstate: its replicated state.
    batches: device batches (`components.device_batches`).
    key: the loop's key.
    steps: timed steps.
    warmup: steps before the clock starts (compiles, the prefetch queue filling).
    log_every: the metrics are read on the host every this many steps (and at the last).

  Returns:
    ({"steps_per_s", "wall_s_per_step", "cpu_s_per_step": this process's CPU seconds a step},
    the state after the loop).
  """
  it = iter(batches)
  metrics = None
  for _ in range(warmup):
    pstate, metrics = p_step(pstate, next(it), key)
  jax.block_until_ready((pstate, metrics))
  pending = []
  t0, c0 = time.perf_counter(), time.process_time()
  for k in range(1, steps + 1):
    pstate, metrics = p_step(pstate, next(it), key)
    pending.append(metrics)
    if progress_lib.itstime(k, log_every, steps):  # the host reads the metrics only here
      if not all(float(np.asarray(m["train/finite"])[0]) >= 1 for m in pending):
        raise FloatingPointError("non-finite training values in the timed loop")
      pending = []
  jax.block_until_ready((pstate, metrics))
  wall, cpu = time.perf_counter() - t0, time.process_time() - c0
  return {
    "steps_per_s": steps / wall,
    "wall_s_per_step": wall / steps,
    "cpu_s_per_step": cpu / steps,
  }, pstate


class _StubFamily:
  """A procedural family whose renderer returns blank images at once (the rest is the family's)."""

  def __init__(self, family: Any):
    self._family = family

  def __getattr__(self, name: str) -> Any:
    # Unpickling (a spawned table-building worker) looks attributes up before `_family` is set.
    if name == "_family" or name.startswith("__"):
      raise AttributeError(name)
    return getattr(self._family, name)

  def _blank(self, n: int, views: int) -> np.ndarray:
    s = int(self._family.image_size)
    return np.zeros((n, views, s, s, 3), np.uint8)

  def render_batch(self, scenes, poses, **kwargs) -> np.ndarray:
    return self._blank(len(scenes), np.shape(poses)[1])

  def render_views(self, scene, poses) -> np.ndarray:
    return self._blank(1, len(poses))[0]


def stub_renderer(pipe: Any) -> Any:
  """Replaces a rendering pipeline's renderer by `_StubFamily`'s (in place); returns the pipe.

  Raises:
    ValueError: the pipeline renders nothing (prepared or in-memory data).
  """
  if not hasattr(pipe, "family") or not hasattr(pipe.family, "render_batch"):
    raise ValueError(f"{type(pipe).__name__} renders no batches: nothing to stub")
  pipe.family = _StubFamily(pipe.family)
  return pipe


@contextlib.contextmanager
def blank_table_renders():
  """Within it, `SceneTable.render` (the pipelines' one-call renderer) returns blank images at
  once: one preallocated array per shape, left on the device when asked (as rendering on an
  accelerator leaves its images), so what remains of a batch is the host's work."""
  original = scene_table.SceneTable.render
  blanks: dict[tuple, Any] = {}

  def render(self, rows, T_world_cam, camera, *, shadows, max_images=None, on_device=False):
    del self, shadows, max_images
    rows = np.asarray(rows)
    shape = (*rows.shape, T_world_cam.shape[rows.ndim], camera.height, camera.width, 3)
    key = (shape, on_device)
    if key not in blanks:
      blank = np.zeros(shape, np.uint8)
      blanks[key] = jnp.asarray(blank) if on_device else blank
    return blanks[key]

  scene_table.SceneTable.render = render
  try:
    yield
  finally:
    scene_table.SceneTable.render = original


def stub_step(num_devices: int) -> tuple[Callable, Any]:
  """(a pmapped step that reads its batch and does next to nothing, its replicated state)."""

  def step(state, batch, key):
    del key
    touched = sum(jnp.sum(v.reshape(-1)[:1]).astype(jnp.float32) for v in batch.values())
    metrics = {"train/finite": jnp.ones(()), "train/loss": touched * 0.0}
    return state + 1, metrics

  p_step = jax.pmap(step, axis_name="batch", in_axes=(0, 0, None), donate_argnums=(0,))
  return p_step, jnp.zeros((num_devices,), jnp.int32)


def host_loop(config, *, steps: int, warmup: int = 3) -> dict[str, Any]:
  """The training loop of `config` (its data path and batch layout) with the step and the
  renderer stubbed: the host's time a step. Returns `train_loop`'s figures, plus the layout and
  "host_ms_per_step" (wall milliseconds a step)."""
  n_dev = jax.local_device_count()
  config.total_steps = max(int(config.total_steps), warmup + steps)  # batches enough for the loop
  pipe = stub_renderer(components.make_pipeline(config, "train", num_devices=n_dev))
  p_step, pstate = stub_step(n_dev)
  key = jax.random.key(0)
  with (
    blank_table_renders(),
    contextlib.closing(components.device_batches(config, pipe, 0)) as batches,
  ):
    rates, _ = train_loop(
      p_step,
      pstate,
      batches,
      key,
      steps=steps,
      warmup=warmup,
      log_every=int(config.log_every_steps),
    )
  d = config.data
  return {
    **rates,
    "host_ms_per_step": 1e3 * rates["wall_s_per_step"],
    "layout": f"{n_dev} x {d.scenes_per_device} scenes x {d.views_per_scene} views",
    "image_size": int(pipe.family.image_size),
    "steps": steps,
  }

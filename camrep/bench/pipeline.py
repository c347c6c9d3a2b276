"""Benchmark: time to prepare a tfds dataset, and pipeline batches/s and images/s.

Prepares a small GQN-rooms-like dataset (the procedural "rooms" family, rendered; or with
`--source stand_in` a built-in source of smooth 64 px images that needs no rendering) into a
temporary data_dir, then reads batches laid out like the GQN train step
(8 scenes x 9 views of 64 px by default) in several ways:

  memory      the same `BatchPipeline` over images already in RAM (batching code alone)
  tfds        `tfds_pipeline(...).batch(k)` in the caller's thread (PNG decoding included)
  grain       `tfds_pipeline(...).iterator()`, grain MapDataset + reader threads, no worker
              processes (`data.num_workers=0`)
  workers=N   the same iterator with N worker processes (`data.num_workers=N`, grain
              `mp_prefetch`; each with `--threads` reader threads), for each N of `--workers`
  +device     the last of those, followed by `pipeline.prefetch_to_device` (2 batches ahead, as
              the train loop does): batches arrive as device arrays
  dataloader  the same steps through `grain.DataLoader` (IndexSampler, worker_count=0)

Worker processes are started before the timing (the first, warm-up batch waits for them); the
line `workers: N (default for this machine's C usable cores: M)` gives the config's default.

Command (about 30 s on a 2-core CPU; no accelerator needed):

  .venv/bin/python -m camrep.bench.pipeline [--source rooms|stand_in] [--scenes 64]
      [--views 10] [--size 64] [--scenes_per_device 8] [--views_per_scene 9] [--steps 30]
      [--threads 2] [--workers 2]

On a 16-core GPU machine, the paper's batch layout (30 scenes x 9 views) against worker counts:

  python -m camrep.bench.pipeline --scenes 256 --scenes_per_device 30 --views_per_scene 9 \
      --steps 60 --workers 4,8,14

Is training input-bound? With `--config=FILE[:VARIANT]` the run instead
measures, for that config's GQN-style train step and batch layout:

  step alone      the pmapped train step on one batch reused (steps/s, images/s; the batch laid
                  out as the loop's, so the loops reuse its compiled program)
  render, per scene / one call
                  the procedural family rendered on demand (`RenderPipeline.batch(k)` in the
                  caller, each batch's images waited for where they were made): the old path
                  (one `render_views` call per scene) and the one-call path
                  (`family.render_batch`)
  memory          the config's in-memory pipeline, when it has one (`data.in_memory`)
  prepared        a prepared-on-disk copy of `--prepared_scenes` of the family's scenes
                  (`storage.prepare` + `tfds_pipeline`, `batch(k)` in the caller)
  end to end      for each data path of `--e2e`: the train loop as `camrep.synthesis.train`
                  runs it (`camrep.bench.host.train_loop`: `components.device_batches`, the
                  step, the metrics read only at log steps), steps/s and the ratio to the step
                  alone

With `--stubbed` (and `--config`) only the loop with the step and the renderer stubbed runs
(`camrep.bench.host.host_loop`): the host's time a step at the config's layout.

The step alone is timed again after the end-to-end loops, and the faster of its two runs is the
reference (the machine's load changes during a run; this gives the lower ratio). The last line
is `input_bound_ratio=<end-to-end steps/s / step-alone steps/s>
steps_per_s=<end-to-end steps/s>` for the first path of `--e2e` (default "render": procedural
batches rendered on demand in one call per batch; "config" is the config's own data path).

  .venv/bin/python -m camrep.bench.pipeline --config=configs/gqn.py:quick \
      --e2e render,config,prepared                                            # ~4 min
  .venv/bin/python -m camrep.bench.pipeline --config=configs/gqn.py:quick --width=paper \
      --bench_steps 3 --e2e render,config --prepared_scenes 0     # paper width, ~6 min
  python -m camrep.bench.pipeline --config=configs/gqn.py --width=paper --bench_steps 30 \
      --e2e render,prepared --prepared_scenes 256
      (on a GPU: the paper-size step, 30 scenes x 9 views; on the 2-core CPU its end-to-end loop
      needs more memory than the shared machine had)
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import os
import tempfile
import time
from collections.abc import Callable, Iterator

import cv2
import grain
import jax
import numpy as np

from camrep import configs
from camrep.bench import host as host_lib
from camrep.data import procedural, sources
from camrep.data.feed import pipeline, storage

WIDTHS = {"paper": 1.0, "quick": 0.125}


class StandInRooms:
  """A GQN-rooms-like stand-in: x, y in [-1, 1], yaw in [0, 2 pi); smooth 'wall' images."""

  name = "bench_rooms"
  pose_names = ("x", "y", "yaw")

  def __init__(self, num_scenes: int, views: int, size: int):
    self.image_size = size
    self._scenes = {"train": num_scenes}
    self._views = views

  def num_scenes(self, split: str) -> int:
    return self._scenes[split]

  def iter_views(self, split: str) -> Iterator[dict]:
    rng = np.random.default_rng(0)
    s = self.image_size
    u = np.linspace(0, 1, s, dtype=np.float32)
    for scene in range(self._scenes[split]):
      colours = rng.uniform(30, 230, size=(4, 3)).astype(np.float32)
      for view in range(self._views):
        x, y = rng.uniform(-1, 1, size=2)
        yaw = rng.uniform(0, 2 * np.pi)
        wall = int(yaw / (np.pi / 2)) % 4
        shade = 0.6 + 0.4 * np.cos(yaw + 6 * u)[None, :, None]
        image = np.empty((s, s, 3), np.float32)
        image[: s // 2] = colours[wall] * shade
        image[s // 2 :] = colours[(wall + 2) % 4] * (0.5 + 0.5 * u[s // 2 :, None, None])
        cv2.circle(
          image, (int(s * (0.5 + 0.3 * x)), int(s * (0.6 + 0.2 * y))), s // 8, (250, 80, 40), -1
        )
        yield {
          "image": np.clip(image, 0, 255).astype(np.uint8),
          "pose": np.array([x, y, yaw], np.float32),
          "scene": scene,
          "view": view,
        }


def make_source(
  kind: str, num_scenes: int, views: int, size: int
) -> tuple[storage.ViewSource, str]:
  """The procedural rooms family ("rooms") or the cheap stand-in ("stand_in")."""
  if kind == "stand_in":
    return StandInRooms(num_scenes, views, size), "stand-in rooms (no rendering)"
  family = procedural.make_family(
    "rooms",
    image_size=size,
    num_train_scenes=num_scenes,
    train_views=views,
    num_test_scenes=1,
    test_views=1,
  )
  return family, "procedural rooms (camrep.data.procedural)"


def time_batches(batches: Iterator[dict], steps: int) -> float:
  """Seconds to pull `steps` batches, after one warm-up batch."""
  next(batches)
  t0 = time.perf_counter()
  for _ in range(steps):
    next(batches)
  return time.perf_counter() - t0


class _Steps:
  """Random-access view of a pipeline's steps, for grain.DataLoader."""

  def __init__(self, pipe: pipeline.BatchPipeline, num_steps: int):
    self._pipe, self._n = pipe, num_steps

  def __len__(self) -> int:
    return self._n

  def __getitem__(self, step: int) -> dict:
    return self._pipe.batch(int(step))


def load_config(spec: str):
  """`configs/NAME.py[:arg]` or `NAME[:arg]`, NAME an installed config (`camrep.configs.NAMES`)
  -> its `get_config(arg)`, as `--config` gives it."""
  file, _, arg = spec.partition(":")
  name = os.path.splitext(os.path.basename(file))[0]
  if name not in configs.NAMES:
    raise ValueError(f"{spec}: name one of the installed configs {', '.join(configs.NAMES)}")
  return importlib.import_module(f"camrep.configs.{name}").get_config(arg or None)


def _rate(run: Callable[[int], object], steps: int) -> float:
  """Calls per second of `run(k)` for k = 1..steps, after run(0) (warm-up, compiles)."""
  run(0)
  t0 = time.perf_counter()
  for k in range(1, steps + 1):
    run(k)
  return steps / (time.perf_counter() - t0)


def input_bound(
  config,
  *,
  steps: int,
  e2e: tuple[str, ...] = ("render",),
  prepared_scenes: int = 64,
  pipeline_steps: int | None = None,
  per_scene: bool = True,
  stub: bool = False,
) -> dict[str, float]:
  """Step alone, input pipelines alone and the end-to-end loop for one config (see the module
  docstring). Prints one line per measurement; returns steps/s (or batches/s) by row name.
  `per_scene=False` leaves out the old per-scene renderer row (a compile and S calls a batch);
  `stub` times the data paths with a near-free step (`host.stub_step`) instead of the model's."""
  import jax
  import jax.numpy as jnp

  from camrep.synthesis import components
  from camrep.synthesis import step as step_lib

  n_dev = jax.local_device_count()
  pipeline_steps = pipeline_steps or steps
  d = config.data
  family = sources.family_of_config(config.data)
  own = components.make_pipeline(config, "train", num_devices=n_dev)
  pcfg = own.config
  images = pcfg.scenes_per_step * pcfg.views_per_scene
  print(
    f"JAX {jax.__version__} on {jax.devices()[0].platform} ({n_dev} device(s)), "
    f"{pipeline.usable_cores()} usable cores; family {family.name}, {d.preset} preset, "
    f"{family.image_size} px; layout {n_dev} x {pcfg.scenes_per_device} scenes x "
    f"{pcfg.views_per_scene} views ({images} images/step); width {config.model.width}; "
    f"config data path: {'memory' if d.in_memory else 'render'}",
    flush=True,
  )
  init_key, keys = step_lib.root_keys(config)
  # The step alone runs on a batch as the loop's batches come (device arrays laid out for the
  # pmapped step), so that the loops below reuse its compiled program.
  config.total_steps = max(int(config.total_steps), steps + 2)  # batches enough for the loops
  with contextlib.closing(components.device_batches(config, own, 0)) as first:
    batch = next(first)
  if stub:
    p_step, state = host_lib.stub_step(n_dev)
  else:
    model = components.make_model(components.resolve(config), components.num_train_scenes(own))
    tx = step_lib.make_optimizers(config)
    b0 = own.batch(0)
    init = {k: jnp.asarray(b0[k]) for k in ("image", "pose", "scene")}
    state = jax.jit(lambda k, b: step_lib.create_train_state(k, model, tx, b))(init_key, init)
    state = step_lib.replicate(state, n_dev)
    p_step = step_lib.make_p_train_step(model, tx, pose_steps=config.optax.pose_steps)
  out: dict[str, float] = {}

  def one_step(_):
    nonlocal state
    state, m = p_step(state, batch, keys)
    float(np.asarray(m["train/finite"])[0])

  t0 = time.perf_counter()
  one_step(0)
  print(f"step compile + first step: {time.perf_counter() - t0:.1f} s", flush=True)
  out["step"] = _rate(one_step, steps)
  print(f"{'step alone':>22}: {out['step']:7.3f} steps/s  {out['step'] * images:8.1f} images/s")

  def show(label: str, rate: float) -> None:
    out[label] = rate
    print(f"{label:>22}: {rate:7.3f} batches/s  {rate * images:8.1f} images/s", flush=True)

  def ready(pipe):  # a batch, waited for where it was made (the renderer may run on the device)
    return lambda k: jax.block_until_ready(pipe.batch(k)["image"])

  pipes = {}
  rows = (("render, per scene", False), ("render, one call", True))
  for label, one_call in rows if per_scene else rows[1:]:
    pipes[label] = pipeline.render_pipeline(family, "train", pcfg, one_call=one_call)
    show(label, _rate(ready(pipes[label]), pipeline_steps))
  pipes["render"] = pipes["render, one call"]
  if d.in_memory:
    pipes["memory"] = own
    show("memory", _rate(ready(own), pipeline_steps))
  pipes["config"] = own
  tmp = None
  if ("prepared" in e2e or prepared_scenes > 0) and hasattr(family.config, "num_train_scenes"):
    tmp = tempfile.TemporaryDirectory()
    n_scenes = max(prepared_scenes, pcfg.scenes_per_step)
    overrides = dict(d.family.to_dict()) if d.family else {}
    overrides.update(num_train_scenes=n_scenes, num_test_scenes=1, test_views=1)
    small = procedural.make_family(family.name, preset=d.preset, **overrides)
    t0 = time.perf_counter()
    storage.prepare(small, tmp.name, progress=False)
    print(f"prepare {n_scenes} scenes of the family: {time.perf_counter() - t0:.1f} s", flush=True)
    pipes["prepared"] = pipeline.tfds_pipeline(tmp.name, small.name, "train", pcfg)
    show("prepared", _rate(ready(pipes["prepared"]), pipeline_steps))

  def end_to_end(pipe) -> float:
    nonlocal state
    with contextlib.closing(components.device_batches(config, pipe, 0)) as batches:
      rates, state = host_lib.train_loop(
        p_step, state, batches, keys, steps=steps, log_every=int(config.log_every_steps)
      )
    return rates["steps_per_s"]

  for name in e2e:
    out[f"e2e {name}"] = end_to_end(pipes[name])
  # The step alone once more, after the loops: on a shared machine the load changes during the
  # run; the faster of the two is the reference (the conservative ratio).
  again = _rate(one_step, steps)
  print(f"{'step alone, again':>22}: {again:7.3f} steps/s  {again * images:8.1f} images/s")
  out["step"] = max(out["step"], again)
  for name in e2e:
    rate = out[f"e2e {name}"]
    print(
      f"{'end to end, ' + name:>22}: {rate:7.3f} steps/s  {rate * images:8.1f} images/s  "
      f"ratio to the faster step alone {rate / out['step']:.3f}",
      flush=True,
    )
  if tmp is not None:
    tmp.cleanup()
  first = out[f"e2e {e2e[0]}"]
  print(f"input_bound_ratio={first / out['step']:.4f} steps_per_s={first:.4f}", flush=True)
  return out


def host_paths(
  *,
  scenes: int = 2000,
  steps: int = 300,
  paths: tuple[str, ...] = ("per_batch", "table", "table_k", "prerendered"),
  k: int = 8,
  per_batch_steps: int = 20,
) -> dict[str, dict[str, float]]:
  """Host time per step of the paper-layout loop with the step and the renderer stubbed.

  The loop is `camrep.synthesis.train`'s: `pipe.iterator` with `configs/gqn.py`'s reader
  threads and prefetch, `prefetch_to_device`, the step; the batch layout is the paper's (one
  device, 30 scenes x 9 views of 64 px rooms, "random" views). The renderer returns
  preallocated images left on the device (as on a GPU, where rendering is device work) and the
  step is a jitted function of the batch's poses, so what is left is the host's work. The rooms
  split has `scenes` scenes (a batch's cost does not depend on their number once they are
  built; the paper's 200,000 cost more to build, printed). Paths:

    per_batch    scenes and poses built for each batch (`RenderPipeline(table=False)`)
    table        the split's scenes and poses built once into a `SceneTable`, batches
                 gathered by index (the default where the table fits in memory)
    table_k      the same, `k` steps per element (`iterator(steps_per_element=k)`, the batches
                 of a train loop that runs k steps per dispatch)
    prerendered  images of the whole split rendered ahead into host memory and served by index
                 (a `BatchPipeline` over random images: the serving cost alone)

  Returns {path: {"wall_ms": ..., "cpu_ms": ...}} per step; prints one line per path and
  `host_ms_per_step=<table wall ms>`.
  """
  import jax
  import jax.numpy as jnp

  from camrep.configs import gqn

  c = gqn.get_config()
  d = c.data
  family = procedural.make_family("rooms", num_train_scenes=scenes, num_test_scenes=1)
  pcfg = pipeline.PipelineConfig(
    scenes_per_device=d.scenes_per_device,
    views_per_scene=d.views_per_scene,
    mode=d.mode,
    num_threads=d.num_threads,
    prefetch=d.prefetch,
  )
  shape = (pcfg.views_per_scene, family.image_size, family.image_size, 3)

  @jax.jit
  def step(s, b):
    return s + 1, {"train/finite": jnp.isfinite(jnp.sum(b["pose"]))}

  def loop(pipe, n_steps: int, per: int = 1) -> dict[str, float]:
    warm = 3 * per
    host = pipe.iterator(start_step=0, num_steps=n_steps + warm, steps_per_element=per)
    it = pipeline.prefetch_to_device(host, int(d.device_prefetch), device_axis=1 if per > 1 else 0)
    s = jnp.zeros(())
    for i, b in enumerate(it):
      if i == 3:  # after warm-up (threads started, prefetch queue full, compiles done)
        t0, c0 = time.perf_counter(), time.process_time()
      s, m = step(s, b)
    jax.block_until_ready(s)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    host.close()
    return {"wall_ms": wall / n_steps * 1e3, "cpu_ms": cpu / n_steps * 1e3}

  out = {}
  print(
    f"host loop: paper layout {pcfg.scenes_per_step} scenes x {pcfg.views_per_scene} views of "
    f"{family.image_size} px rooms, {pcfg.num_threads} reader threads, prefetch {pcfg.prefetch},"
    f" device prefetch {d.device_prefetch}; step and renderer stubbed; split {scenes} scenes",
    flush=True,
  )
  with host_lib.blank_table_renders():
    for path in paths:
      if path == "per_batch":
        pipe = pipeline.render_pipeline(family, "train", pcfg, table=False, images_on_device=True)
        out[path] = loop(pipe, per_batch_steps)
      elif path in ("table", "table_k"):
        pipe = pipeline.render_pipeline(
          family, "train", pcfg, table=True, images_on_device=True, table_workers=0
        )
        t0 = time.perf_counter()
        table = pipe.table
        build = time.perf_counter() - t0
        print(
          f"  table of {scenes} scenes: built in {build:.1f} s ({build / scenes * 1e3:.2f} ms a "
          f"scene; the paper's 200,000: ~{build / scenes * 2e5 / 60:.0f} min on one core), "
          f"{table.nbytes / 2**20:.1f} MiB ({table.nbytes / scenes / 1024:.2f} KiB a scene)",
          flush=True,
        )
        per = k if path == "table_k" else 1
        out[path] = loop(pipe, steps - steps % per, per)
      elif path == "prerendered":
        n_views = family.num_views("train")
        n = scenes * n_views
        index = storage.ViewIndex(
          record=np.arange(n),
          index=np.arange(n),
          scene=np.repeat(np.arange(scenes), n_views),
          view=np.tile(np.arange(n_views), scenes),
          pose=np.random.default_rng(0).uniform(-1, 1, (n, 3)).astype(np.float32),
          pose_names=tuple(family.pose_names),
          image_shape=(family.image_size, family.image_size),
        )
        images = np.random.default_rng(1).integers(0, 255, (n, *shape[1:]), dtype=np.uint8)
        pipe = pipeline.BatchPipeline(index, images.__getitem__, pcfg)
        out[path] = loop(pipe, steps)
      r = out[path]
      label = f"{path} (k={k})" if path == "table_k" else path
      print(
        f"  {label:>18}: {r['wall_ms']:8.3f} ms/step wall, {r['cpu_ms']:8.3f} ms/step CPU "
        f"({1e3 / r['wall_ms']:.0f} steps/s)",
        flush=True,
      )
  if "table" in out:
    print(f"host_ms_per_step={out['table']['wall_ms']:.4f}", flush=True)
  return out


def stubbed(config, *, steps: int) -> dict:
  """The host's time a step: the config's loop with the step and renderer stubbed
  (`camrep.bench.host.host_loop`); prints one line."""
  r = host_lib.host_loop(config, steps=steps)
  print(
    f"loop with the step and renderer stubbed ({r['layout']} of {r['image_size']} px): "
    f"{r['steps_per_s']:.1f} steps/s, host {r['host_ms_per_step']:.2f} ms a step "
    f"(CPU {1e3 * r['cpu_s_per_step']:.2f} ms of this process)",
    flush=True,
  )
  return r


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--source", default="rooms", choices=("rooms", "stand_in"))
  parser.add_argument("--scenes", type=int, default=64)
  parser.add_argument("--views", type=int, default=10)
  parser.add_argument("--size", type=int, default=64)
  parser.add_argument("--scenes_per_device", type=int, default=8)
  parser.add_argument("--views_per_scene", type=int, default=9)
  parser.add_argument("--num_devices", type=int, default=1)
  parser.add_argument("--mode", default="random", choices=pipeline.MODES)
  parser.add_argument("--steps", type=int, default=30)
  parser.add_argument("--threads", type=int, default=2)
  parser.add_argument(
    "--workers", default="2", help="comma-separated worker-process counts to time (0: skip)"
  )
  parser.add_argument(
    "--config", default="", help="config file[:variant]: is its train step input-bound?"
  )
  parser.add_argument("--width", default="", help="--config: model width, paper | quick | number")
  parser.add_argument("--bench_steps", type=int, default=10, help="--config: timed steps")
  parser.add_argument(
    "--e2e", default="render", help="--config: end-to-end data paths (render, config, prepared)"
  )
  parser.add_argument("--prepared_scenes", type=int, default=64, help="--config: 0 to skip")
  parser.add_argument(
    "--host",
    action="store_true",
    help="host time per step, paper layout, step and renderer stubbed",
  )
  parser.add_argument("--host_scenes", type=int, default=2000, help="--host: scenes in the split")
  parser.add_argument("--host_steps", type=int, default=300, help="--host: timed steps")
  parser.add_argument(
    "--host_paths", default="per_batch,table,table_k,prerendered", help="--host: paths to time"
  )
  parser.add_argument("--host_k", type=int, default=8, help="--host: steps per element (table_k)")
  parser.add_argument(
    "--stubbed",
    action="store_true",
    help="--config: only the loop with the step and renderer stubbed (the host's time a step)",
  )
  args = parser.parse_args()
  if args.host:
    host_paths(
      scenes=args.host_scenes,
      steps=args.host_steps,
      paths=tuple(args.host_paths.split(",")),
      k=args.host_k,
    )
    return
  if args.config:
    config = load_config(args.config)
    if args.width:
      config.model.width = WIDTHS.get(args.width) or float(args.width)
    if args.stubbed:
      stubbed(config, steps=args.bench_steps)
      return
    input_bound(
      config,
      steps=args.bench_steps,
      e2e=tuple(args.e2e.split(",")),
      prepared_scenes=args.prepared_scenes,
    )
    return

  source, kind = make_source(args.source, args.scenes, args.views, args.size)
  cfg = pipeline.PipelineConfig(
    num_devices=args.num_devices,
    scenes_per_device=args.scenes_per_device,
    views_per_scene=args.views_per_scene,
    mode=args.mode,
    num_threads=args.threads,
  )
  images_per_batch = cfg.scenes_per_step * cfg.views_per_scene
  print(f"source: {kind}; {args.scenes} scenes x {args.views} views of {args.size} px")
  print(
    f"layout: {cfg.num_devices} x {cfg.scenes_per_device} scenes x {cfg.views_per_scene} "
    f"views ({images_per_batch} images/batch), mode {cfg.mode}"
  )

  with tempfile.TemporaryDirectory() as data_dir:
    t0 = time.perf_counter()
    path = storage.prepare(source, data_dir, progress=False)
    prep = time.perf_counter() - t0
    n = storage.load_metadata(path)["splits"]["train"]["num_views"]
    size_mb = sum(f.stat().st_size for f in path.iterdir()) / 2**20
    print(f"prepare: {prep:.2f} s for {n} views ({n / prep:.0f} views/s, {size_mb:.1f} MiB)")

    t0 = time.perf_counter()
    stored = pipeline.tfds_pipeline(data_dir, source.name, "train", cfg)
    print(f"open tfds pipeline: {time.perf_counter() - t0:.2f} s")
    # The in-memory variant over the same views, loaded from the store (not re-rendered).
    images = storage.load(data_dir, source.name, "train").read_images(np.arange(n))
    memory = pipeline.BatchPipeline(stored.index, lambda records: images[records], cfg)
    workers = [int(w) for w in args.workers.split(",") if int(w) > 0]
    cores = pipeline.usable_cores()
    print(
      f"workers: {workers} (default for this machine's {cores} usable cores: "
      f"{pipeline.default_num_workers(cores)})"
    )

    def with_workers(w: int):
      return pipeline.tfds_pipeline(
        data_dir, source.name, "train", dataclasses.replace(cfg, num_workers=w)
      ).iterator()

    # Each iterator is made just before it is timed and closed after, so no worker processes
    # run during another row's timing.
    runs = {
      "memory": lambda: (memory.batch(k) for k in range(10**9)),
      "tfds": lambda: (stored.batch(k) for k in range(10**9)),
      "grain": stored.iterator,
      **{f"workers={w}": (lambda w=w: with_workers(w)) for w in workers},
      "dataloader": lambda: iter(
        grain.DataLoader(
          data_source=_Steps(stored, args.steps + 1),
          sampler=grain.samplers.IndexSampler(args.steps + 1, shuffle=False, num_epochs=1),
          worker_count=0,
          read_options=grain.ReadOptions(num_threads=args.threads, prefetch_buffer_size=4),
        )
      ),
    }
    if workers:
      runs[f"workers={workers[-1]}+device"] = lambda: with_workers(workers[-1])
    for label, make_batches in runs.items():
      host = make_batches()
      batches = host
      if label.endswith("+device"):
        batches = (jax.block_until_ready(b) for b in pipeline.prefetch_to_device(host, 2))
      dt = time_batches(batches, args.steps)
      print(
        f"{label:>18}: {args.steps / dt:8.1f} batches/s  "
        f"{args.steps * images_per_batch / dt:9.0f} images/s",
        flush=True,
      )
      if hasattr(host, "close"):
        host.close()


if __name__ == "__main__":
  main()

"""Benchmark: the GQN-rooms train step (encoder + decoder + rotation losses), and how it scales.

Measures, in one run (these machines are noisy: compare the ratios printed by one run):

  step      the pmapped `camrep.synthesis.step` train step on the paper's batch layout (30 scenes
            x (6 context + 3 query) views of 64 px = 270 images, 4000 rotation pairs) at `--width`:
            seconds per step (median), images/s, compile time, FLOPs per step counted from
            the jaxpr (`camrep.runtime.flops`: the same on CPU and GPU, where XLA's cost
            analysis leaves cuDNN convolutions out; XLA's count printed beside it), achieved
            FLOP/s, and peak RSS;
  peak      the matmul peak of this machine in each `--dtype` (jnp 2048^3 matmuls), measured in
            the same run; MFU = achieved FLOP/s / the peak in the step's dtype;
  dtype     (`--dtype=float32,bfloat16`) the step at each compute dtype (`model.dtype`: bfloat16
            compute, float32 parameters and optimiser state), and the time ratio;
  grads     the same step with XLA's own conv weight gradients ("xla") against camrep's matmul
            weight gradients ("matmul", `camrep.models.fastconv`); with `--bf16`, one conv
            layer's forward and gradients in bfloat16 against float32;
  tables    (`--tables`) step time against batch size (GQN step), image size (the car model's
            step at 64 and 128 px) and forced host device count (subprocesses);
  decode    (`--tables`) pose decoding throughput, arg-min alone and with refinement;
  parts     (`--breakdown`) encoder, decoder and rotation losses timed alone (forward +
            backward), with their FLOPs: where the step's time goes;
  rewrites  (`--rewrites=off,on`) the step with the models' convs computed as written against
            their equivalent rewrites (`camrep.models.layers.rewrites`): FLOPs and time ratios.

The last line reads `mfu=<fraction> images_per_s=<number>` (the "step" figures at `--width`, the
first `--dtype` and the first `--grad_modes`). With `--end_to_end=CONFIG` (e.g.
`configs/gqn.py:quick`), the run goes on with `camrep.bench.pipeline --config=CONFIG` at `--width`:
the step alone, the input pipelines alone (procedural rendered on demand, per scene and in one
call; in memory; prepared on disk) and the end-to-end loop; the last line is
then `input_bound_ratio=<end-to-end / step alone> steps_per_s=<end-to-end>`.

Commands (2-core CPU):

  .venv/bin/python -m camrep.bench.train_step --width=quick            # ~2 min
  .venv/bin/python -m camrep.bench.train_step --width=quick --tables   # ~6 min
  .venv/bin/python -m camrep.bench.train_step --width=paper --steps=2  # ~8 min
  .venv/bin/python -m camrep.bench.train_step --width=quick --grad_modes=matmul \
    --dtype=float32,bfloat16                                                 # ~3 min
  .venv/bin/python -m camrep.bench.train_step --width=paper --scenes=4 --grad_modes=matmul \
    --rewrites=off,on --steps=2 --repeats=3   # the layers as written against their rewrites
  .venv/bin/python -m camrep.bench.train_step --width=quick --scenes=8 --grad_modes=xla \
    --end_to_end=configs/gqn.py:quick                                        # ~4 min
  .venv/bin/python -m camrep.bench.train_step --skip_synthesis --regression gqn,car \
    --regression_grad_modes matmul,by_channels --steps 5 --repeats 4         # ~3 min + data
  .venv/bin/python -m camrep.bench.train_step --skip_synthesis --regression car,gqn \
    --regression_strided s2d,xla --steps 5 --repeats 4  # strided convs' input gradients

On a GPU (mixed precision is meant for it; conv weight gradients from XLA / cuDNN):

  python -m camrep.bench.train_step --width=paper --grad_modes=xla --steps=30 \
    --dtype=float32,bfloat16
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import resource
import subprocess
import sys
import time

from camrep.runtime import flops as flops_lib
from camrep.synthesis import components
from camrep.synthesis import step as step_lib

WIDTHS = {"paper": 1.0, "quick": 0.125}


def _parse(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--width", default="quick", help="paper | quick | a number (width multiplier)")
  p.add_argument("--scenes", type=int, default=30, help="scenes per step (paper 30)")
  p.add_argument("--steps", type=int, default=3, help="timed steps per round (median)")
  p.add_argument(
    "--repeats", type=int, default=3, help="rounds of (matmul peak, each step) timed in turn"
  )
  p.add_argument("--grad_modes", default="matmul,xla", help="conv weight gradients to compare")
  p.add_argument(
    "--dtype", default="float32", help="compute dtypes (model.dtype) to time, e.g. float32,bfloat16"
  )
  p.add_argument("--bf16", action="store_true", help="also time a conv layer in bfloat16")
  p.add_argument(
    "--rewrites",
    default="on",
    help="the models' equivalent conv rewrites (camrep.models.layers.rewrites) to time: on, "
    "off, or off,on (both in one run, interleaved, and the ratio)",
  )
  p.add_argument(
    "--regression",
    default="",
    help="also time the pose-regression step of these settings (e.g. gqn,car), interleaved",
  )
  p.add_argument("--regression_variant", default="quick", help="configs/regression.py variant")
  p.add_argument("--regression_cache", default="/tmp/camrep_bench_regression_cache")
  p.add_argument(
    "--regression_grad_modes",
    default="",
    help="conv weight gradients of the regression steps to compare (e.g. matmul,by_channels; "
    "fastconv modes); empty: the regressor's own (learner.Regressor.weight_grad)",
  )
  p.add_argument(
    "--regression_strided",
    default="",
    help="strided convs' input gradients of the regression steps to compare (e.g. s2d,xla; "
    "fastconv.strided_input_grad modes); empty: the default",
  )
  p.add_argument(
    "--regression_width", type=float, default=None, help="model.width of the regression steps"
  )
  p.add_argument("--skip_synthesis", action="store_true", help="time only --regression steps")
  p.add_argument("--tables", action="store_true", help="batch / image size / device tables")
  p.add_argument("--breakdown", action="store_true", help="time encoder, decoder, rotation loss")
  p.add_argument("--devices", default="1,2", help="forced host device counts for the table")
  p.add_argument(
    "--end_to_end",
    default="",
    help="config[:variant]: then time its input pipelines and end-to-end loop (bench_pipeline)",
  )
  p.add_argument("--e2e_steps", type=int, default=10, help="--end_to_end: timed steps")
  p.add_argument("--child", default="", help=argparse.SUPPRESS)
  return p.parse_args(argv)


def _width(name: str) -> float:
  return WIDTHS[name] if name in WIDTHS else float(name)


def peak_rss_mb() -> float:
  """Peak resident set size of this process in MiB (Linux reports KiB)."""
  return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def matmul_peak(n: int = 2048, reps: int = 5, dtype: str = "float32", *, cpu: bool = False):
  """Best FLOP/s of an n x n x n jnp matmul (2 n^3 FLOPs), after one warm-up call; with `cpu`,
  (that, FLOPs per second of this process's CPU time over the `reps` calls)."""
  import jax
  import jax.numpy as jnp

  a = jax.random.normal(jax.random.key(0), (n, n), jnp.float32).astype(dtype)
  b = jax.random.normal(jax.random.key(1), (n, n), jnp.float32).astype(dtype)
  f = jax.jit(jnp.matmul)
  f(a, b).block_until_ready()
  best = float("inf")
  c0 = time.process_time()
  for _ in range(reps):
    t = time.perf_counter()
    f(a, b).block_until_ready()
    best = min(best, time.perf_counter() - t)
  per_cpu_s = 2 * n**3 * reps / max(time.process_time() - c0, 1e-9)
  return (2 * n**3 / best, per_cpu_s) if cpu else 2 * n**3 / best


def gqn_config(
  width: float, scenes: int, *, image_size: int = 64, setting: str = "gqn", devices: int = 1
):
  """The paper's config of `setting` ("gqn" or "car") at `width`, `scenes` per device, procedural
  data in memory."""
  from camrep.configs import gqn, shapenet_car

  # The config module, and whether its procedural family takes the image size (the car's objects
  # render at any size; GQN's rooms at their own).
  module, sized = {"gqn": (gqn, False), "car": (shapenet_car, True)}[setting]
  c = module.get_config()
  c.model.width = width
  c.model.image_size = image_size
  c.data.scenes_per_device = scenes
  c.data.in_memory = True
  c.data.preset = "small"
  c.data.num_threads = 0
  c.data.family.num_train_scenes = max(scenes * devices, 4)  # one batch's worth, rendered once
  c.data.family.num_test_scenes = 2
  if sized:
    c.data.family.image_size = image_size
  return c


class StepTimer:
  """The pmapped train step of `config`, built, compiled and warmed up once, timed on demand.

  Attributes:
    images: images per step; flops: FLOPs per step counted from the jaxpr (`camrep.runtime.flops`:
      the same on CPU and GPU, where XLA's cost analysis leaves cuDNN convolutions out);
    xla_flops: XLA's count; compile_s: seconds to compile; finite: the warm-up step's finite flag.
  """

  def __init__(self, config, *, num_devices: int = 1, context=contextlib.nullcontext):
    """`context()` is entered around building and every timing (e.g. a conv-gradient mode)."""
    self._context = context
    with context():
      self._build(config, num_devices)

  def _build(self, config, num_devices: int) -> None:
    import jax
    import jax.numpy as jnp
    import numpy as np

    pipe = components.make_pipeline(config, "train", num_devices=num_devices)
    model = components.make_model(components.resolve(config), components.num_train_scenes(pipe))
    tx = step_lib.make_optimizers(config)
    init_key, keys = jax.random.split(jax.random.key(0))
    b0 = pipe.batch(0)
    batch = {k: jnp.asarray(b0[k]) for k in ("image", "pose", "scene")}
    state = jax.jit(lambda k, b: step_lib.create_train_state(k, model, tx, b))(init_key, batch)
    pstate = step_lib.replicate(state, num_devices)
    p_step = step_lib.make_p_train_step(model, tx, pose_steps=config.optax.pose_steps)
    t = time.perf_counter()
    compiled = p_step.lower(pstate, batch, keys).compile()
    self.compile_s = time.perf_counter() - t
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, list | tuple) else cost
    # cost_analysis() and the jaxpr count of a pmapped step are one device's program.
    xla = float(cost.get("flops", float("nan"))) if cost else float("nan")
    self.xla_flops = xla * num_devices
    self.flops = flops_lib.count_flops(p_step, pstate, batch, keys) * num_devices
    self.images = int(np.prod(batch["image"].shape[:3]))
    self._step, self._batch, self._keys = p_step, batch, keys
    pstate, m = p_step(pstate, batch, keys)  # warm-up
    jax.block_until_ready(m)
    self._state = pstate
    self.finite = float(np.asarray(m["train/finite"])[0])

  def times(self, steps: int) -> list[float]:
    """Seconds of each of `steps` steps (state carried over, device synchronised each step)."""
    import jax

    out = []
    with self._context():
      for _ in range(steps):
        t = time.perf_counter()
        self._state, m = self._step(self._state, self._batch, self._keys)
        jax.block_until_ready((self._state, m))
        out.append(time.perf_counter() - t)
    return out

  def summary(self, times: list[float]) -> dict:
    """The figures of one timing: median seconds, images/s, FLOPs, FLOP/s, compile time."""
    import numpy as np

    sec = float(np.median(times))
    return {
      "sec": sec,
      "images": self.images,
      "images_per_s": self.images / sec,
      "flops": self.flops,
      "xla_flops": self.xla_flops,
      "flops_per_s": self.flops / sec,
      "compile_s": self.compile_s,
      "finite": self.finite,
    }


class RegressionTimer(StepTimer):
  """The pose-regression train step (`camrep.regression.learner.train_step`, jitted as the driver
  runs it) of `configs/regression.py:<variant>` for one setting and representation, on the
  setting's real training batch (rendered once, cached in `cache_dir`). `images` counts every
  image the step's network sees (GQN: the context and query views of each scene). `weight_grad`
  replaces the regressor's conv kernel gradients (`learner.Regressor.weight_grad`), `width` the
  config's model.width."""

  def __init__(self, setting: str, *, variant: str = "quick", representation: str = "quat",
               cache_dir: str = "", weight_grad: str = "", width: float | None = None,
               log=print):  # fmt: skip
    self._context = contextlib.nullcontext
    import jax
    import jax.numpy as jnp
    import numpy as np

    from camrep.configs import regression
    from camrep.regression import config_schema, driver, learner
    from camrep.regression import views as views_lib

    config = regression.get_config(f"{setting},{variant}")
    config.representation = representation
    config.data.cache_dir = cache_dir
    if width is not None:
      config.model.width = width
    setup = driver.prepare(config_schema.check(config), log=log)
    pipe = views_lib.train_pipeline(setup.batching, setup.data.train)
    b0 = views_lib.learner_batch(setup.batching, setup.data.train, pipe.batch(0))
    batch = {k: jnp.asarray(v) for k, v in b0.items()}
    reg = setup.reg
    if weight_grad:
      reg = dataclasses.replace(reg, weight_grad=weight_grad)
    self.weight_grad = reg.weight_grad
    state = learner.init(jax.random.key(0), reg, batch, rep_params=setup.rep_params)
    self.flops = flops_lib.count_flops(learner.train_step, state, batch)
    self.xla_flops = float("nan")
    step = jax.jit(learner.train_step, donate_argnums=0)
    t = time.perf_counter()
    compiled = step.lower(state, batch).compile()
    self.compile_s = time.perf_counter() - t
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, list | tuple) else cost
    self.xla_flops = float(cost.get("flops", float("nan"))) if cost else float("nan")
    self.images = sum(
      int(np.prod(v.shape[: v.ndim - 3])) for k, v in b0.items() if k.endswith("image")
    )
    self.config = config
    state, m = step(state, batch)
    jax.block_until_ready(m)
    self.finite = float(np.isfinite(float(m["loss"])))
    self._state, self._batch = state, batch
    self._regression_step = step

  def times(self, steps: int) -> list[float]:
    import jax

    out = []
    for _ in range(steps):
      t = time.perf_counter()
      self._state, m = self._regression_step(self._state, self._batch)
      jax.block_until_ready((self._state.params, m))
      out.append(time.perf_counter() - t)
    return out


def time_step(config, *, steps: int, num_devices: int = 1) -> dict:
  """Times the pmapped train step of `config`; returns seconds, FLOPs, compile time, images."""
  timer = StepTimer(config, num_devices=num_devices)
  return timer.summary(timer.times(steps))


def spread(values) -> dict:
  """{"median", "min", "max", "n"} of a list of numbers."""
  import numpy as np

  v = np.asarray(list(values), float)
  return {"median": float(np.median(v)), "min": float(v.min()), "max": float(v.max()), "n": len(v)}


def interleaved(
  timers: dict, *, rounds: int, steps: int, peak_n: int = 2048, peak_reps: int = 5
) -> dict:
  """MFU measured stably: the matmul peak and each step timed in turn, `rounds` times.

  Each round measures the matmul peak of every dtype the timers use (best of `peak_reps`
  n^3 matmuls), then each timer's step (median of `steps`), so a peak and the steps it divides
  were measured seconds apart under the same load. Per round, MFU = the step's FLOP/s / the
  same round's peak in the step's dtype. "cpu_mfu" is the same ratio with both rates per second
  of this process's CPU time (`time.process_time`, all its threads) instead of wall time: on a
  shared machine, time spent waiting for a core then counts for neither.

  Args:
    timers: name -> (StepTimer, compute dtype name).
    rounds: repeats of the whole cycle.
    steps: steps per timing.
    peak_n: matmul size of the peak (2048 on a CPU, 8192 on a GPU).

  Returns:
    {"peaks", "cpu_peaks": {dtype: spread of FLOP/s}, name: {"sec", "images_per_s",
    "flops_per_s", "mfu", "cpu_mfu": spread each, "flops", "images", "compile_s", "finite"}}.
  """
  import numpy as np

  dtypes = sorted({d for _, d in timers.values()})
  peaks = {d: [] for d in dtypes}
  cpu_peaks = {d: [] for d in dtypes}
  rows = {name: {"sec": [], "mfu": [], "cpu_mfu": []} for name in timers}
  for _ in range(rounds):
    for d in dtypes:
      wall, per_cpu = matmul_peak(n=peak_n, reps=peak_reps, dtype=d, cpu=True)
      peaks[d].append(wall)
      cpu_peaks[d].append(per_cpu)
    for name, (timer, d) in timers.items():
      c0 = time.process_time()
      sec = float(np.median(timer.times(steps)))
      cpu_per_step = (time.process_time() - c0) / steps
      rows[name]["sec"].append(sec)
      rows[name]["mfu"].append(timer.flops / sec / peaks[d][-1])
      rows[name]["cpu_mfu"].append(timer.flops / cpu_per_step / cpu_peaks[d][-1])
  out = {
    "peaks": {d: spread(v) for d, v in peaks.items()},
    "cpu_peaks": {d: spread(v) for d, v in cpu_peaks.items()},
    "rounds": rounds,
    "steps": steps,
  }
  for name, (timer, d) in timers.items():
    secs = rows[name]["sec"]
    out[name] = {
      "dtype": d,
      "sec": spread(secs),
      "images_per_s": spread(timer.images / s for s in secs),
      "flops_per_s": spread(timer.flops / s for s in secs),
      "mfu": spread(rows[name]["mfu"]),
      "cpu_mfu": spread(rows[name]["cpu_mfu"]),
      "flops": timer.flops,
      "xla_flops": timer.xla_flops,
      "images": timer.images,
      "compile_s": timer.compile_s,
      "finite": timer.finite,
    }
  return out


def format_spread(s: dict, fmt: str = ".3f", scale: float = 1.0) -> str:
  """ "median (min-max, n)" of a `spread` dict."""
  m, lo, hi = (s[k] * scale for k in ("median", "min", "max"))
  return f"{m:{fmt}} ({lo:{fmt}}-{hi:{fmt}}, n={s['n']})"


def decode_throughput(n: int = 4096) -> dict:
  """Poses/s of `camrep.pose.decode` on the paper's GQN pose system (arg-min, refined)."""
  import jax
  import numpy as np

  from camrep import pose as P

  config = gqn_config(1.0, 1)
  spec = components.pose_spec(config)
  params = P.init(jax.random.key(0), spec)
  rng = np.random.default_rng(0)
  poses = np.stack(
    [rng.uniform(-0.8, 0.8, n), rng.uniform(-0.8, 0.8, n), rng.uniform(0, 2 * np.pi, n)], -1
  ).astype(np.float32)
  vecs = P.embed(params, spec, poses, mode="nearest")
  out = {}
  for name, refine in (("argmin", 0), ("refined", 4)):
    f = jax.jit(lambda v, r=refine: P.decode(params, spec, v, refine_steps=r))
    jax.block_until_ready(f(vecs))
    best = float("inf")
    for _ in range(3):
      t = time.perf_counter()
      jax.block_until_ready(f(vecs))
      best = min(best, time.perf_counter() - t)
    out[name] = n / best
  return out


def conv_dtypes(width: float, scenes: int) -> dict:
  """Seconds of one 3x3 conv layer's forward + input and kernel gradients, fp32 vs bf16.

  The layer is the encoder's block at 16 x 16 (180 context images, 256 -> 128 channels at width
  1); this stands in for a bfloat16 step, which XLA:CPU would compute in the same emitters.
  """
  import jax
  import jax.numpy as jnp

  from camrep.models import fastconv

  cin, cout = max(1, round(256 * width)), max(1, round(128 * width))
  out = {}
  for dtype in (jnp.float32, jnp.bfloat16):
    x = jax.random.normal(jax.random.key(0), (scenes * 6, 16, 16, cin)).astype(dtype)
    w = (0.01 * jax.random.normal(jax.random.key(1), (3, 3, cin, cout))).astype(dtype)

    def loss(x, w):
      y = fastconv.conv_general_dilated(
        x, w, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
      )
      return jnp.sum(y.astype(jnp.float32) ** 2)

    f = jax.jit(jax.grad(loss, argnums=(0, 1)))
    jax.block_until_ready(f(x, w))
    best = float("inf")
    for _ in range(3):
      t = time.perf_counter()
      jax.block_until_ready(f(x, w))
      best = min(best, time.perf_counter() - t)
    out[jnp.dtype(dtype).name] = best
  return out


def _timed(f, *args, reps: int) -> tuple[float, float]:
  """(median seconds, XLA cost-analysis FLOPs) of jitted f(*args), after compile + warm-up."""
  import jax
  import numpy as np

  compiled = jax.jit(f).lower(*args).compile()
  cost = compiled.cost_analysis()
  cost = cost[0] if isinstance(cost, list | tuple) else cost
  jax.block_until_ready(compiled(*args))
  times = []
  for _ in range(reps):
    t = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    times.append(time.perf_counter() - t)
  return float(np.median(times)), float(cost.get("flops", float("nan")))


def breakdown(width: float, scenes: int, reps: int) -> dict[str, tuple[float, float]]:
  """Forward + backward of each part of the GQN step on its own: (seconds, FLOPs) each.

  Parts: the encoder on the context views, the decoder on the queries (given a scene code), and
  the rotation + direction losses (4000 pairs per DOF).
  """
  import jax
  import jax.numpy as jnp

  from camrep import pose as P
  from camrep.models.decoder import ResAdaINDecoder
  from camrep.models.encoder import SceneEncoder

  config = gqn_config(width, scenes)
  spec = components.pose_spec(config)
  rep = P.init(jax.random.key(0), spec)
  k = jax.random.split(jax.random.key(1), 4)
  ctx = jax.random.uniform(k[0], (scenes, 6, 64, 64, 3), minval=-1, maxval=1)
  ctx_vec = jax.random.normal(k[1], (scenes, 6, spec.dim * len(spec.dofs)))
  q_vec = jax.random.normal(k[2], (scenes, 3, spec.dim * len(spec.dofs)))
  enc, dec = SceneEncoder(width=width), ResAdaINDecoder(width=width)
  pe = jax.jit(enc.init)(k[3], ctx, ctx_vec)
  scene, _ = jax.jit(enc.apply)(pe, ctx, ctx_vec)
  pd = jax.jit(dec.init)(k[3], scene, q_vec)

  def enc_loss(p):
    out, _ = enc.apply(p, ctx, ctx_vec)
    return sum(jnp.sum(v**2) for v in out.values())

  def dec_loss(p):
    img, _ = dec.apply(p, scene, q_vec)
    return jnp.sum(img**2)

  synth = components.make_model(components.resolve(config), 1)

  def rot_loss(r):
    return synth.pose_loss(r, {}, jax.random.key(2))[0]

  return {
    "encoder (6 context views)": _timed(jax.grad(enc_loss), pe, reps=reps),
    "decoder (3 queries)": _timed(jax.grad(dec_loss), pd, reps=reps),
    "rotation + direction losses": _timed(jax.grad(rot_loss), rep, reps=reps),
  }


def _child(args) -> None:
  """Runs one measurement in this (fresh) process and prints it as JSON."""
  spec = json.loads(args.child)
  config = gqn_config(spec["width"], spec["scenes"], devices=spec["devices"])
  r = time_step(config, steps=spec["steps"], num_devices=spec["devices"])
  r["rss_mb"] = peak_rss_mb()
  print("RESULT " + json.dumps(r), flush=True)


def _in_subprocess(spec: dict, devices: int) -> dict:
  env = dict(os.environ)
  env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
  out = subprocess.run(
    [
      sys.executable,
      "-m",
      "camrep.bench.train_step",
      "--child",
      json.dumps({**spec, "devices": devices}),
    ],
    env=env,
    capture_output=True,
    text=True,
    check=True,
  ).stdout
  return json.loads(next(x for x in out.splitlines() if x.startswith("RESULT "))[7:])


def _rewrites_label(on: str, rewrites: list[str]) -> str:
  """Timer-name suffix of a rewrites setting (none when only one is timed)."""
  return f" rewrites {on}" if len(rewrites) > 1 else ""


def main(argv=None) -> None:
  args = _parse(argv)
  if args.child:
    return _child(args)
  import jax

  from camrep.models import fastconv, layers

  width = _width(args.width)
  print(
    f"JAX {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPU cores; GQN-rooms "
    f"step, width {width}, {args.scenes} scenes x 9 views, 64 px",
    flush=True,
  )
  dtypes = args.dtype.split(",")
  modes = args.grad_modes.split(",")
  rewrites = args.rewrites.split(",")
  timers = {}

  def context(mode: str, on: str):
    stack = contextlib.ExitStack()
    stack.enter_context(fastconv.weight_grad(mode))
    stack.enter_context(layers.rewrites(on == "on"))
    return stack

  for dtype in dtypes if not args.skip_synthesis else []:
    config = gqn_config(width, args.scenes)
    config.model.dtype = dtype
    for mode in modes:
      for on in rewrites:
        timer = StepTimer(config, context=lambda m=mode, o=on: context(m, o))
        timers[f"{dtype} weight grad {mode}" + _rewrites_label(on, rewrites)] = (timer, dtype)
  settings = [x for x in args.regression.split(",") if x]
  reg_modes = [x for x in args.regression_grad_modes.split(",") if x] or [""]
  strided = [x for x in args.regression_strided.split(",") if x] or [""]
  regression_rows = []
  for setting in settings:
    for mode in reg_modes:
      for how in strided:
        # The step is traced (and compiled) when the timer is built: the mode holds then.
        with fastconv.strided_input_grad(how) if how else contextlib.nullcontext():
          timer = RegressionTimer(
            setting,
            variant=args.regression_variant,
            cache_dir=args.regression_cache,
            weight_grad=mode,
            width=args.regression_width,
          )
        name = f"regression {setting}" + (f" weight grad {mode}" if mode else "")
        name += f" strided input grad {how}" if how else ""
        timers[name] = (timer, "float32")
        label = timer.weight_grad + (f", strided input grad {how}" if how else "")
        regression_rows.append((setting, name, label))
  # Peaks and steps timed in turn, --repeats rounds: MFU per round against that round's peak.
  inter = interleaved(timers, rounds=args.repeats, steps=args.steps)
  for dtype in dtypes:
    p = inter["peaks"][dtype]
    c = inter["cpu_peaks"][dtype]
    print(
      f"{dtype} matmul peak (2048^3), GFLOP/s: {format_spread(p, '.1f', 1e-9)}; per CPU second "
      f"{format_spread(c, '.1f', 1e-9)}",
      flush=True,
    )
  peaks = {d: inter["peaks"][d]["median"] for d in dtypes}
  peak = peaks[dtypes[0]]
  results = {}
  print(
    f"step figures: median (min-max, n) over {args.repeats} rounds of {args.steps} steps, each "
    "round's MFU against the same round's peak",
    flush=True,
  )
  for setting, name, mode in regression_rows:
    r = inter[name]
    print(
      f"  regression step, {setting} ({args.regression_variant}, quat, {r['images']} images/step, "
      f"weight grad {mode}):"
      f" s/step {format_spread(r['sec'])}  images/s {format_spread(r['images_per_s'], '.1f')}  "
      f"{r['flops'] / 1e9:.2f} GFLOP/step (XLA's count {r['xla_flops'] / 1e9:.2f})  GFLOP/s "
      f"{format_spread(r['flops_per_s'], '.1f', 1e-9)}  MFU {format_spread(r['mfu'])} (per CPU "
      f"second {format_spread(r['cpu_mfu'])})  compile "
      f"{r['compile_s']:.1f} s",
      flush=True,
    )
  if args.skip_synthesis:
    return
  if len(rewrites) > 1:
    for dtype in dtypes:
      for mode in modes:
        rows = [
          inter[f"{dtype} weight grad {mode}" + _rewrites_label(o, rewrites)] for o in rewrites
        ]
        print(
          f"  {dtype} weight grad {mode}, rewrites {rewrites[1]} / {rewrites[0]}: GFLOP/step "
          f"{rows[1]['flops'] / 1e9:.1f} / {rows[0]['flops'] / 1e9:.1f} = "
          f"{rows[1]['flops'] / rows[0]['flops']:.3f}x, s/step {rows[1]['sec']['median']:.3f} / "
          f"{rows[0]['sec']['median']:.3f} = {rows[1]['sec']['median'] / rows[0]['sec']['median']:.3f}x"
          f" (s/step {format_spread(rows[1]['sec'])} against {format_spread(rows[0]['sec'])})",
          flush=True,
        )
  for on in rewrites[1:]:
    for dtype in dtypes:
      for mode in modes:
        r = inter[f"{dtype} weight grad {mode}" + _rewrites_label(on, rewrites)]
        print(
          f"  {dtype} weight grad {mode:6s} rewrites {on}: s/step {format_spread(r['sec'])}  "
          f"{r['flops'] / 1e9:.1f} GFLOP/step  MFU {format_spread(r['mfu'])}",
          flush=True,
        )
  for dtype in dtypes:
    for mode in modes:
      r = inter[f"{dtype} weight grad {mode}" + _rewrites_label(rewrites[0], rewrites)]
      results[dtype, mode] = {
        "sec": r["sec"]["median"],
        "images_per_s": r["images_per_s"]["median"],
        "flops_per_s": r["flops_per_s"]["median"],
        "mfu": r["mfu"]["median"],
      }
      print(
        f"  {dtype} weight grad {mode:6s}: s/step {format_spread(r['sec'])}  images/s "
        f"{format_spread(r['images_per_s'], '.1f')}  {r['flops'] / 1e9:.1f} GFLOP/step (XLA's "
        f"count {r['xla_flops'] / 1e9:.1f})  GFLOP/s {format_spread(r['flops_per_s'], '.1f', 1e-9)}"
        f"  MFU {format_spread(r['mfu'])} (of the {dtype} peak; per CPU second "
        f"{format_spread(r['cpu_mfu'])})  compile {r['compile_s']:.1f} s"
        f"  finite {r['finite']:.0f}",
        flush=True,
      )
  if len(modes) == 2:
    a, b = (results[dtypes[0], m] for m in modes)
    print(f"  ratio {modes[1]}/{modes[0]} step time: {b['sec'] / a['sec']:.2f}x", flush=True)
  for dtype in dtypes[1:]:
    a, b = results[dtypes[0], modes[0]], results[dtype, modes[0]]
    print(
      f"  ratio {dtype}/{dtypes[0]} step time ({modes[0]}): {b['sec'] / a['sec']:.2f}x",
      flush=True,
    )
  if args.bf16:
    r = conv_dtypes(width, args.scenes)
    print(
      f"  one encoder-sized conv layer (3x3, fwd + both grads): fp32 {r['float32']:.3f} s, "
      f"bf16 {r['bfloat16']:.3f} s ({r['float32'] / r['bfloat16']:.2f}x); bf16 matmul peak "
      f"{matmul_peak(dtype='bfloat16') / 1e9:.1f} GFLOP/s",
      flush=True,
    )
  if args.breakdown:
    print("\nparts of the step, forward + backward each, weight grad auto:", flush=True)
    print("| part | s | GFLOP | GFLOP/s | of matmul peak |\n|---|---|---|---|---|")
    for name, (sec, fl) in breakdown(width, args.scenes, args.steps).items():
      print(
        f"| {name} | {sec:.3f} | {fl / 1e9:.1f} | {fl / sec / 1e9:.1f} | {fl / sec / peak:.2f} |",
        flush=True,
      )
  if args.tables:
    print("\nstep time against batch size (scenes x 9 views, weight grad auto):", flush=True)
    print("| scenes | images | s/step | images/s | GFLOP/s | MFU |\n|---|---|---|---|---|---|")
    for s in sorted({max(1, args.scenes // 4), max(1, args.scenes // 2), args.scenes}):
      r = time_step(gqn_config(width, s), steps=args.steps)
      print(
        f"| {s} | {r['images']} | {r['sec']:.3f} | {r['images_per_s']:.1f} | "
        f"{r['flops_per_s'] / 1e9:.1f} | {r['flops_per_s'] / peak:.3f} |",
        flush=True,
      )
    print("\nstep time against image size (car model, 8 scenes x 10 views):", flush=True)
    print("| image | s/step | images/s | GFLOP/step |\n|---|---|---|---|")
    for size in (64, 128):
      cfg = gqn_config(width, 8, image_size=size, setting="car")
      r = time_step(cfg, steps=args.steps)
      print(
        f"| {size} px | {r['sec']:.3f} | {r['images_per_s']:.1f} | {r['flops'] / 1e9:.1f} |",
        flush=True,
      )
    print("\nstep time against forced host devices (same global batch, subprocesses):")
    print("| devices | s/step | images/s | peak RSS MiB |\n|---|---|---|---|")
    for n in (int(x) for x in args.devices.split(",")):
      spec = {"width": width, "scenes": args.scenes // n, "steps": args.steps}
      r = _in_subprocess(spec, n)
      print(
        f"| {n} | {r['sec']:.3f} | {r['images_per_s']:.1f} | {r['rss_mb']:.0f} |",
        flush=True,
      )
    d = decode_throughput()
    print(
      f"\npose decoding (GQN system, 441 + 36 grid, 4096 poses): arg-min {d['argmin']:.0f} "
      f"poses/s, refined (4 Gauss-Newton steps) {d['refined']:.0f} poses/s",
      flush=True,
    )
  main_r = results[dtypes[0], modes[0]]
  print(f"peak RSS {peak_rss_mb():.0f} MiB", flush=True)
  first = f"{dtypes[0]} weight grad {modes[0]}" + _rewrites_label(rewrites[0], rewrites)
  mfu = inter[first]["mfu"]
  print(
    f"mfu={main_r['mfu']:.4f} images_per_s={main_r['images_per_s']:.2f} "
    f"mfu_min={mfu['min']:.4f} mfu_max={mfu['max']:.4f} "
    f"cpu_mfu={inter[first]['cpu_mfu']['median']:.4f}"
  )
  if args.end_to_end:
    from camrep.bench import pipeline as bench_pipeline

    print(f"\ninput pipelines and end-to-end loop of {args.end_to_end} at width {width}:")
    config = bench_pipeline.load_config(args.end_to_end)
    config.model.width = width
    bench_pipeline.input_bound(config, steps=args.e2e_steps, e2e=("render",))


if __name__ == "__main__":
  with contextlib.suppress(KeyboardInterrupt):
    main()

"""One report of camrep on a GPU: the step alone, end to end, paper configs, :medium runs.

A GPU machine is at hand now and then, for well under an hour, in commands of at most 10
minutes that cannot reach a package registry. This script measures everything in a few such
commands ("calls"), each a group of phases run as subprocesses under one time budget (default
470 s), and writes one Markdown + JSON report:

  env           device, driver, Python, JAX / jaxlib / Flax / Optax / Orbax versions, commit
  step          the paper-size GQN step alone (30 scenes x 9 views of 64 px, width 1) in float32
                and bfloat16 (`model.dtype`): s/step, images/s, analytic FLOPs (jaxpr count,
                `camrep.runtime.flops`), fraction of the same dtype's matmul peak measured in the
                same run (peaks and steps timed in turn, `bench_train_step.interleaved`), peak
                device memory; goals: float32 <= 10.5 ms, bfloat16 <= 7 ms
  profile       a jax.profiler trace of 10 float32 paper-size steps, summarised: the ops (device
                kernels on a GPU, XLA thunks on a CPU) that take the step's time, per step
  host          the paper GQN config's train loop with the step and the renderer stubbed
                (`camrep.bench.host.host_loop`), on the machine's CPU: the host's time a step
                (drawing scenes and poses, assembling and copying the batch, dispatching)
  e2e           the paper GQN config end to end (`camrep.bench.pipeline.input_bound`): the step
                alone, batches rendered on demand (one renderer call a batch, waited for on the
                device), a prepared dataset of 256 rooms, and the train loop fed by each as
                `camrep.synthesis.train` runs it (`camrep.bench.host.train_loop`: metrics read
                only at log steps): steps/s, ratio to the step alone (goal >= 0.9), ETA of the
                config's 1M steps
  car, gibson, seven_scenes
                the same for configs/shapenet_car.py, gibson.py, seven_scenes.py at paper size
                (prepared data only for families with a scene count: car; at --variant smoke
                with a stubbed step: the GQN phase compiles a real one)
  medium        the `:medium` comparison (`python -m camrep.comparison --size medium`) measured
                against its plan (camrep/comparison/plans.toml): a shortened GQN view-synthesis
                run extrapolated to 20,000 steps, `camrep.synthesis.evaluate` on it, and two
                whole regression runs (the first renders and caches the data)

Each phase writes DIR/gpu_report_<phase>.json; every call rewrites DIR/gpu_report.md and .json
from the phase files present (and those of --merge folders), so the last merge is the report.
The exit status is 1 when a phase of the call failed (its error is in its file and the report).
`--dry_run` prints the plan and the commands, imports nothing heavy and runs on any machine.
`--variant smoke` runs every phase at the :smoke sizes in one child process (a check of the code:
113 s on a 2-core CPU at load ~1.2 with a cold compilation cache, figures meaningless; the tests
run it).

  python -m camrep.bench.gpu_report --dry_run                       # the plan and the commands
  python -m camrep.bench.gpu_report --phases env,step --out $OUT    # on the GPU machine
  python -m camrep.bench.gpu_report --merge DIR1 DIR2 ... --out results/gpu   # on the CPU
  python -m camrep.bench.gpu_report --phases all --variant smoke --out /tmp/r  # CPU check
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SMOKE = "smoke"


PHASES = ("env", "step", "profile", "host", "e2e", "car", "gibson", "seven_scenes", "medium")
# Config of each end-to-end phase.
E2E_CONFIGS = {
  "e2e": "configs/gqn.py",
  "car": "configs/shapenet_car.py",
  "gibson": "configs/gibson.py",
  "seven_scenes": "configs/seven_scenes.py",
}
# The calls a GPU machine runs, each inside the device tool's 10 minutes, with its minutes on one
# H200: measured for e2e (144 s), medium (~7.5 min: its 318 s phase ended three of its four runs,
# the fourth took 104 s alone), profile (61 s) and host; the step phase's and the other configs' are guesses
# (compiles dominate: ~0.5-1 min per paper-size step and renderer).
CALLS = (
  ("env,step,profile,host", 5),
  ("e2e", 3),
  ("car,gibson,seven_scenes", 7),
  ("medium", 8),
)
WHEELHOUSE = ".whl"
GOALS = {"float32": 10.5e-3, "bfloat16": 7e-3}
HOST_GOAL_MS = 1.0


def wheelhouse_command() -> str:
  return ".venv/bin/python tools/build_wheelhouse.py"


def install_command(wheelhouse: str = WHEELHOUSE) -> str:
  """The GPU machine's command that installs the carried wheels (prefix of every report call);
  the working tree's camrep is then imported from $PWD."""
  return (
    "python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade "
    f"--target /tmp/site {wheelhouse}/*.whl && export PYTHONPATH=/tmp/site:$PWD"
  )


def gpu_command(phases: str) -> str:
  """The device tool's `run` command of one call (run with carry=[".whl"])."""
  return (
    f"{install_command(WHEELHOUSE)} && "
    f"PYTHONUNBUFFERED=1 python3 -m camrep.bench.gpu_report --phases {phases} --out $OUT"
  )


def how_to_run() -> list[str]:
  """The report's first section: the two commands, the calls, the merge."""
  lines = [
    "## How to run it",
    "",
    "1. On the CPU machine, in the repository root (a fresh clone works; ~1 min, ~10 MiB of "
    f"wheels into `{WHEELHOUSE}/`, which git ignores):",
    "",
    f"       {wheelhouse_command()}",
    "",
    '2. On the GPU machine, through the device tool\'s `run` with `carry=[".whl"]` and '
    "`timeout_s=600`, once per call below (PHASES as listed):",
    "",
    f"       {gpu_command('PHASES')}",
    "",
    "| call | PHASES | minutes on one H200 |",
    "|---|---|---|",
  ]
  lines += [f"| {i} | `{p}` | ~{m} |" for i, (p, m) in enumerate(CALLS, 1)]
  lines += [
    "",
    "The calls are in order of priority (calls 1 and 2 answer the step and end-to-end goals). "
    "Device time is short and a machine goes back soon after it is idle: issue the next call as "
    "soon as one returns, and stop when less than ~8 minutes of device time are left. Give "
    "`medium` `--budget_s 520` (its four runs need ~7.5 min; the default 470 s cuts the last).",
    "",
    "Each call brings back DIR/gpu_report_<phase>.json, gpu_report.md and gpu_report.json "
    "under the tool's files_at. Then, on the CPU machine, merge them into one report:",
    "",
    "       .venv/bin/python -m camrep.bench.gpu_report --merge FILES_AT_1 FILES_AT_2 ... "
    "--out results/gpu",
    "",
  ]
  return lines


def plan_lines(variant: str) -> list[str]:
  """The measurement plan, as --dry_run prints it."""
  doc = __doc__.split("\n\n")[1:3]
  size = "paper size" if not variant else f":{variant} variants (a check of the code, no figure)"
  return [
    f"# camrep GPU report: plan ({size})",
    "",
    *"\n\n".join(doc).splitlines(),
    "",
    *how_to_run(),
  ]


# ---------------------------------------------------------------------------------------------
# Phases (a child process runs them: `--child PHASE[,PHASE...]`).

# The float32 step's timer of this process, shared by `step` and `profile` when one child runs
# both (the smoke check): it is traced and compiled once.
_STEP_TIMERS: dict[tuple[bool, str], object] = {}


def _step_timer(smoke: bool, dtype: str):
  """The `train_step.StepTimer` of `_step_config(smoke)` in `dtype`, built once a process."""
  from camrep.bench import train_step as bts

  if (smoke, dtype) not in _STEP_TIMERS:
    config = _step_config(smoke)
    config.model.dtype = dtype
    _STEP_TIMERS[smoke, dtype] = bts.StepTimer(config)
  return _STEP_TIMERS[smoke, dtype]


def _device_memory() -> dict:
  """Peak device memory of this process (GPU allocator stats; RSS on the CPU), MiB."""
  import jax

  from camrep.bench.train_step import peak_rss_mb

  stats = jax.local_devices()[0].memory_stats() or {}
  out = {"host_peak_rss_mib": peak_rss_mb()}
  if "peak_bytes_in_use" in stats:
    out["device_peak_mib"] = stats["peak_bytes_in_use"] / 2**20
    out["device_limit_mib"] = stats.get("bytes_limit", 0) / 2**20
  return out


def phase_env(args) -> dict:
  import jax

  versions = {"python": platform.python_version()}
  for mod in ("jax", "jaxlib", "flax", "optax", "orbax.checkpoint", "numpy", "grain"):
    try:
      m = __import__(mod, fromlist=["_"])
      versions[mod] = getattr(m, "__version__", "?")
    except ImportError as e:
      versions[mod] = f"missing ({e})"
  dev = jax.devices()[0]
  out = {
    "versions": versions,
    "platform": dev.platform,
    "device_kind": dev.device_kind,
    "devices": len(jax.devices()),
    "cpu_cores": os.cpu_count(),
    "hostname": platform.node(),
  }
  with contextlib.suppress(OSError, subprocess.SubprocessError):
    out["nvidia_smi"] = subprocess.run(
      ["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
      capture_output=True,
      text=True,
      timeout=30,
    ).stdout.strip()
  out["commit"] = _commit()
  return out


def _commit() -> str:
  """The working tree's commit (short hash, "-dirty" with uncommitted changes), or '' outside git."""
  with contextlib.suppress(OSError, subprocess.SubprocessError):
    return subprocess.run(
      ["git", "-C", ROOT, "describe", "--always", "--dirty", "--abbrev=7", "--exclude=*"],
      capture_output=True,
      text=True,
    ).stdout.strip()
  return ""


def phase_step(args) -> dict:
  """The paper GQN step alone, float32 and bfloat16, MFU against the same dtype's peak."""
  import jax

  from camrep.bench import train_step as bts

  smoke = args.variant == SMOKE
  on_gpu = jax.devices()[0].platform == "gpu"
  timers = {}
  # At smoke one dtype: each is its own program, and compiling is most of a check's time.
  for dtype in ("float32",) if smoke else ("float32", "bfloat16"):
    timers[dtype] = (_step_timer(smoke, dtype), dtype)
  res = bts.interleaved(
    timers,
    rounds=1 if smoke else args.rounds,
    steps=1 if smoke else args.steps,
    peak_n=256 if smoke else 8192 if on_gpu else 2048,
    peak_reps=1 if smoke else 10 if on_gpu else 3,
  )
  config = _step_config(smoke)
  res["width"], res["scenes"] = config.model.width, config.data.scenes_per_device
  res["memory"] = _device_memory()
  return res


def summarise_trace(folder: str, steps: int, top: int = 25) -> dict:
  """The largest complete events ("X") of a jax.profiler trace in `folder`, per process (host
  threads, each device's streams): {process: [[name, ms per step, calls per step], ...]}, led by
  the row ALL (every event of the process summed: a device's busy time and kernel launches a step;
  host events nest, so theirs overcounts)."""
  import collections
  import glob
  import gzip

  files = sorted(glob.glob(os.path.join(folder, "**", "*.trace.json.gz"), recursive=True))
  if not files:
    return {}
  with gzip.open(files[-1]) as f:
    events = json.load(f)["traceEvents"]
  names = {
    e["pid"]: e["args"]["name"]
    for e in events
    if e.get("ph") == "M" and e.get("name") == "process_name" and "args" in e
  }
  total: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
  count: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
  for e in events:
    if e.get("ph") == "X" and "dur" in e:
      proc = names.get(e.get("pid"), str(e.get("pid")))
      total[proc][e["name"]] += e["dur"]
      count[proc][e["name"]] += 1
  return {
    proc: [
      [ALL, sum(c.values()) / steps / 1e3, sum(count[proc].values()) / steps],
      *([n, us / steps / 1e3, count[proc][n] / steps] for n, us in c.most_common(top)),
    ]
    for proc, c in total.items()
  }


ALL = "(all events)"


def _step_config(smoke: bool):
  """The paper GQN step's config (width 1, 30 scenes x 9 views, data in memory), or at smoke
  configs/gqn.py:smoke itself (the e2e phase's, so that a compilation cache serves both)."""
  from camrep.bench import train_step as bts
  from camrep.configs import gqn

  return gqn.get_config(SMOKE) if smoke else bts.gqn_config(1.0, 30)


def phase_profile(args) -> dict:
  """Where the float32 paper-size step's time goes: a jax.profiler trace of 10 steps."""
  import jax

  smoke = args.variant == SMOKE
  timer = _step_timer(smoke, "float32")
  timer.times(1 if smoke else 3)
  steps = 1 if smoke else 10
  folder = tempfile.mkdtemp(prefix="gpu_report_trace_")
  with jax.profiler.trace(folder):
    times = timer.times(steps)
  return {
    "steps": steps,
    "sec_per_step_traced": float(sorted(times)[len(times) // 2]),
    "flops": timer.flops,
    "top": summarise_trace(folder, steps),
  }


def phase_host(args) -> dict:
  """The paper GQN config's train loop with the step and renderer stubbed: the host's time a
  step (`camrep.bench.host.host_loop`; goal <= HOST_GOAL_MS)."""
  from camrep.bench import host as host_lib
  from camrep.bench import pipeline as bench_pipeline

  spec = E2E_CONFIGS["e2e"] + (f":{args.variant}" if args.variant else "")
  config = bench_pipeline.load_config(spec)
  config.data.in_memory = False  # the paper config's data path: batches rendered (stubbed here)
  out = host_lib.host_loop(config, steps=4 if args.variant == SMOKE else max(args.steps, 50))
  return {"config": spec, "cpu_cores": os.cpu_count(), **out}


def phase_e2e(args, config_path: str) -> dict:
  """Step alone, renderers, prepared data and the end-to-end loops of one config."""
  from camrep.bench import pipeline as bench_pipeline
  from camrep.data import sources

  smoke = args.variant == SMOKE
  spec = config_path + (f":{args.variant}" if args.variant else "")
  config = bench_pipeline.load_config(spec)
  family = sources.family_of_config(config.data)
  prepared = hasattr(family.config, "num_train_scenes")
  e2e = ("render", "prepared") if prepared else ("render",)
  steps = 2 if smoke else args.steps
  t0 = time.perf_counter()
  rates = bench_pipeline.input_bound(
    config,
    steps=steps,
    e2e=e2e,
    prepared_scenes=(4 if smoke else 256) if prepared else 0,
    pipeline_steps=2 if smoke else 10,
    per_scene=False,
    # At smoke only the GQN phase compiles its model's step; the others check their data paths.
    stub=smoke and config_path != E2E_CONFIGS["e2e"],
  )
  total = int(config.total_steps)
  out = {
    "config": spec,
    "total_steps": total,
    "images_per_step": int(config.data.scenes_per_device * config.data.views_per_scene),
    "rates": rates,
    "seconds": time.perf_counter() - t0,
    "memory": _device_memory(),
  }
  for name in e2e:
    r = rates[f"e2e {name}"]
    out[f"ratio {name}"] = r / rates["step"]
    out[f"eta_s {name}"] = total / r
  out["eta_s step alone"] = total / rates["step"]
  return out


def _run_timed(argv: list[str], log: str, timeout: float) -> tuple[float, int]:
  """(wall seconds, exit code) of a subprocess in the repository root, output to `log`."""
  t0 = time.perf_counter()
  with open(log, "w") as f:
    try:
      rc = subprocess.call(argv, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, timeout=timeout)
    except subprocess.TimeoutExpired:
      rc = -9
  return time.perf_counter() - t0, rc


def _last_rate(workdir: str) -> float | None:
  """The last train/steps_per_sec of a camrep.main workdir's metrics.jsonl."""
  from camrep.runtime import writers

  rows = [r for r in writers.read_metrics(workdir) if "train/steps_per_sec" in r]
  return float(rows[-1]["train/steps_per_sec"]) if rows else None


def phase_medium(args) -> dict:
  """:medium runs against the comparison's medium plan (seconds on one H100, derived); at
  --variant smoke one smoke run of each kind, to check the code."""
  from camrep.comparison import plan as plan_lib
  from camrep.configs import gqn

  plan = plan_lib.plans()["medium"]
  smoke = args.variant == SMOKE
  variant = SMOKE if smoke else "medium"
  py = sys.executable
  tmp = tempfile.mkdtemp(prefix="gpu_report_medium_")
  deadline = time.perf_counter() + args.budget_s - 20
  out = {"variant": variant, "runs": []}

  def left() -> float:
    return max(10.0, deadline - time.perf_counter())

  def run(name: str, argv: list[str], plan_s: float, **extra) -> int:
    sec, code = _run_timed(argv, os.path.join(tmp, f"{name}.log"), left())
    row = {"command": shlex.join(argv), "exit": code, "seconds": sec, "plan_s": plan_s, **extra}
    if code != 0:
      row["log_tail"] = _tail(os.path.join(tmp, f"{name}.log"))
    out["runs"].append(row)
    return code

  # View synthesis, shortened: K steps timed whole, the rest extrapolated at the logged rate.
  total = int(gqn.get_config(variant).total_steps)
  k = min(total, 2 if smoke else 2000)
  wd = os.path.join(tmp, "synthesis_gqn")
  argv = [py, "-m", "camrep.main", f"--config=configs/gqn.py:{variant}", f"--workdir={wd}"]
  argv += [f"--config.total_steps={k}", f"--config.eval_every_steps={k}"]
  argv += [f"--config.ckpt_every_steps={k}", f"--config.log_every_steps={min(k, 100)}"]
  code = run(
    "synthesis", argv, plan.synthesis_s["gqn"], run=f"synthesis gqn:{variant}, {k} of {total} steps"
  )
  rate = _last_rate(wd) if code == 0 else None
  out["runs"][-1].update(
    steps_per_s=rate, projected_s=out["runs"][-1]["seconds"] + (total - k) / rate if rate else None
  )
  if code == 0:
    argv = [py, "-m", "camrep.synthesis.evaluate", "--workdir", wd]
    if smoke:
      argv += ["--what=noise"]
    run("evaluate", argv, plan.evaluate_s, run="camrep.synthesis.evaluate of that run")
  # Regression runs: the first renders and caches the data (plan: data_s + regression_s).
  cache = os.path.join(tmp, "cache")
  for i, lr in enumerate(plan.lrs["gqn"][: 1 if smoke else None]):
    argv = [py, "-m", "camrep.regression", f"--config=configs/regression.py:gqn,{variant}"]
    argv += [f"--workdir={os.path.join(tmp, f'regression_{i}')}"]
    argv += ["--config.representation=quat", f"--config.optax.lr={lr:g}"]
    argv += [f"--config.data.cache_dir={cache}"]
    name = f"regression gqn/quat lr {lr:g}" + (" (renders the data)" if i == 0 else "")
    run(
      f"regression_{i}",
      argv,
      plan.regression_s["gqn"] + (plan.data_s["gqn"] if i == 0 else 0),
      run=name,
    )
  out["plan_total_s_jobs4"] = _plan_total(plan)
  failed = [r["run"] for r in out["runs"] if r["exit"] != 0]
  if failed:
    out["error"] = f"runs failed: {', '.join(failed)}"
  return out


def _tail(log: str) -> str:
  if not os.path.exists(log):
    return ""
  with open(log) as f:
    return "".join(f.readlines()[-15:])


def _plan_total(plan) -> float:
  """The plan's estimate of the whole comparison at its size with --jobs 4 and the noise runs
  (seconds), as its --dry_run prints it."""
  from camrep.comparison import launch as launch_lib

  launch = launch_lib.make_launch(
    plan,
    tempfile.mkdtemp(prefix="gpu_report_plan_"),
    settings=launch_lib.SETTINGS,
    noise_kinds=("lowdim", "mlp", "convdraw"),
  )
  return launch_lib.remaining_s(launch, at_once=4)


def run_phase(phase: str, args) -> dict:
  if phase == "env":
    return phase_env(args)
  if phase == "step":
    return phase_step(args)
  if phase == "profile":
    return phase_profile(args)
  if phase == "host":
    return phase_host(args)
  if phase == "medium":
    return phase_medium(args)
  return phase_e2e(args, E2E_CONFIGS[phase])


# ---------------------------------------------------------------------------------------------
# The report.


def _fmt_s(sec: float | None) -> str:
  from camrep.runtime import progress

  return "-" if sec is None else progress.format_duration(sec)


def _spread(s: dict, fmt: str, scale: float = 1.0) -> str:
  m, lo, hi = (s[k] * scale for k in ("median", "min", "max"))
  return f"{m:{fmt}} ({lo:{fmt}}-{hi:{fmt}})"


def render_markdown(phases: dict[str, dict]) -> str:
  """The report from the phase results present."""
  lines = ["# camrep on a GPU (python -m camrep.bench.gpu_report)", "", *how_to_run()]
  env = phases.get("env")
  lines += ["## Device and versions", ""]
  if env and "error" not in env:
    v = env["versions"]
    lines += [
      f"- device: {env['device_kind']} ({env['platform']}, {env['devices']} device(s)); "
      f"nvidia-smi: {env.get('nvidia_smi') or '-'}; {env['cpu_cores']} CPU cores",
      "- versions: " + ", ".join(f"{k} {x}" for k, x in v.items()),
      f"- commit: {env.get('commit') or '-'}",
    ]
    # Merged calls: a phase measured at another commit says so (each phase records its own).
    other = {
      p: r["commit"]
      for p, r in phases.items()
      if p != "env" and r.get("commit") and r["commit"] != env.get("commit")
    }
    if other:
      lines.append(
        "- measured at other commits: " + ", ".join(f"{p} {c}" for p, c in other.items())
      )
  else:
    lines.append(f"- not measured{': ' + env['error'] if env else ''}")
  lines.append("")

  step = phases.get("step")
  lines += ["## Paper-size GQN step alone", ""]
  if step and "error" not in step:
    lines += [
      f"Width {step['width']}, {step['scenes']} scenes x 9 views of 64 px; median (min-max) "
      f"over {step['rounds']} rounds of {step['steps']} steps, each round's fraction of peak "
      "against the matmul peak of the step's dtype measured in the same round.",
      "",
      "| dtype | s/step | images/s | analytic GFLOP/step | TFLOP/s | matmul peak TFLOP/s | "
      "fraction of peak | goal s/step | compile s |",
      "|---|---|---|---|---|---|---|---|---|",
    ]
    for d in [d for d in ("float32", "bfloat16") if d in step]:
      r = step[d]
      goal = GOALS[d]
      met = "met" if r["sec"]["median"] <= goal else "not met"
      lines.append(
        f"| {d} | {_spread(r['sec'], '.4f')} | {_spread(r['images_per_s'], '.0f')} | "
        f"{r['flops'] / 1e9:.0f} | {_spread(r['flops_per_s'], '.1f', 1e-12)} | "
        f"{_spread(step['peaks'][d], '.0f', 1e-12)} | {_spread(r['mfu'], '.3f')} | "
        f"<= {goal * 1e3:.1f} ms ({met}) | {r['compile_s']:.0f} |"
      )
    lines += ["", f"Peak memory: {_memory(step['memory'])}.", ""]
  else:
    lines += [f"Not measured{': ' + step['error'] if step else ''}.", ""]

  prof = phases.get("profile")
  lines += ["## Where the float32 step's time goes (jax.profiler)", ""]
  if prof and "error" not in prof:
    lines += [f"{prof['steps']} steps traced.", ""]
    lines += [
      f"Median traced step {prof['sec_per_step_traced'] * 1e3:.2f} ms. Largest events per "
      "step, by process (a GPU's kernels are under its device's process):",
      "",
    ]
    for proc, rows in prof["top"].items():
      lines += [f"**{proc}**", "", "| event | ms/step | calls/step |", "|---|---|---|"]
      lines += [f"| `{n[:90]}` | {ms:.3f} | {c:g} |" for n, ms, c in rows[:16]]
      lines.append("")
  else:
    lines += [f"Not measured{': ' + prof['error'] if prof else ''}.", ""]

  host = phases.get("host")
  lines += ["## The host's time a step (the loop with the step and renderer stubbed)", ""]
  if host and "error" not in host:
    met = "met" if host["host_ms_per_step"] <= HOST_GOAL_MS else "not met"
    lines += [
      f"`{host['config']}`, {host['layout']} of {host['image_size']} px, {host['steps']} steps "
      f"on {host['cpu_cores']} CPU cores: {host['steps_per_s']:.1f} steps/s, "
      f"{host['host_ms_per_step']:.2f} ms a step (goal <= {HOST_GOAL_MS:g} ms: {met}; "
      f"{1e3 * host['cpu_s_per_step']:.2f} ms of this process's CPU time a step).",
      "",
    ]
  else:
    lines += [f"Not measured{': ' + host['error'] if host else ''}.", ""]

  lines += [
    "## End to end (batches rendered on the device, and a prepared dataset)",
    "",
    "Steps/s of the train loop as `camrep.synthesis.train` runs it (metrics read at log steps "
    "only), against the step alone (the faster of two timings); ETA of the config's total steps at that rate (goal for GQN: "
    "ratio >= 0.9, 1M steps in under 5 hours).",
    "",
    "| config | step alone steps/s | render one call batches/s | prepared batches/s | end to end, "
    "rendered: steps/s (ratio) ETA | end to end, prepared: steps/s (ratio) ETA | peak memory |",
    "|---|---|---|---|---|---|---|",
  ]
  for phase in E2E_CONFIGS:
    r = phases.get(phase)
    if not r:
      lines.append(f"| {E2E_CONFIGS[phase]} | not measured | | | | | |")
      continue
    if "error" in r:
      lines.append(f"| {E2E_CONFIGS[phase]} | failed: {r['error'][:200]} | | | | | |")
      continue
    rt = r["rates"]
    cells = []
    for name in ("render", "prepared"):
      if f"e2e {name}" in rt:
        cells.append(
          f"{rt[f'e2e {name}']:.2f} ({r[f'ratio {name}']:.2f}) {_fmt_s(r[f'eta_s {name}'])}"
        )
      else:
        cells.append("-")
    prep = f"{rt['prepared']:.1f}" if "prepared" in rt else "-"
    lines.append(
      f"| `{r['config']}` ({r['total_steps']:,} steps) | {rt['step']:.2f} | "
      f"{rt['render, one call']:.2f} | {prep} | {cells[0]} | {cells[1]} | "
      f"{_memory(r['memory'])} |"
    )
  lines.append("")

  med = phases.get("medium")
  lines += ["## The :medium comparison: measured against the plan", ""]
  if med and med.get("runs"):  # runs that ended stand even when a later one failed
    lines += [
      "Plan: camrep/comparison/plans.toml, size medium (derived, not measured). "
      f"Its estimate of the whole comparison with --jobs 4: {_fmt_s(med['plan_total_s_jobs4'])}.",
      "",
      "| run | measured | projected full run | plan | measured / plan | exit |",
      "|---|---|---|---|---|---|",
    ]
    for r in med["runs"]:
      full = r.get("projected_s") or r["seconds"]
      ratio = f"{full / r['plan_s']:.2f}" if r["plan_s"] and r["exit"] == 0 else "-"
      rate = f", {r['steps_per_s']:.1f} steps/s" if r.get("steps_per_s") else ""
      lines.append(
        f"| {r['run']} | {_fmt_s(r['seconds'])}{rate} | {_fmt_s(r.get('projected_s'))} | "
        f"{_fmt_s(r['plan_s'])} | {ratio} | {r['exit']} |"
      )
    if "error" in med:
      lines += ["", f"Incomplete: {med['error']} (a run cut short has no ratio)."]
    lines += ["", "Commands:", ""] + [f"    {r['command']}" for r in med["runs"]] + [""]
  else:
    lines += [f"Not measured{': ' + med['error'] if med else ''}.", ""]
  return "\n".join(lines) + "\n"


def _memory(m: dict) -> str:
  if "device_peak_mib" in m:
    return f"{m['device_peak_mib'] / 1024:.1f} GiB on the device (host RSS {m['host_peak_rss_mib'] / 1024:.1f} GiB)"
  return f"host RSS {m['host_peak_rss_mib'] / 1024:.1f} GiB"


def load_phases(folders: list[str]) -> dict[str, dict]:
  """Phase results from gpu_report_<phase>.json files in `folders` (later folders win)."""
  phases = {}
  for folder in folders:
    for phase in PHASES:
      path = os.path.join(folder, f"gpu_report_{phase}.json")
      if os.path.exists(path):
        with open(path) as f:
          phases[phase] = json.load(f)
  return phases


def write_report(out: str, phases: dict[str, dict]) -> None:
  os.makedirs(out, exist_ok=True)
  with open(os.path.join(out, "gpu_report.json"), "w") as f:
    json.dump(phases, f, indent=1, sort_keys=True)
  with open(os.path.join(out, "gpu_report.md"), "w") as f:
    f.write(render_markdown(phases))


# ---------------------------------------------------------------------------------------------


def _parse(argv):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--phases", default="", help=f"comma-separated, or 'all': {', '.join(PHASES)}")
  p.add_argument("--out", default=os.environ.get("OUT") or "gpu_report", help="report folder")
  p.add_argument("--merge", nargs="*", default=[], help="folders of earlier calls' phase files")
  p.add_argument("--dry_run", action="store_true", help="print the plan and the commands")
  p.add_argument("--variant", default="", help="config variant: '' (paper size) or smoke (a check)")
  p.add_argument(
    "--budget_s", type=float, default=None, help="seconds for all phases (470; smoke 1200)"
  )
  p.add_argument("--steps", type=int, default=30, help="timed steps per timing")
  p.add_argument("--rounds", type=int, default=3, help="step phase: rounds of (peak, steps)")
  p.add_argument("--allow_cpu", action="store_true", help="run paper-size phases without a GPU")
  p.add_argument("--child", default="", help=argparse.SUPPRESS)
  args = p.parse_args(argv)
  phases = PHASES if args.phases == "all" else [x for x in args.phases.split(",") if x]
  bad = set(phases) - set(PHASES)
  if bad:
    p.error(f"unknown phases {sorted(bad)}; choose from {', '.join(PHASES)} or all")
  if args.variant not in ("", SMOKE):
    p.error(f"--variant must be '' or smoke, got {args.variant!r}")
  args.phases = list(phases)
  if args.budget_s is None:
    args.budget_s = 1200.0 if args.variant == SMOKE else 470.0
  return args


def _child(args) -> int:
  """Runs the phases named by --child in turn, each result (or its error) written as it ends."""
  deadline = time.perf_counter() + args.budget_s
  for phase in args.child.split(","):
    t0 = time.perf_counter()
    args.budget_s = deadline - t0  # what is left of the call's budget
    print(f"=== phase {phase} ({args.budget_s:.0f} s left)", flush=True)
    try:
      result = run_phase(phase, args)
    except Exception as e:  # noqa: BLE001 - recorded in the report, the other phases go on
      import traceback

      traceback.print_exc()
      result = {"error": f"{type(e).__name__}: {e}"}
    result.setdefault("commit", _commit())
    with open(os.path.join(args.out, f"gpu_report_{phase}.json"), "w") as f:
      json.dump(result, f, indent=1, default=float)
    print(f"=== phase {phase}: {time.perf_counter() - t0:.0f} s", flush=True)
  return 0


def main(argv=None) -> int:
  args = _parse(argv)
  if args.dry_run:
    print("\n".join(plan_lines(args.variant)))
    return 0
  os.makedirs(args.out, exist_ok=True)
  if args.child:
    return _child(args)
  if args.phases and args.variant != SMOKE and not args.allow_cpu:
    import jax

    if jax.devices()[0].platform == "cpu":
      print("no GPU here: paper-size phases are for a GPU (--variant smoke checks the code)")
      return 2
  env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false", "PYTHONUNBUFFERED": "1"}
  if args.variant == SMOKE:  # a check of the code: compile fast, each program once
    env.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
    env.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.join(args.out, "jax_cache"))
    env.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
  deadline = time.perf_counter() + args.budget_s
  failed = []
  # On a GPU each phase has a process of its own (its memory peak, and a crash, stay its own);
  # the smoke check runs them all in one, which imports the library and builds the smoke step
  # once (cold on 2 cores: 1 min 53 s instead of 2 min 8 s).
  groups = [args.phases] if args.variant == SMOKE else [[p] for p in args.phases]
  for group in groups:
    left = deadline - time.perf_counter()
    paths = {p: os.path.join(args.out, f"gpu_report_{p}.json") for p in group}
    for path in paths.values():
      if os.path.exists(path):  # an earlier call's result must not stand for this one's
        os.remove(path)
    if left < 30:
      for path in paths.values():
        with open(path, "w") as f:
          json.dump({"error": f"not run: the call's {args.budget_s:.0f} s budget was spent"}, f)
      continue
    argv = [sys.executable, "-m", "camrep.bench.gpu_report", "--child", ",".join(group)]
    argv += ["--out", args.out, "--variant", args.variant, "--steps", str(args.steps)]
    argv += ["--rounds", str(args.rounds), "--budget_s", str(left)]
    died = "the phase's process died without a result (memory?)"
    try:
      subprocess.run(argv, env=env, timeout=left, check=False, cwd=ROOT)
    except subprocess.TimeoutExpired:
      died = f"timed out after {left:.0f} s"
    for phase, path in paths.items():
      if not os.path.exists(path):
        with open(path, "w") as f:
          json.dump({"error": died}, f)
      with open(path) as f:
        error = json.load(f).get("error")
      if error:
        failed.append(f"{phase} ({error})")
  phases = load_phases([*args.merge, args.out])
  write_report(args.out, phases)
  print(render_markdown(phases))
  if failed:
    print(f"error: {len(failed)} phases failed: {'; '.join(failed)}", file=sys.stderr, flush=True)
    return 1
  return 0


if __name__ == "__main__":
  sys.exit(main())

"""One report of camrep on a GPU: the step alone, end to end, paper configs, :medium runs (issue 30).

A GPU is lent to this project now and then, for well under an hour, in commands of at most 10
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
  e2e           the paper GQN config end to end (`bench_pipeline.input_bound`): the step alone,
                batches rendered on demand on the device (one renderer call a batch), a prepared
                dataset of 256 rooms, and the train loop fed by each: steps/s, ratio to the step
                alone (goal >= 0.9), ETA of the config's 1M steps
  car, gibson, seven_scenes
                the same for configs/shapenet_car.py, gibson.py, seven_scenes.py at paper size
                (prepared data only for families with a scene count: car)
  medium        the `:medium` comparison (experiments/run_comparison.py --size medium) measured
                against its plan (`PLANS["medium"]`): a shortened GQN view-synthesis run
                extrapolated to 20,000 steps, `camrep.synthesis.evaluate` on it, and two whole
                regression runs (the first renders and caches the data)

Each phase writes DIR/gpu_report_<phase>.json; every call rewrites DIR/gpu_report.md and .json
from the phase files present (and those of --merge folders), so the last merge is the report.
`--dry_run` prints the plan and the commands, imports nothing heavy and runs on any machine.

  python experiments/gpu_report.py --dry_run                       # the plan and the commands
  python experiments/gpu_report.py --phases env,step --out $OUT    # on the GPU machine
  python experiments/gpu_report.py --merge DIR1 DIR2 ... --out results/gpu   # on the CPU
  python experiments/gpu_report.py --phases all --variant smoke --out /tmp/r  # CPU check, tiny
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def _sibling(name: str):
  """experiments/<name>.py as a module (experiments/ is not a package; no sys.path edits)."""
  if name in sys.modules:
    return sys.modules[name]
  spec = importlib.util.spec_from_file_location(name, os.path.join(HERE, f"{name}.py"))
  module = importlib.util.module_from_spec(spec)
  sys.modules[name] = module
  spec.loader.exec_module(module)
  return module


PHASES = ("env", "step", "profile", "e2e", "car", "gibson", "seven_scenes", "medium")
# Config of each end-to-end phase.
E2E_CONFIGS = {
  "e2e": "configs/gqn.py",
  "car": "configs/shapenet_car.py",
  "gibson": "configs/gibson.py",
  "seven_scenes": "configs/seven_scenes.py",
}
# The calls a lent GPU runs, each well inside the device tool's 10 minutes, with a guess of its
# minutes on one H100 (compiles dominate: ~1 min per paper-size step and renderer).
CALLS = (
  ("env,step,profile", 7),
  ("e2e", 7),
  ("car,gibson,seven_scenes", 7),
  ("medium", 7),
)
WHEELHOUSE = ".whl"
GOALS = {"float32": 10.5e-3, "bfloat16": 7e-3}
H100_LAST = "H100, 2026-11-22: step alone 0.015 s float32; end to end 3.5 steps/s, ETA 80 h"


def wheelhouse_command() -> str:
  return ".venv/bin/python experiments/build_wheelhouse.py"


def gpu_command(phases: str) -> str:
  """The device tool's `run` command of one call (run with carry=[".whl"])."""
  build_wheelhouse = _sibling("build_wheelhouse")

  return (
    f"{build_wheelhouse.install_command(WHEELHOUSE)} && "
    f"PYTHONPATH=. PYTHONUNBUFFERED=1 python3 experiments/gpu_report.py --phases {phases} --out $OUT"
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
    "`timeout_s=540`, once per call below (PHASES as listed; each call stays under 8 min):",
    "",
    f"       {gpu_command('PHASES')}",
    "",
    "| call | PHASES | minutes on one H100 (guess) |",
    "|---|---|---|",
  ]
  lines += [f"| {i} | `{p}` | ~{m} |" for i, (p, m) in enumerate(CALLS, 1)]
  lines += [
    "",
    "The calls are in order of priority (calls 1 and 2 answer the step and end-to-end goals). A "
    "session has ~30 minutes of device time and a machine goes back after 30 s idle: issue the "
    "next call as soon as one returns, and stop after call 2 or 3 if less than ~8 minutes are "
    "left.",
    "",
    "Each call brings back DIR/gpu_report_<phase>.json, gpu_report.md and gpu_report.json "
    "under the tool's files_at. Then, on the CPU machine, merge them into one report:",
    "",
    "       .venv/bin/python experiments/gpu_report.py --merge FILES_AT_1 FILES_AT_2 ... "
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
# Phases (each runs in its own process: `--child PHASE`).


def _device_memory() -> dict:
  """Peak device memory of this process (GPU allocator stats; RSS on the CPU), MiB."""
  import jax

  peak_rss_mb = _sibling("bench_train_step").peak_rss_mb

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
  with contextlib.suppress(OSError, subprocess.SubprocessError):
    out["commit"] = subprocess.run(
      ["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
  return out


def phase_step(args) -> dict:
  """The paper GQN step alone, float32 and bfloat16, MFU against the same dtype's peak."""
  _sibling("bench_pipeline")  # bench_train_step imports it by name
  bts = _sibling("bench_train_step")
  import jax

  smoke = args.variant == "smoke"
  width, scenes = (1 / 32, 2) if smoke else (1.0, 30)
  on_gpu = jax.devices()[0].platform == "gpu"
  timers = {}
  for dtype in ("float32", "bfloat16"):
    config = bts.gqn_config(width, scenes)
    config.model.dtype = dtype
    timers[dtype] = (bts.StepTimer(config), dtype)
  res = bts.interleaved(
    timers,
    rounds=args.rounds,
    steps=2 if smoke else args.steps,
    peak_n=8192 if on_gpu else 2048,
    peak_reps=10 if on_gpu else 3,
  )
  res["width"], res["scenes"] = width, scenes
  res["memory"] = _device_memory()
  return res


def summarise_trace(folder: str, steps: int, top: int = 25) -> dict:
  """The largest complete events ("X") of a jax.profiler trace in `folder`, per process (host
  threads, each device's streams): {process: [[name, ms per step, calls per step], ...]}."""
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
    proc: [[n, us / steps / 1e3, count[proc][n] / steps] for n, us in c.most_common(top)]
    for proc, c in total.items()
  }


def phase_profile(args) -> dict:
  """Where the float32 paper-size step's time goes: a jax.profiler trace of 10 steps."""
  _sibling("bench_pipeline")  # bench_train_step imports it by name
  bts = _sibling("bench_train_step")
  import jax

  smoke = args.variant == "smoke"
  config = bts.gqn_config(*((1 / 32, 2) if smoke else (1.0, 30)))
  timer = bts.StepTimer(config)
  timer.times(3)
  steps = 2 if smoke else 10
  folder = tempfile.mkdtemp(prefix="gpu_report_trace_")
  with jax.profiler.trace(folder):
    times = timer.times(steps)
  return {
    "steps": steps,
    "sec_per_step_traced": float(sorted(times)[len(times) // 2]),
    "flops": timer.flops,
    "top": summarise_trace(folder, steps),
  }


def phase_e2e(args, config_path: str) -> dict:
  """Step alone, renderers, prepared data and the end-to-end loops of one config."""
  bench_pipeline = _sibling("bench_pipeline")

  from camrep.synthesis import components

  smoke = args.variant == "smoke"
  spec = config_path + (f":{args.variant}" if args.variant else "")
  config = bench_pipeline.load_config(spec)
  family = components.make_source(config)
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
  """:medium runs against `run_comparison.PLANS["medium"]` (seconds on one H100, derived)."""
  import run_comparison as rc

  plan = rc.PLANS["medium"]
  smoke = args.variant == "smoke"
  variant = "smoke" if smoke else "medium"
  py = sys.executable
  tmp = tempfile.mkdtemp(prefix="gpu_report_medium_")
  deadline = time.perf_counter() + args.budget_s - 20
  out = {"variant": variant, "runs": []}

  def left() -> float:
    return max(10.0, deadline - time.perf_counter())

  # View synthesis, shortened: K steps timed whole, the rest extrapolated at the logged rate.
  from camrep.configs import gqn

  total = int(gqn.get_config(variant).total_steps)
  k = min(total, 4 if smoke else 2000)
  wd = os.path.join(tmp, "synthesis_gqn")
  argv = [py, "-m", "camrep.main", f"--config=configs/gqn.py:{variant}", f"--workdir={wd}"]
  argv += [f"--config.total_steps={k}", f"--config.eval_every_steps={k}"]
  argv += [f"--config.ckpt_every_steps={k}", "--config.log_every_steps=100" if not smoke else ""]
  argv = [a for a in argv if a]
  sec, code = _run_timed(argv, os.path.join(tmp, "synthesis.log"), left())
  rate = _last_rate(wd) if code == 0 else None
  projected = sec + (total - k) / rate if rate else None
  out["runs"].append(
    {
      "run": f"synthesis gqn:{variant}, {k} of {total} steps",
      "command": shlex.join(argv),
      "exit": code,
      "seconds": sec,
      "steps_per_s": rate,
      "projected_s": projected,
      "plan_s": plan.synthesis_s["gqn"],
    }
  )
  if code == 0:
    argv = [py, "-m", "camrep.synthesis.evaluate", "--workdir", wd]
    sec, code = _run_timed(argv, os.path.join(tmp, "evaluate.log"), left())
    out["runs"].append(
      {
        "run": "camrep.synthesis.evaluate of that run",
        "command": shlex.join(argv),
        "exit": code,
        "seconds": sec,
        "plan_s": plan.evaluate_s,
      }
    )
  # Two regression runs: the first renders and caches the data (plan: data_s + regression_s).
  cache = os.path.join(tmp, "cache")
  for i, lr in enumerate(plan.lrs["gqn"]):
    wd = os.path.join(tmp, f"regression_{i}")
    argv = [py, "-m", "camrep.regression", f"--config=configs/regression.py:gqn,{variant}"]
    argv += [f"--workdir={wd}", "--config.representation=quat"]
    argv += [f"--config.optax.lr={lr:g}", f"--config.data.cache_dir={cache}"]
    sec, code = _run_timed(argv, os.path.join(tmp, f"regression_{i}.log"), left())
    out["runs"].append(
      {
        "run": f"regression gqn/quat lr {lr:g}" + (" (renders the data)" if i == 0 else ""),
        "command": shlex.join(argv),
        "exit": code,
        "seconds": sec,
        "plan_s": plan.regression_s["gqn"] + (plan.data_s["gqn"] if i == 0 else 0),
      }
    )
  for r in out["runs"]:
    if r["exit"] != 0:
      log = r["run"].split()[0]
      r["log_tail"] = _tail(tmp, log)
  out["plan_total_s_jobs4"] = _plan_total()
  return out


def _tail(tmp: str, prefix: str) -> str:
  logs = sorted(f for f in os.listdir(tmp) if f.startswith(prefix) and f.endswith(".log"))
  if not logs:
    return ""
  with open(os.path.join(tmp, logs[-1])) as f:
    return "".join(f.readlines()[-15:])


def _plan_total() -> float | None:
  """The plan's estimate of the whole :medium comparison with --jobs 4 (seconds), via its
  --dry_run line."""
  out = subprocess.run(
    [sys.executable, "experiments/run_comparison.py", "--size", "medium", "--out",
     tempfile.mkdtemp(), "--jobs", "4", "--noise_runs", "--dry_run"],
    cwd=ROOT, capture_output=True, text=True,
  ).stdout  # fmt: skip
  import re

  m = re.search(r"estimated (?:(\d+)h)?(?:(\d+)m)?(\d+)s", out)
  if not m:
    return None
  h, mi, s = (int(x) if x else 0 for x in m.groups())
  return 3600 * h + 60 * mi + s


def run_phase(phase: str, args) -> dict:
  if phase == "env":
    return phase_env(args)
  if phase == "step":
    return phase_step(args)
  if phase == "profile":
    return phase_profile(args)
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
  lines = ["# camrep on a GPU (experiments/gpu_report.py)", "", *how_to_run()]
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
  else:
    lines.append(f"- not measured{': ' + env['error'] if env else ''}")
  lines += ["", f"Last GPU figures before this report ({H100_LAST}).", ""]

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
    for d in ("float32", "bfloat16"):
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
      lines += [f"| `{n[:90]}` | {ms:.3f} | {c:g} |" for n, ms, c in rows[:15]]
      lines.append("")
  else:
    lines += [f"Not measured{': ' + prof['error'] if prof else ''}.", ""]

  lines += [
    "## End to end (batches rendered on the device, and a prepared dataset)",
    "",
    "Steps/s of the train loop as `camrep.synthesis.train` runs it, against the step alone "
    "(the faster of two timings); ETA of the config's total steps at that rate (goal for GQN: "
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
  if med and "error" not in med:
    lines += [
      'Plan: `experiments/run_comparison.py` `PLANS["medium"]` (derived, not measured). '
      f"Its estimate of the whole comparison with --jobs 4: {_fmt_s(med['plan_total_s_jobs4'])}.",
      "",
      "| run | measured | projected full run | plan | measured / plan | exit |",
      "|---|---|---|---|---|---|",
    ]
    ratios = []
    for r in med["runs"]:
      full = r.get("projected_s") or r["seconds"]
      ratio = full / r["plan_s"] if r["plan_s"] else float("nan")
      ratios.append(ratio)
      rate = f", {r['steps_per_s']:.1f} steps/s" if r.get("steps_per_s") else ""
      lines.append(
        f"| {r['run']} | {_fmt_s(r['seconds'])}{rate} | {_fmt_s(r.get('projected_s'))} | "
        f"{_fmt_s(r['plan_s'])} | {ratio:.2f} | {r['exit']} |"
      )
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
  p.add_argument("--variant", default="", help="config variant: '' (paper size) or smoke (CPU)")
  p.add_argument("--budget_s", type=float, default=470, help="seconds for all phases of a call")
  p.add_argument("--steps", type=int, default=30, help="timed steps per timing")
  p.add_argument("--rounds", type=int, default=3, help="step phase: rounds of (peak, steps)")
  p.add_argument("--allow_cpu", action="store_true", help="run paper-size phases without a GPU")
  p.add_argument("--child", default="", help=argparse.SUPPRESS)
  args = p.parse_args(argv)
  phases = PHASES if args.phases == "all" else [x for x in args.phases.split(",") if x]
  bad = set(phases) - set(PHASES)
  if bad:
    p.error(f"unknown phases {sorted(bad)}; choose from {', '.join(PHASES)} or all")
  if args.variant not in ("", "smoke"):
    p.error(f"--variant must be '' or smoke, got {args.variant!r}")
  args.phases = list(phases)
  return args


def _child(args) -> int:
  try:
    result = run_phase(args.child, args)
  except Exception as e:  # noqa: BLE001 - recorded in the report, the other phases go on
    import traceback

    traceback.print_exc()
    result = {"error": f"{type(e).__name__}: {e}"}
  with open(os.path.join(args.out, f"gpu_report_{args.child}.json"), "w") as f:
    json.dump(result, f, indent=1, default=float)
  return 0


def main(argv=None) -> int:
  args = _parse(argv)
  if args.dry_run:
    print("\n".join(plan_lines(args.variant)))
    return 0
  os.makedirs(args.out, exist_ok=True)
  if args.child:
    return _child(args)
  if args.phases and args.variant != "smoke" and not args.allow_cpu:
    import jax

    if jax.devices()[0].platform == "cpu":
      print("no GPU here: paper-size phases are for a GPU (--variant smoke checks the code)")
      return 2
  env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false", "PYTHONUNBUFFERED": "1"}
  env["PYTHONPATH"] = os.pathsep.join(x for x in (ROOT, env.get("PYTHONPATH", "")) if x)
  deadline = time.perf_counter() + args.budget_s
  for phase in args.phases:
    left = deadline - time.perf_counter()
    path = os.path.join(args.out, f"gpu_report_{phase}.json")
    if left < 30:
      with open(path, "w") as f:
        json.dump({"error": f"not run: the call's {args.budget_s:.0f} s budget was spent"}, f)
      continue
    print(f"=== phase {phase} ({left:.0f} s left)", flush=True)
    argv = [sys.executable, os.path.abspath(__file__), "--child", phase, "--out", args.out]
    argv += ["--variant", args.variant, "--steps", str(args.steps), "--rounds", str(args.rounds)]
    argv += ["--budget_s", str(left)]
    t0 = time.perf_counter()
    try:
      subprocess.run(argv, env=env, timeout=left, check=False)
    except subprocess.TimeoutExpired:
      with open(path, "w") as f:
        json.dump({"error": f"timed out after {left:.0f} s"}, f)
    if not os.path.exists(path):
      with open(path, "w") as f:
        json.dump({"error": "the phase's process died without a result (memory?)"}, f)
    print(f"=== phase {phase}: {time.perf_counter() - t0:.0f} s", flush=True)
  phases = load_phases([*args.merge, args.out])
  write_report(args.out, phases)
  print(render_markdown(phases))
  return 0


if __name__ == "__main__":
  sys.exit(main())

"""The GPU report (`python -m camrep.bench.gpu_report`: its plan, phases and report) and
tools/build_wheelhouse.py (its list).

Nothing here needs a GPU or downloads anything: the dry run, every phase at --variant smoke on
the CPU, the wheelhouse's listing, the dependency walk on fake metadata, and the Markdown report
rendered from made-up phase results.
"""

from __future__ import annotations

import importlib.metadata as md
import json
import os
import subprocess
import sys

import pytest

from camrep.bench import gpu_report
from tools import build_wheelhouse

pytestmark = pytest.mark.slow

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _run(*argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
  env = dict(os.environ)
  env.pop("OUT", None)
  return subprocess.run(
    [sys.executable, *argv], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout
  )


REPORT = ("-m", "camrep.bench.gpu_report")


def test_dry_run_prints_the_plan_and_the_two_commands():
  r = _run(*REPORT, "--dry_run")
  assert r.returncode == 0, r.stderr
  out = r.stdout
  gr = gpu_report
  # The two commands: the wheelhouse on the CPU, the report call on the GPU (wheels installed
  # first, camrep from the working tree, results into the device tool's $OUT).
  assert "tools/build_wheelhouse.py" in out
  assert "pip install" in out and "--no-index" in out and ".whl/*.whl" in out
  assert "python3 -m camrep.bench.gpu_report --phases PHASES --out $OUT" in out
  # Every phase is in exactly one call, and every call is listed.
  called = [p for phases, _ in gr.CALLS for p in phases.split(",")]
  assert sorted(called) == sorted(gr.PHASES)
  for phases, _ in gr.CALLS:
    assert f"`{phases}`" in out
  assert "--merge" in out
  for goal in ("10.5 ms", "7 ms", "0.9"):
    assert goal in out


def test_unknown_phase_and_cpu_without_smoke_are_refused(tmp_path):
  r = _run(*REPORT, "--phases", "stepp", "--out", str(tmp_path))
  assert r.returncode == 2 and "unknown phases" in r.stderr
  r = _run(*REPORT, "--phases", "env", "--out", str(tmp_path))
  assert r.returncode == 2 and "no GPU here" in r.stdout


def test_env_phase_runs_on_the_cpu_and_writes_the_report(tmp_path):
  r = _run(*REPORT, "--phases", "env", "--allow_cpu", "--out", str(tmp_path))
  assert r.returncode == 0, r.stdout + r.stderr
  env = json.loads((tmp_path / "gpu_report_env.json").read_text())
  assert env["platform"] == "cpu" and env["versions"]["jax"]
  report = (tmp_path / "gpu_report.md").read_text()
  assert "## How to run it" in report and "## Device and versions" in report
  assert json.loads((tmp_path / "gpu_report.json").read_text())["env"] == env


def _spread(x):
  return {"median": x, "min": 0.9 * x, "max": 1.1 * x, "n": 3}


def test_report_from_phase_results(tmp_path):
  gr = gpu_report
  step = {
    "width": 1.0,
    "scenes": 30,
    "rounds": 3,
    "steps": 30,
    "peaks": {"float32": _spread(400e12), "bfloat16": _spread(780e12)},
    "memory": {"device_peak_mib": 20480.0, "host_peak_rss_mib": 3000.0},
  }
  for dtype, sec in (("float32", 0.015), ("bfloat16", 0.006)):
    step[dtype] = {
      "sec": _spread(sec),
      "images_per_s": _spread(270 / sec),
      "flops_per_s": _spread(1.7e12 / sec),
      "mfu": _spread(1.7e12 / sec / step["peaks"][dtype]["median"]),
      "flops": 1.7e12,
      "compile_s": 40.0,
    }
  e2e = {
    "config": "configs/gqn.py",
    "total_steps": 1_000_000,
    "rates": {
      "step": 60.0,
      "render, one call": 30.0,
      "prepared": 200.0,
      "e2e render": 30.0,
      "e2e prepared": 57.0,
    },
    "ratio render": 0.5,
    "ratio prepared": 0.95,
    "eta_s render": 1e6 / 30,
    "eta_s prepared": 1e6 / 57,
    "memory": {"device_peak_mib": 30000.0, "host_peak_rss_mib": 4000.0},
  }
  (tmp_path / "a").mkdir()
  (tmp_path / "b").mkdir()
  (tmp_path / "a" / "gpu_report_step.json").write_text(json.dumps({**step, "commit": "aaa1111"}))
  env = {"versions": {}, "platform": "gpu", "device_kind": "H200", "devices": 1, "cpu_cores": 16}
  (tmp_path / "b" / "gpu_report_env.json").write_text(json.dumps({**env, "commit": "bbb2222"}))
  (tmp_path / "a" / "gpu_report_e2e.json").write_text(json.dumps({"error": "old failure"}))
  (tmp_path / "b" / "gpu_report_e2e.json").write_text(json.dumps(e2e))
  (tmp_path / "b" / "gpu_report_car.json").write_text(json.dumps({"error": "OOM in the step"}))
  run = {"command": "python -m camrep.main ...", "plan_s": 360.0, "steps_per_s": 132.6}
  medium = {
    "plan_total_s_jobs4": 5000.0,
    "runs": [
      {**run, "run": "synthesis", "exit": 0, "seconds": 113.0, "projected_s": 248.0},
      {**run, "run": "regression", "exit": -9, "seconds": 32.0, "steps_per_s": None},
    ],
    "error": "runs failed: regression",
  }
  (tmp_path / "b" / "gpu_report_medium.json").write_text(json.dumps(medium))
  phases = gr.load_phases([str(tmp_path / "a"), str(tmp_path / "b")])
  assert phases["e2e"] == e2e  # the later folder wins
  md_text = gr.render_markdown(phases)
  rows = {line.split(" |")[0]: line for line in md_text.splitlines() if line.startswith("| ")}
  assert "(not met)" in rows["| float32"] and "(met)" in rows["| bfloat16"]
  gqn = next(v for k, v in rows.items() if "configs/gqn.py" in k)
  assert "30.00 (0.50) 9h15m33s" in gqn and "57.00 (0.95)" in gqn and "29.3 GiB" in gqn
  assert "failed: OOM in the step" in md_text
  assert "- commit: bbb2222" in md_text and "- measured at other commits: step aaa1111" in md_text
  assert "| configs/gibson.py | not measured" in md_text
  # A medium call cut short keeps the runs that ended; the one cut short has no ratio.
  assert "| synthesis | 1m53s, 132.6 steps/s | 4m08s | 6m00s | 0.69 | 0 |" in md_text
  assert "| regression | 32s | - | 6m00s | - | -9 |" in md_text
  assert "Incomplete: runs failed: regression" in md_text


def test_wheelhouse_lists_the_missing_dependencies_pinned_here():
  r = _run("tools/build_wheelhouse.py", "--list")
  assert r.returncode == 0, r.stderr
  listed = dict(line.strip().split("==") for line in r.stdout.splitlines() if "==" in line)
  # protobuf is on the image too, but carried: tfds' generated code needs the tested runtime.
  for name in ("tensorflow-datasets", "grain", "ml-collections", "array-record", "protobuf"):
    assert listed[name] == md.version(name)
  for name in ("jax", "flax", "optax", "numpy", "opencv-python-headless", "orbax-checkpoint"):
    assert name not in listed  # on the GPU image already
  assert "--target /tmp/site .whl/*.whl" in r.stdout


def test_wheelhouse_walk_skips_the_image_and_other_pythons():
  bw = build_wheelhouse
  versions = {"a": "1.0", "b": "2.0", "c": "3.0", "d": "4.0", "img": "9.9", "hidden": "0.1"}
  requires = {
    "a": ["b>=1", "c; python_version < '3.12'", "d; extra == 'test'", "img"],
    "b": ["A"],  # a cycle, spelled differently
    "img": ["hidden"],  # the image's own requirements are not walked into
    "x": [],
  }
  pinned, missing = bw.closure(
    ["a", "x", "Z_missing"],
    exclude=frozenset({"img"}),
    version_of=versions.get,
    requires_of=lambda n: requires[n],
  )
  assert pinned == {"a": "1.0", "b": "2.0"}
  assert missing == ["x", "z-missing"]
  cmd = bw.download_command("grain", "0.2.18", "/tmp/w")
  assert cmd[-1] == "grain==0.2.18" and "--only-binary=:all:" in cmd and "--no-deps" in cmd
  assert cmd[cmd.index("--python-version") + 1] == "3.12"


@pytest.mark.parametrize("bad", ["--variant=paper"])
def test_bad_variant_is_refused(bad):
  r = _run(*REPORT, "--phases", "env", bad)
  assert r.returncode == 2 and "--variant" in r.stderr


def test_trace_summary_groups_events_by_process(tmp_path):
  import gzip

  gr = gpu_report
  events = [
    {"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/device:GPU:0"}},
    {"ph": "M", "name": "process_name", "pid": 2, "args": {"name": "/host:CPU"}},
    *({"ph": "X", "pid": 1, "name": "conv_kernel", "dur": 3000} for _ in range(4)),
    *({"ph": "X", "pid": 1, "name": "gemm", "dur": 1000} for _ in range(2)),
    {"ph": "X", "pid": 2, "name": "PjitFunction", "dur": 500},
    {"ph": "i", "pid": 1, "name": "marker"},
  ]
  (tmp_path / "plugins" / "profile" / "run").mkdir(parents=True)
  with gzip.open(tmp_path / "plugins" / "profile" / "run" / "h.trace.json.gz", "wt") as f:
    json.dump({"traceEvents": events}, f)
  top = gr.summarise_trace(str(tmp_path), steps=2)
  all_ = gr.ALL
  assert top["/device:GPU:0"] == [[all_, 7.0, 3.0], ["conv_kernel", 6.0, 2.0], ["gemm", 1.0, 1.0]]
  assert top["/host:CPU"] == [[all_, 0.25, 0.5], ["PjitFunction", 0.25, 0.5]]
  assert gr.summarise_trace(str(tmp_path / "plugins" / "none"), steps=1) == {}


def test_a_failed_phase_makes_the_report_exit_1_and_an_old_result_never_stands_in(
  tmp_path, monkeypatch, capsys
):
  """A phase whose child records an error (or dies without a result) fails the call: exit 1 and
  an `error:` line naming it; a result file left by an earlier call is not taken for its own."""
  gr = gpu_report
  (tmp_path / "gpu_report_host.json").write_text(json.dumps({"steps_per_s": 1.0}))  # stale

  def child(argv, **kw):  # at smoke one child runs every phase: "env,host"
    if "env" in argv[argv.index("--child") + 1].split(","):
      (tmp_path / "gpu_report_env.json").write_text(json.dumps({"error": "AttributeError: x"}))

  monkeypatch.setattr(gr.subprocess, "run", child)
  assert gr.main(["--phases", "env,host", "--variant", "smoke", "--out", str(tmp_path)]) == 1
  err = capsys.readouterr().err
  assert "error: 2 phases failed: env (AttributeError: x); host (the phase's process died" in err
  assert "error" in json.loads((tmp_path / "gpu_report_host.json").read_text())


def test_every_phase_runs_at_smoke_without_an_error(tmp_path):
  """`--phases all --variant smoke`: every phase's code runs on the CPU, with the library's
  smallest configs (one compilation of each program, shared through a compilation cache)."""
  r = _run(*REPORT, "--phases", "all", "--variant", "smoke", "--out", str(tmp_path), timeout=1500)
  assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
  for phase in gpu_report.PHASES:
    result = json.loads((tmp_path / f"gpu_report_{phase}.json").read_text())
    assert "error" not in result, (phase, result)
  host = json.loads((tmp_path / "gpu_report_host.json").read_text())
  assert host["host_ms_per_step"] > 0 and host["layout"] == "1 x 2 scenes x 4 views"
  report = (tmp_path / "gpu_report.md").read_text()
  assert "## The host's time a step" in report and "Not measured" not in report

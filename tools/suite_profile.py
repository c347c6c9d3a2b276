"""Where the test suite's time goes: each test's wall and CPU time, its subprocesses' CPU, and
JAX's tracing, lowering and XLA compile inside both.

  .venv/bin/python tools/suite_profile.py run --out /tmp/prof -- -q -n 2   # the whole suite
  .venv/bin/python tools/suite_profile.py report /tmp/prof [--top 40]

`run` calls pytest with the arguments after `--` and this module as a plugin (one JSON line per
test: worker, start, end, CPU of the worker and of the subprocesses it waited for), with
`tools/suite_profile_site` first on PYTHONPATH, whose sitecustomize.py records JAX's compile
events per test in every process that imports JAX (the workers and the `python -m camrep...`
runs tests start), written when the process exits. It exits with pytest's status. `report` reads
the two files and prints, per test file and then per test, wall seconds, CPU seconds (own /
subprocesses), JAX's trace, lowering and backend compile seconds (subprocesses included), the
number of compiles and the persistent cache's misses and hits; then the totals per kind of
process, the workers' busy spans, and the functions whose compiles cost most.

The durations JAX reports are wall time; with as many busy workers as cores they are close to
CPU time. A child killed by a signal (the resume tests) reports nothing, so its compiles are
missing from the table but not from the test's wall time. A PYTHONPATH sitecustomize of your own
is shadowed during `run`.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import pathlib
import subprocess
import sys
import time

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
SITE = ROOT / "tools" / "suite_profile_site"
ENV = "CAMREP_SUITE_PROFILE"  # the processes' log; the tests' log is its ".tests" sibling
PROCS, TESTS = "processes.jsonl", "processes.jsonl.tests"

TRACE = "/jax/core/compile/jaxpr_trace_duration"
LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
COMPILE = "/jax/core/compile/backend_compile_duration"
MISS = "/jax/compilation_cache/cache_misses"
HIT = "/jax/compilation_cache/cache_hits"


# ------------------------------------------------------------------------------- pytest plugin


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
  """Times one test (setup, call and teardown) in the worker that runs it."""
  log = os.environ.get(ENV)
  t0, c0 = time.time(), os.times()
  yield
  if not log:
    return
  c1 = os.times()
  record = {
    "test": item.nodeid.split("@")[0],  # xdist's loadgroup suffix
    "worker": os.environ.get("PYTEST_XDIST_WORKER"),
    "start": t0,
    "end": time.time(),
    "cpu": (c1.user + c1.system) - (c0.user + c0.system),
    "child_cpu": (c1.children_user + c1.children_system) - (c0.children_user + c0.children_system),
  }
  with open(log + ".tests", "a", encoding="utf-8") as f:
    f.write(json.dumps(record) + "\n")


# ----------------------------------------------------------------------------------------- run


def run(out: pathlib.Path, pytest_args: list[str]) -> int:
  out.mkdir(parents=True, exist_ok=True)
  for name in (PROCS, TESTS):
    (out / name).unlink(missing_ok=True)
  env = dict(os.environ)
  env[ENV] = str(out / PROCS)
  env["PYTHONPATH"] = os.pathsep.join(
    [str(SITE), str(ROOT), *filter(None, [env.get("PYTHONPATH")])]
  )
  cmd = [sys.executable, "-m", "pytest", "-p", "tools.suite_profile", *pytest_args]
  print("running:", " ".join(cmd), flush=True)
  rc = subprocess.call(cmd, cwd=ROOT, env=env)
  print(f"profile in {out}: python tools/suite_profile.py report {out}", flush=True)
  return rc


# -------------------------------------------------------------------------------------- report


def _read(path: pathlib.Path) -> list[dict]:
  if not path.is_file():
    raise SystemExit(f"error: {path} is missing: make it with `suite_profile.py run --out DIR`")
  return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def load(out: pathlib.Path) -> tuple[list[dict], list[dict], dict[str, collections.Counter]]:
  """The tests' records, the processes' records and, per test id, its JAX event totals (own
  process and children: names prefixed by "child:" for the latter), "child_reported_cpu"
  included."""
  tests, procs = _read(out / TESTS), _read(out / PROCS)
  events: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
  for p in procs:
    child = "child:" if p["parent_test"] else ""
    for test, d in p["events"].items():
      for name, value in d.items():
        if name != "named":
          events[test][child + name] += value
    if child:
      events[p["parent_test"].rsplit(" (", 1)[0]]["child_reported_cpu"] += p["cpu"]
  return tests, procs, events


def _jax(c: collections.Counter, name: str) -> float:
  return c[name] + c["child:" + name]


COLUMNS = "wall  cpu  child  trace  lower  compile  n_comp  miss  hit"


def _row(wall, cpu, child, c) -> str:
  return (
    f"{wall:6.0f} {cpu:5.0f} {child:5.0f} {_jax(c, TRACE):6.0f} {_jax(c, LOWER):6.0f} "
    f"{_jax(c, COMPILE):8.0f} {_jax(c, COMPILE + ':n'):7.0f} {_jax(c, MISS + ':n'):5.0f} "
    f"{_jax(c, HIT + ':n'):4.0f}"
  )


def report(out: pathlib.Path, top: int) -> str:
  tests, procs, events = load(out)
  if not tests:
    raise SystemExit(f"error: {out / TESTS} has no tests")
  lines = [f"{len(tests)} tests; seconds ({COLUMNS}: JAX's, subprocesses included)", ""]
  files: dict[str, list] = collections.defaultdict(lambda: [0.0, 0.0, 0.0, collections.Counter()])
  for t in tests:
    f = files[t["test"].split("::")[0]]
    f[0] += t["end"] - t["start"]
    f[1] += t["cpu"]
    f[2] += t["child_cpu"]
    f[3].update(events.get(t["test"], {}))
  lines.append(f"per file: {COLUMNS}")
  for name, (wall, cpu, child, c) in sorted(files.items(), key=lambda kv: -kv[1][0])[:top]:
    lines.append(f"{_row(wall, cpu, child, c)}  {name}")
  lines += ["", f"per test: {COLUMNS}"]
  for t in sorted(tests, key=lambda t: t["start"] - t["end"])[:top]:
    c = events.get(t["test"], collections.Counter())
    lines.append(f"{_row(t['end'] - t['start'], t['cpu'], t['child_cpu'], c)}  {t['test']}")
  # Totals per kind of process, and how busy each worker was.
  kinds: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
  named: collections.Counter = collections.Counter()
  count: collections.Counter = collections.Counter()
  for p in procs:
    kind = "subprocesses" if p["parent_test"] else ("workers" if p["worker"] else "pytest")
    kinds[kind]["cpu"] += p["cpu"]
    kinds[kind]["processes"] += 1
    for d in p["events"].values():
      for name in (TRACE, LOWER, COMPILE, MISS + ":n", HIT + ":n", COMPILE + ":n"):
        kinds[kind][name] += d.get(name, 0)
      for fun, seconds in d.get("named", []):
        named[fun] += seconds
        count[fun] += 1
  lines += [
    "",
    "per kind of process: processes, CPU s, trace s, lower s, compile s, compiles, miss, hit",
  ]
  for kind, c in sorted(kinds.items()):
    lines.append(
      f"  {kind:13s} {c['processes']:5.0f} {c['cpu']:7.0f} {c[TRACE]:6.0f} {c[LOWER]:6.0f} "
      f"{c[COMPILE]:7.0f} {c[COMPILE + ':n']:7.0f} {c[MISS + ':n']:5.0f} {c[HIT + ':n']:5.0f}"
    )
  start = min(t["start"] for t in tests)
  span = max(t["end"] for t in tests) - start
  lines += ["", f"span {span:.0f} s; per worker: tests, busy s, last end s"]
  by_worker = collections.defaultdict(list)
  for t in tests:
    by_worker[t["worker"] or "main"].append(t)
  for w, ts in sorted(by_worker.items()):
    busy = sum(t["end"] - t["start"] for t in ts)
    lines.append(f"  {w}: {len(ts)}, {busy:.0f}, {max(t['end'] for t in ts) - start:.0f}")
  lines += ["", "functions with the most compile seconds (compiles of >= 0.2 s): s, n, name"]
  for fun, seconds in named.most_common(top):
    lines.append(f"  {seconds:7.1f} {count[fun]:4d}  {fun}")
  return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
  argv = list(sys.argv[1:] if argv is None else argv)
  rest: list[str] = []
  if "--" in argv:
    i = argv.index("--")
    argv, rest = argv[:i], argv[i + 1 :]
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  sub = parser.add_subparsers(dest="mode", required=True)
  r = sub.add_parser("run", help="run pytest (arguments after --) with the profile")
  r.add_argument("--out", required=True, type=pathlib.Path)
  p = sub.add_parser("report", help="print the tables of a profile")
  p.add_argument("out", type=pathlib.Path)
  p.add_argument("--top", type=int, default=40)
  args = parser.parse_args(argv)
  if args.mode == "run":
    return run(args.out, rest)
  if rest:
    parser.error("report takes no pytest arguments")
  if args.top < 1:
    parser.error("--top must be at least 1")
  print(report(args.out, args.top))
  return 0


if __name__ == "__main__":
  sys.exit(main())

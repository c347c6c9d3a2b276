"""Start-up hook of `tools/suite_profile.py`: with CAMREP_SUITE_PROFILE set, every Python process
of the profiled test run (pytest's workers and the subprocesses tests start) records JAX's
compile events per test and appends one JSON line to that file when it exits.

JAX reports each jit's trace, lowering and XLA compile through `jax.monitoring` listeners (with
the compiled function's name), and the persistent compilation cache its hits and misses; the
listeners are registered when `jax._src.monitoring` is first imported, so a process that never
imports JAX pays nothing. Events are keyed by PYTEST_CURRENT_TEST, which pytest sets in the worker
while a test runs and which a subprocess inherits. A process killed by a signal (the resume
tests' children) writes nothing."""

import atexit
import importlib.util
import json
import os
import sys
import time

_LOG = os.environ.get("CAMREP_SUITE_PROFILE")
# Backend compiles (or cache reads) at least this long are listed by function name.
_NAMED_S = 0.2


def _install(log: str) -> None:
  acc: dict = {}
  t0 = time.time()

  def key() -> str:
    return os.environ.get("PYTEST_CURRENT_TEST", "-").rsplit(" (", 1)[0]

  def on_duration(event, duration, **kw):
    d = acc.setdefault(key(), {})
    d[event] = d.get(event, 0.0) + duration
    d[event + ":n"] = d.get(event + ":n", 0) + 1
    if event.endswith("backend_compile_duration") and duration >= _NAMED_S:
      d.setdefault("named", []).append([kw.get("fun_name"), round(duration, 3)])

  def on_event(event, **kw):
    d = acc.setdefault(key(), {})
    d[event + ":n"] = d.get(event + ":n", 0) + 1

  class Hook:
    def find_spec(self, name, path, target=None):
      if name != "jax._src.monitoring":
        return None
      sys.meta_path.remove(self)
      spec = importlib.util.find_spec(name)
      run = spec.loader.exec_module

      def exec_module(module):
        run(module)
        module.register_event_duration_secs_listener(on_duration)
        module.register_event_listener(on_event)

      spec.loader.exec_module = exec_module
      return spec

  sys.meta_path.insert(0, Hook())

  def dump():
    t = os.times()
    record = {
      "pid": os.getpid(),
      "worker": os.environ.get("PYTEST_XDIST_WORKER"),
      "parent_test": os.environ.get("PYTEST_CURRENT_TEST"),
      "argv": sys.argv[:4],
      "cpu": t.user + t.system,
      "wall": time.time() - t0,
      "events": acc,
    }
    try:
      with open(log, "a", encoding="utf-8") as f:
        f.write(json.dumps(record) + "\n")
    except OSError:
      pass

  atexit.register(dump)


if _LOG:
  _install(_LOG)

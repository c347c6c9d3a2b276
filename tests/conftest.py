"""pytest configuration: make the repository root importable as `tests.*`, shared fixtures, and
one persistent XLA compilation cache for the whole test session."""

import gc
import os

import jax
import pytest

from camrep.runtime import xla_cpu

# Set CAMREP_TEST_JAX_CACHE to a directory to keep the cache between sessions, or to 0 to turn
# it off; by default it lives in this session's pytest base directory (so a run starts cold,
# and pytest removes it with its other old base directories).
_CACHE_ENV = "CAMREP_TEST_JAX_CACHE"

# Set to 0 to compile every test with XLA's optimisations on, as in production; the default is 1.
_FAST_ENV = "JAX_DISABLE_MOST_OPTIMIZATIONS"

# XLA:CPU's loop emitters instead of its fusion emitters: the same programs, compiled in about
# half the time (the `gqn.py:smoke` train step: 29 s -> 14 s).
EMITTERS_FLAG = "--xla_cpu_use_fusion_emitters=false"
# Each program's LLVM code generated as one module, not split into parts for a thread pool: the
# same code and numbers; on 2 cores, both busy with tests, the parts' overhead is CPU lost
# (a cold `gqn.py:smoke` run 17.1 -> 14.6 s user; BUILD_NOTES, "Tests and CI").
CODEGEN_FLAG = "--xla_cpu_parallel_codegen_split_count=1"
# Added to XLA_FLAGS, each unless the variable names its option already, or
# `JAX_DISABLE_MOST_OPTIMIZATIONS=0`.
COMPILE_FLAGS = (EMITTERS_FLAG, CODEGEN_FLAG)


@pytest.hookimpl(trylast=True)
def pytest_configure(config):
  """Compiles with most XLA optimisations off, and turns on JAX's persistent compilation
  cache; both reach the xdist workers and every subprocess the tests start (`python -m
  camrep.main` runs) through the environment.

  Nearly every test runs a tiny model once, so XLA's compile dominates its time; the
  optimisation passes multiply that compile several-fold and change the numbers only by
  round-off. Tests that need production compilation carry `@pytest.mark.optimized` (see
  pyproject.toml); `_compile_as_marked` turns the optimisations back on for them and their
  subprocesses.

  XLA_FLAGS gets `COMPILE_FLAGS` (XLA:CPU's compile is most of a test's time; the loop emitters
  roughly halve it). XLA reads the variable once, when the process's backend starts, so the
  `optimized` mark cannot undo them in the test's own process (its subprocesses go without them).

  Dozens of tests compile the same smoke-size steps, many in fresh processes; a cache hit skips
  XLA's compile (a `gqn.py:smoke` run: 16.7 s cold, 7.2 s warm) and returns the same executable,
  so results are bit-identical (the resume and multi-process tests compare them). The key covers
  the program, the devices and the compile options (`jax_disable_most_optimizations` included).
  """
  os.environ.setdefault(_FAST_ENV, "1")
  fast = os.environ[_FAST_ENV] != "0"
  jax.config.update("jax_disable_most_optimizations", fast)
  if fast:  # read when the backend starts
    os.environ["XLA_FLAGS"] = xla_cpu.with_flags(os.environ.get("XLA_FLAGS", ""), *COMPILE_FLAGS)
  where = os.environ.get(_CACHE_ENV)
  if where == "0":
    return
  if not where:
    factory = getattr(config, "_tmp_path_factory", None)  # pytest's tmpdir plugin
    if factory is None:
      return
    base = factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
      base = base.parent  # this session's directory, common to its workers
    where = str(base / "jax_compilation_cache")
  settings = {
    "jax_compilation_cache_dir": where,
    # Programs that compile in under 0.1 s (most of the ~9,000 a suite compiles: eager ops,
    # small jits) are not written: writing and reading one costs about what compiling it does
    # (test_models + test_regressor + test_lie, -n 0: 255 -> 241 s user CPU).
    "jax_persistent_cache_min_compile_time_secs": 0.1,
    "jax_persistent_cache_min_entry_size_bytes": -1,
  }
  for name, value in settings.items():
    jax.config.update(name, value)
    os.environ[name.upper()] = str(value)


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
  """Drops JAX's in-memory compilation caches after each test module.

  Every executable XLA:CPU compiles keeps its JIT code mapped while a cache holds it; an xdist
  worker that ran ~900 tests held ~46,500 memory maps, near Linux's `vm.max_map_count` (65,530),
  and twice died inside XLA (an abort, a segfault) when a late test compiled a large step. A
  module that needs a program again recompiles it, mostly from the persistent cache above."""
  yield
  jax.clear_caches()
  gc.collect()


@pytest.fixture(autouse=True)
def _compile_as_marked(request, monkeypatch):
  """Turns XLA's optimisations on for a test marked `optimized` and for the subprocesses it
  starts (see `pytest_configure`); restored afterwards."""
  if request.node.get_closest_marker("optimized") is None:
    yield
    return
  old = jax.config.read("jax_disable_most_optimizations")
  jax.config.update("jax_disable_most_optimizations", False)
  monkeypatch.setenv(_FAST_ENV, "0")
  flags = os.environ.get("XLA_FLAGS", "").split()
  monkeypatch.setenv("XLA_FLAGS", " ".join(f for f in flags if f not in COMPILE_FLAGS))
  try:
    yield
  finally:
    jax.config.update("jax_disable_most_optimizations", old)


@pytest.fixture(scope="module")
def fast_compile():
  """Turns off most XLA optimisations for one module, whatever the session's setting (the
  suite's default already does unless `JAX_DISABLE_MOST_OPTIMIZATIONS=0`); restored afterwards.
  Use with `pytestmark = pytest.mark.usefixtures("fast_compile")`."""
  old = jax.config.read("jax_disable_most_optimizations")
  jax.config.update("jax_disable_most_optimizations", True)
  yield
  jax.config.update("jax_disable_most_optimizations", old)


def _shared_run(tmp_path_factory, name: str, train) -> str:
  """A run trained once per test session and shared by every xdist worker: the first to ask
  calls `train(workdir)` under a file lock; the others wait and reuse its workdir."""
  import fcntl

  base = tmp_path_factory.getbasetemp()
  if os.environ.get("PYTEST_XDIST_WORKER"):
    base = base.parent  # this session's directory, common to its workers
  root = base / f"shared_{name}"
  root.mkdir(exist_ok=True)
  workdir, done = root / "run", root / "done"
  with open(root / "lock", "w") as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)
    try:
      if not done.exists():
        train(workdir)
        done.write_text("ok")
    finally:
      fcntl.flock(lock, fcntl.LOCK_UN)
  return str(workdir)


@pytest.fixture(scope="session")
def gqn_smoke_run(tmp_path_factory):
  """A finished `configs/gqn.py:smoke` run (4 steps: checkpoints at 2 and 4, eval at 4), trained
  once per test session and shared by every xdist worker (`_shared_run`). Read-only: copy it
  (shutil.copytree) to change it."""
  from camrep.configs import gqn
  from camrep.synthesis import train

  def run(workdir):
    old = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", True)
    try:
      train.train_and_evaluate(gqn.get_config("smoke"), str(workdir))
    finally:
      jax.config.update("jax_disable_most_optimizations", old)

  return _shared_run(tmp_path_factory, "gqn_smoke", run)


# The car's shared run: `shapenet_car:smoke` for 2 steps, evaluated at step 2 on one scene.
CAR_SMOKE_FLAGS = (
  "--config=shapenet_car:smoke",
  "--config.total_steps=2",
  "--config.eval_every_steps=2",
  "--config.evals.num_scenes=1",
)


@pytest.fixture(scope="session")
def car_smoke_run(tmp_path_factory):
  """A finished car view-synthesis run (`CAR_SMOKE_FLAGS`), trained once per test session by
  the command line in a fresh process (`python -m camrep.main`, as a user runs it; an in-process
  compile of this step, late in a whole-suite run, once died inside XLA: BUILD_NOTES "A crash in
  the CI rehearsal") and shared by every xdist worker (`_shared_run`). Read-only."""
  import subprocess
  import sys

  def run(workdir):
    r = subprocess.run(
      [sys.executable, "-m", "camrep.main", *CAR_SMOKE_FLAGS, f"--workdir={workdir}"],
      capture_output=True,
      text=True,
      cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
      env={**os.environ, _FAST_ENV: "1"},
      timeout=600,
    )
    assert r.returncode == 0, r.stderr[-3000:]

  return _shared_run(tmp_path_factory, "car_smoke", run)

"""pytest configuration: make the repository root importable as `tests.*`, shared fixtures."""

import jax
import pytest


@pytest.fixture(scope="module")
def fast_compile():
  """Turns off most XLA optimisations for one module (compile time dominates its tiny models,
  and they would double it); restored afterwards. Use with
  `pytestmark = pytest.mark.usefixtures("fast_compile")`."""
  old = jax.config.read("jax_disable_most_optimizations")
  jax.config.update("jax_disable_most_optimizations", True)
  yield
  jax.config.update("jax_disable_most_optimizations", old)


@pytest.fixture(scope="session")
def gqn_smoke_run(tmp_path_factory):
  """A finished `configs/gqn.py:smoke` run (4 steps: checkpoints at 2 and 4, eval at 4), trained
  once per test session and shared by every xdist worker (the first to ask trains it under a
  file lock; the others wait and reuse it). Read-only: copy it (shutil.copytree) to change it."""
  import fcntl
  import os

  from camrep.synthesis import train
  from configs import gqn

  base = tmp_path_factory.getbasetemp()
  if os.environ.get("PYTEST_XDIST_WORKER"):
    base = base.parent  # this session's directory, common to its workers
  root = base / "shared_gqn_smoke"
  root.mkdir(exist_ok=True)
  workdir, done = root / "run", root / "done"
  with open(root / "lock", "w") as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)
    try:
      if not done.exists():
        old = jax.config.read("jax_disable_most_optimizations")
        jax.config.update("jax_disable_most_optimizations", True)
        try:
          train.train_and_evaluate(gqn.get_config("smoke"), str(workdir))
        finally:
          jax.config.update("jax_disable_most_optimizations", old)
        done.write_text("ok")
    finally:
      fcntl.flock(lock, fcntl.LOCK_UN)
  return str(workdir)

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

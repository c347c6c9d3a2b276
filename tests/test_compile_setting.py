"""The suite's compile setting (tests/conftest.py): most XLA optimisations off, XLA:CPU's loop
emitters and unsplit code generation, in the workers and, through JAX_DISABLE_MOST_OPTIMIZATIONS
and XLA_FLAGS, in the subprocesses they start; a test marked `optimized` compiles as in
production, its subprocesses too."""

from __future__ import annotations

import os

import jax
import pytest

from tests import conftest
from tests.utils import one_device_env


def test_the_suite_compiles_with_most_optimisations_off():
  if os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] == "0":
    pytest.skip("JAX_DISABLE_MOST_OPTIMIZATIONS=0: this run compiles as in production")
  assert jax.config.read("jax_disable_most_optimizations") is True
  assert set(conftest.COMPILE_FLAGS) <= set(os.environ["XLA_FLAGS"].split())


def test_a_one_device_subprocess_keeps_the_compile_options(monkeypatch):
  flags = " ".join(("--xla_force_host_platform_device_count=2", *conftest.COMPILE_FLAGS))
  monkeypatch.setenv("XLA_FLAGS", flags)
  env = one_device_env()
  assert env["XLA_FLAGS"] == " ".join(conftest.COMPILE_FLAGS)
  assert env["JAX_DISABLE_MOST_OPTIMIZATIONS"] == "1"


@pytest.mark.optimized
def test_a_test_marked_optimized_compiles_as_in_production():
  assert jax.config.read("jax_disable_most_optimizations") is False
  assert os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] == "0"
  assert not set(conftest.COMPILE_FLAGS) & set(os.environ.get("XLA_FLAGS", "").split())

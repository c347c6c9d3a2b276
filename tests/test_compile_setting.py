"""The suite's compile setting (tests/conftest.py): most XLA optimisations off, in the workers
and, through JAX_DISABLE_MOST_OPTIMIZATIONS, in the subprocesses they start; a test marked
`optimized` compiles as in production, its subprocesses too."""

from __future__ import annotations

import os

import jax
import pytest


def test_the_suite_compiles_with_most_optimisations_off():
  if os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] == "0":
    pytest.skip("JAX_DISABLE_MOST_OPTIMIZATIONS=0: this run compiles as in production")
  assert jax.config.read("jax_disable_most_optimizations") is True


@pytest.mark.optimized
def test_a_test_marked_optimized_compiles_as_in_production():
  assert jax.config.read("jax_disable_most_optimizations") is False
  assert os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] == "0"

"""Shared test helpers: float64 context, samplers, closeness asserts (in the manner of jaxlie)."""

from __future__ import annotations

import contextlib
import functools
import os
import zlib

import jax
import numpy as np
import pytest

from camrep import lie

BATCH_SHAPES = ((), (1,), (3, 1, 2))
REGIMES = ("normal", "large", "near_zero")
# The batch shape that the fast tier (`-m "not slow"`) runs (the most general: several leading
# axes, one of size 1); the whole suite (CI) runs every one of BATCH_SHAPES.
FAST_BATCH_SHAPE = (3, 1, 2)


def slow_except(values, fast) -> list:
  """`values` for `pytest.mark.parametrize`, those not in `fast` marked slow: the fast tier runs
  the `fast` cases of a parametrised test, the whole suite every case (ids unchanged)."""
  return [v if v in fast else pytest.param(v, marks=pytest.mark.slow) for v in values]


@contextlib.contextmanager
def x64():
  """Run in float64 without touching other test modules (jax.enable_x64 is a context)."""
  with jax.enable_x64(True):
    yield


def sample_generator(rng: np.random.Generator, batch: tuple[int, ...], s: int, regime: str):
  """Random skew-symmetric blocks (*batch, s, s) in float64.

  regime: "normal" (spectral norm ~1), "large" (~5), "near_zero" (~1e-7).
  """
  params = rng.normal(size=(*batch, lie.num_skew_params(s)))
  B = np.asarray(lie.skew(params, block_size=s), np.float64)
  norm = (
    np.linalg.norm(B, ord=2, axis=(-2, -1), keepdims=True) if B.ndim > 2 else np.linalg.norm(B, 2)
  )
  scale = {"normal": 1.0, "large": 5.0, "near_zero": 1e-7}[regime]
  return B / np.maximum(norm, 1e-30) * scale


def stable_seed(*parts) -> int:
  """A 32-bit seed from `parts` (strings, numbers, tuples) that is the same in every process.

  Python's `hash` of a string is salted per process (PYTHONHASHSEED), so a seed drawn from it
  changes from run to run and a failure cannot be replayed."""
  return zlib.crc32(repr(parts).encode())


def assert_close(a, b, *, atol=1e-8, rtol=1e-8):
  """assert_allclose that also fails on any NaN/inf."""
  a, b = np.asarray(a), np.asarray(b)
  assert np.all(np.isfinite(a)), "non-finite values in result"
  assert np.all(np.isfinite(b)), "non-finite values in reference"
  np.testing.assert_allclose(a, b, atol=atol, rtol=rtol)


def jac_numerical(f, x, eps=1e-6):
  """Central-difference Jacobian of f: R^n -> R^m at x (float64), shape (m, n)."""
  x = np.asarray(x, np.float64)
  cols = []
  for i in range(x.size):
    dx = np.zeros(x.size)
    dx[i] = eps
    dx = dx.reshape(x.shape)
    cols.append((np.asarray(f(x + dx)) - np.asarray(f(x - dx))).ravel() / (2 * eps))
  return np.stack(cols, -1)


def general_lie_test(f):
  """Parametrise a test over exp methods x batch shapes x sampling regimes, run in float64 (the
  fast tier: every method and regime at FAST_BATCH_SHAPE)."""

  @pytest.mark.parametrize("method", lie.EXP_METHODS)
  @pytest.mark.parametrize("batch", slow_except(BATCH_SHAPES, [FAST_BATCH_SHAPE]))
  @pytest.mark.parametrize("regime", REGIMES)
  @functools.wraps(f)
  def wrapper(method, batch, regime):
    with x64():
      f(method=method, batch=batch, regime=regime)

  return wrapper


def snapshot(workdir) -> dict[str, bytes]:
  """Every file of a directory tree, relative path -> bytes (directories as "name/" -> b"")."""

  out = {}
  for root, dirs, files in os.walk(workdir):
    for d in dirs:
      out[os.path.relpath(os.path.join(root, d), workdir) + "/"] = b""
    for f in files:
      p = os.path.join(root, f)
      with open(p, "rb") as fh:
        out[os.path.relpath(p, workdir)] = fh.read()
  return out


def regression_hparams(setting: str, representation: str):
  """The `learner.HyperParams` that configs/regression.py gives (setting, representation)."""
  from camrep import pose_encodings
  from camrep.configs import regression as regression_config
  from camrep.regression import learner

  c = regression_config.get_config(f"{setting},smoke")
  c.representation = representation
  return learner.resolve_hparams(c, pose_encodings.get(representation))


def one_device_env() -> dict[str, str]:
  """This process's environment for a subprocess on one host device: XLA_FLAGS without a forced
  device count (the suite's other compile options kept), most XLA optimisations off."""
  env = dict(os.environ)
  flags = env.pop("XLA_FLAGS", "").split()
  kept = [f for f in flags if not f.startswith("--xla_force_host_platform_device_count")]
  if kept:
    env["XLA_FLAGS"] = " ".join(kept)
  env["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"
  return env

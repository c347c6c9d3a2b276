"""XLA:CPU's process-wide options: how many host devices a CPU shows and whether each runs its
programs on a thread pool, set through XLA_FLAGS, which XLA reads once, when JAX's backend starts.

On a CPU one process shows one device by default, its programs' operations spread over a thread
pool of every core. The small convolutions of a pose regressor use that pool poorly: on 2 cores
two one-thread programs did 2.0x (car) and 1.33x (7-Scenes) the steps of one program on both, and
a regression grid's members spread over two one-thread host devices of one process 1.56x and 1.28x
its members' steps trained alone (`camrep.bench.regression_grid --host_devices=2`; BUILD_NOTES.md,
"The comparison"). GPU programs are unchanged: the options name the host platform only.
"""

from __future__ import annotations

import math
import os
from collections.abc import MutableMapping

ONE_THREAD = "--xla_cpu_multi_thread_eigen"
"""=false: each XLA:CPU program runs on its own thread, not on the process's pool."""
DEVICE_COUNT = "--xla_force_host_platform_device_count"
"""=N: the CPU shows N host devices (`jax.local_devices()` on the CPU backend)."""


def with_flags(flags: str, *options: str) -> str:
  """XLA_FLAGS `flags` with each "--name=value" of `options` added unless `flags` names its option
  already (a user's choice wins)."""
  for option in options:
    if option.split("=")[0] not in flags:
      flags = f"{flags} {option}".strip()
  return flags


def usable_cores(cpu_max: str = "/sys/fs/cgroup/cpu.max") -> int:
  """The cores this process may run on: its CPU affinity where the OS says (else every core), at
  most its cgroup's CPU quota (`cpu_max`, "QUOTA PERIOD" or "max PERIOD"; a container's limit)."""
  if hasattr(os, "sched_getaffinity"):
    cores = len(os.sched_getaffinity(0))
  else:
    cores = os.cpu_count() or 1
  try:
    with open(cpu_max) as f:
      quota, period = f.read().split()[:2]
    if quota != "max":
      cores = min(cores, math.ceil(int(quota) / int(period)))
  except (OSError, ValueError):
    pass
  return max(1, cores)


def one_thread(environ: MutableMapping[str, str] = os.environ) -> None:
  """Runs each of the process's XLA:CPU programs on one thread (`ONE_THREAD`=false), unless
  XLA_FLAGS name it. Only before JAX's backend starts (no effect after)."""
  environ["XLA_FLAGS"] = with_flags(environ.get("XLA_FLAGS", ""), f"{ONE_THREAD}=false")


def host_devices(n: int, environ: MutableMapping[str, str] = os.environ) -> None:
  """Shows `n` > 1 host devices, each running its programs on one thread (`DEVICE_COUNT`=n,
  `ONE_THREAD`=false), each unless XLA_FLAGS name it; n = 1 changes nothing (one device on the
  pool). Only before JAX's backend starts (no effect after).

  Raises:
    ValueError: n < 1.
  """
  if n < 1:
    raise ValueError(f"host devices must be >= 1, got {n}")
  if n > 1:
    flags = environ.get("XLA_FLAGS", "")
    environ["XLA_FLAGS"] = with_flags(flags, f"{DEVICE_COUNT}={n}", f"{ONE_THREAD}=false")

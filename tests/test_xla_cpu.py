"""Tests of XLA:CPU's process options (camrep.runtime.xla_cpu): flags added unless named, and a
CPU shown as host devices in a fresh process."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from camrep.runtime import xla_cpu

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_flags_are_added_unless_named():
  assert xla_cpu.with_flags("", "--a=1") == "--a=1"
  assert xla_cpu.with_flags("--x=2", "--a=1", "--b=0") == "--x=2 --a=1 --b=0"
  assert xla_cpu.with_flags("--a=3", "--a=1") == "--a=3"  # the user's choice wins
  env = {}
  xla_cpu.host_devices(1, env)
  assert env == {}  # one device on the thread pool: unchanged
  xla_cpu.host_devices(4, env)
  assert env["XLA_FLAGS"] == (
    "--xla_force_host_platform_device_count=4 --xla_cpu_multi_thread_eigen=false"
  )
  env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
  xla_cpu.host_devices(8, env)
  assert env["XLA_FLAGS"].split() == [
    "--xla_force_host_platform_device_count=2", "--xla_cpu_multi_thread_eigen=false",
  ]  # fmt: skip
  env = {"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=true"}
  xla_cpu.one_thread(env)
  assert env["XLA_FLAGS"] == "--xla_cpu_multi_thread_eigen=true"
  with pytest.raises(ValueError, match="host devices must be >= 1"):
    xla_cpu.host_devices(0, {})
  assert 1 <= xla_cpu.usable_cores() <= (os.cpu_count() or 1)


def test_usable_cores_follow_the_cgroup_quota(tmp_path):
  cpu_max = tmp_path / "cpu.max"
  cores = xla_cpu.usable_cores(str(tmp_path / "none"))  # no cgroup file: the affinity
  cpu_max.write_text("max 100000\n")
  assert xla_cpu.usable_cores(str(cpu_max)) == cores
  cpu_max.write_text("150000 100000\n")  # 1.5 cores
  assert xla_cpu.usable_cores(str(cpu_max)) == min(cores, 2)
  cpu_max.write_text("50000 100000\n")
  assert xla_cpu.usable_cores(str(cpu_max)) == 1


def test_a_fresh_process_shows_the_host_devices_asked_for():
  """Set before JAX's backend starts, the options take: two CPU devices."""
  code = (
    "from camrep.runtime import xla_cpu; xla_cpu.host_devices(2)\n"
    "import jax; print(len(jax.local_devices()), jax.default_backend())"
  )
  env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
  out = subprocess.run(
    [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True
  )
  assert out.stdout.split() == ["2", "cpu"]

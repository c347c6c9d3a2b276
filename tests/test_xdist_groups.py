"""The suite's `--dist loadgroup` (pyproject.toml) really groups: the tests of one `xdist_group`
run on one worker, so that a module's shared trained runs (module or session fixtures) are built
once. pytest 9.2 silently broke this (pytest-dev/pytest-xdist#1386): every module then built its
runs once per worker and nothing failed."""

import subprocess
import sys

GROUPED = """
import os

import pytest

pytestmark = pytest.mark.xdist_group("one")


@pytest.mark.parametrize("i", range(6))
def test_grouped(i, tmp_path_factory):
  out = tmp_path_factory.getbasetemp().parent / f"worker_{i}"
  out.write_text(os.environ["PYTEST_XDIST_WORKER"])


@pytest.mark.parametrize("i", range(6))
def test_free(i):
  pass
"""


def test_tests_of_one_group_run_on_one_worker(tmp_path):
  (tmp_path / "test_grouped.py").write_text(GROUPED)
  (tmp_path / "pytest.ini").write_text("[pytest]\naddopts = --dist loadgroup\n")
  base = tmp_path / "base"
  r = subprocess.run(
    [sys.executable, "-m", "pytest", "-q", "-n", "2", "-p", "no:cacheprovider"]
    + [f"--basetemp={base}", str(tmp_path / "test_grouped.py")],
    cwd=tmp_path,
    capture_output=True,
    text=True,
    timeout=300,
  )
  assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
  ran = sorted(base.glob("worker_*"))
  assert len(ran) == 6, ran
  workers = {p.read_text() for p in ran}
  assert len(workers) == 1, f"one group ran on workers {sorted(workers)}"

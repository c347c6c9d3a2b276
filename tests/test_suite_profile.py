"""tools/suite_profile.py: `run` profiles a pytest session (its workers and the subprocesses its
tests start) and `report` prints where the time went; both modes at smoke size, with their
errors."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys

import pytest

from tools import suite_profile

pytestmark = pytest.mark.slow

ROOT = pathlib.Path(__file__).resolve().parent.parent

TESTS = """
import subprocess
import sys

import jax
import jax.numpy as jnp


def test_jits_here():
  assert float(jax.jit(lambda x: jnp.sin(x) * 2)(jnp.ones(3))[0]) > 0


def test_jits_in_a_child():
  code = "import jax, jax.numpy as jnp; print(jax.jit(lambda x: x + 1)(jnp.ones(2)))"
  subprocess.run([sys.executable, "-c", code], check=True)
"""


def _tool(*argv: str) -> subprocess.CompletedProcess:
  return subprocess.run(
    [sys.executable, str(ROOT / "tools" / "suite_profile.py"), *argv],
    cwd=ROOT,
    capture_output=True,
    text=True,
    timeout=300,
  )


def _session(tmp_path: pathlib.Path, body: str) -> tuple[subprocess.CompletedProcess, pathlib.Path]:
  (tmp_path / "test_small.py").write_text(body)
  (tmp_path / "pytest.ini").write_text("[pytest]\n")
  out = tmp_path / "prof"
  r = _tool(
    "run", "--out", str(out), "--",
    "-q", "-n", "2", "-p", "no:cacheprovider", "-c", str(tmp_path / "pytest.ini"),
    "--rootdir", str(tmp_path), str(tmp_path / "test_small.py"),
  )  # fmt: skip
  return r, out


def test_run_records_workers_and_children_and_report_prints_them(tmp_path):
  r, out = _session(tmp_path, TESTS)
  assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
  tests = [json.loads(line) for line in (out / suite_profile.TESTS).read_text().splitlines()]
  assert sorted(t["test"].split("::")[1] for t in tests) == [
    "test_jits_here",
    "test_jits_in_a_child",
  ]
  assert {t["worker"] for t in tests} <= {"gw0", "gw1"}
  _, _, events = suite_profile.load(out)
  here = next(t["test"] for t in tests if t["test"].endswith("test_jits_here"))
  child = next(t["test"] for t in tests if t["test"].endswith("test_jits_in_a_child"))
  assert events[here][suite_profile.COMPILE + ":n"] >= 1  # the worker's own jit
  assert events[child]["child:" + suite_profile.COMPILE + ":n"] >= 1  # the child's, its parent's
  assert events[child]["child_reported_cpu"] > 0
  rep = _tool("report", str(out), "--top", "5")
  assert rep.returncode == 0, rep.stderr
  text = rep.stdout
  assert "2 tests" in text and "test_small.py" in text and here in text and child in text
  assert "subprocesses" in text and "workers" in text and "gw" in text


def test_run_exits_with_pytests_status_and_report_refuses_what_it_cannot_read(tmp_path):
  r, out = _session(tmp_path, "def test_fails():\n  assert False\n")
  assert r.returncode == 1, r.stdout[-2000:] + r.stderr[-2000:]
  assert len((out / suite_profile.TESTS).read_text().splitlines()) == 1
  missing = _tool("report", str(tmp_path / "nowhere"))
  assert missing.returncode != 0 and "is missing" in missing.stderr
  assert _tool("report", str(out), "--top", "0").returncode == 2
  assert _tool("report", str(out), "--", "-q").returncode == 2
  assert _tool("run").returncode == 2  # --out is required

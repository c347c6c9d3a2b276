"""camrep after a plain (not editable) install: build a wheel from the checkout's files, install it
into a fresh virtual environment outside the checkout, then, from a directory outside the
checkout, train `gqn:smoke` by name and execute the quickstart notebook (the suite's one run of
it: tests/test_notebook.py's checks of a fresh run).

The new environment borrows the running interpreter's site-packages for the third-party
dependencies (a .pth line, so nothing is downloaded); camrep itself comes only from the wheel.
"""

from __future__ import annotations

import json
import os
import pathlib
import pickle
import shutil
import site
import subprocess
import sys
import venv

import pytest

from tests import test_notebook
from tests.utils import one_device_env

ROOT = pathlib.Path(__file__).resolve().parents[1]

# One worker for the module: the wheel and its environment (a module fixture) are built once.
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("wheel")]


def _offline_build_possible() -> bool:
  """setuptools >= 70.1 builds wheels itself (no `wheel` package): no build isolation needed."""
  try:
    import setuptools
  except ImportError:
    return False
  return tuple(int(p) for p in setuptools.__version__.split(".")[:2]) >= (70, 1)


def build_wheel(out: pathlib.Path) -> pathlib.Path:
  """A wheel of the checkout's pyproject.toml, README and camrep/ (copied: no build/ left here)."""
  src = out / "src"
  shutil.copytree(
    ROOT / "camrep", src / "camrep", ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
  )
  for name in ("pyproject.toml", "README.md", "LICENSE"):
    if (ROOT / name).exists():
      shutil.copy(ROOT / name, src / name)
  cmd = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(out / "dist")]
  if _offline_build_possible():
    cmd.append("--no-build-isolation")
  subprocess.run(
    [*cmd, str(src)], env=_env(), check=True, capture_output=True, text=True, timeout=300
  )
  (wheel,) = (out / "dist").glob("camrep-*.whl")
  return wheel


def fresh_venv(path: pathlib.Path) -> pathlib.Path:
  """A new venv whose site-packages reaches the running interpreter's (after its own)."""
  venv.EnvBuilder(with_pip=True).create(path)
  python = path / "bin" / "python"
  own = subprocess.run(
    [python, "-c", "import site; print(site.getsitepackages()[0])"],
    env=_env(),
    check=True,
    capture_output=True,
    text=True,
  ).stdout.strip()
  borrowed = [p for p in site.getsitepackages() if os.path.isdir(p)]
  pathlib.Path(own, "_borrowed_site_packages.pth").write_text("\n".join(borrowed) + "\n")
  return python


def _env() -> dict[str, str]:
  env = one_device_env()  # compile in seconds
  env.pop("PYTHONPATH", None)
  return env


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
  """(python of a fresh venv with camrep's wheel installed, an empty directory to run in)."""
  tmp_path = tmp_path_factory.mktemp("wheel_install")
  wheel = build_wheel(tmp_path / "wheel")
  python = fresh_venv(tmp_path / "venv")
  subprocess.run(
    [python, "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)],
    env=_env(),  # no PYTHONPATH: pip would take a checkout on it for camrep already installed
    check=True,
    capture_output=True,
    text=True,
    timeout=300,
  )
  away = tmp_path / "elsewhere"  # no configs/ and no camrep/ here
  away.mkdir()
  return python, away


def test_wheel_installs_and_trains_a_config_by_name(installed):
  python, away = installed
  tmp_path = away.parent
  where = subprocess.run(
    [python, "-c", "import camrep.configs as c; print(c.__file__); print(c.path('gqn'))"],
    cwd=away,
    env=_env(),
    check=True,
    capture_output=True,
    text=True,
  ).stdout.split()
  assert all(p.startswith(str(tmp_path / "venv")) for p in where), where
  assert os.path.isfile(where[1])

  workdir = away / "gqn_smoke"
  r = subprocess.run(
    [python, "-m", "camrep.main", "--config=gqn:smoke", f"--workdir={workdir}"],
    cwd=away,
    env=_env(),
    capture_output=True,
    text=True,
    timeout=600,
  )
  assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
  final = json.loads((workdir / "final_metrics.json").read_text())
  assert final["step"] == 4 and "eval/psnr" in final, final


# Run by the venv's Python in a directory outside the checkout: the notebook executed with
# tools/run_notebook.py (its directory alone on PYTHONPATH: camrep comes from the wheel), the
# executed notebook and its namespace values (tests/test_notebook.py's) written beside it.
_RUN_NOTEBOOK = """
import json, pickle, sys
import run_notebook
names = sys.argv[2].split(",")
with open(sys.argv[1]) as f:
  fresh, ns = run_notebook.execute(json.load(f))
with open("fresh.ipynb", "w") as f:
  json.dump(fresh, f)
values = {k: ns["config"].total_steps if k == "total_steps" else ns[k] for k in names}
with open("namespace.pkl", "wb") as f:
  pickle.dump(values, f)
"""


def test_the_notebook_runs_on_the_installed_package(installed):
  """The quickstart, executed on the installed wheel, is fresh: tests/test_notebook.py's checks
  of its outputs and of the numbers it is about (`check_fresh_run`)."""
  python, away = installed
  names = ",".join(test_notebook.NAMESPACE)
  notebook = str(ROOT / "notebooks" / "quickstart.ipynb")
  r = subprocess.run(
    [python, "-c", _RUN_NOTEBOOK, notebook, names],
    cwd=away,
    # Compiled as a user's session compiles it.
    env={**_env(), "JAX_DISABLE_MOST_OPTIMIZATIONS": "0", "PYTHONPATH": str(ROOT / "tools")},
    capture_output=True,
    text=True,
    timeout=600,
  )
  assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
  fresh = json.loads((away / "fresh.ipynb").read_text())
  with open(away / "namespace.pkl", "rb") as f:
    values = pickle.load(f)
  code = [c for c in fresh["cells"] if c["cell_type"] == "code"]
  # The install cell found the wheel's camrep (and installed nothing); every cell produced output.
  assert "".join(code[0]["outputs"][0]["text"]).strip() == "camrep installed"
  assert all(c["outputs"] for c in code)
  assert not any(o["output_type"] == "error" for c in code for o in c["outputs"])
  test_notebook.check_fresh_run(fresh, values)

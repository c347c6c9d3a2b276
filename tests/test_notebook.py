"""experiments/quickstart.ipynb is a well-formed notebook and its code cells run, in order.

nbformat/nbclient are not dependencies: the JSON is checked by hand and the code cells are
exec'd in one namespace, from a temporary working directory. Without IPython, a stub
`IPython.display` records what the notebook displays.
"""

from __future__ import annotations

import importlib.util
import json
import pathlib
import sys
import types

import cv2
import jax
import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "experiments" / "quickstart.ipynb"


def _load() -> dict:
  nb = json.loads(NOTEBOOK.read_text(encoding="utf-8"))
  assert nb["nbformat"] == 4 and nb["nbformat_minor"] >= 5
  assert nb["metadata"]["kernelspec"]["language"] == "python"
  assert nb["metadata"]["kernelspec"]["name"] == "python3"
  ids = [c["id"] for c in nb["cells"]]
  assert len(set(ids)) == len(ids), "cell ids must be unique"
  for cell in nb["cells"]:
    assert cell["cell_type"] in ("markdown", "code"), cell["cell_type"]
    assert isinstance(cell["metadata"], dict)
    assert isinstance(cell["source"], list) and all(isinstance(s, str) for s in cell["source"])
    assert all(s.endswith("\n") for s in cell["source"][:-1]), "source lines keep their newlines"
    if cell["cell_type"] == "code":
      assert cell["outputs"] == [] and cell["execution_count"] is None, "commit it unexecuted"
  return nb


def _stub_ipython(monkeypatch) -> list:
  """Stubs IPython.display when IPython is not installed; returns the list of displayed PNGs."""
  shown: list[bytes] = []
  if importlib.util.find_spec("IPython") is not None:
    import IPython.display

    real = IPython.display.display

    def display(obj, *args, **kw):
      if isinstance(obj, IPython.display.Image):
        shown.append(obj.data)
      return real(obj, *args, **kw)

    monkeypatch.setattr(IPython.display, "display", display)
    return shown

  class Image:
    def __init__(self, data):
      self.data = data

  def display(obj):
    if isinstance(obj, Image):
      shown.append(obj.data)

  ipython = types.ModuleType("IPython")
  module = types.ModuleType("IPython.display")
  module.Image, module.display = Image, display
  ipython.display = module
  monkeypatch.setitem(sys.modules, "IPython", ipython)
  monkeypatch.setitem(sys.modules, "IPython.display", module)
  return shown


def test_quickstart_notebook_runs(tmp_path, monkeypatch):
  nb = _load()
  kinds = [c["cell_type"] for c in nb["cells"]]
  assert kinds[0] == "markdown" and kinds.count("code") >= 5
  intro = "".join(nb["cells"][0]["source"])
  assert "pip install -e ." in intro and "CVPR 2021" in intro
  shown = _stub_ipython(monkeypatch)
  monkeypatch.chdir(tmp_path)
  monkeypatch.setattr(sys, "path", list(sys.path))  # the notebook may add the repository root
  old_flag = jax.config.read("jax_disable_most_optimizations")
  ns: dict = {"__name__": "__main__"}
  try:
    for i, cell in enumerate(nb["cells"]):
      if cell["cell_type"] == "code":
        code = "".join(cell["source"])
        exec(compile(code, f"{NOTEBOOK.name}[cell {i}, {cell['id']}]", "exec"), ns)
  finally:
    jax.config.update("jax_disable_most_optimizations", old_flag)

  assert ns["ROOT"] == ROOT
  # Section 1: the fitted rotation law holds better than at initialisation, decoding inverts
  # embedding, and decoding rotated vectors finds the shifted poses.
  for name in ("xy", "yaw"):
    assert np.mean(ns["residual_fit"][name]) < 0.5 * np.mean(ns["residual_init"][name]), name
  assert ns["roundtrip_errors"].max() < 1e-3
  errors = ns["decode_errors"]
  assert errors.shape == (4, 3)
  assert errors[:, :2].max() < 0.1 and errors[:, 2].max() < np.deg2rad(3.0), errors
  # Section 3: training wrote metrics with a held-out-view PSNR, and its image grid was shown.
  evals = [r for r in ns["metrics"] if "eval/psnr" in r]
  assert evals and evals[-1]["step"] == ns["config"].total_steps
  assert np.isfinite(evals[-1]["eval/psnr"]) and np.isfinite(evals[-1]["eval/psnr_baseline"])
  assert ns["last"]["eval/psnr"] == evals[-1]["eval/psnr"]
  # Sections 2-4: rendered views, the training grid and the Gram map are displayed as PNGs.
  assert len(shown) >= 3
  images = [cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR) for png in shown]
  assert all(im is not None and im.ndim == 3 and im.std() > 1.0 for im in images)
  assert ns["gram"].shape == (360, 360)
  np.testing.assert_allclose(np.diag(ns["gram"]), 1.0, atol=1e-4)

"""notebooks/quickstart.ipynb: well formed, committed with its outputs, and those outputs are
not stale in kind: a fresh run (tools/run_notebook.py, no Jupyter needed) must produce the
same kinds of output per code cell (text, images) and no exception. Pixels, timings and printed
numbers may differ; the numbers the notebook is about are checked on the fresh run's namespace
(`check_fresh_run`, on the run tests/test_wheel.py makes on camrep installed from its wheel).
"""

from __future__ import annotations

import base64
import json
import pathlib

import cv2
import numpy as np
import pytest

from tools import run_notebook

pytestmark = pytest.mark.slow

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "notebooks" / "quickstart.ipynb"
# Committed with its outputs (PNG images in base64): small enough to review on the web page.
MAX_BYTES = 200 * 1024


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
  return nb


def _images(nb: dict) -> list[np.ndarray]:
  out = []
  for cell in nb["cells"]:
    for o in cell.get("outputs", []):
      if o["output_type"] == "display_data" and "image/png" in o["data"]:
        png = np.frombuffer(base64.b64decode(o["data"]["image/png"]), np.uint8)
        out.append(cv2.imdecode(png, cv2.IMREAD_COLOR))
  return out


def test_committed_with_outputs_small_enough_to_review():
  nb = _load()
  assert NOTEBOOK.stat().st_size < MAX_BYTES, f"{NOTEBOOK.stat().st_size} bytes"
  code = [c for c in nb["cells"] if c["cell_type"] == "code"]
  assert [c["execution_count"] for c in code] == list(range(1, len(code) + 1)), "run in order"
  for c in code:
    assert c["outputs"], f"code cell {c['id']} has no committed output"
    assert all(o["output_type"] != "error" for o in c["outputs"]), f"{c['id']} raised"
  # The pose-system residuals, a rendered scene, the training's image grid and a Gram map.
  text = "".join("".join(o.get("text", [])) for c in code for o in c["outputs"])
  assert "|exp(B d) v(l) - v(l+d)|" in text and "eval/psnr" in text
  images = _images(nb)
  assert len(images) >= 3
  assert all(im is not None and im.ndim == 3 and im.std() > 1.0 for im in images)
  # No local paths of the machine that ran it.
  assert "/tmp/" not in text and "/work/" not in text and "/home/" not in text


def test_install_cell_comes_first_and_finds_its_source(tmp_path, monkeypatch):
  nb = _load()
  kinds = [c["cell_type"] for c in nb["cells"]]
  assert kinds[0] == "markdown" and kinds[1] == "code"
  intro = "".join(nb["cells"][0]["source"])
  assert "CAMREP_SOURCE" in intro and "CVPR 2021" in intro and "GPU" in intro
  install = "".join(nb["cells"][1]["source"])
  assert 'find_spec("camrep") is None' in install and "pip" in install
  ns: dict = {}
  # The cell with camrep present: no install, just the report.
  monkeypatch.chdir(tmp_path)
  monkeypatch.delenv("CAMREP_SOURCE", raising=False)
  executed, ns = run_notebook.execute({"cells": [nb["cells"][1]]})
  out = "".join(executed["cells"][0]["outputs"][0]["text"])
  assert out.startswith("camrep ") and "installing" not in out
  # Where it would install from: the variable, else the clone around the working directory.
  with pytest.raises(RuntimeError, match="CAMREP_SOURCE"):
    ns["camrep_source"]()
  monkeypatch.chdir(ROOT / "notebooks")
  assert ns["camrep_source"]() == str(ROOT)
  monkeypatch.setenv("CAMREP_SOURCE", "git+https://example.org/camrep")
  assert ns["camrep_source"]() == "git+https://example.org/camrep"


# The fresh run's namespace values `check_fresh_run` reads ("total_steps": the config's; values
# of the namespace otherwise).
NAMESPACE = (
  "residual_fit",
  "residual_init",
  "roundtrip_errors",
  "decode_errors",
  "metrics",
  "total_steps",
  "last",
  "gram",
)


def check_fresh_run(fresh: dict, values: dict) -> None:
  """A fresh run of the quickstart (`run_notebook.execute`'s notebook and `namespace_values` of
  its namespace) against the committed notebook. tests/test_wheel.py runs it, on camrep installed
  from its wheel, compiled as a user's session compiles it: the notebook turns XLA's
  optimisations off itself around its training cell."""
  committed = _load()
  assert run_notebook.output_kinds(fresh) == run_notebook.output_kinds(committed), (
    "the committed outputs are stale: refresh them with "
    "`python tools/run_notebook.py notebooks/quickstart.ipynb --write`"
  )
  # Section 1: the fitted rotation law holds better than at initialisation, decoding inverts
  # embedding, and decoding rotated vectors finds the shifted poses.
  for name in ("xy", "yaw"):
    fit, init = values["residual_fit"][name], values["residual_init"][name]
    assert np.mean(fit) < 0.5 * np.mean(init), name
  assert values["roundtrip_errors"].max() < 1e-3
  errors = values["decode_errors"]
  assert errors.shape == (4, 3)
  assert errors[:, :2].max() < 0.1 and errors[:, 2].max() < np.deg2rad(3.0), errors
  # Section 3: training wrote metrics with a held-out-view PSNR, and its image grid was shown.
  evals = [r for r in values["metrics"] if "eval/psnr" in r]
  assert evals and evals[-1]["step"] == values["total_steps"]
  assert np.isfinite(evals[-1]["eval/psnr"]) and np.isfinite(evals[-1]["eval/psnr_baseline"])
  assert values["last"]["eval/psnr"] == evals[-1]["eval/psnr"]
  # Sections 2-4: rendered views, the training grid and the Gram map are displayed as PNGs.
  images = _images(fresh)
  assert len(images) >= 3
  assert all(im is not None and im.ndim == 3 and im.std() > 1.0 for im in images)
  assert values["gram"].shape == (360, 360)
  np.testing.assert_allclose(np.diag(values["gram"]), 1.0, atol=1e-4)


def test_output_kinds_see_a_missing_output_and_an_exception():
  """The staleness check itself: what output_kinds compares."""
  nb = {
    "cells": [
      {"cell_type": "markdown", "source": ["# t"]},
      {"cell_type": "code", "source": ["print(1)\n", "raise ValueError('boom')"]},
    ]
  }
  with pytest.raises(ValueError, match="boom") as e:
    run_notebook.execute(nb)
  assert run_notebook.output_kinds(e.value.notebook) == [["stream:stdout", "error"]]
  ok = {"cells": [{"cell_type": "code", "source": ["print(1)"]}]}
  assert run_notebook.output_kinds(run_notebook.execute(ok)[0]) == [["stream:stdout"]]
  assert run_notebook.output_kinds({"cells": [{"cell_type": "code", "outputs": []}]}) == [[]]

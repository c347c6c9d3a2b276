"""Executes a notebook's code cells in order, in one namespace, and records their outputs, as
`jupyter nbconvert --execute --inplace` would, without Jupyter (nbformat, nbclient and IPython are
not dependencies).

Printed text becomes "stream" outputs; images shown with `IPython.display.display(Image(data=png))`
become "display_data" outputs with their PNG (a stub `IPython.display` is installed while the
cells run); an exception becomes an "error" output and stops the run. Refresh the quickstart's
committed outputs after changing it (the committed run: 165 s on a shared 2-core CPU):

  .venv/bin/python tools/run_notebook.py notebooks/quickstart.ipynb --write

tests/test_wheel.py runs the notebook the same way, on camrep installed from its wheel, and
tests/test_notebook.py checks the committed outputs are of the same kinds as that fresh run's.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import io
import json
import os
import sys
import traceback
import types
from typing import Any


class _Image:
  """The part of IPython.display.Image the notebooks use: Image(data=png_bytes)."""

  def __init__(self, data: bytes | None = None, **_):
    self.data = data


class _Tee(io.TextIOBase):
  """A text stream that appends to the current cell's outputs, merging consecutive writes."""

  def __init__(self, outputs: list, name: str):
    self.outputs, self.name = outputs, name

  def write(self, s: str) -> int:
    if s:
      last = self.outputs[-1] if self.outputs else None
      if last and last["output_type"] == "stream" and last["name"] == self.name:
        last["text"].append(s)
      else:
        self.outputs.append({"output_type": "stream", "name": self.name, "text": [s]})
    return len(s)


def _lines(chunks: list[str]) -> list[str]:
  """Stream text as nbformat stores it: lines keeping their newlines."""
  return "".join(chunks).splitlines(keepends=True)


def execute(nb: dict[str, Any], *, cwd: str | None = None) -> tuple[dict[str, Any], dict]:
  """Runs the code cells of notebook `nb` (nbformat 4 JSON); returns (executed copy, namespace).

  Raises the first cell's exception after recording it as that cell's "error" output (the
  executed copy is on the exception as `.notebook`).
  """
  nb = json.loads(json.dumps(nb))
  ns: dict[str, Any] = {"__name__": "__main__"}
  outputs: list = []

  def display(obj, *args, **kw):
    if isinstance(obj, _Image):
      png = base64.b64encode(obj.data).decode("ascii")
      data = {"image/png": png, "text/plain": ["<IPython.core.display.Image object>"]}
      outputs.append({"output_type": "display_data", "data": data, "metadata": {}})
    else:
      print(obj if not args else (obj, *args))

  stub = types.ModuleType("IPython.display")
  stub.Image, stub.display = _Image, display
  ipython = types.ModuleType("IPython")
  ipython.display = stub
  # What libraries ask an IPython outside a shell (matplotlib's canvas does): no shell here.
  ipython.get_ipython = lambda: None
  ipython.version_info = (0, 0, 0, "stub")
  saved = {k: sys.modules.get(k) for k in ("IPython", "IPython.display")}
  old_cwd = os.getcwd()
  count = 0
  try:
    sys.modules["IPython"], sys.modules["IPython.display"] = ipython, stub
    if cwd:
      os.chdir(cwd)
    for i, cell in enumerate(nb["cells"]):
      if cell["cell_type"] != "code":
        continue
      count += 1
      outputs = []
      cell["outputs"], cell["execution_count"] = outputs, count
      code = "".join(cell["source"])
      try:
        with (
          contextlib.redirect_stdout(_Tee(outputs, "stdout")),
          contextlib.redirect_stderr(_Tee(outputs, "stderr")),
        ):
          exec(compile(code, f"<cell {i}, {cell.get('id', '')}>", "exec"), ns)
      except Exception as e:
        outputs.append(
          {
            "output_type": "error",
            "ename": type(e).__name__,
            "evalue": str(e),
            "traceback": traceback.format_exception(e),
          }
        )
        e.notebook = nb
        raise
      finally:
        for o in outputs:
          if o["output_type"] == "stream":
            o["text"] = _lines(o["text"])
  finally:
    os.chdir(old_cwd)
    for k, v in saved.items():
      if v is None:
        sys.modules.pop(k, None)
      else:
        sys.modules[k] = v
  return nb, ns


def output_kinds(nb: dict[str, Any]) -> list[list[str]]:
  """Per code cell, its outputs' kinds: "stream:stdout", "display_data:image/png", "error"..."""
  kinds = []
  for cell in nb["cells"]:
    if cell["cell_type"] != "code":
      continue
    row = []
    for o in cell["outputs"]:
      t = o["output_type"]
      if t == "stream":
        row.append(f"stream:{o['name']}")
      elif t in ("display_data", "execute_result"):
        row.append(f"{t}:" + ",".join(sorted(k for k in o["data"] if k != "text/plain")))
      else:
        row.append(t)
    kinds.append(row)
  return kinds


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("notebook")
  p.add_argument("--write", action="store_true", help="write the outputs into the notebook")
  args = p.parse_args(argv)
  with open(args.notebook, encoding="utf-8") as f:
    nb = json.load(f)
  try:
    nb, _ = execute(nb)
  except Exception:
    traceback.print_exc()
    return 1
  for i, row in enumerate(output_kinds(nb)):
    print(f"code cell {i}: {', '.join(row) or 'no output'}", file=sys.__stdout__)
  if args.write:
    with open(args.notebook, "w", encoding="utf-8") as f:
      json.dump(nb, f, indent=1, ensure_ascii=False)
      f.write("\n")
    print(f"wrote {args.notebook} ({os.path.getsize(args.notebook) / 1024:.0f} KiB)")
  return 0


if __name__ == "__main__":
  sys.exit(main())

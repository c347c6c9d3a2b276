"""The README's Colab-style example runs as written."""

from __future__ import annotations

import pathlib
import re

import pytest

# The example compiles expm, decode and the rotation losses once each: compilation dominates.
pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs():
  blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
  assert blocks, "README has no python example"
  for code in blocks:
    exec(compile(code, str(README), "exec"), {})

"""The README's Colab-style example runs as written; every timing it quotes is a measured one."""

from __future__ import annotations

import json
import pathlib
import re

import pytest

from camrep.bench import gpu_report
from tools import run_notebook

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BUILD_NOTES = ROOT / "BUILD_NOTES.md"

_NUM = r"\d+(?:\.\d+)?"
_UNIT = r"(?:hours?|h|minutes?|min|seconds?|s)"
# A duration as written in prose: "165 s", "10 min 24 s", "79-82 h", "45-55 minutes".
_TIMING = re.compile(
  rf"(?<![\w.]){_NUM}(?:\s*-\s*{_NUM})?\s*{_UNIT}(?:\s+{_NUM}\s*{_UNIT})*(?![\w/])"
)
_CANONICAL = {"hour": "h", "hours": "h", "minute": "min", "minutes": "min"}
_CANONICAL |= {"second": "s", "seconds": "s"}
# Durations that say nothing checkable ("in about a minute", "every few seconds"); "a second" only
# where no word follows it ("a second launch" is an ordinal).
_VAGUE = re.compile(
  r"\b(?:(?:a|an|a few|few|several)\s+(?:seconds|minutes?|hours?)|(?:a few|few|several)\s+second"
  r"|an?\s+second(?!\s+[a-z]))\b",
  re.I,
)


def _prose(text: str) -> str:
  """The text without its ```text blocks (a program's sample output, not a claim)."""
  return re.sub(r"```text\n.*?```", "", text, flags=re.S)


def _timings(text: str) -> set[str]:
  """Every duration in `text`, normalised ("10 minutes" -> "10 min", "79 - 82 h" -> "79-82 h")."""
  out = set()
  for match in _TIMING.finditer(text):
    words = re.sub(r"\s*-\s*", "-", match.group(0)).split()
    out.add(" ".join(_CANONICAL.get(w, w) for w in words))
  return out


@pytest.mark.slow
@pytest.mark.usefixtures("fast_compile")  # the example compiles expm, decode and the losses once
def test_readme_python_example_runs():
  blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
  assert blocks, "README has no python example"
  for code in blocks:
    exec(compile(code, str(README), "exec"), {})


def test_timings_are_parsed_as_written():
  assert _timings("took 10 min 24 s, then 37 minutes; ETA 79-82 h, 3.2 steps/s, 0.5 m, 64 px") == {
    "10 min 24 s",
    "37 min",
    "79-82 h",
  }
  assert _VAGUE.findall("in about a minute, every few seconds, in a second.") == [
    "a minute",
    "few seconds",
    "a second",
  ]
  assert not _VAGUE.findall("a second launch on the same DIR")


def test_every_readme_timing_is_one_measured_in_build_notes():
  readme = _prose(README.read_text())
  measured = _timings(BUILD_NOTES.read_text())
  quoted = _timings(readme)
  assert quoted, "the README quotes no timing: the parser is broken"
  missing = sorted(quoted - measured)
  assert not missing, f"README timings with no measured twin in BUILD_NOTES.md: {missing}"
  vague = _VAGUE.findall(readme)
  assert not vague, f"README durations that are not measured figures: {vague}"


def test_the_notebook_quotes_only_measured_durations():
  """The quickstart's text (its markdown cells) and the tools' help quote measured durations:
  each is in BUILD_NOTES.md or in the notebook's own committed output, none is vague."""
  nb = json.loads((ROOT / "notebooks" / "quickstart.ipynb").read_text(encoding="utf-8"))
  cells = nb["cells"]
  text = "".join("".join(c["source"]) for c in cells if c["cell_type"] == "markdown")
  output = "".join("".join(o.get("text", [])) for c in cells for o in c.get("outputs", []))
  assert "165 s" in _timings(text) and "165 s" in _timings(output)
  missing = sorted(_timings(text) - _timings(BUILD_NOTES.read_text()) - _timings(output))
  assert not missing, f"notebook durations with no measured twin: {missing}"
  for doc in (text, run_notebook.__doc__):
    assert not _VAGUE.findall(doc), _VAGUE.findall(doc)
  assert "about a minute" not in gpu_report.__doc__  # its smoke check takes 140 s or more

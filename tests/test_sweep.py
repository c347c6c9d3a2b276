"""tools/sweep.py: runs config variants of camrep.main and tabulates their PSNR gains."""

from __future__ import annotations

import argparse
import json

import pytest

from tools import sweep

pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]


def test_parse_variant():
  sw = sweep
  assert sw.parse_variant("base=") == ("base", [])
  assert sw.parse_variant("lr=--config.optax.lr_model=2e-3 --config.seed=1") == (
    "lr",
    ["--config.optax.lr_model=2e-3", "--config.seed=1"],
  )
  for bad in ("no_equals", "=--config.seed=1", "a/b=", "x=--workdir=/tmp"):
    with pytest.raises(argparse.ArgumentTypeError):
      sw.parse_variant(bad)


def test_sweep_runs_variants_and_reports_failures(tmp_path, monkeypatch):
  monkeypatch.setenv("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")  # the runs compile in seconds
  sw = sweep
  out = tmp_path / "sweep"
  rc = sw.main(
    [
      "--config=configs/gqn.py:smoke",
      f"--out={out}",
      "--steps=4",
      "--every=2",
      "--parallel=2",
      "--variant",
      "base=",
      "--variant",
      "no_queries=--config.data.n_context=4",  # refused by train.check_config
    ]
  )
  assert rc == 1
  runs = {r["name"]: r for r in json.loads((out / "sweep.json").read_text())["runs"]}
  base, bad = runs["base"], runs["no_queries"]
  assert base["returncode"] == 0 and [r["step"] for r in base["curve"]] == [2, 4]
  for r in base["curve"]:
    assert r["gain"] == pytest.approx(r["psnr"] - r["baseline"])
  assert bad["returncode"] == 2 and "n_context" in bad["last_line"] and bad["curve"] == []
  md = (out / "sweep.md").read_text()
  assert "| base | `(as configured)` |" in md and "| 2 | 4 |" in md
  assert "exit 2: error:" in md

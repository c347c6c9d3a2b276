"""The regression stopping rule (camrep/regression/stopping.py, issue 29): the rule on given
curves, and the driver applying it at its periodic validation (configs/regression.py:smoke runs
whose validation score is replaced by a fixed curve: flat -> stops early and says why; still
improving -> trains to the cap)."""

from __future__ import annotations

import json
import os

import pytest

from camrep.regression import driver as R
from camrep.regression import stopping
from camrep.runtime.runconfig import ConfigError
from configs import regression as regression_config

RULE = stopping.Rule(min_improvement=0.05, window=0.25, min_steps=0)


def test_rule_on_given_curves():
  flat = [(s, 1.0) for s in range(10, 110, 10)]
  # No evaluation at or before 0.75 * 10 yet: no decision.
  assert stopping.check(RULE, flat[:1])[0] is False
  stop, why = stopping.check(RULE, flat[:2])  # step 20: best at <= 15 is 1.0, best now 1.0
  assert stop and "plateau at step 20" in why and "0.00%" in why
  # 10% better per evaluation: always more than 5% over the last quarter.
  improving = [(s, 0.9 ** (s // 10)) for s in range(10, 110, 10)]
  assert not any(stopping.check(RULE, improving[: i + 1])[0] for i in range(len(improving)))
  # The improvement is measured against the best before the window, not the last value: a
  # spike inside the window does not count as progress when it comes back down.
  spiky = [(10, 1.0), (20, 1.0), (30, 1.0), (40, 3.0), (50, 0.99)]
  assert stopping.check(RULE, spiky)[0]
  assert stopping.check(stopping.Rule(0.05, 0.25, min_steps=60), flat)[0]
  assert stopping.check(stopping.Rule(0.05, 0.25, min_steps=200), flat)[0] is False
  assert stopping.check(stopping.Rule(), flat) == (False, "no stopping rule")
  stop = regression_config.get_config("smoke").stop
  stop.window = 1.0
  with pytest.raises(ValueError, match="0 < window < 1"):
    stopping.rule_from_config(stop)


def _run(tmp_path, cache, monkeypatch, scores, **stop):
  calls = iter(scores)
  monkeypatch.setattr(R.tables_lib, "validation_score", lambda setting, summary: next(calls))
  c = regression_config.get_config("smoke")
  c.setting, c.representation = "car", "euler"
  c.total_steps, c.eval_every_steps, c.data.cache_dir = 12, 2, cache
  c.stop.update(stop)
  wd = str(tmp_path)
  return R.run(c, wd, log=lambda s: None), wd


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
  return str(tmp_path_factory.mktemp("stop_cache"))


@pytest.mark.slow
@pytest.mark.usefixtures("fast_compile")
def test_driver_stops_a_flat_run_and_runs_an_improving_one_to_the_cap(tmp_path, cache, monkeypatch):
  flat = [1.0] * 20
  results, wd = _run(tmp_path / "flat", cache, monkeypatch, flat, min_improvement=0.05, min_steps=6)
  s = results["stopping"]
  # Evaluations at 2, 4, 6: the rule may stop from step 6 (min_steps); the window then starts at
  # step 4.5, and nothing improved since step 2.
  assert s["stopped_early"] and results["steps"] == 6 and results["total_steps"] == 12
  assert "plateau at step 6" in s["reason"] and s["rule"]["min_improvement"] == 0.05
  assert s["curve"] == [[2, 1.0], [4, 1.0], [6, 1.0]]
  lines = [json.loads(x) for x in open(os.path.join(wd, "metrics.jsonl"))]
  assert max(r["step"] for r in lines) == 6
  assert [r["step"] for r in lines if "eval/validation/score" in r] == [2, 4, 6, 6]
  with open(os.path.join(wd, "results.json")) as f:
    assert json.load(f)["stopping"]["reason"] == s["reason"]

  improving = [0.8**i for i in range(20)]
  results, _ = _run(tmp_path / "improving", cache, monkeypatch, improving, min_improvement=0.05)
  s = results["stopping"]
  assert not s["stopped_early"] and results["steps"] == 12 and s["reason"] == "reached total_steps"
  assert [c[0] for c in s["curve"]] == [2, 4, 6, 8, 10, 12]


def test_an_active_rule_needs_periodic_validation(tmp_path):
  c = regression_config.get_config("smoke")
  c.stop.min_improvement = 0.02
  with pytest.raises(ConfigError, match="eval_every_steps"):
    R.resolve_config(c)
  c.eval_every_steps, c.stop.window = 10, 0.0
  with pytest.raises(ConfigError, match="window"):
    R.resolve_config(c)

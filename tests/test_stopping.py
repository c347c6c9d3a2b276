"""The plateau stopping rule (camrep/runtime/stopping.py): the rule on given curves;
the regression driver applying it at its periodic validation (configs/regression.py:smoke runs
whose validation score is replaced by a fixed curve: flat -> stops early and says why; still
improving -> trains to the cap); and the view-synthesis trainer applying it at its held-out
evaluations (configs/gqn.py:smoke runs whose held-out PSNR is replaced by a fixed curve): the
checkpoint and final_metrics.json at the step it stops, a rerun that changes nothing, a resumed
run that goes on with its recorded curve, and a rule turned off that extends the run."""

from __future__ import annotations

import hashlib
import json
import os
import shutil

import pytest

from camrep import settings
from camrep.configs import gqn
from camrep.regression import config_schema
from camrep.regression import driver as R
from camrep.runtime import session, stopping, writers
from camrep.runtime.checkpoint import CHECKPOINT_SUBDIR
from camrep.runtime.runconfig import ConfigError
from camrep.synthesis import config_schema as synthesis_schema
from camrep.synthesis import train
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
  car = settings.get("car")
  monkeypatch.setattr(type(car), "validation_score", lambda self, summary: next(calls))
  c = regression_config.get_config("car,smoke")
  c.representation = "euler"
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

  # Complete at its plateau: the same command does nothing (no step trained, nothing written).
  def files():  # each file's mtime, and the checkpoints' steps
    out = {f: os.path.getmtime(os.path.join(wd, f)) for f in os.listdir(wd)}
    return out | {"checkpoints": sorted(os.listdir(os.path.join(wd, "checkpoints")))}

  before = files()
  lines_before = open(os.path.join(wd, "metrics.jsonl")).read()
  logged = []
  monkeypatch.setattr(type(settings.get("car")), "validation_score", lambda self, summary: 1.0)
  c = regression_config.get_config("car,smoke")
  c.representation = "euler"
  c.total_steps, c.eval_every_steps, c.data.cache_dir = 12, 2, cache
  c.stop.update(min_improvement=0.05, min_steps=6)
  assert R.run(c, wd, log=logged.append) == json.loads(json.dumps(results))
  assert any("complete at step 6, stopped by the plateau rule" in x for x in logged), logged
  assert open(os.path.join(wd, "metrics.jsonl")).read() == lines_before
  assert files() == before

  improving = [0.8**i for i in range(20)]
  results, _ = _run(tmp_path / "improving", cache, monkeypatch, improving, min_improvement=0.05)
  s = results["stopping"]
  assert not s["stopped_early"] and results["steps"] == 12 and s["reason"] == "reached total_steps"
  assert [c[0] for c in s["curve"]] == [2, 4, 6, 8, 10, 12]


def test_an_active_rule_needs_periodic_validation(tmp_path):
  c = regression_config.get_config("smoke")
  c.stop.min_improvement = 0.02
  with pytest.raises(ConfigError, match="eval_every_steps"):
    config_schema.check(c)
  c.eval_every_steps, c.stop.window = 10, 0.0
  with pytest.raises(ConfigError, match="window"):
    config_schema.check(c)


# --------------------------------------------------------------------------------------------
# View synthesis.


def test_psnr_score_is_the_held_out_mse():
  assert stopping.psnr_score(20.0) == pytest.approx(0.01)
  # A 5% relative improvement of the score is a gain of ~0.22 dB.
  assert stopping.psnr_score(20.2228) == pytest.approx(0.0095, rel=1e-4)


def test_an_active_synthesis_rule_needs_held_out_evaluations():
  c = gqn.get_config("smoke")
  synthesis_schema.validate(c)  # off by default
  c.stop.min_improvement, c.eval_every_steps = 0.02, 0
  with pytest.raises(ConfigError, match="eval_every_steps > 0"):
    synthesis_schema.validate(c)
  c.eval_every_steps, c.stop.window = 2, 1.5
  with pytest.raises(ConfigError, match="stop.window"):
    synthesis_schema.validate(c)


def _hashes(workdir) -> dict[str, str]:
  out = {}
  for root, _, files in os.walk(workdir):
    for f in files:
      p = os.path.join(root, f)
      with open(p, "rb") as fh:
        out[os.path.relpath(p, workdir)] = hashlib.sha256(fh.read()).hexdigest()
  return out


def _fake_psnr(monkeypatch, psnrs):
  """The held-out evaluation replaced by `psnrs` in turn (written to metrics.jsonl as usual)."""
  values = iter(psnrs)

  def evaluate_and_log(writer, predict, batches, params, step, *, grid_scenes, log, **_):
    scalars = {"eval/psnr": float(next(values))}
    writer.write_scalars(step, scalars)
    return scalars

  monkeypatch.setattr(train.heldout, "evaluate_and_log", evaluate_and_log)


def _synthesis_config(total=12, **stop):
  c = gqn.get_config("smoke")
  c.total_steps, c.eval_every_steps, c.ckpt_every_steps, c.log_every_steps = total, 2, 4, 2
  c.stop.update(stop)
  return c


def _checkpoints(wd) -> list[int]:
  return sorted(int(n) for n in os.listdir(os.path.join(wd, CHECKPOINT_SUBDIR)) if n.isdigit())


@pytest.mark.slow
@pytest.mark.usefixtures("fast_compile")
def test_synthesis_stops_at_its_plateau_and_a_rerun_changes_nothing(tmp_path, monkeypatch):
  wd = str(tmp_path / "flat")
  rule = {"min_improvement": 0.05, "min_steps": 6}
  _fake_psnr(monkeypatch, [20.0] * 20)
  lines = []
  train.train_and_evaluate(_synthesis_config(**rule), wd, log=lines.append)
  final = session.read_final(wd)
  s = final["stopping"]
  # Evaluations at 2, 4, 6; from step 6 (min_steps) the window starts at 4.5: nothing improved
  # since step 2. The checkpoint of step 6 is saved although ckpt_every_steps is 4.
  assert final["complete"] is True and final["step"] == 6 and s["steps"] == 6
  assert s["stopped_early"] and s["total_steps"] == 12 and "plateau at step 6" in s["reason"]
  assert s["rule"] == {"min_improvement": 0.05, "window": 0.25, "min_steps": 6}
  assert s["curve"] == [[2, 0.01], [4, 0.01], [6, 0.01]]
  assert final["eval/psnr"] == 20.0
  assert _checkpoints(wd)[-1] == 6 and max(r["step"] for r in writers.read_metrics(wd)) == 6
  assert any("stopping at step 6: plateau" in line for line in lines)

  # The same command again: nothing to do, no byte changed.
  before = _hashes(wd)
  lines = []
  train.train_and_evaluate(_synthesis_config(**rule), wd, log=lines.append)
  assert _hashes(wd) == before
  assert len(lines) == 1 and "complete at step 6, stopped by the plateau rule" in lines[0]

  # The rule turned off (a recorded change): the run goes on from step 6 to the cap.
  _fake_psnr(monkeypatch, [21.0] * 20)
  c = _synthesis_config()
  c.allow_changes = "stop"
  train.train_and_evaluate(c, wd, log=lambda s: None)
  final = session.read_final(wd)
  assert final["complete"] is True and final["step"] == 12 and "stopping" not in final
  assert _checkpoints(wd)[-1] == 12


@pytest.mark.slow
@pytest.mark.usefixtures("fast_compile")
def test_a_resumed_synthesis_run_goes_on_with_its_recorded_curve(tmp_path, monkeypatch):
  # Steps 1-4 under a 4-step cap (evaluations at 2 and 4: no plateau before min_steps 6).
  wd = str(tmp_path / "resumed")
  rule = {"min_improvement": 0.05, "min_steps": 6}
  _fake_psnr(monkeypatch, [20.0, 21.0])
  train.train_and_evaluate(_synthesis_config(total=4, **rule), wd, log=lambda s: None)
  s = session.read_final(wd)["stopping"]
  assert not s["stopped_early"] and s["reason"] == "reached total_steps" and s["steps"] == 4
  # Extended to 12: the curve of steps 2 and 4 comes back from metrics.jsonl, so step 6 is
  # judged against step 4's 21 dB (flat since: stop), not against nothing.
  _fake_psnr(monkeypatch, [21.0] * 10)
  c = _synthesis_config(**rule)
  c.allow_changes = "total_steps"
  train.train_and_evaluate(c, wd, log=lambda s: None)
  final = session.read_final(wd)
  s = final["stopping"]
  assert final["step"] == 6 and s["stopped_early"] and _checkpoints(wd)[-1] == 6
  assert [t for t, _ in s["curve"]] == [2, 4, 6]
  assert s["curve"][0][1] == pytest.approx(stopping.psnr_score(20.0))

  # A copy stopped early, extended with a stricter rule checked on the recorded curve at once:
  # still a plateau by it at step 6 (the same decision the uninterrupted run would make).
  strict = str(tmp_path / "strict")
  shutil.copytree(wd, strict)
  c = _synthesis_config(min_improvement=0.5, min_steps=6)
  c.allow_changes = "stop"
  lines = []
  train.train_and_evaluate(c, strict, log=lines.append)
  final = session.read_final(strict)
  assert final["step"] == 6 and final["stopping"]["rule"]["min_improvement"] == 0.5
  assert _checkpoints(strict)[-1] == 6

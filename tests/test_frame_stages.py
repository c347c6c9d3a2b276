"""Both stages in the run frame: K steps per dispatch (`steps_per_dispatch`, the step scanned
over K batches) train as one step per dispatch, up to float round-off, for view synthesis
(configs/gqn.py:smoke) and regression (configs/regression.py:smoke); a regression stopped by a
signal part-way (K = 3, cut at its checkpoints and evaluations) resumes exactly; a regression
rerun with a longer total_steps resumes, one with another representation starts over.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from camrep.configs import gqn
from camrep.configs import regression as regression_config
from camrep.regression import driver
from camrep.runtime import frame as frame_lib
from camrep.runtime import workdir as workdir_lib
from camrep.runtime import writers
from camrep.synthesis import restore, train
from camrep.synthesis import step as step_lib

pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]

# Wall-clock figures differ between any two runs; everything else must be equal.
TIMINGS = ("train_seconds", "steps_per_sec", "eval_seconds", "machine")

# Traces of the trainer's step in a 7-step run, by steps per dispatch: K = 3 runs two programs,
# the step scanned over 3 batches and, for the last dispatch (step 7), over 1.
TRACES = {1: 1, 3: 2}


def _rows(workdir):
  return [
    {k: v for k, v in r.items() if k != "train/steps_per_sec"}
    for r in writers.read_metrics(str(workdir))
  ]


def _assert_rows_close(got, want, rtol):
  assert [r["step"] for r in got] == [r["step"] for r in want]
  for a, b in zip(got, want, strict=True):
    assert a.keys() == b.keys()
    for key in a:
      np.testing.assert_allclose(a[key], b[key], rtol=rtol, err_msg=f"{a['step']} {key}")


def test_synthesis_k_steps_per_dispatch_train_as_one(tmp_path, monkeypatch):
  """K steps a dispatch train as one step a dispatch; the trainer's pmapped step, counted where
  it is traced, is traced once a program for the whole run, checkpoints and evaluation included
  (a state placed unlike the step's output, or a batch of another layout, would trace it again)."""
  traces = []
  real = step_lib.train_step

  def counted(*args, **kw):
    traces.append(1)
    return real(*args, **kw)

  monkeypatch.setattr(step_lib, "train_step", counted)
  runs = {}
  for k in (1, 3):
    c = gqn.get_config("smoke")
    c.total_steps, c.steps_per_dispatch, c.log_every_steps = 7, k, 1
    c.ckpt_every_steps = c.eval_every_steps = 7  # K = 3: dispatches (1-3), (4-6), (7)
    if k == 1:
      c.ckpt_every_steps = 2  # saves at steps 2, 4, 6 and 7 between the steps
    lines = []
    traces.clear()
    train.train_and_evaluate(c, str(tmp_path / f"k{k}"), log=lines.append)
    assert f"compiling the train step ({k} step{'s' if k > 1 else ''} per dispatch) ..." in lines
    assert len(traces) == TRACES[k], (k, len(traces))
    runs[k] = tmp_path / f"k{k}"
  saved = sorted(int(n.name) for n in (runs[1] / "checkpoints").iterdir())
  assert saved[-2:] == [6, 7], saved  # saved between steps, and at the end
  _assert_rows_close(_rows(runs[3]), _rows(runs[1]), rtol=1e-4)
  # Parameters up to round-off: entries whose true gradient is zero (biases before instance
  # norm) get round-off gradients that Adam normalises to +-lr (tests/test_train.py's two
  # devices against one), so they may differ by up to 2 lr per step.
  a, b = (jax.tree.leaves(restore.load_run(str(runs[k])).params) for k in (1, 3))
  close = np.concatenate(
    [np.isclose(x, y, rtol=1e-4, atol=1e-6).ravel() for x, y in zip(a, b, strict=True)]
  )
  assert close.mean() > 0.99
  c = gqn.get_config("smoke")
  bound = 2 * 7 * max(c.optax.lr_model, c.optax.lr_rep)
  for x, y in zip(a, b, strict=True):
    assert np.abs(np.asarray(x) - np.asarray(y)).max() <= bound


def _regression(**kw):
  c = regression_config.get_config("smoke")
  c.setting, c.representation = "car", "euler"
  c.total_steps, c.log_every_steps, c.eval_every_steps, c.ckpt_every_steps = 10, 1, 4, 4
  for k, v in kw.items():
    node = c
    *path, last = k.split(".")
    for p in path:
      node = node[p]
    node[last] = v
  return c


def _results(results):
  return {k: v for k, v in results.items() if k not in TIMINGS}


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
  return str(tmp_path_factory.mktemp("cache"))


def test_regression_k_steps_per_dispatch_train_as_one_and_resume_exactly(
  tmp_path, cache, monkeypatch
):
  one = driver.run(_regression(**{"data.cache_dir": cache}), str(tmp_path / "k1"))
  c3 = _regression(steps_per_dispatch=3, **{"data.cache_dir": cache})
  three = driver.run(c3, str(tmp_path / "k3"))
  _assert_rows_close(_rows(tmp_path / "k3"), _rows(tmp_path / "k1"), rtol=1e-5)
  for split in ("validation", "test"):
    for err, stats in three[split]["all"].items():
      for stat, v in stats.items():
        np.testing.assert_allclose(v, one[split]["all"][err][stat], rtol=1e-4, err_msg=err)
  # A stop signal after the 3rd dispatch ((1-3), (4), (5-6): cut at 4 and 8), then the same call.
  wd = tmp_path / "stopped"
  calls = iter(range(100))
  with monkeypatch.context() as m:
    m.setattr(frame_lib.preemption, "stop_requested", lambda h: next(calls) >= 2)
    assert driver.run(c3, str(wd)) is None
  assert sorted(int(p.name) for p in (wd / "checkpoints").iterdir() if p.name.isdigit()) == [4, 6]
  assert not (wd / workdir_lib.LOCK_FILE).exists() and not (wd / "results.json").exists()
  lines = []
  resumed = driver.run(c3, str(wd), log=lines.append)
  assert f"resumed from step 6 in {wd}" in lines
  assert _results(resumed) == _results(three)
  assert writers.read_metrics(str(wd)) == writers.read_metrics(str(tmp_path / "k3"))


def test_regression_reruns_resume_or_start_over_as_their_change_says(tmp_path, cache):
  wd = str(tmp_path / "w")
  first = driver.run(_regression(**{"data.cache_dir": cache}), wd, log=lambda s: None)
  lines = []
  again = driver.run(_regression(**{"data.cache_dir": cache}), wd, log=lines.append)
  assert again == first and lines == [
    f"{wd} is complete at step 10 (final_metrics.json); nothing to do"
  ]
  # A longer run (a field that may change on resume): resumes at step 10.
  longer = _regression(total_steps=14, allow_changes="total_steps", **{"data.cache_dir": cache})
  lines = []
  results = driver.run(longer, wd, log=lines.append)
  assert f"resumed from step 10 in {wd}" in lines and results["steps"] == 14
  # Another learning rate (a FIXED field, named): the run starts over from step 0.
  other = _regression(
    allow_changes="optax.lr,total_steps", **{"data.cache_dir": cache, "optax.lr": 3e-3}
  )
  results = driver.run(other, wd, log=lambda s: None)
  assert results["lr"] == 3e-3 and results["steps"] == 10
  history = workdir_lib.read_history(wd)
  assert [(h["event"], h["step"]) for h in history] == [("start", 0), ("resume", 10), ("rerun", 0)]
  assert min(r["step"] for r in writers.read_metrics(wd)) == 1  # the old metrics are gone

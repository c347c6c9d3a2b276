"""The run frame and its fit loop (camrep.runtime.frame) on a toy stage whose step compiles in
milliseconds: the dispatches (`spans`), K steps per dispatch giving K = 1's results, logging,
evaluation and checkpoints at their steps, a stop signal that saves and resumes exactly, the
finite policy, the plateau rule, the compile lines, and the frame's records. The real stages on
it: tests/test_frame_stages.py (K > 1 and resume of view synthesis and regression) and
tests/test_regression_resume.py (a regression killed and resumed from the command line).
"""

from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from camrep.runtime import frame as frame_lib
from camrep.runtime import session, writers
from camrep.runtime import workdir as workdir_lib
from tests.utils import snapshot


def _config(**kw) -> ml_collections.ConfigDict:
  c = ml_collections.ConfigDict()
  c.total_steps, c.log_every_steps, c.eval_every_steps = 12, 1, 4
  c.ckpt_every_steps, c.max_to_keep, c.steps_per_dispatch = 4, 2, 1
  c.allow_changes = ""
  c.stop = ml_collections.ConfigDict(dict(min_improvement=0.0, window=0.25, min_steps=0))
  for k, v in kw.items():
    if k.startswith("stop_"):
      c.stop[k[5:]] = v
    else:
      c[k] = v
  return c


class Toy(frame_lib.Stage):
  """w <- 0.5 w + x_step (x_step = sin(step)), and at `nan_at` a NaN: the update is skipped."""

  def __init__(self, nan_at: int | None = None):
    self.nan_at, self.writer, self.compiles = nan_at, None, []

  def init(self):
    return {"w": jnp.float32(1.0), "step": jnp.int32(0)}

  def saved(self, state):
    return jax.tree.map(np.asarray, state)

  def restored(self, saved):
    return jax.tree.map(jnp.asarray, saved)

  def _step(self, state, x):
    w = 0.5 * state["w"] + x
    finite = jnp.isfinite(w)
    new = {"w": jnp.where(finite, w, state["w"]), "step": state["step"] + 1}
    return new, {"train/loss": w, "train/finite": finite.astype(jnp.float32)}

  def dispatch(self, n):
    self.compiles.append(n)
    if n == 1:
      step = jax.jit(self._step)

      def one(state, x):
        state, m = step(state, x)
        return state, m, m["train/finite"]

      return one

    @jax.jit
    def chunk(state, xs):
      state, m = jax.lax.scan(self._step, state, xs)
      return state, m, jnp.min(m["train/finite"])

    return chunk

  def chunks(self, spans):
    for first, n in spans:
      xs = np.sin(np.arange(first, first + n, dtype=np.float32))
      if self.nan_at is not None and first <= self.nan_at < first + n:
        xs[self.nan_at - first] = np.nan
      yield xs[0] if n == 1 else xs

  def rows(self, metrics, n):
    host = jax.device_get(metrics)
    if n == 1:
      return [{k: float(v) for k, v in host.items()}]
    return [{k: float(v[i]) for k, v in host.items()} for i in range(n)]

  def evaluate(self, state, step):
    scalars = {"eval/w2": float(state["w"]) ** 2}
    self.writer.write_scalars(step, scalars)
    return scalars

  def score(self, row):
    return row.get("eval/w2")


def _run(config, workdir, *, stage=None, lines=None):
  """The toy's train_and_evaluate: frame, restore, begin, fit, finish."""
  stage = stage or Toy()
  rule = frame_lib.stopping_rule(config)
  log = lines.append if lines is not None else (lambda s: None)
  with frame_lib.Frame(str(workdir), config, schema=frame_lib.FIELDS, log=log) as frame:
    done = frame.already_complete(rule)
    if done is not None:
      return done
    state, start = frame.restore_or_init(stage.init, saved=stage.saved, restored=stage.restored)
    frame.begin(start)
    stage.writer = frame.writer
    fit = frame_lib.fit(frame, stage, state, start, rule=rule)
    if fit.complete:
      record = dict(fit.last)
      if rule.active:
        record["stopping"] = fit.stopping_record(rule, config.total_steps)
      frame.finish(fit.step, record)
    return fit


def _rows(workdir):
  return [{k: v for k, v in r.items() if k != "train/steps_per_sec"} for r in
          writers.read_metrics(str(workdir))]  # fmt: skip


def _checkpoints(workdir):
  return sorted(int(n) for n in os.listdir(os.path.join(workdir, "checkpoints")) if n.isdigit())


def test_spans_end_at_every_boundary_and_do_not_depend_on_the_start():
  assert list(frame_lib.spans(0, 10, 4, (5,))) == [(1, 4), (5, 1), (6, 3), (9, 2)]
  assert list(frame_lib.spans(0, 3, 1)) == [(1, 1), (2, 1), (3, 1)]
  assert list(frame_lib.spans(4, 4, 4)) == []
  full = list(frame_lib.spans(0, 100, 8, (12, 30, 0)))
  assert sum(n for _, n in full) == 100 and all(n <= 8 for _, n in full)
  for first, n in full:  # restarted at any dispatch end: the same dispatches from there
    end = first + n - 1
    assert list(frame_lib.spans(end, 100, 8, (12, 30, 0))) == [s for s in full if s[0] > end]


@pytest.mark.parametrize("k", [3, 4, 5])
def test_k_steps_per_dispatch_log_and_train_as_one(tmp_path, k):
  one, many = tmp_path / "one", tmp_path / "many"
  _run(_config(), one)
  stage = Toy()
  _run(_config(steps_per_dispatch=k), many, stage=stage)
  got, want = _rows(many), _rows(one)
  assert [r["step"] for r in got] == [r["step"] for r in want]
  for a, b in zip(got, want, strict=True):
    assert a.keys() == b.keys()
    for key in a:
      np.testing.assert_allclose(a[key], b[key], rtol=1e-6, err_msg=f"{a['step']} {key}")
  # Evaluations and checkpoints (every 4) at the same steps; dispatches of at most k steps, cut
  # at those steps, each length compiled once.
  assert _checkpoints(many) == _checkpoints(one) == [8, 12]
  assert sorted(stage.compiles) == sorted({n for _, n in frame_lib.spans(0, 12, k, (4, 4))})
  assert session.is_complete(str(many), 12)


def test_compile_lines_and_the_finished_record(tmp_path):
  lines = []
  _run(_config(steps_per_dispatch=2), tmp_path, lines=lines)
  assert lines[0] == "compiling the train step (2 steps per dispatch) ..."
  assert lines[1].startswith("compiled the train step in ") and lines[1].endswith(" s")
  final = session.read_final(str(tmp_path))
  assert final["complete"] is True and final["step"] == 12 and "eval/w2" in final
  assert not (tmp_path / workdir_lib.LOCK_FILE).exists()
  # The same command again: nothing to do, nothing written.
  before = snapshot(tmp_path)
  lines = []
  _run(_config(steps_per_dispatch=2), tmp_path, lines=lines)
  assert lines == [f"{tmp_path} is complete at step 12 (final_metrics.json); nothing to do"]
  assert snapshot(tmp_path) == before


def _stop_after(monkeypatch, dispatches: int):
  """A stop signal seen after the `dispatches`-th dispatch (as SIGTERM sets the flag)."""
  calls = iter(range(10**6))
  monkeypatch.setattr(
    frame_lib.preemption, "stop_requested", lambda handler: next(calls) + 1 >= dispatches
  )


@pytest.mark.parametrize("k", [1, 3])
def test_a_stop_signal_saves_and_the_same_command_resumes_exactly(tmp_path, monkeypatch, k):
  ref = tmp_path / "ref"
  _run(_config(steps_per_dispatch=k), ref)
  wd = tmp_path / "w"
  lines = []
  with monkeypatch.context() as m:
    _stop_after(m, 3)
    fit = _run(_config(steps_per_dispatch=k), wd, lines=lines)
  stopped_at = 3 if k == 1 else 6  # dispatches (1-3), (4), (5-6) with k = 3 (cut at 4, 8)
  assert fit.stopped and not fit.complete and fit.step == stopped_at
  assert lines[-1] == (
    f"stopping at step {stopped_at} on a stop signal; checkpoint saved in {wd}: run the same "
    "command to resume"
  )
  assert _checkpoints(wd)[-1] == stopped_at
  assert not (wd / workdir_lib.LOCK_FILE).exists()
  assert session.read_final(str(wd)) is None  # not complete
  lines = []
  _run(_config(steps_per_dispatch=k), wd, lines=lines)
  assert f"resumed from step {stopped_at} in {wd}" in lines
  assert _rows(wd) == _rows(ref)  # every logged value, bit for bit
  assert session.is_complete(str(wd), 12)
  history = workdir_lib.read_history(str(wd))
  assert [(h["event"], h["step"]) for h in history] == [("start", 0), ("resume", stopped_at)]


def test_a_non_finite_step_stops_the_run_naming_it_and_keeps_the_checkpoint(tmp_path):
  with pytest.raises(FloatingPointError, match="non-finite training values at step 6 "):
    _run(_config(steps_per_dispatch=3), tmp_path, stage=Toy(nan_at=6))
  # Dispatches (1-3), (4), (5-6): the flag of step 6 is read at its log step, before the save.
  assert _checkpoints(tmp_path) == [4]
  final = session.read_final(str(tmp_path))
  assert final["complete"] is False and final["stopped"] == "non-finite"
  assert "step 6" in final["reason"] and "started from step 0" in final["reason"]
  rows = _rows(tmp_path)
  assert rows[-1]["step"] == 6 and rows[-1]["train/finite"] == 0.0
  assert not (tmp_path / workdir_lib.LOCK_FILE).exists()


def test_the_plateau_rule_stops_at_an_evaluation_with_a_checkpoint(tmp_path):
  config = _config(total_steps=40, eval_every_steps=2, ckpt_every_steps=8, stop_min_improvement=0.5)
  fit = _run(config, tmp_path)
  assert fit.ended and fit.complete and fit.step < 40 and fit.step % 2 == 0
  assert _checkpoints(tmp_path)[-1] == fit.step
  final = session.read_final(str(tmp_path))
  assert final["step"] == fit.step and final["stopping"]["stopped_early"] is True
  assert [t for t, _ in final["stopping"]["curve"]] == list(range(2, fit.step + 1, 2))


def test_a_config_change_is_refused_unless_declared_and_allowed(tmp_path):
  _run(_config(), tmp_path)
  with pytest.raises(frame_lib.ConfigError, match="total_steps: 12 -> 16"):
    _run(_config(total_steps=16), tmp_path)
  fit = _run(_config(total_steps=16, allow_changes="total_steps"), tmp_path)
  assert fit.step == 16 and session.is_complete(str(tmp_path), 16)
  history = workdir_lib.read_history(str(tmp_path))
  assert history[-1]["changes"] == {"total_steps": [12, 16]}
  # A field the frame does not declare may not change (FIXED).
  c = _config(total_steps=16)
  c.width = 2
  old = json.loads((tmp_path / "config.json").read_text())
  old["width"] = 1
  (tmp_path / "config.json").write_text(json.dumps(old))
  c.allow_changes = "width"
  with pytest.raises(frame_lib.ConfigError, match="never allowed"):
    _run(c, tmp_path)

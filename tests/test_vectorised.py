"""Tests of the regression grid (camrep.regression.vectorised): seeds x lrs trained as one program.

Fast: member naming and checks, the unit-rate step against Adam(lr)'s, the group step (every
program, 1 and 2 steps per dispatch) against each member's own steps on a tiny car regressor, the
CPU loop on the members' own states, the members' placement over devices, and a member leaving the
group on non-finite values (listed and stacked states) while the other completes as it would
alone.
Slow: the grid end to end at configs/regression.py:car,smoke against runs trained alone, its
resume and its refusals; the command line's grid on two host devices (listed states), a member
leaving and another moving, against runs alone.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from camrep import pose_encodings, settings
from camrep.configs import regression as regression_config
from camrep.regression import driver, learner, runs, vectorised
from camrep.runtime.runconfig import ConfigError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
pytestmark = pytest.mark.usefixtures("fast_compile")
# Members against runs trained alone: float32 round-off of another summation order.
RTOL, ATOL = 1e-5, 1e-6


def _config(**kw):
  c = regression_config.get_config("car,smoke")
  c.representation = "euler"
  for k, v in kw.items():
    node = c
    *path, last = k.split(".")
    for p in path:
      node = node[p]
    node[last] = v
  return c


# ------------------------------------------------------------------------------ members


def test_member_names_configs_and_checks(tmp_path):
  assert vectorised.member_name(1e-3, 0) == "lr1e-3_seed0"
  assert vectorised.member_name(3e-4, 2) == "lr3e-4_seed2" and vectorised.lr_tag(1e-2) == "lr1e-2"
  base = _config()
  c = vectorised.member_config(base, 3e-3, 2)
  assert (c.optax.lr, c.seed) == (3e-3, 2) and (base.optax.lr, base.seed) != (3e-3, 2)
  ours = _config(representation="ours", synthesis_workdir="/runs/car_seed{seed}")
  assert vectorised.member_config(ours, 1e-3, 1).synthesis_workdir == "/runs/car_seed1"
  specs = vectorised.members(base, str(tmp_path), [1e-3, 3e-3], [0, 1])
  assert [os.path.basename(w) for w, _ in specs] == [
    "lr1e-3_seed0",
    "lr1e-3_seed1",
    "lr3e-3_seed0",
    "lr3e-3_seed1",
  ]
  assert [(r.config.optax.lr, r.config.seed) for _, r in specs] == [
    (1e-3, 0), (1e-3, 1), (3e-3, 0), (3e-3, 1),
  ]  # fmt: skip
  with pytest.raises(ConfigError, match="share a directory"):
    vectorised.members(base, str(tmp_path), [1e-3, 1.2e-3], [0])
  with pytest.raises(ConfigError, match="at least one lr"):
    vectorised.members(base, str(tmp_path), [], [0])
  with pytest.raises(ConfigError, match="member lr=0.001 seed=0: .*synthesis_workdir"):
    vectorised.members(ours, str(tmp_path), [1e-3], [0])  # /runs/car_seed0 is no directory


def test_command_line_errors(tmp_path):
  base = [sys.executable, "-m", "camrep.regression", "--config=configs/regression.py:car,smoke"]
  wd = f"--workdir={tmp_path / 'g'}"
  for args, message in (
    (["--lrs=1e-3,abc"], "error: --lrs=1e-3,abc: not a list of floats"),
    (["--lrs=1e-3", "--config.optax.lr=1e-3"], "error: --lrs sets each member's optax.lr"),
    (["--host_devices=2"], "error: --host_devices spreads a grid's members"),
  ):
    out = subprocess.run([*base, wd, *args], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 2 and out.stderr.strip().splitlines()[-1].startswith(message)
    assert "Traceback" not in out.stderr
  assert not (tmp_path / "g").exists()


# ------------------------------------------------------------------------- the group step


@pytest.fixture(scope="module")
def tiny():
  """A tiny car regressor, two members' states (their own init key and lr) and batches."""
  setting = settings.get("car")
  config = _config()
  config.optax.weight_decay = 1e-4  # the chained optimiser: add_decayed_weights, Adam, scale
  hp = learner.resolve_hparams(config, pose_encodings.get("euler"))
  reg = learner.make_regressor(setting, pose_encodings.get("euler"), hparams=hp, width=1 / 32)
  rng = np.random.default_rng(0)
  n_cols = len(setting.pose_columns)

  def batch(k):
    r = np.random.default_rng(k)
    return {
      "image": r.integers(0, 256, (4, 32, 32, 3), dtype=np.uint8),
      "pose": r.uniform(-1, 1, (4, n_cols)).astype(np.float32),
      "scene": np.zeros((4,), np.int32),
    }

  del rng
  lrs = (1e-3, 3e-2)
  states = [
    learner.init(
      jax.random.key(seed), dataclasses.replace(reg, hparams=dataclasses.replace(hp, lr=lr)),
      batch(0),
    )
    for seed, lr in zip((0, 1), lrs, strict=True)
  ]  # fmt: skip
  # each member its own data order
  batches = [[batch(10 * m + k) for k in range(2)] for m in range(2)]
  return states, lrs, batches


def test_the_unit_rate_step_is_adams_bit_for_bit(tiny):
  states, lrs, batches = tiny
  state, lr = states[1], lrs[1]
  unit = vectorised._unit([state])[0]
  assert unit.regressor.hparams.lr == 1.0
  assert jax.tree.structure(unit.opt_state) == jax.tree.structure(state.opt_state)
  a, ma = jax.jit(learner.train_step)(state, batches[1][0])
  b, mb = jax.jit(learner.train_step)(unit, batches[1][0], jnp.float32(lr))
  for x, y in zip(jax.tree.leaves(a.params), jax.tree.leaves(b.params), strict=True):
    np.testing.assert_array_equal(x, y)
  assert float(ma["loss"]) == float(mb["loss"])
  # without the lr, the unit state's update is Adam(1)'s: another run
  c, _ = jax.jit(learner.train_step)(unit, batches[1][0])
  assert not np.allclose(jax.tree.leaves(c.params)[0], jax.tree.leaves(a.params)[0])


@pytest.mark.parametrize("program", ["loop", "unrolled", "vmap"])
@pytest.mark.parametrize("n", [1, 2])
def test_the_group_step_equals_each_members_own_steps(tiny, program, n):
  states, lrs, batches = tiny
  alone = []
  for state, bs in zip(states, batches, strict=True):
    ms = []
    for b in bs:
      state, m = jax.jit(learner.train_step)(state, b)
      ms.append(m)
    alone.append((state, ms))
  unit = vectorised._unit(states)
  if vectorised.listed(program):  # the members' own states, donated: copies of the fixture's
    group, rates, pack = [jax.tree.map(jnp.copy, s) for s in unit], list(lrs), list
  else:
    group, rates, pack = vectorised.stack(unit), jnp.asarray(lrs, jnp.float32), vectorised.stack
  fn = vectorised.group_step(n, program)
  if n == 1:
    metrics = []
    for k in range(2):
      group, m, ok = fn(group, pack([bs[k] for bs in batches]), rates)
      metrics.append(m)
      assert ok.shape == (2,) and np.all(np.asarray(ok) == 1)
    losses = np.stack([np.asarray(m["loss"]) for m in metrics], axis=1)  # (M, steps)
  else:
    group, m, ok = fn(group, pack([vectorised.stack(bs) for bs in batches]), rates)  # (n, ...)
    losses = np.asarray(m["loss"])
    assert ok.shape == (2,) and losses.shape == (2, 2)
  for i, (state, ms) in enumerate(alone):
    np.testing.assert_allclose(losses[i], [float(x["loss"]) for x in ms], rtol=RTOL)
    member = group[i] if vectorised.listed(program) else vectorised.unstack(group, i)
    assert int(member.step) == 2
    for x, y in zip(jax.tree.leaves(state.params), jax.tree.leaves(member.params), strict=True):
      np.testing.assert_allclose(x, y, rtol=RTOL, atol=ATOL)
    for x, y in zip(
      jax.tree.leaves(state.opt_state), jax.tree.leaves(member.opt_state), strict=True
    ):
      np.testing.assert_allclose(x, y, rtol=RTOL, atol=ATOL)
  # the two members trained apart: their own lr and init
  assert not np.allclose(losses[0], losses[1])


def test_resolve_program():
  auto = "loop" if jax.default_backend() == "cpu" else "vmap"
  assert vectorised.resolve_program("auto") == auto
  assert vectorised.resolve_program("vmap") == "vmap"
  with pytest.raises(ValueError, match="program must be one of"):
    vectorised.resolve_program("scan")


def test_the_cpu_loop_steps_each_members_own_state_with_one_compile():
  """The "loop" program steps each member's own state (listed, never stacked; updated in place:
  donated) with one compiled step for every member and group size; only the metrics are
  stacked."""
  traces = []

  def step(state, batch, lr):
    traces.append(1)  # at trace time only
    return jax.tree.map(lambda x: x - lr * batch, state), {"loss": jnp.sum(state["w"])}, 1.0

  fn = vectorised._looped(step)
  states = [{"w": jnp.arange(3.0) + 3 * i} for i in range(4)]
  lrs = [np.float32(x) for x in (0.1, 0.2, 0.3, 0.4)]
  out, metrics, ok = fn(states, [np.ones(3, np.float32)] * 4, lrs)
  assert isinstance(out, list) and len(traces) == 1
  for i, w in enumerate(out):
    np.testing.assert_allclose(w["w"], np.arange(3.0) + 3 * i - lrs[i])
  if jax.default_backend() == "cpu":
    assert states[0]["w"].is_deleted()  # donated: the step reused its buffer
  np.testing.assert_array_equal(metrics["loss"], [3.0, 12.0, 21.0, 30.0])
  assert ok.shape == (4,)
  fn(out[:2], [np.ones(3, np.float32)] * 2, lrs[:2])  # a smaller group: no new member step
  assert len(traces) == 1
  assert vectorised.listed("loop") and not vectorised.listed("vmap")
  assert vectorised.group_step(1, "loop") is vectorised.group_step(1, "loop")


def test_members_are_placed_in_turn_and_rebalanced_with_the_fewest_moves():
  """Listed members over several devices (`vectorised.place`, `rebalance`): in turn; after members
  leave, no device holds 2 or more members more than another, by the fewest moves."""
  devices = ["a", "b"]
  assert vectorised.place(5, devices) == ["a", "b", "a", "b", "a"]
  assert vectorised.place(2, ["a"]) == ["a", "a"]
  assert vectorised.rebalance(["a", "a"], devices) == ["a", "b"]  # b's member left
  assert vectorised.rebalance(["a", "a", "a", "b"], devices) == ["a", "a", "b", "b"]
  assert vectorised.rebalance(["a", "b", "a"], devices) == ["a", "b", "a"]  # unchanged
  assert vectorised.rebalance(["a", "a", "a", "a"], ["a", "b", "c"]) == ["a", "a", "c", "b"]
  assert vectorised.rebalance([], devices) == []


# --------------------------------------------------------------------------- end to end


def _files(wd: str) -> set[str]:
  out = set()
  for d, _, names in os.walk(wd):
    rel = os.path.relpath(d, wd)
    if rel.startswith("checkpoints"):
      continue
    # TensorBoard's event file is named by its time and host
    out |= {os.path.normpath(os.path.join(rel, n.split(".out.")[0])) for n in names}
  return out


def _metrics(wd: str) -> list[dict]:
  with open(os.path.join(wd, "metrics.jsonl")) as f:
    return [json.loads(x) for x in f]


def _close(a, b, path=""):
  """Nested JSON values equal, numbers within RTOL / ATOL."""
  if isinstance(a, dict):
    assert set(a) == set(b), path
    for k in a:
      _close(a[k], b[k], f"{path}.{k}")
  elif isinstance(a, list):
    assert len(a) == len(b), path
    for i, (x, y) in enumerate(zip(a, b, strict=True)):
      _close(x, y, f"{path}[{i}]")
  elif isinstance(a, float):
    np.testing.assert_allclose(a, b, rtol=RTOL, atol=ATOL, err_msg=path)
  else:
    assert a == b, path


@pytest.mark.slow
def test_members_equal_runs_trained_alone_and_resume_as_a_group(tmp_path):
  cache = str(tmp_path / "cache")
  config = _config(**{"data.cache_dir": cache, "eval_every_steps": 2})
  gdir = str(tmp_path / "grid")
  lines = []
  results = vectorised.run(config, gdir, lrs=[1e-3, 3e-3], seeds=[0, 1], log=lines.append)
  assert [(r["lr"], r["seed"]) for r in results] == [(1e-3, 0), (1e-3, 1), (3e-3, 0), (3e-3, 1)]
  assert any("training 4 members together from step 0" in x for x in lines)
  for lr, seed in ((1e-3, 0), (3e-3, 1)):
    name = vectorised.member_name(lr, seed)
    member, alone = os.path.join(gdir, name), str(tmp_path / "alone" / name)
    r_alone = driver.run(vectorised.member_config(config, lr, seed), alone, log=lambda s: None)
    r_member = driver.read_results(member)
    assert r_member["grid"] == {"lrs": [1e-3, 3e-3], "seeds": [0, 1]}
    skip = {"grid", "train_seconds", "steps_per_sec", "eval_seconds", "machine"}
    _close({k: v for k, v in r_member.items() if k not in skip}, {
      k: v for k, v in r_alone.items() if k not in skip
    })  # fmt: skip
    assert _files(member) == _files(alone)
    for f in ("config.json", "record.json"):
      with open(os.path.join(member, f)) as a, open(os.path.join(alone, f)) as b:
        assert json.load(a) == json.load(b)
    rows = [_metrics(member), _metrics(alone)]
    assert [r["step"] for r in rows[0]] == [r["step"] for r in rows[1]]
    for x, y in zip(*rows, strict=True):
      _close(x, y)
    for split in ("test",):
      a = np.load(os.path.join(member, f"errors_{split}.npz"))
      b = np.load(os.path.join(alone, f"errors_{split}.npz"))
      assert set(a.files) == set(b.files)
      for k in a.files:
        if a[k].dtype.kind == "f":
          np.testing.assert_allclose(a[k], b[k], rtol=RTOL, atol=1e-4, err_msg=k)
        else:
          np.testing.assert_array_equal(a[k], b[k])
    with open(os.path.join(member, "final_metrics.json")) as f:
      assert json.load(f)["complete"] is True
  # Complete: nothing to do.
  lines.clear()
  done = vectorised.run(config, gdir, lrs=[1e-3, 3e-3], seeds=[0, 1], log=lines.append)
  assert done == json.loads(json.dumps(results))
  assert not any("training" in x for x in lines)
  # SIGTERM after the first step: every member saves a checkpoint and the group stops.
  gdir2 = str(tmp_path / "grid2")

  def stop_after_compiling(line):
    if line.startswith("compiled in"):
      os.kill(os.getpid(), signal.SIGTERM)

  assert (
    vectorised.run(config, gdir2, lrs=[1e-3, 3e-3], seeds=[0, 1], log=stop_after_compiling) is None
  )
  for name in os.listdir(gdir2):
    assert os.listdir(os.path.join(gdir2, name, "checkpoints")) == ["1"]
    assert not os.path.exists(os.path.join(gdir2, name, "results.json"))
  # Unfinished members at different steps (seed 2 would start at 0): refused, nothing written.
  with pytest.raises(ConfigError, match="resume from different steps"):
    vectorised.run(config, gdir2, lrs=[1e-3, 3e-3], seeds=[0, 2], log=lambda s: None)
  assert not os.path.exists(os.path.join(gdir2, "lr1e-3_seed2"))
  # The same command resumes the whole group from step 1, to what the uninterrupted grid gave.
  lines.clear()
  resumed = vectorised.run(config, gdir2, lrs=[1e-3, 3e-3], seeds=[0, 1], log=lines.append)
  assert sum("resumed from step 1" in x for x in lines) == 4
  assert any("training 4 members together from step 1" in x for x in lines)
  for a, b in zip(resumed, results, strict=True):
    _close({k: a[k] for k in ("validation", "test", "final_train")}, {
      k: b[k] for k in ("validation", "test", "final_train")
    })  # fmt: skip


@pytest.fixture(scope="module")
def non_finite_case(tmp_path_factory):
  """A 6-step car smoke config (its data cached once) and the results of its lr 1e-3 and 3e-3
  seed 0 runs trained alone ({lr: results.json}; their workdirs: `_ALONE`), shared by the group's
  forms."""
  cache = str(tmp_path_factory.mktemp("cache"))
  config = _config(**{"data.cache_dir": cache, "total_steps": 6})
  alone = {}
  for lr in (1e-3, 3e-3):
    wd = _ALONE[lr] = str(tmp_path_factory.mktemp("alone") / vectorised.member_name(lr, 0))
    alone[lr] = driver.run(vectorised.member_config(config, lr, 0), wd, log=lambda s: None)
  return config, alone


_ALONE: dict[float, str] = {}


def test_a_run_restored_from_an_archive_is_not_trained_again(tmp_path, non_finite_case):
  """A member whose workdir holds only a finished run's archived record (run.json,
  `camrep.comparison.archive.restore`) is complete: nothing trained or written; a record of
  another seed there, or one cut short, is refused."""
  config, alone = non_finite_case
  record = runs.compact(runs.load(_ALONE[1e-3], arrays=True))
  for name in ("lr1e-3_seed0", "lr1e-3_seed1"):  # the second: seed 0's record
    os.makedirs(tmp_path / name)
    runs.write_record(record, str(tmp_path / name / runs.RECORD_FILE))
  lines = []
  (out,) = vectorised.run(config, str(tmp_path), lrs=[1e-3], seeds=[0], log=lines.append)
  assert out["test"] == json.loads(json.dumps(alone[1e-3]["test"]))
  assert os.listdir(tmp_path / "lr1e-3_seed0") == [runs.RECORD_FILE]
  assert any("restored from an archive (run.json); nothing to do" in x for x in lines), lines
  assert not any(x.startswith("training") for x in lines)
  alone_run = driver.run(vectorised.member_config(config, 1e-3, 0), str(tmp_path / "lr1e-3_seed0"))
  assert alone_run["test"] == out["test"]  # the single run's command: nothing to do either
  assert os.listdir(tmp_path / "lr1e-3_seed0") == [runs.RECORD_FILE]
  with pytest.raises(ConfigError, match="run.json.* with seed=0, not 1: move it away"):
    vectorised.run(config, str(tmp_path), lrs=[1e-3], seeds=[1], log=lambda s: None)
  assert os.listdir(tmp_path / "lr1e-3_seed1") == [runs.RECORD_FILE]
  os.makedirs(tmp_path / "lr1e-3_seed2")
  (tmp_path / "lr1e-3_seed2" / runs.RECORD_FILE).write_text('{"format": 1, "ki')  # cut short
  with pytest.raises(ConfigError, match="lr1e-3_seed2"):
    vectorised.run(config, str(tmp_path), lrs=[1e-3], seeds=[2], log=lambda s: None)


def _finals(gdir: str, lr: float) -> dict:
  r = driver.read_results(os.path.join(gdir, vectorised.member_name(lr, 0)))
  return {k: r[k] for k in ("validation", "test", "final_train")}


def _stopped_non_finite(gdir: str) -> None:
  with open(os.path.join(gdir, "lr1e+38_seed0", "final_metrics.json")) as f:
    bad = json.load(f)
  assert bad["complete"] is False and bad["stopped"] == "non-finite"


@pytest.mark.parametrize("program", ["loop", "vmap"])
def test_a_member_gone_non_finite_leaves_and_the_other_completes(
  tmp_path, program, non_finite_case
):
  """A member whose values become non-finite (lr 1e38) leaves the group, its stop recorded; the
  other trains on to the end and completes as it would alone; the grid then raises. Both forms of
  the group's states: listed ("loop", here on one device; on two: the next test) and stacked
  ("vmap")."""
  config, alone = non_finite_case
  gdir, lines = str(tmp_path / "grid"), []
  with pytest.raises(FloatingPointError, match="1 of 2 members stopped on non-finite values"):
    vectorised.run(config, gdir, lrs=[1e-3, 1e38], seeds=[0], log=lines.append, program=program)
  assert any("lr1e+38_seed0: non-finite training values at step" in x for x in lines), lines
  _stopped_non_finite(gdir)
  _close(_finals(gdir, 1e-3), {k: alone[1e-3][k] for k in ("validation", "test", "final_train")})
  assert [r["step"] for r in _metrics(os.path.join(gdir, "lr1e-3_seed0"))][-1] == 6


@pytest.mark.slow
def test_members_on_two_host_devices_leave_rebalance_and_equal_runs_alone(
  tmp_path, non_finite_case
):
  """The command line's grid on a CPU shown as two one-thread host devices (`--host_devices=2`):
  the listed members placed in turn (lr 1e-3 and 3e-3 on the first, 1e38 on the second); the
  non-finite member leaves (exit status 3), the lr 3e-3 member moves to the emptied device, and
  both others complete as they would alone."""
  config, alone = non_finite_case
  gdir = str(tmp_path / "grid")
  out = subprocess.run(
    [
      sys.executable, "-m", "camrep.regression", "--config=configs/regression.py:car,smoke",
      f"--workdir={gdir}", "--lrs=1e-3,1e38,3e-3", "--seeds=0", "--host_devices=2",
      "--config.representation=euler", f"--config.data.cache_dir={config.data.cache_dir}",
      f"--config.total_steps={config.total_steps}",
    ],
    cwd=ROOT, capture_output=True, text=True, timeout=600,
  )  # fmt: skip
  assert out.returncode == 3, out.stderr[-3000:]
  assert "their steps spread over 2 devices" in out.stdout, out.stdout
  assert "lr1e+38_seed0: non-finite training values at step" in out.stdout
  assert "lr3e-3_seed0: moves to cpu:1, the members rebalanced" in out.stdout, out.stdout
  assert "Traceback" not in out.stderr
  _stopped_non_finite(gdir)
  for lr in (1e-3, 3e-3):
    _close(_finals(gdir, lr), {k: alone[lr][k] for k in ("validation", "test", "final_train")})
    assert [r["step"] for r in _metrics(os.path.join(gdir, vectorised.member_name(lr, 0)))][-1] == 6

"""The measuring logic of the benchmark scripts (`camrep.bench`), on tiny or fake work."""

from __future__ import annotations

import numpy as np
import pytest

from camrep.bench import lie as bench_lie
from camrep.bench import train_step as bench_train_step


class _FakeTimer:
  """A StepTimer stand-in: fixed step times per call, known FLOPs and images."""

  def __init__(self, seconds, flops=10.0, images=5):
    self._seconds = list(seconds)
    self.flops, self.images, self.xla_flops = flops, images, flops
    self.compile_s, self.finite = 1.0, 1.0

  def times(self, steps):
    return [self._seconds.pop(0)] * steps


def test_interleaved_divides_each_round_by_its_own_peak(monkeypatch):
  bts = bench_train_step
  order = []
  peaks = iter([100.0, 50.0, 20.0])

  def fake_peak(n, reps, dtype, cpu=False):
    order.append(("peak", dtype))
    p = next(peaks)
    return (p, 2 * p) if cpu else p

  monkeypatch.setattr(bts, "matmul_peak", fake_peak)
  # Round k: step of 1 / (peak_k / 10 / mfu) seconds with an MFU of 0.5 against that round's
  # peak, so a loaded round (low peak, slow step) gives the same MFU.
  timer = _FakeTimer([10 / (0.5 * p) for p in (100.0, 50.0, 20.0)])
  out = bts.interleaved({"f32": (timer, "float32")}, rounds=3, steps=2)
  assert [o[0] for o in order] == ["peak"] * 3
  r = out["f32"]
  np.testing.assert_allclose([r["mfu"][k] for k in ("median", "min", "max")], 0.5)
  assert r["sec"]["n"] == 3 and r["sec"]["min"] == pytest.approx(0.2)
  assert r["sec"]["max"] == pytest.approx(1.0)
  assert r["images_per_s"]["median"] == pytest.approx(5 / 0.4)
  assert out["peaks"]["float32"]["median"] == 50.0
  assert out["cpu_peaks"]["float32"]["median"] == 100.0
  assert 0 < r["cpu_mfu"]["median"]
  assert bts.format_spread(r["sec"]) == "0.400 (0.200-1.000, n=3)"


def test_lie_apply_ratio_is_measured_per_round():
  r = bench_lie.apply_ratio(pairs=16, n_blocks=2, s=4, rounds=2, calls=1)
  assert len(r["ratios"]) == len(r["taylor2"]) == len(r["spectral"]) == 2
  np.testing.assert_allclose(r["ratios"], np.array(r["spectral"]) / np.array(r["taylor2"]))
  assert min(r["taylor2"]) > 0 and min(r["spectral"]) > 0


@pytest.mark.slow
@pytest.mark.usefixtures("fast_compile")  # times a step; compiling it dominates
def test_regression_timer_builds_and_times_the_learners_step(tmp_path):
  """`RegressionTimer` builds the driver's training batch and step of a setting (GQN, :smoke) with
  the regressor's conv gradients replaced as asked, and times it."""
  bts = bench_train_step
  timer = bts.RegressionTimer(
    "gqn", variant="smoke", cache_dir=str(tmp_path), weight_grad="matmul", log=lambda *_: None
  )
  assert timer.weight_grad == "matmul"
  assert timer.images == 2 * (3 + 2)  # :smoke gqn: 2 scenes x (3 context + 2 query) views
  assert timer.flops > 0 and timer.finite == 1.0
  times = timer.times(2)
  assert len(times) == 2 and all(t > 0 for t in times)
  default = bts.RegressionTimer("gqn", variant="smoke", cache_dir=str(tmp_path))
  assert default.weight_grad == "by_channels"


@pytest.mark.slow
@pytest.mark.usefixtures("fast_compile")
def test_the_regression_steps_are_compared_across_strided_input_gradients(tmp_path, capsys):
  """`--skip_synthesis --regression car --regression_strided s2d,xla`: one regression step of
  each mode, traced under it, timed in turn and printed with its mode."""
  bench_train_step.main(
    ["--skip_synthesis", "--regression", "car", "--regression_variant", "smoke"]
    + ["--regression_strided", "s2d,xla", "--regression_cache", str(tmp_path)]
    + ["--steps", "1", "--repeats", "1"]
  )
  out = capsys.readouterr().out
  for mode in ("s2d", "xla"):
    assert (
      f"regression step, car (smoke, quat, 4 images/step, weight grad by_channels, "
      f"strided input grad {mode}): s/step" in out
    ), out


class _Flag:
  """A metric that counts how often the host reads it."""

  reads = 0

  def __array__(self, dtype=None, copy=None):
    _Flag.reads += 1
    return np.ones((1,), dtype or np.float32)


def test_the_timed_loop_reads_the_metrics_only_at_log_steps():
  """`host.train_loop` runs the loop as camrep.synthesis.train does: no per-step host read, so
  the device runs ahead; the metrics of the steps since the last read are checked at log steps."""
  from camrep.bench import host

  _Flag.reads = 0
  calls = []

  def step(state, batch, key):
    calls.append(batch)
    return state + 1, {"train/finite": _Flag()}

  batches = iter(range(100))
  rates, state = host.train_loop(step, 0, batches, None, steps=10, warmup=2, log_every=4)
  assert len(calls) == 12 and state == 12
  assert _Flag.reads == 10  # steps 4, 8 and the last (10) read their pending metrics, once each
  assert rates["steps_per_s"] > 0 and rates["cpu_s_per_step"] >= 0


def test_the_host_loop_stubs_the_renderer_and_the_step():
  """The loop at a config's layout with the renderer and the step stubbed: no image is
  rendered, the batches have the layout's shape, and the host's time a step is measured."""
  from camrep.bench import host
  from camrep.configs import gqn
  from camrep.data.feed import pipeline as pipeline_lib

  config = gqn.get_config("smoke")
  config.data.in_memory = False
  rendered = []
  real = pipeline_lib.RenderPipeline.batch

  def batch(self, step):
    b = real(self, step)
    rendered.append(int(np.asarray(b["image"]).max()))
    return b

  pipeline_lib.RenderPipeline.batch = batch
  try:
    r = host.host_loop(config, steps=3, warmup=1)
  finally:
    pipeline_lib.RenderPipeline.batch = real
  assert rendered and max(rendered) == 0  # blank images: the stub, not the renderer
  assert r["layout"] == "1 x 2 scenes x 4 views" and r["host_ms_per_step"] > 0


def test_the_stubbed_family_survives_pickling_into_a_table_building_worker():
  """On a machine with many cores the scene table is built in spawned processes, which receive
  the stubbed family pickled: it must unpickle (no recursion through its delegation) and build the
  same rows as the family it wraps."""
  import pickle

  from camrep.bench import host
  from camrep.configs import gqn
  from camrep.data import sources
  from camrep.data.procedural import scene_table

  family = sources.family_of_config(gqn.get_config("smoke").data)
  stub = pickle.loads(pickle.dumps(host._StubFamily(family)))
  assert stub.image_size == family.image_size
  assert stub.render_batch([0], np.zeros((1, 2))).max() == 0
  ids = [0, 3, 1]
  a = scene_table.SceneTable.build(stub, "train", ids)
  b = scene_table.SceneTable.build(family, "train", ids)
  np.testing.assert_array_equal(a.poses, b.poses)
  np.testing.assert_array_equal(a.num_views, b.num_views)


@pytest.mark.slow
def test_the_grid_benchmark_times_both_programs_against_the_runs_alone(tmp_path):
  """`camrep.bench.regression_grid`: the members of a small grid (car :smoke, 2 seeds x 2 lrs)
  timed as each group program and one after another, interleaved."""
  from camrep.bench import regression_grid

  timer = regression_grid.GridTimer(
    "car", variant="smoke", representation="euler", seeds=[0, 1], lrs=[1e-3, 3e-3], steps=2,
    cache_dir=str(tmp_path), log=lambda *_: None,
  )  # fmt: skip
  assert timer.members == 4
  assert set(timer.compile_s) == {"loop", "unrolled", "vmap", "sequential"}
  out = regression_grid.measure(timer, rounds=2, log=lambda *_: None)
  assert len(out["rounds"]) == 2 and out["sequential"]["member_steps_per_s"] > 0
  for p in ("loop", "unrolled", "vmap"):
    assert out[p]["speedup"] > 0
    assert out[p]["member_steps_per_s"] == pytest.approx(4 * out[p]["steps_per_s_per_member"])


@pytest.mark.slow
def test_the_grid_benchmark_on_host_devices_times_two_processes_in_turn(tmp_path, capsys):
  """`camrep.bench.regression_grid --host_devices=2`: the group in a process of two one-thread
  host devices, the runs alone in one of one device, timed in turn; the summary line."""
  from camrep.bench import regression_grid

  regression_grid.main([
    "--setting=car", "--variant=smoke", "--representation=euler", "--seeds=0",
    "--lrs=1e-3,3e-3", "--steps=1", "--rounds=1", "--programs=loop", "--host_devices=2",
    f"--cache={tmp_path}",
  ])  # fmt: skip
  out = capsys.readouterr().out
  assert "grid process: devices ['cpu:0', 'cpu:1']" in out
  assert "sequential process: devices ['cpu:0']" in out
  assert "the group on 2 host devices" in out
  last = dict(x.split("=") for x in out.strip().splitlines()[-1].split())
  assert last["program"] == "loop" and float(last["speedup"]) > 0
  with pytest.raises(SystemExit):
    regression_grid.main(["--host_devices=0"])
  assert "--host_devices must be >= 1" in capsys.readouterr().err


def test_the_conditioning_benchmark_times_each_camera_against_the_baseline(capsys):
  """`camrep.bench.conditionings` at :smoke: each conditioning's step built and timed in one
  process, a row per camera and the ratios line; a camera it does not know is a usage error."""
  from camrep.bench import conditionings

  argv = ["--variant=smoke", "--cameras=raymap,learned_rel", "--steps=1", "--rounds=2"]
  conditionings.main(argv)
  out = capsys.readouterr().out
  rows = [line for line in out.splitlines() if line.startswith(("| raymap", "| learned_rel"))]
  assert len(rows) == 2 and rows[0].endswith("| 1.00 |")
  last = out.strip().splitlines()[-1].split()
  assert last[0] == "baseline=raymap" and last[1] == "raymap=1.000"
  assert last[2].startswith("learned_rel=") and float(last[2].split("=")[1]) > 0
  with pytest.raises(SystemExit):
    conditionings.main(["--cameras=raymap,plucker"])
  assert "unknown cameras ['plucker']" in capsys.readouterr().err
  with pytest.raises(SystemExit):
    conditionings.main(["--cameras=none", "--baseline=raymap"])
  assert "--baseline raymap is not among --cameras" in capsys.readouterr().err

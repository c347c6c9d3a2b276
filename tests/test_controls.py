"""The control targets of the comparison: "untrained" (the learned grid of a view-synthesis run at
its random initialisation) and "frozen_gen" (the learned grid of a run whose generators B stayed
at their initial values, `rep.freeze_generators`), each regressed exactly as "ours".

At smoke size: a car view-synthesis run of 2 steps with and without frozen generators, then
regressions of each control through the driver.
"""

from __future__ import annotations

import os
import shutil

import jax
import numpy as np
import pytest

from camrep import pose_encodings
from camrep.configs import regression as regression_config
from camrep.configs import shapenet_car
from camrep.regression import config_schema as reg_schema
from camrep.regression import driver as R
from camrep.regression import pose_system, runs
from camrep.regression import targets as T
from camrep.runtime import runconfig
from camrep.synthesis import restore, train
from camrep.synthesis import step as step_lib

# Two view-synthesis runs and two regressions: ~3 min on the loaded 2-core CPU.
# One worker for the module: its two trained runs (module fixtures) are then built once.
pytestmark = [
  pytest.mark.usefixtures("fast_compile"),
  pytest.mark.slow,
  pytest.mark.xdist_group("controls"),
]


def _synthesis(tmp_path_factory, name, **rep):
  config = shapenet_car.get_config("smoke")
  config.total_steps = 2
  config.evals.num_scenes = 1
  config.rep.update(rep)
  wd = str(tmp_path_factory.mktemp("synthesis") / name)
  train.train_and_evaluate(config, wd, log=lambda s: None)
  return wd


@pytest.fixture(scope="module")
def learned(car_smoke_run):
  """The session's shared car run (`conftest.car_smoke_run`: 2 steps, as `_synthesis`'s)."""
  return car_smoke_run


@pytest.fixture(scope="module")
def frozen(tmp_path_factory):
  return _synthesis(tmp_path_factory, "car_frozen_gen", freeze_generators=True)


def _regression(representation, synthesis_workdir, cache):
  c = regression_config.get_config("car,smoke")
  c.representation = representation
  c.synthesis_workdir = synthesis_workdir
  c.data.cache_dir = cache
  return c


def _leaves(params, generators: bool):
  """{path: array} of the generator leaves ("*_coeffs") or of the others."""
  flat = jax.tree_util.tree_flatten_with_path(params)[0]
  return {
    jax.tree_util.keystr(p): np.asarray(v)
    for p, v in flat
    if str(p[-1].key).endswith("_coeffs") == generators
  }


def _initial_rep(workdir):
  run = restore.load_run(workdir)
  init = step_lib.init_fn(run.config, run.model, step_lib.make_optimizers(run.config))
  return run, init().params["rep"]


def test_the_controls_are_registered_learned_grids():
  for name in ("untrained", "frozen_gen"):
    cls = pose_encodings.get(name)
    assert name in T.REPRESENTATIONS and name in T.LEARNED and name not in T.BASELINES
    assert cls.trained_by() is pose_encodings.GridEncoding and cls.needs_synthesis
    assert name not in pose_encodings.SYNTHESIS_KINDS
  assert pose_encodings.get("untrained").initial_state
  assert pose_encodings.get("frozen_gen").frozen_generators


def test_frozen_generators_stay_at_their_initial_values(frozen, learned):
  run, init = _initial_rep(frozen)
  assert run.step == 2
  gens, init_gens = _leaves(run.params["rep"], True), _leaves(init, True)
  assert gens and gens.keys() == init_gens.keys()
  for k in gens:
    np.testing.assert_array_equal(gens[k], init_gens[k])  # bit for bit
  # The grid vectors learned.
  grid, init_grid = _leaves(run.params["rep"], False), _leaves(init, False)
  assert any(not np.array_equal(grid[k], init_grid[k]) for k in grid)
  # Without the flag the generators learn (the test above could not pass by accident).
  run, init = _initial_rep(learned)
  gens, init_gens = _leaves(run.params["rep"], True), _leaves(init, True)
  assert any(not np.array_equal(gens[k], init_gens[k]) for k in gens)


def test_untrained_reads_the_runs_initial_pose_system(tmp_path, learned):
  _, init = _initial_rep(learned)
  config = _regression("untrained", learned, str(tmp_path / "cache"))
  spec, rep, info = pose_system.representation_params(reg_schema.check(config))
  assert info["source"] == "synthesis" and info["state"] == "initial"
  assert pose_system.params_digest(rep) == pose_system.params_digest(init)
  ours = _regression("ours", learned, str(tmp_path / "cache"))
  _, trained, _ = pose_system.representation_params(reg_schema.check(ours))
  assert pose_system.params_digest(trained) != pose_system.params_digest(rep)
  # A workdir an archive restored (config.json and record.json beside its record, no checkpoint)
  # gives the same initial pose system; "ours" needs the trained one and refuses it.
  restored = tmp_path / "restored"
  restored.mkdir()
  for name in ("config.json", "record.json"):
    shutil.copy(os.path.join(learned, name), restored / name)
  config = _regression("untrained", str(restored), str(tmp_path / "cache"))
  _, again, info = pose_system.representation_params(reg_schema.check(config))
  assert pose_system.params_digest(again) == pose_system.params_digest(init)
  assert info["state"] == "initial" and info["step"] is None
  ours = _regression("ours", str(restored), str(tmp_path / "cache"))
  with pytest.raises(runconfig.ConfigError, match="has no checkpoint"):
    pose_system.representation_params(reg_schema.check(ours))


def test_a_restored_workdir_gives_the_final_pose_system_from_its_pose_file(
  tmp_path, learned, frozen
):
  """A complete run leaves its final pose system in pose_system.npz; a workdir holding only that,
  config.json and record.json (an archive's) gives "ours" and "frozen_gen" the pose system the
  final checkpoint holds, bit for bit, and names a file that does not match the config."""
  cache = str(tmp_path / "cache")
  for rep, syn in (("ours", learned), ("frozen_gen", frozen)):
    _, trained, info = pose_system.representation_params(
      reg_schema.check(_regression(rep, syn, cache))
    )
    restored = tmp_path / f"restored_{rep}"
    restored.mkdir()
    for name in ("config.json", "record.json", restore.POSE_FILE):
      shutil.copy(os.path.join(syn, name), restored / name)
    _, again, again_info = pose_system.representation_params(
      reg_schema.check(_regression(rep, str(restored), cache))
    )
    assert again_info["digest"] == info["digest"] == pose_system.params_digest(trained)
    assert again_info["step"] == info["step"] == 2
    # Complete by its record (an archive's run.json; no final_metrics.json there), at that step.
    assert "no final_metrics.json" in R.synthesis_state(str(restored), 2)
    runs.write_record(runs.compact(runs.load(syn)), str(restored / runs.RECORD_FILE))
    assert R.synthesis_state(str(restored), 2) is None
  with np.load(restored / restore.POSE_FILE) as f:
    arrays = {k: f[k] for k in f.files}
  key = next(k for k in arrays if k.endswith("['grid']"))
  arrays[key] = arrays[key][:-1]
  np.savez(restored / restore.POSE_FILE, **arrays)
  with pytest.raises(runconfig.ConfigError, match=r"the run's config makes float32\["):
    pose_system.representation_params(
      reg_schema.check(_regression("frozen_gen", str(restored), cache))
    )


def test_controls_train_through_regression(tmp_path, learned, frozen):
  cache = str(tmp_path / "cache")
  for rep, syn in (("untrained", learned), ("frozen_gen", frozen)):
    results = R.run(_regression(rep, syn, cache), str(tmp_path / rep), log=lambda s: None)
    assert results["representation"] == rep
    assert results["representation_params"]["source"] == "synthesis"
    assert np.isfinite(results["test"]["all"]["rotation_error_deg"]["mean"])


def test_a_run_of_the_other_kind_is_refused(tmp_path, learned, frozen):
  cache = str(tmp_path / "cache")
  with pytest.raises(runconfig.ConfigError, match="freeze_generators=True"):
    pose_system.representation_params(reg_schema.check(_regression("frozen_gen", learned, cache)))
  with pytest.raises(runconfig.ConfigError, match="held its generators"):
    pose_system.representation_params(reg_schema.check(_regression("ours", frozen, cache)))

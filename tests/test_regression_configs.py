"""configs/regression.py:SETTING[,VARIANT] is the config every regression run of that setting had
before: the runs recorded before the hyper-parameters moved into the config (they were a table in
camrep/regression/targets.py until then), and before the config was one per setting (it held
every setting's tables and the driver resolved them at run time).

tests/data/regression_configs.json was generated once, at commit c3c8414 (before the move), by a
throwaway script that did what `effective` below does with that commit's code: for every variant
(smoke, quick, medium, paper) x setting x representation it took `get_config(variant)`, set
`setting` and `representation` (and `synthesis_workdir="/synthesis"` for "ours"), resolved it with
`driver.resolve_config`, flattened the result to dotted keys without the `settings.*` tables,
and added the fields of the regressor's hyper-parameter record (then a dataclass in targets.py,
as `driver.make_regressor(resolved, spec, 1).config` held it, spec `targets.default_spec` for the
learned representations) as `hparams.<field>`. It then checked that the config part does not
depend on the representation and the hyper-parameters not on the variant, and stored them
factored: "configs" per variant (a "common" dict and one dict per setting) and "hparams" per
setting (a "common" dict and one dict per representation). A setting's config now holds its own
fields only: the fields of GQN's context views and of 7-Scenes' ResNet (`OWN_FIELDS`) are absent
from the other settings' configs.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib

import pytest

from camrep import pose_encodings, settings
from camrep.configs import regression as regression_config
from camrep.regression import config_schema, driver
from camrep.regression import targets as T
from camrep.runtime.runconfig import ConfigError

pytestmark = pytest.mark.slow

REFERENCE = pathlib.Path(__file__).parent / "data" / "regression_configs.json"
FRAME_FIELDS = (
  "ckpt_every_steps",
  "max_to_keep",
  "steps_per_dispatch",
  "allow_incomplete_synthesis",
)
VARIANTS = ("smoke", "quick", "medium", "paper")
# Fields the old configs did not have: command-line overrides of the hyper-parameters, unset
# (None) unless given, so that config.json compares across reruns as before.
NEW_FIELDS = (
  "loss.kind",
  "loss.weighting",
  "loss.init_s",
  "loss.s_factor",
  "loss.learn_s",
  "loss.weights",
  "optax.weight_decay",
  "model.extra_fc",
  "model.quantisation",
)


def _flat(d, prefix=""):
  out = {}
  for k, v in d.items():
    if isinstance(v, dict):
      out.update(_flat(v, f"{prefix}{k}."))
    else:
      out[f"{prefix}{k}"] = list(v) if isinstance(v, tuple) else v
  return out


# The fields of one setting only: GQN's context views (and real GQN's held-out scenes), 7-Scenes'
# ResNet.
OWN_FIELDS = {
  "gqn": ("data.n_context", "data.n_query", "data.test_scenes_fraction"),
  "seven_scenes": ("model.resnet_stages", "model.fc_dim", "model.resnet_weights"),
}


# The control targets, added after the runs were recorded (tests/test_controls.py).
CONTROLS = ("untrained", "frozen_gen")


def _config(variant, setting, rep):
  c = regression_config.get_config(setting if variant == "paper" else f"{setting},{variant}")
  c.representation = rep
  if rep in ("ours", *CONTROLS):
    c.synthesis_workdir = "/synthesis"
  return c


def effective(variant, setting, rep):
  """(config without its hyper-parameter table, flattened; the regressor's hyper-parameters)."""
  config = _config(variant, setting, rep)
  run = config_schema.check(config)
  flat = {k: v for k, v in _flat(config.to_dict()).items() if not k.startswith("hparams.")}
  spec = settings.get(setting).pose_spec() if rep in T.LEARNED else None
  hp = dataclasses.asdict(driver.make_regressor(run, spec, 1).hparams)
  return flat, {k: list(v) if isinstance(v, tuple) else v for k, v in hp.items()}


@pytest.fixture(scope="module")
def reference():
  return json.loads(REFERENCE.read_text())


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("setting", list(regression_config.RECIPES))
def test_configs_resolve_to_the_recorded_runs(reference, variant, setting):
  cfg_ref = {**reference["configs"][variant]["common"], **reference["configs"][variant][setting]}
  others = [f for s, fields in OWN_FIELDS.items() if s != setting for f in fields]
  cfg_ref = {k: v for k, v in cfg_ref.items() if k not in others}
  hp_common = reference["hparams"][setting]["common"]
  assert sorted(set(T.REPRESENTATIONS) - set(CONTROLS)) == sorted(
    k for k in reference["hparams"][setting] if k != "common"
  )
  for rep in T.REPRESENTATIONS:
    flat, hp = effective(variant, setting, rep)
    # The controls regress ours' grid (untrained, or learned with frozen generators): ours' values.
    recorded = "ours" if rep in CONTROLS else rep
    assert hp == {**hp_common, **reference["hparams"][setting][recorded]}, rep
    assert flat.pop("representation") == rep
    assert flat.pop("synthesis_workdir") == ("/synthesis" if rep in ("ours", *CONTROLS) else "")
    for key in NEW_FIELDS:
      assert flat.pop(key) is None, (rep, key)
    # The stopping rule, off by default: every run trains to total_steps as before.
    stop = {k: flat.pop(k) for k in [k for k in flat if k.startswith("stop.")]}
    assert stop == {"stop.min_improvement": 0.0, "stop.window": 0.25, "stop.min_steps": 0}
    # The run frame's checkpoints and dispatches (regression resumes), and the permission to
    # regress an incomplete synthesis run: added since, with these defaults.
    frame = {k: flat.pop(k) for k in FRAME_FIELDS}
    k = 10 if variant == "paper" else 1
    assert frame == {
      "ckpt_every_steps": 1000,
      "max_to_keep": 2,
      "steps_per_dispatch": k,
      "allow_incomplete_synthesis": False,
    }
    assert flat == cfg_ref, rep


def test_the_paper_values_are_where_a_reader_looks():
  """Spot checks against the paper and its supplement, readable without the reference file."""
  c = {s: regression_config.get_config(s) for s in regression_config.RECIPES}
  assert c["gqn"].hparams.ours.loss.init_s == pytest.approx((-math.log(20), -math.log(5)))
  assert c["gibson"].hparams.ours.loss.weights == (20.0, 10.0)
  assert c["gibson"].hparams.ours.model.quantisation == "nearest"
  s7 = c["seven_scenes"].hparams.ours
  assert (s7.loss.kind, s7.loss.init_s, s7.loss.s_factor) == ("l1", (-3.0, -3.0), 3.0)
  assert (c["seven_scenes"].optax.lr, s7.optax.weight_decay) == (5e-5, 5e-4)
  for setting, fc in (("gqn", 196), ("car", 256), ("gibson", 192), ("seven_scenes", None)):
    assert c[setting].hparams.baselines.model.extra_fc == fc
  want = {"euler": "mse", "sincos": "mse", "rot6d": "gram_schmidt_frobenius"}
  for rep in T.BASELINES:
    assert pose_encodings.get(rep).loss == {**want, "svd9d": "svd_frobenius"}.get(rep, "l1")


def test_command_line_values_win_and_bad_ones_are_named():
  c = _config("smoke", "seven_scenes", "quat")
  c.optax.lr, c.loss.kind, c.model.extra_fc = 3e-3, "mse", 7
  hp = config_schema.check(c).hparams
  assert (hp.lr, hp.loss, hp.extra_fc, hp.weight_decay) == (3e-3, "mse", 7, 5e-4)
  for field, value, match in (
    ("weighting", "kendall", "unknown loss.weighting"),
    ("kind", "huber", "unknown loss.kind"),
  ):
    c = _config("smoke", "car", "quat")
    c.loss[field] = value
    with pytest.raises(ConfigError, match=match):
      config_schema.check(c)


def test_pose_system_digest_names_the_parameters():
  """results.json's representation_params "digest": equal trees agree, any change of a value,
  shape or key does not (which pose system a regression read, across machines)."""
  import jax.numpy as jnp

  from camrep.regression import pose_system

  a = {"azimuth": {"grid": jnp.arange(6.0).reshape(2, 3)}, "polar": {"B": jnp.ones(4)}}
  same = {"polar": {"B": jnp.ones(4)}, "azimuth": {"grid": jnp.arange(6.0).reshape(2, 3)}}
  d = pose_system.params_digest(a)
  assert d.startswith("sha256:") and d == pose_system.params_digest(same)
  changed = {**a, "polar": {"B": jnp.ones(4).at[2].set(1.0 + 1e-7)}}
  reshaped = {**a, "azimuth": {"grid": jnp.arange(6.0).reshape(3, 2)}}
  renamed = {"azimuth": a["azimuth"], "roll": a["polar"]}
  assert len({d, *map(pose_system.params_digest, (changed, reshaped, renamed))}) == 4

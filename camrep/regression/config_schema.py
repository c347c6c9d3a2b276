"""The pose-regression config's fields, each declared once (`camrep.runtime.validate.Field`): its
rule, which setting, representation and data use it, and whether it may change when a run
resumes (`SCHEMA`: the run frame's fields, `camrep.runtime.frame.FIELDS`, and those of
`configs/regression.py`). A run whose config changes a FIXED field named in `allow_changes`
starts over from step 0 (`runtime.frame`); MAY_CHANGE fields resume.

The stage's one validation is here: `validate(config, overridden=...)` checks every field's rule
and the fields the run ignores (what `python -m camrep.regression` runs first), then the
cross-field checks on the config resolved per setting (`check`: setting and data source, "ours"
without a workdir, splits, sizes, the stopping rule, the ResNet weights);
`driver.resolve_config` runs `check` on what it resolves.
"""

from __future__ import annotations

import os
from collections.abc import Iterable

from camrep.data import sources
from camrep.regression import learner
from camrep.regression import targets as T
from camrep.regression import views as views_lib
from camrep.runtime import frame as frame_lib
from camrep.runtime import validate as V
from camrep.runtime.runconfig import ConfigError

VARIANTS = ("paper", "quick", "medium", "smoke")
# Test splits a run may score (`evals.test_split` of its setting, `evals.extra_splits`).
SPLITS = ("test", "test_scenes")

_F, _U = V.Field, V.unless
# Resume policies (`validate`): FIXED unless marked (a change named in allow_changes starts the
# run over); MAY_CHANGE fields resume; FREE fields change only speed or where output goes.
_M, _FREE = V.MAY_CHANGE, V.FREE


def _real(c) -> bool:
  return bool(c.data.get("dir", ""))


def _gqn(c) -> bool:
  return c.setting == "gqn"


_NOT_REAL = "used with real data (data.source and data.dir) only"
_NOT_GQN = "used by setting='gqn' (context and query views per scene) only"
_NOT_7S = "used by setting='seven_scenes' (its ResNet) only"
_LEARNED = ("ours", "mlp")


def _other_setting(name: str) -> V.Ignored:
  return _U(lambda c: c.setting == name, f"setting is not {name!r}: its sizes are not used")


SCHEMA: dict[str, V.Field] = {
  **frame_lib.FIELDS,
  # None: the setting's value (settings.<setting>), filled in by `driver.resolve_config`.
  "total_steps": V.Field(V.optional(V.count(1)), resume=_M),
  "setting": _F(V.one_of(T.SETTINGS)),
  "representation": _F(V.one_of(T.REPRESENTATIONS)),
  "seed": _F(V.NONNEG),
  "synthesis_workdir": _F(
    V.optional(V.Rule("dir")),
    _U(
      lambda c: c.representation in _LEARNED,
      "only representations 'ours' and 'mlp' read a view-synthesis workdir",
    ),
  ),
  "allow_incomplete_synthesis": _F(
    V.ANY,
    _U(
      lambda c: c.representation in _LEARNED and bool(c.synthesis_workdir),
      "only a run that reads a view-synthesis workdir (synthesis_workdir) checks its state",
    ),
    resume=_FREE,
  ),
  "variant": _F(V.one_of(VARIANTS)),
  "data.preset": _F(V.ANY),
  "data.batch_size": _F(V.optional(V.POSITIVE)),
  "data.n_context": _F(V.POSITIVE, _U(_gqn, _NOT_GQN)),
  "data.n_query": _F(V.POSITIVE, _U(_gqn, _NOT_GQN)),
  "data.validation_fraction": _F(V.Rule("fraction")),
  "data.cache_dir": _F(V.ANY, resume=_FREE),
  "data.source": _F(V.optional(V.one_of(sources.SOURCES))),
  # A moved copy of the prepared dataset (record.json compares its fingerprint).
  "data.dir": _F(V.optional(V.Rule("dir")), resume=_M),
  "data.dataset_config": _F(V.ANY, _U(_real, _NOT_REAL)),
  "data.image_size": _F(V.optional(V.POSITIVE), _U(_real, _NOT_REAL)),
  "data.test_scenes_fraction": _F(
    V.Rule("fraction"), _U(lambda c: _real(c) and _gqn(c), "used with real GQN data only")
  ),
  "data.max_memory_gb": _F(V.POSITIVE, _U(_real, _NOT_REAL), resume=_FREE),
  "data.stream": _F(V.ANY, _U(_real, _NOT_REAL), resume=_FREE),
  "data.num_threads": _F(V.NONNEG, resume=_FREE),
  "data.prefetch": _F(V.NONNEG, resume=_FREE),
  "model.width": _F(V.optional(V.POSITIVE)),
  "model.refine_steps": _F(
    V.NONNEG,
    _U(lambda c: c.representation == "ours", "used by representation='ours' only"),
    resume=_M,
  ),
  "model.resnet_stages": _F(
    V.Rule("positive_tuple"), _U(lambda c: c.setting == "seven_scenes", _NOT_7S)
  ),
  "model.fc_dim": _F(V.POSITIVE, _U(lambda c: c.setting == "seven_scenes", _NOT_7S)),
  "model.resnet_weights": _F(V.optional(V.Rule("file"))),
  "model.equalise_params": _F(
    V.ANY, _U(lambda c: c.representation != "ours", "used by the baselines only, not 'ours'")
  ),
  "optax.lr": _F(V.optional(V.POSITIVE)),
  "optax.weight_decay": _F(V.optional(V.NONNEG)),
  "model.extra_fc": _F(V.optional(V.NONNEG)),
  "model.quantisation": _F(V.optional(V.one_of(learner.QUANTISATIONS))),
  "loss.kind": _F(V.optional(V.one_of(T.LOSSES))),
  "loss.weighting": _F(V.optional(V.one_of(T.WEIGHTINGS))),
  "loss.init_s": _F(V.optional(V.NUMBERS)),
  "loss.s_factor": _F(V.optional(V.POSITIVE)),
  "loss.learn_s": _F(V.optional(V.ANY)),
  "loss.weights": _F(V.optional(V.NUMBERS)),
  "evals.batch_size": _F(V.POSITIVE, resume=_M),
  "evals.extra_splits": _F(V.ANY, resume=_M),
  "evals.periodic_all_splits": _F(V.ANY, resume=_M),
  # What `driver.resolve_config` writes into the run's config.json.
  "evals.test_split": _F(V.one_of(SPLITS)),
  "data.family.": _F(V.SECTION),
}
# The per-setting tables (sizes; loss, weighting and optimiser), until each setting has its own
# config: their fields as the top-level ones, each used by its own setting only.
for _name in T.SETTINGS:
  SCHEMA.update(
    {
      f"settings.{_name}.family.": _F(V.SECTION, _other_setting(_name)),
      f"settings.{_name}.total_steps": _F(V.POSITIVE, _other_setting(_name), resume=_M),
      f"settings.{_name}.batch_size": _F(V.POSITIVE, _other_setting(_name)),
      f"settings.{_name}.width": _F(V.POSITIVE, _other_setting(_name)),
      f"settings.{_name}.test_split": _F(V.one_of(SPLITS), _other_setting(_name)),
    }
  )
  for _group in ("ours", "baselines"):
    for _section, _keys in learner.HPARAM_FIELDS.items():
      for _key in _keys:
        SCHEMA[f"hparams.{_name}.{_group}.{_section}.{_key}"] = SCHEMA[f"{_section}.{_key}"]


def check_names(config) -> None:
  """The checks that come before a config can be resolved per setting: its setting and
  representation, "ours" without a synthesis workdir, its data source.

  Raises:
    ConfigError: naming the field and what is allowed.
  """
  if config.setting not in T.SETTINGS:
    raise ConfigError(f"unknown setting {config.setting!r}; choose one of {T.SETTINGS}")
  if config.representation not in T.REPRESENTATIONS:
    raise ConfigError(
      f"unknown representation {config.representation!r}; choose one of {T.REPRESENTATIONS}"
    )
  if config.representation == "ours" and not config.synthesis_workdir:
    raise ConfigError(
      'representation "ours" regresses the learned pose system of a view-synthesis run: pass '
      "--config.synthesis_workdir=DIR (a `python -m camrep.main` workdir of setting "
      f"{config.setting!r})"
    )
  check_source(config)


def check(config) -> None:
  """The cross-field checks of a config resolved per setting (`driver.resolve_config`).

  Raises:
    ConfigError: an unknown split, a non-positive size, a validation fraction outside (0, 1), a
      stopping rule without periodic validation, ResNet weights on another setting or missing.
  """
  check_names(config)
  extra = [x.strip() for x in config.evals.extra_splits.split(",") if x.strip()]
  for split in [config.evals.test_split, *extra]:
    if split not in SPLITS:
      raise ConfigError(f"unknown test split {split!r}; choose from {SPLITS}")
  if config.total_steps < 1 or config.data.batch_size < 1 or config.optax.lr <= 0:
    raise ConfigError("total_steps, data.batch_size and optax.lr must be positive")
  if not 0 < config.data.validation_fraction < 1:
    raise ConfigError("data.validation_fraction must be in (0, 1)")
  frame_lib.check_config(config)
  weights = config.model.get("resnet_weights", "")
  if weights:
    if config.setting != "seven_scenes":
      raise ConfigError(
        f"model.resnet_weights initialises the 7-Scenes ResNet-34; setting {config.setting!r} "
        "has no ResNet"
      )
    if not os.path.isfile(weights):
      raise ConfigError(f"model.resnet_weights {weights} does not exist")


def check_source(config) -> None:
  """Refuses a data.source of another setting, a real source without an existing data.dir, and
  a procedural one with a data.dir.

  Raises:
    ConfigError: as above.
  """
  d = config.data
  source = d.get("source", "")
  if not source:
    if d.get("dir", ""):
      raise ConfigError(
        "data.dir is set but data.source is empty: name the prepared dataset's source "
        f"(--config.data.source={views_lib.data_source(config)} is "
        "procedural; real ones: gqn, srn_cars, gibson, seven_scenes)"
      )
    return
  try:
    setting = sources.setting_of(source)
  except ValueError as e:
    raise ConfigError(f"data.source: {e}") from None
  if setting != config.setting:
    raise ConfigError(
      f"data.source {source!r} is data of the {setting!r} setting, but setting is "
      f"{config.setting!r}: pass --config.setting={setting}"
    )
  if sources.is_procedural(source):
    if d.dir:
      raise ConfigError(f"data.source {source!r} is procedural and takes no data.dir")
    return
  if not d.dir:
    raise ConfigError(
      f"data.source {source!r} is a real dataset: prepare it with `python -m camrep.data.prepare "
      f"--source {source} --input RAW --data_dir DIR` and pass --config.data.dir=DIR"
    )
  if not os.path.isdir(d.dir):
    raise ConfigError(f"data.dir {d.dir} does not exist (data.source {source!r})")


def validate(config, *, overridden: Iterable[str] = ()):
  """The stage's validation: every field's rule, the overridden fields the run ignores and
  `allow_changes` naming fields, then the cross-field checks (`check`) of the config resolved
  per setting.

  Returns:
    The resolved config (`driver.resolve_config`).

  Raises:
    ConfigError: the first problem, naming the field, its value and what is allowed.
  """
  from camrep.regression import driver  # the resolution reads the stage's tables

  V.check(config, SCHEMA, overridden=overridden)
  V.check_allow_changes(config, SCHEMA)
  return driver.resolve_config(config)

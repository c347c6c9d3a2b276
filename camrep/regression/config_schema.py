"""The pose-regression config's fields, each declared once (`camrep.runtime.validate.Field`): its
rule, which representation and data use it, and whether it may change when a run resumes
(`SCHEMA`: the run frame's fields, `camrep.runtime.frame.FIELDS`, and those of
`configs/regression.py`). A run whose config changes a FIXED field named in `allow_changes`
starts over from step 0 (`runtime.frame`); MAY_CHANGE fields resume.

The stage's one validation is here: `validate(config, overridden=...)` checks every field's rule
and the fields the run ignores (what `python -m camrep.regression` runs first), then the
cross-field checks (`check`: setting and data source, "ours" without a workdir, splits, sizes,
the stopping rule, the ResNet weights). `check` returns the config `Resolved`: the setting, pose
encoding, data source and hyper-parameters it names, looked up once and passed down to the
run's parts (which take these objects and never look a name up again). A config holds one
setting's fields (`configs/regression.py:SETTING`): an override of another setting's field is
refused when the flag is parsed.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable

import ml_collections

from camrep import pose_encodings
from camrep import settings as settings_lib
from camrep.data import sources
from camrep.regression import learner
from camrep.regression import targets as T
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


def _encoding(c):
  try:
    return pose_encodings.get(c.representation)
  except ValueError:  # an unknown representation: the field's own rule names it
    return pose_encodings.PoseEncoding


def _learned(c) -> bool:
  return _encoding(c).learned


def _quantised(c) -> bool:
  return _encoding(c).quantised


_NOT_REAL = "used with real data (data.source and data.dir) only"


SCHEMA: dict[str, V.Field] = {
  **frame_lib.FIELDS,
  # Chosen by the config argument, never overridden.
  "setting": _F(
    V.one_of(settings_lib.names),
    lambda c: (
      "the config argument chooses the setting, with its sizes: pass "
      f"--config=configs/regression.py:{c.setting}[,quick|,medium|,smoke]"
    ),
  ),
  "representation": _F(V.one_of(T.REPRESENTATIONS)),
  "seed": _F(V.NONNEG),
  "synthesis_workdir": _F(
    V.optional(V.Rule("dir")),
    _U(
      _learned,
      "only the learned representations (ours, its controls, mlp) read a view-synthesis workdir",
    ),
  ),
  "allow_incomplete_synthesis": _F(
    V.ANY,
    _U(
      lambda c: _learned(c) and bool(c.synthesis_workdir),
      "only a run that reads a view-synthesis workdir (synthesis_workdir) checks its state",
    ),
    resume=_FREE,
  ),
  "variant": _F(V.one_of(VARIANTS)),
  "data.preset": _F(V.ANY),
  "data.batch_size": _F(V.POSITIVE),
  "data.n_context": _F(V.POSITIVE),
  "data.n_query": _F(V.POSITIVE),
  "data.validation_fraction": _F(V.Rule("fraction")),
  "data.cache_dir": _F(V.ANY, resume=_FREE),
  "data.source": _F(V.optional(V.one_of(lambda: sources.SOURCES))),
  # A moved copy of the prepared dataset (record.json compares its fingerprint).
  "data.dir": _F(V.optional(V.Rule("dir")), resume=_M),
  "data.dataset_config": _F(V.ANY, _U(_real, _NOT_REAL)),
  "data.image_size": _F(V.optional(V.POSITIVE), _U(_real, _NOT_REAL)),
  "data.test_scenes_fraction": _F(V.Rule("fraction"), _U(_real, "used with real GQN data only")),
  "data.max_memory_gb": _F(V.POSITIVE, _U(_real, _NOT_REAL), resume=_FREE),
  "data.stream": _F(V.ANY, _U(_real, _NOT_REAL), resume=_FREE),
  "data.num_threads": _F(V.NONNEG, resume=_FREE),
  "data.prefetch": _F(V.NONNEG, resume=_FREE),
  "model.width": _F(V.POSITIVE),
  "model.refine_steps": _F(
    V.NONNEG,
    _U(_quantised, "used by the learned grid ('ours' and its controls) only"),
    resume=_M,
  ),
  "model.resnet_stages": _F(V.Rule("positive_tuple")),
  "model.fc_dim": _F(V.POSITIVE),
  "model.resnet_weights": _F(V.optional(V.Rule("file"))),
  "model.equalise_params": _F(
    V.ANY, _U(lambda c: not _quantised(c), "used by the baselines only, not 'ours'")
  ),
  "optax.lr": _F(V.POSITIVE),
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
  "evals.test_split": _F(V.one_of(SPLITS)),
  "data.family.": _F(V.SECTION),
}


# The learned representations' hyper-parameters and what every baseline changes from them
# (`hparams.ours.*`, `hparams.baselines.*`): each with the rule of its top-level override.
for _group in ("ours", "baselines"):
  for _key in (
    "optax.weight_decay", "model.extra_fc", "model.quantisation",
    "loss.kind", "loss.weighting", "loss.init_s", "loss.s_factor", "loss.learn_s",
    "loss.weights",
  ):  # fmt: skip
    SCHEMA[f"hparams.{_group}.{_key}"] = SCHEMA[_key]


@dataclasses.dataclass(frozen=True)
class Resolved:
  """A checked config and what its names stand for, looked up once (`check`).

  Attributes:
    config: the run's config.
    setting: the paper's setting (`config.setting`).
    encoding: the representation's `PoseEncoding` class (`config.representation`).
    source: the data source: `data.source`, or the setting's procedural family.
    hparams: the loss, weighting and optimiser (`learner.resolve_hparams`).
  """

  config: ml_collections.ConfigDict
  setting: settings_lib.Setting
  encoding: type[pose_encodings.PoseEncoding]
  source: sources.Source
  hparams: learner.HyperParams


def check(config) -> Resolved:
  """Checks the fields of a config together (a config of `configs/regression.py`, which holds
  its setting's sizes and hyper-parameters): the setting and representation, "ours" with its
  `synthesis_workdir`, the data source (`check_source`), the hyper-parameters
  (`learner.resolve_hparams`), the test splits, the sizes, the stopping rule and the ResNet
  weights.

  Returns:
    The config `Resolved`.

  Raises:
    ConfigError: naming the field and what is allowed.
  """
  source = check_source(config.data, config.setting)
  setting = source.setting
  if config.representation not in T.REPRESENTATIONS:
    raise ConfigError(
      f"unknown representation {config.representation!r}; choose one of {T.REPRESENTATIONS}"
    )
  encoding = pose_encodings.get(config.representation)
  if encoding.needs_synthesis and not config.synthesis_workdir:
    raise ConfigError(
      f'representation "{config.representation}" regresses the learned pose system of a '
      "view-synthesis run: pass --config.synthesis_workdir=DIR (a `python -m camrep.main` "
      f"workdir of setting {setting.name!r})"
    )
  try:
    hparams = learner.resolve_hparams(config, encoding)
  except ValueError as e:
    raise ConfigError(str(e)) from None
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
  if weights and not os.path.isfile(weights):
    raise ConfigError(f"model.resnet_weights {weights} does not exist")
  return Resolved(config, setting, encoding, source, hparams)


def check_source(d, setting: settings_lib.Setting | str) -> sources.Source:
  """The data source of a config's data section `d` (data.source, or the procedural family of
  `setting`, a name or a `Setting`, when it is empty). Refuses an unknown setting, a data.source
  of another setting, a real source without an existing data.dir, and a procedural one with a
  data.dir.

  Raises:
    ConfigError: as above.
  """
  try:
    setting = settings_lib.get(setting)
  except ValueError as e:
    raise ConfigError(str(e)) from None
  name = d.get("source", "")
  if not name:
    procedural = sources.get(sources.procedural_of(setting))
    if d.get("dir", ""):
      raise ConfigError(
        "data.dir is set but data.source is empty: name the prepared dataset's source "
        f"(--config.data.source={procedural.name} is "
        "procedural; real ones: gqn, srn_cars, gibson, seven_scenes)"
      )
    return procedural
  try:
    source = sources.get(name)
  except ValueError as e:
    raise ConfigError(f"data.source: {e}") from None
  if source.setting is None:
    raise ConfigError(f"data.source: data source {name!r} belongs to no paper setting")
  if source.setting is not setting:
    raise ConfigError(
      f"data.source {name!r} is data of the {source.setting.name!r} setting, but setting is "
      f"{setting.name!r}: pass --config=configs/regression.py:{source.setting.name}"
    )
  if source.procedural:
    if d.dir:
      raise ConfigError(f"data.source {name!r} is procedural and takes no data.dir")
    return source
  if not d.dir:
    raise ConfigError(
      f"data.source {name!r} is a real dataset: prepare it with `python -m camrep.data.prepare "
      f"--source {name} --input RAW --data_dir DIR` and pass --config.data.dir=DIR"
    )
  if not os.path.isdir(d.dir):
    raise ConfigError(f"data.dir {d.dir} does not exist (data.source {name!r})")
  return source


def validate(config, *, overridden: Iterable[str] = ()) -> Resolved:
  """The stage's validation: every field's rule, the overridden fields the run ignores and
  `allow_changes` naming fields, then the cross-field checks (`check`).

  Returns:
    The config `Resolved` (the config itself unchanged: each setting's config holds its own
    values).

  Raises:
    ConfigError: the first problem, naming the field, its value and what is allowed.
  """
  V.check(config, SCHEMA, overridden=overridden)
  V.check_allow_changes(config, SCHEMA)
  return check(config)

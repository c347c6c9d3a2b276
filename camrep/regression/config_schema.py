"""The pose-regression config's validation pass (`camrep.runtime.validate`): a rule per field of
`configs/regression.py`, and which fields the chosen setting, representation and data use.

`validate(config, overridden=...)` is what `python -m camrep.regression` runs first, before
`driver.check_config`'s cross-field checks; it raises `ConfigError`. A config holds one
setting's fields (`configs/regression.py:SETTING`): an override of another setting's field is
refused when the flag is parsed.
"""

from __future__ import annotations

from collections.abc import Iterable

from camrep import settings as settings_lib
from camrep.data import sources
from camrep.regression import driver, learner
from camrep.regression import targets as T
from camrep.runtime import validate as V

VARIANTS = ("paper", "quick", "medium", "smoke")

_F, _U = V.Field, V.unless


def _real(c) -> bool:
  return bool(c.data.get("dir", ""))


_NOT_REAL = "used with real data (data.source and data.dir) only"


SCHEMA: dict[str, V.Field] = {
  # Checked by `driver.check_config`; chosen by the config argument, never overridden.
  "setting": _F(
    V.one_of(settings_lib.names()),
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
      lambda c: c.representation in ("ours", "mlp"),
      "only representations 'ours' and 'mlp' read a view-synthesis workdir",
    ),
  ),
  "variant": _F(V.one_of(VARIANTS)),
  "allow_changes": _F(V.ANY),
  "total_steps": _F(V.POSITIVE),
  "log_every_steps": _F(V.NONNEG),
  "eval_every_steps": _F(V.NONNEG),  # 0: at the end only
  # The stopping rule (camrep/runtime/stopping.py; the ranges `rule_from_config` accepts).
  "stop.min_improvement": _F(V.NONNEG),  # 0: off
  "stop.window": _F(V.Rule("fraction")),
  "stop.min_steps": _F(V.NONNEG),
  "data.preset": _F(V.ANY),
  "data.batch_size": _F(V.POSITIVE),
  "data.n_context": _F(V.POSITIVE),
  "data.n_query": _F(V.POSITIVE),
  "data.validation_fraction": _F(V.Rule("fraction")),
  "data.cache_dir": _F(V.ANY),
  "data.source": _F(V.optional(V.one_of(sources.SOURCES))),
  "data.dir": _F(V.optional(V.Rule("dir"))),
  "data.dataset_config": _F(V.ANY, _U(_real, _NOT_REAL)),
  "data.image_size": _F(V.optional(V.POSITIVE), _U(_real, _NOT_REAL)),
  "data.test_scenes_fraction": _F(V.Rule("fraction"), _U(_real, "used with real GQN data only")),
  "data.max_memory_gb": _F(V.POSITIVE, _U(_real, _NOT_REAL)),
  "data.stream": _F(V.ANY, _U(_real, _NOT_REAL)),
  "data.num_threads": _F(V.NONNEG),
  "data.prefetch": _F(V.NONNEG),
  "model.width": _F(V.POSITIVE),
  "model.refine_steps": _F(
    V.NONNEG, _U(lambda c: c.representation == "ours", "used by representation='ours' only")
  ),
  "model.resnet_stages": _F(V.Rule("positive_tuple")),
  "model.fc_dim": _F(V.POSITIVE),
  "model.resnet_weights": _F(V.optional(V.Rule("file"))),
  "model.equalise_params": _F(
    V.ANY, _U(lambda c: c.representation != "ours", "used by the baselines only, not 'ours'")
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
  "evals.batch_size": _F(V.POSITIVE),
  "evals.extra_splits": _F(V.ANY),
  "evals.periodic_all_splits": _F(V.ANY),
  "evals.test_split": _F(V.one_of(driver.SPLITS)),
  "data.family.": _F(V.SECTION),
}


for _group in ("ours", "baselines"):
  for _key in list(SCHEMA):
    if _key.split(".")[0] in ("loss", "optax", "model") and _key in (
      "optax.weight_decay", "model.extra_fc", "model.quantisation",
      "loss.kind", "loss.weighting", "loss.init_s", "loss.s_factor", "loss.learn_s",
      "loss.weights",
    ):  # fmt: skip
      SCHEMA[f"hparams.{_group}.{_key}"] = SCHEMA[_key]


def validate(config, *, overridden: Iterable[str] = ()) -> None:
  """Every field's rule and the overridden fields the run ignores, then the driver's cross-field
  checks (`driver.check_config`: setting and data source, "ours" without a workdir, splits).

  Raises:
    ConfigError: the first problem, naming the field, its value and what is allowed.
  """
  V.check(config, SCHEMA, overridden=overridden)
  driver.check_config(config)

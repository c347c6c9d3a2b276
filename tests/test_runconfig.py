"""Fields retired from the base config (`camrep.runtime.synthesis_schema.RETIRED`): a workdir whose
config.json still has them resumes with a config that lacks them, without training anything
(the resume of a real workdir: tests/test_workdir.py::
test_a_workdir_written_with_the_retired_fields_resumes, in the slow tier)."""

from __future__ import annotations

import pytest

from camrep.configs import gqn, gqn_convdraw
from camrep.runtime import runconfig
from camrep.synthesis import components, synthesizers
from camrep.synthesis import config_schema as synthesis_schema


def _with_retired(config, **values):
  """`config` as a workdir written before the ConvDRAW fields left configs/common.py:base stores
  it: every `synthesis_schema.RETIRED` field at its old value (or `values["a.b"]`)."""
  old = runconfig.as_plain(config)
  for field, value in synthesis_schema.RETIRED.items():
    section, name = field.split(".")
    old[section][name] = values.get(field, value)
  return old


def test_check_changes_records_retired_fields_the_config_no_longer_has():
  new = gqn.get_config("smoke")
  assert not set(synthesis_schema.RETIRED) & set(runconfig.flatten(runconfig.as_plain(new)))
  got = runconfig.check_changes(
    _with_retired(new), new, schema=synthesis_schema.SCHEMA, workdir="W"
  )
  assert got == {f: (v, None) for f, v in synthesis_schema.RETIRED.items()}
  # A decoder run never read them: a stored value other than base()'s is recorded too.
  old = _with_retired(new, **{"model.draw_steps": 3})
  got = runconfig.check_changes(old, new, schema=synthesis_schema.SCHEMA, workdir="W")
  assert got["model.draw_steps"] == (3, None)
  # Only the retired names: another field the new config lacks is still refused.
  old["model"]["no_such_field"] = 1
  with pytest.raises(runconfig.ConfigError, match=r"model\.no_such_field: 1 -> None"):
    runconfig.check_changes(old, new, schema=synthesis_schema.SCHEMA, workdir="W")
  # A ConvDRAW workdir resumed with a decoder config is refused on model.kind itself.
  old = _with_retired(new)
  old["model"]["kind"] = "convdraw"
  with pytest.raises(runconfig.ConfigError, match=r"model\.kind: 'convdraw' -> 'decoder'"):
    runconfig.check_changes(old, new, schema=synthesis_schema.SCHEMA, workdir="W")
  # A config that has the field (GQN's generator) compares it as any other.
  conv = gqn_convdraw.get_config("smoke")
  old = runconfig.as_plain(conv)
  old["model"]["draw_steps"] = 5
  with pytest.raises(runconfig.ConfigError, match=r"model\.draw_steps: 5 -> 2"):
    runconfig.check_changes(old, conv, schema=synthesis_schema.SCHEMA, workdir="W")


def test_retired_fields_are_the_generators_at_their_old_values():
  """RETIRED holds what configs/common.py:base gave every run: GQN's paper-size generator, now
  configs/gqn_convdraw.py's, and exactly the fields the generator reads."""
  assert set(synthesis_schema.RETIRED) == set(synthesizers.GENERATOR_FIELDS)
  paper = runconfig.flatten(runconfig.as_plain(gqn_convdraw.get_config()))
  assert {f: paper[f] for f in synthesis_schema.RETIRED} == synthesis_schema.RETIRED
  # A generator config without them (e.g. a copy written against the old base) is refused.
  c = gqn_convdraw.get_config("smoke")
  del c.loss["sigma_final"]
  with pytest.raises(runconfig.ConfigError, match=r"reads config\.loss\.sigma_final"):
    components.check_config(c)

"""The source registry (`camrep.data.sources`): one record per source, read by every stage."""

from __future__ import annotations

import pytest

from camrep import settings
from camrep.data import procedural, sources
from camrep.data.errors import DataError


def test_every_setting_has_one_procedural_stand_in_and_the_tables_agree():
  paper = (settings.GQN, settings.CAR, settings.GIBSON, settings.SEVEN_SCENES)
  assert {sources.procedural_of(s) for s in paper} == set(procedural.FAMILIES)
  for name, entry in sources.SOURCES.items():
    assert entry.name == name
    assert sources.setting_of(name) is entry.setting
    assert sources.is_procedural(name) == (name in procedural.FAMILIES)
    # A setting's sources have its pose columns (the regressor and pose system read them).
    stand_in = sources.get(sources.procedural_of(entry.setting))
    assert entry.pose_names == stand_in.pose_names == entry.setting.pose_columns


@pytest.mark.parametrize("name", procedural.FAMILIES)
def test_build_makes_the_family_the_records_describe(name):
  family = sources.build(name, preset="small", overrides={"image_size": 8})
  entry = sources.get(name)
  assert family.name == name and family.pose_names == entry.pose_names
  assert family.splits == entry.splits and family.image_size == 8


def test_family_of_config_reads_source_preset_and_overrides():
  import ml_collections

  data = ml_collections.ConfigDict(
    {
      "source": "rooms",
      "preset": "small",
      "family": {"image_size": 12, "texture_contrast": [0.0, 0.1]},
    }
  )
  family = sources.family_of_config(data)
  assert family.name == "rooms" and family.image_size == 12
  assert family.config.texture_contrast == (0.0, 0.1)  # lists from config.json become tuples
  data.family = {"image_size": 12}
  assert sources.family_of_config(data, "object").name == "object"
  with pytest.raises(DataError, match="not a procedural family"):
    sources.family_of_config(data, "gqn")


def test_errors_name_the_problem(tmp_path):
  with pytest.raises(DataError, match="unknown data source 'nope'"):
    sources.get("nope")
  with pytest.raises(DataError, match="unknown setting 'x'"):
    sources.procedural_of("x")
  with pytest.raises(DataError, match="reads a dataset"):
    sources.build("gqn")
  with pytest.raises(DataError, match="takes no --input"):
    sources.build("rooms", input_path=tmp_path)
  with pytest.raises(DataError, match="rejected the settings"):
    sources.build("rooms", overrides={"not_a_field": 1})


def test_register_adds_a_source_once(monkeypatch):
  monkeypatch.setattr(sources, "SOURCES", dict(sources.SOURCES))
  entry = sources.Source(
    "tiny", "camrep.data.procedural", "make_family", True, None, ("x",), ("train",), "test only"
  )
  assert sources.register(entry) is entry and sources.get("tiny") is entry
  with pytest.raises(ValueError, match="already registered"):
    sources.register(entry)
  with pytest.raises(ValueError, match="unknown setting 'nope'"):
    sources.Source("bad", "m", "a", False, "nope", None, (), "")
  with pytest.raises(ValueError, match="not the car setting's columns"):
    sources.Source("bad", "m", "a", False, "car", ("x",), (), "")
  # A setting given by name is the registered one, and its columns are the source's.
  by_name = sources.Source("named", "m", "a", False, "car", None, ("train",), "")
  assert by_name.setting is settings.CAR and by_name.pose_names == ("azimuth", "polar")
  with pytest.raises(DataError, match="belongs to no paper setting"):
    sources.setting_of("tiny")

"""The installed configs (camrep.configs): `--config` by name or by path, and the checkout's
path-loaded configs/ files are the installed ones."""

from __future__ import annotations

import importlib
import json
import os
import pathlib
import sys

import pytest
from absl import flags

from camrep import configs

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_every_name_is_an_installed_module_with_get_config():
  names = sorted(
    p.stem for p in pathlib.Path(configs.__file__).parent.glob("*.py") if p.stem[0] != "_"
  )
  assert sorted([*configs.NAMES, "common"]) == names
  for name in configs.NAMES:
    assert os.path.isfile(configs.path(name))


def test_resolve_names_and_paths():
  assert configs.resolve("gqn:quick") == configs.path("gqn") + ":quick"
  assert configs.resolve("regression") == configs.path("regression")
  # Paths go to ml_collections unchanged, relative or absolute, with or without an argument.
  for spec in ("configs/gqn.py:smoke", "my.py", "/abs/dir/x:arg", "sub/dir/file:quick"):
    assert configs.resolve(spec) == spec
  with pytest.raises(ValueError, match=r"unknown config 'gqm'.*gqn, gqn_convdraw"):
    configs.resolve("gqm:smoke")


def _parse(argv: list[str], monkeypatch):
  fv = flags.FlagValues()
  holder = configs.define_config_flag("config", "test", flag_values=fv)
  monkeypatch.setattr(sys, "argv", argv)  # ml_collections reads the overrides from sys.argv
  fv(argv)
  return holder.value


@pytest.mark.parametrize("name", configs.NAMES)
def test_a_name_and_the_checkout_path_load_the_same_config(name, monkeypatch):
  monkeypatch.chdir(ROOT)
  by_name = _parse(["prog", f"--config={name}:smoke"], monkeypatch)
  by_path = _parse(["prog", f"--config=configs/{name}.py:smoke"], monkeypatch)
  assert by_name.to_dict() == by_path.to_dict()
  assert by_name.is_locked  # lock_config: a typo in an override is an error


def test_overrides_apply_to_a_named_config(tmp_path, monkeypatch):
  monkeypatch.chdir(tmp_path)  # no configs/ here: the name must find the installed file
  config = _parse(["prog", "--config=gqn:smoke", "--config.total_steps=7"], monkeypatch)
  assert config.total_steps == 7 and config.task == "gqn"


def test_an_unknown_name_is_a_flag_error(monkeypatch):
  with pytest.raises(flags.IllegalFlagValueError, match="unknown config 'nope'"):
    _parse(["prog", "--config=nope:smoke"], monkeypatch)


REFERENCE = pathlib.Path(__file__).parent / "data" / "configs_resolved.json"
VARIANTS = {"paper": "", "quick": "quick", "medium": "medium", "smoke": "smoke"}


def _resolved(name: str, variant: str) -> dict:
  """`get_config(variant).to_dict()` of config `name`, through JSON (tuples become lists)."""
  module = importlib.import_module(f"camrep.configs.{name}")
  return json.loads(json.dumps(module.get_config(VARIANTS[variant]).to_dict(), sort_keys=True))


def test_configs_resolve_as_before():
  """Every variant of every config resolves to the ConfigDict recorded before the configs were
  reduced to what differs from their base (`common.base()`; `gqn` for `gqn_convdraw`).

  tests/data/configs_resolved.json was generated at commit 830ed49, before that edit, by: for each
  name in `camrep.configs.NAMES` and each variant in ("", "quick", "medium", "smoke") whose
  `get_config` does not raise ValueError, `json.loads(json.dumps(get_config(v).to_dict(),
  sort_keys=True))`, stored as {name: {variant or "paper": dict}}; since then the view-synthesis
  configs' `stop` section (defaults: off) was added to their entries, the ConvDRAW fields
  (`synthesis.config_schema.RETIRED`) were deleted from every config but gqn_convdraw when they
  moved from `common.base()` to `gqn_convdraw.py`, and the run frame's `steps_per_dispatch` (10
  at paper size, 1 in every variant) was added to every entry, the lvsm config (no paper
  size) entered with its variants as written, later with its evals.context_counts,
  `rep.freeze_generators` (False: the frozen-generators control's switch) was added to every
  entry with a `rep` section and `evals.split` ("test": the split of the held-out evaluation and
  the plateau rule) and `data.validation_fraction` (0.1: a captures dataset's carved validation
  views) to every entry, and seven_scenes:quick states its family's scenes (the small
  preset's chess and heads, the same data) (nothing else
  changed). A
  workdir's config.json is compared with the requested config on resume
  (`runconfig.check_changes`), so a field that changed or disappeared here would refuse to resume
  existing runs (a gained field is recorded; a retired one excepted: tests/test_workdir.py
  resumes a workdir that still has them). The regression config is one per setting since (each
  with its setting's fields only; a regression rerun starts over): its settings are compared
  with the runs recorded before in tests/test_regression_configs.py.
  """
  reference = json.loads(REFERENCE.read_text())
  assert sorted(reference) == sorted(configs.NAMES)
  for name, variants in reference.items():
    if name == "regression":
      continue
    for variant, expected in variants.items():
      assert _resolved(name, variant) == expected, (name, variant)
  # gqn_convdraw refuses `:medium`, as before.
  with pytest.raises(ValueError):
    _resolved("gqn_convdraw", "medium")


@pytest.mark.parametrize(
  "name, variant, setting_config, source",
  [
    ("gqn_convdraw", "object", "shapenet_car", "object"),
    ("lvsm", "object", "shapenet_car", "object"),
    ("gqn_convdraw", "area", "gibson", "area"),
  ],
)
def test_a_family_variant_is_quick_on_its_settings_family(name, variant, setting_config, source):
  """`:object` (`:area`) differs from `:quick` only in the data source, the family, the number of
  evaluation scenes and, where the family has fewer scenes than a batch, the scenes a step: those
  of configs/shapenet_car.py:quick (configs/gibson.py:quick), the same held-out targets."""

  def flat(tree, prefix=""):
    out = {}
    for k, v in tree.items():
      out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out

  module = importlib.import_module(f"camrep.configs.{name}")
  quick, obj = (
    flat(module.get_config("quick").to_dict()),
    flat(module.get_config(variant).to_dict()),
  )
  own = flat(
    importlib.import_module(f"camrep.configs.{setting_config}").get_config("quick").to_dict()
  )
  differ = {k for k in quick.keys() | obj.keys() if quick.get(k) != obj.get(k)}
  allowed = {"data.source", "evals.num_scenes", "evals.batch_scenes", "data.scenes_per_device"}
  differ -= {k for k in differ if k.startswith("data.family.")}
  assert {"data.source", "evals.num_scenes"} <= differ <= allowed
  family = {k: v for k, v in obj.items() if k.startswith("data.family.")}
  assert family == {k: v for k, v in own.items() if k.startswith("data.family.")}
  assert obj["data.source"] == own["data.source"] == source
  assert obj["evals.num_scenes"] == own["evals.num_scenes"]
  # A step draws its scenes without replacement from the family.
  scenes = obj.get("data.family.num_scenes") or obj.get("data.family.num_train_scenes")
  if scenes is not None:
    assert obj["data.scenes_per_device"] <= scenes

"""The installed configs (camrep.configs): `--config` by name or by path, and the checkout's
path-loaded configs/ files are the installed ones."""

from __future__ import annotations

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

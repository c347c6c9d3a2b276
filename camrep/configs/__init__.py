"""Experiment configs (ml_collections), installed with the package, and the `--config` flag.

One module per experiment (`gqn`, `gqn_convdraw`, `lvsm`, `shapenet_car`, `gibson`, `seven_scenes`,
`regression`), each with `get_config(arg)` built from `common.base()`. A `--config` value names
one in either of two ways:

  --config=gqn:quick                  an installed config by name (works after `pip install`)
  --config=configs/gqn.py:quick       a file by path (a checkout's configs/, or your own copy)

To edit a config outside a checkout, copy its file (`python -c "import camrep.configs as c;
print(c.path('gqn'))"`) and pass the copy's path.
"""

from __future__ import annotations

import importlib
import os

from absl import flags
from ml_collections import config_flags

# The `--config` flag `define_config_flag` defines belongs to the tool that calls it, so that the
# tool's `--help` lists it among its own flags (absl lists only the main module's).
flags.disclaim_key_flags()

_HERE = os.path.dirname(os.path.abspath(__file__))
# The configs a `--config` value may name (modules of this package with a get_config).
NAMES = (
  "gqn",
  "gqn_convdraw",
  "lvsm",
  "shapenet_car",
  "gibson",
  "seven_scenes",
  "regression",
)


def path(name: str) -> str:
  """The installed file of config `name` (one of NAMES)."""
  if name not in NAMES:
    raise ValueError(f"unknown config {name!r}: name one of {', '.join(NAMES)} or give a .py path")
  return os.path.join(_HERE, f"{name}.py")


def resolve(spec: str) -> str:
  """A `--config` value as a file path: `NAME[:ARG]` -> `<installed>/NAME.py[:ARG]`.

  A value whose file part ends in `.py` or contains a path separator is a path, returned unchanged
  (ml_collections loads it, relative to the working directory).
  """
  file, sep, arg = spec.partition(":")
  if file.endswith(".py") or os.sep in file or "/" in file:
    return spec
  return path(file) + sep + arg


class _ResolvingParser(flags.ArgumentParser):
  """ml_collections' config-file parser, given `resolve(value)`."""

  def __init__(self, inner: flags.ArgumentParser):
    self._inner = inner

  def parse(self, argument):
    return self._inner.parse(resolve(argument))

  def flag_type(self):
    return self._inner.flag_type()


# What each variant (`--config=NAME:VARIANT`) is for; "" is the paper-size config.
VARIANT_USES = {
  "": "paper size",
  "quick": "minutes on 2 CPU cores",
  "medium": "one GPU, minutes",
  "smoke": "seconds, for tests",
  "capture": "a posed capture at 128 px",
}


def variants(name: str) -> tuple[str, ...]:
  """The variants installed config `name` accepts (those of `VARIANT_USES` its `get_config`
  takes; "" first)."""
  module = importlib.import_module(f"{__name__}.{name}")
  out = []
  for v in VARIANT_USES:
    try:
      module.get_config(v or None)
    except ValueError:
      continue
    out.append(v)
  return tuple(out)


def describe(flag: str = "config") -> str:
  """The installed configs with their variants, what the variants are for, and how to
  override a field, for a `--config` flag's help."""
  listed = ", ".join(
    name + "[:" + "|:".join(v for v in variants(name) if v) + "]" for name in NAMES
  )
  uses = "; ".join(f"{v or 'none'}: {use}" for v, use in VARIANT_USES.items())
  return (
    f"Installed configs: {listed}. Variants ({uses}). Override any field with "
    f"--{flag}.FIELD=VALUE (e.g. --{flag}.total_steps=100); an unknown field is an error."
  )


def define_config_flag(
  name: str, help_string: str, *, lock_config: bool = True, flag_values=flags.FLAGS
):
  """`config_flags.DEFINE_config_file` whose value may also name an installed config (NAMES).

  Overrides (`--NAME.field=value`), `lock_config` and `--flagfile` work as in ml_collections.
  The help lists the installed configs and their variants (`describe`). Returns the flag holder
  (`.value` is the ConfigDict).
  """
  help_string = f"{help_string} {describe(name)}"
  try:
    holder = config_flags.DEFINE_config_file(
      name, None, help_string, flag_values=flag_values, lock_config=lock_config
    )
  except flags.Error:
    # ml_collections reads --flagfile files while defining the flag; one that cannot be opened
    # is the command line's mistake, reported when the flags are parsed (`camrep.runtime.cli`).
    holder = config_flags.DEFINE_config_file(
      name, None, help_string, flag_values=flag_values, lock_config=lock_config, sys_argv=["-"]
    )
  flag_values[name].parser = _ResolvingParser(flag_values[name].parser)
  return holder

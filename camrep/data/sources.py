"""The one registry of data sources: every stage (prepare, view synthesis, pose regression) builds
its data through `build` and reads a source's facts (setting, pose columns, splits) from `get`.

A source is a procedural family rendered by camrep (`camrep.data.procedural`) or a reader of a
real dataset on disk (`camrep.data.readers`: `gqn`, `srn`, `gibson`, `seven_scenes`, `captures`);
either way it yields the view records of `camrep.data.records`. Adding one is one call, in this
module or in the module that defines it (imported before use):

  sources.register(sources.Source(
    name="nerf", module="camrep.data.readers.nerf", attr="NerfScenes", procedural=False,
    setting=None, pose_names=("x", "y", "z", "theta", "phi", "psi"),
    splits=("train", "test"), description="NeRF-synthetic transforms.json scenes",
    presets={"small": {"image_size": 64}}))

after which `python -m camrep.data.prepare --source nerf --input ROOT ...` prepares it and
`prepare --list` lists it. `setting` is the paper setting (`camrep.settings`) whose pose system
and regressor read the source (None: prepare and the pipelines only); its pose columns are the
setting's.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import os
import pathlib
from collections.abc import Mapping
from typing import Any

from camrep import settings as settings_lib
from camrep.data.errors import DataError


@dataclasses.dataclass(frozen=True)
class Source:
  """One registered data source.

  Attributes:
    name: registry key; the records' `name` and the prepared dataset's default directory name.
    module: the module that defines the constructor (imported only when the source is built).
    attr: the constructor in `module`. Real readers: a class called as
      `attr(input_path, **overrides)`; procedural families: a function called as
      `attr(name, preset=..., **overrides)` (`procedural.make_family`).
    procedural: True: rendered by camrep, `prepare` renders every view and takes no `--input`;
      False: `prepare` reads the dataset at `--input PATH` and stores it.
    setting: the paper setting (a `camrep.settings.Setting`, or its registered name) whose pose
      system reads this source's poses; None for a source that has none (prepare and pipelines
      only).
    pose_names: the P pose columns of its records (units in `camrep.data.records`); None: the
      setting's (`Setting.pose_columns`).
    splits: the splits it can provide (a reader may provide fewer, e.g. SRN's "test_scenes"
      only when that folder exists).
    description: one line for `prepare --list`.
    presets: named keyword-override sets of a real reader (`prepare --preset NAME`); the
      procedural families take "default" / "small" from their own module.
  """

  name: str
  module: str
  attr: str
  procedural: bool
  setting: settings_lib.Setting | None
  pose_names: tuple[str, ...] | None
  splits: tuple[str, ...]
  description: str
  presets: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=dict)

  def __post_init__(self):
    if self.setting is None:
      if self.pose_names is None:
        raise ValueError(f"source {self.name!r}: give its pose_names or its setting")
      return
    setting = settings_lib.get(self.setting)  # a name: the registered setting
    object.__setattr__(self, "setting", setting)
    if self.pose_names is None:
      object.__setattr__(self, "pose_names", setting.pose_columns)
    elif tuple(self.pose_names) != setting.pose_columns:
      raise ValueError(
        f"source {self.name!r}: pose_names {self.pose_names} are not the {setting.name} "
        f"setting's columns {setting.pose_columns}"
      )

  @property
  def needs_input(self) -> bool:
    """Whether building it needs a dataset root (`--input PATH`)."""
    return not self.procedural


SOURCES: dict[str, Source] = {}
"""name -> `Source`, in registration order (`register` adds to it)."""


def register(source: Source) -> Source:
  """Adds a source to `SOURCES`.

  Raises:
    ValueError: the name is taken.
  """
  if source.name in SOURCES:
    raise ValueError(f"a source named {source.name!r} is already registered")
  SOURCES[source.name] = source
  return source


def unregister(name: str) -> None:
  """Removes a registered source (a test's own)."""
  SOURCES.pop(name, None)


_PROCEDURAL = "camrep.data.procedural"
_CAPTURES = "camrep.data.readers.captures.collection"
_GQN, _CAR, _GIBSON, _7S = (
  settings_lib.GQN, settings_lib.CAR, settings_lib.GIBSON, settings_lib.SEVEN_SCENES
)  # fmt: skip

for _source in (
  Source("rooms", _PROCEDURAL, "make_family", True, _GQN, None,
         ("train", "test", "test_scenes"), "procedural _GQN-rooms-like scenes"),
  Source("object", _PROCEDURAL, "make_family", True, _CAR, None,
         ("train", "test", "test_scenes"), "procedural object on a view sphere (car)"),
  Source("area", _PROCEDURAL, "make_family", True, _GIBSON, None, ("train", "test"),
         "procedural Gibson-like areas"),
  Source("scene6dof", _PROCEDURAL, "make_family", True, _7S, None,
         ("train", "test"), "procedural 6-DOF scenes (7-Scenes)"),
  Source("gqn", "camrep.data.readers.gqn", "GQN", False, _GQN, None, ("train", "test"),
         "DeepMind _GQN TFRecords (rooms)", {"small": {"max_files": 1, "max_scenes": 200}}),
  Source("srn_cars", "camrep.data.readers.srn", "SRNCars", False, _CAR, None,
         ("train", "test", "test_scenes"), "SRN ShapeNet cars renders",
         {"small": {"image_size": 64}}),
  Source("gibson", "camrep.data.readers.gibson", "GibsonRooms", False, _GIBSON, None,
         ("train", "test"), "authors' Gibson renders", {"small": {"image_size": 64}}),
  Source("seven_scenes", "camrep.data.readers.seven_scenes", "SevenScenes", False, _7S,
         None, ("train", "test"), "Microsoft 7-Scenes RGB-D",
         {"small": {"image_size": 64, "scenes": ["chess"]}}),
  # Posed captures (_CAPTURES), one --input folder per instance.
  *(
    Source(f"{fmt}{suffix}", _CAPTURES, f"{fmt}_{kind}", False, setting,
           None, ("train", "test", "test_scenes"), f"{what} captures, {setting.name} setting",
           {"small": {"image_size": 64}})
    for fmt, what in (("nerf", "NeRF transforms.json"), ("llff", "LLFF"), ("colmap", "COLMAP"))
    for suffix, kind, setting in (("", "car", _CAR), ("_6dof", "6dof", _7S))
  ),
):  # fmt: skip
  register(_source)


def get(name: str) -> Source:
  """The registered source `name`.

  Raises:
    DataError: no source has that name.
  """
  try:
    return SOURCES[name]
  except KeyError:
    raise DataError(None, f"unknown data source {name!r}; registered: {sorted(SOURCES)}") from None


def is_procedural(name: str) -> bool:
  """Whether `name` is a registered procedural family (False for real and unknown names)."""
  return name in SOURCES and SOURCES[name].procedural


def setting_of(name: str) -> settings_lib.Setting:
  """The paper setting of a source, real or procedural.

  Raises:
    DataError: an unknown source, or one without a setting.
  """
  setting = get(name).setting
  if setting is None:
    raise DataError(None, f"data source {name!r} belongs to no paper setting")
  return setting


def procedural_of(setting: settings_lib.Setting | str) -> str:
  """The procedural family standing in for a setting's real dataset (gqn -> rooms, ...).

  Raises:
    DataError: an unknown setting, or one without a procedural source.
  """
  try:
    setting = settings_lib.get(setting)
  except ValueError as e:
    raise DataError(None, str(e)) from None
  for s in SOURCES.values():
    if s.procedural and s.setting is setting:
      return s.name
  raise DataError(None, f"setting {setting.name!r} has no procedural data source")


def is_available(name: str) -> bool:
  """Whether the module implementing source `name` is present in this tree."""
  return importlib.util.find_spec(get(name).module) is not None


def build(
  name: str,
  *,
  input_path: str | os.PathLike | None = None,
  preset: str | None = None,
  overrides: Mapping[str, Any] | None = None,
) -> Any:
  """Constructs a registered source (a `camrep.data.feed.storage.ViewSource`).

  Args:
    name: a key of `SOURCES`.
    input_path: dataset root, for the real readers only (capture sources: one folder or a list,
      one capture each).
    preset: named override set applied before `overrides` (None: the source's defaults).
    overrides: keyword overrides of the family / reader (a family's lists become tuples, as
      its frozen config holds them).

  Returns:
    The source (a procedural family or a reader).

  Raises:
    DataError: unknown or absent source, unknown preset, missing or extra input path, or
      settings the constructor does not accept.
  """
  entry = get(name)
  if not is_available(name):
    raise DataError(None, f"source {name!r} needs {entry.module}, which is not in this tree")
  kwargs: dict[str, Any] = {}
  if entry.needs_input:
    if input_path is None:
      raise DataError(None, f"source {name!r} reads a dataset: give its root with --input PATH")
    paths = list(input_path) if isinstance(input_path, list | tuple) else [input_path]
    for p in paths:
      if not pathlib.Path(p).exists():
        raise DataError(p, "input path does not exist")
    # Several inputs (one capture folder each) go to the reader as a list.
    input_path = os.fspath(paths[0]) if len(paths) == 1 else [os.fspath(p) for p in paths]
    if preset is not None:
      if preset not in entry.presets:
        raise DataError(
          None, f"source {name!r} has no preset {preset!r} (has: {sorted(entry.presets)})"
        )
      kwargs.update(entry.presets[preset])
  else:
    if input_path is not None:
      raise DataError(input_path, f"source {name!r} is procedural and takes no --input")
    if preset is not None:
      kwargs["preset"] = preset
    overrides = {k: tuple(v) if isinstance(v, list) else v for k, v in (overrides or {}).items()}
  kwargs.update(overrides or {})
  factory = getattr(importlib.import_module(entry.module), entry.attr)
  try:
    if entry.needs_input:
      return factory(input_path, **kwargs)
    return factory(name, **kwargs)
  except DataError:
    raise
  except (TypeError, ValueError) as e:
    raise DataError(None, f"source {name!r} rejected the settings {kwargs}: {e}") from None


def family_of_config(data_config, name: str | None = None) -> Any:
  """The procedural family a run's `config.data` names: source `name` (default
  `data_config.source`) with `data_config.preset` and the overrides `data_config.family`.

  Raises:
    DataError: not a procedural source, or settings the family does not accept.
  """
  name = name or data_config.source
  if not is_procedural(name):
    raise DataError(None, f"data source {name!r} is not a procedural family")
  family = data_config.get("family")
  overrides = family.to_dict() if family else {}
  return build(name, preset=data_config.get("preset", "default"), overrides=overrides)

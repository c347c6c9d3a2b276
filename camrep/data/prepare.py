"""Prepare any registered source as a tfds ArrayRecord dataset (+ sidecar index) for training:
`python -m camrep.data.prepare --source=NAME --data_dir=DIR [--input=PATH] [--preset=NAME]
[--config.FIELD=VALUE ...]`.

Commands (run from the repository root):

  python -m camrep.data.prepare --source=rooms --data_dir=/tmp/tfds --preset=small
  python -m camrep.data.prepare --source=object --data_dir=/tmp/tfds --config.num_train_scenes=20
  python -m camrep.data.prepare --source=gqn --input=/data/gqn-datasets --data_dir=/tmp/tfds \
      --config.max_files=2
  python -m camrep.data.prepare --list

Sources (`SOURCES`): the procedural families "rooms", "object", "area", "scene6dof"
(`camrep.data.procedural.make_family(name, **overrides)`) and the real-format readers
"gqn", "srn_cars", "gibson", "seven_scenes", which need `--input PATH` (the dataset root; see
each reader's docstring for the layout). `--config.FIELD=VALUE` passes a keyword override to
the chosen source's family / reader constructor (`source_fields`; `--list` names them): values
are parsed as the default's type for numbers, strings and booleans, as Python literals otherwise
(`--config.scenes="('chess',)"`); an unknown field is an error. `--preset NAME` applies a named
set of overrides first (see `PRESETS`).

Output: `DATA_DIR/NAME/CONFIG/VERSION/`, CONFIG being `--config_name` or else the preset name
(no CONFIG level without either); see `camrep.data.storage` for the files. Preparing
again into the same directory reuses the dataset if its recorded source settings are the same
and refuses otherwise (pass `--overwrite`, or another `--config_name`). Exit status as every
camrep tool (`camrep.runtime.cli`): a full disk ends with one `error:` line and no half-written
dataset version (storage writes into a temporary directory and renames it when complete).
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import inspect
import json
import os
import pathlib
import sys
import time
from collections.abc import Mapping, Sequence
from typing import Any

from absl import flags

from camrep.data import storage
from camrep.data.errors import DataError
from camrep.data.storage import ViewSource
from camrep.runtime import cli


@dataclasses.dataclass(frozen=True)
class SourceEntry:
  """How to construct one registered source.

  Attributes:
    module: module that defines it.
    attr: the reader class (called as `attr(input_path, **overrides)`) or, for procedural
      families, "make_family" (called as `make_family(name, **overrides)`).
    needs_input: whether `--input PATH` is required (real formats) or refused (procedural).
    description: one line for `--list`.
  """

  module: str
  attr: str
  needs_input: bool
  description: str


SOURCES: dict[str, SourceEntry] = {
  "rooms": SourceEntry(
    "camrep.data.procedural", "make_family", False, "procedural GQN-rooms-like scenes"
  ),
  "object": SourceEntry(
    "camrep.data.procedural", "make_family", False, "procedural object on a view sphere (car)"
  ),
  "area": SourceEntry(
    "camrep.data.procedural", "make_family", False, "procedural Gibson-like areas"
  ),
  "scene6dof": SourceEntry(
    "camrep.data.procedural", "make_family", False, "procedural 6-DOF scenes (7-Scenes)"
  ),
  "gqn": SourceEntry("camrep.data.gqn", "GQN", True, "DeepMind GQN TFRecords (rooms)"),
  "srn_cars": SourceEntry("camrep.data.srn", "SRNCars", True, "SRN ShapeNet cars renders"),
  "gibson": SourceEntry("camrep.data.gibson", "GibsonRooms", True, "authors' Gibson renders"),
  "seven_scenes": SourceEntry(
    "camrep.data.seven_scenes", "SevenScenes", True, "Microsoft 7-Scenes RGB-D"
  ),
}

PRESETS: dict[str, dict[str, dict[str, Any]]] = {
  "gqn": {"small": {"max_files": 1, "max_scenes": 200}},
  "srn_cars": {"small": {"image_size": 64}},
  "gibson": {"small": {"image_size": 64}},
  "seven_scenes": {"small": {"image_size": 64, "scenes": ["chess"]}},
}
"""Named override sets for the real readers. The procedural families take their presets from
`camrep.data.procedural` itself (`make_family(..., preset=NAME)` or its `PRESETS` table)."""


def is_available(name: str) -> bool:
  """Whether the module implementing source `name` is present in this tree."""
  return importlib.util.find_spec(SOURCES[name].module) is not None


def source_fields(name: str) -> dict[str, Any]:
  """The keyword overrides source `name` takes, with their defaults: the procedural family's
  config fields, or the reader's keyword parameters after the dataset root.

  Raises:
    DataError: unknown or absent source.
  """
  if name not in SOURCES:
    raise DataError(None, f"unknown source {name!r}; registered: {sorted(SOURCES)}")
  entry = SOURCES[name]
  if not is_available(name):
    raise DataError(None, f"source {name!r} needs {entry.module}, which is not in this tree")
  module = importlib.import_module(entry.module)
  if entry.attr == "make_family":
    return dataclasses.asdict(module.make_config(name))
  params = list(inspect.signature(getattr(module, entry.attr)).parameters.values())
  return {
    p.name: p.default
    for p in params[1:]  # the first is the dataset root
    if p.default is not inspect.Parameter.empty
    and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
  }


def _procedural_presets(module: Any, name: str, preset: str) -> dict[str, Any] | None:
  """The procedural module's own overrides for `preset`, or None if it routes presets itself."""
  if "preset" in inspect.signature(module.make_family).parameters:
    return None
  table = getattr(module, "PRESETS", {})
  per_family = table.get(name, table)
  if preset not in per_family:
    raise DataError(None, f"source {name!r} has no preset {preset!r} (has: {sorted(per_family)})")
  return dict(per_family[preset])


def make_source(
  name: str,
  *,
  input_path: str | os.PathLike | None = None,
  preset: str | None = None,
  overrides: Mapping[str, Any] | None = None,
) -> ViewSource:
  """Constructs a registered source.

  Args:
    name: a key of `SOURCES`.
    input_path: dataset root, for the real-format readers only.
    preset: named override set applied before `overrides`.
    overrides: keyword overrides for the family / reader.

  Returns:
    The source.

  Raises:
    DataError: unknown or absent source, unknown preset, missing/extra input path,
      or overrides the constructor does not accept.
  """
  if name not in SOURCES:
    raise DataError(None, f"unknown source {name!r}; registered: {sorted(SOURCES)}")
  entry = SOURCES[name]
  if not is_available(name):
    raise DataError(None, f"source {name!r} needs {entry.module}, which is not in this tree")
  module = importlib.import_module(entry.module)
  kwargs: dict[str, Any] = {}
  if entry.needs_input:
    if input_path is None:
      raise DataError(None, f"source {name!r} reads a dataset: give its root with --input PATH")
    if not pathlib.Path(input_path).exists():
      raise DataError(input_path, "input path does not exist")
    if preset is not None:
      presets = PRESETS.get(name, {})
      if preset not in presets:
        raise DataError(None, f"source {name!r} has no preset {preset!r} (has: {sorted(presets)})")
      kwargs.update(presets[preset])
  else:
    if input_path is not None:
      raise DataError(input_path, f"source {name!r} is procedural and takes no --input")
    if preset is not None:
      preset_kwargs = _procedural_presets(module, name, preset)
      kwargs.update({"preset": preset} if preset_kwargs is None else preset_kwargs)
  kwargs.update(overrides or {})
  factory = getattr(module, entry.attr)
  try:
    if entry.needs_input:
      return factory(os.fspath(input_path), **kwargs)
    return factory(name, **kwargs)
  except DataError:
    raise
  except (TypeError, ValueError) as e:
    raise DataError(None, f"source {name!r} rejected the settings {kwargs}: {e}") from None


def _check_reuse(path: pathlib.Path, settings: Mapping[str, Any], overwrite: bool) -> None:
  """Refuses to reuse an existing dataset that was prepared with other settings."""
  meta_file = path / storage.METADATA_FILE
  if overwrite or not meta_file.exists():
    return
  recorded = json.loads(meta_file.read_text()).get("metadata", {})
  wanted = json.loads(json.dumps(dict(settings), default=str))
  if recorded != wanted:
    raise DataError(
      path,
      f"already prepared with {recorded}, now asked for {wanted}; pass --overwrite or a "
      "different --config_name",
    )


def target_dir(
  data_dir: str | os.PathLike, name: str, config_name: str | None, version: str
) -> pathlib.Path:
  """Where `prepare_source` writes: `data_dir/name[/config_name]/version`."""
  path = pathlib.Path(data_dir) / name
  return (path / config_name if config_name else path) / version


def prepare_source(
  name: str,
  data_dir: str | os.PathLike,
  *,
  input_path: str | os.PathLike | None = None,
  preset: str | None = None,
  overrides: Mapping[str, Any] | None = None,
  config_name: str | None = None,
  dataset_name: str | None = None,
  version: str = storage.DEFAULT_VERSION,
  overwrite: bool = False,
  progress: bool = True,
) -> pathlib.Path:
  """Constructs source `name` and stores it with `storage.prepare`.

  Args:
    name: a key of `SOURCES`.
    data_dir: tfds data directory.
    input_path: dataset root (real formats).
    preset: named override set.
    overrides: keyword overrides for the family / reader.
    config_name: builder-config sub-directory; defaults to `preset`.
    dataset_name: dataset directory name; defaults to `name`.
    version: tfds version string.
    overwrite: regenerate even if the dataset exists.
    progress: show tqdm bars.

  Returns:
    The dataset directory.
  """
  source = make_source(name, input_path=input_path, preset=preset, overrides=overrides)
  config_name = config_name or preset
  dataset_name = dataset_name or name
  settings = {
    "source": name,
    "input": None if input_path is None else os.fspath(input_path),
    "preset": preset,
    "overrides": dict(overrides or {}),
  }
  _check_reuse(target_dir(data_dir, dataset_name, config_name, version), settings, overwrite)
  return storage.prepare(
    source,
    data_dir,
    name=dataset_name,
    version=version,
    config=config_name,
    metadata=settings,
    overwrite=overwrite,
    progress=progress,
  )


def define_flags(fv: flags.FlagValues, argv: Sequence[str] = ()) -> None:
  """The tool's flags (`camrep.runtime.cli.Define`); `--config.` are the chosen source's
  constructor keywords (`source_fields`)."""
  flags.DEFINE_enum("source", None, sorted(SOURCES), "Source to prepare.", flag_values=fv)
  flags.DEFINE_string("data_dir", None, "tfds data directory to write into.", flag_values=fv)
  flags.DEFINE_string("input", None, "Dataset root (real formats only).", flag_values=fv)
  flags.DEFINE_string("preset", None, "Named override set, e.g. 'small'.", flag_values=fv)
  flags.DEFINE_string(
    "config_name", None, "Sub-directory for this variant (default: the preset).", flag_values=fv
  )
  flags.DEFINE_string("name", None, "Dataset name (default: the source name).", flag_values=fv)
  flags.DEFINE_string("version", storage.DEFAULT_VERSION, "tfds version string.", flag_values=fv)
  flags.DEFINE_bool("overwrite", False, "Regenerate if present.", flag_values=fv)
  flags.DEFINE_bool("no_progress", False, "No progress bars.", flag_values=fv)
  flags.DEFINE_bool("list", False, "List the sources and their fields, and exit.", flag_values=fv)
  source = cli.peek_flag(argv, "source")
  if source in SOURCES and is_available(source):
    cli.define_overrides(
      fv, argv, source_fields(source), f"A keyword of the {source!r} source's constructor."
    )
  elif any(a.startswith("--config.") for a in argv):
    raise cli.UsageError("--config.FIELD=VALUE overrides need --source=NAME (see --list)")


def _list() -> None:
  for name, entry in SOURCES.items():
    state = "" if is_available(name) else f"  [missing: {entry.module}]"
    kind = "--input PATH" if entry.needs_input else "procedural"
    print(f"{name:13s} {kind:13s} {entry.description}{state}")
    if not state:
      print(f"{'':13s} --config.: {', '.join(source_fields(name))}")


def run_cli(fv: flags.FlagValues) -> int:
  """The tool (`camrep.runtime.cli.Body`)."""
  if fv.list:
    _list()
    return 0
  if fv.source is None or fv.data_dir is None:
    raise cli.UsageError("--source and --data_dir are required (--list shows the sources)")
  entry = SOURCES[fv.source]
  if entry.needs_input and fv.input is None:
    raise cli.UsageError(f"--source={fv.source} reads a dataset: give its root with --input PATH")
  if not entry.needs_input and fv.input is not None:
    raise cli.UsageError(f"--source={fv.source} is procedural and takes no --input")
  target = target_dir(fv.data_dir, fv.name or fv.source, fv.config_name or fv.preset, fv.version)
  existed = (target / storage.METADATA_FILE).exists() and not fv.overwrite
  t0 = time.perf_counter()
  path = prepare_source(
    fv.source,
    fv.data_dir,
    input_path=fv.input,
    preset=fv.preset,
    overrides=cli.overrides(fv),
    config_name=fv.config_name,
    dataset_name=fv.name,
    version=fv.version,
    overwrite=fv.overwrite,
    progress=not fv.no_progress,
  )
  meta = storage.load_metadata(path)
  counts = ", ".join(
    f"{split}: {c['num_scenes']} scenes / {c['num_views']} views"
    for split, c in meta["splits"].items()
  )
  verb = "reused" if existed else "wrote"
  print(f"{verb} {path} ({counts}) in {time.perf_counter() - t0:.1f} s")
  return 0


def main(argv: Sequence[str] | None = None) -> int:
  """In-process entry (tests, notebooks): `argv` are the flags; returns the exit status."""
  return cli.call(define_flags, run_cli, sys.argv[1:] if argv is None else argv, prog=__name__)


if __name__ == "__main__":
  cli.main(define_flags, run_cli)

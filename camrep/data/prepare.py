"""Prepare any registered source as a tfds ArrayRecord dataset (+ sidecar index) for training.

Commands (run from the repository root):

  python -m camrep.data.prepare --source rooms --data_dir /tmp/tfds --preset small
  python -m camrep.data.prepare --source object --data_dir /tmp/tfds --set num_scenes=20
  python -m camrep.data.prepare --source gqn --input /data/gqn-datasets --data_dir /tmp/tfds \
      --set max_files=2
  python -m camrep.data.prepare --list

Sources: the procedural families "rooms", "object", "area", "scene6dof"
(`camrep.data.procedural.make_family(name, **overrides)`) and the real-format readers
"gqn", "srn_cars", "gibson", "seven_scenes", which need `--input PATH` (the dataset root; see
each reader's docstring for the layout). `--set key=value` passes a keyword override to the
family / reader constructor (values parsed as Python literals, else kept as strings);
`--preset NAME` applies a named set of overrides first (see `PRESETS`).

Output: `DATA_DIR/NAME/CONFIG/VERSION/`, CONFIG being `--config_name` or else the preset name
(no CONFIG level without either); see `camrep.data.storage` for the files. Preparing
again into the same directory reuses the dataset if its recorded source settings are the same
and refuses otherwise (pass `--overwrite`, or another `--config_name`).
"""

from __future__ import annotations

import argparse
import ast
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

from camrep.data import storage
from camrep.data.errors import DataError
from camrep.data.storage import ViewSource


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
  # Posed captures (camrep.data.captures.source), one --input folder per instance.
  **{
    f"{fmt}{suffix}": SourceEntry(
      "camrep.data.captures.source", f"{fmt}_{kind}", True, f"{what} captures, {setting}"
    )
    for fmt, what in (("nerf", "NeRF transforms.json"), ("llff", "LLFF"), ("colmap", "COLMAP"))
    for suffix, kind, setting in (("", "car", "car setting"), ("_6dof", "6dof", "6-DOF setting"))
  },
}

PRESETS: dict[str, dict[str, dict[str, Any]]] = {
  "gqn": {"small": {"max_files": 1, "max_scenes": 200}},
  "srn_cars": {"small": {"image_size": 64}},
  "gibson": {"small": {"image_size": 64}},
  "seven_scenes": {"small": {"image_size": 64, "scenes": ["chess"]}},
  **{
    f"{f}{x}": {"small": {"image_size": 64}}
    for f in ("nerf", "llff", "colmap")
    for x in ("", "_6dof")
  },
}
"""Named override sets for the real readers. The procedural families take their presets from
`camrep.data.procedural` itself (`make_family(..., preset=NAME)` or its `PRESETS` table)."""


def is_available(name: str) -> bool:
  """Whether the module implementing source `name` is present in this tree."""
  return importlib.util.find_spec(SOURCES[name].module) is not None


def parse_set(items: Sequence[str]) -> dict[str, Any]:
  """Parses `key=value` strings; values are Python literals where they parse, else strings.

  Raises:
    ValueError: an item without "=" or with an empty key.
  """
  out = {}
  for item in items:
    key, sep, value = item.partition("=")
    key = key.strip()
    if not sep or not key:
      raise ValueError(f"--set expects key=value, got {item!r}")
    try:
      out[key] = ast.literal_eval(value)
    except (ValueError, SyntaxError):
      out[key] = value
  return out


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
    paths = list(input_path) if isinstance(input_path, list | tuple) else [input_path]
    for p in paths:
      if not pathlib.Path(p).exists():
        raise DataError(p, "input path does not exist")
    # Several inputs (one capture folder each) go to the reader as a list.
    input_path = os.fspath(paths[0]) if len(paths) == 1 else [os.fspath(p) for p in paths]
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
      return factory(input_path, **kwargs)
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
    "input": None if input_path is None else _input_setting(input_path),
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


def _input_setting(input_path: Any) -> str | list[str]:
  """The recorded --input: a path, or a list of paths (several capture folders)."""
  if isinstance(input_path, list | tuple):
    paths = [os.fspath(p) for p in input_path]
    return paths[0] if len(paths) == 1 else paths
  return os.fspath(input_path)


def _parser() -> argparse.ArgumentParser:
  parser = argparse.ArgumentParser(
    prog="python -m camrep.data.prepare",
    description="Store a camrep source as a tfds ArrayRecord dataset.",
  )
  parser.add_argument("--source", choices=sorted(SOURCES), help="source to prepare")
  parser.add_argument("--data_dir", help="tfds data directory to write into")
  parser.add_argument(
    "--input", nargs="+", help="dataset root (real formats); captures: one folder per instance"
  )
  parser.add_argument("--preset", help="named override set, e.g. 'small'")
  parser.add_argument(
    "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
    help="keyword override for the family/reader (repeatable)",
  )  # fmt: skip
  parser.add_argument("--config_name", help="sub-directory for this variant (default: preset)")
  parser.add_argument("--name", help="dataset name (default: the source name)")
  parser.add_argument("--version", default=storage.DEFAULT_VERSION)
  parser.add_argument("--overwrite", action="store_true", help="regenerate if present")
  parser.add_argument("--no_progress", action="store_true", help="no progress bars")
  parser.add_argument("--list", action="store_true", help="list the sources and exit")
  return parser


def main(argv: Sequence[str] | None = None) -> pathlib.Path | None:
  """Command-line entry point; returns the dataset directory (None for --list)."""
  parser = _parser()
  args = parser.parse_args(argv)
  if args.list:
    for name, entry in SOURCES.items():
      state = "" if is_available(name) else f"  [missing: {entry.module}]"
      kind = "--input PATH" if entry.needs_input else "procedural"
      print(f"{name:13s} {kind:13s} {entry.description}{state}")
    return None
  if args.source is None or args.data_dir is None:
    parser.error("--source and --data_dir are required")
  entry = SOURCES[args.source]
  if entry.needs_input and args.input is None:
    parser.error(f"--source {args.source} reads a dataset: give its root with --input PATH")
  if not entry.needs_input and args.input is not None:
    parser.error(f"--source {args.source} is procedural and takes no --input")
  try:
    overrides = parse_set(args.overrides)
  except ValueError as e:
    parser.error(str(e))
  target = target_dir(
    args.data_dir, args.name or args.source, args.config_name or args.preset, args.version
  )
  existed = (target / storage.METADATA_FILE).exists() and not args.overwrite
  t0 = time.perf_counter()
  path = prepare_source(
    args.source,
    args.data_dir,
    input_path=args.input,
    preset=args.preset,
    overrides=overrides,
    config_name=args.config_name,
    dataset_name=args.name,
    version=args.version,
    overwrite=args.overwrite,
    progress=not args.no_progress,
  )
  meta = storage.load_metadata(path)
  counts = ", ".join(
    f"{split}: {c['num_scenes']} scenes / {c['num_views']} views"
    for split, c in meta["splits"].items()
  )
  verb = "reused" if existed else "wrote"
  print(f"{verb} {path} ({counts}) in {time.perf_counter() - t0:.1f} s")
  return path


if __name__ == "__main__":
  try:
    main()
  except DataError as e:
    sys.exit(f"error: {e}")

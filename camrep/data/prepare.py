"""Prepare any registered source as a tfds ArrayRecord dataset (+ sidecar index) for training.

Commands (run from the repository root):

  python -m camrep.data.prepare --source rooms --data_dir /tmp/tfds --preset small
  python -m camrep.data.prepare --source object --data_dir /tmp/tfds --set num_scenes=20
  python -m camrep.data.prepare --source gqn --input /data/gqn-datasets --data_dir /tmp/tfds \
      --set max_files=2
  python -m camrep.data.prepare --list

Sources: every source of the registry `camrep.data.sources` (`--list` prints them): the
procedural families "rooms", "object", "area", "scene6dof" and the real-format readers "gqn",
"srn_cars", "gibson", "seven_scenes", which need `--input PATH` (the dataset root; see each
reader's docstring for the layout). `--set key=value` passes a keyword override to the
family / reader constructor (values parsed as Python literals, else kept as strings);
`--preset NAME` applies a named set of overrides first (a reader's `Source.presets`; the
families' "default" / "small").

Output: `DATA_DIR/NAME/CONFIG/VERSION/`, CONFIG being `--config_name` or else the preset name
(no CONFIG level without either); see `camrep.data.storage` for the files. Preparing
again into the same directory reuses the dataset if its recorded source settings are the same
and refuses otherwise (pass `--overwrite`, or another `--config_name`).
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import pathlib
import sys
import time
from collections.abc import Mapping, Sequence
from typing import Any

from camrep.data import sources, storage
from camrep.data.errors import DataError


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
    name: a registered source (`camrep.data.sources`).
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
  source = sources.build(name, input_path=input_path, preset=preset, overrides=overrides)
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


def _parser() -> argparse.ArgumentParser:
  parser = argparse.ArgumentParser(
    prog="python -m camrep.data.prepare",
    description="Store a camrep source as a tfds ArrayRecord dataset.",
  )
  parser.add_argument("--source", choices=sorted(sources.SOURCES), help="source to prepare")
  parser.add_argument("--data_dir", help="tfds data directory to write into")
  parser.add_argument("--input", help="dataset root (real formats only)")
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
    for name, entry in sources.SOURCES.items():
      state = "" if sources.is_available(name) else f"  [missing: {entry.module}]"
      kind = "--input PATH" if entry.needs_input else "procedural"
      print(f"{name:13s} {kind:13s} {entry.description}{state}")
    return None
  if args.source is None or args.data_dir is None:
    parser.error("--source and --data_dir are required")
  entry = sources.get(args.source)
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

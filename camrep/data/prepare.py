"""Prepare any registered source as a tfds ArrayRecord dataset (+ sidecar index) for training:
`python -m camrep.data.prepare --source=NAME --data_dir=DIR [--input=PATH ...] [--preset=NAME]
[--config.FIELD=VALUE ...]`.

Commands (run from the repository root):

  python -m camrep.data.prepare --source=rooms --data_dir=/tmp/tfds --preset=small
  python -m camrep.data.prepare --source=object --data_dir=/tmp/tfds --config.num_train_scenes=20
  python -m camrep.data.prepare --source=nerf --input=path/to/chair \
      --data_dir=/tmp/capture --preset=small
  python -m camrep.data.prepare --source=gqn --input=/data/gqn-datasets --data_dir=/tmp/tfds \
      --config.max_files=2
  python -m camrep.data.prepare --list

Sources (`--list` prints each one's `--config.` fields) and the layout each reads:

  rooms, object, area, scene6dof
              procedural families (GQN rooms, a car-like object on a view sphere, Gibson-like
              areas, 6-DOF scenes), rendered by camrep; no --input
  gqn         --input DIR/: DIR/<dataset>/{train,test}/NNN-of-MMM.tfrecord (deepmind/gqn-datasets)
  srn_cars    --input DIR/: DIR/<split dir>/<car>/{rgb/*.png, pose/*.txt, intrinsics.txt}
              (cars_train, cars_train_test, cars_test)
  gibson      --input DIR/: DIR/<Building>/<area>/{train_meta.json, test_meta.json, images}
              (the authors' renders)
  seven_scenes
              --input DIR/: DIR/<scene>/{TrainSplit.txt, TestSplit.txt,
              seq-XX/frame-NNNNNN.{color.png,pose.txt}} (Microsoft 7-Scenes)
  nerf        --input CAPTURE/ (repeat per capture): CAPTURE/transforms.json, or Blender's
              transforms_{train,val,test}.json, with the images their file_path names
              (NeRF, instant-ngp, nerfstudio)
  llff        --input CAPTURE/: CAPTURE/poses_bounds.npy (N x 17) and images/ or images_N/
              (optional masks_N/)
  colmap      --input CAPTURE/: CAPTURE/images/ and CAPTURE/sparse/0/{cameras,images,points3D}
              .{bin,txt} (a COLMAP sparse model)
  nerf_6dof, llff_6dof, colmap_6dof
              the same capture folders in the 6-DOF (7-Scenes-like) setting, for forward-facing
              or walk-through captures

The capture sources (nerf, llff, colmap) take one --input folder per instance: the car setting's
pose is (azimuth, polar) around the point the cameras look at. A capture with a test split of its
own keeps it; any other holds out every --config.holdout_every-th view (default 8) as its test
views; the summary printed at the end names, per capture, its views per split and why.

`--config.FIELD=VALUE` passes a keyword override to the chosen source's family / reader
constructor (`source_fields`; `--list` names them): values are parsed as the default's type for
numbers, strings and booleans, as Python literals otherwise (`--config.scenes="('chess',)"`); an
unknown field is an error. `--preset NAME` applies a named set of overrides first (a reader's
`Source.presets`; the families' "default" / "small").

Output: `DATA_DIR/NAME/CONFIG/VERSION/`, CONFIG being `--config_name` or else the preset name
(no CONFIG level without either); see `camrep.data.feed.storage` for the files. Preparing
again into the same directory reuses the dataset if its recorded source settings are the same
and, for captures, its inputs are unchanged (each frame's image and mask files by size and
modification time, pose, intrinsics; `CaptureSource.inputs`); it refuses otherwise, naming what
differs (pass `--overwrite`, or another `--config_name`). One prepare at a time writes a dataset
(a lock in `DATA_DIR/NAME[/CONFIG]`; a second is refused by name). Exit status as every camrep
tool (`camrep.runtime.cli`): a full disk ends with one `error:` line and no half-written dataset
version (storage writes into a temporary directory and renames it when complete; an overwritten
version stays in place until the new one is complete).
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

from camrep.data import records, sources
from camrep.data.errors import DataError
from camrep.data.feed import storage
from camrep.runtime import cli


def source_fields(name: str) -> dict[str, Any]:
  """The keyword overrides source `name` takes, with their defaults: the procedural family's
  config fields, or the reader's keyword parameters after the dataset root.

  Raises:
    DataError: unknown or absent source.
  """
  entry = sources.get(name)
  if not sources.is_available(name):
    raise DataError(None, f"source {name!r} needs {entry.module}, which is not in this tree")
  module = importlib.import_module(entry.module)
  if entry.procedural:
    return dataclasses.asdict(module.make_config(name))
  params = list(inspect.signature(getattr(module, entry.attr)).parameters.values())
  return {
    p.name: p.default
    for p in params[1:]  # the first is the dataset root
    if p.default is not inspect.Parameter.empty
    and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
  }


def _check_reuse(
  path: pathlib.Path, settings: Mapping[str, Any], overwrite: bool, source: Any
) -> None:
  """Refuses to reuse an existing dataset that was prepared with other settings or, for a
  source that fingerprints its inputs (`inputs()`), from inputs that have changed since."""
  meta_file = path / storage.METADATA_FILE
  if overwrite or not meta_file.exists():
    return
  meta = storage.load_metadata(path)
  recorded = meta.get("metadata", {})
  wanted = json.loads(json.dumps(dict(settings), default=str))
  if recorded != wanted:
    raise DataError(
      path,
      f"already prepared with {recorded}, now asked for {wanted}; pass --overwrite or a "
      "different --config_name",
    )
  inputs = getattr(source, "inputs", None)
  if not callable(inputs):
    return
  before, now = meta.get("inputs"), inputs()
  if before is None:
    print(
      f"warning: {path} was prepared before camrep recorded its inputs, so whether they changed "
      "since cannot be told; reusing it (pass --overwrite to prepare it again)",
      file=sys.stderr,
      flush=True,
    )
  elif before.get("digest") != now["digest"]:
    raise DataError(
      path,
      f"its inputs changed since it was prepared: {input_changes(before, now)}; pass "
      "--overwrite to prepare it again, or another --config_name to keep both",
    )


def input_changes(before: Mapping[str, Any], now: Mapping[str, Any], limit: int = 3) -> str:
  """What differs between two `inputs()` fingerprints, in words (captures and frames by name).

  Args:
    before, now: {"captures": [{"name", "root", "frames": {path: digest}}]}.
    limit: frame names listed per kind of change.
  """

  def names(keys: Sequence[str]) -> str:
    keys = sorted(keys)
    return ", ".join(keys[:limit]) + (f", ... ({len(keys)} in all)" if len(keys) > limit else "")

  old, new = before.get("captures", []), now.get("captures", [])
  if [c["root"] for c in old] != [c["root"] for c in new]:
    return f"captures were {[c['root'] for c in old]}, now {[c['root'] for c in new]}"
  parts = []
  for a, b in zip(old, new, strict=True):
    fa, fb = a.get("frames", {}), b.get("frames", {})
    removed = [k for k in fa if k not in fb]
    added = [k for k in fb if k not in fa]
    changed = [k for k in fa if k in fb and fa[k] != fb[k]]
    what = [
      f"{len(x)} frame(s) {verb} ({names(x)})"
      for x, verb in ((removed, "removed"), (added, "added"), (changed, "changed"))
      if x
    ]
    if what:
      parts.append(f"{b['name']}: {len(fb)} frames, was {len(fa)}; " + ", ".join(what))
  return "; ".join(parts) or "the fingerprint differs"


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
    input_path: dataset root (real formats); a list of folders for the capture sources.
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
  check_overrides(name, overrides or {})
  storage.check_path(data_dir, "--data_dir")
  source = sources.build(name, input_path=input_path, preset=preset, overrides=overrides)
  config_name = config_name or preset
  dataset_name = dataset_name or name
  settings = {
    "source": name,
    "input": None if input_path is None else _input_setting(input_path),
    "preset": preset,
    "overrides": dict(overrides or {}),
  }
  path = target_dir(data_dir, dataset_name, config_name, version)
  _check_reuse(path, settings, overwrite, source)
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


def check_overrides(name: str, overrides: Mapping[str, Any]) -> None:
  """Refuses sizes that no source can render or resize to, before anything is built.

  Raises:
    DataError: an `image_size` (or another `*_size` field whose default is a positive integer)
      that is not a positive integer.
  """
  defaults = source_fields(name)
  for key, value in overrides.items():
    default = defaults.get(key)
    sized = key == "image_size" or key.endswith("_size")
    if sized and isinstance(default, int) and not isinstance(default, bool) and default > 0:
      if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise DataError(None, f"--config.{key}={value}: must be a positive integer (pixels)")


def _input_setting(input_path: Any) -> str | list[str]:
  """The recorded --input: a path, or a list of paths (several capture folders)."""
  if isinstance(input_path, list | tuple):
    paths = [os.fspath(p) for p in input_path]
    return paths[0] if len(paths) == 1 else paths
  return os.fspath(input_path)


def define_flags(fv: flags.FlagValues, argv: Sequence[str] = ()) -> None:
  """The tool's flags (`camrep.runtime.cli.Define`); `--config.` are the chosen source's
  constructor keywords (`source_fields`)."""
  flags.DEFINE_enum("source", None, sorted(sources.SOURCES), "Source to prepare.", flag_values=fv)
  flags.DEFINE_string("data_dir", None, "tfds data directory to write into.", flag_values=fv)
  flags.DEFINE_multi_string(
    "input",
    None,
    "Dataset root (real formats only); capture sources: one folder per instance (repeat).",
    flag_values=fv,
  )
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
  if source in sources.SOURCES and sources.is_available(source):
    fields = source_fields(source)
    cli.define_overrides(
      fv,
      argv,
      fields,
      f"--config.FIELD=VALUE: a keyword of the {source!r} source's constructor, one of (with "
      f"its default) {', '.join(f'{k}={v!r}' for k, v in fields.items())}.",
    )
  elif any(a.startswith("--config.") for a in argv):
    raise cli.UsageError("--config.FIELD=VALUE overrides need --source=NAME (see --list)")
  else:
    cli.define_overrides(
      fv,
      argv,
      {},
      "--config.FIELD=VALUE: a keyword of the chosen source's constructor (image_size, "
      "holdout_every, ...); `--source=NAME --help` lists a source's fields, --list every "
      "source's.",
    )


def _list() -> None:
  for name, entry in sources.SOURCES.items():
    state = "" if sources.is_available(name) else f"  [missing: {entry.module}]"
    kind = "procedural" if entry.procedural else "--input PATH"
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
  entry = sources.get(fv.source)
  if not entry.procedural and fv.input is None:
    raise cli.UsageError(f"--source={fv.source} reads a dataset: give its root with --input PATH")
  if entry.procedural and fv.input is not None:
    raise cli.UsageError(f"--source={fv.source} is procedural and takes no --input")
  if entry.procedural:  # rendered with JAX: refuse an unusable JAX_PLATFORMS before writing
    cli.check_jax_backend()
  target = target_dir(fv.data_dir, fv.name or fv.source, fv.config_name or fv.preset, fv.version)
  existed = (target / storage.METADATA_FILE).exists() and not fv.overwrite
  t0 = time.perf_counter()
  path = prepare_source(
    fv.source,
    fv.data_dir,
    input_path=None if fv.input is None else (fv.input[0] if len(fv.input) == 1 else fv.input),
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
  for line in records.split_summary(meta):  # captures: per capture, its views per split and why
    print(f"  {line}")
  return 0


def main(argv: Sequence[str] | None = None) -> int:
  """In-process entry (tests, notebooks): `argv` are the flags; returns the exit status."""
  return cli.call(define_flags, run_cli, sys.argv[1:] if argv is None else argv, prog=__name__)


if __name__ == "__main__":
  cli.main(define_flags, run_cli)

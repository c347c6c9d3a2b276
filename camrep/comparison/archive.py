"""A launch's archive (`--archive DIR`, e.g. results/converge): one compact record per finished run.

A converge launch takes more hours than a machine is kept. The archive holds, for every finished
run of a launch's DIR, its record `run.json` (`camrep.regression.runs`: what the tables and
figures read; never checkpoints), at the run's place (synthesis/<name>, regression/<column>/
<representation>/<lr>_seed<k>, crossed/<column>/<run>), beside the record of a run under
synthesis/ its config.json and record.json (3 KB: what its initial pose system is made from, so
that the "untrained" control regresses it on another machine, `restore.load_model`) and, up to
`POSE_FILE_LIMIT` bytes, its final pose system (pose_system.npz, `restore.load_pose_file`: the
car's, 7-Scenes' and the captures' 1-D grids, ~30 KB; not the rooms' and area's 2-D grids,
0.6-1.1 MB, whose readers run where the run trained), and the launch's tables and figures. A
launch copies each run's record in as soon as the run ends (`sync`), and starts by restoring the
records DIR holds into its own DIR (`restore`): a launch cut short resumes on another machine,
losing only the runs in flight. An archive of whole run files (config.json, results.json,
errors_*.npz, ... as launches kept them before) is restored alike; `tools/compact_results.py`
turns one into records.
"""

from __future__ import annotations

import glob
import os
import shutil

from camrep.regression import runs
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import restore as restore_lib

# Run workdirs inside a launch's DIR, and the launch's own tables and figures. "lvsm/*/*" are a
# transformer launch's view-synthesis runs (`camrep.comparison.transformer`).
RUN_PATTERNS = ("synthesis/*", "lvsm/*/*", "regression/*/*/*", "crossed/*/*")
# The top folders of view-synthesis runs: restored only where DIR has no workdir of that name.
SYNTHESIS_ROOTS = ("synthesis", "lvsm")
TOP_PATTERNS = ("*.md", "*.png", "*.pdf")
# A view-synthesis run's files kept beside its record (runs under synthesis/, whose pose systems
# regressions read): its config and data record (`restore.load_model`), and its final pose
# system where it is no larger than POSE_FILE_LIMIT bytes (an archive is committed to git).
SYNTHESIS_FILES = (runs.CONFIG_FILE, workdir_lib.RECORD_FILE, restore_lib.POSE_FILE)
POSE_FILE_LIMIT = 64 * 1024


def run_dirs(root: str) -> list[str]:
  """The run directories under a launch's DIR or an archive (relative paths, sorted)."""
  out = []
  for pattern in RUN_PATTERNS:
    out += [
      os.path.relpath(d, root)
      for d in sorted(glob.glob(os.path.join(root, pattern)))
      if os.path.isdir(d)
    ]
  return out


def _copy_if_changed(src: str, dst: str, rewrite=None) -> bool:
  """Copies src to dst (a temporary file, then a rename) unless dst has the same bytes (those of
  `rewrite(src's bytes)` when given)."""
  with open(src, "rb") as f:
    data = f.read()
  if rewrite is not None:
    data = rewrite(data)
  if os.path.exists(dst):
    with open(dst, "rb") as f:
      if f.read() == data:
        return False
  os.makedirs(os.path.dirname(dst), exist_ok=True)
  tmp = f"{dst}.tmp{os.getpid()}"
  with open(tmp, "wb") as f:
    f.write(data)
  os.replace(tmp, dst)
  return True


def sync(out: str, archive: str) -> int:
  """Writes into `archive` the record of every finished, readable run of `out` and the launch's
  tables and figures (the runs a table names moved into the archive: `_moved_paths`), where
  missing or changed; returns how many files it wrote. A run that cannot be read is left out (it
  is trained again)."""
  n = 0
  for rel in run_dirs(out):
    wd = os.path.join(out, rel)
    if not runs.is_finished(wd) or not _complete(wd):
      continue
    try:
      record = runs.compact(runs.load(wd, arrays=True))
    except runs.DamagedRun:
      continue
    n += runs.write_record(record, os.path.join(archive, rel, runs.RECORD_FILE))
    if _keeps_config(rel):
      n += _copy_files(wd, os.path.join(archive, rel), replace=True)
  moved = _moved_paths(out, archive)
  for pattern in TOP_PATTERNS:
    for path in sorted(glob.glob(os.path.join(out, pattern))):
      rewrite = moved if path.endswith(".md") else None
      n += _copy_if_changed(path, os.path.join(archive, os.path.basename(path)), rewrite)
  return n


def _moved_paths(out: str, archive: str):
  """bytes -> bytes: a table of DIR's with the runs it names moved into the archive. DIR's path
  becomes the archive's, relative to the working directory where it lies below it (a launch run
  from the repository root with `--archive results/<size>`), so that the archived table is the
  one its reader makes from the archived records (`tests/test_tables.py` checks that)."""
  rel = os.path.relpath(archive)
  to = (os.path.abspath(archive) if rel.startswith("..") else rel) + os.sep
  src = (os.path.abspath(out) + os.sep).encode()
  return lambda data: data.replace(src, to.encode())


def _keeps_config(rel: str) -> bool:
  """Whether the run at `rel` keeps its `SYNTHESIS_FILES` in the archive (synthesis/<name>)."""
  return rel.split(os.sep, 1)[0] == "synthesis"


def _copy_files(src: str, dst: str, *, replace: bool) -> int:
  """Copies a view-synthesis run's `SYNTHESIS_FILES` that src holds into dst (where dst lacks
  them, or also where they differ with `replace`); returns how many it wrote."""
  n = 0
  for name in SYNTHESIS_FILES:
    path, to = os.path.join(src, name), os.path.join(dst, name)
    if not os.path.isfile(path) or (os.path.exists(to) and not replace):
      continue
    if name == restore_lib.POSE_FILE and os.path.getsize(path) > POSE_FILE_LIMIT:
      continue
    n += _copy_if_changed(path, to)
  return n


def _complete(workdir: str) -> bool:
  """A regression run with its results, or a view-synthesis run whose final record says it
  completed (one stopped or killed mid-way is not archived)."""
  try:
    run = runs.load(workdir)
  except (FileNotFoundError, runs.DamagedRun):
    return False
  return run.kind == "regression" or (run.final or {}).get("complete") is True


def restore(archive: str, out: str, *, warn=print) -> int:
  """Writes into `out` the record of every archived run that `out` does not hold finished (a
  view-synthesis run only where `out` has no workdir of that name: a partial run there resumes
  from its own checkpoints); returns how many runs it restored. An archived run that cannot be
  read is named (`warn`) and not restored: the launch trains it again. A synthesis/ run's
  `SYNTHESIS_FILES` are written where `out`'s workdir lacks them (never over a run's own). The
  archive's tables and figures replace `out`'s where they differ: they are the record, and
  `sync` would otherwise copy older ones of `out` over them."""
  for pattern in TOP_PATTERNS:
    for path in sorted(glob.glob(os.path.join(archive, pattern))):
      _copy_if_changed(path, os.path.join(out, os.path.basename(path)))
  n = 0
  for rel in run_dirs(archive):
    src, dst = os.path.join(archive, rel), os.path.join(out, rel)
    if not runs.is_finished(src):
      continue
    partial = rel.split(os.sep, 1)[0] in SYNTHESIS_ROOTS and os.path.exists(dst)
    if not runs.is_finished(dst) and not partial:
      try:
        record = runs.compact(runs.load(src, arrays=True))
      except runs.DamagedRun as e:
        warn(f"warning: the archived run {src} cannot be read ({e}); it is trained again")
        continue
      runs.write_record(record, os.path.join(dst, runs.RECORD_FILE))
      n += 1
    if _keeps_config(rel) and _archived_record(dst):  # restored now or by an earlier launch
      _copy_files(src, dst, replace=False)
  return n


def _archived_record(workdir: str) -> bool:
  """Whether a workdir holds a run's record and none of a run's own files (results.json,
  final_metrics.json): a run an archive restored."""
  return os.path.isfile(os.path.join(workdir, runs.RECORD_FILE)) and not any(
    os.path.exists(os.path.join(workdir, f)) for f in (runs.RESULTS_FILE, runs.FINAL_FILE)
  )


def set_aside(damaged: runs.DamagedRun) -> str:
  """Renames a damaged file to <name>.damaged (kept for a look, read by nothing); a damaged
  errors file takes its results.json with it, so the run counts as not finished. Returns the
  damaged file's new path."""
  moved = [damaged.path]
  name = os.path.basename(damaged.path)
  if name.startswith("errors_") and name.endswith(".npz"):
    moved.append(os.path.join(os.path.dirname(damaged.path), runs.RESULTS_FILE))
  for path in moved:
    if os.path.exists(path):
      shutil.move(path, path + ".damaged")
  return damaged.path + ".damaged"

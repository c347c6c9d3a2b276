"""Compacts a comparison archive (e.g. results/converge) to one record per run.

  python tools/compact_results.py results/converge [--dry_run]

An archive written before compact records held each finished run's files: config.json,
record.json, results.json or final_metrics.json, metrics.jsonl, errors_<split>.npz and
eval/noise.json. For every run directory of the archive (`camrep.comparison.archive.run_dirs`)
this writes the run's record run.json (`camrep.regression.runs.compact`: what the tables and
figures read), reads it back, checks that it gives the readers the same values as the files (the
results, every kept per-view array bit for bit, the eval curves, the final record and the noise
curve), and only then removes those files. A directory holding checkpoints (a live workdir, not
an archive) or a run that cannot be read is named and left as it is (exit 1). Prints the number
of files and their size before and after.
"""

from __future__ import annotations

import argparse
import glob
import os
import sys
from collections.abc import Sequence

import numpy as np

from camrep.comparison import archive
from camrep.regression import runs

# The files an archive kept per run (paths inside the run's directory).
RUN_FILES = (
  "config.json",
  "record.json",
  runs.RESULTS_FILE,
  runs.FINAL_FILE,
  runs.METRICS_FILE,
  runs.NOISE_FILE,
)
RUN_PATTERNS = ("errors_*.npz",)


def run_files(workdir: str) -> list[str]:
  """The archived files of a run directory (absolute paths)."""
  out = [os.path.join(workdir, f) for f in RUN_FILES if os.path.isfile(os.path.join(workdir, f))]
  for pattern in RUN_PATTERNS:
    out += sorted(glob.glob(os.path.join(workdir, pattern)))
  return out


def same(a: runs.Run, b: runs.Run) -> list[str]:
  """What a record `b` gives the readers differently from the files `a` ([] when nothing)."""
  diffs = []
  if a.kind != b.kind or a.config != b.config or a.curves != b.curves:
    diffs.append("kind, config or curves")
  if a.kind == "regression":
    ra = {k: v for k, v in a.results.items() if k != "validation"}
    rb = {k: v for k, v in b.results.items() if k != "validation"}
    if ra != rb or a.results["validation"].get("all") != b.results["validation"].get("all"):
      diffs.append("results")
    ea, eb = a.view_errors() or {}, b.view_errors() or {}
    for k in set(ea) - set(runs.compact(a).get("errors", {})) - {"pred"}:
      diffs.append(f"array {k} dropped")
    for k, v in eb.items():
      if k not in ea or v.dtype != ea[k].dtype or not np.array_equal(v, ea[k], equal_nan=True):
        diffs.append(f"array {k}")
  elif a.final != b.final or a.noise != b.noise:
    diffs.append("final or noise")
  return diffs


def _tree(root: str) -> tuple[int, int]:
  n = size = 0
  for d, _, files in os.walk(root):
    for f in files:
      n += 1
      size += os.path.getsize(os.path.join(d, f))
  return n, size


def compact_archive(root: str, *, dry_run: bool = False, log=print) -> int:
  """Compacts every run of the archive `root`; returns the number of runs left as they were."""
  left = 0
  for rel in archive.run_dirs(root):
    wd = os.path.join(root, rel)
    files = run_files(wd)
    if not files:
      continue  # already a record only
    if os.path.isdir(os.path.join(wd, "checkpoints")):
      log(f"left {wd}: it holds checkpoints (a workdir, not an archive)")
      left += 1
      continue
    try:
      before = runs.from_workdir(wd, arrays=True)
      record = runs.compact(before)
    except (FileNotFoundError, runs.DamagedRun) as e:
      log(f"left {wd}: {e}")
      left += 1
      continue
    if dry_run:
      log(f"would compact {wd}: {len(files)} files")
      continue
    path = os.path.join(wd, runs.RECORD_FILE)
    runs.write_record(record, path)
    diffs = same(before, runs.load(path))
    if diffs:
      os.remove(path)
      log(f"left {wd}: its record would differ ({', '.join(diffs)})")
      left += 1
      continue
    for f in files:
      os.remove(f)
    for d in (os.path.join(wd, "eval"),):
      if os.path.isdir(d) and not os.listdir(d):
        os.rmdir(d)
  return left


def main(argv: Sequence[str] | None = None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("archive", help="the archive's directory, e.g. results/converge")
  p.add_argument("--dry_run", action="store_true", help="say what would be compacted")
  args = p.parse_args(argv)
  if not os.path.isdir(args.archive):
    print(f"error: {args.archive} is not a directory", file=sys.stderr)
    return 2
  n0, s0 = _tree(args.archive)
  left = compact_archive(args.archive, dry_run=args.dry_run)
  n1, s1 = _tree(args.archive)
  mib = 2**20
  print(
    f"{args.archive}: {n0} files, {s0 / mib:.1f} MiB before; {n1} files, {s1 / mib:.1f} MiB after"
  )
  if left:
    print(f"{left} runs left as they were (named above)", file=sys.stderr)
  return 1 if left else 0


if __name__ == "__main__":
  sys.exit(main())

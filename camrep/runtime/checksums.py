"""The integrity manifest of a checkpoint step: `<step>/camrep_checksums.json`, the crc32c and
size of every file of the step, written once the step is complete on disk and checked before
the step is read (`checkpoint.Checkpointer` writes and checks it).

A file whose size or checksum differs (bit rot, a flipped byte that Orbax would read without
complaint), a missing file or an unreadable manifest raises `_ChecksumMismatch`, naming it; the
checkpointer then treats the step as unreadable. The class keeps its private name because it is
what the checkpointer's warnings print ("_ChecksumMismatch: checksum mismatch in FILE"). A step
without a manifest (written by an older camrep) is reported as unverified, not as bad.
"""

from __future__ import annotations

import json
import os

import crc32c

from camrep.runtime import writers

MANIFEST_NAME = "camrep_checksums.json"
_MANIFEST_VERSION = 1


class _ChecksumMismatch(ValueError):
  """A step's files differ from its checksum manifest."""


def _file_crc32c(path: str, chunk: int = 1 << 22) -> str:
  value = 0
  with open(path, "rb") as fh:
    while block := fh.read(chunk):
      value = crc32c.crc32c(block, value)
  return f"{value:08x}"


def _step_files(step_dir: str) -> list[str]:
  """Paths relative to `step_dir` of every file under it except the manifest (and its tmp)."""
  out = []
  for root, _, names in os.walk(step_dir):
    for name in names:
      if name.startswith(MANIFEST_NAME):
        continue
      out.append(os.path.relpath(os.path.join(root, name), step_dir))
  return sorted(out)


def write_manifest(step_dir: str) -> None:
  """Writes `step_dir/camrep_checksums.json` (crc32c and size per file), atomically."""
  files = {}
  for rel in _step_files(step_dir):
    path = os.path.join(step_dir, rel)
    files[rel] = {"size": os.path.getsize(path), "crc32c": _file_crc32c(path)}
  text = json.dumps({"version": _MANIFEST_VERSION, "files": files}, indent=1, sort_keys=True)
  writers.write_text_atomic(os.path.join(step_dir, MANIFEST_NAME), text)


def verify_manifest(step_dir: str) -> bool:
  """Checks the files of `step_dir` against its manifest.

  Returns:
    True if verified, False if the step has no manifest (written by an older camrep).

  Raises:
    _ChecksumMismatch: naming the first file that is missing or differs, or an unreadable
      manifest.
  """
  path = os.path.join(step_dir, MANIFEST_NAME)
  if not os.path.exists(path):
    return False
  try:
    with open(path) as fh:
      files = json.load(fh)["files"]
  except (OSError, ValueError, KeyError, TypeError) as e:
    raise _ChecksumMismatch(f"checksum manifest {MANIFEST_NAME} unreadable ({_short(e)})") from e
  for rel, want in sorted(files.items()):
    full = os.path.join(step_dir, rel)
    if not os.path.isfile(full):
      raise _ChecksumMismatch(f"checksum mismatch in {rel}: file missing")
    if os.path.getsize(full) != want["size"] or _file_crc32c(full) != want["crc32c"]:
      raise _ChecksumMismatch(f"checksum mismatch in {rel}")
  return True


def _short(exc: BaseException, limit: int = 300) -> str:
  """An error in one line for a message: "TypeName: text", whitespace collapsed, cut after
  `limit` characters (`checkpoint` words its errors with it too)."""
  text = " ".join(str(exc).split())
  if len(text) > limit:
    text = text[:limit] + "..."
  return f"{type(exc).__name__}: {text}"

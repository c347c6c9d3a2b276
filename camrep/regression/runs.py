"""Finished runs as the tables and figures read them: a run's workdir, or its compact record.

A workdir of `camrep.regression` holds config.json, metrics.jsonl, results.json and
errors_<test split>.npz (plus checkpoints and logs); a workdir of `camrep.main` holds config.json,
metrics.jsonl, final_metrics.json and eval/noise.json. Its compact record, `run.json`, keeps in one
file what the tables and figures read of it, and nothing else:

  kind       "regression" or "synthesis"
  config     the config fields a reader names a run by (`CONFIG_FIELDS`)
  results    regression: results.json, with only the "all" summary of the validation split (the
             learning rate is chosen on it); the test summaries whole (Table 2 reads its scenes)
  errors     regression: the arrays of errors_<test split>.npz but the predicted poses ("pred"),
             each {"dtype", "shape", "zlib": base64 of its zlib-compressed bytes}: exact values
  curves     every `eval/` metric of metrics.jsonl, {metric: [[step, value], ...]} (the last value
             logged at each step): the validation and held-out PSNR curves the figures draw
  final      synthesis: final_metrics.json (complete, step, the plateau rule's record)
  noise      synthesis: eval/noise.json, when the run was evaluated

`load(path)` reads either form; `damage(workdir)` says why a finished-looking run cannot be read
(a cut results.json, a damaged errors file), so that a launcher trains it again and a table refuses
it by name instead of failing on it or counting it.
"""

from __future__ import annotations

import base64
import dataclasses
import glob
import json
import os
import zipfile
import zlib
from collections.abc import Mapping
from typing import Any

import numpy as np

RECORD_FILE = "run.json"
RESULTS_FILE = "results.json"
FINAL_FILE = "final_metrics.json"
NOISE_FILE = os.path.join("eval", "noise.json")
CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"
FORMAT = 1

CONFIG_FIELDS = (
  "seed",
  "setting",
  "representation",
  "variant",
  "task",
  "total_steps",
  "synthesis_workdir",
  "optax.lr",
  "rep.kind",
  "model.kind",
  "model.width",
  "model.camera",
  "data.n_context",
  "data.source",
  "data.dir",
  "data.preset",
  "rep.freeze_generators",
)
"""The config fields a record keeps (dotted paths): what the readers label and group runs by."""

UNSET_FIELDS = {"rep.freeze_generators": False}
"""Fields of `CONFIG_FIELDS` a record leaves out at this value: the control they mark is named,
and the records of every other run stay as they were before the field was kept."""


def pose_input(config: Mapping[str, Any]) -> str | None:
  """The pose input a view-synthesis run's config (whole, or a record's fields) names: its
  rep.kind (grid, lowdim, mlp), "convdraw" for GQN's own generator (whose rep.kind is lowdim),
  "frozen_gen" for the grid with its generators frozen (the control); None without a rep.kind."""
  rep = config.get("rep")
  if config.get("model", {}).get("kind") == "convdraw":
    return "convdraw"
  if isinstance(rep, Mapping) and rep.get("freeze_generators"):
    return "frozen_gen"
  if isinstance(rep, Mapping) and rep.get("kind"):
    return rep["kind"]
  return None


# Per-view arrays no reader uses (the regressor's predicted poses).
_DROPPED_ARRAYS = ("pred",)


class DamagedRun(ValueError):
  """A finished-looking run whose files cannot be read; the message names the file.

  Attributes:
    path: the file that cannot be read.
  """

  def __init__(self, path: str, message: str):
    super().__init__(f"{path} {message}")
    self.path = path


@dataclasses.dataclass
class Run:
  """One finished run, from either form.

  Attributes:
    path: the run's workdir, or its run.json.
    kind: "regression" or "synthesis".
    config: `CONFIG_FIELDS` of its config.json (nested dicts).
    results: regression: results.json (None for synthesis).
    final: synthesis: final_metrics.json (None for regression).
    noise: synthesis: eval/noise.json, or None.
    curves: {metric: {step: value}} of its `eval/` metrics.
  """

  path: str
  kind: str
  config: dict[str, Any]
  results: dict[str, Any] | None
  final: dict[str, Any] | None
  noise: dict[str, Any] | None
  curves: dict[str, dict[int, float]]
  _errors: dict[str, np.ndarray] | None = None
  _errors_file: str = ""

  @property
  def workdir(self) -> str:
    """The run's directory (the folder of its run.json)."""
    return self.path if os.path.isdir(self.path) else os.path.dirname(self.path)

  def view_errors(self) -> dict[str, np.ndarray] | None:
    """The per-view arrays of its test split ({name: (N, ...)}), or None without them."""
    if self._errors is None and self._errors_file and os.path.isfile(self._errors_file):
      self._errors = read_errors(self._errors_file)
    return self._errors


def lr_tag(lr: float) -> str:
  """The lr part of a run directory's name: 1e-3 -> "lr1e-3", 3e-4 -> "lr3e-4"."""
  return f"lr{lr:.0e}".replace("e-0", "e-")


def run_name(lr: float, seed: int) -> str:
  """A regression run's directory name under DIR/regression/<column>/<representation> (the
  comparison's layout, and a grid's members: `camrep.regression.vectorised`): "lr1e-3_seed0"."""
  return f"{lr_tag(lr)}_seed{seed}"


def read_json(path: str) -> Any:
  """A JSON file.

  Raises:
    DamagedRun: it cannot be read (naming it).
  """
  try:
    with open(path, encoding="utf-8") as f:
      return json.load(f)
  except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
    raise DamagedRun(path, f"cannot be read as JSON ({e})") from e


def read_errors(path: str) -> dict[str, np.ndarray]:
  """The arrays of an errors_<split>.npz.

  Raises:
    DamagedRun: it cannot be read (a cut or corrupted file).
  """
  try:
    with np.load(path) as z:
      return {k: np.asarray(z[k]) for k in z.files}
  except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
    raise DamagedRun(path, f"cannot be read as per-view errors ({type(e).__name__}: {e})") from e


_ABSENT = object()


def _lookup(tree: Mapping[str, Any], name: str, default: Any = _ABSENT) -> Any:
  """The value of the dotted field `name` in a nested dict; `default` when it has none."""
  node = tree
  for p in name.split("."):
    if not isinstance(node, Mapping) or p not in node:
      return default
    node = node[p]
  return node


def _pick(tree: Mapping[str, Any], fields=CONFIG_FIELDS) -> dict[str, Any]:
  """The dotted `fields` of a nested dict that it has (but `UNSET_FIELDS` at their value),
  nested again."""
  out: dict[str, Any] = {}
  for name in fields:
    node = _lookup(tree, name)
    if node is _ABSENT or (name in UNSET_FIELDS and node == UNSET_FIELDS[name]):
      continue
    *parents, last = name.split(".")
    dst = out
    for p in parents:
      dst = dst.setdefault(p, {})
    dst[last] = node
  return out


def _curves(workdir: str) -> dict[str, dict[int, float]]:
  """{metric: {step: value}} of the `eval/` metrics in a workdir's metrics.jsonl."""
  from camrep.runtime import writers

  out: dict[str, dict[int, float]] = {}
  try:
    rows = writers.read_metrics(workdir)
  except (OSError, ValueError, UnicodeDecodeError) as e:
    raise DamagedRun(os.path.join(workdir, METRICS_FILE), f"cannot be read ({e})") from e
  for row in rows:
    for k, v in row.items():
      if k.startswith("eval/") and "step" in row:
        out.setdefault(k, {})[int(row["step"])] = float(v)
  return out


def errors_file(workdir: str, results: Mapping[str, Any]) -> str:
  """errors_<test split>.npz of a regression workdir."""
  split = results.get("data", {}).get("test_split", "test")
  return os.path.join(workdir, f"errors_{split}.npz")


def _kind(workdir: str) -> str | None:
  """ "regression" (results.json), "synthesis" (final_metrics.json) or None (neither)."""
  if os.path.isfile(os.path.join(workdir, RESULTS_FILE)):
    return "regression"
  if os.path.isfile(os.path.join(workdir, FINAL_FILE)):
    return "synthesis"
  return None


def from_workdir(workdir: str, *, arrays: bool = False) -> Run:
  """A finished run from its workdir's files (a run.json beside them is not read).

  Raises:
    FileNotFoundError: the workdir holds no finished run's files.
    DamagedRun: a file of it cannot be read (named in the message).
  """
  kind = _kind(workdir)
  if kind is None:
    raise FileNotFoundError(f"{workdir} holds no {RESULTS_FILE}, {FINAL_FILE} or {RECORD_FILE}")
  config_path = os.path.join(workdir, CONFIG_FILE)
  config = _pick(read_json(config_path)) if os.path.isfile(config_path) else {}
  results = final = noise = None
  errors, efile = None, ""
  if kind == "regression":
    results = read_json(os.path.join(workdir, RESULTS_FILE))
    if not isinstance(results, dict) or not {"setting", "representation"} <= set(results):
      raise DamagedRun(os.path.join(workdir, RESULTS_FILE), "is not a run's results")
    efile = errors_file(workdir, results)
    if arrays and os.path.isfile(efile):
      errors = read_errors(efile)
  else:
    final = read_json(os.path.join(workdir, FINAL_FILE))
    if not isinstance(final, dict):
      raise DamagedRun(os.path.join(workdir, FINAL_FILE), "is not a run's final record")
    if os.path.isfile(os.path.join(workdir, NOISE_FILE)):
      noise = read_json(os.path.join(workdir, NOISE_FILE))
  return Run(workdir, kind, config, results, final, noise, _curves(workdir), errors, efile)


def _encode(a: np.ndarray) -> dict[str, Any]:
  a = np.ascontiguousarray(a)
  data = base64.b64encode(zlib.compress(a.astype(a.dtype.newbyteorder("<")).tobytes(), 9))
  return {"dtype": a.dtype.str.lstrip("<>|="), "shape": list(a.shape), "zlib": data.decode()}


def _decode(x: Mapping[str, Any], path: str) -> np.ndarray:
  try:
    raw = zlib.decompress(base64.b64decode(x["zlib"], validate=True))
    return np.frombuffer(raw, np.dtype("<" + x["dtype"])).reshape(x["shape"]).copy()
  except (KeyError, TypeError, ValueError, zlib.error) as e:
    raise DamagedRun(path, f"has an array that cannot be decoded ({type(e).__name__}: {e})") from e


def _from_record(path: str) -> Run:
  r = read_json(path)
  if (
    not isinstance(r, dict)
    or r.get("format") != FORMAT
    or r.get("kind")
    not in (
      "regression",
      "synthesis",
    )
  ):
    raise DamagedRun(path, f"is not a run record (format {FORMAT})")
  curves = {m: {int(s): float(v) for s, v in pts} for m, pts in (r.get("curves") or {}).items()}
  errors = None
  if r.get("errors") is not None:
    errors = {k: _decode(v, path) for k, v in r["errors"].items()}
  return Run(
    path,
    r["kind"],
    r.get("config") or {},
    r.get("results"),
    r.get("final"),
    r.get("noise"),
    curves,
    errors,
  )


def load(path: str, *, arrays: bool = False) -> Run:
  """A finished run from its workdir, its run.json, or a workdir holding a run.json.

  Args:
    path: a workdir, a run.json, or a results.json (stands for its workdir).
    arrays: read a workdir's per-view errors now (they are read on first use otherwise; a
      record's always are).

  Raises:
    FileNotFoundError: `path` holds no finished run.
    DamagedRun: it does, but a file of it cannot be read (named in the message).
  """
  if os.path.basename(path) == RESULTS_FILE:
    path = os.path.dirname(path)
  if os.path.isdir(path) and os.path.isfile(os.path.join(path, RECORD_FILE)):
    path = os.path.join(path, RECORD_FILE)
  if os.path.isfile(path):
    return _from_record(path)
  return from_workdir(path, arrays=arrays)


RESTORED_FIELDS = ("setting", "representation", "optax.lr", "seed")
"""The fields a restored run must share with the run a command would train there (`restored`)."""


def restored(workdir: str, config: Mapping[str, Any]) -> Run | None:
  """The finished run an archive restored into `workdir` (its run.json, and none of a run's own
  results.json or final_metrics.json: `camrep.comparison.archive.restore`), checked to be the
  run `config` (a config's nested dict) names; None when the workdir holds no such record.

  Raises:
    ValueError: the record is another run's (`RESTORED_FIELDS` differ; named in the message).
    DamagedRun: the record cannot be read.
  """
  if not os.path.isfile(os.path.join(workdir, RECORD_FILE)) or _kind(workdir) is not None:
    return None
  run = _from_record(os.path.join(workdir, RECORD_FILE))
  for name in RESTORED_FIELDS:
    a, b = _lookup(run.config, name, None), _lookup(config, name, None)
    if a != b:
      raise ValueError(
        f"{workdir} holds a finished run restored from an archive ({RECORD_FILE}) with {name}="
        f"{a!r}, not {b!r}: move it away or use another --workdir"
      )
  return run


def is_finished(workdir: str) -> bool:
  """Whether `workdir` holds a finished run in either form (readable or not)."""
  return os.path.isfile(os.path.join(workdir, RECORD_FILE)) or _kind(workdir) is not None


def damage(workdir: str) -> DamagedRun | None:
  """Why a finished-looking run in `workdir` cannot be read (None when it can, or holds none)."""
  if not is_finished(workdir):
    return None
  try:
    load(workdir, arrays=True)
  except DamagedRun as e:
    return e
  return None


def compact(run: Run) -> dict[str, Any]:
  """The run.json content of a run (see the module docstring)."""
  out: dict[str, Any] = {"format": FORMAT, "kind": run.kind, "config": run.config}
  if run.kind == "regression":
    results = dict(run.results or {})
    results.pop("_path", None)
    if isinstance(results.get("validation"), dict) and "all" in results["validation"]:
      results["validation"] = {"all": results["validation"]["all"]}
    out["results"] = results
    errors = run.view_errors()
    if errors is not None:
      out["errors"] = {k: _encode(v) for k, v in errors.items() if k not in _DROPPED_ARRAYS}
  else:
    out["final"] = run.final
    if run.noise is not None:
      out["noise"] = run.noise
  out["curves"] = {m: [[s, v] for s, v in sorted(c.items())] for m, c in sorted(run.curves.items())}
  return out


def write_record(record: Mapping[str, Any], path: str) -> bool:
  """Writes a record to `path` (a temporary file, then a rename) unless the file already holds
  these bytes; returns whether it wrote."""
  data = (json.dumps(record, sort_keys=True, separators=(",", ":")) + "\n").encode()
  if os.path.isfile(path):
    with open(path, "rb") as f:
      if f.read() == data:
        return False
  os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
  tmp = f"{path}.tmp{os.getpid()}"
  with open(tmp, "wb") as f:
    f.write(data)
  os.replace(tmp, path)
  return True


def expand(patterns) -> list[str]:
  """The run directories and run.json / results.json files that glob `patterns` match (a
  results.json or run.json stands for its directory), sorted, each once."""
  dirs = set()
  for pattern in patterns:
    for p in glob.glob(pattern):
      if os.path.basename(p) in (RESULTS_FILE, RECORD_FILE) and os.path.isfile(p):
        p = os.path.dirname(p)
      if os.path.isdir(p):
        dirs.add(os.path.abspath(p))
  return sorted(dirs)

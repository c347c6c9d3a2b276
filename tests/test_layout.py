"""The package's layout: layers import only downwards, modules say what they hold, no twin names.

Layers, lowest first (a module may import its own layer and those below):

  0  camrep.lie, .spectral, .metrics,         Lie operators and their exact exponential, image
     .rotations                                metrics, rotations of 3-space
  1  camrep.dofs, camrep.pose                  the pose system's DOFs and the system
  2  camrep.settings                           the paper's settings (poses, errors, splits)
  3  camrep.data, camrep.runtime,              data; checkpoints, writers, plots; experiment
     camrep.configs                            configs; camrep.data in sub-layers, lowest first:
     3.0 camrep.data (errors, records,         the data error, the record format, the source
         sources)                              registry (which names its modules as strings)
     3.1 camrep.data.readers                   readers of real datasets and their file helpers
     3.2 camrep.data.procedural                the procedural families and their renderer
     3.3 camrep.data.feed                      storage, the data fingerprint, the batch pipeline
     3.4 camrep.data.prepare, .show, .oracle   the data commands
  4  camrep.pose_encodings                     every pose encoding of both stages
  5  camrep.models                             Flax modules
  6  camrep.synthesis                          view-synthesis training and evaluation
  7  camrep.regression                         pose regression and its tables
  8  camrep.main, camrep.comparison,           the entry points: training, the comparison
     camrep.bench                              launcher, the benchmarks and the GPU report
"""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "camrep"

LAYERS = {
  "camrep.lie": 0,
  "camrep.metrics": 0,
  "camrep.rotations": 0,
  "camrep.spectral": 0,
  "camrep.dofs": 1,
  "camrep.pose": 1,
  "camrep.settings": 2,
  "camrep.data": 3,
  "camrep.data.readers": 3.1,
  "camrep.data.procedural": 3.2,
  "camrep.data.feed": 3.3,
  "camrep.data.prepare": 3.4,
  "camrep.data.show": 3.4,
  "camrep.data.oracle": 3.4,
  "camrep.runtime": 3,
  "camrep.configs": 3,
  "camrep.pose_encodings": 4,
  "camrep.models": 5,
  "camrep.synthesis": 6,
  "camrep.regression": 7,
  "camrep.main": 8,
  "camrep.comparison": 8,
  "camrep.bench": 8,
}
# Near-twins that name a real pair, not a muddle.
NOT_TWINS = {frozenset({"decoder", "encoder"})}


def _module_name(path: pathlib.Path) -> str:
  parts = path.relative_to(ROOT).with_suffix("").parts
  return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _layer(module: str) -> float:
  if module == "camrep":  # the package's own __init__: a docstring
    return 0
  for prefix in sorted(LAYERS, key=len, reverse=True):
    if module == prefix or module.startswith(prefix + "."):
      return LAYERS[prefix]
  raise KeyError(f"{module} is in no layer: add it to LAYERS in tests/test_layout.py")


def _imports(path: pathlib.Path) -> list[tuple[int, str]]:
  """Every camrep module the file imports, at any depth (function-level imports included)."""
  out = []
  for node in ast.walk(ast.parse(path.read_text())):
    if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
      if node.module.startswith("camrep"):
        for a in node.names:  # `from camrep.x import y`: y may be a module or a name in x
          sub = f"{node.module}.{a.name}"
          try:
            _layer(sub)
            out.append((node.lineno, sub))
          except KeyError:
            out.append((node.lineno, node.module))
    elif isinstance(node, ast.Import):
      out += [(node.lineno, a.name) for a in node.names if a.name.startswith("camrep")]
  return out


MODULES = sorted(PACKAGE.rglob("*.py"))


def test_every_module_is_in_a_layer():
  for path in MODULES:
    _layer(_module_name(path))


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_run_downwards(path):
  me = _module_name(path)
  for line, target in _imports(path):
    if target == "camrep":
      continue
    assert _layer(target) <= _layer(me), (
      f"{path.relative_to(ROOT)}:{line} imports {target} (layer {_layer(target)}) from layer "
      f"{_layer(me)}: move the shared code down, or the importer up"
    )


def test_the_layer_check_sees_function_level_imports(tmp_path):
  src = tmp_path / "m.py"
  src.write_text("def f():\n  from camrep.synthesis import train\n  import camrep.lie\n")
  found = [t for _, t in _imports(src)]
  assert found == ["camrep.synthesis.train", "camrep.lie"]
  assert _layer(found[0]) > _layer("camrep.pose")  # what test_imports_run_downwards refuses


def test_data_sub_layers_order_readers_procedural_feed_commands():
  """A reader never needs the procedural machinery or the pipeline, the pipeline never a
  command: the data package's sub-layers refuse such imports as the package's layers do."""
  order = [
    "camrep.data.sources",
    "camrep.data.readers.captures.collection",
    "camrep.data.procedural.families",
    "camrep.data.feed.pipeline",
    "camrep.data.prepare",
  ]
  layers = [_layer(m) for m in order]
  assert layers == sorted(layers) and len(set(layers)) == len(layers), layers
  assert _layer("camrep.data.feed.storage") > _layer("camrep.runtime.writers")


def test_the_package_and_configs_import_neither_experiments_nor_tools():
  """experiments/ (the readers) and tools/ sit on top of camrep: the package never needs them."""
  for path in [*MODULES, *(ROOT / "configs").rglob("*.py")]:
    for node in ast.walk(ast.parse(path.read_text())):
      names = []
      if isinstance(node, ast.ImportFrom) and node.module:
        names = [node.module]
      elif isinstance(node, ast.Import):
        names = [a.name for a in node.names]
      for top in ("experiments", "tools"):
        assert not any(n == top or n.startswith(top + ".") for n in names), path


def test_nothing_edits_sys_path_or_loads_a_module_by_its_file():
  """Modules are imported by name (camrep is installed; experiments and tools are packages of
  the checkout): no `sys.path` edit and no loading from a file path anywhere in the tree."""
  banned = ("sys.path.insert", "sys.path.append", "spec_from_file_location", "load_module(")
  dirs = ("camrep", "configs", "experiments", "tools", "tests")
  for path in sorted(p for d in dirs for p in (ROOT / d).rglob("*.py")):
    if path == pathlib.Path(__file__):  # names them
      continue
    found = [b for b in banned if b in path.read_text()]
    assert not found, f"{path.relative_to(ROOT)}: {found}"


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_module_says_what_it_holds(path):
  doc = ast.get_docstring(ast.parse(path.read_text()))
  assert doc and len(doc.splitlines()[0]) > 20, f"{path.relative_to(ROOT)}: no module docstring"


def _distance(a: str, b: str) -> int:
  prev = list(range(len(b) + 1))
  for i, ca in enumerate(a, 1):
    cur = [i]
    for j, cb in enumerate(b, 1):
      cur.append(min(prev[j] + 1, cur[j - 1] + 1, prev[j - 1] + (ca != cb)))
    prev = cur
  return prev[-1]


def twins(names) -> list[tuple[str, str]]:
  """Pairs of module names a reader would confuse: one a prefix of the other without a word
  boundary (regress / regression), or a small edit apart (writer / writers, decoder / encoder)."""
  names = sorted(set(names))
  out = []
  for i, a in enumerate(names):
    for b in names[i + 1 :]:
      short, long = sorted((a, b), key=len)
      prefix = long.startswith(short) and not long[len(short) :].startswith("_")
      close = _distance(a, b) <= (2 if min(len(a), len(b)) >= 7 else 1)
      if (prefix or close) and frozenset({a, b}) not in NOT_TWINS:
        out.append((a, b))
  return out


def test_no_module_names_are_twins():
  names = [p.stem for p in MODULES if not p.stem.startswith("__")]
  names += [p.parent.name for p in PACKAGE.rglob("__init__.py") if p.parent != PACKAGE]
  assert twins(names) == []


def test_the_twin_check_catches_the_old_names():
  assert ("regress", "regression") in twins(["regress", "regression", "targets"])
  assert twins(["pose", "pose_encodings"]) == []


def _setting_name_comparisons(path: pathlib.Path, names: set[str]) -> list[str]:
  """`x == "gqn"`, `x != "car"`, `x in ("gqn", "gibson")`: comparisons with a setting's name."""

  def constants(node):
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
      return {node.value}
    if isinstance(node, ast.Tuple | ast.List | ast.Set):
      return {e.value for e in node.elts if isinstance(e, ast.Constant)}
    return set()

  out = []
  for node in ast.walk(ast.parse(path.read_text())):
    if isinstance(node, ast.Compare):
      found = set().union(*(constants(n) for n in (node.left, *node.comparators)))
      if found & names:
        out.append(f"{path.name}:{node.lineno}: {ast.unparse(node)}")
  return out


def test_setting_names_are_compared_in_the_registry_only():
  """Code takes a `camrep.settings.Setting`, never compares its name: the names appear in the
  registry (camrep/settings.py) and where a config or record names one (looked up there)."""
  from camrep import settings

  names = set(settings.names())
  hits = [
    h for p in MODULES if p.name != "settings.py" for h in _setting_name_comparisons(p, names)
  ]
  assert hits == []


def test_the_comparison_check_sees_every_form(tmp_path):
  src = tmp_path / "m.py"
  src.write_text('a == "gqn"\nb in ("car", "x")\n"gibson" != c\nd == "table"\n')
  assert len(_setting_name_comparisons(src, {"gqn", "car", "gibson"})) == 3

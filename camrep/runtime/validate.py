"""Config fields declared once, and one validation pass over a config before anything runs.

A stage (view synthesis, regression) declares its config as a schema, {field path: `Field`}: each
field once, with its rule (what values it takes), when the run uses it (`ignored`), and whether it
may change when a run resumes in the same workdir (`resume`: FIXED, MAY_CHANGE or FREE). The
fields every training loop reads (durations, cadences, the stopping rule) are declared once by the
run frame (`camrep.runtime.frame.FIELDS`) and merged into each stage's schema. Everything else is
derived from the declarations: this module's checks, the resume rules of
`runconfig.check_changes`, the retired fields a stored config may still hold (`retired`), and the
names `allow_changes` accepts (`check_allow_changes`).

`check(config, schema, overridden=...)` raises one `ConfigError` naming the field, the value and
what is allowed, for the first field that breaks its rule:

  * a value outside its rule (a non-positive size, an unknown enum name, a fraction outside
    (0, 1), a path that does not exist);
  * a field the chosen task, model or data does not use but the user set on the command line
    (`overridden`, e.g. `--config.model.image_size=100000` on the GQN task, whose model renders
    64 px images). Refused rather than warned about: a flag that silently does nothing is a
    user's mistake, and a run recorded with a value it never used is a false record. A config
    file may still carry such fields (its defaults); only command-line overrides are refused.

Types are checked by ml_collections when a flag is parsed (`--config.total_steps=abc`) and by
the ConfigDict on assignment; `check` checks the values. A field missing from the schema is
accepted (a workdir's config.json written by an older camrep); `unchecked` lists them, and the
tests require it to be empty for the shipped configs.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

from camrep.runtime.runconfig import ConfigError, as_plain, flatten

# A predicate on the whole config: None when the field is used, else why it is not.
Ignored = Callable[[Any], "str | None"]

# Whether a field may differ between a workdir's stored config and the config that resumes it:
# FIXED never (it changes the model, the pose system or the data: what the checkpoints mean; a
# stage that starts over instead, like regression, may start over when the change is named in
# `allow_changes`); MAY_CHANGE when named in `allow_changes` (durations, cadences, learning
# rates, loss weights), recorded in config_history.jsonl with its step; FREE always, recorded
# (speed or where output goes only).
FIXED, MAY_CHANGE, FREE = "fixed", "may_change", "free"
RESUME_POLICIES = (FIXED, MAY_CHANGE, FREE)
# The largest step count a run may take: the train state counts steps in int32.
MAX_STEPS = 2**31 - 1


@dataclasses.dataclass(frozen=True)
class Rule:
  """What values a field takes.

  Attributes:
    kind: "positive" (> 0), "nonneg" (>= 0), "at_least" (>= low), "count" (an integer from low
      to `MAX_STEPS`: a number of steps), "fraction" (strictly between
      0 and 1), "number_tuple" (a non-empty tuple of finite numbers), "enum" (one of
      `choices`), "dir" / "file" (an existing path, "" allowed when
      `optional`), "positive_tuple" (a non-empty tuple of positive ints), "any" (no constraint
      beyond the type), "section" (a mapping checked elsewhere, e.g. a family's overrides).
    low: for "at_least" and "count".
    choices: for "enum".
    optional: None (a placeholder left unset) or "" (paths) is allowed.
  """

  kind: str
  low: float = 0
  choices: tuple[Any, ...] = ()
  optional: bool = False

  def problem(self, value: Any) -> str | None:
    """None when `value` is allowed, else what is allowed."""
    if self.optional and (value is None or value == ""):
      return None
    if self.kind in ("any", "section"):
      return None
    if self.kind == "enum":
      return None if value in self.choices else f"one of {list(self.choices)}"
    if self.kind in ("dir", "file"):
      ok = isinstance(value, str) and (os.path.isdir if self.kind == "dir" else os.path.isfile)(
        value
      )
      return None if ok else f"an existing {'directory' if self.kind == 'dir' else 'file'}"
    if self.kind == "positive_tuple":
      ok = (
        isinstance(value, (tuple, list))
        and len(value) > 0
        and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
      )
      return None if ok else "a non-empty tuple of positive integers"
    if self.kind == "number_tuple":
      ok = (
        isinstance(value, (tuple, list))
        and len(value) > 0
        and all(
          isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
          for v in value
        )
      )
      return None if ok else "a non-empty tuple of finite numbers"
    if self.kind == "count":
      ok = isinstance(value, int) and not isinstance(value, bool) and self.low <= value <= MAX_STEPS
      return None if ok else f"an integer from {self.low:g} to {MAX_STEPS} (2**31 - 1)"
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
      return "a finite number"
    if self.kind == "positive":
      return None if value > 0 else "a number > 0"
    if self.kind == "nonneg":
      return None if value >= 0 else "a number >= 0"
    if self.kind == "at_least":
      return None if value >= self.low else f"a number >= {self.low:g}"
    if self.kind == "fraction":
      return None if 0 < value < 1 else "a number strictly between 0 and 1"
    raise ValueError(f"unknown rule kind {self.kind!r}")

  def bad_values(self) -> list[Any]:
    """Values this rule refuses (for tests: the sweep over a config's fields)."""
    return {
      "positive": [0, -1],
      "nonneg": [-1],
      "at_least": [int(self.low) - 1 if float(self.low).is_integer() else self.low - 1],
      "fraction": [0, 1.5],
      "enum": ["no-such-choice"],
      "dir": ["/nonexistent/camrep-validate"],
      "file": ["/nonexistent/camrep-validate.npz"],
      "positive_tuple": [(0,)],
      "number_tuple": [("abc",)],
      "count": [int(self.low) - 1, MAX_STEPS + 1],
    }.get(self.kind, [])


POSITIVE = Rule("positive")
NUMBERS = Rule("number_tuple")
NONNEG = Rule("nonneg")
ANY = Rule("any")
SECTION = Rule("section")


def at_least(low: float) -> Rule:
  return Rule("at_least", low=low)


def count(low: int = 0) -> Rule:
  """A number of steps: an integer from `low` to `MAX_STEPS`."""
  return Rule("count", low=low)


class _Registered:
  """The names of a registry as they are when a config is checked (a source or setting may be
  registered after the schema was built)."""

  def __init__(self, names: Callable[[], Iterable[Any]]):
    self._names = names

  def __contains__(self, value: Any) -> bool:
    return value in tuple(self._names())

  def __iter__(self):
    return iter(tuple(self._names()))


def one_of(choices: Iterable[Any] | Callable[[], Iterable[Any]]) -> Rule:
  """An "enum" rule: `choices`, or a function returning the registered names at check time."""
  if callable(choices):
    return Rule("enum", choices=_Registered(choices))
  return Rule("enum", choices=tuple(choices))


def optional(rule: Rule) -> Rule:
  return dataclasses.replace(rule, optional=True)


class _NotRetired:
  def __repr__(self) -> str:
    return "NOT_RETIRED"


NOT_RETIRED = _NotRetired()


@dataclasses.dataclass(frozen=True)
class Field:
  """One config field's declaration.

  Attributes:
    rule: the values it takes.
    ignored: when the run does not use it (`ignored(config)` -> why, or None when it is used).
    resume: whether it may change when a run resumes (FIXED, MAY_CHANGE or FREE; see above).
    retired: for a field that the base config no longer holds (only the configs whose code reads
      it set it), the value every config held before it moved: a stored config.json that still
      has it resumes with a config that lacks it, the difference recorded (`runconfig`).
  """

  rule: Rule
  ignored: Ignored | None = None
  resume: str = FIXED
  retired: Any = NOT_RETIRED

  def __post_init__(self):
    if self.resume not in RESUME_POLICIES:
      raise ValueError(f"resume must be one of {RESUME_POLICIES}, got {self.resume!r}")


Schema = Mapping[str, Field]


def field_of(schema: Schema, path: str) -> Field | None:
  """The field's entry; a name ending in "." covers every field under it."""
  if path in schema:
    return schema[path]
  for name, f in schema.items():
    if name.endswith(".") and (path.startswith(name) or path == name[:-1]):
      return f
  return None


def leaves(config: Any) -> dict[str, Any]:
  """{"a.b": value} for every leaf of the config (empty sections are leaves)."""
  return flatten(as_plain(config))


def unchecked(config: Any, schema: Schema) -> list[str]:
  """The config's fields that the schema has no rule for."""
  return [p for p in leaves(config) if field_of(schema, p) is None]


def _flag(path: str, value: Any) -> str:
  return f"--config.{path}={value!r}" if isinstance(value, str) else f"--config.{path}={value}"


def check(config: Any, schema: Schema, *, overridden: Iterable[str] = ()) -> None:
  """Checks every field of `config` against `schema`.

  Args:
    config: a ConfigDict (or mapping).
    schema: {path: Field}; a path ending in "." covers a section.
    overridden: the fields the user set on the command line (`cli.overridden()`); those the run
      does not use are refused.

  Raises:
    ConfigError: an overridden field the run ignores ("--config.PATH=VALUE: this run does not
      use ..."), else the first field that breaks its rule ("--config.PATH=VALUE: must be ...").
  """
  values = leaves(config)
  for path in sorted(set(overridden)):
    f = field_of(schema, path)
    if f is None or f.ignored is None:
      continue
    why = f.ignored(config)
    if why:
      value = values.get(path, _get(config, path))
      raise ConfigError(
        f"{_flag(path, value)}: this run does not use config.{path} ({why}); drop the flag"
      )
  for path, value in values.items():
    f = field_of(schema, path)
    if f is None:
      continue
    problem = f.rule.problem(value)
    if problem is not None:
      raise ConfigError(f"{_flag(path, value)}: must be {problem}")


def _get(config: Any, path: str) -> Any:
  node = config
  for part in path.split("."):
    try:
      node = node[part]
    except (KeyError, TypeError):
      return None
  return node


def unless(condition: Callable[[Any], bool], why: str) -> Ignored:
  """An `ignored` predicate: the field is unused (for reason `why`) unless `condition(config)`."""
  return lambda c: None if condition(c) else why


def resume_policy(schema: Schema, path: str) -> str:
  """FIXED, MAY_CHANGE or FREE for a field (FIXED for a field the schema does not declare)."""
  f = field_of(schema, path)
  return FIXED if f is None else f.resume


def with_resume(schema: Schema, resume: str, paths: Iterable[str]) -> dict[str, Field]:
  """`schema` with the fields `paths` given another resume policy."""
  out = dict(schema)
  for p in paths:
    out[p] = dataclasses.replace(out[p], resume=resume)
  return out


def retired(schema: Schema) -> dict[str, Any]:
  """{field: the value every config held} of the schema's retired fields."""
  return {p: f.retired for p, f in schema.items() if f.retired is not NOT_RETIRED}


def may_change(schema: Schema) -> list[str]:
  """The fields that may change on resume when named in `allow_changes` (for messages, tests)."""
  return [p for p, f in schema.items() if f.resume == MAY_CHANGE]


def check_allow_changes(config: Any, schema: Schema, *, extra: Iterable[str] = ()) -> None:
  """Refuses an `allow_changes` that names no field of the config (nor a section of it, nor one
  of `extra`, e.g. "global_batch").

  Raises:
    ConfigError: naming the unknown name.
  """
  from camrep.runtime.runconfig import parse_allow_changes

  fields = set(leaves(config))
  for name in parse_allow_changes(_get(config, "allow_changes") or ""):
    if name in extra:
      continue
    if name not in fields and not any(f.startswith(name + ".") for f in fields):
      allowed = ", ".join(n.rstrip(".") for n in may_change(schema))
      raise ConfigError(
        f"--config.allow_changes={_get(config, 'allow_changes')!r}: {name!r} is not a config "
        f"field (fields that may change on resume: {allowed}; or a section name"
        + (f", or {', '.join(extra)})" if extra else ")")
      )


def fields_with(schema: Schema, kinds: Sequence[str]) -> list[str]:
  """Schema paths whose rule kind is one of `kinds` (for tests)."""
  return [p for p, f in schema.items() if f.rule.kind in kinds]

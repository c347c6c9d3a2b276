"""The config of a run as a whole: the one error a bad config raises, whatever the stage (view
synthesis or regression), and what may change when a run resumes in the same workdir.

A workdir's config.json must describe every step in it. Resuming with another config is refused
unless every differing field is one a run may change midway (declared `MAY_CHANGE` in the stage's
schema, `camrep.runtime.validate`: durations, cadences, learning rates, loss weights; never the
model, the pose system or the data) and is named in `config.allow_changes` ("total_steps,
optax.lr_model", or a section: "evals"); allowed changes are recorded in the workdir's
config_history.jsonl with the step they took effect at. A stage that starts over instead of
resuming a changed run (regression) may also change its FIXED fields when they are named: the
run then starts again from step 0 (`fixed_changes`). Nothing here names a field: the rules come
from the stage's declarations.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from typing import Any


class ConfigError(ValueError):
  """A config whose parts do not fit together or name something unknown (raised before any data
  or model is built)."""


def as_plain(config: Any) -> dict[str, Any]:
  """A ConfigDict (or mapping) as plain JSON values: what config.json holds."""
  if hasattr(config, "to_json_best_effort"):
    return json.loads(config.to_json_best_effort())
  return json.loads(json.dumps(dict(config), default=str))


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
  """{"a": {"b": 1}} -> {"a.b": 1}."""
  out = {}
  for k, v in tree.items():
    if isinstance(v, Mapping) and v:
      out.update(flatten(v, f"{prefix}{k}."))
    else:
      out[f"{prefix}{k}"] = v
  return out


def differences(old: Mapping[str, Any], new: Mapping[str, Any]) -> dict[str, tuple[Any, Any]]:
  """{field: (old value, new value)} over the flattened configs; a missing side is None."""
  a, b = flatten(as_plain(old)), flatten(as_plain(new))
  return {k: (a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)}


def _covered(field: str, names: Iterable[str]) -> bool:
  return any(field == n or (n.endswith(".") and field.startswith(n)) for n in names)


def parse_allow_changes(value: str) -> tuple[str, ...]:
  """ "total_steps, optax.lr_model,evals" -> ("total_steps", "optax.lr_model", "evals")."""
  return tuple(n.strip() for n in (value or "").split(",") if n.strip())


def _judged(old, new, schema) -> tuple[dict, list[tuple[str, str]]]:
  """(every difference, [(field, policy)] of those the resume rules judge: not free, not gained
  since the workdir was written, not retired)."""
  from camrep.runtime import validate as V

  diffs = differences(old, new)
  old_fields = flatten(as_plain(old))
  new_fields = flatten(as_plain(new))
  diffs.pop("allow_changes", None)  # the permission itself is not a change of the run
  retired = V.retired(schema)
  judged = []
  for field in diffs:
    policy = V.resume_policy(schema, field)
    if policy == V.FREE:
      continue
    if field not in old_fields:
      # A field camrep gained after the workdir was written: its default keeps the old
      # behaviour, so it is recorded, not refused (setting it on resume is still recorded).
      continue
    if field in retired and field not in new_fields:
      continue  # moved out of the base config; this run never reads it: recorded
    judged.append((field, policy))
  return diffs, judged


def fixed_changes(old: Mapping[str, Any], new: Any, *, schema: Mapping) -> list[str]:
  """The FIXED fields (model, pose system, data) that differ between the stored and requested
  configs: a stage that starts over on such a change (`check_changes(restart=True)`) does."""
  from camrep.runtime import validate as V

  return [f for f, policy in _judged(old, new, schema)[1] if policy == V.FIXED]


def check_changes(
  old: Mapping[str, Any],
  new: Any,
  *,
  schema: Mapping,
  workdir: str,
  what: str = "resume",
  restart: bool = False,
) -> dict[str, tuple[Any, Any]]:
  """The differences between a workdir's stored config and the requested one, if allowed.

  Args:
    old: the stored config (config.json).
    new: the requested config; its `allow_changes` ("" when absent) names what may differ.
    schema: the stage's declarations ({path: `validate.Field`}): each field's resume policy
      and the retired fields.
    workdir: for the message.
    what: the verb of the message ("resume", "rerun").
    restart: the stage starts over on a FIXED change named in `allow_changes` (regression);
      without it such a change is refused.

  Returns:
    {field: (old, new)} of every difference (allowed and free ones, fields the stored config
    lacks, and retired fields the requested config lacks: (stored value, None)).

  Raises:
    ConfigError: some field differs that is not free and not allowed; the message names each
      (old -> new) and the ways out.
  """
  from camrep.runtime import validate as V

  diffs, judged = _judged(old, new, schema)
  allowed = parse_allow_changes(as_plain(new).get("allow_changes", ""))
  sections = tuple(a + "." for a in allowed)  # a section name allows its fields
  refused, need_flag = [], []
  for field, policy in judged:
    a, b = diffs[field]
    if policy == V.FIXED and not restart:
      refused.append(f"  {field}: {a!r} -> {b!r}")
    elif not (_covered(field, allowed) or _covered(field, sections)):
      need_flag.append(field)
  if not refused and not need_flag:
    return diffs
  lines = [f"cannot {what} in {workdir}: its config.json differs from the requested config"]
  if refused:
    shown = (
      refused if len(refused) <= 12 else [*refused[:12], f"  ... and {len(refused) - 12} more"]
    )
    lines += ["fields that change the model, pose system or data (never allowed):", *shown]
    lines.append("use a new --workdir for this config")
  if need_flag:
    lines += ["fields that may change but were not named in allow_changes:"]
    lines += [f"  {f}: {diffs[f][0]!r} -> {diffs[f][1]!r}" for f in need_flag]
    if not refused:
      starts_over = restart and any(V.resume_policy(schema, f) == V.FIXED for f in need_flag)
      lines.append(
        f"use a new --workdir, or add --config.allow_changes={','.join(need_flag)} to record "
        "the change in config_history.jsonl"
        + (" (the run then starts over from step 0)" if starts_over else "")
      )
  raise ConfigError("\n".join(lines))

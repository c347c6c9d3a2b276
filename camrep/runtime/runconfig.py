"""The config of a run as a whole: the one error a bad config raises, whatever the stage (view
synthesis or regression), and what may change when a run resumes in the same workdir.

A workdir's config.json must describe every step in it. Resuming with another config is refused
unless every differing field is one a run may change midway (`RESUMABLE` of the stage: durations,
cadences, learning rates, loss weights; never the model, the pose system or the data) and is named
in `config.allow_changes` ("total_steps,optax.lr_model", or a section: "evals"); allowed changes
are recorded in the workdir's config_history.jsonl with the step they took effect at.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from typing import Any

# Fields that change how a run goes on, never what its parameters mean or their shapes.
# A name ending in "." covers its whole section.
SYNTHESIS_RESUMABLE = (
  "total_steps",
  "log_every_steps",
  "eval_every_steps",
  "ckpt_every_steps",
  "max_to_keep",
  "seed",
  "evals.",
  "optax.lr_model",
  "optax.lr_rep",
  "loss.rec_weight",
  "loss.rot_weight",
  "loss.dir_weight",
  "loss.n_pairs",
  "loss.sigma_initial",
  "loss.sigma_final",
  "loss.sigma_anneal_steps",
  "loss.kl_weight_initial",
  "loss.kl_anneal_steps",
  "model.draw_temperature",
  "optax.final_scale",
  "optax.anneal_steps",
  "data.dir",
  "model.dtype",
  "stop.",
)
# Retired fields: {field: the value every config had} for fields that `configs/common.py:base`
# gave every run and that now live only in the config whose code reads them. A workdir written
# before the move stores them in config.json; a requested config without them resumes it, the
# difference recorded (old -> None in config_history.jsonl), whatever the stored value: the
# runs whose configs lack a retired field never read it (the fields below are read by
# model.kind "convdraw" only, configs/gqn_convdraw.py, and a convdraw workdir resumed with
# another model.kind is refused on model.kind itself). A requested config that has the field
# compares it as any other. The values are base()'s, kept as the record of what those runs held.
RETIRED = {
  "model.draw_steps": 12,
  "model.z_channels": 3,
  "model.draw_temperature": 1.0,
  "loss.sigma_initial": 2.0,
  "loss.sigma_final": 0.7,
  "loss.sigma_anneal_steps": 200_000,
  "loss.kl_weight_initial": 1.0,
  "loss.kl_anneal_steps": 0,
}
# Fields that change only speed or where output goes: they differ silently (still recorded).
FREE = (
  "allow_changes",
  "data.num_threads",
  "data.prefetch",
  "data.num_workers",
  "data.device_prefetch",
)


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


def check_changes(
  old: Mapping[str, Any],
  new: Any,
  *,
  resumable: Iterable[str] | None,
  workdir: str,
  what: str = "resume",
) -> dict[str, tuple[Any, Any]]:
  """The differences between a workdir's stored config and the requested one, if allowed.

  Args:
    old: the stored config (config.json).
    new: the requested config; its `allow_changes` ("" when absent) names what may differ.
    resumable: the stage's fields that may differ at all; None: any field, when named in
      `allow_changes` (a stage that starts over instead of resuming, like regression).
    workdir: for the message.
    what: the verb of the message ("resume", "rerun").

  Returns:
    {field: (old, new)} of every difference (allowed and free ones, fields the stored config
    lacks, and `RETIRED` fields the requested config lacks: (stored value, None)).

  Raises:
    ConfigError: some field differs that is not free and not allowed; the message names each
      (old -> new) and the ways out.
  """
  diffs = differences(old, new)
  old_fields = flatten(as_plain(old))
  new_fields = flatten(as_plain(new))
  diffs.pop("allow_changes", None)  # the permission itself is not a change of the run
  allowed = parse_allow_changes(as_plain(new).get("allow_changes", ""))
  sections = tuple(a + "." for a in allowed)  # a section name allows its fields
  refused, need_flag = [], []
  for field, (a, b) in diffs.items():
    if _covered(field, FREE):
      continue
    if field not in old_fields:
      # A field camrep gained after the workdir was written: its default keeps the old
      # behaviour, so it is recorded, not refused (setting it on resume is still recorded).
      continue
    if field in RETIRED and field not in new_fields:
      continue  # moved out of the base config; this run never reads it (RETIRED): recorded
    if resumable is not None and not _covered(field, resumable):
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
      lines.append(
        f"use a new --workdir, or add --config.allow_changes={','.join(need_flag)} to record "
        "the change in config_history.jsonl"
      )
  raise ConfigError("\n".join(lines))

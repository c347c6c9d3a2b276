"""Where a view-synthesis run ends: at `total_steps`, or earlier by the plateau rule
(`config.stop`, `runtime.stopping`) checked at the held-out evaluations.

With the rule on (`config.stop.min_improvement > 0`), each held-out evaluation adds
(step, 10^(-eval/psnr / 10)) to the validation curve (the curve of a resumed run is read back
from metrics.jsonl: `recorded_curve`), and when `stopping.check` says the curve has plateaued
(`agree`: the lead decides, every process follows) the run saves its checkpoint at that step and
completes there: final_metrics.json's "step" is that step and its "stopping" record
(`stopping_record`) = {rule, score, stopped_early, steps, total_steps, reason, curve [[step,
score], ...]} (written whenever the rule is on, also when the run reaches the cap). Rerunning an
early-stopped run with the same rule changes nothing (`already_complete`); with another rule
(`stop` named in `allow_changes`) or the rule off it resumes from that step, and the rule is
checked at once on the recorded curve.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax
import numpy as np

from camrep.runtime import runconfig, stopping, writers
from camrep.runtime import session as session_lib


def already_complete(
  config, workdir: str, latest: int | None, log, *, rule: stopping.Rule | None = None
) -> dict[str, float] | None:
  """final_metrics.json's scalars when the workdir holds this run complete (nothing is written):
  at `total_steps`, or stopped early at its latest checkpoint by the same plateau `rule`. None
  when there is training (or the final record) left to do.

  Raises:
    ConfigError: `total_steps` is below the latest checkpoint's step.
  """
  total = config.total_steps
  if latest is not None and latest > total:
    raise runconfig.ConfigError(
      f"total_steps={total} is below the step {latest} of the latest checkpoint in {workdir}: "
      "the run is already past it; raise total_steps or use another --workdir (nothing changed)"
    )
  if latest is None or not session_lib.is_complete(workdir, latest):
    return None
  final = session_lib.read_final(workdir)
  if latest == total:
    log(f"{workdir} is complete at step {total} (final_metrics.json); nothing to do")
  elif stopped_early_by(final, rule):
    log(
      f"{workdir} is complete at step {latest}, stopped by the plateau rule "
      f"({final['stopping']['reason']}); nothing to do"
    )
  else:
    return None
  return {k: v for k, v in final.items() if "/" in k}


def stopped_early_by(final: Mapping | None, rule: stopping.Rule | None) -> bool:
  """Whether a final_metrics.json record says its run stopped early under this active `rule`."""
  s = (final or {}).get("stopping")
  if rule is None or not rule.active or not isinstance(s, Mapping):
    return False
  return s.get("stopped_early") is True and s.get("rule") == dataclasses.asdict(rule)


def recorded_curve(workdir: str, start: int) -> list[tuple[int, float]]:
  """The plateau rule's curve up to `start` from metrics.jsonl: (step, 10^(-eval/psnr / 10)) of
  each held-out evaluation logged (a resumed run goes on with the curve it had)."""
  return [
    (int(r["step"]), stopping.psnr_score(r["eval/psnr"]))
    for r in writers.read_metrics(workdir)
    if "eval/psnr" in r and int(r["step"]) <= start
  ]


def agree(rule: stopping.Rule, curve, lead: bool, *, check_now: bool = True) -> tuple[bool, str]:
  """The lead's `stopping.check` of the curve (only the lead evaluates), shared with every
  process (saves are collective: all must stop at the same step). Call on every process."""
  stop, why = stopping.check(rule, curve) if lead and check_now else (False, "")
  if jax.process_count() > 1 and rule.active:
    from jax.experimental import multihost_utils

    flags = multihost_utils.process_allgather(np.asarray(stop, np.int32))
    stop = bool(np.any(flags))
  return stop, why


def stopping_record(rule, curve, step: int, total: int, stopped_early: bool, reason: str) -> dict:
  """final_metrics.json's "stopping": the rule, its score, where and why the run ended, and
  the validation curve [[step, score], ...]."""
  return {
    "rule": dataclasses.asdict(rule),
    "score": "10^(-eval/psnr / 10): held-out-view MSE (geometric mean over the evaluated views)",
    "stopped_early": bool(stopped_early),
    "steps": int(step),
    "total_steps": int(total),
    "reason": reason,
    "curve": [[int(t), float(v)] for t, v in curve],
  }

"""When a training run stops: a plateau rule on its periodic validation score.

The run frame's fit loop (`camrep.runtime.frame.fit`) applies it for both stages, each on its
own validation-like score (the stage's `score`), one number per evaluation, lower is better: pose
regression on `tables.validation_score` of its validation split; view synthesis on the
held-out-view MSE 10^(-eval/psnr / 10) (`psnr_score`). Evaluated at each periodic evaluation
(every `eval_every_steps`): with the scores s(t_1), ..., s(t_k) so far, at step t = t_k

  best_now    = min over t_i <= t of s(t_i)
  best_before = min over t_i <= (1 - window) * t of s(t_i)
  improvement = (best_before - best_now) / best_before

and the run stops when improvement < `min_improvement` and t >= `min_steps`: the best validation
error improved by less than that share over the last `window` of the steps. `total_steps` is the
cap. Nothing is decided before an evaluation lies at or before (1 - window) * t (no baseline yet).
`min_improvement` = 0 turns the rule off (the run trains to `total_steps`, as before).

Where the rule stops a run, the run saves its checkpoint at that step and completes there; its
record ("stopping": `stopping_record`) says the rule, where and why it ended and the curve
[[step, score], ...] (in final_metrics.json, whenever the rule is on; a regression's results.json
holds it too). A rerun of an early-stopped run with the same rule changes
nothing (`runtime.frame.Frame.already_complete`, `stopped_early_by`); with another rule (`stop`
named in `allow_changes`) or the rule off it resumes from that step, its curve read back from
metrics.jsonl, and the rule is checked at once on the recorded curve.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence


@dataclasses.dataclass(frozen=True)
class Rule:
  """The stopping rule (`config.stop`): see the module docstring."""

  min_improvement: float = 0.0
  window: float = 0.25
  min_steps: int = 0

  @property
  def active(self) -> bool:
    return self.min_improvement > 0

  def describe(self) -> str:
    if not self.active:
      return "none (runs to total_steps)"
    return (
      f"stop when the best validation score improved by less than {self.min_improvement:.3g} "
      f"(relative) over the last {self.window:.3g} of the steps, not before step "
      f"{self.min_steps}; total_steps is the cap"
    )


def rule_from_config(stop) -> Rule:
  """The `Rule` of a config's `stop` section (absent: the rule is off).

  Raises:
    ValueError: min_improvement < 0, window outside (0, 1), or min_steps < 0.
  """
  if stop is None:
    return Rule()
  rule = Rule(float(stop.min_improvement), float(stop.window), int(stop.min_steps))
  if rule.min_improvement < 0 or not 0 < rule.window < 1 or rule.min_steps < 0:
    raise ValueError(
      f"stop: need min_improvement >= 0, 0 < window < 1 and min_steps >= 0; got {rule}"
    )
  return rule


def check(rule: Rule, curve: Sequence[tuple[int, float]]) -> tuple[bool, str]:
  """Whether to stop after the last evaluation of `curve`, and why (a sentence either way).

  Args:
    rule: the rule.
    curve: (step, validation score) in step order; the last entry is the evaluation just made.

  Returns:
    (stop, reason).
  """
  if not rule.active or not curve:
    return False, "no stopping rule"
  t, _ = curve[-1]
  if t < rule.min_steps:
    return False, f"step {t} < min_steps {rule.min_steps}"
  cut = (1.0 - rule.window) * t
  before = [s for step, s in curve if step <= cut]
  if not before:
    return False, f"no evaluation at or before step {cut:g} yet"
  best_before = min(before)
  best_now = min(s for _, s in curve)
  if not math.isfinite(best_before) or best_before <= 0:
    return False, f"best score before step {cut:g} is {best_before}: no relative improvement"
  improvement = (best_before - best_now) / best_before
  if improvement < rule.min_improvement:
    return True, (
      f"plateau at step {t}: best validation score {best_now:.4g} improved by "
      f"{100 * improvement:.2f}% since step {cut:g} ({best_before:.4g}), less than "
      f"{100 * rule.min_improvement:.3g}%"
    )
  return False, f"improved by {100 * improvement:.2f}% over the last {rule.window:g} of the steps"


def psnr_score(psnr: float) -> float:
  """The view-synthesis stopping score of a mean held-out PSNR (dB, images in [0, 1]):
  10^(-psnr / 10), the geometric mean over the evaluated images of their MSE; lower is better,
  and a relative improvement x of it is a gain of -10 log10(1 - x) dB (2% ~ 0.088 dB)."""
  return float(10.0 ** (-float(psnr) / 10.0))


def stopped_early_by(final: Mapping | None, rule: Rule | None) -> bool:
  """Whether a final record (final_metrics.json) says its run stopped early under this active
  `rule`."""
  s = (final or {}).get("stopping")
  if rule is None or not rule.active or not isinstance(s, Mapping):
    return False
  return s.get("stopped_early") is True and s.get("rule") == dataclasses.asdict(rule)


def stopping_record(
  rule: Rule,
  curve: Sequence[tuple[int, float]],
  step: int,
  total: int,
  stopped_early: bool,
  reason: str,
  *,
  score: str | None = None,
) -> dict:
  """The record of where and why a run ended: {"rule", "score" (what the curve's values are,
  when given), "stopped_early", "steps", "total_steps", "reason", "curve": [[step, score],
  ...]}."""
  out = {"rule": dataclasses.asdict(rule)}
  if score is not None:
    out["score"] = score
  out.update(
    stopped_early=bool(stopped_early),
    steps=int(step),
    total_steps=int(total),
    reason=reason,
    curve=[[int(t), float(v)] for t, v in curve],
  )
  return out

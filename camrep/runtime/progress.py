"""Progress of long loops: the status line (steps/s, elapsed, ETA) and `itstime`, the one place
where every 'every N steps' duration of a config becomes a yes/no for a step.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import jax

Array = jax.Array


def format_duration(seconds: float) -> str:
  """Formats seconds as "12s", "4m44s" or "1h02m03s" ("--" when unknown or infinite)."""
  if not math.isfinite(seconds) or seconds < 0:
    return "--"
  s = round(seconds)
  h, rem = divmod(s, 3600)
  m, s = divmod(rem, 60)
  if h:
    return f"{h}h{m:02d}m{s:02d}s"
  if m:
    return f"{m}m{s:02d}s"
  return f"{s}s"


class Progress:
  """Rate-limited one-line progress reports, for logs that are not a terminal (CI, cluster).

  `update(step)` is cheap and meant to be called every step; it returns a line such as
  "step 120/1000 (12.0%) 3.1 steps/s ETA 4m44s" on the first call, on the last step, and
  otherwise at most once every `every_seconds`; else None. The rate is measured over the
  interval since the previous report (since the first update before that), so the time spent in
  the first step (compilation) and before it does not count.
  """

  def __init__(
    self,
    total_steps: int,
    *,
    start_step: int = 0,
    every_seconds: float = 30.0,
    log_fn: Callable[[str], None] | None = None,
    clock: Callable[[], float] = time.monotonic,
  ):
    """Sets up the reporter.

    Args:
      total_steps: Step number at which training ends.
      start_step: Step the run starts (or resumes) from.
      every_seconds: Minimum time between two reports.
      log_fn: Called with each report line (e.g. `logging.info` or `print`); none by default.
      clock: Time source in seconds (tests pass a fake one).
    """
    self.total_steps = int(total_steps)
    self.every_seconds = float(every_seconds)
    self._log_fn = log_fn
    self._clock = clock
    self._last_step = int(start_step)
    self._anchor: tuple[float, int] | None = None  # (time, step) where the window starts.
    self._last_report: float | None = None
    self._rate = math.nan

  @property
  def steps_per_second(self) -> float:
    """Steps/s over the latest measuring window (NaN before two updates)."""
    return self._rate

  def update(self, step: int) -> str | None:
    """Records that `step` is done; returns a report line when one is due, else None."""
    step = int(step)
    now = self._clock()
    self._last_step = step
    if self._anchor is None:
      self._anchor = (now, step)
    else:
      t0, s0 = self._anchor
      if now > t0 and step > s0:
        self._rate = (step - s0) / (now - t0)
    due = (
      self._last_report is None
      or step >= self.total_steps
      or now - self._last_report >= self.every_seconds
    )
    if not due:
      return None
    self._last_report = now
    if self._rate == self._rate:  # Once a rate exists, the next window starts here.
      self._anchor = (now, step)
    line = self.status()
    if self._log_fn is not None:
      self._log_fn(line)
    return line

  def status(self) -> str:
    """The current status line, whether or not a report is due."""
    total = max(self.total_steps, 1)
    pct = 100.0 * self._last_step / total
    rate = self._rate
    if math.isfinite(rate) and rate > 0:
      eta = format_duration(max(self.total_steps - self._last_step, 0) / rate)
      speed = f"{rate:.1f} steps/s" if rate >= 1 else f"{rate:.2g} steps/s"
    else:
      eta, speed = "--", "-- steps/s"
    return f"step {self._last_step}/{self.total_steps} ({pct:.1f}%) {speed} ETA {eta}"


def itstime(step: int, every: int, total: int, *, first: bool = False) -> bool:
  """Whether a periodic action (log, eval, checkpoint) runs at `step`.

  Steps count completed updates: 1 .. total. True when `step` is a positive multiple of
  `every`, when `step == total` (the last step, even if not a multiple), and with `first=True`
  also at step 1. `every <= 0` disables the action entirely (never true, not even at the last
  step). Follows big_vision `utils.py:itstime`.

  Args:
    step: Number of completed steps.
    every: Period in steps; <= 0 means never.
    total: Total number of steps of the run.
    first: Also fire at step 1.

  Returns:
    Whether to act at this step.
  """
  if every <= 0:
    return False
  return (step > 0 and step % every == 0) or step == total or (first and step == 1)

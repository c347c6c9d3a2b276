"""Stopping a training run cleanly on SIGTERM/SIGINT (a cluster's preemption, Ctrl-C): the first
signal only sets a flag; the train loop then saves a checkpoint and stops.

  with install_signal_handlers() as preempt:
    for step in range(start_step + 1, total_steps + 1):
      state, metrics = p_train_step(state, batch, loop_key)
      stopped = stop_requested(preempt)
      if itstime(step, ckpt_every_steps, total_steps) or stopped:
        ckpt.save(step, state, extra={"data_step": step})
      if stopped:
        break

Several processes: a save is collective, so a save that only some processes enter would hang;
`stop_requested` combines the flags of every process (an all-gather) so all stop at one step.
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Iterable
from typing import Any

import jax
import numpy as np


class PreemptionHandler:
  """Records SIGTERM/SIGINT so the train loop can save a checkpoint and stop cleanly.

  The first signal sets `requested` (and `signum`). A second SIGINT raises
  `KeyboardInterrupt` as usual (press Ctrl-C twice to abort without saving); a second
  SIGTERM is only logged. Use `install_signal_handlers()` to create one.

  Attributes:
    requested: True once a signal arrived.
    signum: the first signal received, or None.
  """

  def __init__(self, signals: Iterable[int]) -> None:
    self.requested = False
    self.signum: int | None = None
    self._signals = tuple(signals)
    self._previous: dict[int, Any] = {}

  def _install(self) -> None:
    if threading.current_thread() is not threading.main_thread():
      raise RuntimeError("Signal handlers can only be installed from the main thread.")
    for sig in self._signals:
      self._previous[sig] = signal.signal(sig, self._handle)

  def _handle(self, signum: int, frame: object) -> None:
    del frame
    name = signal.Signals(signum).name
    if self.requested:
      if signum == signal.SIGINT:
        raise KeyboardInterrupt
      logging.warning("Received %s again; still stopping at the next checkpoint.", name)
      return
    self.requested = True
    self.signum = signum
    logging.warning("Received %s: will save a checkpoint and stop.", name)

  def uninstall(self) -> None:
    """Restores the handlers that were active before; safe to call twice."""
    for sig, previous in self._previous.items():
      # None means the previous handler was not installed from Python.
      signal.signal(sig, signal.SIG_DFL if previous is None else previous)
    self._previous.clear()

  def __enter__(self) -> PreemptionHandler:
    return self

  def __exit__(self, *exc_info: object) -> None:
    self.uninstall()


def install_signal_handlers(
  *, signals: Iterable[int] = (signal.SIGTERM, signal.SIGINT)
) -> PreemptionHandler:
  """Installs handlers that turn SIGTERM/SIGINT into a `requested` flag.

  Must be called from the main thread. Usable as a context manager, which uninstalls on exit.

  Args:
    signals: the signals to catch.

  Returns:
    The installed `PreemptionHandler`.
  """
  handler = PreemptionHandler(signals)
  handler._install()
  return handler


def stop_requested(handler: PreemptionHandler) -> bool:
  """Whether any process was signalled to stop (saves are collective: all must agree)."""
  if jax.process_count() == 1:
    return handler.requested
  from jax.experimental import multihost_utils

  flags = multihost_utils.process_allgather(np.asarray(handler.requested, np.int32))
  return bool(np.any(flags))

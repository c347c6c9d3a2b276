"""Trains a view-synthesis run: `python -m camrep.main --config=configs/gqn.py[:quick|:smoke]
--workdir=DIR [--config.FIELD=VALUE ...]`.

`--config=gqn:quick` names the installed config instead of a file (`camrep.configs`).

Kept short on purpose: it parses flags, checks the config (`camrep.synthesis.config_schema`:
every field, what the task uses, the data's image size) before anything runs, joins a
jax.distributed job when asked, logs the devices, and calls
`camrep.synthesis.train.train_and_evaluate`. `lock_config` turns an unknown `--config.` field
into an error, and types are checked.

Exit status (`camrep.runtime.cli`): 0 done (or stopped by SIGTERM / Ctrl-C after saving a
checkpoint), 2 a user's mistake or an unusable resource (bad flag or config, workdir, data,
checkpoint, full disk; one `error:` line), 3 non-finite training values, 1 a bug.
"""

from __future__ import annotations

import os
import sys
import threading
import time

import jax
from absl import flags, logging

from camrep import configs
from camrep.runtime import cli
from camrep.synthesis import config_schema, train

_CONFIG = configs.define_config_flag(
  "config", "A config file (configs/gqn.py[:quick]) or an installed config's name (gqn:quick)."
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Directory for checkpoints, metrics and images.")
_COORDINATOR = flags.DEFINE_string(
  "coordinator_address",
  None,
  "Several processes: host:port of process 0 (jax.distributed); with --num_processes and "
  "--process_id. Leave all three unset for one process.",
)
_NUM_PROCESSES = flags.DEFINE_integer("num_processes", None, "Several processes: how many.")
_PROCESS_ID = flags.DEFINE_integer("process_id", None, "Several processes: this one's index.")
_DISTRIBUTED = flags.DEFINE_bool(
  "distributed",
  False,
  "Call jax.distributed.initialize() with cluster auto-detection (SLURM, TPU pods, Open MPI); "
  "implied by --coordinator_address.",
)
_COORDINATOR_TIMEOUT = flags.DEFINE_integer(
  "coordinator_timeout",
  120,
  "Several processes: seconds to wait for every process to join before exiting 2 with an "
  "error naming the coordinator.",
)
flags.mark_flags_as_required(["config", "workdir"])


def check_process_flags(
  coordinator: str | None,
  num_processes: int | None,
  process_id: int | None,
  *,
  distributed: bool = False,
  timeout: int = 120,
) -> None:
  """Refuses an incomplete or inconsistent set of multi-process flags.

  Without `--distributed`, --coordinator_address, --num_processes and --process_id go together
  (all three or none); with it, cluster detection fills in those not given.

  Raises:
    cli.UsageError: naming the flags and what is allowed.
  """
  given = {
    "--coordinator_address": coordinator,
    "--num_processes": num_processes,
    "--process_id": process_id,
  }
  named = [k for k, v in given.items() if v is not None]
  if named and len(named) < 3 and not distributed:
    missing = [k for k, v in given.items() if v is None]
    raise cli.UsageError(
      f"{', '.join(named)} given without {', '.join(missing)}: several processes need all "
      "three (or --distributed for cluster auto-detection); one process needs none"
    )
  if num_processes is not None and num_processes < 1:
    raise cli.UsageError(f"--num_processes={num_processes}: must be >= 1")
  if process_id is not None:
    if process_id < 0:
      raise cli.UsageError(f"--process_id={process_id}: must be >= 0")
    if num_processes is not None and process_id >= num_processes:
      raise cli.UsageError(
        f"--process_id={process_id}: must be < --num_processes={num_processes} "
        f"(0 .. {num_processes - 1})"
      )
  if coordinator is not None:
    host, sep, port = coordinator.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
      raise cli.UsageError(
        f"--coordinator_address={coordinator}: expected host:port (port 1..65535)"
      )
  if timeout < 1:
    raise cli.UsageError(f"--coordinator_timeout={timeout}: must be >= 1 second")


def init_distributed() -> None:
  """Joins the jax.distributed job named by the flags, if any (before any JAX computation).

  jax aborts the whole process (a C++ stack dump, exit 134) when the coordinator cannot be
  reached within its `initialization_timeout`; a watchdog exits 2 with an `error:` line first,
  after `--coordinator_timeout` seconds (jax's own timeout is set 30 s later). While it waits,
  a line says for how long (`wait_progress`).
  """
  if not (_COORDINATOR.value or _DISTRIBUTED.value):
    return
  # CPU processes all-reduce through gloo; GPU / TPU backends bring their own collectives.
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  timeout = _COORDINATOR_TIMEOUT.value
  where = _COORDINATOR.value or "the auto-detected coordinator"

  def give_up():
    print(
      f"error: could not join the jax.distributed job at {where} within {timeout} s (process "
      f"{_PROCESS_ID.value} of {_NUM_PROCESSES.value}): is process 0 running there, is the "
      "address reachable, and were all processes started? (--coordinator_timeout)",
      file=sys.stderr,
      flush=True,
    )
    os._exit(cli.EXIT_USER)

  who = f"process {_PROCESS_ID.value} of {_NUM_PROCESSES.value}"
  print(
    f"joining the jax.distributed job at {where} as {who} (--coordinator_timeout={timeout} s)",
    flush=True,
  )
  watchdog = threading.Timer(timeout, give_up)
  watchdog.daemon = True
  done = threading.Event()
  progress = threading.Thread(
    target=wait_progress, args=(done, where, who, timeout), name="coordinator_wait", daemon=True
  )
  watchdog.start()
  progress.start()
  try:
    jax.distributed.initialize(
      coordinator_address=_COORDINATOR.value,
      num_processes=_NUM_PROCESSES.value,
      process_id=_PROCESS_ID.value,
      initialization_timeout=timeout + 30,
    )
  finally:
    done.set()
    watchdog.cancel()


def wait_progress(done: threading.Event, where: str, who: str, timeout: float) -> None:
  """Prints how long this process has waited for the other processes to join, every quarter
  of the timeout (1 to 15 s apart), until `done` is set."""
  every = min(15.0, max(1.0, timeout / 4))
  t0 = time.monotonic()
  while not done.wait(every):
    waited = time.monotonic() - t0
    print(
      f"waiting for the jax.distributed job at {where} ({who}): {waited:.0f} s of "
      f"--coordinator_timeout={timeout:g} s",
      flush=True,
    )


def main(argv):
  if len(argv) > 1:
    raise cli.UsageError(f"unexpected arguments: {argv[1:]}")
  if not flags.FLAGS["verbosity"].present:
    logging.set_verbosity(logging.WARNING)  # orbax logs every save at INFO; -v 0 brings it back
  check_process_flags(
    _COORDINATOR.value,
    _NUM_PROCESSES.value,
    _PROCESS_ID.value,
    distributed=_DISTRIBUTED.value,
    timeout=_COORDINATOR_TIMEOUT.value,
  )
  config_schema.validate(_CONFIG.value, overridden=cli.overridden())
  init_distributed()
  where = f"process {jax.process_index()}/{jax.process_count()}"
  print(f"JAX {jax.__version__}, {where}, local devices {jax.local_devices()}", flush=True)
  train.train_and_evaluate(_CONFIG.value, _WORKDIR.value)


if __name__ == "__main__":
  cli.run(main)

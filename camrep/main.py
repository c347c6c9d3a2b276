"""Entry point: `python -m camrep.main --config=configs/gqn.py[:quick|:smoke] --workdir=DIR`.

`--config=gqn:quick` names the installed config instead of a file (`camrep.configs`).

Kept short on purpose: it parses flags, joins a jax.distributed job when asked, logs the devices,
and calls `camrep.synthesis.train.train_and_evaluate`. Override config fields with
`--config.total_steps=...`
(`lock_config` turns an unknown key into an error, and types are checked).

Exit status: 0 done (or stopped by SIGTERM / Ctrl-C after saving a checkpoint), 1 bad flags,
2 bad input (workdir, data or checkpoint; the message names it), 3 non-finite training values.
"""

from __future__ import annotations

import sys

import jax
from absl import app, flags, logging

from camrep import configs
from camrep.data.errors import DataError
from camrep.runtime import runconfig
from camrep.runtime import workdir as workdir_lib
from camrep.runtime.checkpoint import CheckpointError
from camrep.synthesis import train

_CONFIG = configs.define_config_flag(
  "config", "A config file (configs/gqn.py[:quick]) or an installed config's name (gqn:quick)."
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Directory for checkpoints, metrics and images.")
_COORDINATOR = flags.DEFINE_string(
  "coordinator_address",
  None,
  "Several processes: host:port of process 0 (jax.distributed). Leave unset for one process.",
)
_NUM_PROCESSES = flags.DEFINE_integer("num_processes", None, "Several processes: how many.")
_PROCESS_ID = flags.DEFINE_integer("process_id", None, "Several processes: this one's index.")
_DISTRIBUTED = flags.DEFINE_bool(
  "distributed",
  False,
  "Call jax.distributed.initialize() with no arguments (cluster auto-detection: SLURM, TPU "
  "pods, Open MPI); implied by --coordinator_address.",
)
flags.mark_flags_as_required(["config", "workdir"])


def init_distributed() -> None:
  """Joins the jax.distributed job named by the flags, if any (before any JAX computation)."""
  if not (_COORDINATOR.value or _DISTRIBUTED.value):
    return
  # CPU processes all-reduce through gloo; GPU / TPU backends bring their own collectives.
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  jax.distributed.initialize(
    coordinator_address=_COORDINATOR.value,
    num_processes=_NUM_PROCESSES.value,
    process_id=_PROCESS_ID.value,
  )


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments: {argv[1:]}")
  if not flags.FLAGS["verbosity"].present:
    logging.set_verbosity(logging.WARNING)  # orbax logs every save at INFO; -v 0 brings it back
  init_distributed()
  where = f"process {jax.process_index()}/{jax.process_count()}"
  print(f"JAX {jax.__version__}, {where}, local devices {jax.local_devices()}", flush=True)
  try:
    train.train_and_evaluate(_CONFIG.value, _WORKDIR.value)
  except FloatingPointError as e:
    print(f"error: {e}", file=sys.stderr, flush=True)
    sys.exit(3)
  except (runconfig.ConfigError, workdir_lib.WorkdirError, DataError, CheckpointError) as e:
    print(f"error: {e}", file=sys.stderr, flush=True)
    sys.exit(2)


if __name__ == "__main__":
  app.run(main)

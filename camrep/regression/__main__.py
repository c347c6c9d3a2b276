"""`python -m camrep.regression --config=configs/regression.py[:quick|:smoke] --workdir=DIR`: one
pose-regression run (`camrep.regression.driver.run`). Exit status: 0 done, 1 bad flags, 2 bad config
or workdir, 3 non-finite training values."""

from __future__ import annotations

import sys

import jax
from absl import app, flags, logging

from camrep import configs
from camrep.regression import driver
from camrep.runtime import runconfig
from camrep.runtime import workdir as workdir_lib

_CONFIG = configs.define_config_flag(
  "config", "configs/regression.py[:quick|:smoke], or the installed regression[:quick|:smoke]."
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Output directory (results.json, metrics).")
flags.mark_flags_as_required(["config", "workdir"])


def main(argv) -> None:
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments: {argv[1:]}")
  if not flags.FLAGS["verbosity"].present:
    logging.set_verbosity(logging.ERROR)  # orbax warns that a read-only manager saves nothing
  print(f"JAX {jax.__version__}, devices {jax.local_devices()}", flush=True)
  try:
    driver.run(_CONFIG.value, _WORKDIR.value, log=lambda s: print(s, flush=True))
  except (runconfig.ConfigError, workdir_lib.WorkdirError) as e:
    print(f"error: {e}", file=sys.stderr, flush=True)
    sys.exit(2)
  except FloatingPointError as e:
    print(f"error: {e}", file=sys.stderr, flush=True)
    sys.exit(3)


if __name__ == "__main__":
  app.run(main)

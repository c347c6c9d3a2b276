"""Trains one pose regressor: `python -m camrep.regression
--config=configs/regression.py[:quick|:smoke] --workdir=DIR [--config.FIELD=VALUE ...]`
(`camrep.regression.driver.run`).

The config is checked first (`camrep.regression.config_schema`: every field, and the fields the
chosen setting, representation and data use). The same command resumes a run from its latest
checkpoint (a complete run: nothing to do). Exit status (`camrep.runtime.cli`): 0 done (or
stopped by SIGTERM / Ctrl-C after saving a checkpoint: the same command resumes), 2 a user's
mistake (bad flag, config or workdir; one `error:` line), 3 non-finite training values, 1 a bug.
"""

from __future__ import annotations

import jax
from absl import flags, logging

from camrep import configs
from camrep.regression import config_schema, driver
from camrep.runtime import cli

_CONFIG = configs.define_config_flag(
  "config", "configs/regression.py[:quick|:smoke], or the installed regression[:quick|:smoke]."
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Output directory (results.json, metrics).")
flags.mark_flags_as_required(["config", "workdir"])


def main(argv) -> None:
  if len(argv) > 1:
    raise cli.UsageError(f"unexpected arguments: {argv[1:]}")
  if not flags.FLAGS["verbosity"].present:
    logging.set_verbosity(logging.ERROR)  # orbax warns that a read-only manager saves nothing
  config_schema.validate(_CONFIG.value, overridden=cli.overridden())
  print(f"JAX {jax.__version__}, devices {jax.local_devices()}", flush=True)
  driver.run(_CONFIG.value, _WORKDIR.value, log=lambda s: print(s, flush=True))


if __name__ == "__main__":
  cli.run(main)

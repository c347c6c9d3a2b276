"""Trains one pose regressor: `python -m camrep.regression
--config=configs/regression.py[:quick|:smoke] --workdir=DIR [--config.FIELD=VALUE ...]`
(`camrep.regression.driver.run`); with `--lrs=LR,LR,... --seeds=K,K,...` (either or both), a grid
of such runs trained together as one vectorised program, member (lr, k) into
DIR/<lr tag>_seed<k> (`camrep.regression.vectorised`); on a CPU its members are spread over
--host_devices one-thread host devices (default: the usable cores, at most the members).

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
from camrep.regression import config_schema, driver, vectorised
from camrep.runtime import cli, xla_cpu

_CONFIG = configs.define_config_flag(
  "config", "configs/regression.py[:quick|:smoke], or the installed regression[:quick|:smoke]."
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Output directory (results.json, metrics).")
_LRS = flags.DEFINE_list(
  "lrs", None, "A grid: its learning rates (default: the config's optax.lr); see --seeds."
)
_SEEDS = flags.DEFINE_list(
  "seeds",
  None,
  "A grid of runs trained together (camrep.regression.vectorised): its seeds (default: the "
  "config's seed); member (lr, k) writes DIR/lr<lr>_seed<k>. A {seed} in "
  "--config.synthesis_workdir is each member's seed.",
)
_HOST_DEVICES = flags.DEFINE_integer(
  "host_devices",
  0,
  "A grid on a CPU: the host devices its members are spread over, each running XLA:CPU on one "
  "thread (camrep.runtime.xla_cpu.host_devices), at most one per member; 0: the usable cores; 1: "
  "one device on a thread pool of every core. Unless XLA_FLAGS name them; GPU programs unchanged.",
  lower_bound=0,
)
flags.mark_flags_as_required(["config", "workdir"])


def _numbers(flag: str, values: list[str], kind: type) -> list:
  try:
    out = [kind(v) for v in values]
  except ValueError:
    raise cli.UsageError(f"--{flag}={','.join(values)}: not a list of {kind.__name__}s") from None
  if not out or any(x <= 0 if kind is float else x < 0 for x in out):
    what = "positive" if kind is float else "non-negative"
    raise cli.UsageError(f"--{flag}={','.join(values)}: give one or more {what} values")
  return out


def grid_axes(config, overridden: set[str]) -> tuple[list[float], list[int]] | None:
  """(lrs, seeds) of a grid command, or None for a single run.

  Raises:
    UsageError: a bad list, or a grid that also sets the field it varies.
  """
  if _LRS.value is None and _SEEDS.value is None:
    return None
  for flag, field, given in (("lrs", "optax.lr", _LRS.value), ("seeds", "seed", _SEEDS.value)):
    if given is not None and field in overridden:
      raise cli.UsageError(f"--{flag} sets each member's {field}: drop --config.{field}")
  lrs = [config.optax.lr] if _LRS.value is None else _numbers("lrs", _LRS.value, float)
  seeds = [config.seed] if _SEEDS.value is None else _numbers("seeds", _SEEDS.value, int)
  return lrs, seeds


def main(argv) -> None:
  if len(argv) > 1:
    raise cli.UsageError(f"unexpected arguments: {argv[1:]}")
  if not flags.FLAGS["verbosity"].present:
    logging.set_verbosity(logging.ERROR)  # orbax warns that a read-only manager saves nothing
  overridden = cli.overridden()
  axes = grid_axes(_CONFIG.value, overridden)
  if axes is None and flags.FLAGS["host_devices"].present:
    raise cli.UsageError("--host_devices spreads a grid's members (--lrs, --seeds); a run is one")
  log = lambda s: print(s, flush=True)  # noqa: E731
  if axes is not None:
    vectorised.members(_CONFIG.value, _WORKDIR.value, *axes, overridden=overridden)  # checked first
    n = min(_HOST_DEVICES.value or xla_cpu.usable_cores(), len(axes[0]) * len(axes[1]))
    xla_cpu.host_devices(n)  # before JAX's backend starts (the line below)
    print(f"JAX {jax.__version__}, devices {jax.local_devices()}", flush=True)
    vectorised.run(
      _CONFIG.value, _WORKDIR.value, lrs=axes[0], seeds=axes[1], overridden=overridden, log=log
    )
    return
  config_schema.validate(_CONFIG.value, overridden=overridden)
  print(f"JAX {jax.__version__}, devices {jax.local_devices()}", flush=True)
  driver.run(_CONFIG.value, _WORKDIR.value, log=log)


if __name__ == "__main__":
  cli.run(main)

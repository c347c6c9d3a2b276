"""A trained view-synthesis run restored from its workdir: config, pose system, model,
parameters and pipelines (for evaluation, figures and regression targets).

Restoring reads no data: the state template comes from `batches.dummy_batch` and the per-scene
table size from `batches.describe`; the pipelines are built when first used.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import ml_collections

from camrep import pose as P
from camrep.data.feed import batches
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import components
from camrep.synthesis import step as step_lib

Array = jax.Array


@dataclasses.dataclass
class Run:
  """A trained run, restored from its workdir.

  Attributes:
    workdir: the training workdir.
    config: the run's config, read back from workdir/config.json.
    spec: its pose system.
    model: its view-synthesis model (`synthesizers.Synthesizer`).
    params: {"model": flax params, "rep": pose-system params} of the restored checkpoint.
    step: the restored checkpoint's step.
    train_pipe: training-split pipeline (context views of the evaluation set), built (and, for
      in-memory data, rendered) on first use.
    test_pipe: held-out-view pipeline (for_eval), built on first use.
  """

  workdir: str
  config: ml_collections.ConfigDict
  spec: P.PoseSystemSpec
  model: Any
  params: dict
  step: int

  @functools.cached_property
  def train_pipe(self) -> Any:
    n = jax.local_device_count()
    return components.make_pipeline(self.config, "train", num_devices=n)

  @functools.cached_property
  def test_pipe(self) -> Any:
    return components.make_pipeline(self.config, "test", num_devices=1, for_eval=True)


def load_model(workdir: str) -> tuple[ml_collections.ConfigDict, Any]:
  """(config, model) of a run as `train.train_and_evaluate` builds them, from its config.json
  alone: no checkpoint, data or rendering is read (the per-scene table size comes from
  `batches.describe`). What a run's initial state needs (`Synthesizer.init_pose` of its root
  key), e.g. a workdir an archive restored with its config.json and record.json only.

  Raises:
    FileNotFoundError: no workdir, or no config.json.
    ConfigError: the data or pose system the config rebuilds today differ from the workdir's
      record.json (a changed library default).
  """
  config = workdir_lib.read_config(workdir)
  resolved = components.resolve(config)
  # Today's defaults must rebuild the data and pose system that trained it (record.json; a
  # workdir written before camrep kept one is not checked).
  workdir_lib.check_record(workdir, components.run_record(resolved), what="restore")
  info = batches.describe(config.data, "train")
  return config, components.make_model(resolved, int(info.scene_ids.max()) + 1)


def load_run(workdir: str, *, step: int | None = None) -> Run:
  """Rebuilds a run as `train.train_and_evaluate` does and restores a checkpoint's parameters.

  Args:
    workdir: a training workdir (config.json, checkpoints/).
    step: the checkpoint step to restore; None: the latest readable one.

  Returns:
    The `Run`.

  Raises:
    FileNotFoundError: no workdir, no config.json, or no checkpoint.
    ConfigError: the data or pose system the config rebuilds today differ from the workdir's
      record.json (a changed library default).
    camrep.runtime.checkpoint.CheckpointError: the requested step is missing, or no checkpoint is
      readable or matches the config's model.
  """
  from camrep.runtime import checkpoint as ckpt_lib

  config, model = load_model(workdir)
  try:
    checkpointer = ckpt_lib.Checkpointer(workdir, read_only=True)
  except ckpt_lib.CheckpointError:
    raise FileNotFoundError(f"no checkpoint in {workdir!r} (no checkpoints/ directory)") from None
  try:
    steps = checkpointer.all_steps()
    if not steps:
      raise FileNotFoundError(f"no checkpoint in {checkpointer.directory}")
    if step is not None and step not in steps:
      raise ckpt_lib.CheckpointError(
        f"no checkpoint for step {step} in {checkpointer.directory}; available: {steps}"
      )
    # The training layout's shapes from the config alone (`batches.dummy_batch`).
    init = step_lib.init_fn(config, model, step_lib.make_optimizers(config))
    state, restored = step_lib.restore_state(checkpointer, init, step=step)
  finally:
    checkpointer.close()
  return Run(
    workdir=workdir,
    config=config,
    spec=model.spec,
    model=model,
    params=state.params,
    step=int(restored),
  )

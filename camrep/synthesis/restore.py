"""A trained view-synthesis run restored from its workdir: config, pose system, model,
parameters and pipelines (for evaluation, figures and regression targets).

Restoring reads no data: the state template comes from `batches.dummy_batch` and the per-scene
table size from `batches.describe`; the pipelines are built when first used.

A complete run whose model reads the setting's pose vectors also leaves its final pose system,
the regression targets' "rep" parameters, in pose_system.npz (`save_pose_file`, written by
`train.train_and_evaluate` beside the final checkpoint: the same values; `load_pose_file` reads
it back with the config's model as the template): a few KB for a 1-D grid per DOF, about 1 MB
for the 2-D grids of the rooms and the area. An archive keeps the small ones
(`camrep.comparison.archive`), so that regressions read them on a machine without the run's
checkpoints.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any

import jax
import ml_collections
import numpy as np

from camrep import pose as P
from camrep.data.feed import batches
from camrep.runtime import workdir as workdir_lib
from camrep.synthesis import components
from camrep.synthesis import step as step_lib

Array = jax.Array

POSE_FILE = "pose_system.npz"
_STEP_KEY = "__step__"


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


def save_pose_file(workdir: str, rep, step: int) -> str:
  """Writes a run's pose system `rep` (its "rep" parameters at `step`) to workdir/POSE_FILE, one
  array per leaf named by its path (`jax.tree_util.keystr`), through a temporary file; returns
  the path."""
  leaves = jax.tree_util.tree_leaves_with_path(rep)
  arrays = {jax.tree_util.keystr(p): np.asarray(v) for p, v in leaves}
  arrays[_STEP_KEY] = np.asarray(int(step))
  path = os.path.join(workdir, POSE_FILE)
  tmp = f"{path}.tmp{os.getpid()}.npz"
  np.savez(tmp, **arrays)
  os.replace(tmp, path)
  return path


def load_pose_file(workdir: str, model) -> tuple[Any, int]:
  """(rep, step) of workdir/POSE_FILE, as the pytree of `model.init_pose` (the run's model,
  `load_model`): every leaf's path, shape and dtype must match.

  Raises:
    FileNotFoundError: the workdir has no POSE_FILE.
    ValueError: the file cannot be read, or does not match the model's pose system.
  """
  path = os.path.join(workdir, POSE_FILE)
  template = jax.eval_shape(model.init_pose, jax.random.key(0))
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{path} not found")
  try:
    with np.load(path) as f:
      arrays = {k: f[k] for k in f.files}
  except Exception as e:  # a cut or foreign file: zipfile, pickle and format errors
    raise ValueError(f"{path} cannot be read ({type(e).__name__}: {e})") from None
  leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
  names = [jax.tree_util.keystr(p) for p, _ in leaves]
  if set(arrays) != {*names, _STEP_KEY}:
    raise ValueError(
      f"{path} holds {sorted(set(arrays) - {_STEP_KEY})}, not the pose system {names} of the "
      "run's config"
    )
  out = []
  for name, (_, leaf) in zip(names, leaves, strict=True):
    a = arrays[name]
    if a.shape != leaf.shape or a.dtype != leaf.dtype:
      raise ValueError(
        f"{path}: {name} is {a.dtype}{list(a.shape)}, the run's config makes "
        f"{leaf.dtype}{list(leaf.shape)}"
      )
    out.append(jax.numpy.asarray(a))
  return jax.tree_util.tree_unflatten(treedef, out), int(arrays[_STEP_KEY])

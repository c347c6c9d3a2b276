"""The frozen pose input a regression run regresses from (paper section 4.4), and the checks that
tie it to a view-synthesis workdir trained on the same data.

  representation_params  (spec, params, info) of a resolved config's encoding
                         (`config_schema.Resolved`): nothing for the baselines; a learned
                         encoding's from `config.synthesis_workdir` when that run trained the
                         same encoding ("ours": the learned grid system, required; the controls
                         "untrained": that run's initial grid, "frozen_gen": a run that froze
                         its generators), else a frozen randomly initialised one ("mlp":
                         `MlpEncoding`)
  load_pose_system       restores a view-synthesis workdir's pose input (the synthesis
                         `load_run`, which reads no data), checked against the setting
                         (`restore_pose_system`: given the regression's resolved config, also
                         against its data and encoding)
  check_same_data        the same data.source and prepared directory and dataset as the
                         regression reads, and (`check_same_world`) the same data fingerprint:
                         the family's parameters apart from scene and view counts and image
                         size, or the prepared dataset's identity and content
"""

from __future__ import annotations

import hashlib
import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from camrep import pose_encodings
from camrep import settings as settings_lib
from camrep.data import sources
from camrep.regression import views as views_lib
from camrep.runtime import workdir as workdir_lib
from camrep.runtime.runconfig import ConfigError
from camrep.synthesis import components, restore


def check_same_data(workdir: str, syn_config, config, source: sources.Source) -> None:
  """Refuses a view-synthesis run trained on other data than this regression reads (`config`'s,
  from `source`): another data.source, or (real data) another prepared directory or dataset.

  Raises:
    ConfigError: as above.
  """
  ours, theirs = source.name, syn_config.data.source
  our_dir = os.path.abspath(config.data.dir) if config.data.get("dir", "") else ""
  their_dir = os.path.abspath(syn_config.data.dir) if syn_config.data.get("dir", "") else ""
  if ours != theirs or our_dir != their_dir:
    raise ConfigError(
      f"synthesis_workdir {workdir} was trained on data.source={theirs!r}"
      + (f" data.dir={their_dir}" if their_dir else " (procedural)")
      + f", but this regression reads data.source={ours!r}"
      + (f" data.dir={our_dir}" if our_dir else " (procedural)")
      + ': "ours" must regress a pose system learned on the same data'
    )
  check_same_world(workdir, syn_config, config, source)
  if not our_dir:
    return
  from camrep.data.errors import DataError
  from camrep.data.feed import storage

  preset = syn_config.data.get("preset", "default")
  try:
    theirs_path = storage.dataset_dir(
      their_dir, theirs, config=preset if preset != "default" else None
    )
  except DataError:
    return  # the run's dataset cannot be resolved any more; source and dir matched
  ours_path, _ = views_lib.open_dataset(config)
  if os.path.abspath(theirs_path) != os.path.abspath(ours_path):
    raise ConfigError(
      f"synthesis_workdir {workdir} was trained on the prepared dataset {theirs_path}, this "
      f"regression reads {ours_path} (pass --config.data.dataset_config to pick the same one)"
    )


def _synthesis_data_record(workdir: str, syn_config) -> dict[str, Any] | None:
  """The data record of a view-synthesis workdir: its record.json's, or (a workdir written
  before camrep kept one) computed from its config.json with today's library defaults, with a
  warning; None when neither is possible (its prepared dataset is gone)."""
  import sys

  from camrep.data.errors import DataError
  from camrep.data.feed import fingerprint

  record = workdir_lib.read_record(workdir)
  if record is not None and isinstance(record.get("data"), dict):
    return record["data"]
  try:
    data = fingerprint.data_record(syn_config.data)
  except DataError:
    return None
  print(
    f"warning: synthesis_workdir {workdir} has no {workdir_lib.RECORD_FILE} (an older camrep): "
    "its data is identified from its config.json with today's library defaults",
    file=sys.stderr,
    flush=True,
  )
  return data


def check_same_world(workdir: str, syn_config, config, source: sources.Source) -> None:
  """Refuses a view-synthesis run whose data fingerprint ("world": the family's parameters apart
  from scene and view counts and image resolution, or the prepared dataset's identity and
  content) differs from this regression's, e.g. rooms of another wall style, light or seed.

  Raises:
    ConfigError: the first differing parameter (or the fingerprints) named, synthesis value ->
      this regression's.
  """
  from camrep.data.feed import fingerprint

  theirs = _synthesis_data_record(workdir, syn_config)
  if theirs is None:
    return  # its dataset is gone: data.source and data.dir were compared
  ours = views_lib.data_record(config, source)
  if theirs.get("world") == ours.get("world"):
    return
  a, b = theirs.get("family") or {}, ours.get("family") or {}
  fields = [
    f"data.family.{k}: {a.get(k)!r} -> {b.get(k)!r}"
    for k in sorted(set(a) | set(b))
    if k not in fingerprint.EXTENT_FIELDS and a.get(k) != b.get(k)
  ]
  if theirs.get("renderer") != ours.get("renderer"):
    fields.append(f"data.renderer: {theirs.get('renderer')!r} -> {ours.get('renderer')!r}")
  what = "; ".join(fields) or (
    f"data.fingerprint: {theirs.get('fingerprint')} -> {ours.get('fingerprint')}"
  )
  raise ConfigError(
    f"synthesis_workdir {workdir} learned its pose system on other data than this regression "
    f'reads ({what}; synthesis -> regression): "ours" must regress a pose system learned on '
    "the same data (the same family parameters apart from scene and view counts and image "
    "size, or the same prepared dataset)"
  )


def check_same_validation(workdir: str, syn_config, config) -> None:
  """Refuses a view-synthesis run on the same prepared captures dataset whose held-out views were
  carved from its training views at another k than this regression's validation views (both
  every k-th training view, `records.validation_rows`): its plateau rule read other views than
  this regression validates on, and it trained on some of those.

  Raises:
    ConfigError: naming both fractions and the flag that makes them agree.
  """
  from camrep.data import records

  if syn_config.evals.get("split", "test") != "validation" or not syn_config.data.get("dir", ""):
    return
  if sources.is_procedural(syn_config.data.source):
    return  # the family's own validation split: no carve
  theirs = float(syn_config.data.get("validation_fraction", 0.1))
  ours = float(config.data.validation_fraction)
  k_theirs, k_ours = records.validation_every(theirs), records.validation_every(ours)
  if k_theirs != k_ours:
    raise ConfigError(
      f"synthesis_workdir {workdir} held out every {k_theirs}th training "
      f"view (data.validation_fraction={theirs:g}) for its plateau rule, but this regression "
      f"validates on every {k_ours}th (data.validation_fraction="
      f"{ours:g}): pass --config.data.validation_fraction={theirs:g} so that both stages hold "
      "out the same views"
    )


def load_pose_system(workdir: str, setting: settings_lib.Setting | str) -> dict[str, Any]:
  """The frozen pose input of a view-synthesis workdir, checked against the setting (a name is
  looked up); `restore_pose_system` with no regression data to check.
  """
  return restore_pose_system(workdir, settings_lib.get(setting))


def restore_pose_system(
  workdir: str, setting: settings_lib.Setting, run=None, *, initial: bool = False
) -> dict[str, Any]:
  """The frozen pose input of a view-synthesis workdir, checked against the setting (and, given
  the regression's `run`, a `config_schema.Resolved`, against its data, held-out views and
  encoding: `check_same_data`, `check_same_validation`, `check_trained_encoding`).

  Restores the latest checkpoint with the synthesis `load_run` (which reads no data); with
  `initial`, the run's pose input as its init gave it (`Synthesizer.init_pose` of its root key),
  from its config.json and record.json alone (`restore.load_model`): no checkpoint is read. A
  workdir without checkpoints (an archive's, `camrep.comparison.archive`) gives its final pose
  system from its pose_system.npz (`restore.load_pose_file`): the final checkpoint's values.

  Returns:
    {"spec": PoseSystemSpec, "rep": pose-input params, "kind": "grid" / "mlp" / "lowdim",
     "step": restored step (`initial`: the latest checkpoint's, None without one), "workdir":
     absolute path, "digest": `params_digest` of "rep"}.

  Raises:
    ConfigError: the workdir is missing, has neither a checkpoint nor a pose_system.npz (not
      `initial`), or its setting or data differ.
  """
  from camrep.runtime import checkpoint as ckpt_lib

  workdir = os.path.abspath(workdir)
  try:
    syn_config = workdir_lib.read_config(workdir)
  except FileNotFoundError as e:
    raise ConfigError(f"synthesis_workdir: {e}") from None
  syn_setting = components.setting(syn_config)
  if syn_setting is not setting:
    raise ConfigError(
      f"synthesis_workdir {workdir} is a {syn_setting.name!r} run (data.source "
      f"{syn_config.data.source!r}); this regression's setting is {setting.name!r}"
    )
  kind = syn_config.rep.get("kind", "grid")
  if run is not None:
    check_same_data(workdir, syn_config, run.config, run.source)
    check_same_validation(workdir, syn_config, run.config)
    check_trained_encoding(workdir, run.encoding, syn_config)
  try:
    with ckpt_lib.Checkpointer(workdir, read_only=True) as ck:
      step = ck.latest_step()
  except ckpt_lib.CheckpointError:
    step = None
  # Without a checkpoint: the run's final pose system in its pose_system.npz (an archive's).
  from_file = step is None and not initial
  if from_file and not os.path.isfile(os.path.join(workdir, restore.POSE_FILE)):
    raise ConfigError(
      f"synthesis_workdir {workdir} has no checkpoint and no {restore.POSE_FILE} (train it first)"
    )
  try:
    if initial or from_file:
      _, model = restore.load_model(workdir)
    else:
      syn_run = restore.load_run(workdir)
      model, step = syn_run.model, syn_run.step
  except (FileNotFoundError, ckpt_lib.CheckpointError) as e:
    raise ConfigError(f"synthesis_workdir: {e}") from None
  if model.own_pose_system or not model.reads_pose_vectors:
    raise ConfigError(
      f"synthesis_workdir {workdir} is a {type(model).__name__} run (task "
      f"{syn_config.task!r}) whose pose input is not the setting's pose system as pose vectors; "
      "representation 'ours' reads the pose system of a decoder run (configs/gqn.py, "
      "configs/shapenet_car.py, ...)"
    )
  if initial:
    from camrep.synthesis import step as step_lib

    # Jitted as the run's own init (`step.init_fn`): the same bits (eager differs by 1e-10).
    rep = jax.jit(model.init_pose)(step_lib.root_keys(syn_config)[0])
  elif from_file:
    try:
      rep, step = restore.load_pose_file(workdir, model)
    except ValueError as e:
      raise ConfigError(f"synthesis_workdir: {e}") from None
  else:
    rep = jax.tree.map(jnp.asarray, syn_run.params["rep"])
  return {
    "spec": model.spec,
    "rep": rep,
    "kind": kind,
    "step": None if step is None else int(step),
    "workdir": workdir,
    "digest": params_digest(rep),
  }


def params_digest(params) -> str:
  """ "sha256:<hex>" of a parameter pytree's paths, dtypes, shapes and bytes: which pose system a
  regression read, comparable across machines (a system retrained elsewhere may differ)."""
  h = hashlib.sha256()
  for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
    a = np.asarray(leaf)
    h.update(f"{jax.tree_util.keystr(path)}:{a.dtype}:{a.shape};".encode())
    h.update(np.ascontiguousarray(a).tobytes())
  return "sha256:" + h.hexdigest()


def check_trained_encoding(
  workdir: str, cls: type[pose_encodings.PoseEncoding], syn_config
) -> None:
  """Refuses a view-synthesis run that did not train the encoding a representation `cls` must
  read from one (`PoseEncoding.needs_synthesis`: the learned grid, "ours", and its controls), or
  that froze its generators where `cls` needs them learned, or the reverse
  (`PoseEncoding.frozen_generators`).

  Raises:
    ConfigError: as above.
  """
  kind = syn_config.rep.get("kind", "grid")
  if not cls.needs_synthesis:
    return
  trained = cls.trained_by()
  if pose_encodings.get(kind) is not trained:
    raise ConfigError(
      f"synthesis_workdir {workdir} was trained with another pose system, rep.kind={kind!r}; "
      f'"{cls.table_name()}" needs the learned grid system (rep.kind="{trained.name}")'
    )
  frozen = bool(syn_config.rep.get("freeze_generators", False))
  if frozen != cls.frozen_generators:
    held = "held its generators at their initial values" if frozen else "learned its generators"
    want = (
      "a run with --config.rep.freeze_generators=True"
      if cls.frozen_generators
      else 'a run that learned them ("frozen_gen" regresses a run with frozen generators)'
    )
    raise ConfigError(
      f"synthesis_workdir {workdir} {held} (rep.freeze_generators={frozen}); "
      f'"{cls.table_name()}" needs {want}'
    )


def representation_params(run) -> tuple[Any, Any, dict[str, Any]]:
  """(spec, rep_params, info) of a resolved config's representation (`run`, a
  `config_schema.Resolved`; see the module docstring).

  Raises:
    ConfigError: "ours" without a learned-grid synthesis run of the same setting.
  """
  config, cls, setting = run.config, run.encoding, run.setting
  if not cls.learned:
    return None, None, {"source": "none"}
  system = None
  if config.synthesis_workdir:
    system = restore_pose_system(config.synthesis_workdir, setting, run, initial=cls.initial_state)
  if system is None and cls.needs_synthesis:
    raise ConfigError(
      f'representation "{cls.table_name()}" regresses the learned pose system of a '
      "view-synthesis run: pass --config.synthesis_workdir=DIR"
    )
  if system is not None:
    if pose_encodings.get(system["kind"]) is cls.trained_by():
      info = {k: system[k] for k in ("workdir", "step", "digest")}
      if cls.initial_state:
        # The run's step-0 pose system; "step" names its latest checkpoint (None: none there).
        info["state"] = "initial"
      return system["spec"], system["rep"], {"source": "synthesis", **info}
  spec = system["spec"] if system else setting.pose_spec()
  key = jax.random.fold_in(jax.random.key(config.seed), 1)
  info = {"source": "random_init", "note": f"frozen randomly initialised {cls.title}"}
  return spec, cls.create(setting, spec).init(key), info

"""Pose-regression runs for the paper's Tables 1 and 2 (section 4.4) on procedural or real data.

`python -m camrep.regression --config=configs/regression.py[:quick|:smoke] --workdir=DIR
[--config.setting=gqn --config.representation=ours --config.synthesis_workdir=W ...]` trains one
pose regressor (`learner`) for one (setting, representation, learning rate, seed) and
writes into DIR:

  config.json        the resolved config (per-setting sizes filled in)
  record.json        what identifies its data and pose system beyond the config
                     (`views.data_record`: the family's resolved parameters or the prepared
                     dataset's identity, their fingerprints; the pose spec of a learned
                     representation)
  metrics.jsonl      train/* every log_every_steps, eval/validation/* (with the lr-selection
                     score eval/validation/score: the validation curve) every eval_every_steps,
                     every split's at the end
  results.json       setting, representation, seed, lr, steps trained (and total_steps, the
                     cap), parameter count, data sizes, "stopping" (the stopping rule of
                     `config.stop`, whether and why it stopped early, and the validation curve
                     [[step, score], ...]) and the error summaries {"validation", "test",
                     "extra"}: per error kind (as `scoring.pose_errors` names them) the mean and
                     median over all examples ("all") and per scene id
  errors_<split>.npz per-example errors, scene ids, true and predicted poses of the test split(s)

Data (`views.make_data`), all from the setting's procedural family
(`camrep.data.sources.procedural_of`), rendered once and held in memory (prepared once as an
ArrayRecord dataset in `data.cache_dir` when set), batched by the view-synthesis pipeline:

  train       the family's "train" split minus the validation part;
  validation  held out of "train" to choose the learning rate and for nothing else: gqn the last
              `validation_fraction` of the training scenes (whole scenes, like the test), the
              other settings the last `validation_fraction` of every training scene's views by
              view id (for 7-Scenes, the end of the training trajectory);
  test        the split of the paper's protocol (`settings.<s>.test_split`): gqn "test_scenes"
              (held-out rooms; context = views 0..n_context-1 of the scene, queries = its other
              views), car / gibson / seven_scenes "test" (held-out views of the training cars,
              areas and 7-Scenes test trajectories). `evals.extra_splits` adds the other one
              (rooms "test": held-out views of training rooms, context from their training
              views; object "test_scenes": held-out cars).

Real data: with `data.source` a real source (gqn, srn_cars, gibson, seven_scenes; it must be of
`setting`) and `data.dir` a directory prepared by `camrep.data.prepare`, the views come from that
dataset with the paper's splits per dataset (`views.make_real_data`; its module docstring lists
them), decoded once and held in memory (or batch by batch with `data.stream`). results.json's
"data" then names the source, the directory, the dataset path, the test split, what each
evaluation split is, and the number of test views.

Representations (`pose_system.representation_params`): baselines need nothing more; "ours"
restores the frozen pose system of a view-synthesis workdir (`pose_system.load_pose_system`, via
`camrep.synthesis`'s `load_run`); "mlp" uses that workdir's MLP embedding when it was trained with
rep.kind="mlp", else a frozen randomly initialised MLP embedding (`MlpPoseInput`; the
supplement's MLP is trained by view synthesis). The synthesis workdir must have been trained on
the same data (`pose_system.check_same_data`: same source, same prepared directory and dataset)
and, for "ours", with the learned grid system.
`model.resnet_weights` (seven_scenes) loads a torchvision ResNet-34 state dict into the trunk
(`load_resnet_weights`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
from collections.abc import Mapping
from typing import Any

import jax
import ml_collections
import numpy as np

from camrep.data import records, sources
from camrep.regression import learner, pose_system, scoring
from camrep.regression import tables as tables_lib
from camrep.regression import targets as T
from camrep.regression import views as views_lib
from camrep.runtime import progress as progress_lib
from camrep.runtime import runconfig, stopping, writers
from camrep.runtime import workdir as workdir_lib
from camrep.runtime.runconfig import ConfigError
from camrep.synthesis import components

RESULTS_FILE = "results.json"
SPLITS = ("test", "test_scenes")


# --------------------------------------------------------------------------------------------
# Config.


def resolve_config(config: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
  """Checks the config and fills the per-setting values (a new, unlocked ConfigDict).

  Adds `data.family` (the setting's family overrides) and `evals.test_split`; sets
  `total_steps`, `data.batch_size`, `model.width` from `settings.<setting>` unless given, and
  `optax.lr` from `hparams.<setting>` unless given; checks the other hyper-parameters, which
  `learner.resolve_hparams` reads from `hparams.<setting>` where they are not given.

  Raises:
    ConfigError: unknown setting / representation / split, a non-positive size, or "ours"
      without `synthesis_workdir`.
  """
  if config.setting not in T.SETTINGS:
    raise ConfigError(f"unknown setting {config.setting!r}; choose one of {T.SETTINGS}")
  if config.representation not in T.REPRESENTATIONS:
    raise ConfigError(
      f"unknown representation {config.representation!r}; choose one of {T.REPRESENTATIONS}"
    )
  if config.representation == "ours" and not config.synthesis_workdir:
    raise ConfigError(
      'representation "ours" regresses the learned pose system of a view-synthesis run: pass '
      "--config.synthesis_workdir=DIR (a `python -m camrep.main` workdir of setting "
      f"{config.setting!r})"
    )
  check_source(config)
  c = ml_collections.ConfigDict(config.to_dict())
  s = c.settings[c.setting]
  with c.ignore_type():
    if c.total_steps is None:
      c.total_steps = s.total_steps
    if c.data.batch_size is None:
      c.data.batch_size = s.batch_size
    if c.model.width is None:
      c.model.width = s.width
  try:
    hparams = learner.resolve_hparams(c)
  except ValueError as e:
    raise ConfigError(str(e)) from None
  if c.optax.lr is None:
    with c.ignore_type():
      c.optax.lr = hparams.lr
  c.data.family = ml_collections.ConfigDict(s.family.to_dict())
  c.evals.test_split = s.test_split
  extra = [x.strip() for x in c.evals.extra_splits.split(",") if x.strip()]
  for split in [c.evals.test_split, *extra]:
    if split not in SPLITS:
      raise ConfigError(f"unknown test split {split!r}; choose from {SPLITS}")
  if c.total_steps < 1 or c.data.batch_size < 1 or c.optax.lr <= 0:
    raise ConfigError("total_steps, data.batch_size and optax.lr must be positive")
  if not 0 < c.data.validation_fraction < 1:
    raise ConfigError("data.validation_fraction must be in (0, 1)")
  try:
    rule = stopping.rule_from_config(c.get("stop"))
  except ValueError as e:
    raise ConfigError(str(e)) from None
  if rule.active and c.eval_every_steps <= 0:
    raise ConfigError(
      "stop.min_improvement > 0 checks the periodic validation: set eval_every_steps > 0"
    )
  weights = c.model.get("resnet_weights", "")
  if weights:
    if c.setting != "seven_scenes":
      raise ConfigError(
        f"model.resnet_weights initialises the 7-Scenes ResNet-34; setting {c.setting!r} has "
        "no ResNet"
      )
    if not os.path.isfile(weights):
      raise ConfigError(f"model.resnet_weights {weights} does not exist")
  return c


def check_source(config) -> None:
  """Refuses a data.source of another setting, a real source without an existing data.dir, and
  a procedural one with a data.dir.

  Raises:
    ConfigError: as above.
  """
  d = config.data
  source = d.get("source", "")
  if not source:
    if d.get("dir", ""):
      raise ConfigError(
        "data.dir is set but data.source is empty: name the prepared dataset's source "
        f"(--config.data.source={views_lib.data_source(config)} is "
        "procedural; real ones: gqn, srn_cars, gibson, seven_scenes)"
      )
    return
  try:
    setting = sources.setting_of(source)
  except ValueError as e:
    raise ConfigError(f"data.source: {e}") from None
  if setting != config.setting:
    raise ConfigError(
      f"data.source {source!r} is data of the {setting!r} setting, but setting is "
      f"{config.setting!r}: pass --config.setting={setting}"
    )
  if sources.is_procedural(source):
    if d.dir:
      raise ConfigError(f"data.source {source!r} is procedural and takes no data.dir")
    return
  if not d.dir:
    raise ConfigError(
      f"data.source {source!r} is a real dataset: prepare it with `python -m camrep.data.prepare "
      f"--source {source} --input RAW --data_dir DIR` and pass --config.data.dir=DIR"
    )
  if not os.path.isdir(d.dir):
    raise ConfigError(f"data.dir {d.dir} does not exist (data.source {source!r})")


# --------------------------------------------------------------------------------------------
# The run.


def make_regressor(config, spec, num_scenes: int) -> learner.Regressor:
  """The resolved config's `learner.Regressor`."""
  return learner.make_regressor(
    config.setting,
    config.representation,
    spec=spec,
    width=config.model.width,
    num_scenes=num_scenes,
    fc_dim=config.model.fc_dim,
    stage_sizes=tuple(config.model.resnet_stages),
    refine_steps=config.model.refine_steps,
    equalise_params=config.model.equalise_params,
    image_norm="imagenet" if config.model.get("resnet_weights", "") else "symmetric",
    hparams=learner.resolve_hparams(config),
  )


def _json_summary(summary: Mapping) -> dict[str, Any]:
  return {str(k): v for k, v in summary.items()}


def _scalars(prefix: str, summary: Mapping) -> dict[str, float]:
  return {f"{prefix}/{k}_{stat}": v[stat] for k, v in summary["all"].items() for stat in v}


def count_params(tree) -> int:
  """Number of scalars in a pytree of arrays."""
  return int(sum(np.size(x) for x in jax.tree.leaves(tree)))


@dataclasses.dataclass
class Setup:
  """What one regression run is built from: the resolved config, the frozen pose input, the
  data and the regressor."""

  config: ml_collections.ConfigDict
  spec: Any
  rep_params: Any
  rep_info: dict[str, Any]
  data: views_lib.Data
  reg: learner.Regressor


def prepare(config: ml_collections.ConfigDict, *, log=print) -> Setup:
  """Restores the pose input and renders the data of a resolved config (in that order, so that a
  bad synthesis workdir fails before minutes of rendering)."""
  t0 = time.perf_counter()
  spec, rep_params, rep_info = pose_system.representation_params(config)
  data = views_lib.make_data(config)
  t_data = time.perf_counter() - t0
  scene_max = [data.train.scenes.max(), *(e.queries.scenes.max() for e in data.evals.values())]
  reg = make_regressor(config, spec, int(max(scene_max)) + 1)
  log(
    f"{config.setting}/{config.representation} lr={config.optax.lr:g} seed={config.seed}: "
    f"{len(data.train)} training views, "
    + ", ".join(f"{k} {len(e.queries)} views" for k, e in data.evals.items())
    + f" (data {t_data:.1f}s)"
  )
  return Setup(config, spec, rep_params, rep_info, data, reg)


def load_resnet_weights(config, state: learner.RegressionState) -> learner.RegressionState:
  """The state with its ResNet trunk replaced by `config.model.resnet_weights` (a torchvision
  ResNet-34 state dict, .npz; the paper's ImageNet initialisation); fc, heads, s unchanged and
  the optimiser state re-initialised. Unchanged when the field is empty.

  Raises:
    ConfigError: the file lacks a trunk key or a shape differs from the model's (e.g. a width
      other than 1, or other `model.resnet_stages`).
  """
  from camrep.models import pose_regressor

  path = config.model.get("resnet_weights", "")
  if not path:
    return state
  variables = {"params": state.params["net"], "batch_stats": state.batch_stats}
  try:
    loaded = pose_regressor.load_torchvision_resnet34(
      path, variables=variables, stage_sizes=tuple(config.model.resnet_stages)
    )
  except (ValueError, OSError, KeyError) as e:
    raise ConfigError(
      f"model.resnet_weights {path}: {e} (torchvision ResNet-34 weights need model.width=1 "
      f"and model.resnet_stages=(3, 4, 6, 3) or a prefix of them; got width "
      f"{config.model.width:g}, stages {tuple(config.model.resnet_stages)})"
    ) from None
  params = {**state.params, "net": loaded["params"]}
  return state.replace(
    params=params, batch_stats=loaded["batch_stats"], opt_state=state.tx.init(params)
  )


def train(setup: Setup, writer, eval_sets, *, predict_fn, log=print):
  """Trains the regressor for config.total_steps; validation errors every eval_every_steps (every
  split's with `evals.periodic_all_splits`), where the stopping rule (`config.stop`,
  `stopping.check`) may end training early.

  Returns:
    (state, the last logged train/* scalars, training seconds, stopping record: {"rule",
    "stopped_early", "steps" trained, "reason", "curve": [[step, validation score], ...]}).
  """
  config = setup.config
  train_views = setup.data.train
  pipe = views_lib.train_pipeline(config, train_views)
  batches = (views_lib.learner_batch(config, train_views, b) for b in pipe.iterator())
  init_key = jax.random.fold_in(jax.random.key(config.seed), 0)
  first = views_lib.learner_batch(config, train_views, pipe.batch(0))
  state = learner.init(init_key, setup.reg, first, rep_params=setup.rep_params)
  state = load_resnet_weights(config, state)
  step_fn = jax.jit(learner.train_step, donate_argnums=0)
  total = config.total_steps
  progress = progress_lib.Progress(total, every_seconds=20.0)
  t_train = time.perf_counter()
  last: dict[str, float] = {}
  rule = stopping.rule_from_config(config.get("stop"))
  curve: list[tuple[int, float]] = []
  stop, reason = False, "reached total_steps"
  for step in range(1, total + 1):
    state, m = step_fn(state, next(batches))
    if progress_lib.itstime(step, config.log_every_steps, total):
      host = {f"train/{k}": float(v) for k, v in m.items()}
      writer.write_scalars(step, host)
      bad = [k for k, v in host.items() if not math.isfinite(v)]
      if bad:
        raise FloatingPointError(f"non-finite {', '.join(bad)} at step {step}")
      last = host
    status = progress.update(step)
    if status:
      log(f"{status} loss={float(m['loss']):.4f}")
    if step < total and progress_lib.itstime(step, config.eval_every_steps, total):
      periodic = eval_sets if config.evals.get("periodic_all_splits") else ["validation"]
      for name in periodic:
        errs = scoring.evaluate_regression(state, eval_sets[name], predict_fn=predict_fn)
        summary = scoring.summarise_errors(errs)
        writer.write_scalars(step, _scalars(f"eval/{name}", summary))
        if name == "validation":
          score = tables_lib.validation_score(config.setting, summary)
          writer.write_scalars(step, {"eval/validation/score": score})
          curve.append((step, score))
      stop, why = stopping.check(rule, curve)
      if stop:
        reason = why
        log(f"stopping early: {why}")
        break
  jax.block_until_ready(state.params)
  record = {
    "rule": dataclasses.asdict(rule),
    "stopped_early": stop,
    "steps": step,
    "reason": reason,
    "curve": [[int(s), float(v)] for s, v in curve],
  }
  return state, last, time.perf_counter() - t_train, record


def evaluate_splits(
  setup: Setup, state, writer, eval_sets, *, predict_fn, workdir: str, step: int | None = None
):
  """Errors on every evaluation split (logged at `step`, default total_steps); per-example
  errors saved as errors_<split>.npz.

  Returns:
    ({"validation": summary, test_split: summary}, {other split: summary}).
  """
  config = setup.config
  summaries, extra = {}, {}
  for name, bs in eval_sets.items():
    errs = scoring.evaluate_regression(state, bs, predict_fn=predict_fn)
    summary = scoring.summarise_errors(errs)
    setup.data.info["num_examples"][name] = len(errs["scene"])
    step = config.total_steps if step is None else step
    scalars = _scalars(f"eval/{name}", summary)
    if name == "validation":
      scalars["eval/validation/score"] = tables_lib.validation_score(config.setting, summary)
    writer.write_scalars(step, scalars)
    if name != "validation":
      names = records.scene_name_column(setup.data.info, name, errs["scene"])
      np.savez(os.path.join(workdir, f"errors_{name}.npz"), **errs, **names)
    if name in ("validation", config.evals.test_split):
      summaries[name] = _json_summary(summary)
    else:
      extra[name] = _json_summary(summary)
  return summaries, extra


def write_results(path: str, results: Mapping[str, Any]) -> None:
  """results.json, written atomically (a reader never sees half a file)."""
  with open(path + ".tmp", "w", encoding="utf-8") as f:
    json.dump(results, f, indent=1)
  os.replace(path + ".tmp", path)


def results_record(
  setup: Setup, state, last, train_seconds, eval_seconds, summaries, extra, stop=None
):
  """The content of results.json ("steps": steps trained; "stopping": the stopping record of
  `train`, its curve with the final validation score appended)."""
  config = setup.config
  steps = int(stop["steps"]) if stop else int(config.total_steps)
  out = {
    "setting": config.setting,
    "representation": config.representation,
    "seed": int(config.seed),
    "lr": float(config.optax.lr),
    "steps": steps,
    "total_steps": int(config.total_steps),
    "batch_size": int(config.data.batch_size),
    "width": float(config.model.width),
    "variant": config.variant,
    "params": count_params(state.params["net"]),
    "representation_params": setup.rep_info,
    "resnet_weights": config.model.get("resnet_weights", "") or None,
    "data": setup.data.info,
    "final_train": last,
    "train_seconds": train_seconds,
    "steps_per_sec": steps / max(train_seconds, 1e-9),
    "eval_seconds": eval_seconds,
    "validation": summaries["validation"],
    "test": summaries[config.evals.test_split],
    "extra": extra,
    "machine": workdir_lib.machine(),
  }
  if stop is not None:
    final = tables_lib.validation_score(config.setting, summaries["validation"])
    curve = [c for c in stop["curve"] if c[0] != steps] + [[steps, final]]
    out["stopping"] = {**stop, "curve": curve}
  return out


def clear_outputs(workdir: str) -> None:
  """Removes what an earlier run in `workdir` wrote (results.json, errors_*.npz): a rerun starts
  over, and a stale file would mark an unfinished run as done."""
  for name in os.listdir(workdir):
    if name == RESULTS_FILE or (name.startswith("errors_") and name.endswith(".npz")):
      os.remove(os.path.join(workdir, name))


def run(config: ml_collections.ConfigDict, workdir: str, *, log=print) -> dict[str, Any]:
  """Trains and evaluates one regressor; writes config.json, metrics.jsonl, results.json and
  errors_<split>.npz into `workdir`.

  A rerun in a workdir starts over (its results.json and errors files are removed first); when
  the workdir holds another config, only the fields named in `config.allow_changes` may differ,
  and the change is recorded in config_history.jsonl. One run per workdir at a time (a lock).

  Args:
    config: a configs/regression.py config (resolved here).
    workdir: output directory.
    log: progress printer.

  Returns:
    The results.json content.

  Raises:
    ConfigError: bad config or synthesis workdir, or a config that differs from the workdir's.
    WorkdirError: the workdir cannot be written, or another run holds it.
    FloatingPointError: the loss became non-finite.
  """
  config = resolve_config(config)
  existed = os.path.isdir(workdir)
  workdir_lib.check_workdir(workdir)
  stored = workdir_lib.read_stored_config(workdir)
  changes = {}
  if stored is not None:
    changes = runconfig.check_changes(stored, config, resumable=None, workdir=workdir, what="rerun")
  lock = workdir_lib.WorkdirLock(workdir)
  lock.acquire()
  try:
    try:
      record = {"version": 1, "data": views_lib.data_record(config)}
      setup = prepare(config, log=log)
    except BaseException:
      if not existed:
        shutil.rmtree(workdir, ignore_errors=True)  # holds nothing but the lock
      raise
    if setup.spec is not None:
      record["pose_spec"] = components.spec_record(setup.spec)
    old_record = workdir_lib.read_record(workdir) if stored is not None else None
    if old_record is not None:  # a rerun starts over: a changed record is recorded, not refused
      refused, accepted = workdir_lib.record_differences(old_record, record)
      changes.update({f"record.{k}": v for k, v in {**refused, **accepted}.items()})
    clear_outputs(workdir)
    writer = writers.MetricWriter(workdir)
    writer.truncate_after(0)
    writer.write_config(config)
    workdir_lib.write_record(workdir, record)
    workdir_lib.append_history(workdir, 0, changes, what="rerun" if stored else "start")
    predict_fn = jax.jit(learner.predict_poses)
    eval_sets = {k: views_lib.eval_batches(config, e) for k, e in setup.data.evals.items()}
    try:
      state, last, train_seconds, stop = train(
        setup, writer, eval_sets, predict_fn=predict_fn, log=log
      )
      t_eval = time.perf_counter()
      summaries, extra = evaluate_splits(
        setup, state, writer, eval_sets, predict_fn=predict_fn, workdir=workdir, step=stop["steps"]
      )
    finally:
      writer.close()
  finally:
    lock.release()
  results = results_record(
    setup, state, last, train_seconds, time.perf_counter() - t_eval, summaries, extra, stop
  )
  write_results(os.path.join(workdir, RESULTS_FILE), results)
  overall = results["test"]["all"]
  log(
    f"test ({config.evals.test_split}): "
    + ", ".join(f"{k} mean {v['mean']:.4g} median {v['median']:.4g}" for k, v in overall.items())
  )
  return results

"""Pose-regression runs for the paper's Tables 1 and 2 (section 4.4) on procedural or real data.

`python -m camrep.regression --config=configs/regression.py:SETTING[,quick|,smoke] --workdir=DIR
[--config.representation=ours --config.synthesis_workdir=W ...]` trains one
pose regressor (`learner`) for one (setting, representation, learning rate, seed) and
writes into DIR (with `--lrs` / `--seeds`, a grid of such runs trained as one program, each into
its own DIR/<lr>_seed<k>: `camrep.regression.vectorised`):

  config.json        the config (its setting's sizes and hyper-parameters)
  record.json        what identifies its data and pose system beyond the config
                     (`views.data_record`: the family's resolved parameters or the prepared
                     dataset's identity, their fingerprints; the pose spec of a learned
                     representation and the digest of the parameters it read)
  checkpoints/       the regressor's state every ckpt_every_steps (the run frame,
                     `camrep.runtime.frame`: the same command resumes from the latest; SIGTERM
                     or Ctrl-C saves one and stops), config_history.jsonl, final_metrics.json
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

The config is checked and resolved once (`config_schema.validate`: its setting, pose encoding,
data source and hyper-parameters, `config_schema.Resolved`); the run's parts take those objects.

Data (`views.make_data`), all from the setting's procedural family (the resolved data source),
rendered once and held in memory (prepared once as an ArrayRecord dataset in `data.cache_dir`
when set), batched by the view-synthesis pipeline:

  train       the family's "train" split minus the validation part;
  validation  held out of "train" to choose the learning rate and for nothing else: gqn the last
              `validation_fraction` of the training scenes (whole scenes, like the test), the
              other settings the last `validation_fraction` of every training scene's views by
              view id (for 7-Scenes, the end of the training trajectory);
  test        the split of the paper's protocol (`evals.test_split`): gqn "test_scenes" (held-out
              rooms; context = views 0..n_context-1 of the scene, queries = its other
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
restores the frozen pose system of a view-synthesis workdir (`pose_system.restore_pose_system`, via
`camrep.synthesis`'s `load_run`); "mlp" uses that workdir's MLP embedding when it was trained with
rep.kind="mlp", else a frozen randomly initialised MLP embedding (`MlpEncoding`; the
supplement's MLP is trained by view synthesis). The synthesis workdir must have been trained on
the same data (`pose_system.check_same_data`: same source, same prepared directory and dataset)
and, for "ours", with the learned grid system, and its run must be complete (`check_synthesis`:
not still training, not stopped on non-finite values or by a signal) unless
`allow_incomplete_synthesis` (then recorded in results.json).
`model.resnet_weights` (seven_scenes) loads a torchvision ResNet-34 state dict into the trunk
(`load_resnet_weights`).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import time
from collections.abc import Mapping
from typing import Any

import flax.serialization
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from typing_extensions import override

from camrep.configs import regression as regression_config
from camrep.data import records
from camrep.regression import config_schema, learner, pose_system, runs, scoring
from camrep.regression import views as views_lib
from camrep.runtime import frame as frame_lib
from camrep.runtime import session as session_lib
from camrep.runtime import workdir as workdir_lib
from camrep.runtime.runconfig import ConfigError
from camrep.synthesis import components

RESULTS_FILE = "results.json"
SPLITS = config_schema.SPLITS


# --------------------------------------------------------------------------------------------
# The run.


def make_regressor(run: config_schema.Resolved, spec, num_scenes: int) -> learner.Regressor:
  """The `learner.Regressor` of a resolved config."""
  config = run.config
  return learner.make_regressor(
    run.setting,
    run.encoding,
    spec=spec,
    width=config.model.width,
    num_scenes=num_scenes,
    fc_dim=config.model.get("fc_dim", 2048),
    stage_sizes=tuple(config.model.get("resnet_stages", ())),
    refine_steps=config.model.refine_steps,
    equalise_params=config.model.equalise_params,
    image_norm="imagenet" if config.model.get("resnet_weights", "") else "symmetric",
    hparams=run.hparams,
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
  """What one regression run is built from: the config, its batch layout, the frozen pose input,
  the data and the regressor."""

  config: ml_collections.ConfigDict
  batching: views_lib.Batching
  spec: Any
  rep_params: Any
  rep_info: dict[str, Any]
  data: views_lib.Data
  reg: learner.Regressor

  @property
  def setting(self):
    """The run's paper setting (a `camrep.settings.Setting`: the regressor's)."""
    return self.reg.setting


def prepare(run: config_schema.Resolved, *, log=print, data: views_lib.Data | None = None) -> Setup:
  """Restores the pose input and renders the data of a resolved config (`config_schema.check`;
  in that order, so that a bad synthesis workdir fails before minutes of rendering); `data`: the
  config's data, made already (runs that differ only in seed and lr share it: `vectorised`).

  Raises:
    ConfigError: as `pose_system.representation_params`, or the synthesis workdir's run is not
      complete (`synthesis_state`) and `allow_incomplete_synthesis` is not set.
  """
  config, t0 = run.config, time.perf_counter()
  spec, rep_params, rep_info = pose_system.representation_params(run)
  if rep_info.get("source") == "synthesis":
    rep_info = check_synthesis(config, rep_info, log=log)
  data = views_lib.make_data(config, run.source) if data is None else data
  t_data = time.perf_counter() - t0
  scene_max = [data.train.scenes.max(), *(e.queries.scenes.max() for e in data.evals.values())]
  reg = make_regressor(run, spec, int(max(scene_max)) + 1)
  log(
    f"{config.setting}/{config.representation} lr={config.optax.lr:g} seed={config.seed}: "
    f"{len(data.train)} training views, "
    + ", ".join(f"{k} {len(e.queries)} views" for k, e in data.evals.items())
    + f" (data {t_data:.1f}s)"
  )
  batching = views_lib.Batching.of(config, run.setting)
  return Setup(config, batching, spec, rep_params, rep_info, data, reg)


def synthesis_state(workdir: str, step: int | None = None) -> str | None:
  """None when the view-synthesis run in `workdir` is complete (at checkpoint `step`, when
  given), else what it is: still training (a live process holds its lock), stopped on non-finite
  values, or not complete (no final record, or one that says so: stopped by a signal, killed,
  or being extended). A workdir an archive restored (`camrep.comparison.archive`) has its final
  record in its run.json."""
  holder = workdir_lib.WorkdirLock(workdir).live_holder()
  if holder is not None:
    return (
      f"still training (PID {holder.get('pid')} on {holder.get('host')} holds its lock, "
      f"started {holder.get('started', '?')})"
    )
  final = session_lib.read_final(workdir)
  if final is None and os.path.isfile(os.path.join(workdir, runs.RECORD_FILE)):
    try:
      final = runs.load(workdir).final
    except runs.DamagedRun:
      final = None
  if final is None:
    return (
      f"not complete: it has no {session_lib.FINAL_FILE} (stopped by a signal, killed, or "
      "never finished)"
    )
  if final.get("stopped") == "non-finite":
    return f"stopped on non-finite values ({final.get('reason', 'see its log')})"
  if final.get("complete") is not True:
    return (
      f'not complete: its {session_lib.FINAL_FILE} says "complete": false (stopped by a signal, '
      "killed, or being extended)"
    )
  if step is not None and final.get("step") != step:
    return f"not complete at its latest checkpoint, step {step} (complete at {final.get('step')})"
  return None


def check_synthesis(config, rep_info: Mapping[str, Any], *, log=print) -> dict[str, Any]:
  """Refuses a representation read from a view-synthesis run that is not complete
  (`synthesis_state`) unless `config.allow_incomplete_synthesis`; then it is used and the
  returned info records it ("synthesis_incomplete": what the run was).

  Raises:
    ConfigError: the run is not complete and it is not allowed.
  """
  info = dict(rep_info)
  why = synthesis_state(info["workdir"], info.get("step"))
  if why is None:
    return info
  if not config.get("allow_incomplete_synthesis", False):
    raise ConfigError(
      f"synthesis_workdir {info['workdir']} is {why}: its pose system (checkpoint step "
      f"{info.get('step')}) may not be the one it ends with. Wait for it to finish (or run its "
      "command again to resume it), or pass --config.allow_incomplete_synthesis=True to regress "
      "its latest checkpoint anyway (recorded in results.json)"
    )
  log(f"warning: synthesis_workdir {info['workdir']} is {why}; used as allowed")
  info["synthesis_incomplete"] = why
  return info


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


class RegressionStage(frame_lib.Stage):
  """The regression's part of the fit loop (`runtime.frame.Stage`): its state, step over K
  batches, training batches (a pure function of (seed, step): `views.train_pipeline`), periodic
  validation (every split's with `evals.periodic_all_splits`) and its plateau score
  (eval/validation/score, `Setting.validation_score`). The final evaluation of every split is the
  run's own (`evaluate_splits`), so the periodic one does not run at total_steps."""

  eval_at_end = False
  log_rate = False
  unlogged = ("train/finite",)

  def __init__(self, setup: Setup, eval_sets=None, *, predict_fn):
    """`eval_sets`: {split: evaluation batches}; default each of the data's evaluation sets'
    (`views.eval_batches`)."""
    self.setup, self.config, self.predict_fn = setup, setup.config, predict_fn
    self.pipe = views_lib.train_pipeline(setup.batching, setup.data.train)
    if eval_sets is None:
      evals = setup.data.evals
      eval_sets = {k: views_lib.eval_batches(setup.batching, e) for k, e in evals.items()}
    self.eval_sets = eval_sets
    self.writer = None
    self._template: learner.RegressionState | None = None
    self._seconds_before, self._t0 = 0.0, time.perf_counter()

  def start(self, writer, *, train_seconds: float = 0.0) -> None:
    """Training begins: the frame's writer, and the seconds trained by earlier starts."""
    self.writer = writer
    self._seconds_before, self._t0 = float(train_seconds), time.perf_counter()

  def init(self) -> learner.RegressionState:
    """The fresh state (`learner.init` on the first batch's shapes, the ResNet weights)."""
    config = self.config
    init_key = jax.random.fold_in(jax.random.key(config.seed), 0)
    first = views_lib.learner_batch(self.setup.batching, self.setup.data.train, self.pipe.batch(0))
    state = learner.init(init_key, self.setup.reg, first, rep_params=self.setup.rep_params)
    self._template = state = load_resnet_weights(config, state)
    return state

  @override
  def saved(self, state):
    d = flax.serialization.to_state_dict(state)
    d.pop("rep_params")  # frozen, read from the synthesis workdir (its digest in record.json)
    return jax.tree.map(np.asarray, d)

  def restored(self, saved) -> learner.RegressionState:
    """A checkpoint's state dict back into the state `init` shaped."""
    full = {**flax.serialization.to_state_dict(self._template), **saved}
    state = flax.serialization.from_state_dict(self._template, full)
    return jax.tree.map(jnp.asarray, state)

  @override
  def dispatch(self, n):
    if n == 1:
      step = jax.jit(learner.train_step, donate_argnums=0)

      def one(state, batch):
        state, metrics = step(state, batch)
        return state, metrics, metrics["finite"]

      return one
    return jax.jit(learner.train_steps, donate_argnums=0)

  @override
  def chunks(self, spans):
    spans = iter(spans)
    first = next(spans, None)
    if first is None:
      return
    views, batching = self.setup.data.train, self.setup.batching
    host = self.pipe.iterator(start_step=first[0] - 1)  # step k trains on batch k - 1
    try:
      for _, n in itertools.chain([first], spans):
        bs = [views_lib.learner_batch(batching, views, next(host)) for _ in range(n)]
        yield bs[0] if n == 1 else {k: np.stack([b[k] for b in bs]) for k in bs[0]}
    finally:
      if hasattr(host, "close"):
        host.close()

  @override
  def rows(self, metrics, n):
    host = jax.device_get(metrics)
    if n == 1:
      return [{f"train/{k}": float(v) for k, v in host.items()}]
    return [{f"train/{k}": float(v[i]) for k, v in host.items()} for i in range(n)]

  @override
  def evaluate(self, state, step):
    config, out = self.config, {}
    periodic = self.eval_sets if config.evals.get("periodic_all_splits") else ["validation"]
    for name in periodic:
      errs = scoring.evaluate_regression(state, self.eval_sets[name], predict_fn=self.predict_fn)
      summary = scoring.summarise_errors(errs)
      scalars = _scalars(f"eval/{name}", summary)
      self.writer.write_scalars(step, scalars)
      out.update(scalars)
      if name == "validation":
        score = {"eval/validation/score": self.setup.setting.validation_score(summary)}
        self.writer.write_scalars(step, score)
        out.update(score)
    return out

  @override
  def score(self, row):
    return row.get("eval/validation/score")

  @override
  def extra(self, step):
    return {"train_seconds": self.train_seconds()}

  def train_seconds(self) -> float:
    """Seconds trained, over every start of the run."""
    return self._seconds_before + time.perf_counter() - self._t0


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
      scalars["eval/validation/score"] = setup.setting.validation_score(summary)
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
    final = setup.setting.validation_score(summaries["validation"])
    curve = [c for c in stop["curve"] if c[0] != steps] + [[steps, final]]
    out["stopping"] = {**stop, "curve": curve}
  return out


def restored_results(workdir: str, config, *, log=print) -> dict[str, Any] | None:
  """The results of the finished run an archive restored into `workdir` (`runs.restored`: its
  run.json alone), said by `log`: nothing to train; None without one.

  Raises:
    ConfigError: the record there is another run's (setting, representation, lr or seed), or
      cannot be read.
  """
  try:
    archived = runs.restored(workdir, config.to_dict())
  except ValueError as e:  # runs.DamagedRun too
    raise ConfigError(str(e)) from None
  if archived is None:
    return None
  log(
    f"{workdir} holds a finished run restored from an archive ({runs.RECORD_FILE}); nothing to do"
  )
  return archived.results


def check_stored_layout(workdir: str) -> None:
  """Refuses a workdir whose config.json has the old layout (`configs.regression.check_layout`).

  Raises:
    ConfigError: it has.
  """
  stored = workdir_lib.read_stored_config(workdir) if os.path.isdir(workdir) else None
  if stored is not None:
    try:
      regression_config.check_layout(stored)
    except ValueError as e:
      raise ConfigError(f"{workdir}: {e}") from None


def read_results(workdir: str) -> dict[str, Any] | None:
  """The workdir's results.json content, or None without one."""
  path = os.path.join(workdir, RESULTS_FILE)
  if not os.path.exists(path):
    return None
  with open(path, encoding="utf-8") as f:
    return json.load(f)


def data_record(config, source) -> dict[str, Any]:
  """record.json's data part of a run reading `source` (`sources.Source`): {"version", "data":
  `views.data_record`}; a captures dataset's, whose validation split interleaves
  (`views.split_validation`), is version 2 with "validation": "interleaved" (version 1: the last
  10% of each capture's views)."""
  record = {"version": 1, "data": views_lib.data_record(config, source)}
  if not source.procedural and views_lib.interleaved_validation(views_lib.open_dataset(config)[1]):
    record = {**record, "version": 2, "validation": "interleaved"}
  return record


def check_validation_record(workdir: str, record: Mapping[str, Any]) -> None:
  """Refuses to resume a capture run (`record`: this start's `data_record`, version 2) whose
  record.json (version 1) predates the interleaved validation split: its validation errors, and
  so its stopping and its lr's selection, read the last 10% of each capture's views.

  Raises:
    ConfigError: naming the way out.
  """
  old = workdir_lib.read_record(workdir)
  if record.get("version") == 2 and old is not None and old.get("version") == 1:
    raise ConfigError(
      f"cannot resume in {workdir}: it was trained with the old validation split of a capture "
      "(the last 10% of each capture's views, extrapolated), and validation is now every k-th "
      "training view (interleaved as the test views are): its stopping and lr selection read "
      "the old split. Train it again in a new --workdir (or move this one aside); its finished "
      'results keep their meaning, named by results.json "data.validation"'
    )


def pose_record(setup: Setup) -> dict[str, Any]:
  """What record.json holds of a run's pose system: its spec (learned representations) and the
  digest of the parameters it read (a resume must read the same ones)."""
  record = {}
  if setup.spec is not None:
    record["pose_spec"] = components.spec_record(setup.spec)
  if "digest" in setup.rep_info:
    record["representation"] = {"digest": setup.rep_info["digest"]}
  return record


def clear_outputs(workdir: str) -> None:
  """Removes what an earlier run in `workdir` wrote (results.json, errors_*.npz), before a run
  starts at step 0 in it: a stale file would mark an unfinished run as done."""
  for name in os.listdir(workdir):
    if name == RESULTS_FILE or (name.startswith("errors_") and name.endswith(".npz")):
      os.remove(os.path.join(workdir, name))


def complete(
  frame: frame_lib.Frame,
  stage: RegressionStage,
  fit: frame_lib.FitResult,
  eval_sets,
  *,
  predict_fn,
  rule,
  grid: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
  """The outputs of a run whose fit is complete: every split's errors (`evaluate_splits`),
  results.json (with `grid`, the group it was trained in, when given) and final_metrics.json.

  Returns:
    The results.json content.
  """
  setup, workdir, state = stage.setup, frame.workdir, fit.state
  jax.block_until_ready(state.params)
  train_seconds = stage.train_seconds()
  last = {k: v for k, v in fit.last.items() if k.startswith("train/")}
  if not last:  # nothing logged since the restored step: the run's last train scalars
    last = {k: v for k, v in session_lib.last_logged(workdir).items() if k.startswith("train/")}
  record = fit.stopping_record(rule, setup.config.total_steps)
  stop = {k: record[k] for k in ("rule", "stopped_early", "steps", "reason", "curve")}
  t_eval = time.perf_counter()
  summaries, extra = evaluate_splits(
    setup, state, frame.writer, eval_sets, predict_fn=predict_fn, workdir=workdir, step=fit.step
  )
  results = results_record(
    setup, state, last, train_seconds, time.perf_counter() - t_eval, summaries, extra, stop
  )
  if grid is not None:
    results["grid"] = dict(grid)
  write_results(os.path.join(workdir, RESULTS_FILE), results)
  # The stop in final_metrics.json too, where `Frame.already_complete` reads it: a run stopped at
  # its plateau is complete, and the same command does nothing.
  frame.finish(fit.step, {**last, "results": RESULTS_FILE, "stopping": stop})
  return results


def run(config: ml_collections.ConfigDict, workdir: str, *, log=print) -> dict[str, Any] | None:
  """Trains and evaluates one regressor in the run frame (`runtime.frame`); writes config.json,
  metrics.jsonl, checkpoints/, results.json, errors_<split>.npz and final_metrics.json into
  `workdir`.

  A rerun of the same config resumes from the workdir's latest checkpoint (a complete run:
  nothing to do, its results.json returned; a finished run an archive restored, `runs.restored`:
  nothing to do, its record's results returned). When the workdir holds another config, only the
  fields named in `config.allow_changes` may differ: a change of a field that may change on
  resume (`config_schema.SCHEMA`: durations, cadences, evaluations, the stopping rule) resumes,
  any other starts the run over (its checkpoints, results.json and errors files removed first);
  either is recorded in config_history.jsonl. One run per workdir at a time (a lock). SIGTERM or
  Ctrl-C saves a checkpoint and stops (returns None); the same command resumes.

  Args:
    config: a configs/regression.py config (checked here: `config_schema.validate`).
    workdir: output directory.
    log: progress printer.

  Returns:
    The results.json content, or None when a signal stopped the run.

  Raises:
    ConfigError: bad config or synthesis workdir, or a config that differs from the workdir's.
    WorkdirError: the workdir cannot be written, or another run holds it.
    FloatingPointError: the loss became non-finite (the last checkpoint is kept).
  """
  run = config_schema.validate(config)  # the stage's checks; the names resolved once
  if (archived := restored_results(workdir, config, log=log)) is not None:
    return archived
  check_stored_layout(workdir)
  rule = frame_lib.stopping_rule(config)
  with frame_lib.Frame(
    workdir, config, schema=config_schema.SCHEMA, log=log, restart=True, outputs=clear_outputs
  ) as frame:
    if frame.already_complete(rule) is not None and (done := read_results(workdir)) is not None:
      return done
    record = data_record(config, run.source)
    check_validation_record(workdir, record)
    setup = prepare(run, log=log)
    frame.check_record({**record, **pose_record(setup)})
    predict_fn = jax.jit(learner.predict_poses)
    stage = RegressionStage(setup, predict_fn=predict_fn)
    state, start = frame.restore_or_init(stage.init, saved=stage.saved, restored=stage.restored)
    frame.begin(start)
    stage.start(frame.writer, train_seconds=frame.extra.get("train_seconds", 0.0))
    fit = frame_lib.fit(frame, stage, state, start, rule=rule, progress_every=20.0)
    if not fit.complete:
      return None
    results = complete(frame, stage, fit, stage.eval_sets, predict_fn=predict_fn, rule=rule)
  overall = results["test"]["all"]
  log(
    f"test ({config.evals.test_split}): "
    + ", ".join(f"{k} mean {v['mean']:.4g} median {v['median']:.4g}" for k, v in overall.items())
  )
  return results

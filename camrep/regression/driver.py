"""Pose-regression runs for the paper's Tables 1 and 2 (section 4.4) on procedural data.

`python -m camrep.regression --config=configs/regression.py[:quick|:smoke] --workdir=DIR
[--config.setting=gqn --config.representation=ours --config.synthesis_workdir=W ...]` trains one
pose regressor (`learner`) for one (setting, representation, learning rate, seed) and
writes into DIR:

  config.json        the resolved config (per-setting sizes filled in)
  metrics.jsonl      train/* every log_every_steps, eval/validation/* and eval/test/* at the end
  results.json       setting, representation, seed, lr, steps, parameter count, data sizes and
                     the error summaries {"validation", "test", "extra"}: per error kind (as
                     `learner.pose_errors` names them) the mean and median over all examples
                     ("all") and per scene id
  errors_<split>.npz per-example errors, scene ids, true and predicted poses of the test split(s)

Data (`make_data`), all from the setting's procedural family (`SOURCE_OF_SETTING`), rendered
once and held in memory (cached in `data.cache_dir` when set):

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

Representations: baselines need nothing more; "ours" restores the frozen pose system of a
view-synthesis workdir (`load_pose_system`, via `camrep.synthesis`'s `load_run`); "mlp" uses that
workdir's MLP embedding when it was trained with rep.kind="mlp", else a frozen randomly
initialised MLP embedding (`targets.init_mlp`; the supplement's MLP is trained by view synthesis).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from collections.abc import Iterator, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from camrep.regression import learner
from camrep.regression import targets as T
from camrep.runtime import writers

SOURCE_OF_SETTING = {"gqn": "rooms", "car": "object", "gibson": "area", "seven_scenes": "scene6dof"}
RESULTS_FILE = "results.json"
SPLITS = ("test", "test_scenes")


class ConfigError(ValueError):
  """The config asks for something impossible (unknown names, missing synthesis workdir)."""


# --------------------------------------------------------------------------------------------
# Config.


def resolve_config(config: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
  """Checks the config and fills the per-setting values (a new, unlocked ConfigDict).

  Adds `data.family` (the setting's family overrides) and `evals.test_split`; sets
  `total_steps`, `data.batch_size`, `model.width` from `settings.<setting>` unless given, and
  `optax.lr` from `targets.DEFAULTS` unless given.

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
  c = ml_collections.ConfigDict(config.to_dict())
  s = c.settings[c.setting]
  with c.ignore_type():
    if c.total_steps is None:
      c.total_steps = s.total_steps
    if c.data.batch_size is None:
      c.data.batch_size = s.batch_size
    if c.model.width is None:
      c.model.width = s.width
    if c.optax.lr is None:
      c.optax.lr = T.defaults(c.setting, c.representation).lr
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
  return c


# --------------------------------------------------------------------------------------------
# Data.


@dataclasses.dataclass
class ViewSet:
  """Views held in memory, N of them.

  Attributes:
    images: (N, H, W, 3) uint8.
    poses: (N, P) float32, in the setting's pose columns.
    scenes: (N,) int64 scene ids.
    views: (N,) int64 view ids within the scene.
  """

  images: np.ndarray
  poses: np.ndarray
  scenes: np.ndarray
  views: np.ndarray

  def __len__(self) -> int:
    return len(self.scenes)

  def subset(self, rows: np.ndarray) -> ViewSet:
    """The views at `rows` (int indices or a boolean mask)."""
    return ViewSet(self.images[rows], self.poses[rows], self.scenes[rows], self.views[rows])

  def scene_ids(self) -> np.ndarray:
    """Sorted distinct scene ids."""
    return np.unique(self.scenes)

  def scene_rows(self, scene: int) -> np.ndarray:
    """Rows of one scene, sorted by view id."""
    rows = np.flatnonzero(self.scenes == scene)
    return rows[np.argsort(self.views[rows], kind="stable")]


def _family_key(family, split: str) -> str:
  text = f"{family.name}|{split}|{family.config!r}"
  return hashlib.sha256(text.encode()).hexdigest()[:16]


def load_split(family, split: str, *, cache_dir: str = "") -> ViewSet:
  """Renders (or reads from `cache_dir`) one split of a procedural family.

  The cache file `<cache_dir>/<family>_<split>_<hash of the family config>.npz` is written
  atomically, so concurrent or interrupted runs never read a partial file.
  """
  from camrep.data import pipeline

  path = ""
  if cache_dir:
    path = os.path.join(cache_dir, f"{family.name}_{split}_{_family_key(family, split)}.npz")
    if os.path.exists(path):
      with np.load(path) as z:
        return ViewSet(z["images"], z["poses"], z["scenes"], z["views"])
  index, images = pipeline.views_in_memory(family, split)
  views = ViewSet(images, index.pose.astype(np.float32), index.scene, index.view)
  if path:
    os.makedirs(cache_dir, exist_ok=True)
    tmp = f"{path}.{os.getpid()}.tmp.npz"
    np.savez(tmp, **dataclasses.asdict(views))
    os.replace(tmp, path)
  return views


def split_validation(setting: str, views: ViewSet, fraction: float) -> tuple[ViewSet, ViewSet]:
  """(train, validation) parts of the training split (see the module docstring).

  gqn: the last ceil(fraction * n_scenes) scenes by id; the others: per scene the last
  ceil(fraction * n_views) views by view id (at least one view stays in training).
  """
  val = np.zeros(len(views), bool)
  ids = views.scene_ids()
  if setting == "gqn":
    k = max(1, math.ceil(fraction * len(ids)))
    if k >= len(ids):
      raise ConfigError(f"validation would take all {len(ids)} training scenes")
    val = np.isin(views.scenes, ids[-k:])
  else:
    for s in ids:
      rows = views.scene_rows(s)
      k = min(max(1, math.ceil(fraction * len(rows))), len(rows) - 1)
      val[rows[len(rows) - k :]] = True
  return views.subset(~val), views.subset(val)


@dataclasses.dataclass
class EvalSet:
  """Query views to regress and, for gqn, where each scene's context views come from.

  Attributes:
    queries: the views whose poses are regressed.
    context: gqn: the views holding each scene's first n_context (context) views; the queries
      exclude them when `context is queries`. None for the other settings.
  """

  queries: ViewSet
  context: ViewSet | None = None


@dataclasses.dataclass
class Data:
  """Everything a run reads: train views, evaluation sets, and facts for results.json."""

  train: ViewSet
  evals: dict[str, EvalSet]
  info: dict[str, Any]


def make_family(config):
  """The config's procedural family (`camrep.data.procedural.make_family`)."""
  from camrep.data import procedural

  overrides = config.data.family.to_dict()
  overrides = {k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}
  return procedural.make_family(
    SOURCE_OF_SETTING[config.setting], preset=config.data.preset, **overrides
  )


def make_data(config) -> Data:
  """Train, validation and test sets of a resolved config (see the module docstring)."""
  setting, cache = config.setting, config.data.cache_dir
  family = make_family(config)
  full_train = load_split(family, "train", cache_dir=cache)
  train, val = split_validation(setting, full_train, config.data.validation_fraction)
  gqn = setting == "gqn"
  evals = {"validation": EvalSet(val, val if gqn else None)}
  extra = [x.strip() for x in config.evals.extra_splits.split(",") if x.strip()]
  for name in [config.evals.test_split, *extra]:
    if name not in family.splits:
      raise ConfigError(f"family {family.name!r} has no split {name!r}; it has {family.splits}")
    views = load_split(family, name, cache_dir=cache)
    if gqn:
      # Held-out scenes bring their own context; held-out views use their scene's training views.
      evals[name] = EvalSet(views, views if name == "test_scenes" else full_train)
    else:
      evals[name] = EvalSet(views)
  if gqn:
    for name, e in evals.items():
      ctx_counts = [len(e.context.scene_rows(s)) for s in e.queries.scene_ids()]
      need = config.data.n_context + (1 if e.context is e.queries else 0)
      if min(ctx_counts) < need:
        raise ConfigError(f"{name}: a scene has {min(ctx_counts)} views, {need} needed")
    if config.data.n_context + config.data.n_query > min(
      len(train.scene_rows(s)) for s in train.scene_ids()
    ):
      raise ConfigError("a training scene has fewer than n_context + n_query views")
  info = {
    "family": family.name,
    "preset": config.data.preset,
    "family_overrides": config.data.family.to_dict(),
    "image_size": int(full_train.images.shape[1]),
    "train_views": len(train),
    "train_scenes": len(train.scene_ids()),
    "validation": (
      f"last {config.data.validation_fraction:g} of the training scenes"
      if gqn
      else f"last {config.data.validation_fraction:g} of each training scene's views"
    ),
    "test_split": config.evals.test_split,
    "num_examples": {},
  }
  if family.name == "scene6dof":
    info["scene_names"] = {str(i): family.scene_name(i) for i in range(len(family.config.scenes))}
  return Data(train, evals, info)


def train_batches(config, views: ViewSet) -> Iterator[dict[str, np.ndarray]]:
  """Endless training batches in `learner`'s layout, a pure function of (seed, step).

  gqn: per step `batch_size` distinct scenes (epoch permutations), each with n_context + n_query
  distinct random views, the first n_context the context: "context_image" (S, V, H, W, 3),
  "context_pose" (S, V, P), "image" (S, Q, H, W, 3), "pose" (S, Q, P), "scene" (S,). Others:
  `batch_size` distinct views (epoch permutations of all training views): "image" (B, H, W, 3),
  "pose" (B, P), "scene" (B,).
  """
  bs, seed = config.data.batch_size, config.seed
  if config.setting == "gqn":
    ids = views.scene_ids()
    rows = [views.scene_rows(s) for s in ids]
    c, q = config.data.n_context, config.data.n_query
    per_epoch = len(ids) // bs
    if per_epoch == 0:
      raise ConfigError(f"batch of {bs} scenes but only {len(ids)} training scenes")
    step = 0
    while True:
      epoch, pos = divmod(step, per_epoch)
      order = np.random.default_rng([seed, 0, epoch]).permutation(len(ids))[
        pos * bs : (pos + 1) * bs
      ]
      rng = np.random.default_rng([seed, 1, step])
      picked = np.stack([rng.choice(rows[i], c + q, replace=False) for i in order])
      yield {
        "context_image": views.images[picked[:, :c]],
        "context_pose": views.poses[picked[:, :c]],
        "image": views.images[picked[:, c:]],
        "pose": views.poses[picked[:, c:]],
        "scene": ids[order].astype(np.int32),
      }
      step += 1
  n = len(views)
  per_epoch = n // bs
  if per_epoch == 0:
    raise ConfigError(f"batch of {bs} images but only {n} training views")
  step = 0
  while True:
    epoch, pos = divmod(step, per_epoch)
    rows = np.random.default_rng([seed, 0, epoch]).permutation(n)[pos * bs : (pos + 1) * bs]
    yield {
      "image": views.images[rows],
      "pose": views.poses[rows],
      "scene": views.scenes[rows].astype(np.int32),
    }
    step += 1


def _pad(x: np.ndarray, n: int) -> np.ndarray:
  """Pads axis 0 to n by repeating the last entry."""
  if len(x) == n:
    return x
  return np.concatenate([x, np.repeat(x[-1:], n - len(x), axis=0)])


def eval_batches(config, eval_set: EvalSet) -> list[dict[str, np.ndarray]]:
  """Fixed-shape evaluation batches with a "mask" (False for padding).

  gqn: per scene, context = the first n_context views (by id) of `eval_set.context`; queries =
  the scene's query views (minus the context views when both are the same set), padded to the
  largest count; `max(1, batch_size // Q)` scenes per batch. Others: `batch_size` views a batch.
  """
  q_views, bs = eval_set.queries, config.evals.batch_size
  out = []
  if config.setting != "gqn":
    for start in range(0, len(q_views), bs):
      rows = np.arange(start, min(start + bs, len(q_views)))
      mask = np.arange(bs) < len(rows)
      rows = _pad(rows, bs)
      out.append(
        {
          "image": q_views.images[rows],
          "pose": q_views.poses[rows],
          "scene": q_views.scenes[rows].astype(np.int32),
          "mask": mask,
        }
      )
    return out
  c = config.data.n_context
  same = eval_set.context is q_views
  ctx_rows, query_rows = [], []
  for s in q_views.scene_ids():
    ctx_all = eval_set.context.scene_rows(s)
    ctx_rows.append(ctx_all[:c])
    qr = q_views.scene_rows(s)
    query_rows.append(qr[c:] if same else qr)
  n_q = max(len(r) for r in query_rows)
  per_batch = max(1, bs // n_q)
  for start in range(0, len(ctx_rows), per_batch):
    chunk = list(range(start, min(start + per_batch, len(ctx_rows))))
    qr = np.stack([_pad(query_rows[i], n_q) for i in chunk])
    qmask = np.stack([np.arange(n_q) < len(query_rows[i]) for i in chunk])
    cr = np.stack([ctx_rows[i] for i in chunk])
    n_real = len(chunk)
    qr, cr = _pad(qr, per_batch), _pad(cr, per_batch)
    qmask = np.concatenate([qmask, np.zeros((per_batch - n_real, n_q), bool)])
    ctx = eval_set.context
    out.append(
      {
        "context_image": ctx.images[cr],
        "context_pose": ctx.poses[cr],
        "image": q_views.images[qr],
        "pose": q_views.poses[qr],
        "scene": q_views.scenes[qr[:, 0]].astype(np.int32),
        "mask": qmask,
      }
    )
  return out


# --------------------------------------------------------------------------------------------
# The frozen representation.


def load_pose_system(workdir: str, setting: str, *, cache_dir: str = "") -> dict[str, Any]:
  """The frozen pose input of a view-synthesis workdir, checked against the setting.

  Restores the latest checkpoint with the synthesis `load_run`; with `cache_dir`, the pose
  parameters are also saved there (keyed by the workdir's path and checkpoint step), so later
  runs skip load_run's data rendering.

  Returns:
    {"spec": PoseSystemSpec, "rep": pose-input params, "kind": "grid" / "mlp" / "lowdim",
     "step": restored step, "workdir": absolute path}.

  Raises:
    ConfigError: the workdir is missing, has no checkpoint, or its setting differs.
  """
  import flax.serialization

  from camrep.runtime import checkpoint as ckpt_lib
  from camrep.synthesis import evaluate, train

  workdir = os.path.abspath(workdir)
  try:
    syn_config = evaluate.read_config(workdir)
  except FileNotFoundError as e:
    raise ConfigError(f"synthesis_workdir: {e}") from None
  syn_setting = train.setting(syn_config)
  if syn_setting != setting:
    raise ConfigError(
      f"synthesis_workdir {workdir} is a {syn_setting!r} run (data.source "
      f"{syn_config.data.source!r}); this regression's setting is {setting!r}"
    )
  kind = syn_config.rep.get("kind", "grid")
  spec = train.pose_spec(syn_config)
  try:
    with ckpt_lib.Checkpointer(workdir, read_only=True) as ck:
      step = ck.latest_step()
  except ckpt_lib.CheckpointError:
    step = None
  if step is None:
    raise ConfigError(f"synthesis_workdir {workdir} has no checkpoint (train it first)")
  path = ""
  if cache_dir:
    key = hashlib.sha256(f"{workdir}|{step}".encode()).hexdigest()[:16]
    path = os.path.join(cache_dir, f"pose_system_{key}.msgpack")
  if path and os.path.exists(path):
    with open(path, "rb") as f:
      rep = flax.serialization.msgpack_restore(f.read())
  else:
    try:
      run = evaluate.load_run(workdir)
    except (FileNotFoundError, ckpt_lib.CheckpointError) as e:
      raise ConfigError(f"synthesis_workdir: {e}") from None
    rep, step = jax.tree.map(np.asarray, run.params["rep"]), run.step
    if path:
      os.makedirs(cache_dir, exist_ok=True)
      with open(path + ".tmp", "wb") as f:
        f.write(flax.serialization.msgpack_serialize(rep))
      os.replace(path + ".tmp", path)
  rep = jax.tree.map(jnp.asarray, rep)
  return {"spec": spec, "rep": rep, "kind": kind, "step": int(step), "workdir": workdir}


def representation_params(config) -> tuple[Any, Any, dict[str, Any]]:
  """(spec, rep_params, info) of the config's representation (see the module docstring).

  Raises:
    ConfigError: "ours" without a learned-grid synthesis run of the same setting.
  """
  rep = config.representation
  if rep not in T.LEARNED:
    return None, None, {"source": "none"}
  system = None
  if config.synthesis_workdir:
    system = load_pose_system(
      config.synthesis_workdir, config.setting, cache_dir=config.data.cache_dir
    )
  if rep == "ours":
    if system["kind"] != "grid":
      raise ConfigError(
        f"synthesis_workdir {system['workdir']} was trained with rep.kind={system['kind']!r}; "
        '"ours" needs the learned grid system (rep.kind="grid")'
      )
    info = {"source": "synthesis", "workdir": system["workdir"], "step": system["step"]}
    return system["spec"], system["rep"], info
  spec = system["spec"] if system else T.default_spec(config.setting)
  if system and system["kind"] == "mlp":
    info = {"source": "synthesis", "workdir": system["workdir"], "step": system["step"]}
    return spec, system["rep"], info
  key = jax.random.fold_in(jax.random.key(config.seed), 1)
  info = {"source": "random_init", "note": "frozen randomly initialised MLP embedding"}
  return spec, T.init_mlp(key, spec), info


# --------------------------------------------------------------------------------------------
# The run.


def make_regressor(config, spec, num_scenes: int) -> learner.Regressor:
  """The resolved config's `learner.Regressor` (lr from config.optax.lr)."""
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
    lr=config.optax.lr,
  )


def _json_summary(summary: Mapping) -> dict[str, Any]:
  return {str(k): v for k, v in summary.items()}


def _scalars(prefix: str, summary: Mapping) -> dict[str, float]:
  return {f"{prefix}/{k}_{stat}": v[stat] for k, v in summary["all"].items() for stat in v}


def count_params(tree) -> int:
  """Number of scalars in a pytree of arrays."""
  return int(sum(np.size(x) for x in jax.tree.leaves(tree)))


def run(config: ml_collections.ConfigDict, workdir: str, *, log=print) -> dict[str, Any]:
  """Trains and evaluates one regressor; writes config.json, metrics.jsonl, results.json and
  errors_<split>.npz into `workdir` (an existing results.json is overwritten).

  Args:
    config: a configs/regression.py config (resolved here).
    workdir: output directory.
    log: progress printer.

  Returns:
    The results.json content.

  Raises:
    ConfigError: bad config or synthesis workdir.
    FloatingPointError: the loss became non-finite.
  """
  from camrep.synthesis import train as train_lib

  config = resolve_config(config)
  train_lib.check_workdir(workdir)
  path = os.path.join(workdir, RESULTS_FILE)
  if os.path.exists(path):  # a rerun: a stale file would mark an unfinished run as done
    os.remove(path)
  t0 = time.perf_counter()
  spec, rep_params, rep_info = representation_params(config)
  data = make_data(config)
  t_data = time.perf_counter() - t0
  num_scenes = (
    int(max(data.train.scenes.max(), *(e.queries.scenes.max() for e in data.evals.values()))) + 1
  )
  reg = make_regressor(config, spec, num_scenes)
  log(
    f"{config.setting}/{config.representation} lr={config.optax.lr:g} seed={config.seed}: "
    f"{len(data.train)} training views, "
    + ", ".join(f"{k} {len(e.queries)} views" for k, e in data.evals.items())
    + f" (data {t_data:.1f}s)"
  )

  writer = writers.MetricWriter(workdir)
  writer.truncate_after(0)
  writer.write_config(config)
  batches = train_batches(config, data.train)
  init_key = jax.random.fold_in(jax.random.key(config.seed), 0)
  first = next(train_batches(config, data.train))
  state = learner.init(init_key, reg, first, rep_params=rep_params)
  n_params = count_params(state.params["net"])
  step_fn = jax.jit(learner.train_step, donate_argnums=0)
  predict_fn = jax.jit(learner.predict_poses)
  eval_sets = {k: eval_batches(config, e) for k, e in data.evals.items()}
  total = config.total_steps
  progress = writers.Progress(total, every_seconds=20.0)
  t_train = time.perf_counter()
  last: dict[str, float] = {}
  try:
    for step in range(1, total + 1):
      state, m = step_fn(state, next(batches))
      if writers.itstime(step, config.log_every_steps, total):
        host = {f"train/{k}": float(v) for k, v in m.items()}
        writer.write_scalars(step, host)
        bad = [k for k, v in host.items() if not math.isfinite(v)]
        if bad:
          raise FloatingPointError(f"non-finite {', '.join(bad)} at step {step}")
        last = host
      status = progress.update(step)
      if status:
        log(f"{status} loss={float(m['loss']):.4f}")
      if step < total and writers.itstime(step, config.eval_every_steps, total):
        errs = learner.evaluate_regression(state, eval_sets["validation"], predict_fn=predict_fn)
        writer.write_scalars(step, _scalars("eval/validation", learner.summarise_errors(errs)))
    jax.block_until_ready(state.params)
    train_seconds = time.perf_counter() - t_train
    t_eval = time.perf_counter()
    summaries, extra = {}, {}
    for name, bs in eval_sets.items():
      errs = learner.evaluate_regression(state, bs, predict_fn=predict_fn)
      summary = learner.summarise_errors(errs)
      data.info["num_examples"][name] = len(errs["scene"])
      writer.write_scalars(total, _scalars(f"eval/{name}", summary))
      if name != "validation":
        np.savez(os.path.join(workdir, f"errors_{name}.npz"), **errs)
      if name in ("validation", config.evals.test_split):
        summaries[name] = _json_summary(summary)
      else:
        extra[name] = _json_summary(summary)
  finally:
    writer.close()
  results = {
    "setting": config.setting,
    "representation": config.representation,
    "seed": int(config.seed),
    "lr": float(config.optax.lr),
    "steps": int(total),
    "batch_size": int(config.data.batch_size),
    "width": float(config.model.width),
    "variant": config.variant,
    "params": n_params,
    "representation_params": rep_info,
    "data": data.info,
    "final_train": last,
    "train_seconds": train_seconds,
    "steps_per_sec": total / max(train_seconds, 1e-9),
    "eval_seconds": time.perf_counter() - t_eval,
    "validation": summaries["validation"],
    "test": summaries[config.evals.test_split],
    "extra": extra,
  }
  with open(path + ".tmp", "w", encoding="utf-8") as f:
    json.dump(results, f, indent=1)
  os.replace(path + ".tmp", path)
  overall = results["test"]["all"]
  log(
    "test ("
    + config.evals.test_split
    + "): "
    + ", ".join(f"{k} mean {v['mean']:.4g} median {v['median']:.4g}" for k, v in overall.items())
  )
  return results

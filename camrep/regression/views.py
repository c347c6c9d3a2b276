"""The posed images a regression run learns from and is scored on (paper section 4.4): the
setting's procedural family rendered once into memory (cached on disk when asked), split into
train / validation / test, and batched for the learner.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
from collections.abc import Iterator
from typing import Any

import jax
import numpy as np

from camrep.data import records
from camrep.runtime.runconfig import ConfigError

Array = jax.Array


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
    records.SOURCE_OF_SETTING[config.setting], preset=config.data.preset, **overrides
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

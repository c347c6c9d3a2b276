"""Pose regression for the paper's Tables 1 and 2 (sections 4.2 and 5.4, and the supplement).

One run trains one pose regressor for one (setting, representation, learning rate, seed) on the
setting's procedural family (gqn: rooms, car: object, gibson: area, seven_scenes: scene6dof) or
on a prepared real dataset (`data.source`, `data.dir`),
picks nothing itself, and writes results.json (validation and test errors) for
`experiments/table1.py` / `table2.py`, which choose the learning rate on the validation errors.
"ours" (and "mlp" when the run has one) takes its targets from a view-synthesis workdir.

One config per setting, derived from one base: the config argument names the setting and the
size, comma-separated in either order (`:car`, `:gqn,quick`, `:quick` = `:car,quick`; a setting
registered in `camrep.settings` without its own recipe here gets the base one). A run's config
holds its setting's sizes, data family, learning rate and test split, and in `hparams` the
loss, weighting and optimiser of its learned representations (`ours`) and what every baseline
changes from that (`baselines`); the top-level `loss.*`, `optax.weight_decay`,
`model.extra_fc` and `model.quantisation` override those when set (None: the table's value,
read by `camrep.regression.learner.resolve_hparams`). The setting is the argument's: an
override `--config.setting=...` is refused.

  python -m camrep.regression --config=configs/regression.py:car --workdir=/tmp/reg_car_ours \
      --config.representation=ours --config.synthesis_workdir=/tmp/car
    paper size (GPU): car 108k steps of 200 images at lr 1e-3 (~3 h on one GPU at a guess);
    gqn 100k steps of 30 scenes x (6 + 3) views, lr 1e-4; gibson 25k steps of 200 images, lr
    1e-3; seven_scenes ResNet-34 from scratch (ImageNet weights with
    --config.model.resnet_weights=PATH), 24k steps of 64 images (60 epochs), lr 5e-5.
    Expected (paper Table 1, real data): car ours 2.85 deg (q 4.28, log q 5.35, Euler 7.75,
    sin/cos 7.29, axis-angle 11.29, MLP 3.63); GQN ours x, y 0.053, yaw 4.07 deg; Gibson ours
    0.021 m, 0.020 m, 0.87 deg; Table 2 (7-Scenes, medians) ours 0.21 m, 7.92 deg on average.
  python -m camrep.regression --config=configs/regression.py:car,quick --workdir=/tmp/reg_q \
      --config.representation=quat [--config.optax.lr=3e-3 --config.seed=1]
    ~1-1.5 minutes on 2 CPU cores once the data is cached (a few thousand 64 px images,
    rendered once, ~30 s, into --config.data.cache_dir), eighth-width networks, 1500 steps of
    32 images (gqn: 600 steps of 4 scenes x (6 + 4) views, ~1.5 minutes). Baselines get as
    many parameters as ours (model.equalise_params). Measured in the quick comparison
    (results/quick/table1.md, mean of seeds 0 and 1 at the validation-chosen lr): car ours 3.71
    deg mean rotation error, sin/cos 4.50, quat 7.73 (paper, real data: 2.85 / 7.29 / 4.28);
    rooms (GQN) every representation at chance (x, y ~0.41, yaw ~89 deg) with the old rooms,
    whose views can be placed only relative to their room's context. The quick rooms now have
    compass walls (`data.family.wall_style` of `:gqn,quick`, "tinted" for the old look): quat
    at 600 steps, yaw 31.4 deg on new rooms, 28.0 on held-out views of training rooms
    (BUILD_NOTES "Rooms regression").
  python -m camrep.regression --config=configs/regression.py:seven_scenes,quick \
      --workdir=/tmp/reg_7s --config.representation=quat \
      --config.data.source=seven_scenes --config.data.dir=/data/tfds
    real data prepared by `python -m camrep.data.prepare --source seven_scenes --input RAW
    --data_dir /data/tfds` (likewise srn_cars / gqn / gibson for car / gqn / gibson); the paper's
    splits per dataset, see camrep/regression/views.py. Not yet measured at quick size.
  python -m camrep.regression --config=configs/regression.py:car,smoke --workdir=/tmp/reg_s \
      --config.representation=euler
    seconds; for tests.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import ml_collections
from ml_collections import config_dict

from camrep import settings as settings_lib
from camrep.configs import common

DEFAULT_SETTING = "car"
"""The setting of a config argument that names none (`:quick` is `:car,quick`)."""


def parse_arg(arg: str | None) -> tuple[settings_lib.Setting, str]:
  """(setting, variant) of a config argument: comma-separated, a registered setting's name and
  a variant (`common.VARIANTS`), either or both, in either order.

  Raises:
    ValueError: an unknown word, or two settings or two variants.
  """
  names, variants = [], []
  for word in (w.strip() for w in (arg or "").split(",")):
    if word in settings_lib.SETTINGS:
      names.append(word)
    elif word:
      variants.append(common.parse_arg(word))
  if len(names) > 1 or len(variants) > 1:
    raise ValueError(f"config argument {arg!r}: name at most one setting and one variant")
  return settings_lib.get(names[0] if names else DEFAULT_SETTING), (variants or [""])[0]


def check_layout(stored: Mapping[str, Any]) -> None:
  """Refuses a workdir's config.json written before the configs were per setting (it holds
  every setting's `settings` and `hparams` tables).

  Raises:
    ValueError: saying how to go on.
  """
  if "settings" in stored:
    raise ValueError(
      "its config.json is of the layout before per-setting regression configs (every "
      "setting's `settings` and `hparams` tables in one config), which this camrep does not "
      "read: a rerun starts over anyway, so rerun in a new workdir, or remove the workdir's "
      "config.json to rerun in it (its results.json stays readable by the table tools)"
    )


def _ours(
  *, loss: dict | None = None, optax: dict | None = None, model: dict | None = None
) -> ml_collections.ConfigDict:
  """The loss, weighting and optimiser of the learned representations ("ours", "mlp") in one
  setting: this base with the fields of `loss`, `optax` and `model` changed."""
  h = ml_collections.ConfigDict()
  h.loss = ml_collections.ConfigDict()
  # Head loss (a key of camrep.regression.targets.LOSSES); "": the representation's own
  # (`PoseEncoding.loss`: l2 for ours and mlp).
  h.loss.kind = ""
  # "homoscedastic": L = sum_g e^{-s_g} L_g + s_factor s_g over the groups (position,
  # orientation), s_g from init_s and trained when learn_s (Kendall et al. 2017); "fixed":
  # L = sum_g w_g L_g with `weights`.
  h.loss.weighting = "homoscedastic"
  h.loss.init_s = (0.0, 0.0)
  h.loss.s_factor = 1.0
  h.loss.learn_s = True
  h.loss.weights = (1.0, 1.0)
  h.optax = ml_collections.ConfigDict()
  # Coupled L2 added to the gradients before Adam (PyTorch's Adam weight_decay; also on s).
  h.optax.weight_decay = 0.0
  h.model = ml_collections.ConfigDict()
  # Units (at width 1) of an extra dense layer before the heads; None: none.
  h.model.extra_fc = config_dict.placeholder(int)
  # "ours": quantisation of the targets and of the decoding candidates, "floor" or "nearest".
  h.model.quantisation = "floor"
  for name, diff in (("loss", loss), ("optax", optax), ("model", model)):
    h[name].update(diff or {})
  return h


def _hparams(ours: ml_collections.ConfigDict, *, extra_fc: int | None) -> ml_collections.ConfigDict:
  """One setting's `ours` and what every baseline changes from it (paper section 5.4): its own
  loss (MSE for euler / sincos, L1 for quat / logq / axis_angle, the matrix losses of rot6d /
  svd9d), Kendall's weighting from s = (0, -3), learned, and an extra dense layer of `extra_fc`
  units that equalises parameter counts at paper width. Baselines keep the setting's learning
  rate and weight decay (the paper does not give its tuned values)."""
  baselines = ml_collections.ConfigDict()
  baselines.loss = ml_collections.ConfigDict(
    dict(kind="", weighting="homoscedastic", init_s=(0.0, -3.0), s_factor=1.0, learn_s=True)
  )
  baselines.model = ml_collections.ConfigDict()
  baselines.model.extra_fc = config_dict.placeholder(int)
  baselines.model.extra_fc = extra_fc
  h = ml_collections.ConfigDict()
  h.ours = ours
  h.baselines = baselines
  return h


def _sizes(
  c: ml_collections.ConfigDict,
  *,
  family: dict,
  total_steps: int,
  batch_size: int,
  width: float,
) -> None:
  """The setting's data family (overrides of its procedural family,
  `camrep.data.procedural.make_family`), steps, images per step (gqn: scenes, each with
  n_context context views and n_query queries) and network width."""
  c.data.family = ml_collections.ConfigDict(family)
  c.total_steps = total_steps
  c.data.batch_size = batch_size
  c.model.width = width


def base(setting: settings_lib.Setting, variant: str) -> ml_collections.ConfigDict:
  """The config every setting derives from: the fields of every setting, with the base recipe
  (`_ours()`, no baseline layer, the car's sizes and no family overrides)."""
  c = ml_collections.ConfigDict()
  c.setting = setting.name
  # One of camrep.regression.targets.REPRESENTATIONS: ours, mlp, euler, axis_angle, sincos, quat,
  # logq, rot6d, svd9d.
  c.representation = "quat"
  c.seed = 0
  # A `camrep.main` workdir of the same setting: "ours" takes its learned pose system (required);
  # "mlp" its MLP embedding if it was trained with rep.kind=mlp, else (and without a workdir) a
  # frozen randomly initialised MLP embedding.
  c.synthesis_workdir = ""
  # Use a synthesis workdir whose run is not complete (still training, stopped on non-finite
  # values or by a signal): refused unless True, and recorded in results.json.
  c.allow_incomplete_synthesis = False
  c.variant = variant or "paper"
  # Rerunning in a workdir that holds another config: the fields allowed to differ
  # (comma-separated; the rerun starts over and the change goes to config_history.jsonl).
  c.allow_changes = ""

  c.total_steps = 108_000
  c.log_every_steps = 100
  # Validation errors during training (metrics.jsonl only); 0: at the end only.
  c.eval_every_steps = 0
  # Checkpoints (a killed or signalled run resumes from the latest), of which the last
  # `max_to_keep` are kept; train steps per dispatch (`configs/common.py`: 1 outside paper size).
  c.ckpt_every_steps = 1000
  c.max_to_keep = 2
  c.steps_per_dispatch = 1 if variant else 10
  # Stopping rule (camrep/runtime/stopping.py), checked at each periodic validation (needs
  # eval_every_steps): stop when the best validation score (`Setting.validation_score`) improved
  # by less than `min_improvement` (relative) over the last `window` of the steps, not before
  # `min_steps`; total_steps is the cap. min_improvement 0: off (train to total_steps).
  c.stop = ml_collections.ConfigDict()
  c.stop.min_improvement = 0.0
  c.stop.window = 0.25
  c.stop.min_steps = 0

  c.data = ml_collections.ConfigDict()
  c.data.preset = "default"
  c.data.batch_size = 200
  # Held out of the training split to choose the learning rate (never trained on): gqn this
  # share of the training scenes, the other settings this share of every training scene's views
  # (its last views by id; for 7-Scenes the end of the training trajectory).
  c.data.validation_fraction = 0.1
  # The procedural family is prepared here once (an ArrayRecord dataset per family config, as
  # `camrep.data.prepare` writes) and decoded by later runs; empty: rendered by every run.
  c.data.cache_dir = ""
  # Real data, read as `camrep.main` reads it: "" = the setting's procedural family; gqn,
  # srn_cars, gibson or seven_scenes (must be of the setting) read `dir`, a directory prepared by
  # `python -m camrep.data.prepare --source SOURCE --input RAW --data_dir DIR`.
  c.data.source = ""
  c.data.dir = ""
  # The prepared dataset's builder config ("" = the preset's when prepared, else its only one).
  c.data.dataset_config = ""
  # Real data: resize the decoded images to this side (None: as prepared).
  c.data.image_size = config_dict.placeholder(int)
  # Real data is decoded into memory; a split larger than this is refused unless `stream`: then
  # batches are decoded on the fly from the prepared files. Training and evaluation batches are
  # read by `num_threads` grain reader threads, `prefetch` batches ahead.
  c.data.max_memory_gb = 16.0
  c.data.stream = False
  c.data.num_threads = 2
  c.data.prefetch = 2
  c.data.family = ml_collections.ConfigDict()

  c.model = ml_collections.ConfigDict()
  c.model.width = 1.0
  # Gauss-Newton refinement steps when decoding ours (0: the authors' plain arg-min).
  c.model.refine_steps = 4
  # Baselines' extra dense layer: False: the setting's fixed units (`hparams.baselines`: 196
  # gqn, 256 car, 192 gibson, scaled by the width), which equalise parameter counts at paper
  # width only; True: units solved so that each baseline has as many parameters as ours at any
  # width (quick runs).
  c.model.equalise_params = False

  # Baselines' extra dense layer (units at width 1; None: hparams.baselines).
  c.model.extra_fc = config_dict.placeholder(int)
  # "ours": quantisation of targets and candidates (None: hparams.ours).
  c.model.quantisation = config_dict.placeholder(str)

  # The loss and optimiser; None: the setting's value for the representation (`hparams`).
  c.loss = ml_collections.ConfigDict()
  c.loss.kind = config_dict.placeholder(str)
  c.loss.weighting = config_dict.placeholder(str)
  c.loss.init_s = config_dict.placeholder(tuple)
  c.loss.s_factor = config_dict.placeholder(float)
  c.loss.learn_s = config_dict.placeholder(bool)
  c.loss.weights = config_dict.placeholder(tuple)
  c.optax = ml_collections.ConfigDict()
  c.optax.lr = 1e-4  # Adam
  c.optax.weight_decay = config_dict.placeholder(float)

  # The loss, weighting and optimiser of the setting (paper section 5.4 and its supplement).
  c.hparams = _hparams(_ours(), extra_fc=None)

  c.evals = ml_collections.ConfigDict()
  c.evals.batch_size = 64  # images (gqn: queries) per evaluation batch
  # More test splits, comma-separated ("test", "test_scenes"), written as results.json "extra".
  c.evals.extra_splits = ""
  # Every eval_every_steps: False: the validation split only (what choosing the lr needs);
  # True: every evaluation split (test and extra ones too), for learning curves.
  c.evals.periodic_all_splits = False
  # The split the paper's protocol tests on (`Setting.test_split`): gqn held-out scenes, the
  # others held-out views.
  c.evals.test_split = setting.test_split

  if variant in ("quick", "medium"):
    c.data.preset = "small"
    c.log_every_steps = 50
    c.evals.batch_size = 128
    c.model.equalise_params = True
    _sizes(c, family={}, total_steps=1500, batch_size=32, width=0.125)
    if variant == "medium":
      # One GPU: the `:quick` families with the data of the `:medium` view-synthesis configs, a
      # quarter of the paper width, twice the batch and ~4x the steps.
      c.log_every_steps = 200
      _sizes(c, family={}, total_steps=6_000, batch_size=64, width=0.25)
  elif variant == "smoke":
    c.data.preset = "small"
    c.data.validation_fraction = 0.25
    c.log_every_steps = 2
    c.evals.batch_size = 8
    c.model.refine_steps = 1
    _sizes(c, family={}, total_steps=3, batch_size=4, width=1 / 32)
  return c


def _set_hparams(c, ours: ml_collections.ConfigDict, *, lr: float, extra_fc: int | None) -> None:
  c.optax.lr = lr
  c.hparams = _hparams(ours, extra_fc=extra_fc)


def _gqn(c: ml_collections.ConfigDict, variant: str) -> None:
  """GQN rooms: scenes of context and query views; Kendall's weighting from
  s = (-log 20, -log 5), learned."""
  c.data.n_context = 6  # context views per scene (test: views 0..5, as the authors)
  c.data.n_query = 3  # query views per scene in a training step
  # Real GQN: this share of the prepared scenes (the last by id) is the held-out test scenes.
  c.data.test_scenes_fraction = 0.1
  _set_hparams(c, _ours(loss=dict(init_s=(-math.log(20.0), -math.log(5.0)))), lr=1e-4, extra_fc=196)
  if not variant:
    # Procedural data is held in memory, so the rooms family is capped at 20k scenes (the
    # paper's GQN files hold 200k).
    family = dict(num_train_scenes=20_000, num_test_scenes=1_000)
    _sizes(c, family=family, total_steps=100_000, batch_size=30, width=1.0)
  elif variant in ("quick", "medium"):
    c.data.n_query = 4  # 4 scenes x (6 context + 4 query) views a step
    family = dict(
      num_train_scenes=400,
      num_test_scenes=32,
      train_views=10,
      test_views=2,
      texture_contrast=(0.0, 0.08),
      # Wall hues fixed to the world directions, so that a view tells the yaw (with the old
      # look, wall_style="tinted", every cue that tells a view from its quarter-turn twins is
      # drawn afresh per room and the regression stays at chance).
      wall_style="compass",
    )
    _sizes(c, family=family, total_steps=600, batch_size=4, width=0.125)
    if variant == "medium":
      family.update(num_train_scenes=2_000, num_test_scenes=64)
      _sizes(c, family=family, total_steps=3_000, batch_size=8, width=0.25)
  elif variant == "smoke":
    c.data.n_context = 3
    c.data.n_query = 2
    c.data.batch_size = 2


def _car(c: ml_collections.ConfigDict, variant: str) -> None:
  """ShapeNet car: fixed weights, lr 1e-3; 2000 cars x 50 training views, 10 test views per
  car."""
  _set_hparams(c, _ours(loss=dict(weighting="fixed")), lr=1e-3, extra_fc=256)
  if not variant:
    _sizes(c, family=dict(test_views=10), total_steps=108_000, batch_size=200, width=1.0)
  elif variant in ("quick", "medium"):
    family = dict(
      image_size=64, num_train_scenes=64, num_test_scenes=8, train_views=40, test_views=8
    )
    _sizes(c, family=family, total_steps=1500, batch_size=32, width=0.125)
    if variant == "medium":
      family.update(num_train_scenes=256, num_test_scenes=16)
      _sizes(c, family=family, total_steps=6_000, batch_size=64, width=0.25)


def _gibson(c: ml_collections.ConfigDict, variant: str) -> None:
  """Gibson areas: fixed weights (20, 10), lr 1e-3, nearest quantisation."""
  ours = _ours(
    loss=dict(weighting="fixed", weights=(20.0, 10.0)), model=dict(quantisation="nearest")
  )
  _set_hparams(c, ours, lr=1e-3, extra_fc=192)
  if not variant:
    _sizes(c, family=dict(test_views=1_000), total_steps=25_000, batch_size=200, width=1.0)
  elif variant in ("quick", "medium"):
    family = dict(image_size=64, num_scenes=4, train_views=600, test_views=100)
    _sizes(c, family=family, total_steps=1500, batch_size=32, width=0.125)
    if variant == "medium":
      family.update(train_views=1_000)
      _sizes(c, family=family, total_steps=6_000, batch_size=64, width=0.25)


def _seven_scenes(c: ml_collections.ConfigDict, variant: str) -> None:
  """7-Scenes: a ResNet; an L1 loss per DOF, the three DOF terms of a group sharing one s
  (factor 3), lr 5e-5 with weight decay; baselines have no extra layer (MapNet's heads)."""
  # The ResNet: blocks per stage, fc units, and the ImageNet initialisation: a torchvision
  # ResNet-34 state dict (.npz; .pth with torch) loaded into the trunk (needs model.width=1;
  # images then normalised with ImageNet's mean / std), or "": from scratch.
  c.model.resnet_stages = (3, 4, 6, 3)
  c.model.fc_dim = 2048
  c.model.resnet_weights = ""
  ours = _ours(
    loss=dict(kind="l1", init_s=(-3.0, -3.0), s_factor=3.0), optax=dict(weight_decay=5e-4)
  )
  _set_hparams(c, ours, lr=5e-5, extra_fc=None)
  if not variant:
    _sizes(c, family={}, total_steps=24_000, batch_size=64, width=1.0)
  elif variant in ("quick", "medium"):
    c.model.resnet_stages = (1, 1, 1, 1)
    c.model.fc_dim = 256
    family = dict(
      image_size=64,
      scenes=("chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs"),
      train_stride=20,
      test_stride=50,
    )
    _sizes(c, family=family, total_steps=1500, batch_size=32, width=0.125)
    if variant == "medium":
      c.model.resnet_stages = (2, 2, 2, 2)
      c.model.fc_dim = 512
      family.update(train_stride=10, test_stride=25)
      _sizes(c, family=family, total_steps=6_000, batch_size=64, width=0.25)
  elif variant == "smoke":
    c.model.resnet_stages = (1,)
    c.model.fc_dim = 16


RECIPES: dict[str, Callable[[ml_collections.ConfigDict, str], None]] = {
  settings_lib.GQN.name: _gqn,
  settings_lib.CAR.name: _car,
  settings_lib.GIBSON.name: _gibson,
  settings_lib.SEVEN_SCENES.name: _seven_scenes,
}
"""Setting name -> what its config changes from `base` (sizes, family, hyper-parameters and its
own fields); a setting without one runs the base recipe."""


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
  setting, variant = parse_arg(arg)
  c = base(setting, variant)
  recipe = RECIPES.get(setting.name)
  if recipe is not None:
    recipe(c, variant)
  return c

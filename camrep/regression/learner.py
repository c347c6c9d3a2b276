"""Pose regression on a frozen pose representation (paper section 4.4; the authors' code).

Plain functions, independent of the view-synthesis trainer (`camrep.synthesis.train`):

  resolve_hparams(config, encoding)             a run config's loss and optimiser settings
  make_regressor(setting, encoding, ...)        the static description: network, heads, loss
  init(key, regressor, batch, rep_params)       a `RegressionState`
  train_step(state, batch[, lr])                one Adam step; pure, jit it at the call site:
                                                `step = jax.jit(regress.train_step)`
  train_steps(state, batches[, lr])             K steps over stacked batches (`lax.scan`)
  unit_rate(regressor)                          the regressor whose optimiser has lr 1, for
                                                steps given their lr (`jax.vmap` over lrs)
  predict_poses(state, batch)                   network -> heads -> decode -> poses
  pose_errors(setting, pred, true)              per-example errors (camrep.metrics)
  evaluate_regression(state, batches)           per-example errors over an eval set
  summarise_errors(errors)                      mean and median per scene and overall

Batches are dicts of arrays:
  "image": (..., H, W, 3) uint8 (mapped to [-1, 1]) or float (used as given, e.g. a ResNet's
           per-scene normalised input);
  "pose":  (..., P) float poses in the setting's columns (`camrep.settings.Setting.pose_columns`);
  "scene": (...) int scene / area index (Gibson's instance-norm tables; per-scene summaries);
  GQN only, with leading axes (S, Q) of scenes and queries:
  "context_image": (S, V, H, W, 3) and "context_pose": (S, V, P) of each scene's context views;
  optional "mask": (...) bool, false for padding (evaluation).

The targets' representation parameters (`rep_params`: the stage-1 pose system for "ours", MLP
embeddings for "mlp", nothing for the baselines) are part of the state but never trained.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from typing import Any

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import optax

from camrep import pose as P
from camrep import pose_encodings
from camrep import settings as settings_lib
from camrep.models import fastconv, layers, pose_regressor
from camrep.models import pose_regressor as R
from camrep.regression import targets as T

Array = jax.Array


# The hyper-parameters of a run config (configs/regression.py), by section.
HPARAM_FIELDS = {
  "loss": ("kind", "weighting", "init_s", "s_factor", "learn_s", "weights"),
  "optax": ("lr", "weight_decay"),
  "model": ("extra_fc", "quantisation"),
}
QUANTISATIONS = ("floor", "nearest")


@dataclasses.dataclass(frozen=True)
class HyperParams:
  """The loss, weighting and optimiser of one regressor (a run config's: `resolve_hparams`).

  Attributes:
    loss: head loss, a key of `targets.LOSSES` (config `loss.kind`).
    weighting: "homoscedastic" (learned or fixed s per group) or "fixed" (constant weights).
    init_s: initial (s_position, s_orientation) of the homoscedastic weighting.
    s_factor: factor of s in `targets.homoscedastic`.
    learn_s: whether s_position, s_orientation are trained.
    weights: fixed (position, orientation) weights of weighting="fixed".
    lr: Adam learning rate.
    weight_decay: coupled L2 added to the gradients before Adam (also on s).
    extra_fc: units (at width 1) of the baselines' extra dense layer before the heads, or None.
    quantisation: "ours": quantisation of targets and candidates ("floor" or "nearest").
  """

  loss: str
  weighting: str
  init_s: tuple[float, float]
  s_factor: float
  learn_s: bool
  weights: tuple[float, float]
  lr: float
  weight_decay: float
  extra_fc: int | None
  quantisation: str


def resolve_hparams(config, encoding: type[pose_encodings.PoseEncoding]) -> HyperParams:
  """The hyper-parameters of a run config (configs/regression.py) whose representation is
  `encoding` (the `PoseEncoding` class `config.representation` names).

  Each field (`HPARAM_FIELDS`) is the config's own when set (not None), else that of
  `config.hparams` (the setting's): its `ours` for the learned representations, `ours` updated
  by its `baselines` for the baselines. An empty `loss.kind` is the representation's own loss
  (`PoseEncoding.loss`). The config is not changed.

  Raises:
    ValueError: an unknown loss, weighting or quantisation, or a field unset.
  """
  table = config.hparams
  chosen = table.ours.to_dict()
  if not encoding.learned:
    for section, fields in table.baselines.to_dict().items():
      chosen[section].update(fields)
  for section, keys in HPARAM_FIELDS.items():
    for k in keys:
      given = config[section].get(k)
      if given is not None:
        chosen[section][k] = given
      elif chosen[section].get(k) is None and k != "extra_fc":
        raise ValueError(f"{section}.{k} is unset, and so is the setting's (hparams)")
  loss, optax_, model = chosen["loss"], chosen["optax"], chosen["model"]
  h = HyperParams(
    loss=loss["kind"] or encoding.loss,
    weighting=loss["weighting"],
    init_s=tuple(float(x) for x in loss["init_s"]),
    s_factor=float(loss["s_factor"]),
    learn_s=bool(loss["learn_s"]),
    weights=tuple(float(x) for x in loss["weights"]),
    lr=float(optax_["lr"]),
    weight_decay=float(optax_["weight_decay"]),
    extra_fc=None if model["extra_fc"] is None else int(model["extra_fc"]),
    quantisation=model["quantisation"],
  )
  for name, value, allowed in (
    ("loss.kind", h.loss, tuple(T.LOSSES)),
    ("loss.weighting", h.weighting, T.WEIGHTINGS),
    ("model.quantisation", h.quantisation, QUANTISATIONS),
  ):
    if value not in allowed:
      raise ValueError(f"unknown {name} {value!r}; choose one of {allowed}")
  if len(h.init_s) != 2 or len(h.weights) != 2:
    raise ValueError("loss.init_s and loss.weights take (position, orientation) pairs")
  return h


@dataclasses.dataclass(frozen=True)
class Regressor:
  """Everything static about one pose regressor (hashable; lives in the state's treedef).

  Attributes:
    setting: the `camrep.settings.Setting`.
    representation: one of `targets.REPRESENTATIONS`.
    module: the Flax network (`camrep.models.pose_regressor`).
    heads: its output heads (`targets.head_specs`).
    hparams: loss, weighting and optimiser settings.
    spec: the pose system of a learned representation, else None.
    refine_steps: Gauss-Newton refinement steps when decoding "ours" (0: plain arg-min).
    image_norm: how uint8 images become network inputs: "symmetric" [-1, 1] (the authors' code), or
      "imagenet" ((x / 255 - mean) / std, torchvision's, for ImageNet-pretrained weights).
    weight_grad: the conv kernel gradients `train_step` traces (`camrep.models.fastconv` modes):
      "by_channels" (matmuls on a CPU for convs of 128 or more output channels, XLA's own for
      narrower ones: 2.3x faster at the quick width's GQN step than all matmuls, the same at
      paper width). The same math, summed in another order.
  """

  setting: settings_lib.Setting
  representation: str
  module: nn.Module
  heads: tuple[pose_regressor.HeadSpec, ...]
  hparams: HyperParams
  spec: P.PoseSystemSpec | None = None
  refine_steps: int = 4
  image_norm: str = "symmetric"
  weight_grad: str = "by_channels"


IMAGE_NORMS = ("symmetric", "imagenet")
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def make_regressor(
  setting: settings_lib.Setting | str,
  encoding: type[pose_encodings.PoseEncoding],
  *,
  hparams: HyperParams,
  spec: P.PoseSystemSpec | None = None,
  width: float = 1.0,
  num_scenes: int = 1,
  fc_dim: int = 2048,
  stage_sizes: tuple[int, ...] = R.RESNET34_STAGES,
  refine_steps: int = 4,
  equalise_params: bool = False,
  image_norm: str = "symmetric",
) -> Regressor:
  """The regressor of a setting and a representation (its `PoseEncoding` class) at a given
  width.

  The network is the setting's (`Setting.network`: gqn `GQNRegressor`, car `CarRegressor`,
  gibson `GibsonRegressor`, seven_scenes `ResNetRegressor`). The baselines' extra dense layer
  (`hparams.extra_fc`) is scaled by `width`.

  Args:
    setting: a `camrep.settings.Setting` (or its name).
    encoding: the representation's class, a regression target (`pose_encodings.get(name)` of
      one of `targets.REPRESENTATIONS`).
    hparams: loss, weighting and optimiser (`resolve_hparams` of a run config).
    spec: pose system of a learned representation (default `setting.pose_spec()`;
      pass `camrep.synthesis.components.pose_spec(config)` for a stage-1 run's system).
    width: channel multiplier (paper 1.0).
    num_scenes: rows of Gibson's per-area instance-norm tables.
    fc_dim, stage_sizes: ResNet fc units and blocks per stage (7-Scenes).
    refine_steps: decoding refinement of "ours".
    equalise_params: size a baseline's extra dense layer so that its parameter count equals
      that of "ours" (the paper's fixed units equalise only at paper width; at a reduced width
      they leave a baseline with about half the parameters of ours). 7-Scenes baselines, which
      have no extra layer in the paper (MapNet's heads), get one solved the same way.
    image_norm: see `Regressor.image_norm`.

  Returns:
    a `Regressor`.

  Raises:
    ValueError: an encoding a regressor cannot predict, or a spec of other columns than the
      setting's.
  """
  setting = settings_lib.get(setting)
  if not encoding.regression_target:
    raise ValueError(
      f"a regressor cannot predict {encoding.table_name()!r}; choose one of {T.REPRESENTATIONS}"
    )
  if encoding.per_dof:  # the learned representations ("ours", "mlp")
    spec = spec or setting.pose_spec()
    setting.check_spec(spec)
  else:
    spec = None
  heads = encoding.create(setting, spec).heads()  # `targets.head_specs`
  extra = layers.scaled(hparams.extra_fc, width) if hparams.extra_fc else None
  if equalise_params and not encoding.per_dof and not extra:
    extra = 1  # a placeholder: the units are solved from `match` (PoseHeads)
  match = None
  if equalise_params and extra:
    ours = pose_encodings.GridEncoding.create(setting, setting.pose_spec())
    match = sum(h.size for h in ours.heads())
  module = R.make_network(
    setting.network,
    heads,
    width=width,
    extra_fc=extra,
    extra_fc_match=match,
    num_scenes=num_scenes,
    stage_sizes=tuple(stage_sizes),
    fc_dim=fc_dim,
  )
  if image_norm not in IMAGE_NORMS:
    raise ValueError(f"image_norm must be one of {IMAGE_NORMS}, got {image_norm!r}")
  representation = encoding.table_name()
  return Regressor(setting, representation, module, heads, hparams, spec, refine_steps, image_norm)


def make_optimizer(hparams: HyperParams) -> optax.GradientTransformation:
  """Adam(lr) (eps 1e-8, b1 0.9); with weight_decay, coupled L2 added to the gradient first
  (PyTorch Adam's weight_decay, the authors' code), which also acts on s_x, s_q."""
  if hparams.weight_decay:
    return optax.chain(
      optax.add_decayed_weights(hparams.weight_decay),
      optax.scale_by_adam(),
      optax.scale(-hparams.lr),
    )
  return optax.adam(hparams.lr)


@flax.struct.dataclass
class RegressionState:
  """The regression train state.

  Attributes:
    step: () int32.
    params: {"net": network params, "log_var": {"position", "orientation"} learned s (or {})}.
    batch_stats: batch-norm statistics (ResNet) or {}.
    opt_state: optimiser state of `params`.
    rep_params: frozen representation parameters (pose system / MLP / {}).
    regressor: the static `Regressor`.
    tx: the optimiser.
  """

  step: Array
  params: dict
  batch_stats: dict
  opt_state: Any
  rep_params: Any
  regressor: Regressor = flax.struct.field(pytree_node=False)
  tx: optax.GradientTransformation = flax.struct.field(pytree_node=False)


def prepare_images(images: Array, norm: str = "symmetric") -> Array:
  """uint8 [0, 255] -> float32 [-1, 1] (the authors' code), or with norm="imagenet" torchvision's
  (x / 255 - mean) / std; float images are returned unchanged."""
  images = jnp.asarray(images)
  if not jnp.issubdtype(images.dtype, jnp.integer):
    return images
  if norm == "imagenet":
    x = images.astype(jnp.float32) / 255.0
    return (x - jnp.asarray(IMAGENET_MEAN)) / jnp.asarray(IMAGENET_STD)
  return images.astype(jnp.float32) * (2.0 / 255.0) - 1.0


def encode_poses(reg: Regressor, rep_params: Any, poses: Array) -> dict[str, Array]:
  """Targets of poses (..., P) in the regressor's representation: {head: (..., size)}."""
  return T.encode(
    reg.representation,
    reg.setting,
    poses,
    spec=reg.spec,
    rep_params=rep_params,
    mode=reg.hparams.quantisation,
  )


def context_pose_input(reg: Regressor, rep_params: Any, poses: Array) -> Array:
  """GQN encoder's pose input: the representation's targets of the context poses concatenated
  in head order (ours: [v_xy || v_yaw], 2 d = 192; baselines: e.g. [x, y, q], 6), (..., P_c)."""
  enc = encode_poses(reg, rep_params, poses)
  return jnp.concatenate([enc[h.name] for h in reg.heads], axis=-1)


def network_inputs(reg: Regressor, rep_params: Any, batch: Mapping[str, Array]):
  """(images, keyword arguments) of the network for a batch."""
  kw = {"scene": batch.get("scene")}
  if reg.setting.context_views:
    kw["context_images"] = prepare_images(batch["context_image"], reg.image_norm)
    kw["context_poses"] = context_pose_input(reg, rep_params, batch["context_pose"])
  return prepare_images(batch["image"], reg.image_norm), kw


def _variables(params: Mapping, batch_stats: Mapping) -> dict:
  v = {"params": params["net"]}
  if batch_stats:
    v["batch_stats"] = batch_stats
  return v


@functools.partial(jax.jit, static_argnums=0)
def _init_variables(reg: Regressor, key: Array, rep_params: Any, batch: Mapping[str, Array]):
  """The network's variables for the batch's shapes: one compiled initialisation instead of
  op-by-op dispatch (as flax's examples do), compiled once per regressor at rate 1 (`unit_rate`)
  and shapes, so the members of a vectorised grid (`camrep.regression.vectorised`) share it (a
  ResNet-34's costs seconds at full optimisation: 60 members each compiling it again took ~25
  min)."""
  images, kw = network_inputs(reg, rep_params, batch)
  return reg.module.init(key, images, **kw, train=False)


def init(
  key: Array, reg: Regressor, batch: Mapping[str, Array], *, rep_params: Any = None
) -> RegressionState:
  """Initial state: network parameters for the batch's shapes, s at the table's values.

  Args:
    key: PRNG key of the network initialisation.
    reg: from `make_regressor`.
    batch: an example batch (only shapes matter).
    rep_params: the frozen representation ("ours": pose-system params, "mlp": `MlpEncoding.init`).
  """
  if reg.representation in T.LEARNED and rep_params is None:
    raise ValueError(f"representation {reg.representation!r} needs rep_params")
  rep_params = {} if rep_params is None else rep_params
  batch = {k: jnp.asarray(v) for k, v in batch.items()}
  variables = _init_variables(unit_rate(reg), key, rep_params, batch)  # the lr plays no part
  hp = reg.hparams
  log_var = T.init_log_vars(hp.weighting, hp.init_s, learn_s=hp.learn_s)
  params = {"net": variables["params"], "log_var": log_var}
  tx = make_optimizer(hp)
  return RegressionState(
    step=jnp.zeros((), jnp.int32),
    params=params,
    batch_stats=dict(variables.get("batch_stats", {})),
    opt_state=jax.jit(tx.init)(params),  # compiled once, not a program per leaf shape
    rep_params=rep_params,
    regressor=reg,
    tx=tx,
  )


def loss_terms(
  reg: Regressor, heads: Mapping[str, Array], target: Mapping[str, Array], params: Mapping
) -> tuple[Array, dict[str, Array]]:
  """(total loss, {"position": L_pos, "orientation": L_ori}) of predicted vs target heads."""
  hp = reg.hparams
  groups = T.group_losses(hp.loss, heads, target, reg.heads)
  total = T.total_loss(
    groups,
    weighting=hp.weighting,
    init_s=hp.init_s,
    s_factor=hp.s_factor,
    weights=hp.weights,
    log_vars=params.get("log_var") or None,
  )
  return total, groups


def unit_rate(reg: Regressor) -> Regressor:
  """The regressor with learning rate 1: its optimiser (`make_optimizer`) ends in scale(-1), so
  that `train_step(state, batch, lr)` gives Adam(lr)'s update: (-u) * lr is u * (-lr) in IEEE
  arithmetic, bit for bit. Its optimiser state has the same structure as the regressor's."""
  return dataclasses.replace(reg, hparams=dataclasses.replace(reg.hparams, lr=1.0))


def train_step(
  state: RegressionState, batch: Mapping[str, Array], lr: Array | None = None
) -> tuple[RegressionState, dict[str, Array]]:
  """One optimiser step on the regression loss; pure (jit at the call site).

  Args:
    state: the state.
    batch: a training batch.
    lr: () the learning rate of a state whose regressor has rate 1 (`unit_rate`): its updates
      are scaled by it, so that runs of several rates share one program (`jax.vmap` over states
      and rates). None: the optimiser's own rate.

  Returns:
    (new state, metrics {"loss", "loss_position", "loss_orientation", "s_position",
    "s_orientation" (when learned), "grad_norm", "finite" (1.0, or 0.0 when a value was not
    finite: the update is skipped)}).
  """
  with fastconv.weight_grad(state.regressor.weight_grad):  # read while the step is traced
    return _train_step(state, batch, lr)


def _train_step(state, batch, lr):
  reg = state.regressor
  images, kw = network_inputs(reg, state.rep_params, batch)
  target = encode_poses(reg, state.rep_params, batch["pose"])

  def loss_fn(params):
    (heads, _), new_vars = reg.module.apply(
      _variables(params, state.batch_stats), images, **kw, train=True, mutable=["batch_stats"]
    )
    total, groups = loss_terms(reg, heads, target, params)
    return total, (groups, new_vars.get("batch_stats", {}))

  (total, (groups, batch_stats)), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
  updates, opt_state = state.tx.update(grads, state.opt_state, state.params)
  if lr is not None:
    updates = jax.tree.map(lambda u: u * lr, updates)
  params = optax.apply_updates(state.params, updates)
  out = {"loss": total, "grad_norm": optax.tree.norm(grads)}
  out.update({f"loss_{g}": v for g, v in groups.items()})
  out.update({f"s_{g}": v for g, v in state.params["log_var"].items()})
  # The finite guard: a step with a non-finite loss, s or gradient keeps the old state and says
  # so ("finite" 0); the training loop stops at its next log or checkpoint step.
  finite = jnp.array(True)
  for v in out.values():
    finite &= jnp.all(jnp.isfinite(v))
  out["finite"] = finite.astype(jnp.float32)
  keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, old)
  new_stats = dict(batch_stats) if batch_stats else state.batch_stats
  new = state.replace(
    step=state.step + 1,
    params=keep(params, state.params),
    batch_stats=keep(new_stats, state.batch_stats),
    opt_state=keep(opt_state, state.opt_state),
  )
  return new, out


def train_steps(
  state: RegressionState, batches: Mapping[str, Array], lr: Array | None = None
) -> tuple[RegressionState, dict[str, Array], Array]:
  """`train_step` over K stacked batches (`lax.scan`); pure (jit at the call site).

  Args:
    state: the state.
    batches: K batches stacked on a leading axis (K, ...).
    lr: as `train_step`'s.

  Returns:
    (state after the K steps, metrics stacked (K,) per key, 1.0 when every step was finite).
  """
  state, metrics = jax.lax.scan(lambda s, b: train_step(s, b, lr), state, batches)
  return state, metrics, jnp.min(metrics["finite"])


def predict_heads(state: RegressionState, batch: Mapping[str, Array]) -> dict[str, Array]:
  """The network's heads for a batch (inference mode): {name: (..., size)}."""
  reg = state.regressor
  images, kw = network_inputs(reg, state.rep_params, batch)
  heads, _ = reg.module.apply(_variables(state.params, state.batch_stats), images, **kw)
  return heads


def predict_poses(state: RegressionState, batch: Mapping[str, Array]) -> Array:
  """Predicted poses (..., P): network -> heads -> `targets.decode`."""
  reg = state.regressor
  return T.decode(
    reg.representation,
    reg.setting,
    predict_heads(state, batch),
    spec=reg.spec,
    rep_params=state.rep_params,
    mode=reg.hparams.quantisation,
    refine_steps=reg.refine_steps,
  )


__all__ = [
  "HyperParams",
  "Regressor",
  "RegressionState",
  "context_pose_input",
  "encode_poses",
  "init",
  "loss_terms",
  "make_optimizer",
  "make_regressor",
  "network_inputs",
  "predict_heads",
  "predict_poses",
  "prepare_images",
  "resolve_hparams",
  "train_step",
  "train_steps",
  "unit_rate",
]

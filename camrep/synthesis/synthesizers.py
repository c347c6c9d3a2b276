"""View-synthesis models behind one interface (paper sections 3.3-3.6), and `model_class`, the one
place that maps a config to its model's class (built on the run's `components.Resolved`).

A `Synthesizer` holds a Flax module, the pose encoding that feeds it (`config.rep.kind`, see
`camrep.pose_encodings`; `pose_input`) and its losses. Its parameters are two groups,
{"model": module params, "rep": the encoding's params}, each trained by its own optimiser
(`step.train_step`):

  model group  minimises the model's loss (`loss`): L_rec of eq. 9 for camrep's decoders, the
               negative ELBO for GQN's generator;
  rep group    minimises `loss_weight` * that loss + the encoding's own loss (`pose_loss`, its
               `regulariser`: lambda_2 sum_l L_rot,l + lambda_4 L_rot,theta, eqs. 6-9, for the
               learned grid; zero for the others).

Implementations: `GQNDecoder` (encoder over context views, AdaIN decoder), `TableDecoder`
(per-scene tables), one per `config.task` (`TASKS`), and `ConvDraw` (GQN's generator, Eslami et
al. 2018).

Batches, on one device (see camrep.data.feed.pipeline): training {"image": uint8 (S, V, H, W, 3),
"pose": (S, V, P), "scene": (S,)}; held-out views (`heldout.eval_batches`) {"context_image"
(E, C, H, W, 3), "context_pose" (E, C, P), "target_image" (E, Q, H, W, 3), "target_pose"
(E, Q, P), "scene" (E,)}.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING

import flax.linen as nn
import jax
import jax.numpy as jnp

from camrep import pose as P
from camrep import pose_encodings
from camrep.models import convdraw, mvt, relative_attention
from camrep.models.composite import GQNSynthesis, TableSynthesis
from camrep.runtime.runconfig import ConfigError
from camrep.synthesis import conditionings

if TYPE_CHECKING:
  from camrep.synthesis.components import Resolved

Array = jax.Array
Params = dict
Terms = dict[str, Array]

AXIS = "batch"  # the pmapped step's device axis

# config.model.kind: camrep's decoders (trained on L_rec) or GQN's generator (trained on its ELBO).
MODEL_KINDS = ("decoder", "convdraw")

# The fields GQN's generator reads and no other model does: set by configs/gqn_convdraw.py, absent
# from configs/common.py:base (a workdir written before they moved stores them:
# config_schema.RETIRED).
GENERATOR_FIELDS = (
  "model.draw_steps",
  "model.z_channels",
  "model.draw_temperature",
  "loss.sigma_initial",
  "loss.sigma_final",
  "loss.sigma_anneal_steps",
  "loss.kl_weight_initial",
  "loss.kl_anneal_steps",
)

# config.model.dtype -> the models' `dtype` (None: float32, Flax's inference from the parameters).
COMPUTE_DTYPES = {"float32": None, "bfloat16": jnp.bfloat16}

# Latent draws of GQN's generator at evaluation: scene s samples from fold_in(key(SAMPLE_SEED), s),
# so predictions do not depend on the batching, and the noise test at alpha = 0 repeats the eval.
SAMPLE_SEED = 20180615


def to_float_images(images: Array) -> Array:
  """uint8 [0, 255] -> float32 [-1, 1]."""
  return images.astype(jnp.float32) * (2.0 / 255.0) - 1.0


def compute_dtype(name: str):
  """The dtype of the model's computation that `model.dtype` names (`COMPUTE_DTYPES`).

  Raises:
    ValueError: an unknown name.
  """
  if name not in COMPUTE_DTYPES:
    raise ValueError(f"unknown model.dtype {name!r}; choose one of {tuple(COMPUTE_DTYPES)}")
  return COMPUTE_DTYPES[name]


def scene_keys(key: Array, num_scenes: int) -> Array:
  """Per-scene keys from the scene's position in the GLOBAL batch (device-count independent);
  call inside the pmapped step."""
  start = jax.lax.axis_index(AXIS) * num_scenes
  return jax.vmap(lambda i: jax.random.fold_in(key, i))(start + jnp.arange(num_scenes))


def sample_keys(scene_ids: Array) -> Array:
  """(E,) scene ids -> (E,) PRNG keys of GQN's generator at evaluation (`SAMPLE_SEED`)."""
  base = jax.random.key(SAMPLE_SEED)
  return jax.vmap(lambda i: jax.random.fold_in(base, i))(scene_ids)


class Synthesizer(abc.ABC):
  """A view-synthesis model: a Flax module fed by a pose input, with its losses.

  Attributes:
    config: the run's config.
    spec: the pose system (the DOFs whose columns the poses hold).
    module: the Flax module.
    pose_encoding: the pose input (`pose_input`: the learned grid, GQN's low-dim vector or the
      MLP).
    loss_weight: lambda_1, the weight of `loss` in the rep group's objective.
    n_context: context views per scene (GQN layouts), None for per-scene tables.
    reads_context: the model encodes each scene's context views (GQN layouts).
    temperature: latent temperature of `predict` for a generative model, else None.
    reads_pose_vectors: the model reads the pose encoding's per-DOF vectors, which `predict`'s
      `transform` perturbs (the noise test) and the Gram maps show.
    own_pose_system: `spec` is the model's own (the transformer's learned conditionings: one DOF
      per pose column), not the setting's pose system (`components.pose_spec`).
    noise_on: where the noise test perturbs the query pose by default (`noise.NOISE_ON`): its
      per-DOF vectors ("vectors", the paper's test) or the pose before conditioning ("pose").
    variants: further predictions of the held-out evaluation, {name: temperature}.
  """

  n_context: int | None = None
  temperature: float | None = None
  variants: Mapping[str, float] = {}
  reads_context = False
  reads_pose_vectors = True
  own_pose_system = False
  noise_on = "vectors"

  @classmethod
  def check(cls, run: Resolved) -> None:
    """Raises ConfigError where this model cannot run the config on its pose system (beyond
    `check_config`'s layout checks); builds nothing but shapes."""
    del run

  def __init__(self, run: Resolved, module: nn.Module, spec: P.PoseSystemSpec | None = None):
    """The model of a resolved run (`components.Resolved`) around `module`, fed on pose system
    `spec` (default: the run's, `run.spec`)."""
    spec = run.spec if spec is None else spec
    self.config, self.spec, self.module = run.config, spec, module
    self.pose_encoding = pose_input(run, spec)
    self.loss_weight = float(run.config.loss.rec_weight)

  @abc.abstractmethod
  def init(self, key: Array, batch: Mapping[str, Array]) -> Params:
    """Initial parameters {"model", "rep"} shaped from one device's training batch; "rep" is
    `init_pose(key)`."""

  @abc.abstractmethod
  def init_pose(self, key: Array) -> Params:
    """The pose input's initial parameters, `init(key, ...)["rep"]` without the model's (the
    "untrained" control target reads them; jitted, as `step.init_fn` runs `init`, for the same
    bits)."""

  @abc.abstractmethod
  def loss(
    self, params: Params, batch: Mapping[str, Array], key: Array, step: Array
  ) -> tuple[Array, Terms]:
    """The model's training loss on one device's batch, inside the pmapped step.

    Args:
      params: {"model", "rep"}.
      batch: a training batch.
      key: the step's key (the loop key with the step folded in).
      step: the step counter (annealed schedules).

    Returns:
      (total, terms): the loss the model group minimises, and its named terms and diagnostics,
      logged as train/<name>.
    """

  @abc.abstractmethod
  def predict(
    self,
    params: Params,
    batch: Mapping[str, Array],
    *,
    mode: str = "nearest",
    keys: tuple[Array | None, Array | None] = (None, None),
    transform: Callable[[dict[str, Array]], dict[str, Array]] | None = None,
    temperature: float | None = None,
  ) -> Array:
    """Predicted target views of a held-out batch: (E, Q, H, W, 3) in [-1, 1].

    Args:
      params: {"model", "rep"}.
      batch: a held-out-view batch.
      mode: quantisation of the poses ("nearest", "random", "floor").
      keys: (context, target) per-image keys (E,), for mode "random".
      transform: applied to the target views' per-DOF vectors (the noise test).
      temperature: latents of a generative model (default `self.temperature`).
    """

  def vectors(
    self, params_rep: Params, poses: Array, *, mode: str = "nearest", keys: Array | None = None
  ) -> Array:
    """Decoder input of poses (E, V, P): (E, V, n_dofs * d), `per_dof` concatenated."""
    return P.concat(self.per_dof(params_rep, poses, mode=mode, keys=keys), self.spec)

  def per_dof(
    self, params_rep: Params, poses: Array, *, mode: str = "nearest", keys: Array | None = None
  ) -> dict[str, Array]:
    """The pose encoding's vectors of poses (E, V, P): {name: (E, V, k)}; `mode` and `keys` (E,)
    quantise the learned system and are ignored by the other encodings
    (`PoseEncoding.embed_images`)."""
    return self.pose_encoding.embed_images(params_rep, poses, mode=mode, keys=keys)

  def pose_loss(self, params_rep: Params, batch: Mapping[str, Array], key: Array):
    """The pose encoding's own loss and its terms (`PoseEncoding.regulariser`: for the learned
    grid lambda_2 sum_l L_rot,l + lambda_4 sum L_rot,theta, eqs. 9, 9.2).

    Extra pairs use the same key on every device (the term is replicated); data pairs (the
    batch's image pairs, `loss.data_pairs`) use per-scene keys and are averaged over devices by
    the step's pmean.
    """
    L = self.config.loss
    weights = pose_encodings.Regularisation(
      rot_weight=L.rot_weight,
      dir_weight=L.dir_weight,
      n_pairs=L.n_pairs,
      mode=self.config.rep.quantisation,
    )
    pairs = batch["pose"] if L.data_pairs else None
    return self.pose_encoding.regulariser(
      params_rep, key, weights=weights, pair_poses=pairs, scene_keys=scene_keys
    )


class _VectorFed(Synthesizer):
  """A module fed the pose input's vectors (`vectors`: camrep's decoders, GQN's generator): the
  pose input's parameters from the second half of `init`'s key, the module's from the first."""

  def init(self, key, batch):
    k_model, _ = jax.random.split(key)
    rep = self.init_pose(key)
    images = to_float_images(jnp.asarray(batch["image"]))
    vecs = self.vectors(rep, jnp.asarray(batch["pose"]))
    variables = self._init_module(k_model, images, vecs, jnp.asarray(batch["scene"]))
    return {"model": variables["params"], "rep": rep}

  def init_pose(self, key):
    return self.pose_encoding.init(jax.random.split(key)[1])

  @abc.abstractmethod
  def _init_module(self, key: Array, images: Array, vecs: Array, scenes: Array) -> dict:
    """The module's variables, from float images (S, V, H, W, 3) and pose vectors (S, V, P)."""


class _Decoder(_VectorFed):
  """camrep's decoders: trained on L_rec = mean over target images of the sum over pixels of
  (x_hat - x)^2 (eq. 9); `_render` maps (images, pose vectors, scenes) to (prediction, target)."""

  @abc.abstractmethod
  def _render(self, params_model, images, vecs, scenes) -> tuple[Array, Array]:
    """(prediction, target) images (S, Q, H, W, 3) of a training batch."""

  def loss(self, params, batch, key, step):
    del step
    _, k_quant = jax.random.split(key)
    keys = scene_keys(k_quant, batch["pose"].shape[0])
    images = to_float_images(batch["image"])
    mode = self.config.rep.quantisation
    vecs = self.vectors(params["rep"], batch["pose"], mode=mode, keys=keys)
    pred, target = self._render(params["model"], images, vecs, batch["scene"])
    rec = jnp.mean(jnp.sum((pred - target) ** 2, axis=(-3, -2, -1)))
    return rec, {"rec": rec}


class GQNDecoder(_Decoder):
  """GQN rooms: an encoder over the first `n_context` views of a scene and an AdaIN decoder of
  the others (`camrep.models.composite.GQNSynthesis`)."""

  reads_context = True

  def __init__(self, run: Resolved, num_scenes: int | None = None):
    del num_scenes  # the encoder gives the scene code
    m = run.config.model
    module = GQNSynthesis(
      width=m.width, gamma_offset=1.0 if m.gamma_init_one else 0.0, dtype=run.dtype
    )
    super().__init__(run, module)
    self.n_context = int(run.config.data.n_context)

  def _init_module(self, key, images, vecs, scenes):
    c = self.n_context
    return jax.jit(self.module.init)(key, images[:, :c], vecs[:, :c], vecs[:, c:])

  def _render(self, params_model, images, vecs, scenes):
    c = self.n_context
    pred, _ = self.module.apply({"params": params_model}, images[:, :c], vecs[:, :c], vecs[:, c:])
    return pred, images[:, c:]

  def predict(self, params, batch, *, mode="nearest", keys=(None, None), transform=None, **_):
    ctx = to_float_images(batch["context_image"])
    c = self.vectors(params["rep"], batch["context_pose"], mode=mode, keys=keys[0])
    q = _query_vectors(self, params, batch, mode, keys[1], transform)
    pred, _ = self.module.apply({"params": params["model"]}, ctx, c, q)
    return pred


class TableDecoder(_Decoder):
  """ShapeNet car, Gibson, 7-Scenes: a learned code per training scene and an up-convolution
  decoder (`camrep.models.composite.TableSynthesis`)."""

  reads_context = False

  def __init__(self, run: Resolved, num_scenes: int):
    m = run.config.model
    module = TableSynthesis(
      num_scenes=num_scenes,
      scene_dim=m.scene_dim,
      width=m.width,
      image_size=m.image_size,
      per_scene_norm=m.per_scene_norm,
      norm_eps=m.norm_eps,
      gamma_init_one=m.gamma_init_one,
      dtype=run.dtype,
    )
    super().__init__(run, module)

  def _init_module(self, key, images, vecs, scenes):
    return jax.jit(self.module.init)(key, scenes, vecs)

  def _render(self, params_model, images, vecs, scenes):
    pred, _ = self.module.apply({"params": params_model}, scenes, vecs)
    return pred, images

  def predict(self, params, batch, *, mode="nearest", keys=(None, None), transform=None, **_):
    q = _query_vectors(self, params, batch, mode, keys[1], transform)
    pred, _ = self.module.apply({"params": params["model"]}, batch["scene"], q)
    return pred


class ConvDraw(_VectorFed):
  """GQN's generator (`camrep.models.convdraw`), trained on its negative ELBO with the pixel std
  annealed by the step (config.loss.sigma_*) and an optional KL weight schedule
  (config.loss.kl_*); fed GQN's 7-D pose vector (rep.kind "lowdim", no parameters). Predictions
  are the mean image of one prior sample with the scenes' `sample_keys`, clipped to [-1, 1]."""

  variants = {"sample": 1.0, "prior_mean": 0.0}
  reads_context = True

  @classmethod
  def check(cls, run):
    """The GQN task's layout and GQN's 7-D pose vector (rep.kind "lowdim"), every field the
    generator reads (`GENERATOR_FIELDS`), float32."""
    config = run.config
    gqn_layout = TASKS.get(config.task) is GQNDecoder
    if not gqn_layout or run.encoding is not pose_encodings.LowDimEncoding:
      raise ConfigError(
        "model.kind='convdraw' (GQN's generator) needs task='gqn' and rep.kind='lowdim' (its 7-D "
        f"pose vector; the ELBO trains the model group only), got task={config.task!r}, "
        f"rep.kind={run.encoding.name!r}"
      )
    missing = [f for f in GENERATOR_FIELDS if _field(config, f) is None]
    if missing:
      raise ConfigError(
        f"model.kind='convdraw' (GQN's generator) reads config.{', config.'.join(missing)}, "
        "which this config lacks: derive it from configs/gqn_convdraw.py, which sets them "
        "(configs/common.py:base does not)"
      )
    if run.dtype is not None:
      raise ConfigError(
        f"model.dtype={config.model.dtype!r} is implemented for model.kind='decoder' only; "
        "GQN's generator (convdraw) computes in float32"
      )

  def __init__(self, run: Resolved, num_scenes: int | None = None):
    del num_scenes  # the context views give the scene
    m = run.config.model
    module = convdraw.GQNConvDraw(width=m.width, steps=m.draw_steps, z_channels=m.z_channels)
    super().__init__(run, module)
    self.n_context = int(run.config.data.n_context)
    self.loss_weight = 1.0  # the pose input has no parameters: the objective is the ELBO's

  @property
  def temperature(self) -> float:
    """config.model.draw_temperature: 1 GQN's sample, 0 the prior mean."""
    return float(self.config.model.get("draw_temperature", 1.0))

  def _init_module(self, key, images, vecs, scenes):
    c = self.n_context
    keys = jax.random.split(key, images.shape[0])
    return jax.jit(self.module.init)(
      key, images[:, :c], vecs[:, :c], vecs[:, c:], images[:, c:], keys
    )

  def loss(self, params, batch, key, step):
    """Terms: elbo (negative ELBO per query image, nats) = nll + kl; the total is nll +
    kl_weight kl (= elbo unless a KL weight schedule is set); rec (L_rec of the posterior mean,
    comparable with the decoders' train/rec); sigma (pixel std of this step); kl_weight."""
    L = self.config.loss
    keys = scene_keys(key, batch["pose"].shape[0])
    images = to_float_images(batch["image"])
    vecs = self.vectors(params["rep"], batch["pose"])
    c = self.n_context
    target = images[:, c:]
    mean, aux = self.module.apply(
      {"params": params["model"]}, images[:, :c], vecs[:, :c], vecs[:, c:], target, keys
    )
    sigma = convdraw.pixel_sigma(
      step, initial=L.sigma_initial, final=L.sigma_final, anneal_steps=L.sigma_anneal_steps
    )
    beta = convdraw.kl_weight(
      step, initial=L.get("kl_weight_initial", 1.0), anneal_steps=L.get("kl_anneal_steps", 0)
    )
    loss, terms = convdraw.negative_elbo(mean, target, aux["kl"], sigma, beta)
    rec = jnp.mean(jnp.sum((mean - target) ** 2, axis=(-3, -2, -1)))
    return loss, {**terms, "rec": rec, "sigma": sigma, "kl_weight": beta}

  def predict(
    self, params, batch, *, mode="nearest", keys=(None, None), transform=None, temperature=None
  ):
    ctx = to_float_images(batch["context_image"])
    c = self.vectors(params["rep"], batch["context_pose"], mode=mode, keys=keys[0])
    q = _query_vectors(self, params, batch, mode, keys[1], transform)
    t = self.temperature if temperature is None else temperature
    pred, _ = self.module.apply(
      {"params": params["model"]}, ctx, c, q, sample_keys(batch["scene"]), t, method="sample"
    )
    return jnp.clip(pred, -1.0, 1.0)


class MVTSynthesizer(Synthesizer):
  """The multi-view transformer (`camrep.models.mvt`, LVSM-style) on the GQN layout: the first
  `n_context` views of a scene are its context, the others its queries, each query rendered from
  the context images and the cameras of all views through the conditioning `config.model.camera`
  (`conditionings.CONDITIONINGS`). Trained on L_rec (eq. 9, as the decoders); "rep" holds the
  conditioning's parameters (`CameraConditioning.init`: the learned pose system of (d), (e); {}
  for the fixed encodings) and its objective adds the conditioning's rotation loss
  (`pose_loss`).

  Attributes:
    conditioning: the camera conditioning.
    posed: the transformer tied to it (`mvt.PosedMVT`).
  """

  reads_context = True
  # Every conditioning takes the noise test's noise the same way: on the query pose.
  noise_on = "pose"

  def __init__(self, run: Resolved, num_scenes: int | None = None):
    del num_scenes  # the context views give the scene
    self.conditioning = conditionings.from_config(run.config, run.spec)
    module = mvt.SIZES[run.config.model.size](dtype=run.dtype)
    self.posed = mvt.PosedMVT(module, self.conditioning)
    # The learned conditionings' own pose system (one DOF per column) is the run's.
    super().__init__(run, module, self.conditioning.spec or run.spec)
    self.n_context = int(run.config.data.n_context)

  @property
  def reads_pose_vectors(self) -> bool:
    return self.conditioning.vector_input

  @property
  def own_pose_system(self) -> bool:
    return self.conditioning.spec is not None

  @classmethod
  def check(cls, run):
    """An unknown model.size or model.camera, rep.kind other than 'grid' (the learned
    conditionings' pose system), a conditioning the data or the pose system cannot feed, or a
    relative transform wider than a head."""
    m, spec = run.config.model, run.spec
    if m.size not in mvt.SIZES:
      raise ConfigError(f"unknown model.size {m.size!r}; choose one of {tuple(mvt.SIZES)}")
    if run.encoding is not pose_encodings.GridEncoding:
      raise ConfigError(
        "task='mvt' reads the learned pose system through model.camera (learned_abs, "
        f"learned_rel): rep.kind must be 'grid', got {run.encoding.name!r}"
      )
    try:
      conditioning = conditionings.from_config(run.config, spec)
    except ValueError as e:
      raise ConfigError(f"--config.model.camera={m.camera!r}: {e}") from None
    if not conditioning.relative:
      return
    module = mvt.SIZES[m.size]()
    grid = mvt.PatchGrid(module.patch, module.patch, module.patch)
    poses = jax.ShapeDtypeStruct((1, 1, spec.pose_dim), jnp.float32)
    rep = jax.eval_shape(conditioning.init, jax.random.key(0))
    codes = jax.eval_shape(lambda r, p: conditioning.view_codes(r, p, grid), rep, poses)
    *_, k, b, _ = codes.transform.D.shape
    try:
      relative_attention.HeadLayout.of(module.width // module.heads, k, b)
    except ValueError as e:
      raise ConfigError(
        f"--config.model.camera={m.camera!r} with model.size={m.size!r}: {e} (learned_rel: "
        "the number of DOFs * rep.n_blocks * rep.block_size must fit in a head)"
      ) from None

  def init(self, key, batch):
    """`mvt.PosedMVT.init` on the training layout (views [:C] context, [C:] queries)."""
    images = to_float_images(jnp.asarray(batch["image"]))
    poses = jnp.asarray(batch["pose"])
    c = self.n_context
    return jax.jit(self.posed.init)(key, images[:, :c], poses[:, :c], poses[:, c:])

  def init_pose(self, key):
    """The conditioning's initial parameters (`CameraConditioning.init`; {} for the fixed
    encodings), drawn as `mvt.PosedMVT.init` draws them."""
    return self.conditioning.init(jax.random.split(key)[1])

  def _codes(self, params_rep, poses, grid, *, mode, keys, transform=None):
    """ViewCodes of poses (S, V, P): the conditioning's, or for one that reads the pose vectors
    v(p), `per_dof` quantised by `mode` / `keys` and passed through `transform` first."""
    if not self.conditioning.vector_input:
      if transform is not None:
        raise ValueError(_NO_VECTORS.format(type(self.conditioning).__name__))
      return self.conditioning.view_codes(params_rep, poses, grid)
    vecs = self.per_dof(params_rep, poses, mode=mode, keys=keys)
    vecs = vecs if transform is None else transform(vecs)
    return self.conditioning.codes_of_vectors(P.concat(vecs, self.spec), grid)

  def loss(self, params, batch, key, step):
    del step
    _, k_quant = jax.random.split(key)
    keys = scene_keys(k_quant, batch["pose"].shape[0])
    images, c = to_float_images(batch["image"]), self.n_context
    grid = self.posed.grid(images)
    # All views of a scene at once, quantised with the scene's key (as the decoders' `loss`).
    codes = self._codes(
      params["rep"], batch["pose"], grid, mode=self.config.rep.quantisation, keys=keys
    )
    ctx_codes = jax.tree.map(lambda a: a[:, :c], codes)
    query_codes = jax.tree.map(lambda a: a[:, c:], codes)
    pred, _ = self.module.apply({"params": params["model"]}, images[:, :c], ctx_codes, query_codes)
    err = (pred - images[:, c:]) ** 2
    rec = jnp.mean(jnp.sum(err, axis=(-3, -2, -1)))
    return rec, {"rec": rec, "mse": jnp.mean(err)}

  def predict(self, params, batch, *, mode="nearest", keys=(None, None), transform=None, **_):
    ctx = to_float_images(batch["context_image"])
    grid = self.posed.grid(ctx)
    rep = params["rep"]
    c = self._codes(rep, batch["context_pose"], grid, mode=mode, keys=keys[0])
    q = self._codes(rep, batch["target_pose"], grid, mode=mode, keys=keys[1], transform=transform)
    pred, _ = self.module.apply({"params": params["model"]}, ctx, c, q)
    return pred

  def pose_loss(self, params_rep, batch, key):
    """The conditioning's own loss (`CameraConditioning.pose_loss`: loss.rot_weight sum_l
    L_rot,l of eq. 9 for the learned ones, zero otherwise)."""
    del batch
    return self.conditioning.pose_loss(key, params_rep)


_NO_VECTORS = (
  "the noise test perturbs the per-DOF pose vectors v(p) (paper section 4.3); the {} "
  "conditioning feeds the transformer no such vectors (only model.camera='learned_abs' does)"
)


def _query_vectors(model: Synthesizer, params, batch, mode, keys, transform) -> Array:
  vecs = model.per_dof(params["rep"], batch["target_pose"], mode=mode, keys=keys)
  return P.concat(vecs if transform is None else transform(vecs), model.spec)


def check_config(run: Resolved) -> None:
  """Raises ConfigError on model / layout combinations the train step cannot run."""
  config, encoding = run.config, run.encoding
  d = config.data
  context = reads_context(config)
  if context and not 1 <= d.n_context < d.views_per_scene:
    raise ConfigError(
      f"data.n_context must be in [1, views_per_scene) so that each scene has query views, "
      f"got n_context={d.n_context}, views_per_scene={d.views_per_scene}"
    )
  if config.loss.data_pairs and encoding.regularised and d.mode != "pairs":
    raise ConfigError(
      "loss.data_pairs reads the batch's views as (anchor, partner) pairs: it needs "
      f"data.mode='pairs', got {d.mode!r} (GQN rooms: leave data_pairs off)"
    )


def _field(config, path: str):
  """config's value at "section.name", None where absent."""
  section, _, name = path.rpartition(".")
  return config.get(section, {}).get(name) if section else config.get(name)


TASKS: dict[str, type[Synthesizer]] = {
  "gqn": GQNDecoder,
  "table": TableDecoder,
  "mvt": MVTSynthesizer,
}
"""config.task -> camrep's model of that task ("mvt": the multi-view transformer,
configs/lvsm.py)."""


def model_class(kind: str, task: str) -> type[Synthesizer]:
  """The view-synthesis model's class: GQN's generator for `model.kind` "convdraw", else camrep's
  model of `task` (`TASKS`).

  Raises:
    ValueError: an unknown model.kind or task.
  """
  if kind not in MODEL_KINDS:
    raise ValueError(f"unknown model.kind {kind!r}; choose one of {MODEL_KINDS}")
  if kind == "convdraw":
    return ConvDraw
  if task not in TASKS:
    raise ValueError(f"unknown task {task!r}; choose one of {tuple(TASKS)}")
  return TASKS[task]


def reads_context(config) -> bool:
  """Whether the config's model encodes context views of each scene (the GQN task: an encoder
  and a decoder, or GQN's generator) rather than keeping a table of scene vectors (False for
  an unknown task, which the config's validation refuses)."""
  return config.task in TASKS and TASKS[config.task].reads_context


def is_generator(config) -> bool:
  """Whether the config's model is GQN's generator (ConvDRAW, trained on its ELBO): `model.kind`
  "convdraw" (another unknown kind: False; the schema's rule names it)."""
  return config.model.get("kind", "decoder") == "convdraw"


def pose_input(run: Resolved, spec: P.PoseSystemSpec) -> pose_encodings.PoseEncoding:
  """The run's pose input (`run.encoding`) on pose system `spec`; GQN's low-dim vector takes the
  rooms' camera height and pitch from `config.data.family` when the data's setting uses GQN's 7-D
  vector (`Setting.gqn_pose_vector`)."""
  family = run.config.data.family
  camera = pose_encodings.gqn_lowdim_constants(family) if run.setting.gqn_pose_vector else None
  return run.encoding.create(run.setting, spec, camera=camera)

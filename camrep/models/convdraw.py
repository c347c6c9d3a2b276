"""GQN's generator (Eslami et al., Science 2018, supplementary), the paper's view-synthesis
baseline: the "tower" representation network summed over context views, and a convolutional
DRAW generator with ConvLSTM cores, a latent variable per generation step and its ELBO.

Shapes at width 1.0 (S scenes, C context views, Q query views, images 64 x 64 x 3 in [-1, 1],
pose vectors of size P = 7: GQN's (x, y, z, sin yaw, cos yaw, sin pitch, cos pitch), which camrep
computes as `rep.kind = "lowdim"`):

  Tower, per context view (ReLU after every conv; the 16 x 16 pose concat as Eslami et al.):
    conv1  2x2 s2, 256                          -> 32 x 32 x 256   ("skip" input)
    conv2  2x2 s2, 256                          -> 16 x 16 x 256   (skip)
    conv3  3x3, 128 on conv1; conv4 2x2 s2, 256 -> 16 x 16 x 256   (+ skip)
    concat the pose vector tiled to 16 x 16     -> 16 x 16 x (256 + P)
    conv5  3x3, 256                             -> 16 x 16 x 256   (skip)
    conv6  3x3, 128; conv7 3x3, 256             -> 16 x 16 x 256   (+ skip)
    conv8  1x1, 256                             -> 16 x 16 x 256
  r = sum over the C context views              -> (S, 16, 16, 256)

  ConvDRAW, per query view, L = 12 steps l, all at 16 x 16 (cores shared across steps):
    prior     (mu_p, log sigma_p) = conv5x5(h_g)                       3 + 3 channels
    inference (h_e, c_e) = ConvLSTM_e([h_g, down(x_q), v_q, r], h_e, c_e)    128 channels
    posterior (mu_q, log sigma_q) = conv5x5(h_e)                       3 + 3 channels
    z ~ posterior (training) or prior (sampling)                       16 x 16 x 3
    generator (h_g, c_g) = ConvLSTM_g([z, v_q, r], h_g, c_g)           128 channels
    canvas    u = u + h_g                                              16 x 16 x 128
  image mean  conv1x1(convT 4x4 s4(u)) -> 64 x 64 x 3, in [-1, 1] units (not squashed).
  down(x_q) is a 4x4 stride-4 conv of the target (3 channels), as the Eslami et al. inference
  network sees the image at the cores' resolution.

Loss (the negative ELBO per target image, in nats, minimised):
  -ELBO = sum_l KL(q_l || p_l) + sum_pixels -log N(x | mu, sigma_t^2),
  with pixels mapped to [0, 1] (GQN's units, so that sigma has the meaning of the GQN paper)
  and sigma_t the annealed pixel standard deviation (`pixel_sigma`).

Hyper-parameters and their sources (BUILD_NOTES, "GQN generator (ConvDRAW)"):
  L = 12 steps, ConvLSTM kernel 5x5, prior / posterior heads 5x5, output head 1x1, 4x4 stride-4
    upsampling, hidden 128, r 256: Eslami et al. 2018 supplement, as kept by
    wohlert/generative-query-network-pytorch (gqn/generator.py: h_dim=128, L=12, kernel 5, SCALE 4;
    run-gqn.py: r_dim=256) and ogroth/tf-gqn (gqn/gqn_params.py: LSTM and eta kernel 5, external
    kernel 1, "SEQ_LENGTH ... orig.: 12").
  Latent 3 channels per step: the task brief; both open-source implementations above use
    64 (`z_channels` is a field; 3 keeps the KL small and the cores cheap).
  Pixel sigma 2.0 -> 0.7 linearly over 200k steps; Adam lr 5e-4 -> 5e-5 linearly over 1.6M steps,
    b1 0.9, b2 0.999, eps 1e-8: wohlert run-gqn.py (sigma_i 2.0, sigma_f 0.7, 2e5 steps; mu_i 5e-4,
    mu_f 5e-5, 1.6e6 steps), ogroth gqn_params.py (ANNEAL_SIGMA_TAU 200000, 2.0 / 0.7,
    ANNEAL_LR_TAU 1600000, "orig.: 5 * 10e-4 / 5 * 10e-5"), a TF2 port's flags (mu_i 5e-4, mu_f
    5e-5, n_mu 1.6e6, beta_1 0.9, beta_2 0.999). The schedules live in the config
    (`loss.sigma_*`, `optax.schedule = "linear"`), not here.

Deviations: the canvas is accumulated at 16 x 16 and upsampled once (the implementations above
upsample every h_g and sum at 64 x 64; the transposed conv is linear, so the two agree up to its
bias, counted once here instead of L times); ConvLSTM gates read [input, h] (the standard
ConvLSTM; wohlert's cell reads the input only); forget-gate bias 0.
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp

from camrep.models import layers

Array = jax.Array

CORE_KERNEL = 5  # ConvLSTM and prior / posterior head kernels (Eslami et al.; ogroth, wohlert)
SCALE = 4  # 64 x 64 images, 16 x 16 cores: 4x4 stride-4 down / upsampling


def tile_pose(v: Array, size: int) -> Array:
  """(..., P) -> (..., size, size, P): the pose vector repeated at every pixel."""
  return jnp.broadcast_to(v[..., None, None, :], (*v.shape[:-1], size, size, v.shape[-1]))


def gaussian_kl(mu_q: Array, log_sigma_q: Array, mu_p: Array, log_sigma_p: Array) -> Array:
  """KL(N(mu_q, sigma_q^2) || N(mu_p, sigma_p^2)) per element (>= 0), shapes broadcast.

  = log sigma_p - log sigma_q + (sigma_q^2 + (mu_q - mu_p)^2) / (2 sigma_p^2) - 1/2.
  """
  var_ratio = jnp.exp(2.0 * (log_sigma_q - log_sigma_p))
  t = jnp.square(mu_q - mu_p) * jnp.exp(-2.0 * log_sigma_p)
  return 0.5 * (var_ratio + t - 1.0) - (log_sigma_q - log_sigma_p)


def gaussian_nll(x: Array, mu: Array, sigma: Array | float) -> Array:
  """-log N(x | mu, sigma^2) per element: 0.5 ((x - mu) / sigma)^2 + log sigma + 0.5 log 2 pi."""
  sigma = jnp.asarray(sigma, jnp.float32)
  return 0.5 * jnp.square((x - mu) / sigma) + jnp.log(sigma) + 0.5 * jnp.log(2.0 * jnp.pi)


def pixel_sigma(step: Array | int, *, initial: float, final: float, anneal_steps: int) -> Array:
  """GQN's annealed pixel std: max(final + (initial - final) (1 - step / anneal_steps), final).

  Eslami et al. 2018 supplement (2.0 -> 0.7 over 2e5 steps; see the module docstring).
  """
  frac = 1.0 - jnp.asarray(step, jnp.float32) / max(float(anneal_steps), 1.0)
  return jnp.maximum(final + (initial - final) * frac, final)


def normal_per_scene(keys: Array, shape: tuple[int, ...]) -> Array:
  """Standard normal draws (S, *shape), row s from keys[s]: independent of how scenes batch."""
  return jax.vmap(lambda k: jax.random.normal(k, shape))(keys)


class Tower(nn.Module):
  """GQN's "tower" representation network for one view (see the module docstring).

  Attributes:
    width: channel multiplier (1.0: 256 / 128 channels).
  """

  width: float = 1.0

  @nn.compact
  def __call__(self, image: Array, v: Array) -> Array:
    """Args: image (..., 64, 64, 3) in [-1, 1]; v (..., P). Returns r (..., 16, 16, 256 w)."""
    k = layers.scaled(256, self.width)
    k2 = layers.scaled(128, self.width)
    x, lead = layers.flatten_leading(image, 3)
    v = v.reshape((-1, v.shape[-1]))
    relu = nn.relu
    skip_in = relu(layers.conv(k, 2, strides=2, name="conv1")(x))
    skip_out = relu(layers.conv(k, 2, strides=2, name="conv2")(skip_in))
    x = relu(layers.conv(k2, 3, name="conv3")(skip_in))
    x = relu(layers.conv(k, 2, strides=2, name="conv4")(x)) + skip_out
    skip_in = jnp.concatenate([x, tile_pose(v, x.shape[-2])], axis=-1)
    skip_out = relu(layers.conv(k, 3, name="conv5")(skip_in))
    x = relu(layers.conv(k2, 3, name="conv6")(skip_in))
    x = relu(layers.conv(k, 3, name="conv7")(x)) + skip_out
    r = relu(layers.conv(k, 1, name="conv8")(x))
    return r.reshape((*lead, *r.shape[1:]))


class ConvLSTMCell(nn.Module):
  """Convolutional LSTM cell: gates = conv_kxk([input, h]); c' = f c + i g; h' = o tanh(c').

  Attributes:
    features: hidden (and cell) channels.
    kernel: conv kernel size.
  """

  features: int
  kernel: int = CORE_KERNEL

  @nn.compact
  def __call__(self, x: Array, h: Array, c: Array) -> tuple[Array, Array]:
    """Args: x (N, H, W, Cin); h, c (N, H, W, features). Returns the new (h, c)."""
    gates = layers.conv(4 * self.features, self.kernel, name="gates")(
      jnp.concatenate([x, h], axis=-1)
    )
    i, f, o, g = jnp.split(gates, 4, axis=-1)
    c = nn.sigmoid(f) * c + nn.sigmoid(i) * jnp.tanh(g)
    return nn.sigmoid(o) * jnp.tanh(c), c


class GQNConvDraw(nn.Module):
  """GQN: tower over context views + ConvDRAW generator (module docstring has the layout).

  `__call__` runs the posterior path (training: the ELBO's terms and the posterior-sampled mean
  image); `sample` runs the prior path (prediction), deterministic given its keys.

  Attributes:
    width: channel multiplier of the tower and the cores (1.0: r 256, hidden 128).
    steps: generation steps L (12).
    z_channels: latent channels per step (3).
  """

  width: float = 1.0
  steps: int = 12
  z_channels: int = 3

  def setup(self):
    h = layers.scaled(128, self.width)
    self.tower = Tower(width=self.width, name="tower")
    self.inference_core = ConvLSTMCell(h, name="inference_core")
    self.generator_core = ConvLSTMCell(h, name="generator_core")
    self.prior_head = layers.conv(2 * self.z_channels, CORE_KERNEL, name="prior")
    self.posterior_head = layers.conv(2 * self.z_channels, CORE_KERNEL, name="posterior")
    self.downsample = layers.conv(3, SCALE, strides=SCALE, name="downsample")
    self.upsample = nn.ConvTranspose(
      h,
      (SCALE, SCALE),
      strides=(SCALE, SCALE),
      padding="VALID",
      kernel_init=layers.kernel_init,
      name="upsample",
    )
    self.observation = layers.conv(3, 1, name="observation")
    self.hidden = h

  def represent(self, context_images: Array, context_vecs: Array) -> Array:
    """Scene representation r: (S, C, 64, 64, 3), (S, C, P) -> (S, 16, 16, 256 w), summed."""
    return jnp.sum(self.tower(context_images, context_vecs), axis=1)

  def _inputs(self, r: Array, query_vecs: Array) -> tuple[Array, Array, tuple[int, int]]:
    """(S, 16, 16, R), (S, Q, P) -> r and v per query image, flattened to N = S Q."""
    S, Q = query_vecs.shape[:2]
    n = r.shape[-2]
    r_q = jnp.broadcast_to(r[:, None], (S, Q, *r.shape[1:])).reshape((S * Q, *r.shape[1:]))
    v_q = tile_pose(query_vecs, n).reshape((S * Q, n, n, query_vecs.shape[-1]))
    return r_q, v_q, (S, Q)

  def _draws(self, keys: Array, step: int, SQ: tuple[int, int], n: int) -> Array:
    """Standard normal latent noise of one step: (S Q, n, n, z), scene s from keys[s]."""
    S, Q = SQ
    eps = normal_per_scene(
      jax.vmap(lambda k: jax.random.fold_in(k, step))(keys), (Q, n, n, self.z_channels)
    )
    return eps.reshape((S * Q, n, n, self.z_channels))

  def _render(self, u: Array, SQ: tuple[int, int]) -> Array:
    """Canvas (S Q, 16, 16, h) -> image mean (S, Q, 64, 64, 3)."""
    x = self.observation(self.upsample(u))
    return x.reshape((*SQ, *x.shape[1:]))

  def __call__(
    self,
    context_images: Array,
    context_vecs: Array,
    query_vecs: Array,
    query_images: Array,
    keys: Array,
  ) -> tuple[Array, dict]:
    """Posterior path (training).

    Args:
      context_images: (S, C, 64, 64, 3) in [-1, 1].
      context_vecs: (S, C, P) pose vectors of the context views.
      query_vecs: (S, Q, P) pose vectors of the query views.
      query_images: (S, Q, 64, 64, 3) in [-1, 1], the targets the posterior reads.
      keys: (S,) PRNG keys, one per scene (latent draws of step l fold in l).

    Returns:
      mean images (S, Q, 64, 64, 3) in [-1, 1] units, and aux {"kl": (S, Q) KL summed over steps
      and latent elements, "kl_steps": (L,) mean KL per step, "r": (S, 16, 16, R)}.
    """
    r = self.represent(context_images, context_vecs)
    r_q, v_q, SQ = self._inputs(r, query_vecs)
    N, n = r_q.shape[0], r_q.shape[1]
    x_q = self.downsample(query_images.reshape((N, *query_images.shape[2:])))
    zeros = jnp.zeros((N, n, n, self.hidden), r_q.dtype)
    h_g, c_g, h_e, c_e, u = zeros, zeros, zeros, zeros, zeros
    kl, kl_steps = jnp.zeros((N,), jnp.float32), []
    for step in range(self.steps):
      mu_p, ls_p = jnp.split(self.prior_head(h_g), 2, axis=-1)
      h_e, c_e = self.inference_core(jnp.concatenate([h_g, x_q, v_q, r_q], -1), h_e, c_e)
      mu_q, ls_q = jnp.split(self.posterior_head(h_e), 2, axis=-1)
      z = mu_q + jnp.exp(ls_q) * self._draws(keys, step, SQ, n)
      h_g, c_g = self.generator_core(jnp.concatenate([z, v_q, r_q], -1), h_g, c_g)
      u = u + h_g
      kl_l = jnp.sum(gaussian_kl(mu_q, ls_q, mu_p, ls_p), axis=(-3, -2, -1))
      kl = kl + kl_l
      kl_steps.append(jnp.mean(kl_l))
    aux = {"kl": kl.reshape(SQ), "kl_steps": jnp.stack(kl_steps), "r": r}
    return self._render(u, SQ), aux

  def sample(
    self,
    context_images: Array,
    context_vecs: Array,
    query_vecs: Array,
    keys: Array,
    temperature: float = 1.0,
  ) -> tuple[Array, dict]:
    """Prior path (prediction): z_l ~ N(mu_p, sigma_p^2) from the generator's own state.

    Args:
      context_images, context_vecs, query_vecs: as `__call__`.
      keys: (S,) PRNG keys, one per scene; the same keys give the same images.
      temperature: z_l = mu_p + temperature sigma_p eps; 1 is GQN's sample, 0 the prior mean
        (deterministic, the keys unused).

    Returns:
      mean images (S, Q, 64, 64, 3) in [-1, 1] units (not clipped), and aux {"r"}.
    """
    r = self.represent(context_images, context_vecs)
    r_q, v_q, SQ = self._inputs(r, query_vecs)
    N, n = r_q.shape[0], r_q.shape[1]
    zeros = jnp.zeros((N, n, n, self.hidden), r_q.dtype)
    h_g, c_g, u = zeros, zeros, zeros
    for step in range(self.steps):
      mu_p, ls_p = jnp.split(self.prior_head(h_g), 2, axis=-1)
      z = mu_p + temperature * jnp.exp(ls_p) * self._draws(keys, step, SQ, n)
      h_g, c_g = self.generator_core(jnp.concatenate([z, v_q, r_q], -1), h_g, c_g)
      u = u + h_g
    return self._render(u, SQ), {"r": r}


def kl_weight(step: Array | int, *, initial: float, anneal_steps: int) -> Array:
  """The KL term's weight beta: `initial` falling linearly to 1 over `anneal_steps`, then 1.

  camrep option for short runs (GQN's ELBO: beta = 1 throughout, `anneal_steps` 0).
  """
  if anneal_steps <= 0:
    return jnp.asarray(1.0, jnp.float32)
  return pixel_sigma(step, initial=initial, final=1.0, anneal_steps=anneal_steps)


def negative_elbo(
  mean: Array, target: Array, kl: Array, sigma: Array | float, beta: Array | float = 1.0
) -> tuple[Array, dict[str, Array]]:
  """-ELBO per target image, averaged over images (the training loss), and its terms.

  Pixels are mapped [-1, 1] -> [0, 1] before the Gaussian NLL, so `sigma` is in GQN's units.

  Args:
    mean: (S, Q, H, W, 3) image means in [-1, 1] units (`GQNConvDraw.__call__`).
    target: (S, Q, H, W, 3) targets in [-1, 1].
    kl: (S, Q) KL summed over steps (aux["kl"]).
    sigma: the pixel std (scalar).
    beta: the KL term's weight in the minimised loss (`kl_weight`; 1: the negative ELBO).

  Returns:
    (mean over images of nll + beta kl, {"elbo": mean of nll + kl, "nll": mean per-image NLL,
     "kl": mean per-image KL}); all in nats per image.
  """
  nll = jnp.sum(gaussian_nll(0.5 * (target + 1.0), 0.5 * (mean + 1.0), sigma), axis=(-3, -2, -1))
  nll, kl = jnp.mean(nll), jnp.mean(kl)
  return nll + beta * kl, {"elbo": nll + kl, "nll": nll, "kl": kl}


# Test-only: two steps at 1/32 width (tower 8 channels, hidden 4).
GQNConvDrawTiny = functools.partial(GQNConvDraw, width=1 / 32, steps=2)

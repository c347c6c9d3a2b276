"""Tests of camrep.models: shapes, ranges, stable parameter names, numerics of the shared layers.

Models run at tiny widths; paper-width models are only traced with `jax.eval_shape` (no compute).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from camrep import models
from camrep.models import layers
from tests.utils import assert_close, x64

SDS = jax.ShapeDtypeStruct
POSE_DIM = 192  # GQN rooms: v_view (96) || v_loc (96).
STYLE_KEYS = ("gamma8", "beta8", "gamma16", "beta16")


pytestmark = pytest.mark.usefixtures("fast_compile")


def _init(module, key, *args):
  """Jitted `module.init` (one compile instead of one per op)."""
  return jax.jit(module.init)(key, *args)


def _apply(module, variables, *args):
  """Jitted `module.apply`."""
  return jax.jit(module.apply)(variables, *args)


def _abstract_params(module, *args):
  """Parameter tree of `module.init(key, *args)` as ShapeDtypeStructs, at no cost."""
  return jax.eval_shape(lambda *a: module.init(jax.random.key(0), *a), *args)["params"]


def _gqn_inputs(rng, scenes=2, views=3, queries=2):
  images = jnp.asarray(rng.uniform(-1, 1, (scenes, views, 64, 64, 3)), jnp.float32)
  poses = jnp.asarray(rng.normal(size=(scenes, views, POSE_DIM)) * 0.1, jnp.float32)
  queries = jnp.asarray(rng.normal(size=(scenes, queries, POSE_DIM)) * 0.1, jnp.float32)
  return images, poses, queries


@pytest.fixture(scope="module")
def gqn_tiny():
  """Tiny GQN encoder and decoder with initialised parameters and example inputs."""
  rng = np.random.default_rng(0)
  images, poses, queries = _gqn_inputs(rng)
  enc, dec = models.GQNEncoderTiny(), models.GQNDecoderTiny()
  enc_vars = _init(enc, jax.random.key(1), images, poses)
  scene, _ = _apply(enc, enc_vars, images, poses)
  dec_vars = _init(dec, jax.random.key(2), scene, queries)
  return {
    "enc": enc,
    "dec": dec,
    "enc_vars": enc_vars,
    "dec_vars": dec_vars,
    "images": images,
    "poses": poses,
    "queries": queries,
  }


# --------------------------------------------------------------------------------------------
# Shared layers.


def test_lrelu_slope_is_0_2():
  x = jnp.array([-2.0, -0.5, 0.0, 0.5, 3.0])
  assert_close(models.lrelu(x), [-0.4, -0.1, 0.0, 0.5, 3.0], atol=1e-7)


def test_upsample_is_nearest_neighbour():
  x = np.arange(2 * 2 * 3 * 4, dtype=np.float32).reshape(2, 2, 3, 4)
  y = np.asarray(models.upsample2(jnp.asarray(x)))
  assert y.shape == (2, 4, 6, 4)
  assert_close(y, x.repeat(2, axis=1).repeat(2, axis=2))


def _adain_reference(x, gamma, beta, eps):
  """Numpy AdaIN: per sample and channel over (H, W), biased variance, eps inside the sqrt."""
  mu = x.mean(axis=(1, 2), keepdims=True)
  var = ((x - mu) ** 2).mean(axis=(1, 2), keepdims=True)
  return gamma[:, None, None, :] * (x - mu) / np.sqrt(var + eps) + beta[:, None, None, :]


def test_instance_norm_and_adain_match_numpy():
  rng = np.random.default_rng(3)
  x = rng.normal(size=(2, 5, 6, 4)) * 3.0 + 1.5
  x[0, :, :, 1] = 0.7  # a constant channel: output must be beta exactly.
  x[1, :, :, 2] *= 1e-4  # variance ~1e-8 < eps: the eps placement matters.
  gamma = rng.normal(size=(2, 4))  # raw scale, may be negative
  beta = rng.normal(size=(2, 4))
  with x64():
    got = np.asarray(models.adain(jnp.asarray(x), jnp.asarray(gamma), jnp.asarray(beta)))
    normed = np.asarray(models.instance_norm(jnp.asarray(x)))
  ref = _adain_reference(x, gamma, beta, 1e-7)
  assert_close(got, ref, atol=1e-10, rtol=1e-10)
  assert_close(normed, _adain_reference(x, np.ones((2, 4)), np.zeros((2, 4)), 1e-7), atol=1e-10)
  assert_close(got[0, :, :, 1], np.full((5, 6), beta[0, 1]), atol=1e-12)
  # eps outside the sqrt (sqrt(var) + eps) gives a visibly different result on the tiny channel.
  mu = x.mean(axis=(1, 2), keepdims=True)
  sd = np.sqrt(((x - mu) ** 2).mean(axis=(1, 2), keepdims=True))
  wrong = gamma[:, None, None, :] * (x - mu) / (sd + 1e-7) + beta[:, None, None, :]
  assert np.abs(wrong[1, :, :, 2] - got[1, :, :, 2]).max() > 1e-2
  # float32 path, the one the models use.
  got32 = models.adain(
    jnp.asarray(x, jnp.float32), jnp.asarray(gamma, jnp.float32), jnp.asarray(beta, jnp.float32)
  )
  assert_close(got32, ref, atol=2e-4, rtol=2e-4)


def test_scene_table_init_and_normalisation():
  idx = jnp.array([[0, 4], [4, 6]])
  table = models.SceneTable(num_scenes=7, dim=96)
  variables = _init(table, jax.random.key(0), idx)
  raw = np.asarray(variables["params"]["table"])
  assert raw.shape == (7, 96)
  assert 0.5e-3 < raw.std() < 2e-3  # N(0, 0.001^2)
  u, aux = _apply(table, variables, idx)
  assert u.shape == (2, 2, 96)
  assert_close(np.linalg.norm(u, axis=-1), np.ones((2, 2)), atol=1e-5)
  assert_close(aux["raw_norm"], np.linalg.norm(raw[np.asarray(idx)], axis=-1), rtol=1e-5)
  # 7-Scenes variant: the norm is offset by 1e-6.
  seven = models.SevenScenesSceneTable()
  sv = _init(seven, jax.random.key(0), idx)
  u7, _ = _apply(seven, sv, idx)
  rows = np.asarray(sv["params"]["table"])[np.asarray(idx)]
  ref = rows / (np.linalg.norm(rows, axis=-1, keepdims=True) + 1e-6)
  assert_close(u7, ref, atol=1e-6, rtol=1e-5)
  raw_u, _ = models.SceneTable(num_scenes=7, dim=96, normalise=False).apply(variables, idx)
  assert_close(raw_u, raw[np.asarray(idx)])


# --------------------------------------------------------------------------------------------
# GQN rooms encoder and decoder.


def test_gqn_encoder_shapes_and_keys(gqn_tiny):
  enc, variables = gqn_tiny["enc"], gqn_tiny["enc_vars"]
  out, aux = _apply(enc, variables, gqn_tiny["images"], gqn_tiny["poses"])
  c = layers.scaled(256, enc.width)
  assert out["u"].shape == (2, 128)
  for k in STYLE_KEYS:
    assert out[k].shape == (2, c)
    assert aux["per_view"][k].shape == (2, 3, c)
  assert set(aux["rms"]) == {"h5", "h7", "h9"}
  assert all(np.isfinite(v).all() for v in jax.tree_util.tree_leaves((out, aux)))
  expected = {
    "conv1", "block2_conv3", "block2_conv1", "conv3", "block4_conv3", "block4_conv1", "conv5",
    "conv6", "block7_conv3", "block7_conv1", "conv8", "block9_conv3", "block9_conv1",
    "head_u", "head_gamma8", "head_beta8", "head_gamma16", "head_beta16",
  }  # fmt: skip
  assert set(variables["params"]) == expected
  assert set(variables["params"]["conv1"]) == {"kernel", "bias"}
  # The pose vector is tiled at 16 x 16 and concatenated to the conv3 output.
  block4 = variables["params"]["block4_conv3"]["kernel"]
  assert block4.shape == (3, 3, layers.scaled(256, enc.width) + POSE_DIM, 8)


def test_gqn_encoder_sums_over_context_views(gqn_tiny):
  enc, variables = gqn_tiny["enc"], gqn_tiny["enc_vars"]
  images, poses = gqn_tiny["images"][:, :2], gqn_tiny["poses"][:, :2]
  both, aux = _apply(enc, variables, images, poses)
  # Each view alone, as its own one-view scene: (2, 2, ...) -> (4, 1, ...).
  singles, _ = _apply(enc, variables, images.reshape(4, 1, 64, 64, 3), poses.reshape(4, 1, -1))
  for k in both:
    one, two = singles[k][0::2], singles[k][1::2]
    assert_close(both[k], one + two, atol=1e-5, rtol=1e-5)
    assert_close(aux["per_view"][k][:, 0], one, atol=1e-5, rtol=1e-5)
  # Summed, not averaged: the views differ, and scenes do not mix.
  assert not np.allclose(singles["u"][0], singles["u"][1])
  swapped, _ = _apply(enc, variables, images[::-1], poses[::-1])
  assert_close(swapped["u"], both["u"][::-1], atol=1e-5, rtol=1e-5)


def test_gqn_decoder_shapes_range_and_broadcast(gqn_tiny):
  enc, dec = gqn_tiny["enc"], gqn_tiny["dec"]
  scene, _ = _apply(enc, gqn_tiny["enc_vars"], gqn_tiny["images"], gqn_tiny["poses"])
  queries = gqn_tiny["queries"]
  images, aux = _apply(dec, gqn_tiny["dec_vars"], scene, queries)
  assert images.shape == (2, 2, 64, 64, 3)
  assert np.isfinite(images).all()
  assert np.abs(images).max() <= 1.0
  assert float(jnp.std(images)) > 0.0
  assert set(aux["style"]) == set(STYLE_KEYS)
  assert set(aux["rms"]) == {"fc", "res8", "res16", "res32", "res64"}
  # Several queries per scene == one query at a time with the scene's code broadcast.
  single = {k: v[1:2] for k, v in scene.items()}
  alone, _ = _apply(dec, gqn_tiny["dec_vars"], single, queries[1:2, 1:2])
  assert_close(alone[0, 0], images[1, 1], atol=1e-5, rtol=1e-5)
  expected = {"fc"} | {f"res{r}_{p}" for r in (8, 16, 32, 64) for p in ("conv_a", "conv_b", "skip")}
  assert set(gqn_tiny["dec_vars"]["params"]) == expected
  with pytest.raises(ValueError, match="channels"):
    _apply(dec, gqn_tiny["dec_vars"], {**scene, "gamma8": scene["gamma8"][:, :3]}, queries)


def test_gqn_paper_width_parameter_count_under_9m():
  scene = {"u": SDS((1, 128), jnp.float32)} | {k: SDS((1, 256), jnp.float32) for k in STYLE_KEYS}
  enc_params = _abstract_params(
    models.GQNEncoder(), SDS((1, 6, 64, 64, 3), jnp.float32), SDS((1, 6, POSE_DIM), jnp.float32)
  )
  dec_params = _abstract_params(models.GQNDecoder(), scene, SDS((1, 3, POSE_DIM), jnp.float32))
  n_enc, n_dec = models.param_count(enc_params), models.param_count(dec_params)
  print(f"GQN paper width: encoder {n_enc:,} + decoder {n_dec:,} = {n_enc + n_dec:,} parameters")
  assert n_enc + n_dec < 9_000_000
  assert n_enc == 4_299_136 and n_dec == 4_358_150  # pin the architecture
  assert dec_params["fc"]["kernel"].shape == (128 + POSE_DIM, 4 * 4 * 256)
  assert enc_params["head_gamma16"]["kernel"].shape == (3, 3, 256, 256)


def test_intermediate_shapes_of_encoder():
  shapes = models.intermediate_shapes(
    models.GQNEncoder(), SDS((2, 6, 64, 64, 3), jnp.float32), SDS((2, 6, POSE_DIM), jnp.float32)
  )
  assert shapes == {"h5": (12, 16, 16, 256), "h7": (12, 8, 8, 128), "h9": (12, 4, 4, 128)}


# --------------------------------------------------------------------------------------------
# Car, Gibson and 7-Scenes decoders.


def test_car_decoder_tiny_shapes_and_keys():
  dec = models.CarDecoderTiny()
  z = jnp.asarray(np.random.default_rng(4).normal(size=(2, 3, 320)) * 0.1, jnp.float32)
  variables = _init(dec, jax.random.key(0), z)
  images, aux = _apply(dec, variables, z)
  assert images.shape == (2, 3, 64, 64, 3)
  assert np.isfinite(images).all() and np.abs(images).max() <= 1.0
  assert aux["style"] == {}
  assert set(variables["params"]) == {"fc", "conv8", "conv16", "conv32", "to_rgb"}
  # Paper size: 128 x 128 output and the extra 64-channel block.
  params = _abstract_params(models.CarDecoder(), SDS((2, 320), jnp.float32))
  assert set(params) == {"fc", "conv8", "conv16", "conv32", "conv64", "to_rgb"}
  out = jax.eval_shape(
    lambda p, z: models.CarDecoder().apply({"params": p}, z)[0], params, SDS((5, 320), jnp.float32)
  )
  assert out.shape == (5, 128, 128, 3)


def test_gibson_decoder_tables_and_lookup():
  dec = models.GibsonDecoderTiny()
  rng = np.random.default_rng(5)
  z = jnp.asarray(rng.normal(size=(4, 40)) * 0.1, jnp.float32)
  idx = jnp.array([0, 2, 2, 1])
  variables = _init(dec, jax.random.key(0), z, idx)
  params = variables["params"]
  tables = {f"{g}{r}" for g in ("gamma", "beta") for r in (8, 16, 32)}
  assert set(params) == {"fc", "conv8", "conv16", "conv32", "to_rgb"} | tables
  assert params["gamma8"].shape == (3, layers.scaled(256, dec.width))
  assert params["gamma32"].shape == (3, layers.scaled(128, dec.width))
  for k in tables:  # N(0, 0.001^2): gamma ~ 0 at the start, as the authors.
    assert np.abs(params[k]).max() < 0.01
  images, aux = _apply(dec, variables, z, idx)
  assert images.shape == (4, 64, 64, 3)
  assert np.isfinite(images).all() and np.abs(images).max() <= 1.0
  assert_close(aux["style"]["gamma16"], np.asarray(params["gamma16"])[np.asarray(idx)])
  # Rows 1 and 2 share scene 2: same tables, so equal inputs give equal images.
  same, _ = _apply(dec, variables, z.at[2].set(z[1]), idx)
  assert_close(same[1], same[2], atol=1e-6)
  with pytest.raises(ValueError, match="scene_index"):
    _apply(dec, variables, z)
  # Gradients reach every parameter and are finite despite gamma ~ 0.
  grads = jax.jit(jax.grad(lambda p: jnp.sum(dec.apply({"params": p}, z, idx)[0] ** 2)))(params)
  assert all(np.isfinite(g).all() for g in jax.tree_util.tree_leaves(grads))
  assert float(jnp.abs(grads["fc"]["kernel"]).max()) > 0.0


def test_gqn_decoder_gamma_offset_adds_to_the_encoder_gammas(gqn_tiny):
  enc, dec = gqn_tiny["enc"], gqn_tiny["dec"]
  scene, _ = _apply(enc, gqn_tiny["enc_vars"], gqn_tiny["images"], gqn_tiny["poses"])
  shifted = {k: v + 1.0 if k.startswith("gamma") else v for k, v in scene.items()}
  want, _ = _apply(dec, gqn_tiny["dec_vars"], shifted, gqn_tiny["queries"])
  offset = models.ResAdaINDecoder(width=dec.width, gamma_offset=1.0)
  got, _ = _apply(offset, gqn_tiny["dec_vars"], scene, gqn_tiny["queries"])
  assert_close(got, want, atol=1e-6, rtol=1e-6)
  plain, _ = _apply(dec, gqn_tiny["dec_vars"], scene, gqn_tiny["queries"])
  assert not np.allclose(plain, got)


def test_gibson_gamma_init_one_option():
  dec = models.GibsonDecoderTiny(gamma_init_one=True)
  z, idx = jnp.zeros((2, 40)), jnp.array([0, 1])
  params = _init(dec, jax.random.key(0), z, idx)["params"]
  assert_close(params["gamma8"], np.ones(params["gamma8"].shape), atol=0.01)
  assert np.abs(params["beta8"]).max() < 0.01


def test_paper_size_room_decoders():
  idx = SDS((2,), jnp.int32)
  gib = _abstract_params(models.GibsonDecoder(), SDS((2, 960), jnp.float32), idx)
  assert gib["fc"]["kernel"].shape == (960, 4096)
  assert gib["gamma8"].shape == (20, 256) and gib["gamma64"].shape == (20, 64)
  assert gib["conv8"]["kernel"].shape == (4, 4, 256, 256)
  seven = _abstract_params(models.SevenScenesDecoder(), SDS((2, 288), jnp.float32), idx)
  assert seven["gamma32"].shape == (7, 128)
  shapes = models.intermediate_shapes(models.GibsonDecoder(), SDS((2, 960), jnp.float32), idx)
  assert shapes["conv16_out"] == (2, 16, 16, 256)
  assert shapes["to_rgb_out"] == (2, 128, 128, 3)


# --------------------------------------------------------------------------------------------
# Determinism.


def test_init_is_deterministic_by_key():
  dec = models.CarDecoderTiny()
  z = jnp.zeros((1, 320))
  a = _init(dec, jax.random.key(7), z)
  b = _init(dec, jax.random.key(7), z)
  c = _init(dec, jax.random.key(8), z)
  jax.tree_util.tree_map(lambda x, y: np.testing.assert_array_equal(x, y), a, b)
  assert not np.allclose(a["params"]["fc"]["kernel"], c["params"]["fc"]["kernel"])
  # Biases start at zero and kernels are glorot-uniform bounded.
  assert not np.any(a["params"]["conv16"]["bias"])
  k = np.asarray(a["params"]["conv16"]["kernel"])
  fan_in, fan_out = 4 * 4 * k.shape[2], 4 * 4 * k.shape[3]
  assert np.abs(k).max() <= np.sqrt(6.0 / (fan_in + fan_out))


@pytest.mark.parametrize(
  "kernel,stride,padding",
  [
    (1, 1, "SAME"),
    (2, 2, "SAME"),
    (3, 1, "SAME"),
    (4, 1, "SAME"),
    (4, 2, "SAME"),
    (3, 1, "VALID"),
    (4, 2, ((1, 2), (0, 1))),
  ],
)
@pytest.mark.parametrize("cin", [3, 5])
def test_fastconv_gradients_match_xla(kernel, stride, padding, cin):
  """The matmul kernel gradient and the space-to-depth forward and input gradient of strided
  convs, alone and together, equal XLA's own in float64, for every kernel / stride / padding the
  models use, odd spatial sizes, and inputs of few channels (3: the space-to-depth forward) and
  more (5)."""
  from camrep.models import fastconv

  def loss(x, w):
    y = fastconv.conv_general_dilated(
      x, w, (stride, stride), padding, dimension_numbers=("NHWC", "HWIO", "NHWC")
    )
    return jnp.sum(jnp.sin(y)), y

  def outputs(kernel_grad, strided):
    with fastconv.weight_grad(kernel_grad), fastconv.strided_input_grad(strided):
      (_, y), (dx, dw) = jax.jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))(x, w)
    return {"y": y, "dx": dx, "dw": dw}

  with x64():
    rng = np.random.default_rng(kernel * 10 + stride + cin)
    x = jnp.asarray(rng.normal(size=(3, 11, 10, cin)))
    w = jnp.asarray(rng.normal(size=(kernel, kernel, cin, 7)))
    want = outputs("xla", "xla")
    for kernel_grad, strided in (("matmul", "xla"), ("xla", "s2d"), ("matmul", "s2d")):
      got = outputs(kernel_grad, strided)
      for k in ("y", "dx", "dw"):
        assert_close(got[k], want[k], atol=1e-10, rtol=1e-10)


def test_fastconv_strided_input_gradient_reads_no_dilated_cotangent():
  """In "s2d" mode a stride-2 conv's input gradient is a stride-1 transposed conv (no product
  with the zeros of a dilated cotangent), and an RGB input's forward pass is one stride-1 conv
  over 12 channels; in "xla" mode both are XLA's own (a dilated cotangent)."""
  from camrep.models import fastconv

  x, w = jnp.ones((2, 8, 8, 3)), jnp.ones((4, 4, 3, 6))

  def jaxpr(mode):
    def loss(x_, w_):
      y = fastconv.conv_general_dilated(
        x_, w_, (2, 2), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
      )
      return jnp.sum(y**2)

    with fastconv.weight_grad("xla"), fastconv.strided_input_grad(mode):
      return str(jax.make_jaxpr(jax.grad(loss, argnums=(0, 1)))(x, w))

  assert "lhs_dilation=(2, 2)" in jaxpr("xla")
  s2d = jaxpr("s2d")
  assert "lhs_dilation=(2, 2)" not in s2d and "window_strides=(2, 2)" not in s2d
  assert fastconv.get_strided_input_grad() == "s2d"  # "auto" on the CPU backend
  with pytest.raises(ValueError, match="strided_input_grad must be one of"):
    with fastconv.strided_input_grad("fast"):
      pass
  assert not fastconv.s2d_applies((3, 3), (2, 2), ((1, 1), (1, 1)))  # 3 is not a multiple of 2
  assert not fastconv.s2d_applies((4, 4), (1, 1), ((1, 2), (1, 2)))  # stride 1: nothing to gain
  assert fastconv.s2d_applies((4, 4), (2, 2), ((1, 1), (1, 1)))


def test_fastconv_by_channels_chooses_per_layer():
  """The "by_channels" mode computes kernel gradients as matmuls (one per tap) only for convs with
  at least MATMUL_MIN_CHANNELS output channels on the CPU, XLA's own for narrower ones; both
  equal XLA's gradients."""
  from camrep.models import fastconv

  def grads(cout):
    rng = np.random.default_rng(cout)
    x = jnp.asarray(rng.normal(size=(2, 6, 6, 3)), jnp.float32)
    w = jnp.asarray(rng.normal(size=(3, 3, 3, cout)), jnp.float32)

    def loss(w_):
      y = fastconv.conv_general_dilated(
        x, w_, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
      )
      return jnp.sum(jnp.sin(y))

    return str(jax.make_jaxpr(jax.grad(loss))(w)), jax.jit(jax.grad(loss))(w)

  wide = fastconv.MATMUL_MIN_CHANNELS
  with fastconv.weight_grad("xla"):
    want = {c: grads(c)[1] for c in (wide - 1, wide)}
  with fastconv.weight_grad("by_channels"):
    assert fastconv.get_weight_grad() == "by_channels"
    assert fastconv.get_weight_grad(wide - 1) == "xla"
    assert fastconv.get_weight_grad(wide) == "matmul"
    narrow_jaxpr, narrow = grads(wide - 1)
    wide_jaxpr, wide_g = grads(wide)
  assert "dot_general" not in narrow_jaxpr  # XLA's conv gradient
  assert wide_jaxpr.count("dot_general") == 9  # one matmul per tap of the 3 x 3 kernel
  assert_close(narrow, want[wide - 1], atol=1e-4, rtol=1e-5)
  assert_close(wide_g, want[wide], atol=1e-4, rtol=1e-5)


def test_fastconv_mode_and_fallbacks():
  from camrep.models import fastconv

  with pytest.raises(ValueError, match="weight_grad must be one of"):
    fastconv.set_weight_grad("fast")
  assert fastconv.get_weight_grad() == "matmul"  # "auto" on the CPU backend
  with fastconv.weight_grad("xla"):
    assert fastconv.get_weight_grad() == "xla"
  assert fastconv.get_weight_grad() == "matmul"
  # NCHW layout and dilations go to lax unchanged.
  x, w = jnp.ones((1, 2, 5, 5)), jnp.ones((3, 2, 3, 3))
  y = fastconv.conv_general_dilated(x, w, (1, 1), "SAME", rhs_dilation=(2, 2))
  want = jax.lax.conv_general_dilated(x, w, (1, 1), "SAME", rhs_dilation=(2, 2))
  np.testing.assert_array_equal(y, want)


# --------------------------------------------------------------------------------------------
# Equivalent rewrites (layers.ConvMean, UpConv, ConcatConstantConv).


def _rewrite_grads(module, args, *, scale: float = 1.0):
  """(initial params, {rewrites on/off: (loss, grads in (params, args[0]))}) in float64."""
  params = module.init(jax.random.key(0), *args)

  def loss(p, x0, *rest):
    out = module.apply(p, x0, *rest)
    out = out[0] if isinstance(out, tuple) else out
    return sum(jnp.sum(jnp.sin(scale * y)) for y in jax.tree.leaves(out))

  res = {}
  for on in (False, True):
    with layers.rewrites(on):
      res[on] = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))(params, *args)
  return params, res


def _assert_same_function(module, args, *, scale: float = 1.0):
  """The rewritten layers create the plain layers' parameters (same tree, same values) and give
  their values and gradients (parameters and first input) to float64 round-off."""
  with layers.rewrites(False):
    plain = module.init(jax.random.key(0), *args)
  with layers.rewrites(True):
    fast = module.init(jax.random.key(0), *args)
  assert jax.tree.structure(plain) == jax.tree.structure(fast)
  jax.tree.map(np.testing.assert_array_equal, plain, fast)
  _, res = _rewrite_grads(module, args, scale=scale)
  (v0, g0), (v1, g1) = res[False], res[True]
  assert_close(v1, v0, atol=1e-10 * max(1.0, abs(float(v0))), rtol=1e-12)
  # Gradients that are 0 in exact arithmetic (biases before an instance norm) are round-off of
  # the size of the largest gradient times 1e-16 either way: compare on that scale.
  top = max(float(jnp.max(jnp.abs(g))) for g in jax.tree.leaves(g0))
  for a, b in zip(jax.tree.leaves(g1), jax.tree.leaves(g0), strict=True):
    assert_close(a, b, atol=1e-11 * top, rtol=1e-9)


@pytest.mark.parametrize("kernel", [1, 2, 3, 4])
@pytest.mark.parametrize("kind", ["ConvMean", "UpConv", "ConcatConstantConv"])
def test_rewritten_convs_compute_the_plain_layers(kind, kernel):
  """Each rewrite equals its plain form (conv then mean; conv of the nearest x2 upsampling; conv
  of x concatenated with a tiled vector) in value and gradient, odd and even kernels, sizes with
  borders on every side."""
  with x64():
    rng = np.random.default_rng(kernel)
    x = jnp.asarray(rng.normal(size=(3, 5, 6, 4)))
    args = (x, jnp.asarray(rng.normal(size=(3, 7)))) if kind == "ConcatConstantConv" else (x,)
    _assert_same_function(layers.conv(5, kernel, name="c", kind=getattr(layers, kind)), args)


@pytest.mark.parametrize(
  "name",
  [
    "gqn_encoder",
    "gqn_decoder",
    *(pytest.param(n, marks=pytest.mark.slow) for n in ("car", "gibson")),
  ],
)
def test_rewritten_models_compute_the_plain_models(name):
  """The GQN encoder and decoder and the car and Gibson decoders with their rewritten layers:
  the same parameters, values and gradients as computed as written (float64)."""
  with x64():
    rng = np.random.default_rng(0)
    images = jnp.asarray(rng.uniform(-1, 1, (1, 2, 16, 16, 3)))
    poses = jnp.asarray(rng.normal(size=(1, 2, 10)))
    z = jnp.asarray(rng.normal(size=(1, 2, 20)))
    if name == "gqn_encoder":
      _assert_same_function(models.GQNEncoderTiny(), (images, poses))
    elif name == "gqn_decoder":
      scene = {k: jnp.asarray(rng.normal(size=(1, 16))) for k in STYLE_KEYS}
      scene["u"] = jnp.asarray(rng.normal(size=(1, 128)))
      _assert_same_function(models.GQNDecoderTiny(), (scene, poses), scale=3.0)
    elif name == "car":
      _assert_same_function(models.CarDecoderTiny(), (z,), scale=3.0)
    else:
      ids = jnp.asarray([[0, 2]])
      _assert_same_function(models.GibsonDecoderTiny(), (z, ids), scale=3.0)


def test_rewrites_cut_the_paper_size_step_flops():
  """The rewrites remove over 30% of the paper-size GQN model's multiply-adds (forward and
  backward of encoder and decoder, `runtime.flops`), and restored parameters need no change."""
  from camrep.runtime import flops

  enc, dec = models.GQNEncoder(), models.GQNDecoder()
  images = SDS((30, 6, 64, 64, 3), jnp.float32)
  poses, queries = SDS((30, 6, POSE_DIM), jnp.float32), SDS((30, 3, POSE_DIM), jnp.float32)
  enc_p = _abstract_params(enc, images, poses)
  scene = jax.eval_shape(lambda p, i, q: enc.apply({"params": p}, i, q)[0], enc_p, images, poses)
  dec_p = _abstract_params(dec, scene, queries)

  def loss(ep, dp, i, p, q):
    s, _ = enc.apply({"params": ep}, i, p)
    return jnp.sum(dec.apply({"params": dp}, s, q)[0])

  counts = {}
  for on in (False, True):
    with layers.rewrites(on):
      counts[on] = flops.count_flops(
        jax.grad(loss, argnums=(0, 1)), enc_p, dec_p, images, poses, queries
      )
  assert counts[True] < 0.7 * counts[False]

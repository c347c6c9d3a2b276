"""Tests of GQN's generator (camrep.models.convdraw) and its run through the training loop
(model.kind "convdraw", configs/gqn_convdraw.py:smoke), small shapes."""

from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from camrep.configs import gqn_convdraw
from camrep.models import convdraw
from camrep.runtime import runconfig
from camrep.synthesis import components, noise, restore, train

# The fast tier (`-m "not slow"`) keeps the schedules, the KL and the configs; the model and the
# training loop run in the whole suite.
pytestmark = pytest.mark.usefixtures("fast_compile")

S, C, Q, P = 2, 2, 2, 7


def _inputs(seed=0):
  rng = np.random.default_rng(seed)
  ctx = jnp.asarray(rng.uniform(-1, 1, (S, C, 64, 64, 3)), jnp.float32)
  cvec = jnp.asarray(rng.normal(size=(S, C, P)), jnp.float32)
  qvec = jnp.asarray(rng.normal(size=(S, Q, P)), jnp.float32)
  qimg = jnp.asarray(rng.uniform(-1, 1, (S, Q, 64, 64, 3)), jnp.float32)
  return ctx, cvec, qvec, qimg


@pytest.fixture(scope="module")
def tiny():
  model = convdraw.GQNConvDrawTiny()
  ctx, cvec, qvec, qimg = _inputs()
  keys = jax.random.split(jax.random.key(0), S)
  params = jax.jit(model.init)(jax.random.key(1), ctx, cvec, qvec, qimg, keys)["params"]
  return model, params


@pytest.mark.slow
def test_shapes_and_elbo_terms(tiny):
  model, params = tiny
  ctx, cvec, qvec, qimg = _inputs()
  keys = jax.random.split(jax.random.key(2), S)
  mean, aux = model.apply({"params": params}, ctx, cvec, qvec, qimg, keys)
  assert mean.shape == (S, Q, 64, 64, 3)
  assert aux["kl"].shape == (S, Q)
  assert aux["kl_steps"].shape == (model.steps,)
  assert aux["r"].shape == (S, 16, 16, 8)  # 256 channels at width 1/32
  assert np.all(np.asarray(aux["kl"]) >= 0)
  loss, terms = convdraw.negative_elbo(mean, qimg, aux["kl"], 2.0)
  for v in (loss, *terms.values()):
    assert np.isfinite(float(v))
  np.testing.assert_allclose(float(terms["elbo"]), float(terms["nll"] + terms["kl"]), rtol=1e-6)
  assert float(terms["kl"]) >= 0
  # (Finite gradients: the smoke run below, whose step skips and flags non-finite updates.)


def test_kl_is_zero_iff_distributions_agree():
  rng = np.random.default_rng(0)
  mu, ls = rng.normal(size=(2, 100)), rng.normal(size=(2, 100)) * 0.5
  np.testing.assert_allclose(convdraw.gaussian_kl(mu[0], ls[0], mu[0], ls[0]), 0.0, atol=1e-6)
  kl = np.asarray(convdraw.gaussian_kl(mu[0], ls[0], mu[1], ls[1]))
  assert np.all(kl >= 0) and np.all(kl > 0)
  # Against a Monte-Carlo estimate for one pair.
  x = mu[0, 0] + np.exp(ls[0, 0]) * rng.normal(size=400_000)
  logq = -0.5 * ((x - mu[0, 0]) / np.exp(ls[0, 0])) ** 2 - ls[0, 0]
  logp = -0.5 * ((x - mu[1, 0]) / np.exp(ls[1, 0])) ** 2 - ls[1, 0]
  np.testing.assert_allclose(kl[0], np.mean(logq - logp), rtol=0.05, atol=0.01)


def test_pixel_sigma_schedule():
  sig = lambda n: float(convdraw.pixel_sigma(n, initial=2.0, final=0.7, anneal_steps=200_000))
  assert sig(0) == pytest.approx(2.0)
  assert sig(100_000) == pytest.approx(1.35)
  assert sig(200_000) == pytest.approx(0.7)
  assert sig(1_000_000) == pytest.approx(0.7)


@pytest.mark.slow
def test_sampling_deterministic_given_the_key(tiny):
  model, params = tiny
  ctx, cvec, qvec, _ = _inputs()
  sample = jax.jit(lambda k: model.apply({"params": params}, ctx, cvec, qvec, k, method="sample"))
  k1 = jax.random.split(jax.random.key(3), S)
  k2 = jax.random.split(jax.random.key(4), S)
  a, b, c = (np.asarray(sample(k)[0]) for k in (k1, k1, k2))
  assert a.shape == (S, Q, 64, 64, 3)
  np.testing.assert_array_equal(a, b)
  assert np.max(np.abs(a - c)) > 1e-6
  # Scene s depends only on its own key: the same key in another batch slot gives the same image.
  d = np.asarray(sample(jnp.stack([k1[0], k2[1]]))[0])
  np.testing.assert_array_equal(d[0], a[0])
  np.testing.assert_array_equal(d[1], c[1])


@pytest.mark.slow
def test_prior_mean_temperature(tiny):
  model, params = tiny
  ctx, cvec, qvec, _ = _inputs()
  sample = jax.jit(
    lambda k, t: model.apply({"params": params}, ctx, cvec, qvec, k, t, method="sample")[0]
  )
  k1 = jax.random.split(jax.random.key(3), S)
  k2 = jax.random.split(jax.random.key(4), S)
  # Temperature 1 is the default sample; temperature 0 (the prior mean) ignores the keys.
  default = model.apply({"params": params}, ctx, cvec, qvec, k1, method="sample")[0]
  np.testing.assert_allclose(np.asarray(sample(k1, 1.0)), np.asarray(default), atol=1e-6)
  np.testing.assert_allclose(np.asarray(sample(k1, 0.0)), np.asarray(sample(k2, 0.0)), atol=1e-6)
  assert np.max(np.abs(np.asarray(sample(k1, 0.0) - sample(k1, 1.0)))) > 1e-6


def test_kl_weight_schedule_and_weighted_loss():
  beta = lambda n: float(convdraw.kl_weight(n, initial=10.0, anneal_steps=1000))
  assert (beta(0), beta(500), beta(1000), beta(5000)) == pytest.approx((10.0, 5.5, 1.0, 1.0))
  assert float(convdraw.kl_weight(0, initial=10.0, anneal_steps=0)) == 1.0  # off: the ELBO
  mean, target = jnp.zeros((1, 2, 4, 4, 3)), jnp.full((1, 2, 4, 4, 3), 0.5)
  kl = jnp.asarray([[3.0, 5.0]])
  loss1, t1 = convdraw.negative_elbo(mean, target, kl, 0.7)
  loss3, t3 = convdraw.negative_elbo(mean, target, kl, 0.7, 3.0)
  assert float(loss1) == pytest.approx(float(t1["elbo"]))
  assert float(loss3) == pytest.approx(float(t3["nll"] + 3.0 * t3["kl"]))
  assert float(t3["elbo"]) == pytest.approx(float(t1["elbo"]))


def test_config_variants_build():
  for variant in (None, "quick", "smoke"):
    c = gqn_convdraw.get_config(variant)
    components.check_config(c)
    assert isinstance(components.make_model(components.resolve(c), 7).module, convdraw.GQNConvDraw)
  c = gqn_convdraw.get_config()
  assert (c.model.draw_steps, c.loss.sigma_initial, c.loss.sigma_final) == (12, 2.0, 0.7)
  assert (c.loss.sigma_anneal_steps, c.optax.anneal_steps) == (200_000, 1_600_000)
  assert (c.optax.lr_model, c.optax.lr_model * c.optax.final_scale) == (5e-4, pytest.approx(5e-5))
  c.rep.kind = "grid"
  with pytest.raises(runconfig.ConfigError, match="convdraw"):
    components.check_config(c)


@pytest.mark.slow
def test_smoke_run_trains_evaluates_restores_and_takes_the_noise_test(tmp_path):
  workdir = str(tmp_path / "run")
  last = train.train_and_evaluate(gqn_convdraw.get_config("smoke"), workdir)
  keys = ("train/elbo", "train/kl", "train/nll", "train/sigma", "train/kl_weight", "eval/psnr")
  for k in (*keys, "eval/psnr_sample", "eval/psnr_prior_mean"):
    assert np.isfinite(last[k]), k
  with open(os.path.join(workdir, "metrics.jsonl")) as f:
    rows = [json.loads(line) for line in f]
  train_rows = [r for r in rows if "train/elbo" in r]
  assert [r["step"] for r in train_rows] == [2, 4]
  assert train_rows[-1]["train/elbo"] < train_rows[0]["train/elbo"]
  assert train_rows[-1]["train/kl"] >= 0
  assert all(r["train/finite"] == 1.0 for r in train_rows)

  run = restore.load_run(workdir)
  assert run.step == 4 and isinstance(run.model.module, convdraw.GQNConvDraw)
  key = jax.random.key(0)
  res = noise.noise_robustness(run, key=key, alphas=[0.0, 0.3], quantisation="nearest")
  # alpha = 0 with the eval's rounding repeats the training loop's eval (same sample keys).
  assert res["psnr"][0] == pytest.approx(last["eval/psnr"], abs=1e-4)
  assert np.all(np.isfinite(res["psnr"]))
  assert set(res["beta"]) == {"xy", "yaw"}
  assert res["beta"]["xy"].shape == (3,) and res["beta"]["yaw"].shape == (4,)  # GQN's 7-D vector
  # The default prediction is the sample; the prior mean (temperature 0) is logged beside it.
  assert last["eval/psnr_sample"] == pytest.approx(last["eval/psnr"], abs=1e-6)
  run.config.model.draw_temperature = 0.0
  res0 = noise.noise_robustness(run, key=key, alphas=[0.0], quantisation="nearest")
  assert res0["psnr"][0] == pytest.approx(last["eval/psnr_prior_mean"], abs=1e-4)

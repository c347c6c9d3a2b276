"""Benchmark of the exp methods of camrep.lie on the GQN-rooms rotation-loss workload.

Workload (digest 1.5): 4000 pose pairs, one generator of 6 blocks of 16 x 16, float32.
  vectors:  the rotation loss itself, mean_p ||exp(B dl_p) v0_p - v1_p||^2, forward and its
            gradient with respect to the generator parameters and v0 (what the train step runs);
  matrices: exp(B dl_p) materialised, (4000, 6, 16, 16), forward and the gradient of
            sum(M * T) with respect to the generator parameters.
Generator blocks have spectral norm 1 and dl ~ U(-dmax, dmax), so ||B dl|| <= dmax.

Times are medians over --repeats runs after a warm-up, jitted, block_until_ready; compile time
is printed separately. Errors are max abs differences of the forward output against the expm
method (float32) and against scipy.linalg.expm in float64, and the relative error of the gradient
against expm's gradient. Ratios are to expm, measured in the same run.

Command:
  .venv/bin/python experiments/bench_lie.py            # ~1-2 min on 2 CPU cores
  .venv/bin/python experiments/bench_lie.py --pairs 100 --repeats 1   # smoke
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from camrep import lie


def _time(fn, *args, repeats):
  t0 = time.perf_counter()
  jax.block_until_ready(fn(*args))
  compile_s = time.perf_counter() - t0
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - t0)
  return statistics.median(times), compile_s


def make_problem(pairs: int, n_blocks: int, s: int, dmax: float, seed: int = 0):
  rng = np.random.default_rng(seed)
  p = rng.normal(size=(n_blocks, lie.num_skew_params(s)))
  B = np.asarray(lie.skew(p, block_size=s), np.float64)
  B = B / np.linalg.norm(B, ord=2, axis=(-2, -1), keepdims=True)
  params = np.asarray(lie.vee(B), np.float32)
  dl = rng.uniform(-dmax, dmax, size=pairs).astype(np.float32)
  v0 = rng.normal(size=(pairs, n_blocks * s)).astype(np.float32)
  v0 /= np.linalg.norm(v0, axis=-1, keepdims=True)
  v1 = rng.normal(size=(pairs, n_blocks * s)).astype(np.float32)
  v1 /= np.linalg.norm(v1, axis=-1, keepdims=True)
  T = rng.normal(size=(pairs, n_blocks, s, s)).astype(np.float32)
  return params, dl, v0, v1, T


def run(pairs=4000, n_blocks=6, s=16, dmax=1.0, repeats=7, seed=0):
  params, dl, v0, v1, T = make_problem(pairs, n_blocks, s, dmax, seed)
  B64 = np.asarray(lie.skew(params.astype(np.float64), block_size=s))
  ref_M = np.stack([[scipy.linalg.expm(t * b) for b in B64] for t in dl.astype(np.float64)])
  ref_y = np.einsum("pbij,pbj->pbi", ref_M, v0.reshape(pairs, n_blocks, s).astype(np.float64))
  ref_y = ref_y.reshape(pairs, -1)

  def rot_loss(params, v0, method):
    B = lie.skew(params, block_size=s)
    moved = lie.apply_exp_blocks(B, dl, v0, method=method)
    return jnp.mean(jnp.sum((moved - v1) ** 2, -1)), moved

  def mat_loss(params, method):
    M = lie.exp_blocks(lie.skew(params, block_size=s), dl, method=method)
    return jnp.sum(M * T), M

  rows = {}
  outs = {}
  for method in lie.EXP_METHODS:
    fwd_v = jax.jit(lambda p, v, m=method: rot_loss(p, v, m)[1])
    grad_v = jax.jit(jax.grad(lambda p, v, m=method: rot_loss(p, v, m)[0], argnums=(0, 1)))
    fwd_m = jax.jit(lambda p, m=method: mat_loss(p, m)[1])
    grad_m = jax.jit(jax.grad(lambda p, m=method: mat_loss(p, m)[0]))
    r = {}
    r["vec_fwd"], r["vec_fwd_compile"] = _time(fwd_v, params, v0, repeats=repeats)
    r["vec_grad"], r["vec_grad_compile"] = _time(grad_v, params, v0, repeats=repeats)
    r["mat_fwd"], r["mat_fwd_compile"] = _time(fwd_m, params, repeats=repeats)
    r["mat_grad"], r["mat_grad_compile"] = _time(grad_m, params, repeats=repeats)
    y, M = np.asarray(fwd_v(params, v0)), np.asarray(fwd_m(params))
    g = grad_v(params, v0)
    outs[method] = (y, M, g, np.asarray(grad_m(params)))
    r["err64_vec"] = float(np.abs(y - ref_y).max())
    r["err64_mat"] = float(np.abs(M - ref_M).max())
    rows[method] = r

  y_e, M_e, g_e, gm_e = outs["expm"]
  for method, r in rows.items():
    y, M, g, gm = outs[method]
    r["err_vec"] = float(np.abs(y - y_e).max())
    r["err_mat"] = float(np.abs(M - M_e).max())
    r["gerr"] = float(
      max(
        np.abs(np.asarray(a) - np.asarray(b)).max() / np.abs(np.asarray(b)).max()
        for a, b in zip(g, g_e, strict=True)
      )
    )
    r["gerr_mat"] = float(np.abs(gm - gm_e).max() / np.abs(gm_e).max())
  return rows


def report(rows, *, pairs, n_blocks, s, dmax):
  dev = jax.devices()[0]
  print(
    f"camrep.lie exp methods: {pairs} pairs, {n_blocks} blocks of {s}x{s}, float32, |B dl| <= {dmax}"
  )
  print(f"device: {dev.platform} ({dev.device_kind}), jax {jax.__version__}")
  e = rows["expm"]
  print()
  print(
    "rotation loss (vectors)  fwd ms   grad ms  fwd+grad  vs expm  vs taylor2  err vs expm  err vs f64  grad rel err"
  )
  t2 = rows["taylor2"]["vec_fwd"] + rows["taylor2"]["vec_grad"]
  for m, r in rows.items():
    tot = r["vec_fwd"] + r["vec_grad"]
    print(
      f"  {m:10s}            {1e3 * r['vec_fwd']:8.2f} {1e3 * r['vec_grad']:8.2f} {1e3 * tot:9.2f}"
      f"  {(e['vec_fwd'] + e['vec_grad']) / tot:6.1f}x  {tot / t2:8.2f}x   {r['err_vec']:.1e}     {r['err64_vec']:.1e}"
      f"    {r['gerr']:.1e}"
    )
  print()
  print(
    "matrices exp(B dl)       fwd ms   grad ms  fwd+grad  vs expm  vs taylor2  err vs expm  err vs f64  grad rel err"
  )
  t2 = rows["taylor2"]["mat_fwd"] + rows["taylor2"]["mat_grad"]
  for m, r in rows.items():
    tot = r["mat_fwd"] + r["mat_grad"]
    print(
      f"  {m:10s}            {1e3 * r['mat_fwd']:8.2f} {1e3 * r['mat_grad']:8.2f} {1e3 * tot:9.2f}"
      f"  {(e['mat_fwd'] + e['mat_grad']) / tot:6.1f}x  {tot / t2:8.2f}x   {r['err_mat']:.1e}     {r['err64_mat']:.1e}"
      f"    {r['gerr_mat']:.1e}"
    )
  print()
  print("compile s (vec fwd / vec grad / mat fwd / mat grad):")
  for m, r in rows.items():
    print(
      f"  {m:10s} {r['vec_fwd_compile']:.2f} / {r['vec_grad_compile']:.2f} / {r['mat_fwd_compile']:.2f} / {r['mat_grad_compile']:.2f}"
    )
  sp, t2r = rows["spectral"], rows["taylor2"]
  speed = (e["vec_fwd"] + e["vec_grad"]) / (sp["vec_fwd"] + sp["vec_grad"])
  vs_t2 = (sp["vec_fwd"] + sp["vec_grad"]) / (t2r["vec_fwd"] + t2r["vec_grad"])
  print(
    f"spectral_vs_expm={speed:.1f}x spectral_vs_taylor2={vs_t2:.2f}x spectral_err_vs_expm={sp['err_vec']:.1e}"
  )


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--pairs", type=int, default=4000)
  ap.add_argument("--blocks", type=int, default=6)
  ap.add_argument("--block_size", type=int, default=16)
  ap.add_argument("--dmax", type=float, default=1.0, help="largest |B dl| (spectral norm 1 blocks)")
  ap.add_argument("--repeats", type=int, default=7)
  args = ap.parse_args(argv)
  rows = run(args.pairs, args.blocks, args.block_size, args.dmax, args.repeats)
  report(rows, pairs=args.pairs, n_blocks=args.blocks, s=args.block_size, dmax=args.dmax)
  return rows


if __name__ == "__main__":
  main()

"""GQN rooms with GQN's own generator (Eslami et al. 2018): the paper's view-synthesis baseline.

The tower representation network summed over context views and the ConvDRAW generator
(`camrep.models.convdraw`), fed GQN's 7-D pose vector (`rep.kind = "lowdim"`), trained on the
negative ELBO with GQN's annealed pixel std and learning rate; evaluation predicts the mean image
of one prior sample with fixed per-scene keys. Same data, splits, loop, checkpoints and evaluation
as configs/gqn.py. Goal: the baseline the paper compares its pose system with (sections 5.2-5.3).

Paper size (Eslami et al. 2018 supplement; sources in BUILD_NOTES "GQN generator (ConvDRAW)"):
L = 12 steps, hidden 128, r 256, latent 3 channels per step (camrep's choice; open-source
ports use 64), pixel std 2.0 -> 0.7 over 200k steps, Adam 5e-4 -> 5e-5 over 1.6M steps (b1 0.9,
b2 0.999, eps 1e-8); batch 36 scenes in GQN, here the camrep GQN layout (30 scenes x 6 context +
3 query views).

  python -m camrep.main --config=configs/gqn_convdraw.py --workdir=/tmp/gqn_convdraw
    paper size: GPU only (no figure measured). Expected: the GQN PSNR the paper compares with
    (not reported in its full text) and a PSNR that falls faster with pose noise than ours.
  python -m camrep.main --config=configs/gqn_convdraw.py:quick --workdir=/tmp/gqn_convdraw_quick
    eighth width, the scenes of configs/gqn.py:quick (400 in memory) with 3 context + 2 query
    views per scene, 4 generation steps, 2000 steps, the KL weight annealed 10 -> 1 over the
    first 1000 (a camrep option for short runs; GQN: 1 throughout): 10 min 42 s on a 2-core
    CPU (3.1 steps/s). Expected on the compass rooms of gqn.py:quick: held-out-view PSNR
    19.14 dB (prior sample) against 16.95 dB for the mean of the 3 context views. On the old
    rooms (wall_style=tinted) 19.72 against 19.12 dB; there, with GQN's plain ELBO
    (--config.loss.kl_weight_initial=1) 18.92 dB, below the baseline: the prior ignored the pose
    (BUILD_NOTES "GQN generator (ConvDRAW)").
  python -m camrep.main --config=configs/gqn_convdraw.py:object --workdir=/tmp/gqn_convdraw_car
    `:quick` on the car setting's procedural family (configs/shapenet_car.py:quick's `object`
    instances, the same held-out targets: the first test view of each of its first 32
    instances), 3 context views of the instance (the paper's GQN on cars: 15) and GQN's
    low-dimensional pose (sin / cos of the azimuth and polar angle): the paper's GQN baseline on
    the car (its section 5.2), which the comparison's `--noise_runs` trains on the car column.
  python -m camrep.main --config=configs/gqn_convdraw.py:area --workdir=/tmp/gqn_convdraw_area
    `:quick` on the Gibson setting's procedural areas (configs/gibson.py:quick's 4 areas of 400
    training views, the same 4 held-out targets), 4 areas a step, 3 context views of the area
    (the paper's GQN on Gibson rooms: 15) and GQN's low-dimensional pose: the paper's GQN
    baseline on Gibson rooms (its section 5.2), trained on the comparison's gibson column.
  python -m camrep.main --config=configs/gqn_convdraw.py:smoke --workdir=/tmp/gqn_convdraw_smoke
    seconds; for tests.
  python -m camrep.synthesis.evaluate --workdir W --what=noise
    the noise test on its own 7-D query pose vector.
"""

from __future__ import annotations

from camrep.configs import common, gibson, gqn, shapenet_car


def quick_schedules(total_steps: int) -> dict[str, int]:
  """The quick run's schedules as fractions of its length (GQN's schedules compressed into a
  short run): the pixel std annealed over the first 10%, the learning rate over 80%, the KL
  weight over the first half. {flat config field: steps}; a run of another length (e.g. the
  converge comparison's 4x, `python -m camrep.comparison`) sets them all from its own length."""
  return {
    "loss.sigma_anneal_steps": total_steps // 10,
    "optax.anneal_steps": (8 * total_steps) // 10,
    "loss.kl_anneal_steps": total_steps // 2,
  }


def get_config(arg: str | None = None):
  # No `:medium` size for the generator yet; `:object` and `:area` are `:quick` on the car's and
  # the Gibson setting's families.
  arg = common.parse_arg(arg, (*common.NO_MEDIUM, "object", "area"))
  family = arg if arg in ("object", "area") else None
  arg = "quick" if family else arg
  c = gqn.get_config(arg)  # data, layout and durations of the GQN-rooms setting and variant
  c.model.kind = "convdraw"
  # The generator's own fields (no other config has them; the decoders never read them).
  # Generation steps L and latent channels per step (GQN's paper size: 12 and 3).
  c.model.draw_steps = 12
  c.model.z_channels = 3
  # Prediction (held-out eval, noise test): latents z = mu_p + T sigma_p eps of the prior; T = 1 is
  # GQN's sample, T = 0 the prior mean (deterministic; camrep option).
  c.model.draw_temperature = 1.0
  # The ELBO's pixel std, annealed linearly from sigma_initial to sigma_final over
  # sigma_anneal_steps (GQN: 2.0 -> 0.7 over 200k steps, pixels in [0, 1]).
  c.loss.sigma_initial = 2.0
  c.loss.sigma_final = 0.7
  c.loss.sigma_anneal_steps = 200_000
  # camrep option (GQN: 1.0, the plain ELBO): the KL term's weight beta, annealed linearly from
  # kl_weight_initial to 1 over kl_anneal_steps (0: beta = 1 from the start). beta > 1 early
  # pushes information out of the latents into the pose-conditioned path.
  c.loss.kl_weight_initial = 1.0
  c.loss.kl_anneal_steps = 0
  c.model.gamma_init_one = False  # (decoder option, unused by the generator)
  c.rep.kind = "lowdim"
  # No pose-system parameters: no rotation losses.
  c.loss.n_pairs = 0
  c.loss.rot_weight = 0.0
  c.loss.dir_weight = 0.0
  c.optax.lr_model = 5e-4
  # GQN's learning-rate decay: common.base()'s "linear" schedule (optax.final_scale 0.1 over
  # optax.anneal_steps 1.6M; a schedule any model may use, so its fields stay in the base).
  c.optax.schedule = "linear"
  if arg == "quick":
    # 2 cores: 4 generation steps and 3 context + 2 query views per scene (configs/gqn.py:quick
    # has 6 queries), ~6x less generator work than 8 steps x 6 queries, which ran at 0.24 steps/s.
    c.model.draw_steps = 4
    c.data.views_per_scene = 5
    # GQN's schedules compressed into the short run (sigma over the first 10% of it, the learning
    # rate over 80%); the quick decoder's 10x-paper rate as the starting rate.
    c.optax.lr_model = 1e-3
    schedules = quick_schedules(c.total_steps)
    c.loss.sigma_anneal_steps = schedules["loss.sigma_anneal_steps"]
    c.optax.anneal_steps = schedules["optax.anneal_steps"]
    # The KL weight beta 10 -> 1 over the first half: with the plain ELBO (beta = 1) the short
    # run keeps the pose information in the posterior's latents and the prior ignores the pose
    # (18.92 dB, below the context-mean baseline); beta > 1 early pushes it into the
    # pose-conditioned path (19.72 dB). camrep option; GQN's paper size keeps beta = 1.
    c.loss.kl_weight_initial = 10.0
    c.loss.kl_anneal_steps = schedules["loss.kl_anneal_steps"]
  elif arg == "smoke":
    c.model.draw_steps = 2
    c.loss.sigma_anneal_steps = c.total_steps
    c.optax.anneal_steps = c.total_steps
  if family == "object":
    shapenet_car.on_quick_objects(c)
  elif family == "area":
    gibson.on_quick_areas(c)
  return c

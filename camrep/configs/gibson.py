"""Gibson rooms (procedural `area` family by default): polar (x, y) + yaw over 2 m x 2 m areas.

Goal: the Gibson pose system the paper regresses in Table 1 (section 5.4), learned by view synthesis
(section 4.1). Paper size (the supplement's "Gibson rooms dataset", the authors' code): 500k steps
of 4 areas x 25 neighbouring pairs, 128 px, per-area unit vectors u (768) and per-area instance-norm
tables, 2 pose steps per decoder step, lr 1e-4 / 1e-2, lambda_1 0.01, lambda_2 100, lambda_4 0.8,
3000 extra pairs plus image pairs, 41 x 41 position grid (0.05 m), extra-pair radius 2.2 grid units.

  python -m camrep.main --config=configs/gibson.py --workdir=/tmp/gibson
    paper size: ~5 days on one Titan RTX (on one H100 it trained, using ~17 GiB of GPU memory;
    no steady rate measured). Expected Table 1 Gibson errors 0.021 m, 0.020 m, 0.87 deg.
  python -m camrep.main --config=configs/gibson.py:quick --workdir=/tmp/gibson_quick
    64 px, 4 areas in memory, eighth width, 600 steps: 4.7 min on a 2-core CPU. Expected:
    held-out-view PSNR 19.41 dB against 16.76 dB for the mean of up to 16 training views (+2.65 dB;
    BUILD_NOTES "View synthesis, quick configs").
  python -m camrep.main --config=configs/gibson.py:smoke --workdir=/tmp/gibson_smoke
    seconds; for tests.
"""

from __future__ import annotations

from camrep.configs import common


def on_quick_areas(c) -> None:
  """Sets `c` (a context-view config's `:quick`) to `:quick`'s procedural areas and evaluation
  set here: the same 4 areas and held-out targets (configs/gqn_convdraw.py's `:area`). A batch
  holds at most the family's 4 areas: a step draws its scenes without replacement."""
  area = get_config("quick")
  common.on_family_of(c, area)
  c.data.scenes_per_device = min(c.data.scenes_per_device, area.data.family.num_scenes)


def get_config(arg: str | None = None):
  variant = common.parse_arg(arg)
  c = common.base()
  c.task = "table"
  c.data.source = "area"
  c.data.mode = "pairs"
  c.data.scenes_per_device = 4
  c.data.views_per_scene = 50  # 25 pairs
  c.model.image_size = 128
  c.model.scene_dim = 768
  c.model.per_scene_norm = True
  c.rep.position_spacing = 0.05
  c.rep.pair_radius = 2.2
  c.loss.rec_weight = 0.01
  c.loss.n_pairs = 3000
  c.loss.data_pairs = True
  c.optax.pose_steps = 2
  c.total_steps = 500_000
  c.ckpt_every_steps = 3000
  if variant in ("quick", "medium"):
    common.quick(c)
    c.data.family.image_size = 64
    c.data.family.num_scenes = 4
    c.data.family.train_views = 400
    c.data.family.test_views = 16
    c.data.views_per_scene = 8
    c.model.image_size = 64
    c.loss.n_pairs = 1000
    c.optax.pose_steps = 1
    c.evals.num_scenes = 4
    c.evals.batch_scenes = 4
    if variant == "medium":
      common.medium(c)
      c.data.family.train_views = 1_000
  elif variant == "smoke":
    common.smoke(c)
    c.model.scene_dim = 16
  return c

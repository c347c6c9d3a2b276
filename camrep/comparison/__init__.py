"""The pose-regression comparison (the paper's Tables 1 and 2), launched as subprocesses.

  python -m camrep.comparison --size quick --out DIR [--dry_run]
  python -m camrep.comparison --size medium --out DIR --jobs 4 [--dry_run]   # one GPU
  python -m camrep.comparison --size paper --out DIR [--dry_run]             # a GPU, days
  python -m camrep.comparison --size quick --settings seven_scenes \\
      --data seven_scenes=PREPARED_DIR --out DIR       # Table 2 from prepared real 7-Scenes
  python -m camrep.comparison --size converge --out DIR --archive results/converge \\
      --max_hours 2 [--data car_chair=nerf:PREPARED_DIR ...] [--noise_runs] [--crossed car]
  python -m camrep.comparison --size protocol --out DIR [--noise_runs] [--dry_run]

Run from a checkout (its configs/ and experiments/). The plans, one per `--size`, are data in
camrep/comparison/plans.toml (seeds, learning-rate grids, caps, the inputs of the estimates).

Steps (`launch.execute`), each finished run skipped, so a launch that stops resumes where it
stopped (a run whose record cannot be read counts as not finished: it is named, its file set
aside as <name>.damaged, and trained again; a view-synthesis run that stopped at its plateau
under another cap than the plan's is stale, and so is every run that reads its pose system: the
dry run names them, a launch moves them, in DIR and the archive alike, to
<root>/stale/<path>.stale-<cap> and trains them again):

  1. view-synthesis runs (`python -m camrep.main --config=configs/<setting>.py[:variant]`) into
     DIR/synthesis/<name>: each setting's learned pose system; the car's (and each capture
     column's) MLP embedding (`--config.rep.kind=mlp`); where the plan adds the control targets,
     each column's learned system with frozen generators (<column>_frozen_gen,
     `--config.rep.freeze_generators=True`); with --noise_runs each setting's other pose inputs
     (plans.toml `noise_inputs`: GQN's lowdim, mlp and its own generator, configs/gqn_convdraw.py,
     not at medium size; the car's lowdim and ConvDRAW, configs/gqn_convdraw.py:object; the
     area's lowdim, mlp and ConvDRAW, configs/gqn_convdraw.py:area; :object and :area at quick
     width only);
  2. regression runs (`python -m camrep.regression
     --config=configs/regression.py:SETTING[,variant]`)
     into DIR/regression/<column>/<representation>/<lr>_seed<k>: phase 1 trains seed 0 at every
     lr of the setting's grid; phase 2 the other seeds at the lr seed 0's validation errors chose
     (`camrep.regression.tables.select`), or at every lr with --full_grid. Rendered data and
     restored pose systems are cached in DIR/cache. Where the plan says `vectorise` (converge,
     medium), each column's and representation's runs of a phase are one program (`python -m
     camrep.regression --lrs=... --seeds=...`, `camrep.regression.vectorised`): phase 1 over its
     lrs, phase 2 over its later seeds once every seed's view synthesis is done (the full grid:
     one program); each run still writes its own workdir. `--no_vectorise`: one process per
     run, seed by seed;
  3. tables: experiments/table1.py -> DIR/table1.md (and DIR/table1_<capture>.md),
     experiments/table2.py -> DIR/table2.md, experiments/lead_table.py -> DIR/lead_table.md,
     `python -m experiments.claims_table` -> DIR/claims.md (the paper's claims, from DIR's
     regression and view-synthesis runs);
  4. figures: `python -m camrep.synthesis.evaluate` of every view-synthesis run (noise curve,
     Gram maps), the noise figure of each column with several pose inputs (DIR/noise_<column>),
     and at sizes with a stopping rule the validation and held-out PSNR curves
     (DIR/curve_<column>, DIR/curve_synthesis_<column>).

`--size converge`: the quick sizes with 3 seeds a cell; every run stopped by the stopping rule
(`--config.stop.*`) under a cap; lr grids extended by phase 1 (up to `--extend_grid N` lrs) while
seed 0's choice sits at an edge; one view-synthesis run per seed, synthesis/<name>_seed<k>, read
by regression seed k of ours; the launch goes seed by seed (vectorised: every seed's view
synthesis before phase 2). `--crossed COLUMN` adds, after phase
2, every regression seed of ours on every other synthesis seed's pose system (DIR/crossed/,
never tabled with the paired runs), then experiments/seed_spread.py -> DIR/seed_spread_<column>.md.

`--size protocol`: the converge rules and caps with 10 seeds a cell on the area and 5 on the other
settings (plans.toml's `seed_counts`, `Plan.seeds_for`), every seed at every lr
(`full_grid`: the lr chosen on the validation mean over all seeds), the same lrs for every
representation of a column (no extension), the control targets "untrained" (ours' own
synthesis run at its initialisation) and "frozen_gen" in every column, view synthesis stopped on
validation views (`--config.evals.split=validation`: the procedural families' own split; a
capture column's every 10th training view, carved from its prepared training split and not
trained on, the views its regressions validate on), and 7-Scenes synthesis over all seven scenes'
trajectories.

`--archive DIR`: each finished run's compact record (`camrep.comparison.archive`) is written into
DIR as soon as the run ends, and a launch starts by restoring the records DIR holds; a restored
view-synthesis run comes back without checkpoints, with its config.json and record.json (all the
"untrained" control reads) and a final pose system of up to 64 KB (pose_system.npz, what ours,
frozen_gen, MLP and crossed regressions read: the car's, 7-Scenes' and captures' 1-D grids), and
is trained again only while a run that needs its checkpoints (a regression of a larger pose
system, a noise evaluation) is missing.

`--data SETTING=DIR` runs a setting on real data prepared by `python -m camrep.data.prepare`
(both stages get `--config.data.source/dir`); `--data car_NAME=SOURCE:DIR` adds a capture column
car_NAME: a capture prepared with `--preset small` (SOURCE nerf, llff or colmap), regressed in the
car setting into regression/car_NAME and tabled alone.

`--max_hours H` starts no run after H hours; `--jobs N` runs N subprocesses at once within each
step (each told 0.9 / N of a GPU's memory). One launch per DIR at a time (a lock naming the
first). Ctrl-C or SIGTERM stops the runs in flight (a training run saves a checkpoint first)
and exits 130 with a line on what was kept. `--dry_run` prints every command with an estimate
and the total.
"""

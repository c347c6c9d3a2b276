"""A grid of regression runs (seeds x learning rates of one setting and representation) trained
together as one vectorised program.

`python -m camrep.regression --config=configs/regression.py:SETTING[,VARIANT] --workdir=DIR
--lrs=1e-3,3e-3 --seeds=0,1,2 [--config.FIELD=VALUE ...]` (`run`; either flag alone takes the
other from the config) trains one member per (lr, seed): the run that

  python -m camrep.regression --config=... --workdir=DIR/<lr tag>_seed<k> \\
    --config.optax.lr=LR --config.seed=K [--config.FIELD=VALUE ...]

trains (`runs.run_name`: "lr1e-3_seed0", the comparison launcher's layout), into that workdir, with
the same files (`driver`'s docstring) and the same config.json: the tables read it unchanged and
that command resumes or reruns it alone. A `{seed}` in `--config.synthesis_workdir` is each
member's seed (the comparison's paired view-synthesis runs, DIR/synthesis/car_seed{seed}).

One program: one group step (`group_step`) trains every member: on accelerators a jitted
`jax.vmap` of `learner.train_step` (or `train_steps`, K per dispatch) over their states stacked on
a leading member axis; on a CPU one jitted step shared by every member, called member by member on
the members' own states, never stacked (`resolve_program`: XLA:CPU runs vmapped convolutions,
grouped convolutions, 4-5x slower), the members placed in turn over the local devices (`place`):
the command line shows a CPU as one-thread host devices, one per core (its --host_devices,
`camrep.runtime.xla_cpu`), whose steps run at once.
What a single run takes from its seed and lr, each member keeps:

  init      its seed's (`driver.RegressionStage.init`), and its frozen representation ("mlp"'s
            random embedding, "ours"' pose system of its own synthesis workdir), stacked;
  data      its seed's batch order (each seed's `views.train_pipeline`; members of one seed
            share its batches): the batches are stacked (M, B, ...) on the member axis;
  lr        the optimiser runs at rate 1 (`learner.unit_rate`) and each member's updates are
            scaled by its lr: Adam(lr)'s update bit for bit. Vectorised convolutions and
            reductions may sum in another order than a run's own, so a member equals the run
            trained alone up to float32 round-off (tests/test_vectorised.py: predictions, losses and
            errors within 1e-5 relative after a few steps, in every program).

Everything else is per member, as in a single run: its run frame (`runtime.frame.Frame`: lock,
config and record checks, checkpoints, config_history.jsonl), its metrics.jsonl rows, its
periodic validation and plateau rule (`config.stop`), its final evaluation, results.json
(with "grid": the lrs and seeds it was trained with, whose "train_seconds" is the group's wall
time), errors_<split>.npz and final_metrics.json. A member whose rule stops it is completed at
that step and leaves the group (the others train on; one compile per group size); a member
whose values become non-finite is recorded as such in its final_metrics.json and leaves the
group, and the command exits with status 3 once the others are done.

Resume: the whole group. Every member's checkpoint is saved at the same steps
(`ckpt_every_steps`, a stop signal: SIGTERM or Ctrl-C saves all and stops), so the same command
resumes every unfinished member from the same step; complete members are skipped, and so are
finished runs an archive restored (a run.json alone: `camrep.comparison.archive`; refused when it
is another lr's or seed's). Unfinished
members at different steps (e.g. one resumed alone) are refused with an `error:` line that says
how to go on.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import copy
import dataclasses
import functools
import itertools
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from camrep.regression import config_schema, driver, learner, runs
from camrep.regression import views as views_lib
from camrep.runtime import frame as frame_lib
from camrep.runtime import preemption, stopping
from camrep.runtime import progress as progress_lib
from camrep.runtime.runconfig import ConfigError

SEED_FIELD = "{seed}"


lr_tag = runs.lr_tag
member_name = runs.run_name


def member_config(
  config: ml_collections.ConfigDict, lr: float, seed: int
) -> ml_collections.ConfigDict:
  """The single run's config of member (lr, seed): `config` with optax.lr, seed and a `{seed}`
  in synthesis_workdir set."""
  c = copy.deepcopy(config)
  c.optax.lr = float(lr)
  c.seed = int(seed)
  if SEED_FIELD in c.get("synthesis_workdir", ""):
    c.synthesis_workdir = c.synthesis_workdir.replace(SEED_FIELD, str(seed))
  return c


def members(
  config: ml_collections.ConfigDict,
  workdir: str,
  lrs: Sequence[float],
  seeds: Sequence[int],
  *,
  overridden=(),
) -> list[tuple[str, config_schema.Resolved]]:
  """(workdir, checked and resolved config) of every member, lr by lr and seed by seed.

  Raises:
    ConfigError: no lr or seed, one given twice, two lrs that share a directory name, or a
      member's config that `config_schema.validate` refuses (named by its member).
  """
  if not lrs or not seeds:
    raise ConfigError("a grid needs at least one lr (--lrs) and one seed (--seeds)")
  names = [member_name(lr, k) for lr in lrs for k in seeds]
  if len(set(names)) < len(names):
    dup = sorted({n for n in names if names.count(n) > 1})
    raise ConfigError(
      f"--lrs={','.join(format(x, 'g') for x in lrs)} --seeds={','.join(map(str, seeds))}: "
      f"members share a directory ({', '.join(dup)}); give each lr and seed once, and lrs that "
      "differ in their first significant digit"
    )
  out = []
  for lr in lrs:
    for k in seeds:
      c = member_config(config, lr, k)
      try:
        run = config_schema.validate(c, overridden=overridden)
      except ConfigError as e:
        raise ConfigError(f"member lr={lr:g} seed={k}: {e}") from None
      out.append((os.path.join(workdir, member_name(lr, k)), run))
  return out


@dataclasses.dataclass
class Member:
  """One run of the grid while it trains.

  Attributes:
    workdir, config: the single run's.
    run: its config resolved (`config_schema.Resolved`).
    frame: its entered run frame (None for a run an archive restored: nothing to do).
    setup, record: its `driver.Setup` and record.json content.
    stage: its `driver.RegressionStage`.
    state: its state (its own regressor and optimiser) until it joins the group.
    start: the step it starts or resumes from.
    last: its last logged train and evaluation scalars.
    curve: its plateau rule's curve [(step, score)].
    results: its results.json content once complete.
    error: why it left the group unfinished (non-finite values), else None.
  """

  workdir: str
  config: ml_collections.ConfigDict
  run: config_schema.Resolved
  frame: frame_lib.Frame | None
  setup: driver.Setup | None = None
  record: dict[str, Any] = dataclasses.field(default_factory=dict)
  stage: driver.RegressionStage | None = None
  state: Any = None
  start: int = 0
  last: dict[str, float] = dataclasses.field(default_factory=dict)
  curve: list[tuple[int, float]] = dataclasses.field(default_factory=list)
  results: dict[str, Any] | None = None
  error: FloatingPointError | None = None

  @property
  def label(self) -> str:
    return os.path.basename(self.workdir)


def stack(trees: Sequence[Any]) -> Any:
  """Pytrees of equal structure stacked on a new leading axis."""
  return jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *trees)


def unstack(tree: Any, i: int) -> Any:
  """Member `i` of a stacked pytree."""
  return jax.tree.map(lambda x: x[i], tree)


PROGRAMS = ("auto", "vmap", "unrolled", "loop")
"""How the group step holds its members (`group_step`)."""


def resolve_program(program: str = "auto") -> str:
  """The group step's form: "vmap" (one `jax.vmap` over the member axis, the accelerators'
  choice), "unrolled" (each member's own step side by side in one jitted program) or "loop" (one
  jitted step, the same for every member since they differ only in data, init and lr, called
  member by member on a list of the members' own states: the CPU's choice, "auto" there). On
  XLA:CPU, vmapping a conv layer over members with their own kernels makes it a grouped
  convolution (feature_group_count = M), which runs 4-5x slower than the members' convolutions
  one by one, and the unrolled program of 12 members ran 0.6-1.2x the runs' speed
  (camrep.bench.regression_grid). On one CPU device the loop steps at the runs' speed (0.87-0.98x)
  and saves their start-ups and compiles; placed over one-thread host devices, one per core
  (`_Group`), its steps run side by side (1.56x the runs' speed on the car's regressor, 1.28x on
  7-Scenes')."""
  if program not in PROGRAMS:
    raise ValueError(f"program must be one of {PROGRAMS}, got {program!r}")
  if program == "auto":
    return "loop" if jax.default_backend() == "cpu" else "vmap"
  return program


def _unrolled(step: Callable) -> Callable:
  """`step` over stacked members, each member's own call in one program (see `resolve_program`)."""

  def run(states, batch, lrs):
    outs = [step(unstack(states, i), unstack(batch, i), lrs[i]) for i in range(lrs.shape[0])]
    return tuple(stack([o[j] for o in outs]) for j in range(len(outs[0])))

  return run


def _looped(step: Callable) -> Callable:
  """`step` over listed members, one jitted call a member on its own state, updated in place
  (donated), and batch, on the member's device (see `resolve_program`): one compile per device
  for every member and group size; only the small metrics are stacked, on the first member's
  device (one compile per group size: a group shrinks as members stop)."""
  one = jax.jit(step, donate_argnums=0)
  join = jax.jit(lambda outs: jax.tree.map(lambda *xs: jnp.stack(xs), *outs))

  def run(states, batches, lrs):
    outs = [one(*member) for member in zip(states, batches, lrs, strict=True)]
    # Members on several devices: the others' metrics gathered on the first's (only those: a
    # device_put of all, on one device, cost 7 ms a step for 30 members).
    first = jax.tree.leaves(outs[0][1])[0].sharding
    here = lambda o: jax.tree.leaves(o[1])[0].sharding == first  # noqa: E731
    metrics, ok = join([o[1:] if here(o) else jax.device_put(o[1:], first) for o in outs])
    return [o[0] for o in outs], metrics, ok

  return run


def listed(program: str = "auto") -> bool:
  """Whether `program`'s group step takes the members as lists of their own states, batches and
  lrs ("loop") rather than stacked on a member axis (`group_step`)."""
  return resolve_program(program) == "loop"


@functools.cache
def group_step(n: int, program: str = "auto") -> Callable:
  """The group's step over `n` steps per dispatch: fn(states, batches, lrs) -> (states, metrics,
  ok), with states, batches and lrs stacked on the member axis (M, ...) (batches (M, n, ...) for
  n > 1), or for the "loop" program (`listed`) lists of M: each member's own state, batch
  ((n, ...) for n > 1) and lr, no member axis, so nothing is copied; metrics (M,) per key
  (n = 1) or (M, n); ok (M,): 1.0 where every step of the member was finite. Each member's
  numbers are those of `learner.train_step` (`train_steps`) on it alone; `program`
  (`resolve_program`) decides only how they are computed. One function per (n, program): the
  loop's member step compiles once for every group size."""
  program = resolve_program(program)
  if n == 1:

    def step(state, batch, lr):
      state, metrics = learner.train_step(state, batch, lr)
      return state, metrics, metrics["finite"]

  else:
    step = learner.train_steps
  if program == "loop":
    return _looped(step)
  batched = jax.vmap if program == "vmap" else _unrolled
  return jax.jit(batched(step), donate_argnums=0)


def _rows(metrics, i: int, n: int, stage: driver.RegressionStage) -> list[dict[str, float]]:
  return stage.rows({k: v[i] for k, v in metrics.items()}, n)


def run(
  config: ml_collections.ConfigDict,
  workdir: str,
  *,
  lrs: Sequence[float],
  seeds: Sequence[int],
  overridden=(),
  log=print,
  program: str = "auto",
) -> list[dict[str, Any]] | None:
  """Trains and evaluates the grid's members together (see the module docstring).

  Args:
    config: a configs/regression.py config (its optax.lr and seed are the members').
    workdir: the grid's directory; member (lr, k) writes DIR/<member_name(lr, k)>.
    lrs: the learning rates.
    seeds: the seeds.
    overridden: the config fields set on the command line (`config_schema.validate`).
    log: progress printer.
    program: the group step's form (`resolve_program`).

  Returns:
    Each member's results.json content (lr by lr, seed by seed), or None when a signal stopped
    the group (every unfinished member saved a checkpoint).

  Raises:
    ConfigError: bad grid or config, members that cannot share one program, or unfinished
      members at different steps.
    WorkdirError: a member's workdir cannot be written, or another run holds it.
    FloatingPointError: a member's values became non-finite (the others completed first).
  """
  specs = members(config, workdir, lrs, seeds, overridden=overridden)
  rule = frame_lib.stopping_rule(specs[0][1].config)
  group: list[Member] = []
  with contextlib.ExitStack() as frames:
    for wd, run in specs:
      if (archived := driver.restored_results(wd, run.config, log=log)) is not None:
        group.append(Member(wd, run.config, run, None, results=archived))  # no frame: no writes
        continue
      driver.check_stored_layout(wd)
      frame = frame_lib.Frame(
        wd, run.config, schema=config_schema.SCHEMA, log=log, restart=True,
        outputs=driver.clear_outputs,
      )  # fmt: skip
      member = Member(wd, run.config, run, frame)
      frame.__enter__()  # a failed entry undoes itself
      frames.push(functools.partial(_leave, member))
      if frame.already_complete(rule) is not None:
        member.results = driver.read_results(wd)
      group.append(member)
    todo = [m for m in group if m.results is None]
    if todo and _train(todo, rule, log=log, lrs=lrs, seeds=seeds, program=program):
      return None
  bad = [m for m in group if m.error is not None]
  if bad:
    raise FloatingPointError(
      f"{len(bad)} of {len(group)} members stopped on non-finite values (the others "
      "completed): " + "; ".join(f"{m.label}: {m.error}" for m in bad)
    )
  return [m.results for m in group]


def _leave(member: Member, exc_type, exc, tb):
  """Leaves a member's frame: with its own non-finite stop when it had one (recorded in its
  final_metrics.json), else as the group leaves."""
  if member.error is not None:
    err = member.error
    return member.frame.__exit__(type(err), err, err.__traceback__)
  return member.frame.__exit__(exc_type, exc, tb)


def _prepare(todo: Sequence[Member], *, log) -> tuple[dict, Callable]:
  """Each member's setup (one data for all; the record checked by its frame), checked to fit one
  program; the shared evaluation batches and the jitted prediction."""
  data = None
  for m in todo:
    record = driver.data_record(m.config, m.run.source)
    driver.check_validation_record(m.workdir, record)
    if data is not None and record["data"] != todo[0].record["data"]:
      raise ConfigError(
        f"member {m.label}: its data differ from those of {todo[0].label}; train it alone"
      )
    m.setup = driver.prepare(m.run, log=log, data=data)
    data = m.setup.data
    m.record = {**record, **driver.pose_record(m.setup)}
    m.frame.check_record(m.record)
  if len({learner.unit_rate(m.setup.reg) for m in todo}) > 1:
    raise ConfigError(
      "the members' regressors differ in more than their lr (synthesis workdirs of different "
      "pose systems?): train them alone"
    )
  batching = todo[0].setup.batching
  eval_sets = {k: views_lib.eval_batches(batching, e) for k, e in data.evals.items()}
  return eval_sets, jax.jit(learner.predict_poses)


def _unit(states: Sequence[learner.RegressionState]) -> list[learner.RegressionState]:
  """The states with one regressor at rate 1 (`learner.unit_rate`) and its optimiser: one
  static part (pytree metadata) for all, so that they stack."""
  reg = learner.unit_rate(states[0].regressor)
  tx = learner.make_optimizer(reg.hparams)
  return [s.replace(regressor=reg, tx=tx) for s in states]


def _not_finite(pending, active: Sequence[Member]) -> list[Member]:
  """The active members whose values in the pending dispatches were not finite, each with its
  `error` set (the single run's FloatingPointError) and its first bad step's values logged."""
  bad = []
  for first, n, metrics, ok, then in pending:
    ok = np.asarray(jax.device_get(ok))
    if np.all(ok >= 1):
      continue
    host = jax.device_get(metrics)
    for i, m in enumerate(then):
      if ok[i] >= 1 or m not in active or m in bad:
        continue
      for j, row in enumerate(_rows(host, i, n, m.stage)):
        if row.get("train/finite", 1.0) >= 1:
          continue
        step = first + j
        names = [key for key, v in row.items() if not np.isfinite(v)]
        m.frame.writer.write_scalars(step, row)
        m.error = FloatingPointError(
          f"non-finite training values at step {step} ({', '.join(names) or 'gradients'}); "
          f"updates of this step were skipped; {m.frame.origin}; the last checkpoint is kept in "
          f"{m.workdir} and a resume verifies its checksums before using it"
        )
        bad.append(m)
        break
  return bad


def place(n: int, devices: Sequence[Any]) -> list[Any]:
  """Where each of `n` members trains: the devices in turn (member i on devices[i % D])."""
  return [devices[i % len(devices)] for i in range(n)]


def rebalance(where: Sequence[Any], devices: Sequence[Any]) -> list[Any]:
  """`where` (each member's device) after members left: the fewest moves that leave no device
  with 2 or more members more than another (a member from the fullest to the emptiest, the last
  of the fullest first)."""
  where = list(where)
  if not where:
    return where
  while True:
    count = {d: where.count(d) for d in devices}
    full, empty = max(devices, key=count.get), min(devices, key=count.get)
    if count[full] - count[empty] <= 1:
      return where
    where[len(where) - 1 - where[::-1].index(full)] = empty


class _Group:
  """The members training together, their states and rates as `program`'s group step takes them
  (`group_step`: stacked, or listed for "loop"); leaving shrinks them. Listed members are placed in
  turn over `devices` (`place`; default the local devices: a CPU shown as host devices,
  `camrep.runtime.xla_cpu.host_devices`, runs their steps at once) and rebalanced as members leave
  (`rebalance`); their metrics are gathered on the first member's device."""

  def __init__(self, members_: Sequence[Member], program: str = "auto", devices=None):
    self.members = list(members_)
    self.program = resolve_program(program)
    self.listed = listed(self.program)
    self.devices = list(devices or jax.local_devices()) if self.listed else []
    states = _unit([m.state for m in self.members])
    rates = np.asarray([m.config.optax.lr for m in self.members], np.float32)
    if self.listed:
      self.where = place(len(states), self.devices)
      self.states = [jax.device_put(s, d) for s, d in zip(states, self.where, strict=True)]
      self.rates = list(rates)
    else:
      self.states, self.rates = stack(states), jnp.asarray(rates)
    for m in self.members:
      m.state = None  # the group holds it

  def state(self, m: Member) -> learner.RegressionState:
    i = self.members.index(m)
    return self.states[i] if self.listed else unstack(self.states, i)

  def batches(self, chunks: dict[int, Any]) -> Any:
    """The group step's batches from each seed's chunk ({seed: chunk}; a seed's members share
    it): listed (each seed's on each of its members' devices once) or stacked on the member
    axis."""
    if self.listed:
      seeds = [int(m.config.seed) for m in self.members]
      on = {(k, d): jax.device_put(chunks[k], d) for k, d in zip(seeds, self.where, strict=True)}
      return [on[k, d] for k, d in zip(seeds, self.where, strict=True)]
    per = [chunks[int(m.config.seed)] for m in self.members]
    return jax.tree.map(lambda *xs: np.stack(xs), *per)

  def each(self, fn: Callable[[Member], Any]) -> list:
    """fn(m) of each member, in their order; the members of different devices at once (a thread
    per device, each device's members in turn), so that one-thread host devices evaluate side by
    side. Raises the first member's error."""
    if len(self.devices) < 2:
      return [fn(m) for m in self.members]
    by_device: dict[Any, list[Member]] = {}
    for m, d in zip(self.members, self.where, strict=True):
      by_device.setdefault(d, []).append(m)
    with concurrent.futures.ThreadPoolExecutor(len(by_device)) as pool:
      done = pool.map(lambda ms: [(m, fn(m)) for m in ms], by_device.values())
      out = {id(m): r for pairs in done for m, r in pairs}
    return [out[id(m)] for m in self.members]

  def leave(self, m: Member) -> list[tuple[Member, Any]]:
    """Drops member `m`; returns the members moved to another device (`rebalance`), with it."""
    keep = [j for j, x in enumerate(self.members) if x is not m]
    self.members = [self.members[j] for j in keep]
    if not self.listed:
      if self.members:
        self.states = jax.tree.map(lambda x: x[np.asarray(keep)], self.states)
        self.rates = self.rates[np.asarray(keep)]
      return []
    self.rates = [self.rates[j] for j in keep]
    was = [self.where[j] for j in keep]
    self.where = rebalance(was, self.devices)
    states = [self.states[j] for j in keep]
    moved = [i for i, (w, d) in enumerate(zip(was, self.where, strict=True)) if w != d]
    for i in moved:
      states[i] = jax.device_put(states[i], self.where[i])
    self.states = states
    return [(self.members[i], self.where[i]) for i in moved]


def _train(todo: list[Member], rule: stopping.Rule, *, log, lrs, seeds, program="auto") -> bool:
  """Trains the unfinished members together (see the module docstring); True when a signal
  stopped them."""
  eval_sets, predict_fn = _prepare(todo, log=log)
  for m in todo:
    m.stage = driver.RegressionStage(m.setup, eval_sets, predict_fn=predict_fn)
    m.state, m.start = m.frame.restore_or_init(
      m.stage.init, saved=m.stage.saved, restored=m.stage.restored
    )
  starts = {m.start for m in todo}
  if len(starts) > 1:
    at = ", ".join(f"{m.label} at step {m.start}" for m in todo)
    raise ConfigError(
      f"the grid's unfinished members resume from different steps ({at}): one program trains "
      "them from one step. Resume each alone with `python -m camrep.regression` and its own "
      "--workdir, --config.optax.lr and --config.seed (the same config otherwise), then rerun "
      "the grid (nothing changed)"
    )
  start = starts.pop()
  for m in todo:
    m.frame.begin(start)
    m.stage.start(m.frame.writer, train_seconds=m.frame.extra.get("train_seconds", 0.0))
    m.curve = m.frame.recorded_curve(m.stage.score, start)
  config = todo[0].config
  total = int(config.total_steps)
  log_every, eval_every = int(config.log_every_steps), int(config.eval_every_steps)
  ckpt_every, k = int(config.ckpt_every_steps), frame_lib.steps_per_dispatch(config)
  grid_record = {"lrs": [float(x) for x in lrs], "seeds": [int(x) for x in seeds]}
  group = _Group(todo, program)
  log(
    f"training {len(todo)} members together from step {start}: " + ", ".join(m.label for m in todo)
  )
  if len(group.devices) > 1:
    log(
      f"their steps spread over {len(group.devices)} devices: {', '.join(map(str, group.devices))}"
    )

  def leave(m: Member) -> None:
    for x, device in group.leave(m):
      log(f"{x.label}: moves to {device}, the members rebalanced over the devices")

  def finish(m: Member, step: int, ended: bool, reason: str) -> None:
    fit = frame_lib.FitResult(group.state(m), step, m.last, m.curve, ended, reason, False)
    m.results = driver.complete(
      m.frame, m.stage, fit, eval_sets, predict_fn=predict_fn, rule=rule, grid=grid_record
    )
    overall = m.results["test"]["all"]
    log(
      f"{m.label}: complete at step {step}; test: "
      + ", ".join(f"{k} mean {v['mean']:.4g}" for k, v in overall.items())
    )

  def save(m: Member, step: int) -> None:
    m.frame.save(step, m.stage.saved(group.state(m)), m.stage.extra(step))

  compiled: dict[tuple[int, int], Callable] = {}
  progress = progress_lib.Progress(total, start_step=start, every_seconds=20.0)
  seed_list = sorted({int(m.config.seed) for m in todo})
  plan, *aheads = itertools.tee(
    frame_lib.spans(start, total, k, (eval_every, ckpt_every)), 1 + len(seed_list)
  )
  first_of_seed = {int(m.config.seed): m for m in reversed(todo)}
  # The batches of each seed, read ahead of the loop (members of one seed share them).
  batches = {s: first_of_seed[s].stage.chunks(a) for s, a in zip(seed_list, aheads, strict=True)}
  step, pending = start, []
  with preemption.install_signal_handlers() as signals:
    try:
      for first, n in plan:
        chunk = group.batches({s: next(b) for s, b in batches.items()})
        size = len(group.members)
        fn = compiled.get((n, size))
        if fn is None:
          log(f"compiling the train step of {size} members ({n} step(s) per dispatch) ...")
          t0 = time.perf_counter()
          fn = compiled[(n, size)] = group_step(n, group.program)
          group.states, metrics, ok = fn(group.states, chunk, group.rates)
          log(f"compiled in {time.perf_counter() - t0:.1f} s")
        else:
          group.states, metrics, ok = fn(group.states, chunk, group.rates)
        step = first + n - 1
        members_then = list(group.members)  # the member axis of this dispatch's metrics
        pending.append((first, n, metrics, ok, members_then))
        stopped = preemption.stop_requested(signals)
        saving = progress_lib.itstime(step, ckpt_every, total) or stopped
        logged = [s for s in range(first, step + 1) if progress_lib.itstime(s, log_every, total)]
        if logged or saving:  # the host reads the flags only here: the device runs ahead
          for m in _not_finite(pending, group.members):
            log(f"{m.label}: {m.error}")
            leave(m)
          pending = []
          if not group.members:
            break
        if logged:
          host, then = jax.device_get(metrics), list(members_then)
          for m in group.members:
            rows = _rows(host, then.index(m), n, m.stage)
            for s in logged:
              row = {key: v for key, v in rows[s - first].items() if key not in m.stage.unlogged}
              m.frame.writer.write_scalars(s, row)
              m.last.update(row)
        status = progress.update(step)
        if status:
          loss = np.asarray(jax.device_get(metrics["loss"]))
          loss = loss[:, -1] if n > 1 else loss
          log(f"{status} loss=" + ",".join(f"{x:.4f}" for x in loss))
        ended = []
        if progress_lib.itstime(step, eval_every, total) and step < total:
          evaluated = group.each(lambda m, at=step: m.stage.evaluate(group.state(m), at))
          for m, scalars in zip(list(group.members), evaluated, strict=True):
            m.last.update(scalars)
            score = m.stage.score(scalars)
            if score is not None:
              m.curve.append((step, score))
            if rule.active:
              stop, reason = stopping.check(rule, m.curve)
              if stop:
                ended.append((m, reason))
        if ended:  # the single run's finite check before it saves at its plateau
          for m in _not_finite(pending, group.members):
            log(f"{m.label}: {m.error}")
            leave(m)
          pending = []
        if saving:
          for m in group.members:
            save(m, step)
        for m, reason in ended:
          if m not in group.members:
            continue
          log(f"{m.label}: stopping at step {step}: {reason}")
          if not saving:
            save(m, step)
          finish(m, step, True, reason)
          leave(m)
        if not group.members:
          break
        if stopped:
          log(
            f"stopping at step {step} on a stop signal; every member's checkpoint saved: run "
            "the same command to resume the grid"
          )
          return True
    finally:
      for b in batches.values():
        b.close()
  group.each(lambda m: finish(m, step, False, "reached total_steps"))
  return False

"""The comparison's run plans, read from plans.toml, and the flags and estimates they give.

A plan (one `--size`) is data: seeds, learning-rate grids per setting, step caps and the
stopping rule, and the inputs of its time estimate. What the library already says is read from
it, not restated: the settings (`camrep.settings`), each setting's real dataset, the
representations a regression run accepts, the :quick configs' step counts the converge caps are
multiples of, and GQN's ConvDRAW schedules.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import pathlib
import tomllib
from collections.abc import Mapping
from typing import Any

from camrep import pose_encodings
from camrep import settings as settings_lib
from camrep.configs import common
from camrep.configs import gqn_convdraw as gqn_convdraw_config
from camrep.configs import regression as regression_config
from camrep.data import sources

PLANS_FILE = pathlib.Path(__file__).with_name("plans.toml")
SETTINGS = settings_lib.names()
NOISE_INPUTS = ("lowdim", "mlp", "convdraw")
"""The noise figure's other pose inputs (`noise_inputs` of a setting, `--noise_kinds`): GQN's
low-dimensional vector, the MLP embedding, GQN's own generator (ConvDRAW: GQN's layout, the rooms'
own or a setting's `convdraw_variant`)."""
FROZEN_GENERATORS = "frozen_gen"
"""The view-synthesis run kind "<column>_frozen_gen": the learned grid with
`--config.rep.freeze_generators=True` (the "frozen_gen" control's pose system)."""


@dataclasses.dataclass(frozen=True)
class Plan:
  """One launch size.

  Attributes:
    name: the size ("quick", "converge", ...).
    variant: the config variant of its runs ("quick", "medium", or "" for paper size).
    seeds: regression seeds (and synthesis seeds where `paired_synthesis`); a setting named in
      `seed_counts` takes its first that many (`seeds_for`).
    lrs: learning-rate grid per setting.
    synthesis_s: estimated seconds per view-synthesis run, per setting ("capture": a capture
      column's; "<setting>_convdraw": GQN's generator), where given.
    regression_s: estimated seconds per regression run (data cached), per setting.
    data_s: one-time rendering of a setting's regression data, seconds.
    evaluate_s: `camrep.synthesis.evaluate` of one synthesis run, seconds.
    where: what the estimate assumes, in words.
    paired_synthesis: one view-synthesis run per seed, read by the regression seed of that number.
    extend_grid: how many lrs beyond its grid phase 1 may try while seed 0's choice is at an edge.
    stop: the stopping rule ({min_improvement, window, min_share, evaluations}); empty: none.
    regression_caps: steps per setting under the stopping rule.
    synthesis_caps: view-synthesis steps per setting under the rule; a setting not named keeps
      its config's own total_steps and no rule.
    convdraw_steps: GQN's ConvDRAW length, its schedules stretched to it (0: its config's own).
    full_grid: every seed at every lr of its grid (the lr then chosen on the validation mean
      over all seeds, never on one seed's), as `--full_grid` asks.
    controls: the control targets added to every column (plans.toml's `controls`, where the
      size says `controls = true`).
    synthesis_extra: per setting, --config flags its view-synthesis runs on procedural data add
      (the plateau rule on the validation split; 7-Scenes over all seven scenes' trajectories
      where the :quick config learns from two); "capture": those of a capture column's runs
      (`capture_synthesis_flags`).
    seed_counts: per setting, how many of `seeds` its columns run (plans.toml's `seed_counts`);
      a setting not named runs them all.
    vectorise: the regression runs of one column and representation trained as one program
      (`camrep.regression.vectorised`: phase 1 one over the lrs, phase 2 one over the later seeds):
      {"step_speedup": member-steps per second of the program over the runs one after another,
      "startup_s": what a run spends outside its steps, paid once per program}; empty: one
      process per run.
  """

  name: str
  variant: str
  seeds: tuple[int, ...]
  lrs: dict[str, tuple[float, ...]]
  synthesis_s: dict[str, float]
  regression_s: dict[str, float]
  data_s: dict[str, float]
  evaluate_s: float
  where: str = ""
  paired_synthesis: bool = False
  extend_grid: int = 0
  stop: dict[str, float] = dataclasses.field(default_factory=dict)
  regression_caps: dict[str, int] = dataclasses.field(default_factory=dict)
  synthesis_caps: dict[str, int] = dataclasses.field(default_factory=dict)
  convdraw_steps: int = 0
  vectorise: dict[str, float] = dataclasses.field(default_factory=dict)
  full_grid: bool = False
  controls: tuple[str, ...] = ()
  synthesis_extra: dict[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
  seed_counts: dict[str, int] = dataclasses.field(default_factory=dict)

  def __post_init__(self):
    for s, n in self.seed_counts.items():
      if s not in SETTINGS or not 1 <= n <= len(self.seeds):
        raise ValueError(
          f"{PLANS_FILE}: size {self.name}: seed_counts {s} = {n}: the setting must be one of "
          f"{SETTINGS} and the count within 1..{len(self.seeds)} (its seeds)"
        )

  def seeds_for(self, setting: str) -> tuple[int, ...]:
    """The seeds of `setting`'s columns: the first `seed_counts[setting]` of `seeds`, else all."""
    return self.seeds[: self.seed_counts.get(setting, len(self.seeds))]

  @property
  def suffix(self) -> str:
    """The `:variant` of its config arguments ("" at paper size)."""
    return f":{self.variant}" if self.variant else ""

  def convdraw_config(self, setting: str) -> str | None:
    """The `--config` of GQN's generator on `setting` at this plan's variant: the rooms' own
    variant, or the setting's `convdraw_variant` (plans.toml) where the plan's is "quick"; None
    where it has none (`:medium`)."""
    variant = settings()[setting].get("convdraw_variant")
    if variant:
      return f"configs/gqn_convdraw.py:{variant}" if self.variant == "quick" else None
    return f"configs/gqn_convdraw.py{self.suffix}" if self.variant in common.NO_MEDIUM else None


def real_source(setting: str) -> str:
  """The real dataset a setting's `--data SETTING=DIR` holds: the first registered reader of the
  setting that is neither procedural nor a capture format (gqn, srn_cars, gibson, seven_scenes)."""
  return next(
    s.name
    for s in sources.SOURCES.values()
    if settings_lib.get(s.setting).name == setting
    and not s.procedural
    and ".captures." not in s.module
  )


def quick_steps(config_module: str) -> int:
  """total_steps of camrep.configs.<module>'s :quick variant."""
  return int(
    importlib.import_module(f"camrep.configs.{config_module}").get_config("quick").total_steps
  )


@functools.cache
def settings() -> dict[str, dict[str, Any]]:
  """{setting: {synthesis_config, representations, table, ...}} of plans.toml, in its order,
  checked against the library."""
  data = _read()["settings"]
  if set(data) != set(SETTINGS):
    raise ValueError(f"{PLANS_FILE}: settings {sorted(data)} are not the library's {SETTINGS}")
  for name, s in data.items():
    bad = set(s["representations"]) - set(pose_encodings.REPRESENTATIONS)
    if bad:
      raise ValueError(f"{PLANS_FILE}: {name}: unknown representations {sorted(bad)}")
    kinds = set(s.get("noise_inputs", ()))
    bad = kinds - set(NOISE_INPUTS)
    if bad:
      raise ValueError(
        f"{PLANS_FILE}: {name}: unknown noise_inputs {sorted(bad)}; choose from {NOISE_INPUTS}"
      )
    variant = s.get("convdraw_variant")
    if "convdraw" in kinds and not (settings_lib.get(name).context_views or variant):
      raise ValueError(
        f"{PLANS_FILE}: {name}: GQN's generator (convdraw) reads context views (task gqn); "
        f"the {name} setting has none and no convdraw_variant puts its family in that layout"
      )
    if variant:
      gqn_convdraw_config.get_config(variant)  # a ValueError names the config's variants
  # In plans.toml's order: the order of the tables' columns.
  return {
    n: {
      **s,
      "representations": tuple(s["representations"]),
      "noise_inputs": tuple(s.get("noise_inputs", ())),
    }
    for n, s in data.items()
  }


def synthesis_suffix(representation: str) -> str | None:
  """The suffix of the view-synthesis run ("<column><suffix>[_seed<k>]") whose pose input a
  regression of `representation` reads, None for one that reads none: "" for the learned grid
  and its untrained control, "_mlp" for the MLP embedding, "_frozen_gen" for the grid learned
  with frozen generators."""
  cls = pose_encodings.get(representation)
  if not cls.learned:
    return None
  kind = cls.trained_by()
  suffix = "" if kind is pose_encodings.GridEncoding else f"_{kind.name}"
  return suffix + (f"_{FROZEN_GENERATORS}" if cls.frozen_generators else "")


@functools.cache
def _read() -> dict[str, Any]:
  with open(PLANS_FILE, "rb") as f:
    return tomllib.load(f)


def _floats(d: Mapping[str, Any]) -> dict[str, float]:
  return {k: float(v) for k, v in d.items()}


def _plan(name: str, d: Mapping[str, Any]) -> Plan:
  common_fields = dict(
    name=name,
    variant=d["variant"],
    seeds=tuple(d["seeds"]),
    lrs={s: tuple(float(x) for x in v) for s, v in d["lrs"].items()},
    where=d.get("where", ""),
    paired_synthesis=bool(d.get("paired_synthesis", False)),
    extend_grid=int(d.get("extend_grid", 0)),
    vectorise=_floats(d.get("vectorise", {})),
    full_grid=bool(d.get("full_grid", False)),
    controls=tuple(_read()["controls"]) if d.get("controls", False) else (),
    synthesis_extra={s: tuple(v) for s, v in d.get("synthesis_extra", {}).items()},
    seed_counts={s: int(n) for s, n in d.get("seed_counts", {}).items()},
  )
  if "seconds" in d:
    sec = d["seconds"]
    return Plan(
      synthesis_s=_floats(sec["synthesis"]),
      regression_s=_floats(sec["regression"]),
      data_s=_floats(sec["data"]),
      evaluate_s=float(sec["evaluate"]),
      **common_fields,
    )
  # A plan with a stopping rule: caps, and estimates from per-step times and expected shares.
  est, factors = d["estimate"], d["synthesis_cap_factors"]
  configs = {s: settings()[s]["synthesis_config"] for s in SETTINGS}
  quick = {s: quick_steps(pathlib.Path(c).stem) for s, c in configs.items()}
  syn_caps = {s: int(factors[s]) * quick[s] for s in SETTINGS}
  convdraw = int(factors["convdraw"]) * quick_steps("gqn_convdraw")
  reg_caps = {s: int(v) for s, v in d["regression_caps"].items()}
  syn_s = {
    s: est["synthesis_overhead_s"] + est["synthesis_share"] * syn_caps[s] * t
    for s, t in est["synthesis_step_s"].items()
  }
  syn_s["capture"] = (
    est["synthesis_overhead_s"]
    + est["synthesis_share"] * syn_caps["car"] * est["capture_synthesis_step_s"]
  )
  for s in SETTINGS:  # GQN's generator, where a setting's noise figure has it
    if "convdraw" in settings()[s]["noise_inputs"]:
      syn_s[f"{s}_convdraw"] = est["convdraw_overhead_s"] + convdraw * est["convdraw_step_s"]
  reg_s = {
    s: est["regression_overhead_s"] + est["regression_share"] * reg_caps[s] * t
    for s, t in est["regression_step_s"].items()
  }
  return Plan(
    synthesis_s=syn_s,
    regression_s=reg_s,
    data_s=_floats(est["data"]),
    evaluate_s=float(est["evaluate"]),
    stop=_floats(d["stop"]),
    regression_caps=reg_caps,
    synthesis_caps=syn_caps,
    convdraw_steps=convdraw,
    **common_fields,
  )


@functools.cache
def plans() -> dict[str, Plan]:
  """Every size of plans.toml, by name."""
  return {name: _plan(name, d) for name, d in _read()["sizes"].items()}


def group_s(plan: Plan, setting: str, runs: int) -> float:
  """Estimated seconds of `runs` regression runs of `setting` trained as one program: one
  start-up, and their steps at the program's speedup (`Plan.vectorise`); `runs` times a run's
  estimate without vectorising."""
  one = plan.regression_s[setting]
  if not plan.vectorise:
    return runs * one
  startup = min(plan.vectorise["startup_s"], one)
  return startup + runs * (one - startup) / plan.vectorise["step_speedup"]


def expected_share(plan: Plan) -> float:
  """The share of its cap a regression run is expected to train (for the plan's summary)."""
  return float(_read()["sizes"][plan.name].get("estimate", {}).get("regression_share", 1.0))


def regression_flags(plan: Plan, setting: str) -> list[str]:
  """The plan's --config flags of a regression run of `setting`: cap, evaluation period and the
  stopping rule (none without a rule)."""
  if not plan.stop:
    return []
  cap = plan.regression_caps[setting]
  return [
    f"--config.total_steps={cap}",
    f"--config.eval_every_steps={cap // int(plan.stop['evaluations'])}",
    f"--config.stop.min_steps={int(cap * plan.stop['min_share'])}",
    f"--config.stop.min_improvement={plan.stop['min_improvement']:g}",
    f"--config.stop.window={plan.stop['window']:g}",
  ]


def capture_synthesis_flags(plan: Plan) -> list[str]:
  """A capture column's extra view-synthesis flags (`Plan.synthesis_extra["capture"]`); where they
  evaluate on the validation split (carved from the capture's training views), also the car
  regression's `data.validation_fraction` at the plan's variant, so that the run holds out the
  views its regressions validate on (which `regression.pose_system.check_same_validation`
  demands)."""
  flags = list(plan.synthesis_extra.get("capture", ()))
  if "--config.evals.split=validation" in flags:
    args = ",".join(x for x in (settings_lib.CAR.name, plan.variant) if x)
    fraction = regression_config.get_config(args).data.validation_fraction
    flags.append(f"--config.data.validation_fraction={fraction:g}")
  return flags


def synthesis_flags(plan: Plan, setting: str, kind: str = "") -> list[str]:
  """The plan's --config flags of a view-synthesis run of `setting` with pose input `kind`: its
  cap and the plateau rule (none without synthesis caps); for GQN's generator ("convdraw") its
  length with the schedules stretched to it (no rule, no resuming at another length)."""
  if kind == "convdraw":
    n = plan.convdraw_steps
    if not n:
      return []
    stretched = gqn_convdraw_config.quick_schedules(n)
    return [f"--config.total_steps={n}", f"--config.eval_every_steps={n // 20}"] + [
      f"--config.{field}={steps}" for field, steps in stretched.items()
    ]
  cap = plan.synthesis_caps.get(setting)
  if not cap:
    return []
  return [
    f"--config.total_steps={cap}",
    f"--config.eval_every_steps={cap // int(plan.stop['evaluations'])}",
    f"--config.stop.min_improvement={plan.stop['min_improvement']:g}",
    f"--config.stop.window={plan.stop['window']:g}",
    f"--config.stop.min_steps={int(cap * plan.stop['min_share'])}",
    # A raised cap resumes a run that reached the old one (recorded in config_history.jsonl).
    "--config.allow_changes=total_steps,eval_every_steps,stop",
  ]

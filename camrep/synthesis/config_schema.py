"""The view-synthesis config's validation pass (`camrep.runtime.validate`): a rule per field of
`configs/common.py:base` and of GQN's generator (`configs/gqn_convdraw.py` adds them; on another
config `--config.model.draw_steps=...` is an unknown field, refused when the flag is parsed),
which fields each task, model and data source uses, and the data-model checks (image size) made
against the family's or the prepared dataset's own record before any data is read or anything
compiled.

`validate(config, overridden=...)` is what `python -m camrep.main` runs first; it raises
`ConfigError` (or `DataError` for a prepared directory that cannot be found).
"""

from __future__ import annotations

from collections.abc import Iterable

from camrep import lie, pose, pose_encodings
from camrep.data import procedural, sources, storage
from camrep.data.errors import DataError
from camrep.runtime import runconfig
from camrep.runtime import validate as V
from camrep.runtime.runconfig import ConfigError
from camrep.synthesis import components, synthesizers

TASKS = tuple(synthesizers.TASKS)
DATA_MODES = ("random", "pairs")
SCHEDULES = ("constant", "cosine", "linear")
POLAR_VARIANTS = tuple(pose.POLAR_VARIANTS)
# Image sides the decoders render: the GQN model 64 px; the table decoder 64 (quick) or 128.
GQN_IMAGE_SIZE = 64
TABLE_IMAGE_SIZES = (64, 128)


def _setting(c):
  try:
    return components.setting(c)
  except ValueError:
    return None


def _table(c) -> bool:
  return c.task == "table"


def _convdraw(c) -> bool:
  return synthesizers.is_generator(c)


def _grid(c) -> bool:
  return c.rep.get("kind", "grid") == "grid"


def _polar(c) -> bool:
  setting = _setting(c)
  return setting is not None and setting.has_polar_dof


def _prepared(c) -> bool:
  return bool(c.data.dir)


_NOT_TABLE = "the GQN task's encoder gives the scene code; used by task='table' only"
_NOT_CONVDRAW = "used by model.kind='convdraw' (GQN's generator) only"
_NOT_GRID = "rep.kind is not 'grid': no learned generators, no rotation losses"
_NOT_POLAR = "the setting has no polar (x, y) DOF; used by gqn and gibson data only"

_F, _U = V.Field, V.unless

SCHEMA: dict[str, V.Field] = {
  "seed": _F(V.NONNEG),
  "task": _F(V.one_of(TASKS)),
  "allow_changes": _F(V.ANY),
  "total_steps": _F(V.POSITIVE),
  "log_every_steps": _F(V.NONNEG),  # 0: never
  "eval_every_steps": _F(V.NONNEG),  # 0: never
  # Retention that keeps no checkpoint would lose the run: refused.
  "ckpt_every_steps": _F(V.POSITIVE),
  "max_to_keep": _F(V.POSITIVE),
  # The plateau stopping rule (camrep/runtime/stopping.py; the ranges `rule_from_config` accepts).
  "stop.min_improvement": _F(V.NONNEG),  # 0: off
  "stop.window": _F(V.Rule("fraction")),
  "stop.min_steps": _F(V.NONNEG),
  "data.source": _F(V.one_of(sources.SOURCES)),
  "data.preset": _F(V.ANY),  # procedural: checked by `check_data`; prepared: a builder config
  "data.dir": _F(V.optional(V.Rule("dir"))),
  "data.in_memory": _F(V.ANY, _U(lambda c: not _prepared(c), "data.dir is set (prepared data)")),
  "data.family.": _F(
    V.SECTION, _U(lambda c: not _prepared(c), "data.dir is set: the prepared data is used")
  ),
  "data.scenes_per_device": _F(V.POSITIVE),
  "data.views_per_scene": _F(V.at_least(2)),
  "data.n_context": _F(V.POSITIVE, _U(synthesizers.reads_context, "used by task='gqn' only")),
  "data.mode": _F(V.one_of(DATA_MODES)),
  "data.num_threads": _F(V.NONNEG),
  "data.prefetch": _F(V.NONNEG),
  "data.num_workers": _F(
    V.at_least(-1), _U(_prepared, "worker processes decode prepared data (data.dir) only")
  ),
  "data.device_prefetch": _F(V.NONNEG),
  "model.width": _F(V.POSITIVE),
  "model.image_size": _F(
    V.one_of(TABLE_IMAGE_SIZES),
    _U(_table, f"the GQN task's model renders {GQN_IMAGE_SIZE} px images; task='table' only"),
  ),
  "model.scene_dim": _F(V.POSITIVE, _U(_table, _NOT_TABLE)),
  "model.per_scene_norm": _F(V.ANY, _U(_table, _NOT_TABLE)),
  "model.norm_eps": _F(V.NONNEG, _U(_table, _NOT_TABLE)),
  "model.gamma_init_one": _F(V.ANY),
  "model.kind": _F(V.one_of(synthesizers.MODEL_KINDS)),
  "model.dtype": _F(V.one_of(synthesizers.COMPUTE_DTYPES)),
  "model.draw_steps": _F(V.POSITIVE, _U(_convdraw, _NOT_CONVDRAW)),
  "model.z_channels": _F(V.POSITIVE, _U(_convdraw, _NOT_CONVDRAW)),
  "model.draw_temperature": _F(V.NONNEG, _U(_convdraw, _NOT_CONVDRAW)),
  "rep.kind": _F(V.one_of(pose_encodings.SYNTHESIS_KINDS)),
  "rep.n_blocks": _F(V.POSITIVE),
  "rep.block_size": _F(V.POSITIVE),
  "rep.exp_method": _F(V.one_of(lie.EXP_METHODS)),
  "rep.n_steps": _F(V.POSITIVE),
  "rep.periodic": _F(V.ANY),
  "rep.angle_spacing_deg": _F(V.POSITIVE),
  "rep.position_spacing": _F(V.POSITIVE),
  "rep.polar_variant": _F(V.one_of(POLAR_VARIANTS), _U(_polar, _NOT_POLAR)),
  "rep.n_directions": _F(V.POSITIVE, _U(_polar, _NOT_POLAR)),
  "rep.block_norm": _F(V.ANY, _U(_polar, _NOT_POLAR)),
  "rep.pair_radius": _F(V.POSITIVE, _U(_polar, _NOT_POLAR)),
  "rep.quantisation": _F(V.one_of(pose.QUANTISATION_MODES)),
  "loss.rec_weight": _F(V.NONNEG),
  "loss.rot_weight": _F(V.NONNEG, _U(_grid, _NOT_GRID)),
  "loss.dir_weight": _F(
    V.NONNEG,
    _U(
      lambda c: _grid(c) and _polar(c) and c.rep.polar_variant == "binned",
      "used by binned polar systems (rep.polar_variant='binned', gqn / gibson data) only",
    ),
  ),
  "loss.n_pairs": _F(V.NONNEG, _U(_grid, _NOT_GRID)),
  "loss.data_pairs": _F(V.ANY),
  "loss.sigma_initial": _F(V.POSITIVE, _U(_convdraw, _NOT_CONVDRAW)),
  "loss.sigma_final": _F(V.POSITIVE, _U(_convdraw, _NOT_CONVDRAW)),
  "loss.sigma_anneal_steps": _F(V.POSITIVE, _U(_convdraw, _NOT_CONVDRAW)),
  "loss.kl_weight_initial": _F(V.NONNEG, _U(_convdraw, _NOT_CONVDRAW)),
  "loss.kl_anneal_steps": _F(V.NONNEG, _U(_convdraw, _NOT_CONVDRAW)),
  "optax.lr_model": _F(V.POSITIVE),
  "optax.lr_rep": _F(V.NONNEG),
  "optax.schedule": _F(V.one_of(SCHEDULES)),
  "optax.final_scale": _F(
    V.NONNEG, _U(lambda c: c.optax.schedule == "linear", "used by optax.schedule='linear' only")
  ),
  "optax.anneal_steps": _F(
    V.POSITIVE, _U(lambda c: c.optax.schedule == "linear", "used by optax.schedule='linear' only")
  ),
  "optax.pose_steps": _F(V.NONNEG),
  "evals.num_scenes": _F(V.POSITIVE),
  "evals.batch_scenes": _F(V.POSITIVE),
  "evals.grid_scenes": _F(V.POSITIVE),
  "evals.baseline_views": _F(
    V.POSITIVE,
    _U(
      lambda c: not synthesizers.reads_context(c),
      "the GQN task's baseline is the mean of the context views",
    ),
  ),
}


def model_image_size(config) -> int:
  """The side of the images the config's model renders."""
  return GQN_IMAGE_SIZE if synthesizers.reads_context(config) else int(config.model.image_size)


def data_image_shape(config) -> tuple[tuple[int, int], str]:
  """(H, W) of the config's data and where that comes from, read from the prepared dataset's
  record (`camrep_source.json`) or the procedural family's config (nothing is rendered).

  Raises:
    ConfigError: an unknown preset or family field.
    DataError: the prepared dataset cannot be found.
  """
  d = config.data
  if d.dir:
    dataset_config = d.preset if d.preset != "default" else None
    path = storage.dataset_dir(d.dir, d.source, config=dataset_config)
    meta = storage.load_metadata(path)
    shape = meta.get("image_shape")
    if not shape:
      raise DataError(path, "its camrep_source.json has no image_shape; prepare it again")
    want = sources.SOURCES[d.source].pose_names if d.source in sources.SOURCES else None
    got = meta.get("pose_names")
    if want is not None and got is not None and tuple(got) != tuple(want):
      raise ConfigError(
        f"--config.data.source={d.source!r} takes poses {list(want)}, but the prepared dataset "
        f"{path} holds poses {list(got)} (another source's data?)"
      )
    return (int(shape[0]), int(shape[1])), f"the prepared dataset {path}"
  family = dict(d.family.to_dict()) if d.family else {}
  try:
    fam = procedural.make_config(d.source, d.preset, **family)
  except TypeError as e:
    raise ConfigError(f"config.data.family {family}: {e}") from None
  except ValueError as e:
    raise ConfigError(f"config.data (source {d.source!r}, preset {d.preset!r}): {e}") from None
  size = int(fam.image_size)
  return (size, size), f"the procedural {d.source!r} family (preset {d.preset!r})"


def check_data(config) -> None:
  """The model's image size against the data's (before any data is read or step compiled)."""
  if not sources.is_procedural(config.data.source) and not config.data.dir:
    return  # components.make_pipeline names the missing prepared directory
  (h, w), where = data_image_shape(config)
  side = model_image_size(config)
  if (h, w) != (side, side):
    if synthesizers.reads_context(config):
      model = f"the GQN task's model renders {side}x{side} images"
    else:
      model = f"--config.model.image_size={side}: the model renders {side}x{side} images"
    raise ConfigError(
      f"{model}, but {where} has {h}x{w} images; "
      + (
        f"set --config.model.image_size={h} (allowed: {list(TABLE_IMAGE_SIZES)})"
        if not synthesizers.reads_context(config) and h == w and h in TABLE_IMAGE_SIZES
        else f"use data of {side}x{side} images"
      )
    )


def validate(config, *, overridden: Iterable[str] = ()) -> None:
  """The whole pass: every field's rule, overridden fields the run ignores, the cross-field
  checks of `components.check_config`, the data-model checks, and `allow_changes` naming fields
  that exist.

  Raises:
    ConfigError: the first problem, naming the field, its value and what is allowed.
    DataError: a prepared dataset that cannot be found.
  """
  V.check(config, SCHEMA, overridden=overridden)
  fields = set(V.leaves(config))
  for name in runconfig.parse_allow_changes(config.get("allow_changes", "")):
    if name == "global_batch":
      continue
    if name not in fields and not any(f.startswith(name + ".") for f in fields):
      raise ConfigError(
        f"--config.allow_changes={config.allow_changes!r}: {name!r} is not a config field "
        "(allowed: fields of runconfig.SYNTHESIS_RESUMABLE, a section name, or global_batch)"
      )
  components.check_config(config)
  check_data(config)

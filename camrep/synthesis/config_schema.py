"""The view-synthesis config's fields, each declared once (`camrep.runtime.validate.Field`): its
rule, which task, model and data source use it, and whether it may change when a run resumes
(`SCHEMA`: the run frame's fields, `camrep.runtime.frame.FIELDS`, and those of
`configs/common.py:base` and of GQN's generator; `configs/gqn_convdraw.py` adds the generator's,
and on another config `--config.model.draw_steps=...` is an unknown field, refused when the flag
is parsed). The retired fields a stored config may still hold (`RETIRED`) and the resume rules
are derived from it.

`validate(config, overridden=...)` is the stage's one validation: every field's rule, the
cross-field checks, and the data-model checks (image size) made against the family's or the
prepared dataset's own record before any data is read or anything compiled; it returns the
config `components.Resolved` (its names looked up once) that the stage builds on. `python -m
camrep.main` runs it first (with the command line's overrides) and `train.train_and_evaluate`
runs it again; it raises `ConfigError` (or `DataError` for a prepared directory that cannot be
found).
"""

from __future__ import annotations

from collections.abc import Iterable

from camrep import lie, pose, pose_encodings
from camrep.data import sources
from camrep.data.errors import DataError
from camrep.data.feed import storage
from camrep.models import mvt
from camrep.runtime import frame as frame_lib
from camrep.runtime import validate as V
from camrep.runtime import workdir as workdir_lib
from camrep.runtime.runconfig import ConfigError
from camrep.synthesis import components, conditionings, synthesizers

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


def _mvt(c) -> bool:
  return synthesizers.TASKS.get(c.task) is synthesizers.MVTSynthesizer


def _not_mvt(c) -> bool:
  return not _mvt(c)


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
_NOT_MVT = "used by task='mvt' (the multi-view transformer, configs/lvsm.py) only"
_MVT_SIZE = "task='mvt' sizes its transformer by model.size"

_F, _U = V.Field, V.unless
# Resume policies (`validate`): FIXED unless marked. MAY_CHANGE fields change how a run goes on,
# never what its parameters mean or their shapes; FREE fields only speed or where output goes.
_M, _FREE = V.MAY_CHANGE, V.FREE

SCHEMA: dict[str, V.Field] = {
  **frame_lib.FIELDS,
  "seed": _F(V.NONNEG, resume=_M),
  "task": _F(V.one_of(TASKS)),
  "data.source": _F(V.one_of(lambda: sources.SOURCES)),
  "data.preset": _F(V.ANY),  # procedural: checked by `check_data`; prepared: a builder config
  "data.dir": _F(V.optional(V.Rule("dir")), resume=_M),
  "data.in_memory": _F(V.ANY, _U(lambda c: not _prepared(c), "data.dir is set (prepared data)")),
  "data.family.": _F(
    V.SECTION, _U(lambda c: not _prepared(c), "data.dir is set: the prepared data is used")
  ),
  "data.scenes_per_device": _F(V.POSITIVE),
  "data.views_per_scene": _F(V.at_least(2)),
  "data.n_context": _F(V.POSITIVE, _U(synthesizers.reads_context, "used by task='gqn' only")),
  "data.mode": _F(V.one_of(DATA_MODES)),
  "data.num_threads": _F(V.NONNEG, resume=_FREE),
  "data.prefetch": _F(V.NONNEG, resume=_FREE),
  "data.num_workers": _F(
    V.at_least(-1),
    _U(_prepared, "worker processes decode prepared data (data.dir) only"),
    resume=_FREE,
  ),
  "data.device_prefetch": _F(V.NONNEG, resume=_FREE),
  "data.validation_fraction": _F(
    V.Rule("fraction"),
    _U(
      lambda c: c.evals.get("split", "test") == "validation" and _prepared(c),
      "used by a prepared captures dataset with evals.split='validation' only",
    ),
  ),
  "model.width": _F(V.POSITIVE, _U(_not_mvt, _MVT_SIZE)),
  "model.image_size": _F(
    V.one_of(TABLE_IMAGE_SIZES),
    _U(_table, f"the GQN task's model renders {GQN_IMAGE_SIZE} px images; task='table' only"),
  ),
  "model.scene_dim": _F(V.POSITIVE, _U(_table, _NOT_TABLE)),
  "model.per_scene_norm": _F(V.ANY, _U(_table, _NOT_TABLE)),
  "model.norm_eps": _F(V.NONNEG, _U(_table, _NOT_TABLE)),
  "model.gamma_init_one": _F(V.ANY, _U(_not_mvt, "the transformer has no AdaIN")),
  # The multi-view transformer (configs/lvsm.py; absent from configs/common.py:base).
  "model.camera": _F(V.one_of(tuple(conditionings.CONDITIONINGS)), _U(_mvt, _NOT_MVT)),
  "model.size": _F(V.one_of(tuple(mvt.SIZES)), _U(_mvt, _NOT_MVT)),
  "model.init_scale": _F(V.POSITIVE, _U(_mvt, _NOT_MVT)),
  "model.kind": _F(V.one_of(synthesizers.MODEL_KINDS)),
  "model.dtype": _F(V.one_of(synthesizers.COMPUTE_DTYPES), resume=_M),
  # GQN's generator (configs/gqn_convdraw.py; `retired`: the values configs/common.py:base gave
  # every run before they moved there, which a workdir written then still stores).
  "model.draw_steps": _F(V.POSITIVE, _U(_convdraw, _NOT_CONVDRAW), retired=12),
  "model.z_channels": _F(V.POSITIVE, _U(_convdraw, _NOT_CONVDRAW), retired=3),
  "model.draw_temperature": _F(V.NONNEG, _U(_convdraw, _NOT_CONVDRAW), resume=_M, retired=1.0),
  "rep.kind": _F(V.one_of(pose_encodings.SYNTHESIS_KINDS)),
  "rep.freeze_generators": _F(V.ANY, _U(_grid, _NOT_GRID)),
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
  "loss.rec_weight": _F(V.NONNEG, resume=_M),
  "loss.rot_weight": _F(V.NONNEG, _U(_grid, _NOT_GRID), resume=_M),
  "loss.dir_weight": _F(
    V.NONNEG,
    _U(
      lambda c: _grid(c) and _polar(c) and c.rep.polar_variant == "binned",
      "used by binned polar systems (rep.polar_variant='binned', gqn / gibson data) only",
    ),
    resume=_M,
  ),
  "loss.n_pairs": _F(V.NONNEG, _U(_grid, _NOT_GRID), resume=_M),
  "loss.data_pairs": _F(V.ANY),
  "loss.sigma_initial": _F(V.POSITIVE, _U(_convdraw, _NOT_CONVDRAW), resume=_M, retired=2.0),
  "loss.sigma_final": _F(V.POSITIVE, _U(_convdraw, _NOT_CONVDRAW), resume=_M, retired=0.7),
  "loss.sigma_anneal_steps": _F(
    V.POSITIVE, _U(_convdraw, _NOT_CONVDRAW), resume=_M, retired=200_000
  ),
  "loss.kl_weight_initial": _F(V.NONNEG, _U(_convdraw, _NOT_CONVDRAW), resume=_M, retired=1.0),
  "loss.kl_anneal_steps": _F(V.NONNEG, _U(_convdraw, _NOT_CONVDRAW), resume=_M, retired=0),
  "optax.lr_model": _F(V.POSITIVE, resume=_M),
  "optax.lr_rep": _F(V.NONNEG, resume=_M),
  "optax.schedule": _F(V.one_of(SCHEDULES)),
  "optax.final_scale": _F(
    V.NONNEG,
    _U(lambda c: c.optax.schedule == "linear", "used by optax.schedule='linear' only"),
    resume=_M,
  ),
  "optax.anneal_steps": _F(
    V.POSITIVE,
    _U(lambda c: c.optax.schedule == "linear", "used by optax.schedule='linear' only"),
    resume=_M,
  ),
  "optax.pose_steps": _F(V.NONNEG),
  "evals.split": _F(V.one_of(("test", "validation"))),
  "evals.num_scenes": _F(V.POSITIVE, resume=_M),
  "evals.batch_scenes": _F(V.POSITIVE, resume=_M),
  "evals.grid_scenes": _F(V.POSITIVE, resume=_M),
  "evals.context_counts": _F(
    V.Rule("positive_tuple"),
    _U(lambda c: not synthesizers.reads_context(c), "per-scene tables read no context views"),
    resume=_M,
  ),
  "evals.baseline_views": _F(
    V.POSITIVE,
    _U(
      lambda c: not synthesizers.reads_context(c),
      "the GQN task's baseline is the mean of the context views",
    ),
    resume=_M,
  ),
}
# The fields configs/common.py:base no longer holds, with the value every config held (GQN's
# generator's: a workdir written before they moved resumes with a config that lacks them).
RETIRED = V.retired(SCHEMA)


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
  try:  # the family, built (nothing is rendered)
    fam = sources.family_of_config(d).config
  except ValueError as e:
    raise ConfigError(f"config.data (source {d.source!r}, preset {d.preset!r}): {e}") from None
  size = int(fam.image_size)
  return (size, size), f"the procedural {d.source!r} family (preset {d.preset!r})"


def check_data(config) -> None:
  """The evaluation split against the data's splits (a captures dataset's "validation" is carved
  from its training views, `components.carved_validation`), the model's image size against the
  data's (before any data is read or step compiled)."""
  split = config.evals.get("split", "test")
  source = sources.SOURCES.get(config.data.source)
  if source is not None and split not in source.splits:
    carved = split == "validation" and bool(config.data.dir)
    if not carved or components.carved_validation(config) is None:
      raise ConfigError(
        f"--config.evals.split={split}: data.source {config.data.source!r} has no {split!r} "
        f"split (it has {list(source.splits)}; a prepared captures dataset holds out every "
        "round(1 / data.validation_fraction)-th training view as one); use "
        "--config.evals.split=test"
      )
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


def validate(config, *, overridden: Iterable[str] = ()) -> components.Resolved:
  """The whole pass: every field's rule, overridden fields the run ignores, `allow_changes`
  naming fields that exist, the run frame's checks (`frame.check_config`: the stopping rule),
  the cross-field checks of `components.check_config`, and the data-model checks.

  Returns:
    The config `components.Resolved` (the config itself unchanged).

  Raises:
    ConfigError: the first problem, naming the field, its value and what is allowed.
    DataError: a prepared dataset that cannot be found.
  """
  V.check(config, SCHEMA, overridden=overridden)
  V.check_allow_changes(config, SCHEMA, extra=(workdir_lib.GLOBAL_BATCH,))
  frame_lib.check_config(config)
  run = components.check_config(config)
  check_data(config)
  return run

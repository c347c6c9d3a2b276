"""camrep's public API, in the style of dm_pix's `api_test.py`: the public names of the main
modules exist and are callable, and the keyword-only arguments of the public functions stay
keyword-only (a positional call would silently bind a different parameter after a reorder).

The pose modules are left out here (tests/test_pose.py covers their interface)."""

import importlib
import inspect

import pytest

PUBLIC = {
  "camrep.lie": (
    "skew",
    "vee",
    "init_generator",
    "block_diag",
    "matvec_blocks",
    "exp_skew",
    "apply_exp_skew",
    "exp_blocks",
    "apply_exp_blocks",
    "num_skew_params",
    "block_size_from_num_params",
  ),
  "camrep.metrics": (
    "psnr",
    "ssim",
    "to_unit_range",
    "translation_error",
    "rotation_error_deg",
    "wrapped_angle_error_deg",
    "abs_error",
    "masked_mean",
  ),
  "camrep.rotations": (
    "quat_to_matrix",
    "matrix_to_quat",
    "standardise_quat",
    "orthonormalize",
    "axis_angle_to_quat",
    "quat_to_axis_angle",
    "quat_log",
    "quat_exp",
    "matrix_to_rot6d",
    "rot6d_to_matrix",
    "euler_sxyz_to_matrix",
    "matrix_to_euler_sxyz",
    "yaw_to_quat",
    "quat_to_yaw",
    "rot_x",
    "rot_y",
    "rot_z",
  ),
  "camrep.data.sources": ("Source", "register", "get", "build", "is_available", "setting_of"),
  "camrep.data.feed.batches": ("ViewBatch", "SplitInfo", "describe", "dummy_batch"),
  "camrep.synthesis.train": ("train_and_evaluate",),
  "camrep.regression.driver": ("run",),
  "camrep.regression.targets": ("encoding", "head_specs", "encode", "decode"),
  "camrep.settings": ("Setting", "register", "get", "names"),
  "camrep.pose_encodings": ("PoseEncoding", "HeadSpec", "get", "create"),
  "camrep.runtime.cli": ("UsageError", "fail", "call", "main", "run", "parse_flags"),
  "camrep.configs": ("path", "resolve", "define_config_flag"),
}

# (module, function) -> the parameters that must be keyword-only.
KEYWORD_ONLY = {
  ("camrep.synthesis.train", "train_and_evaluate"): ("log",),
  ("camrep.regression.driver", "run"): ("log",),
  ("camrep.data.sources", "build"): ("input_path", "preset", "overrides"),
  ("camrep.data.feed.batches", "dummy_batch"): ("num_devices", "info"),
  ("camrep.lie", "skew"): ("block_size",),
  ("camrep.lie", "exp_skew"): ("method", "n_steps"),
  ("camrep.lie", "apply_exp_skew"): ("method", "n_steps", "index"),
  ("camrep.metrics", "ssim"): ("filter_size",),
  ("camrep.regression.targets", "encoding"): ("spec", "refine_steps", "mlp_hidden"),
  ("camrep.regression.targets", "encode"): ("spec", "rep_params", "mode"),
  ("camrep.regression.targets", "decode"): ("spec", "rep_params"),
  ("camrep.runtime.cli", "call"): ("prog",),
  ("camrep.configs", "define_config_flag"): ("lock_config", "flag_values"),
}

# Leading positional parameters, in order, of the entry points a user calls by hand.
POSITIONAL = {
  ("camrep.synthesis.train", "train_and_evaluate"): ("config", "workdir"),
  ("camrep.regression.driver", "run"): ("config", "workdir"),
  ("camrep.data.sources", "build"): ("name",),
}


@pytest.mark.parametrize("module_name,name", [(m, n) for m, names in PUBLIC.items() for n in names])
def test_public_name_exists_and_is_callable(module_name, name):
  module = importlib.import_module(module_name)
  assert hasattr(module, name), f"{module_name}.{name} is gone"
  assert callable(getattr(module, name)), f"{module_name}.{name} is not callable"


def test_rotations_all_lists_exactly_its_public_functions():
  rotations = importlib.import_module("camrep.rotations")
  defined = {
    n
    for n, v in vars(rotations).items()
    if inspect.isfunction(v) and v.__module__ == rotations.__name__ and not n.startswith("_")
  }
  assert set(rotations.__all__) == defined
  assert set(PUBLIC["camrep.rotations"]) == defined


@pytest.mark.parametrize("module_name,name", sorted(KEYWORD_ONLY))
def test_keyword_only_arguments_stay_keyword_only(module_name, name):
  fn = getattr(importlib.import_module(module_name), name)
  params = inspect.signature(fn).parameters
  for arg in KEYWORD_ONLY[(module_name, name)]:
    assert arg in params, f"{module_name}.{name} lost its argument {arg!r}"
    assert params[arg].kind is inspect.Parameter.KEYWORD_ONLY, (
      f"{module_name}.{name}'s {arg!r} is {params[arg].kind.description}, not keyword-only"
    )


@pytest.mark.parametrize("module_name,name", sorted(POSITIONAL))
def test_entry_points_keep_their_positional_arguments(module_name, name):
  fn = getattr(importlib.import_module(module_name), name)
  positional = [
    p.name
    for p in inspect.signature(fn).parameters.values()
    if p.kind in (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
  ]
  assert tuple(positional) == POSITIONAL[(module_name, name)]

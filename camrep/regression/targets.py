"""Pose encodings as regression targets (paper section 4.4, Table 1): the heads, their losses and
their weighting.

A pose regressor predicts a dict of heads {head name: (..., size)}; the representation
(`config.representation`) is a `camrep.pose_encodings.PoseEncoding`, which maps poses in the
setting's columns (`camrep.settings`) to those heads and back. `encode`, `decode` and
`head_specs` build it from a representation's name, a setting and the frozen parameters; this
module adds the head losses and the weighting of the position and orientation groups (Kendall
et al. 2017's L = e^{-s_x} L_pos + s_x + e^{-s_q} L_ori + s_q, or fixed weights). Training
hyper-parameters (which loss weighting, learning rates, ...) live in configs/regression.py.
Everything is a pure, batched function; callers jit.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp

from camrep import pose as P
from camrep import pose_encodings, rotations
from camrep import settings as settings_lib
from camrep.pose_encodings import GROUPS, HeadSpec

Array = jax.Array

REPRESENTATIONS = pose_encodings.REPRESENTATIONS
"""The representations a regression run can predict, by their regression names."""
LEARNED = tuple(
  c.table_name() for c in pose_encodings.ENCODINGS.values() if c.learned and c.regression_target
)
"""The learned representations ("ours", "mlp"): their targets need a view-synthesis run's (or
an initialised) parameters."""
BASELINES = tuple(
  c.table_name() for c in pose_encodings.ENCODINGS.values() if c.regression_target and not c.per_dof
)
"""The hand-designed representations."""


def encoding(
  representation: str,
  setting: settings_lib.Setting | str,
  *,
  spec: P.PoseSystemSpec | None = None,
  refine_steps: int = 4,
  mlp_hidden: int = 128,
) -> pose_encodings.PoseEncoding:
  """The `PoseEncoding` of (representation, setting): a learned one on `spec` (default the
  setting's paper-size pose system).

  Raises:
    ValueError: an unknown representation or setting, or one a regressor cannot predict.
  """
  if representation not in REPRESENTATIONS:
    raise ValueError(f"unknown representation {representation!r}; choose one of {REPRESENTATIONS}")
  return pose_encodings.create(
    representation, setting, spec, refine_steps=refine_steps, mlp_hidden=mlp_hidden
  )


def head_specs(
  representation: str, setting: settings_lib.Setting | str, *, spec: P.PoseSystemSpec | None = None
) -> tuple[HeadSpec, ...]:
  """The heads a regressor for (representation, setting) predicts (`PoseEncoding.heads`).

  Learned ("ours", "mlp"): one head of size spec.dim per DOF (96 at paper size; 7-Scenes 32),
  group "position" for polar / linear DOFs and "orientation" for angles; norm "block" for a polar
  DOF with block_norm (ours), "unit" otherwise. Baselines: "position" (2 or 3, none for car) and
  "orientation" (euler 1/2/3, sincos 2/4/6, quat 4, logq 3, axis_angle 3, rot6d 6, svd9d 9), both
  unnormalised.

  Args:
    representation: one of `REPRESENTATIONS`.
    setting: a setting (or its name).
    spec: the pose system (learned representations; default the setting's paper size).
  """
  return encoding(representation, setting, spec=spec).heads()


def _check_quantisation(enc: pose_encodings.PoseEncoding, rep_params: Any, mode: str | None):
  if enc.learned and rep_params is None:
    raise ValueError(f"representation {enc.table_name()!r} needs rep_params")
  if enc.quantised and mode is None:
    raise ValueError(
      f'representation "{enc.table_name()}" needs the quantisation mode ("floor" or "nearest")'
    )


def encode(
  representation: str,
  setting: settings_lib.Setting | str,
  poses: Array,
  *,
  spec: P.PoseSystemSpec | None = None,
  rep_params: Any = None,
  mode: str | None = None,
  mlp_hidden: int = 128,
) -> dict[str, Array]:
  """Regression targets of poses: {head name: (..., head size)}, as `head_specs` lists them.

  Args:
    representation: one of `REPRESENTATIONS`.
    setting: a setting (or its name).
    poses: (..., P) poses in the setting's columns (`Setting.pose_columns`).
    spec: pose system of a learned representation (default the setting's paper size).
    rep_params: "ours": the frozen pose-system params; "mlp": `MlpEncoding.init` params. Taken
      under stop_gradient.
    mode: quantisation of "ours" ("floor" / "nearest"; required there).
    mlp_hidden: hidden size of the MLP embedding.

  Returns:
    dict of (..., size) float arrays.
  """
  enc = encoding(representation, setting, spec=spec, mlp_hidden=mlp_hidden)
  _check_quantisation(enc, rep_params, mode)
  poses = settings_lib.get(setting).check_poses(poses)
  if enc.learned:
    rep_params = jax.lax.stop_gradient(rep_params)
  return enc.embed(rep_params, poses, mode=mode or "nearest")


def decode(
  representation: str,
  setting: settings_lib.Setting | str,
  heads: Mapping[str, Array],
  *,
  spec: P.PoseSystemSpec | None = None,
  rep_params: Any = None,
  mode: str | None = None,
  refine_steps: int = 4,
  mlp_hidden: int = 128,
) -> Array:
  """Poses (..., P) from predicted heads: the inverse of `encode`.

  ours: `camrep.pose.decode` (arg-min over the candidate list, eq. 12, then `refine_steps`
  Gauss-Newton steps; 0 gives the authors' plain arg-min). mlp: arg-min over the same candidate
  lists. Baselines: positions as predicted; euler angles wrapped (periodic) or clipped to their
  range; sincos via atan2; quat / logq / axis_angle / rot6d (Gram-Schmidt) / svd9d (SVD
  projection) via the quaternion (`Setting.angles_from_quat`).

  Args:
    heads: {head name: (..., size)}; extra entries are ignored.
    (others as `encode`.)

  Returns:
    (..., P) poses in the setting's columns.
  """
  enc = encoding(
    representation, setting, spec=spec, refine_steps=refine_steps, mlp_hidden=mlp_hidden
  )
  _check_quantisation(enc, rep_params, mode)
  return enc.decode(rep_params, heads, mode=mode or "nearest")


# --------------------------------------------------------------------------------------------
# Losses and weighting.


def _as_matrix(x: Array) -> Array:
  return x.reshape(*x.shape[:-1], 3, 3)


def _l2(diff: Array) -> Array:
  return jnp.mean(jnp.sum(diff * diff, axis=-1))


def _gram_schmidt_frobenius(pred: Array, target: Array) -> Array:
  d = rotations.rot6d_to_matrix(pred) - rotations.rot6d_to_matrix(target)
  return jnp.mean(jnp.sum(d * d, axis=(-2, -1)))


def _svd_frobenius(pred: Array, target: Array) -> Array:
  d = rotations.orthonormalize(_as_matrix(pred)) - _as_matrix(target)
  return jnp.mean(jnp.sum(d * d, axis=(-2, -1)))


LOSSES: dict[str, Callable[[Array, Array], Array]] = {
  # Mean over examples of the squared L2 distance, mean_b sum_i (pred - target)^2 (ours).
  "l2": lambda pred, target: _l2(pred - target),
  # Mean over all entries of (pred - target)^2 (Euler, sin/cos; torch's MSELoss).
  "mse": lambda pred, target: jnp.mean((pred - target) * (pred - target)),
  # Mean over all entries of |pred - target| (q, log q, axis-angle; 7-Scenes ours).
  "l1": lambda pred, target: jnp.mean(jnp.abs(pred - target)),
  # Mean over examples of ||GS(pred) - GS(target)||_F^2, 6-D (rot6d, Zhou et al. 2019).
  "gram_schmidt_frobenius": _gram_schmidt_frobenius,
  # Mean over examples of ||SVDO+(pred) - target||_F^2, 9-D (svd9d, Levinson et al. 2020).
  "svd_frobenius": _svd_frobenius,
}
"""Head losses: name -> (pred (..., size), target (..., size)) -> scalar."""

# Losses defined on rotations: a position head of the same run takes the "l2" loss instead.
_ROTATION_LOSSES = ("gram_schmidt_frobenius", "svd_frobenius")


def head_loss(kind: str, pred: Array, target: Array) -> Array:
  """Loss of one head, a scalar: `LOSSES[kind](pred, target)`.

  Args:
    kind: a key of `LOSSES`.
    pred, target: (..., size).

  Raises:
    ValueError: an unknown kind, or shapes that differ.
  """
  if kind not in LOSSES:
    raise ValueError(f"unknown loss {kind!r}; choose one of {tuple(LOSSES)}")
  if pred.shape != target.shape:
    raise ValueError(f"pred {pred.shape} and target {target.shape} differ")
  return LOSSES[kind](pred, target)


def group_losses(
  kind: str,
  pred: Mapping[str, Array],
  target: Mapping[str, Array],
  heads: tuple[HeadSpec, ...],
) -> dict[str, Array]:
  """Sum of the head losses of each group present: {"position": L_pos, "orientation": L_ori}.

  For 7-Scenes "ours" L_pos = L1_x + L1_y + L1_z; for GQN L_pos = L_loc. The rotation losses of
  rot6d / svd9d are for the orientation; positions take their L2 analogue.
  """
  out = {}
  for h in heads:
    k = "l2" if kind in _ROTATION_LOSSES and h.group == "position" else kind
    val = head_loss(k, pred[h.name], target[h.name])
    out[h.group] = out[h.group] + val if h.group in out else val
  return out


def homoscedastic(loss: Array, s: Array, *, factor: float = 1.0) -> Array:
  """Kendall et al. 2017 learned weighting of one term: e^{-s} loss + factor * s.

  d/ds = factor - e^{-s} loss, so s tends to log(loss / factor). `factor` is 3 for the 7-Scenes
  "ours" loss (three DOF terms per group share one s), else 1.
  """
  return jnp.exp(-s) * loss + factor * s


WEIGHTINGS = ("homoscedastic", "fixed")


def init_log_vars(
  weighting: str, init_s: tuple[float, float], *, learn_s: bool = True
) -> dict[str, Array]:
  """Trainable s per group: {"position": (), "orientation": ()} at `init_s` when the weighting
  is homoscedastic and `learn_s`; {} otherwise (fixed weights, or s held at init_s)."""
  if weighting != "homoscedastic" or not learn_s:
    return {}
  return {g: jnp.asarray(s, jnp.float32) for g, s in zip(GROUPS, init_s, strict=True)}


def total_loss(
  groups: Mapping[str, Array],
  *,
  weighting: str,
  init_s: tuple[float, float] = (0.0, 0.0),
  s_factor: float = 1.0,
  weights: tuple[float, float] = (1.0, 1.0),
  log_vars: Mapping[str, Array] | None = None,
) -> Array:
  """The regression objective from the group losses.

  homoscedastic: sum over groups of e^{-s_g} L_g + s_factor s_g, with s_g from `log_vars` (the
  trained values) or, when None or empty, the constants `init_s`; fixed: sum over groups of
  w_g L_g with `weights`. Groups absent from `groups` (car has no position) contribute nothing.

  Args:
    groups: {"position": (), "orientation": ()} group losses (either may be absent).
    weighting: one of `WEIGHTINGS`.
    init_s, s_factor, weights: per group, in the order of `GROUPS`.
    log_vars: the trained s per group (`init_log_vars`).

  Raises:
    ValueError: an unknown weighting.
  """
  if weighting not in WEIGHTINGS:
    raise ValueError(f"unknown weighting {weighting!r}; choose one of {WEIGHTINGS}")
  total = jnp.zeros((), jnp.float32)
  for i, g in enumerate(GROUPS):
    if g not in groups:
      continue
    if weighting == "homoscedastic":
      s = log_vars[g] if log_vars else jnp.asarray(init_s[i], jnp.float32)
      total = total + homoscedastic(groups[g], s, factor=s_factor)
    else:
      total = total + weights[i] * groups[g]
  return total

"""FLOPs of a JAX function counted from its jaxpr: the same number on every backend.

XLA's cost analysis on GPU leaves cuDNN convolutions out (3.0 GFLOP a step on an H100
against 1,622 on the CPU for the same program), so MFU computed from it is wrong there. This
module walks the jaxpr instead and counts, for every matrix product and convolution, 2 x the
multiply-adds its shapes imply (elementwise work is left out: it is a few percent of these
models' FLOPs and none of their matmul-unit time). Nested jaxprs (jit, custom_jvp / custom_vjp,
remat, scan, while, cond, pmap) are followed; scan bodies count once per iteration.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import jax
import jax.extend.core as jax_core
import numpy as np


def _dot_general_flops(eqn) -> float:
  (lhs_contract, _), (lhs_batch, _) = eqn.params["dimension_numbers"]
  lhs = eqn.invars[0].aval.shape
  out = eqn.outvars[0].aval.shape
  contract = math.prod(lhs[d] for d in lhs_contract)
  del lhs_batch  # batch dims are in the output shape already
  return 2.0 * math.prod(out) * contract


def _conv_flops(eqn) -> float:
  rhs = eqn.invars[1].aval.shape
  out = eqn.outvars[0].aval.shape
  rhs_spec = eqn.params["dimension_numbers"].rhs_spec  # (out features, in features, *spatial)
  in_per_group = rhs[rhs_spec[1]]  # a grouped kernel holds only its group's input features
  window = math.prod(rhs[d] for d in rhs_spec[2:])
  # Every output element is a dot product of in_per_group x window inputs.
  return 2.0 * math.prod(out) * in_per_group * window


def _sub_jaxprs(eqn):
  """(jaxpr, multiplicity) of each jaxpr nested in an equation."""
  p = eqn.params
  if eqn.primitive.name == "scan":
    return [(p["jaxpr"].jaxpr, p["length"])]
  if eqn.primitive.name == "cond":
    return [(max(p["branches"], key=lambda b: jaxpr_flops(b.jaxpr)).jaxpr, 1)]
  out = []
  for v in p.values():
    for item in v if isinstance(v, (tuple, list)) else (v,):
      if isinstance(item, jax_core.ClosedJaxpr):
        out.append((item.jaxpr, 1))
      elif isinstance(item, jax_core.Jaxpr):
        out.append((item, 1))
  return out


def jaxpr_flops(jaxpr) -> float:
  """FLOPs of the matrix products and convolutions of a (closed) jaxpr."""
  jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
  total = 0.0
  for eqn in jaxpr.eqns:
    name = eqn.primitive.name
    if name == "dot_general":
      total += _dot_general_flops(eqn)
    elif name == "conv_general_dilated":
      total += _conv_flops(eqn)
    for sub, times in _sub_jaxprs(eqn):
      total += times * jaxpr_flops(sub)
  return total


def count_flops(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> float:
  """FLOPs of one call fn(*args, **kwargs), from its jaxpr (arrays or ShapeDtypeStructs)."""
  return jaxpr_flops(jax.make_jaxpr(fn)(*args, **kwargs))


def mfu(flops: float, seconds: float, peak_flops_per_s: float) -> float:
  """Model FLOP utilisation: achieved FLOP/s over the device's peak (NaN when unknown)."""
  if not (seconds > 0 and peak_flops_per_s > 0):
    return float(np.nan)
  return flops / seconds / peak_flops_per_s

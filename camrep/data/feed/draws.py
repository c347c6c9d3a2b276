"""NumPy's `Generator.choice` and `Generator.integers` reproduced draw for draw, for many scenes at
once: the batch planner's view choice without a Python call per scene.

A batch's views are chosen scene after scene from ONE generator (`default_rng([seed, 1, step,
process])`, see `camrep.data.feed.pipeline`): for each scene `rng.choice(n, size, replace=False)`
and, in "pairs" mode, `rng.integers(k, size=...)`. This module computes the same numbers for all the
batch's scenes with array operations, from the generator's raw 64-bit outputs
(`bit_generator.random_raw`, one call), following numpy's own algorithms (numpy/random
`_generator.pyx` `Generator.choice`, `_shuffle_int`; `distributions.c` `random_bounded_uint64`,
`buffered_bounded_lemire_uint32`):

- a PCG64 generator hands out 32-bit words as the low then the high half of each 64-bit output
  (`pcg64_next32`), so the words are `random_raw(m).view(np.uint32)` on little-endian machines;
- a bounded integer in [0, r], r < 2^32, takes one word w: m = w (r + 1), value m >> 32, unless
  the low half of m is below (2^32 - 1 - r) mod (r + 1) (Lemire's rejection: then more words are
  drawn). The chance is below (r + 1) / 2^32 per draw; when it happens this module says so
  (returns None) and the caller draws scene by scene with numpy itself;
- `choice(n, size, replace=False)` (population <= 10,000, or size small enough, numpy's Floyd
  branch): for j in n - size .. n - 1, t = bounded(j); keep t unless already kept, else keep j;
  then `_shuffle_int(size, first=1)`: for i in size - 1 .. 1, swap positions i and bounded(i);
- `integers(k, size=c)`: c bounded draws in [0, k - 1] (none when k == 1).

`tests/test_pipeline.py` checks the result against numpy's draws for thousands of (seed, counts,
sizes), and the pipelines check one batch against numpy when they are built
(`choice_matches_numpy`), so a numpy whose algorithms differ is noticed, not followed silently.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

_MASK32 = np.uint64(0xFFFFFFFF)
_ONE = np.uint64(1)
_SHIFT = np.uint64(32)


def _floyd_branch(n: np.ndarray, size: int) -> bool:
  """Whether numpy's `choice(n, size, replace=False, shuffle=True)` takes its Floyd branch for
  every population size in `n`."""
  n = np.asarray(n)
  return not bool(np.any((n > 10000) & (size > n // 50)))


def sequential_draws(
  rngs: Sequence[np.random.Generator],
  counts: np.ndarray,
  size: int,
  *,
  pair_k: int | None = None,
) -> tuple[np.ndarray, np.ndarray | None] | None:
  """For each generator `rngs[b]` and its scenes `counts[b]`, what this numpy code draws:

      for n in counts[b]:
        chosen = rngs[b].choice(n, size=size, replace=False)
        if pair_k is not None:
          picks = rngs[b].integers(min(pair_k, n - 1), size=size)

  Args:
    rngs: B fresh `np.random.Generator`s over PCG64 (no draw taken yet); they are used up.
    counts: int (B, S) views of each scene (each >= size, and >= 2 with `pair_k`).
    size: views chosen per scene.
    pair_k: also draw the "pairs" partner picks (see above); None: choices only.

  Returns:
    (chosen int64 (B, S, size), picks int64 (B, S, size) or None), or None when a draw would
    have been rejected (Lemire), when a population is outside numpy's Floyd branch, or on a
    big-endian machine: then draw with numpy (`numpy_draws`, the same seeds, fresh generators).
  """
  counts = np.asarray(counts, np.int64)
  n_b, n_s = counts.shape
  if sys.byteorder != "little" or not _floyd_branch(counts, size):
    return None
  if not all(isinstance(g.bit_generator, np.random.PCG64) for g in rngs):
    return None
  plan = _draw_plan(counts.tobytes(), counts.shape, size, pair_k)
  r, take, position, threshold, floyd = plan[:5]
  words = np.empty((n_b, plan.words_max), np.uint64)
  for b, g in enumerate(rngs):
    raw = g.bit_generator.random_raw((plan.words[b] + 1) // 2)
    row = raw.view(np.uint32)
    words[b, : len(row)] = row
  w = np.take_along_axis(words, position.reshape(n_b, -1), axis=1).reshape(r.shape)
  m = w * (r + _ONE)
  if np.logical_and(take, (m & _MASK32) < threshold).any():
    return None
  value = (m >> _SHIFT).astype(np.int64)
  value[~take] = 0
  # Floyd's algorithm: for j in n - size .. n - 1, keep t = bounded(j) unless kept, else j.
  chosen = value[:, :size].copy()
  for t in range(1, size):
    dup = np.equal(chosen[:, :t], chosen[:, t : t + 1]).any(axis=1)
    chosen[:, t] = np.where(dup, floyd[:, t], chosen[:, t])
  # numpy's _shuffle_int(size, first=1): for i = size - 1 .. 1, swap i and bounded(i).
  rows = np.arange(len(chosen))
  for c, i in enumerate(range(size - 1, 0, -1)):
    j = value[:, size + c]
    held = chosen[rows, j]
    chosen[rows, j] = chosen[:, i]
    chosen[:, i] = held
  picks = value[:, 2 * size - 1 :].reshape(n_b, n_s, size) if pair_k is not None else None
  return chosen.reshape(n_b, n_s, size), picks


class _Plan(NamedTuple):
  """Where each draw of `sequential_draws` takes its word (rows: B * S scenes, columns: draws)."""

  r: np.ndarray  # uint64 (B S, D) inclusive ranges of the draws
  take: np.ndarray  # bool (B S, D) the draw takes a word (range > 0)
  position: np.ndarray  # int64 (B S, D) its word in its generator's stream
  threshold: np.ndarray  # uint64 (B S, D) Lemire's rejection threshold
  floyd: np.ndarray  # int64 (B S, size) Floyd's j = n - size + t
  words: tuple[int, ...]  # words taken from each generator
  words_max: int


@functools.lru_cache(maxsize=64)
def _draw_plan(counts_bytes: bytes, shape: tuple[int, int], size: int, pair_k: int | None) -> _Plan:
  counts = np.frombuffer(counts_bytes, np.int64).reshape(shape).reshape(-1)
  n_b, n_s = shape
  # The draws of one scene, in order: `size` Floyd draws in [0, n - size + t], `size - 1`
  # shuffle draws in [0, i] for i = size - 1 .. 1, then (pairs) `size` picks in [0, k - 1].
  # A draw whose range is 0 takes no word.
  floyd = counts[:, None] - size + np.arange(size)
  ranges = [floyd, np.tile(np.arange(size - 1, 0, -1), (len(counts), 1))]
  if pair_k is not None:
    k = np.minimum(pair_k, counts - 1)
    ranges.append(np.repeat(k[:, None] - 1, size, axis=1))
  r = np.concatenate(ranges, axis=1).astype(np.uint64)
  take = r > 0
  per_gen = take.reshape(n_b, -1)
  position = (np.cumsum(per_gen, axis=1) - 1).clip(0).reshape(r.shape)
  words = tuple(int(x) for x in per_gen.sum(axis=1))
  threshold = (_MASK32 - r) % (r + _ONE)
  for a in (r, take, position, threshold, floyd):
    a.flags.writeable = False
  return _Plan(r, take, position, threshold, floyd, words, max(1, max(words) + 1))


def numpy_draws(
  rngs: Sequence[np.random.Generator],
  counts: np.ndarray,
  size: int,
  *,
  pair_k: int | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
  """What `sequential_draws` computes, drawn by numpy itself scene by scene (the reference, and
  the fallback)."""
  counts = np.asarray(counts, np.int64)
  chosen = np.empty((*counts.shape, size), np.int64)
  picks = np.empty((*counts.shape, size), np.int64) if pair_k is not None else None
  for b, g in enumerate(rngs):
    for s, n in enumerate(counts[b].tolist()):
      chosen[b, s] = g.choice(n, size=size, replace=False)
      if picks is not None:
        picks[b, s] = g.integers(min(pair_k, n - 1), size=size)
  return chosen, picks

"""Every procedural family, at its small preset, round-trips exactly through its tfds builder."""

from __future__ import annotations

import numpy as np
import pytest

from camrep.data import procedural
from camrep.data.feed import storage

pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]


@pytest.mark.parametrize("name", procedural.FAMILIES)
def test_family_round_trips_through_builder(name, tmp_path):
  family = procedural.make_family(name, preset="small")
  storage.prepare(family, tmp_path, progress=False)
  for split in family.splits:
    expected = sorted(family.iter_views(split), key=lambda r: (r["scene"], r["view"]))
    stored = storage.load(tmp_path, family.name, split)
    assert len(stored) == len(expected) > 0
    got = sorted(
      (stored[i] for i in range(len(stored))), key=lambda r: (int(r["scene"]), int(r["view"]))
    )
    for want, have in zip(expected, got, strict=True):
      assert (int(have["scene"]), int(have["view"])) == (want["scene"], want["view"])
      np.testing.assert_array_equal(have["image"], want["image"])
      np.testing.assert_array_equal(have["pose"], np.asarray(want["pose"], np.float32))

"""Golden tests: today's probes against the committed arrays (:mod:`tests.golden`).

A failure lists the keys that moved and by how much. If the change is meant to move them,
regenerate with ``python -m tests.golden FAMILY`` (it says which results files the change
can move) and commit the arrays with the change.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests import golden
from tests.golden import probes

REGENERATE = "python -m tests.golden {family}"


def _family_params():
  for family, (_, tier) in probes.FAMILIES.items():
    marks = [pytest.mark.full] if tier == "full" else []
    yield pytest.param(family, marks=marks, id=family)


@pytest.mark.parametrize("family", list(_family_params()))
def test_probes_match_their_golden_arrays(family):
  old = golden.load(family)
  assert old, f"no golden arrays for {family}: write them with {REGENERATE.format(family=family)}"
  new = probes.FAMILIES[family][0]()
  bad = golden.compare(family, new, old)
  assert not bad, (f"{len(bad)} of {len(old)} golden values of {family} moved:\n  " + "\n  ".join(bad[:30])
                   + f"\nIf the change is meant to move them: {REGENERATE.format(family=family)}")


# The issue this machinery answers asks that a 1e-4 relative change anywhere in a classic method, the
# scan, a network's forward pass or a train step fail a golden test. Each key's tolerance is checked
# here against exactly that change of its own golden array, at its largest element.
PINNED_TO_1E4 = ("classic", "scan", "forward", "train", "scores")


@pytest.mark.parametrize("family", PINNED_TO_1E4)
def test_a_change_of_1e4_relative_moves_every_float_key_beyond_its_tolerance(family):
  arrays = golden.load(family)
  assert arrays
  missed = []
  for key, g in arrays.items():
    if g.dtype.kind not in "fc" or not np.any(np.isfinite(g) & (g != 0)):
      continue
    planted = np.array(g, copy=True)
    flat = planted.reshape(-1)
    i = np.nanargmax(np.where(np.isfinite(flat), np.abs(flat), -1))
    flat[i] = flat[i] * (1 + 1e-4)
    how = probes.tolerance(family, key, g)
    measured, allowed = golden.difference(planted, g, how)
    if measured <= allowed:
      missed.append(f"{key} ({how})")
  assert not missed, f"a 1e-4 relative change passes: {missed[:10]}"


def test_the_comparison_tells_noise_from_a_change():
  g = np.linspace(-2.0, 3.0, 50, dtype=np.float32)
  assert golden.difference(g * (1 + 1e-6), g, ("rel", 1e-5))[0] <= 1e-5
  assert golden.difference(g * (1 + 1e-4), g, ("rel", 1e-5))[0] > 1e-5
  assert golden.difference(g[:-1], g, ("rel", 1e-5))[0] == float("inf")             # a shape change
  with np.errstate(invalid="ignore"):
    assert golden.difference(g * np.nan, g, ("rel", 1e-5))[0] == float("inf")      # NaN where none was
  counts = np.arange(1000, dtype=np.uint16) % 7
  flipped = counts.copy()
  flipped[3] += 1                                                                     # one draw in 1000
  measured, allowed = golden.difference(flipped, counts, probes.COUNTS)
  assert measured <= allowed
  assert golden.difference(counts * 2, counts, probes.COUNTS)[0] > 1.0
  assert golden.difference(counts + 1, counts, ("exact",))[0] == counts.size
  bad = golden.compare("scores", {"a": g, "b": g}, {"a": g * 1.01, "c": g})
  assert [line.split(":")[0] for line in bad] == ["scores/a", "scores/b", "scores/c"]

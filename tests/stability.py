"""Helpers of the stability tests (``tests/test_stability_*.py``): deviations, checks, bad values."""

import numpy as np
import pytest

from tests.xla_options import xla_optimizations

# What the bad-value tests put into one element of an input: each must be caught or propagate.
BAD_VALUES = {"NaN": np.nan, "+inf": np.inf, "negative": -1.0}


@pytest.fixture(scope="module")
def fast_compiles():
  """Small shapes: XLA's optimisations cost more compile time than they save (as test_models;
  measured: the 12 x 12 reconstructions compile in 60 % of the time, the paper-sized LCT runs
  25 % slower). A module uses it with ``pytestmark = pytest.mark.usefixtures("fast_compiles")``
  after importing it."""
  with xla_optimizations(False):
    yield


def rel_dev(a, b) -> float:
  """``max |a - b| / max |b|`` in float64."""
  a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
  return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def assert_finite_nonnegative(x, what: str = "") -> None:
  x = np.asarray(x, np.float64)
  assert np.all(np.isfinite(x)), f"non-finite values {what}"
  assert np.all(x >= 0), f"negative values {what}"


def peak(vol) -> tuple[int, ...]:
  """Index of the maximum of an array (e.g. ``(k, i, j)`` of a ``[Z, H, W]`` volume)."""
  return np.unravel_index(int(np.argmax(np.asarray(vol))), np.shape(vol))

"""Compare nested results (dicts of lists of numbers), the way the tables are written.

``pytest.approx`` compares flat mappings and sequences only, and since pytest
9.2 it raises on nested ones. A results table is ``method -> metric -> values``,
so the tests walk it here: the keys must match exactly at every level, and the
numeric leaves must agree within ``rtol``/``atol`` (as ``np.testing.assert_allclose``).
"""

from collections.abc import Mapping, Sequence

import numpy as np


def assert_nested_close(actual, expected, *, rtol=1e-6, atol=1e-12, path="") -> None:
  """Assert that two nested dict/list/number structures are equal up to tolerance.

  Args:
    actual, expected: dicts, lists/tuples or numbers (NumPy/JAX scalars and
      arrays count as numbers), nested to any depth. A list and a tuple of the
      same values are equal: JSON turns one into the other.
    rtol, atol: tolerances for numeric leaves (defaults: those of ``pytest.approx``).
    path: where in the structure we are, for the message (callers leave it empty).

  Raises:
    AssertionError naming the first differing key path.
  """
  where = path or "<root>"
  actual, expected = _as_list(actual), _as_list(expected)
  if isinstance(expected, Mapping):
    assert isinstance(actual, Mapping), f"{where}: expected a mapping, got {type(actual).__name__}"
    assert set(actual) == set(expected), \
        f"{where}: keys differ: only actual {sorted(map(str, set(actual) - set(expected)))}, " \
        f"only expected {sorted(map(str, set(expected) - set(actual)))}"
    for key in expected:
      assert_nested_close(actual[key], expected[key], rtol=rtol, atol=atol, path=f"{path}/{key}")
  elif isinstance(expected, Sequence) and not isinstance(expected, (str, bytes)):
    assert isinstance(actual, Sequence) and not isinstance(actual, (str, bytes)), \
        f"{where}: expected a sequence, got {type(actual).__name__}"
    assert len(actual) == len(expected), f"{where}: length {len(actual)} != {len(expected)}"
    for i, (a, e) in enumerate(zip(actual, expected)):
      assert_nested_close(a, e, rtol=rtol, atol=atol, path=f"{path}[{i}]")
  elif isinstance(expected, (str, bytes, bool)) or expected is None:
    assert actual == expected, f"{where}: {actual!r} != {expected!r}"
  else:
    np.testing.assert_allclose(np.asarray(actual, dtype=np.float64),
                               np.asarray(expected, dtype=np.float64),
                               rtol=rtol, atol=atol, err_msg=where)


def _as_list(x):
  """A NumPy/JAX array of rank >= 1 as a (nested) list; anything else as it is."""
  return np.asarray(x).tolist() if hasattr(x, "shape") and np.ndim(x) > 0 else x

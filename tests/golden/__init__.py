"""Golden tests: every number of a fixed set of tiny probes, pinned in committed arrays.

    python -m pytest -q tests/test_golden.py                   # compare (default tier; --tier full for the rest)
    python -m tests.golden                                      # regenerate every family, say what moved
    python -m tests.golden classic scan                         # regenerate some families
    python -m tests.golden --check                              # compare only, write nothing

The probes (:mod:`tests.golden.probes`) run every classic method, every scan kernel, each
network's forward pass and two train steps of each variant, the scores and losses, a
simulated sequence of each renderer, the shipped networks, the evaluation protocol and the
command lines, at sizes that take seconds. Each family's arrays live in
``tests/golden/<family>.npz``. A change that is meant to move numbers regenerates the families
it moves (the command prints, per key, how far it moved) and says which results files that
change can move: those whose command imports a changed module (``benchmarks.index --touched``).
Documentation, comments and help strings move no golden and no results file.

Where the test suite runs with its speed settings (``conftest.py``: XLA's optimisations off,
XLA:CPU's elemental emitters), so do the probes when regenerated: :func:`suite_environment`.
"""

from __future__ import annotations

import pathlib

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent


def golden_path(family: str) -> pathlib.Path:
  return HERE / f"{family}.npz"


def load(family: str) -> dict[str, np.ndarray]:
  """The committed golden arrays of ``family`` (``{}`` where none are committed)."""
  path = golden_path(family)
  if not path.exists():
    return {}
  with np.load(path, allow_pickle=False) as z:
    return {k: z[k] for k in z.files}


def save(family: str, arrays: dict[str, np.ndarray]) -> pathlib.Path:
  path = golden_path(family)
  np.savez_compressed(path, **{k: np.asarray(v) for k, v in sorted(arrays.items())})
  return path


def difference(new: np.ndarray, golden: np.ndarray, how: tuple) -> tuple[float, float]:
  """``(measured, allowed)`` for one key: the difference in the unit of ``how`` and its tolerance.

  ``("rel", rtol)``: ``max |new - golden| / max |golden|`` against ``rtol`` (0 / 0 counts as 0);
  ``("counts", frac, sum_rtol)``: the larger of (the fraction of elements that differ / ``frac``)
  and (the relative difference of the sums / ``sum_rtol``), against 1; ``("exact",)``: the
  number of differing elements, against 0. A shape or dtype kind that differs measures ``inf``.
  """
  new, golden = np.asarray(new), np.asarray(golden)
  if new.shape != golden.shape or (new.dtype.kind in "iub") != (golden.dtype.kind in "iub"):
    return float("inf"), 0.0
  if how[0] == "exact":
    return float(np.count_nonzero(new != golden)), 0.0
  a, b = new.astype(np.float64), golden.astype(np.float64)
  if not (np.array_equal(np.isnan(a), np.isnan(b)) and np.array_equal(np.isinf(a), np.isinf(b))):
    return float("inf"), 0.0
  ok = np.isfinite(b)
  a, b = a[ok], b[ok]
  if how[0] == "counts":
    _, frac, sum_rtol = how
    differing = np.count_nonzero(a != b) / max(a.size, 1)
    total = abs(a.sum() - b.sum()) / max(abs(b.sum()), 1e-300)
    return max(differing / frac, total / sum_rtol), 1.0
  scale = np.max(np.abs(b), initial=0.0)
  diff = np.max(np.abs(a - b), initial=0.0)
  if scale == 0.0:
    return (0.0 if diff == 0.0 else float("inf")), how[1]
  return float(diff / scale), how[1]


def compare(family: str, new: dict, golden: dict) -> list[str]:
  """One line per key of ``family`` that is out of tolerance, missing or new (``[]``: all within)."""
  from tests.golden.probes import tolerance
  bad = []
  for key in sorted(set(golden) | set(new)):
    if key not in new:
      bad.append(f"{family}/{key}: in the golden file, not produced by the probe")
      continue
    if key not in golden:
      bad.append(f"{family}/{key}: produced by the probe, not in the golden file")
      continue
    how = tolerance(family, key, golden[key])
    measured, allowed = difference(new[key], golden[key], how)
    if not measured <= allowed:
      bad.append(f"{family}/{key}: moved {measured:.3g} (allowed {allowed:.3g}, {how[0]})")
  return bad


def suite_environment(environ) -> None:
  """Set in ``environ`` the XLA settings ``conftest.py`` gives the suite (before JAX is imported)."""
  import conftest
  environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
  environ["XLA_FLAGS"] = conftest.suite_xla_flags(environ.get("XLA_FLAGS", ""))


def closest_call(family: str, new: dict, golden: dict) -> str:
  """``"key 0.12"``: the key whose difference is the largest share of its tolerance, and that share."""
  from tests.golden.probes import tolerance
  worst, name = -1.0, "none"
  for key in set(new) & set(golden):
    how = tolerance(family, key, golden[key])
    measured, allowed = difference(new[key], golden[key], how)
    share = measured / allowed if allowed else (0.0 if measured == 0 else float("inf"))
    if share > worst:
      worst, name = share, key
  return f"{name} {worst:.3g}"

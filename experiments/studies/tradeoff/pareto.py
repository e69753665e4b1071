"""The Pareto logic: the front of (time, PSNR) points, the recommended settings, and the
learned points that beat every classic one.

:func:`pareto_points` turns :func:`experiments.studies.tradeoff.study.run`'s results into points;
the report and the plot both read the front from here.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np


def pareto_front(times, scores) -> np.ndarray:
  """Boolean mask ``[n]`` of the points no other point dominates.

  Point ``j`` dominates ``i`` when ``times[j] <= times[i]``, ``scores[j] >=
  scores[i]`` and one of the two is strict (less time is better, more score
  is better). Identical points do not dominate each other, so both stay on
  the front. Points with a non-finite time or score are never on it (and
  dominate nothing). A sweep in order of time: ``O(n log n)``.

  Args:
    times: ``[n]`` seconds (or any cost).
    scores: ``[n]`` e.g. PSNR in dB.
  """
  t = np.asarray(times, np.float64)
  s = np.asarray(scores, np.float64)
  if t.shape != s.shape or t.ndim != 1:
    raise ValueError(f"times and scores must be 1-D of one length, got {t.shape} and {s.shape}")
  mask = np.zeros(t.shape, bool)
  ok = np.flatnonzero(np.isfinite(t) & np.isfinite(s))
  order = ok[np.lexsort((-s[ok], t[ok]))]        # time ascending, score descending
  best, last = -np.inf, None
  for i in order:
    if s[i] > best:
      mask[i], best, last = True, s[i], (t[i], s[i])
    elif last is not None and (t[i], s[i]) == last:
      mask[i] = True
  return mask


def recommend(points: Sequence[dict], *, tolerance_db: float = 1.0) -> dict:
  """``{"fastest", "balanced", "best"}``: names of Pareto-front points.

  ``best`` has the highest PSNR, ``fastest`` the least time per frame, and
  ``balanced`` is the fastest point within ``tolerance_db`` of the best PSNR.

  Args:
    points: dicts with ``name``, ``time`` (s per frame) and ``psnr`` (dB).
  """
  if not points:
    raise ValueError("recommend needs at least one point")
  t = np.array([p["time"] for p in points], np.float64)
  s = np.array([p["psnr"] for p in points], np.float64)
  front = np.flatnonzero(pareto_front(t, s))
  if front.size == 0:
    raise ValueError("no point has a finite time and PSNR")
  best = front[np.argmax(s[front])]
  fastest = front[np.argmin(t[front])]
  near = front[s[front] >= s[best] - tolerance_db]
  balanced = near[np.argmin(t[near])]
  return {"fastest": points[fastest]["name"], "balanced": points[balanced]["name"],
          "best": points[best]["name"]}


def learned_beats_classic(points: Sequence[dict]) -> list[str]:
  """Learned front points faster than every classic point at least as accurate, and more
  accurate than every faster classic point (both vacuous when there is none).

  Args:
    points: dicts with ``name``, ``time``, ``psnr``, ``kind`` ("classic" | "learned").
  Returns:
    the names of such learned points on the Pareto front of ``points``.
  """
  t = np.array([p["time"] for p in points], np.float64)
  s = np.array([p["psnr"] for p in points], np.float64)
  front = pareto_front(t, s)
  classic = [i for i, p in enumerate(points) if p["kind"] == "classic"]
  out = []
  for i, p in enumerate(points):
    if p["kind"] != "learned" or not front[i]:
      continue
    if all(t[i] < t[j] for j in classic if s[j] >= s[i]) and all(
        s[i] > s[j] for j in classic if t[j] <= t[i]):
      out.append(p["name"])
  return out


def pareto_points(res: dict) -> list[dict]:
  """Every configuration as a point; ``default`` capture ones are the front's candidates."""
  return [{"name": r["name"], "label": r["label"], "time": r["time"], "psnr": r["psnr"][0],
           "kind": r["kind"], "capture": r["capture"], "knob": r["knob"]} for r in res["configs"]]

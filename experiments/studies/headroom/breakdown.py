"""Each frame's attributes (object size, depth, photons, motion), and scores broken down by them.

Attributes of an evaluated frame (the middle frame of its triplet), from the dataset file:

* ``size``: the true object pixels (depth > 0) as a share of the image;
* ``objects``: the scene's number of objects (the sequence's ``kinds`` or ``objects``
  attribute; NaN where it has neither);
* ``depth``: the mean true depth over the object pixels, metres;
* ``photons``: the sequence's photon budget (its ``photons`` attribute: signal photons per scan
  point per frame, before the detection ``efficiency``, also recorded);
* ``motion``: the dynamic object's speed, metres per frame: the mean of the two steps of its
  ``trajectory`` the triplet spans, ``|p_m - p_{m-1}|`` and ``|p_{m+1} - p_m|`` (one step at a
  sequence's end); NaN in a file that stores no trajectory.

The breakdown splits one set's frames into terciles of an attribute (:func:`tercile_edges`,
:func:`bins`) and summarises each method's scores in each bin with 95 % bootstrap intervals over
the sequences that have frames in it (:mod:`nlosjax.stats`).
"""

from __future__ import annotations

import json

import numpy as np

__all__ = ["ATTRIBUTES", "BREAKDOWN", "frame_attributes", "tercile_edges", "bins", "bin_summaries",
           "bin_differences"]

#: Every attribute recorded per frame (module docstring).
ATTRIBUTES = ("size", "objects", "depth", "photons", "efficiency", "motion")
#: The attributes the report breaks scores down by, with their headers.
BREAKDOWN = {"size": "object size (share of the image)", "depth": "object depth (m)",
             "photons": "photons (per scan point and frame)", "motion": "motion (m per frame)"}


def _object_count(attrs: dict) -> float:
  for key in ("kinds", "objects"):
    if key in attrs:
      return float(len(json.loads(attrs[key])))
  return float("nan")


def frame_attributes(path, split: str, sequence, frame, gt_depth) -> dict:
  """The attributes of each evaluated frame of ``split`` of the file at ``path``.

  Args:
    path: a dataset file (any of the layout's writers).
    split: the split the frames were read from.
    sequence: ``[N]`` index of each frame's sequence among the split's sorted names (as the
      loader numbers them).
    frame: ``[N]`` the frame's index in its sequence.
    gt_depth: ``[N, H, W]`` the frames' true depth (m, 0 at background).
  Returns:
    ``{name: [N] float64}`` for :data:`ATTRIBUTES`, plus ``"name": [N]`` the sequences' names.
  """
  from nlosjax.data.dataset import open_dataset
  sequence = np.asarray(sequence).reshape(-1)
  frame = np.asarray(frame).reshape(-1)
  gt_depth = np.asarray(gt_depth, np.float64)
  obj = gt_depth > 0
  n_obj = obj.sum(axis=(-2, -1))
  out = {"size": obj.mean(axis=(-2, -1)),
         "depth": np.where(n_obj > 0, np.where(obj, gt_depth, 0.0).sum(axis=(-2, -1)) / np.maximum(n_obj, 1),
                           np.nan)}
  with open_dataset(path) as ds:
    names = ds.names(split)
    seq_names = [names[int(s)] for s in sequence]
    attrs = {n: ds.sequence_attrs(n) for n in set(seq_names)}
    traj = {n: (ds.read(n, "trajectory") if ds.has(n, "trajectory") else None) for n in set(seq_names)}
  out["objects"] = np.asarray([_object_count(attrs[n]) for n in seq_names])
  out["photons"] = np.asarray([float(attrs[n]["photons"]) for n in seq_names])
  out["efficiency"] = np.asarray([float(attrs[n]["efficiency"]) for n in seq_names])
  motion = []
  for n, m in zip(seq_names, frame.tolist()):
    p = traj[n]
    if p is None:
      motion.append(np.nan)
      continue
    steps = [np.linalg.norm(p[b] - p[a]) for a, b in ((m - 1, m), (m, m + 1)) if 0 <= a and b < len(p)]
    motion.append(float(np.mean(steps)) if steps else np.nan)
  out["motion"] = np.asarray(motion)
  out = {k: np.asarray(out[k], np.float64) for k in ATTRIBUTES}
  out["name"] = seq_names
  return out


def tercile_edges(values) -> np.ndarray:
  """``[2]`` edges splitting the finite ``values`` into terciles (their 1/3 and 2/3 quantiles)."""
  v = np.asarray(values, np.float64)
  v = v[np.isfinite(v)]
  if v.size == 0:
    return np.full(2, np.nan)
  return np.quantile(v, [1 / 3, 2 / 3])


def bins(values, edges) -> np.ndarray:
  """``[N]`` int bin of each value: 0 up to ``edges[0]`` (inclusive), 1 up to ``edges[1]``
  (inclusive), then 2; -1 where the value (or an edge) is not finite."""
  v = np.asarray(values, np.float64)
  e = np.asarray(edges, np.float64)
  out = np.searchsorted(e, v, side="left")
  return np.where(np.isfinite(v) & np.all(np.isfinite(e)), out, -1).astype(np.int64)


def bin_summaries(scores: dict, sequence, which, n_bins: int = 3, **kwargs) -> list[dict | None]:
  """One ``metric -> summary`` (:func:`nlosjax.stats.summarize`) per bin; None for an empty bin.

  ``scores``: ``metric -> [N]`` per-frame scores; ``which``: ``[N]`` each frame's bin (-1: none).
  """
  from nlosjax.evaluation.scores import summarize_scores
  which = np.asarray(which)
  seq = np.asarray(sequence)
  out = []
  for b in range(n_bins):
    sel = which == b
    out.append(summarize_scores({k: np.asarray(v)[sel] for k, v in scores.items()}, seq[sel], **kwargs)
               if sel.any() else None)
  return out


def bin_differences(a: dict, b: dict, sequence, which, n_bins: int = 3, **kwargs) -> list[dict | None]:
  """Per bin, ``metric -> paired difference a - b`` on the bin's frames (None for an empty bin)."""
  from nlosjax.evaluation.scores import compare_scores
  which = np.asarray(which)
  seq = np.asarray(sequence)
  out = []
  for k in range(n_bins):
    sel = which == k
    out.append(compare_scores({m: np.asarray(v)[sel] for m, v in a.items()},
                              {m: np.asarray(v)[sel] for m, v in b.items()}, seq[sel], **kwargs)
               if sel.any() else None)
  return out

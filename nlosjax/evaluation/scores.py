"""Per-frame scores of a method, grouped by sequence, summarised with bootstrap intervals.

The metrics of every table (:data:`METRICS`): intensity ``psnr`` (dB) and
``ssim`` against the ground-truth intensity (data range 1), whole-image depth
``rmse`` and ``mad`` (metres, every pixel: kept for comparison with the
paper, but they reward outputting background), and the object-aware scores
of :func:`nlosjax.metrics.surface_scores`: ``rmse_object``, ``mad_object``
(depth error over the ground truth's surface pixels), ``recall``,
``precision`` and ``f1`` of "reconstructed as surface" (depth >=
:data:`nlosjax.metrics.SURFACE_MIN_DEPTH`, the same rule for every method).

Scores are arrays ``[N]`` (one per frame) or ``[K, N]`` (K training seeds of
a learned method); :func:`by_sequence` turns them into the ``[K, S, F]``
layout of :mod:`nlosjax.stats` using each frame's sequence index, so an
interval resamples sequences (and seeds), never single frames.
"""

from __future__ import annotations

import numpy as np

from nlosjax import metrics, stats

__all__ = ["METRICS", "HIGHER_IS_BETTER", "frame_scores", "by_sequence", "summarize_scores",
           "compare_scores"]

METRICS = ("psnr", "ssim", "rmse", "mad") + tuple(metrics.OBJECT_METRICS)
#: Whether a larger value of the metric is better.
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "rmse": False, "mad": False,
                    "rmse_object": False, "mad_object": False, "recall": True,
                    "precision": True, "f1": True}


def frame_scores(intensity, depth, gt_intensity, gt_depth) -> dict[str, np.ndarray]:
  """Every metric of :data:`METRICS` per frame.

  Args:
    intensity, gt_intensity: ``[N, H, W]`` in [0, 1].
    depth, gt_depth: ``[N, H, W]`` metres (0 = background in the ground truth).
  Returns:
    ``metric -> [N]`` float64 NumPy (NaN where a score is undefined, e.g.
    recall on a frame without an object).
  """
  out = {"psnr": metrics.psnr(intensity, gt_intensity),
         "ssim": metrics.ssim(intensity, gt_intensity),
         "rmse": metrics.rmse(depth, gt_depth),
         "mad": metrics.mad(depth, gt_depth),
         **metrics.surface_scores(depth, gt_depth)}
  return {k: np.asarray(out[k], np.float64) for k in METRICS}


def by_sequence(values, sequence) -> np.ndarray:
  """``[N]`` or ``[K, N]`` per-frame values -> ``[K, S, F]`` by sequence (NaN-padded).

  Args:
    values: per-frame values, frames in any order.
    sequence: ``[N]`` integer sequence index of each frame.
  Returns:
    ``[K, S, F]`` float64: S distinct sequences in ascending index order, F the
    most frames any sequence has; a shorter sequence is padded with NaN
    (which :mod:`nlosjax.stats` leaves out).
  """
  v = np.asarray(values, np.float64)
  v = v[None] if v.ndim == 1 else v
  seq = np.asarray(sequence).reshape(-1)
  if v.ndim != 2 or v.shape[1] != seq.size:
    raise ValueError(f"values {np.shape(values)} must be [N] or [K, N] with N = {seq.size} "
                     "(one sequence index per frame)")
  ids, inverse, counts = np.unique(seq, return_inverse=True, return_counts=True)
  out = np.full((v.shape[0], len(ids), int(counts.max())), np.nan)
  slot = np.zeros(len(ids), int)
  for n, s in enumerate(inverse):
    out[:, s, slot[s]] = v[:, n]
    slot[s] += 1
  return out


def summarize_scores(scores: dict, sequence, **kwargs) -> dict:
  """``metric -> summary`` (:func:`nlosjax.stats.summarize`) of a method's per-frame scores.

  Args:
    scores: ``metric -> [N]`` or ``[K, N]``.
    sequence: ``[N]`` sequence index of each frame.
    **kwargs: passed to :func:`nlosjax.stats.summarize` (``n_boot``, ``seed``).
  Returns:
    ``metric -> {"mean", "ci95": [lo, hi], "std", "n_sequences", "n_frames", "n_seeds"}``.
  """
  return {k: stats.summarize(by_sequence(v, sequence), **kwargs) for k, v in scores.items()}


def compare_scores(a: dict, b: dict, sequence, **kwargs) -> dict:
  """``metric -> paired difference a - b`` (:func:`nlosjax.stats.paired_difference`) on the same frames.

  ``a`` and ``b`` as in :func:`summarize_scores`; a method without seeds
  (``[N]``) is broadcast against the other's seeds. Only the metrics both hold.
  """
  return {k: stats.paired_difference(by_sequence(a[k], sequence), by_sequence(b[k], sequence),
                                     **kwargs)
          for k in a if k in b}

"""Per-frame scores of a method, grouped by sequence, summarised with bootstrap intervals.

The metrics of every table (:data:`TABLE_METRICS`). Per frame
(:data:`METRICS`): intensity ``psnr`` (dB) beside ``psnr_zero``, the all-zero
image's PSNR on the same frame (a floor: a dark background alone reaches it);
``psnr_balanced``, the PSNR with object and background pixels weighted equally, beside its
own all-zero floor ``psnr_balanced_zero`` (:func:`nlosjax.metrics.psnr_balanced`: a dark
image cannot score well on it); ``ssim`` against the ground-truth intensity (data range 1); ``intensity_mae_object``,
the intensity's mean absolute error over the true object pixels (an image dark on
the objects scores their mean intensity); whole-image depth
``rmse`` and ``mad`` (metres, every pixel: kept for comparison with the
paper, but they reward outputting background), and the object-aware scores
of :func:`nlosjax.metrics.surface_scores`: ``rmse_object``, ``mad_object``
(depth error over the ground truth's surface pixels), ``recall``,
``precision`` and ``f1`` of "reconstructed as surface" (depth >=
:data:`nlosjax.metrics.SURFACE_MIN_DEPTH`, the same rule for every method).

Per *pair* of consecutive evaluated frames of one test sequence, the
temporal-consistency scores (:data:`TEMPORAL_METRICS`, :func:`temporal_scores`):
``temporal_rmse`` (RMSE of the change of the intensity
between the two frames against the true change; lower is better),
``temporal_psnr`` (its PSNR form, peak 1 as for ``psnr``) and
``temporal_rmse_object`` (the same for depth, metres, over the pixels that
are true surface in both frames); :mod:`nlosjax.metrics`, "Temporal
consistency". A pair's score is stored at its later frame; a sequence's
first evaluated frame (no predecessor) holds NaN, which every summary
leaves out, so ``n_frames`` counts frame pairs. A pair is two frames of the
same sequence whose frame indices differ by 1 (the protocol scores the
consecutive middle frames of each sequence): never two sequences, and never
two seeds (each seed's images are scored on their own).

Scores are arrays ``[N]`` (one per frame) or ``[K, N]`` (K training seeds of
a learned method); :func:`by_sequence` turns them into the ``[K, S, F]``
layout of :mod:`nlosjax.stats` using each frame's sequence index, so an
interval resamples sequences (and seeds), never single frames or pairs.
"""

from __future__ import annotations

import numpy as np

from nlosjax import metrics, stats

__all__ = ["METRICS", "TEMPORAL_METRICS", "TABLE_METRICS", "HIGHER_IS_BETTER", "frame_scores",
           "consecutive_pairs", "temporal_scores", "by_sequence", "summarize_scores", "compare_scores"]

#: The metrics scored on each frame alone. ``psnr_zero`` is not a method's score but its test
#: frames': the all-zero image's PSNR, the floor beside each PSNR.
METRICS = ("psnr", "psnr_zero", "psnr_balanced", "psnr_balanced_zero", "ssim", "rmse", "mad",
           "intensity_mae_object") + tuple(metrics.OBJECT_METRICS)
#: The metrics scored on each pair of consecutive evaluated frames (stored at the later frame).
TEMPORAL_METRICS = tuple(metrics.TEMPORAL_METRICS)
#: Every metric of an evaluation's table.
TABLE_METRICS = METRICS + TEMPORAL_METRICS
#: Whether a larger value of the metric is better.
HIGHER_IS_BETTER = {"psnr": True, "psnr_zero": True, "psnr_balanced": True, "psnr_balanced_zero": True,
                    "intensity_mae_object": False, "ssim": True,
                    "rmse": False, "mad": False,
                    "rmse_object": False, "mad_object": False, "recall": True,
                    "precision": True, "f1": True, "temporal_rmse": False,
                    "temporal_psnr": True, "temporal_rmse_object": False}


def frame_scores(intensity, depth, gt_intensity, gt_depth, *, sequence=None,
                 frame=None) -> dict[str, np.ndarray]:
  """Every metric of :data:`METRICS` per frame; with ``sequence``, :data:`TEMPORAL_METRICS` too.

  Args:
    intensity, gt_intensity: ``[N, H, W]`` in [0, 1].
    depth, gt_depth: ``[N, H, W]`` metres (0 = background in the ground truth).
    sequence: optional ``[N]`` sequence index of each frame: adds the
      temporal scores (:func:`temporal_scores`).
    frame: optional ``[N]`` frame index of each frame within its sequence
      (:func:`consecutive_pairs`).
  Returns:
    ``metric -> [N]`` float64 NumPy (NaN where a score is undefined, e.g.
    recall on a frame without an object, a temporal score on a sequence's
    first evaluated frame).
  """
  out = {"psnr": metrics.psnr(intensity, gt_intensity),
         "psnr_zero": metrics.psnr_zero(gt_intensity),
         "psnr_balanced": metrics.psnr_balanced(intensity, gt_intensity, gt_depth),
         "psnr_balanced_zero": metrics.psnr_balanced_zero(gt_intensity, gt_depth),
         "intensity_mae_object": metrics.intensity_mae_object(intensity, gt_intensity, gt_depth),
         "ssim": metrics.ssim(intensity, gt_intensity),
         "rmse": metrics.rmse(depth, gt_depth),
         "mad": metrics.mad(depth, gt_depth),
         **metrics.surface_scores(depth, gt_depth)}
  out = {k: np.asarray(out[k], np.float64) for k in METRICS}
  if sequence is not None:
    out.update(temporal_scores(intensity, depth, gt_intensity, gt_depth, sequence, frame))
  return out


def consecutive_pairs(sequence, frame=None) -> tuple[np.ndarray, np.ndarray]:
  """Every pair of consecutive evaluated frames of one sequence: indices ``(previous, current)``.

  Args:
    sequence: ``[N]`` sequence index of each frame, frames in any order.
    frame: optional ``[N]`` integer frame index of each frame within its
      sequence; a pair is two frames of one sequence whose indices are ``f - 1``
      and ``f`` (a gap in the evaluated frames makes no pair). Without it the
      frames of each sequence are taken to be consecutive in the order they
      appear (the protocol's file order: sequence, then middle frame).
  Returns:
    ``(previous, current)``: ``[P]`` int arrays of positions in ``[N]``, one
    entry per pair, in the order of ``current``; never two sequences.
  Raises:
    ValueError: ``frame`` of another length than ``sequence``, or a frame that
      appears twice in one sequence.
  """
  seq = np.asarray(sequence).reshape(-1)
  if frame is None:
    seen: dict = {}
    index = []
    for s in seq.tolist():
      index.append(seen.get(s, 0))
      seen[s] = index[-1] + 1
  else:
    index = np.asarray(frame).reshape(-1).tolist()
    if len(index) != seq.size:
      raise ValueError(f"frame has {len(index)} entries but sequence has {seq.size}; one frame "
                       "index per frame")
  where: dict = {}
  for n, key in enumerate(zip(seq.tolist(), index)):
    if key in where:
      raise ValueError(f"frame {key[1]} of sequence {key[0]} appears twice (positions "
                       f"{where[key]} and {n})")
    where[key] = n
  pairs = [(where[(s, f - 1)], n) for n, (s, f) in enumerate(zip(seq.tolist(), index))
           if (s, f - 1) in where]
  prev = np.asarray([p for p, _ in pairs], np.int64)
  cur = np.asarray([c for _, c in pairs], np.int64)
  return prev, cur


def temporal_scores(intensity, depth, gt_intensity, gt_depth, sequence,
                    frame=None) -> dict[str, np.ndarray]:
  """Every metric of :data:`TEMPORAL_METRICS` per pair of consecutive frames, stored at the later one.

  For each pair ``(previous, current)`` of :func:`consecutive_pairs`:
  :func:`nlosjax.metrics.temporal_rmse`, :func:`~nlosjax.metrics.temporal_psnr`
  (data range 1) of the intensity and :func:`~nlosjax.metrics.temporal_rmse_object`
  of the depth, on the two-frame sequence ``[previous, current]``.

  Args:
    intensity, gt_intensity: ``[N, H, W]`` in [0, 1] (one method, one seed).
    depth, gt_depth: ``[N, H, W]`` metres (0 = background in the ground truth).
    sequence, frame: as :func:`consecutive_pairs`.
  Returns:
    ``metric -> [N]`` float64 NumPy: the pair's score at its current frame;
    NaN at a frame with no previous frame in its sequence, and where the
    score is undefined (no object pixel in both frames, for the depth).
  Raises:
    ValueError: arrays not ``[N, H, W]`` with one sequence index per frame, or
      as :func:`consecutive_pairs`.
  """
  seq = np.asarray(sequence).reshape(-1)
  arrays = [np.asarray(x) for x in (intensity, depth, gt_intensity, gt_depth)]
  if any(a.ndim != 3 or a.shape[0] != seq.size for a in arrays):
    raise ValueError(f"intensity, depth and the ground truth must be [N, H, W] with N = {seq.size} "
                     f"(one sequence index per frame), got {[a.shape for a in arrays]}")
  prev, cur = consecutive_pairs(seq, frame)
  out = {k: np.full(seq.size, np.nan) for k in TEMPORAL_METRICS}
  if prev.size == 0:
    return out
  inten, dep, gt_inten, gt_dep = (np.stack([a[prev], a[cur]], axis=1) for a in arrays)  # [P, 2, H, W]
  values = {"temporal_rmse": metrics.temporal_rmse(inten, gt_inten),
            "temporal_psnr": metrics.temporal_psnr(inten, gt_inten),
            "temporal_rmse_object": metrics.temporal_rmse_object(dep, gt_dep)}
  for k in TEMPORAL_METRICS:
    out[k][cur] = np.asarray(values[k], np.float64)[:, 0]
  return out


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

"""Accuracy against the ground truth: whole-frame scores as in Table 1 (:func:`scores`) and
the depth accuracy inside a depth range, gated against ungated (:func:`in_range_accuracy`).
"""

from __future__ import annotations

import numpy as np


def scores(intensity, depth, gt_i, gt_d) -> dict:
  """``metric -> [mean, std]`` over frames: ``psnr``, ``ssim``, ``rmse``, ``mad``."""
  from nlosjax.evaluation.scores import frame_scores
  per_frame = frame_scores(intensity, depth, gt_i, gt_d)
  return {k: [float(np.mean(per_frame[k])), float(np.std(per_frame[k]))]
          for k in ("psnr", "ssim", "rmse", "mad")}


def in_range_accuracy(gated: dict, ungated: dict, gt_d: np.ndarray, gated_setup, *,
                      near: float = 0.1) -> dict:
  """Depth accuracy inside a depth range, gated against ungated, on the same pixels.

  Args:
    gated, ungated: ``{"depth": [N, H, W]}`` metres, reconstructions with and
      without the depth range.
    gt_d: ``[N, H, W]`` true depth (0 = background).
    gated_setup: the Setup with the range (none: every foreground pixel).
    near: depths below this (metres) count as background (the networks'
      soft depth fades to 0 m rather than reaching it).
  Returns:
    ``pixels`` (true depth in the range, pooled over frames), ``rmse_gated``,
    ``rmse_ungated``, ``mad_gated``, ``mad_ungated`` (metres, against the
    truth over those pixels), ``missed_gated``, ``missed_ungated`` (the
    fraction of them reconstructed as background, depth below ``near``) and
    ``agreement`` (mean ``|gated - ungated|`` over them, metres); NaN when
    no pixel is in the range.
  """
  if gated_setup.depth_range is None:
    mask = gt_d > 0
  else:
    lo, hi = gated_setup.depth_range
    mask = (gt_d >= lo) & (gt_d <= hi) & (gt_d > 0)
  out = {"pixels": int(mask.sum())}
  nan = float("nan")
  for tag, r in (("gated", gated), ("ungated", ungated)):
    err = (np.asarray(r["depth"], np.float64) - gt_d)[mask]
    out[f"rmse_{tag}"] = float(np.sqrt(np.mean(err ** 2))) if err.size else nan
    out[f"mad_{tag}"] = float(np.mean(np.abs(err))) if err.size else nan
    out[f"missed_{tag}"] = float(np.mean(np.asarray(r["depth"])[mask] < near)) if err.size else nan
  diff = np.abs(np.asarray(gated["depth"], np.float64) - ungated["depth"])[mask]
  out["agreement"] = float(np.mean(diff)) if diff.size else nan
  return out

"""Gate a capture to the depths its hidden scene occupies, estimated from the capture itself.

Reconstruction cost follows ``setup.depth_range`` (time bins read, depth bins
computed), but a user must know the range. :func:`estimate_depth_range` finds
it from the data: a cheap coarse f-k migration (time bins summed in groups,
Setup spacing), its depth profile ``p(z) = max over scan points of
sqrt(volume)`` (f-k's volume is albedo squared), the depths where ``p`` reaches
``threshold`` of its peak, widened by ``margin`` metres on each side and
clipped to ``[0, max_depth]``. :func:`auto_depth_range` returns the gated
Setup; ``reconstruct(..., depth_range="auto")`` and the CLI's
``--depth-range auto`` use it.

The defaults (``threshold`` 0.3, ``margin`` 0.2 m) were chosen on the cpu
preset's validation split (40 frames, classic protocol input): the highest
threshold whose range still held >= 98.9 % of every frame's true surface
pixels (mean 99.95 %), 1.81 m wide on average of the 2.53 m window; 0.1
kept every pixel but spanned 2.50 m, 0.2 spanned 2.35 m.
``benchmarks/results/depth_range.md`` measures what the defaults save and keep
on the test split and the shipped scans. A scene with dim objects far behind
bright ones can lose them below ``threshold``: lower it, or widen the margin.

Imports run one way: this module uses :func:`nlosjax.physics.methods.fk.fk`
directly, and :mod:`nlosjax.physics.reconstruct` (the dispatch, for
``depth_range="auto"``) imports this module, never the reverse.
"""

from __future__ import annotations

import math

import numpy as np

from nlosjax.physics import _validate
from nlosjax.physics.methods.fk import fk
from nlosjax.physics.setup import Setup

DEFAULT_THRESHOLD = 0.3
DEFAULT_MARGIN = 0.2        # m
#: Coarse bins are at most this long (s), and at most this many fine bins.
COARSE_BIN_MAX = 1e-9
COARSE_FACTOR = 4


def estimate_depth_range(transient, setup: Setup, *, threshold: float = DEFAULT_THRESHOLD,
                         margin: float = DEFAULT_MARGIN, skip: float = 0.05
                         ) -> tuple[float, float]:
  """``(z_min, z_max)`` metres of a capture's hidden scene (see the module docstring).

  Args:
    transient: ``[..., T, H, W]`` counts (concrete, not traced: the range sets
      array shapes); leading axes (frames) are summed, so every frame shares it.
    setup: the capture; its own ``depth_range`` is ignored.
    threshold: fraction of the depth profile's peak that counts as scene, in (0, 1).
    margin: metres added on both sides, >= 0.
    skip: depths below this (m) are left out of the profile: the residue of
      the direct reflection off the wall (zeroed or gated in most captures).
  Returns:
    ``(z_min, z_max)`` with ``0 <= z_min < z_max <= setup.max_depth``.
  Raises:
    ValueError: traced input, bad options, or a capture with no photon.
  """
  if not _validate.is_concrete(transient):
    raise ValueError("estimate_depth_range needs concrete counts (it sets array shapes); call it"
                     " outside jit")
  if not 0 < threshold < 1:
    raise ValueError(f"threshold must be in (0, 1), got {threshold!r}")
  if not (math.isfinite(margin) and margin >= 0):
    raise ValueError(f"margin must be >= 0 metres, got {margin!r}")
  full = setup.ungated()
  full.check_transient(transient)
  _validate.check_counts(transient, "transient")
  x = np.asarray(transient, np.float32)
  x = x.reshape((-1,) + x.shape[-3:]).sum(0)                   # [T, H, W], frames summed
  if not x.any():
    raise ValueError("the capture holds no photon: no depth range to estimate")
  factor = max(1, min(COARSE_FACTOR, int(COARSE_BIN_MAX // full.bin_width)))
  bins = full.num_bins // factor
  if bins < 2:
    factor, bins = 1, full.num_bins
  coarse = x[:bins * factor].reshape(bins, factor, *x.shape[1:]).sum(1)
  coarse_setup = Setup(full.wall_size, full.grid, full.bin_width * factor, bins)
  vol = np.sqrt(np.maximum(np.asarray(fk(coarse, coarse_setup, variant="refined")), 0.0))
  profile = vol.max(axis=(1, 2))
  depths = np.arange(bins) * coarse_setup.depth_bin_length
  profile = np.where(depths >= skip, profile, 0.0)
  peak = float(profile.max())
  if peak <= 0:
    return (0.0, full.max_depth)
  inside = np.flatnonzero(profile >= threshold * peak)
  z_lo = depths[inside[0]] - margin
  z_hi = depths[inside[-1]] + coarse_setup.depth_bin_length + margin
  return (max(0.0, float(z_lo)), min(full.max_depth, float(z_hi)))


def auto_depth_range(transient, setup: Setup, **options) -> Setup:
  """``setup`` gated to :func:`estimate_depth_range` of ``transient`` (same options)."""
  return setup.ungated().with_depth_range(*estimate_depth_range(transient, setup, **options))

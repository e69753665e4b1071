"""Format ``"lct_mat"``: the O'Toole et al. 2018 confocal LCT scans.

The confocal scans published with O'Toole, Lindell and Wetzstein,
"Confocal non-line-of-sight imaging based on the light-cone transform",
Nature 555, 338-341 (2018), in its supplementary code (copies in the public
GitHub repository ``chenyuege/C-NLOS-imaging-based-on-LCT``, folder
``confocal_nlos_code/``). MATLAB v5 files with two variables:

* ``rect_data``: uint16 ``[W, H, T]`` photon counts, ``rect_data[x, y, t]``,
  already rectified so that bin 0 is when light reaches the wall; 4 ps bins
  (``T = 2048`` for the 64 x 64 scans).
* ``width``: HALF the side of the scanned square on the wall, metres; the
  scan points span ``[-width, width]`` along both axes.

nlosjax follows the public reconstruction code, whose
``permute(rect_data, [3 2 1])`` gives ``(t, y, x)``: ``rect_data[i, j, :]`` is
scan column ``i`` (x) and row ``j`` (y), and the transient is
``rect_data.transpose(2, 1, 0)``. (``shared/data/README.md`` calls the layout
``[y, x, t]``; read that way the exit sign's text runs down the side.)
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import scipy.io

from nlosjax.data.formats._common import _int_arg
from nlosjax.data.formats.registry import DAMAGED_INPUT, _container, _variables, register_format
from nlosjax.physics.setup import Setup

# ------------------------------------------------------------------ lct_mat

#: Native bin width of the O'Toole et al. 2018 SPAD histograms, seconds.
LCT_NATIVE_BIN_WIDTH = 4e-12
_LCT_ZERO_BINS = 600   # raw bins holding the direct reflection off the wall
_LCT_BIN_FACTOR = 4    # 4 ps -> 16 ps (the published K = 2 halvings)


def _read_lct_mat(path: Path, *, zero_bins=None, bin_factor=None, num_bins=None):
  """Read one O'Toole et al. 2018 ``rect_data``/``width`` MATLAB v5 scan.

  Preparation (``cnlos_reconstruction.m`` of the paper's supplementary code):
  zero raw bins ``[0, zero_bins)`` (default 600, the direct reflection off
  the wall); sum groups of ``bin_factor`` raw bins (default 4: 4 ps -> 16 ps),
  dropping a trailing partial group; keep the first ``num_bins`` binned bins
  (default: all of them, 512 for the published 2048-bin scans).

  The published code bins first and then zeros ``600 / 4 = 150`` binned bins;
  zeroing raw bins first is the same whenever ``bin_factor`` divides
  ``zero_bins``, and otherwise keeps the photons after ``zero_bins`` in the
  straddling group.

  Returns:
    ``(counts, setup)``: float64 ``[T, H, W]`` with ``counts[t, y, x]`` the sum
    of ``rect_data[y, x, t * bin_factor : (t + 1) * bin_factor]`` after
    zeroing, and ``Setup(wall_size=2 * width, grid=(H, W),
    bin_width=4 ps * bin_factor, num_bins=T)``.
  """
  zero_bins = _LCT_ZERO_BINS if zero_bins is None else _int_arg(path, "zero_bins", zero_bins, 0)
  bin_factor = _LCT_BIN_FACTOR if bin_factor is None else _int_arg(path, "bin_factor", bin_factor, 1)

  try:
    contents = scipy.io.loadmat(path, variable_names=("rect_data", "width"))
  except MemoryError:
    raise
  except Exception as exc:  # corrupt or truncated files raise many exception types
    hint = (" It is an HDF5 file (MATLAB v7.3?); 'lct_mat' reads MATLAB v5 only."
            if _container(path) == "hdf5" else "")
    raise ValueError(
        f"{path}: cannot be read as a MATLAB v5 file (corrupt, truncated or another"
        f" format): {type(exc).__name__}: {' '.join(str(exc).split())}.{hint} ({DAMAGED_INPUT})") from exc

  missing = [key for key in ("rect_data", "width") if key not in contents]
  if missing:
    try:
      found = sorted(name for name, _, _ in scipy.io.whosmat(path))
    except Exception:  # the listing is only a courtesy in the message
      found = "?"
    raise ValueError(
        f"{path}: missing variable(s) {missing} of format 'lct_mat'"
        f" (needs rect_data [H, W, T] and width); the file holds {found}")

  rect = contents["rect_data"]
  if not isinstance(rect, np.ndarray) or rect.dtype.kind not in "uif":
    raise ValueError(
        f"{path}: rect_data must be a real numeric array of photon counts, got"
        f" {type(rect).__name__} of dtype {getattr(rect, 'dtype', None)}")
  if rect.ndim != 3:
    raise ValueError(f"{path}: rect_data must be [H, W, T] (rank 3), got rank {rect.ndim} shape {rect.shape}")
  height, width_px, raw_bins = rect.shape
  if height < 2 or width_px < 2:
    raise ValueError(f"{path}: rect_data needs at least 2 x 2 scan points, got shape {rect.shape}")
  if rect.dtype.kind == "f" and not np.isfinite(rect).all():
    bad = int(np.size(rect) - np.count_nonzero(np.isfinite(rect)))
    raise ValueError(f"{path}: rect_data holds {bad} NaN or infinite value(s); photon counts must be finite")
  if rect.dtype.kind in "if" and (rect < 0).any():
    raise ValueError(
        f"{path}: rect_data holds {int(np.count_nonzero(rect < 0))} negative value(s)"
        f" (min {rect.min()}); photon counts must be >= 0")

  half = np.asarray(contents["width"])
  if half.dtype.kind not in "uif" or half.size != 1 or not math.isfinite(float(half.ravel()[0])) \
      or float(half.ravel()[0]) <= 0:
    raise ValueError(
        f"{path}: width must be one finite positive number (half the wall side, metres),"
        f" got {half!r}")
  half = float(half.ravel()[0])

  if zero_bins >= raw_bins:
    raise ValueError(f"{path}: zero_bins={zero_bins} would zero all {raw_bins} time bins")
  if bin_factor > raw_bins // 2:
    raise ValueError(f"{path}: bin_factor={bin_factor} leaves fewer than 2 of {raw_bins} bins")
  available = raw_bins // bin_factor
  num_bins = available if num_bins is None else _int_arg(path, "num_bins", num_bins, 2)
  if num_bins > available:
    raise ValueError(
        f"{path}: num_bins={num_bins} but {raw_bins} raw bins summed in groups of"
        f" {bin_factor} give only {available}")

  counts = rect[:, :, :num_bins * bin_factor].astype(np.float64)  # a copy
  counts[:, :, :zero_bins] = 0.0
  counts = counts.reshape(height, width_px, num_bins, bin_factor).sum(axis=3)
  # rect_data is [x, y, t]: the public code's permute(rect_data, [3 2 1]) gives (t, y, x).
  setup = Setup(wall_size=2.0 * half, grid=(width_px, height),
                bin_width=LCT_NATIVE_BIN_WIDTH * bin_factor, num_bins=num_bins)
  return counts.transpose(2, 1, 0), setup


def _accepts_lct(path: Path) -> bool:
  _, names = _variables(path)
  return "rect_data" in names or "width" in names


register_format(
    "lct_mat", _read_lct_mat, container="mat5", accepts=_accepts_lct,
    summary="MATLAB v5 .mat with rect_data [H, W, T] (4 ps bins) and width (half wall side, m),"
            " the O'Toole et al. 2018 confocal LCT scans")

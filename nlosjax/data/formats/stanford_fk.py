"""Format ``"stanford_fk"``: the Stanford f-k captures.

The captures of Lindell, Wetzstein and O'Toole, "Wave-based non-line-of-sight
imaging using fast f-k migration", SIGGRAPH 2019 (README of the public
``computational-imaging/nlos-fk``): ``meas_<exposure>.mat`` holds ``meas``
``[H, W, T]`` (512 x 512 x 2048; the interactive videos ``[F, H, W, T]``),
photon counts in 32 ps bins, MATLAB v7.3 (an HDF5 file: h5py sees the axes
reversed, which the reader undoes); ``tof.mat`` / ``tof_<res>.mat`` holds
``tofgrid`` ``[H, W]``, the time of flight in picoseconds from the hardware
to each scan point. The sensor is gated, so the raw histograms are not
aligned: nlos-fk's ``cnlos_reconstruction.m`` circularly shifts each one
left by ``floor(tofgrid / 32 ps)`` bins, then crops to 512 bins; the
scanned area is 2 m x 2 m. ``transient[t, i, j] = meas(i, j, t)`` (first
MATLAB index = row).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from nlosjax.data.formats._common import (
  _bin_time,
  _check_counts,
  _frame_selection,
  _make_setup,
  _MatFile,
  _positive_float,
  _time_plan,
)
from nlosjax.data.formats.registry import _existing_file, _variables, register_format

# ------------------------------------------------------------- stanford_fk

#: Native bin width of the Stanford f-k captures (Lindell et al. 2019), seconds.
FK_NATIVE_BIN_WIDTH = 32e-12
#: Raw bins kept after alignment by default (nlos-fk ``cnlos_reconstruction``'s ``crop``).
FK_CROP = 512
#: Side of the scanned square of the Stanford f-k captures, metres.
FK_WALL_SIZE = 2.0


def _tof_candidates(path: Path) -> list[Path]:
  """Sibling files that may hold the ``tofgrid`` of measurement file ``path``.

  ``meas_<suffix>.mat`` -> ``tof_<suffix>.mat`` then ``tof.mat`` in the same folder.
  """
  stem = path.stem
  out = []
  if stem.lower().startswith("meas"):
    out.append(path.with_name("tof" + stem[4:] + path.suffix))
  out.append(path.with_name("tof" + path.suffix))
  out.append(path.with_name("tof.mat"))
  seen, unique = set(), []
  for p in out:
    if p != path and p not in seen:
      seen.add(p)
      unique.append(p)
  return unique


def _read_tofgrid(meas_path: Path, source) -> tuple[np.ndarray, str]:
  """``(tofgrid [H, W] float64 ps, description)`` from a file path or an array."""
  if isinstance(source, (str, os.PathLike)):
    tof_path = _existing_file(source)
    with _MatFile(tof_path, ("tofgrid",)) as mf:
      if not mf.has("tofgrid"):
        raise ValueError(f"{tof_path}: no variable 'tofgrid' (the file holds {mf.names()}); it was"
                         f" given as the time-of-flight file of {meas_path}")
      grid = np.asarray(mf.get("tofgrid")[...], np.float64)
    where = str(tof_path)
  else:
    try:
      grid = np.asarray(source, np.float64)
    except (TypeError, ValueError):
      raise ValueError(f"{meas_path}: tofgrid must be a file path, an [H, W] array in picoseconds,"
                       f" False or None, got {type(source).__name__}") from None
    where = "the tofgrid argument"
  if grid.ndim != 2:
    raise ValueError(f"{meas_path}: tofgrid from {where} must be [H, W], got shape {grid.shape}")
  if not np.isfinite(grid).all():
    raise ValueError(f"{meas_path}: tofgrid from {where} holds NaN or infinite values")
  return grid, where


def _read_stanford_fk(path: Path, *, zero_bins=None, bin_factor=None, num_bins=None, frame=0,
                      tofgrid=None, wall_size=None):
  """Read a Stanford f-k capture (Lindell, Wetzstein, O'Toole, SIGGRAPH 2019).

  ``meas`` is ``[H, W, T]`` (or ``[F, H, W, T]`` for the interactive videos)
  photon counts in 32 ps bins, MATLAB v7.3 (HDF5) or v5; its time axis is not
  aligned: ``tofgrid`` ``[H, W]`` gives the time of flight (picoseconds) from
  the hardware to each scan point. Preparation (nlos-fk
  ``cnlos_reconstruction.m``): each histogram is circularly shifted left by
  ``floor(tofgrid / 32 ps)`` bins so that bin 0 is when light reaches the
  wall; then raw bins ``[0, zero_bins)`` are zeroed (default 0), groups of
  ``bin_factor`` bins summed (default 1) and the first ``num_bins`` kept
  (default ``512 // bin_factor``, the public ``crop = 512``).

  Orientation: ``transient[t, i, j] = meas(i, j, t)``: MATLAB's first index
  is the row (y), the second the column (x), as the nlos-fk demo's
  ``% y, x, t`` and its front view (rows top to bottom, columns left to
  right once its paired flips and reversed tick labels are undone).

  Args (beyond the shared ones):
    frame: frame(s) of a 4-D video ``meas``; a 3-D scan has frame 0 only.
    tofgrid: ``None`` finds it: a ``tofgrid`` variable in the file itself,
      else the sibling ``tof_<suffix>.mat`` of ``meas_<suffix>.mat``, else
      ``tof.mat``; a path names the file; an ``[H, W]`` array (picoseconds)
      gives it; ``False`` skips alignment (already aligned data).
    wall_size: side of the scanned square, metres (default 2, the published
      captures; the files do not record it).
  """
  wall = _positive_float(path, "wall_size", wall_size, FK_WALL_SIZE)
  with _MatFile(path, ("meas", "tofgrid")) as mf:
    if not mf.has("meas"):
      raise ValueError(f"{path}: missing variable 'meas' of format 'stanford_fk' (needs meas"
                       f" [H, W, T] and a tofgrid); the file holds {mf.names()}")
    meas = mf.get("meas")
    if meas.ndim not in (3, 4):
      raise ValueError(f"{path}: meas must be [H, W, T] or [F, H, W, T] (MATLAB order), got"
                       f" rank {meas.ndim} shape {meas.shape}")
    video = meas.ndim == 4
    height, width_px, raw_bins = meas.shape[-3:]
    if height < 2 or width_px < 2:
      raise ValueError(f"{path}: meas needs at least 2 x 2 scan points, got shape {meas.shape}")
    frames, single = _frame_selection(path, frame, meas.shape[0] if video else 1)

    shifts = None
    if tofgrid is None:
      if mf.has("tofgrid"):
        grid, where = np.asarray(mf.get("tofgrid")[...], np.float64), f"{path} (its own tofgrid)"
        if grid.ndim != 2 or not np.isfinite(grid).all():
          raise ValueError(f"{path}: its tofgrid must be a finite [H, W] array, got shape {grid.shape}")
      else:
        found = [p for p in _tof_candidates(path) if p.is_file()]
        if not found:
          raise ValueError(
              f"{path}: no time-of-flight calibration found: the file has no 'tofgrid' and none of"
              f" {[str(p) for p in _tof_candidates(path)]} exists; pass tofgrid=PATH (the capture's"
              " tof file), an [H, W] array in picoseconds, or tofgrid=False for aligned data")
        grid, where = _read_tofgrid(path, found[0])
    elif tofgrid is False:
      grid, where = None, None
    else:
      grid, where = _read_tofgrid(path, tofgrid)
    if grid is not None:
      if grid.shape != (height, width_px):
        raise ValueError(f"{path}: tofgrid from {where} is {grid.shape} but meas has"
                         f" {height} x {width_px} scan points")
      bin_ps = round(FK_NATIVE_BIN_WIDTH * 1e12, 9)
      shifts = np.floor(grid / bin_ps).astype(np.int64)

    zero_bins, bin_factor, num_bins = _time_plan(path, raw_bins, zero_bins, bin_factor, num_bins,
                                                 default_raw_keep=FK_CROP)
    keep = num_bins * bin_factor
    out = np.zeros((len(frames), num_bins, height, width_px), np.float32)
    rows_per_block = max(1, (1 << 24) // max(1, width_px * raw_bins))
    for fi, f in enumerate(frames):
      for r0 in range(0, height, rows_per_block):
        r1 = min(height, r0 + rows_per_block)
        block = meas[(f, slice(r0, r1)) if video else (slice(r0, r1),)]    # [h, W, T_raw]
        _check_counts(path, "meas", block)
        if shifts is not None:
          idx = (np.arange(keep)[None, None, :] + shifts[r0:r1, :, None]) % raw_bins
          block = np.take_along_axis(block, idx, axis=2)
        else:
          block = block[:, :, :keep]
        out[fi, :, r0:r1, :] = _bin_time(block, zero_bins, bin_factor, num_bins).transpose(2, 0, 1)
  setup = _make_setup(path, wall_size=wall, grid=(height, width_px),
                      bin_width=FK_NATIVE_BIN_WIDTH * bin_factor, num_bins=num_bins)
  return (out[0] if single else out), setup


def _accepts_fk(path: Path) -> bool:
  _, names = _variables(path)
  return "meas" in names


register_format(
    "stanford_fk", _read_stanford_fk, container=("hdf5", "mat5"), accepts=_accepts_fk,
    options=("frame", "tofgrid", "wall_size"),
    summary="MATLAB v7.3 (or v5) .mat with meas [H, W, T] or [F, H, W, T] (32 ps bins) and a"
            " tofgrid [H, W] in ps (in the file or a sibling tof*.mat), the Stanford f-k captures")

"""Reading helpers shared by the format readers of :mod:`nlosjax.data.formats`.

Argument checks (``_int_arg``, ``_positive_float``, ``_frame_selection``), a
MATLAB v5 / v7.3 file opened read-only with variables indexed in MATLAB axis
order (``_MatFile``, ``_MatVariable``), the photon-count check
(``_check_counts``), the time-axis preparation shared by every format
(``_time_plan``: validate and default ``zero_bins``, ``bin_factor``,
``num_bins``; ``_bin_time``: zero, then sum groups of bins) and
``_make_setup`` (a Setup whose errors name the file).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np
import scipy.io

from nlosjax.data.formats.registry import DAMAGED_INPUT, _container
from nlosjax.physics.setup import Setup

# -------------------------------------------------------------- arguments

def _open_hdf5(path: Path) -> h5py.File:
  """``path`` opened read-only as HDF5; a file HDF5 cannot open is one ValueError naming it."""
  try:
    return h5py.File(path, "r")
  except OSError as exc:
    raise ValueError(f"{path}: cannot be read as an HDF5 file (corrupt or truncated):"
                     f" {' '.join(str(exc).split())}; {DAMAGED_INPUT}") from None


def _int_arg(path: Path, name: str, value, minimum: int) -> int:
  if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
    raise ValueError(f"{path}: {name} must be an integer >= {minimum}, got {value!r}")
  return int(value)


# ------------------------------------------------- shared reading helpers

class _MatVariable:
  """A numeric variable of a MATLAB v5 or v7.3 file, indexed in MATLAB axis order.

  MATLAB stores arrays column-major; scipy returns them in MATLAB's axis
  order, h5py (v7.3) in the reverse order. ``var[i, j, ...]`` here always
  means MATLAB's ``var(i+1, j+1, ...)``, and an h5py-backed variable reads only
  the selected block from disk.
  """

  def __init__(self, path: Path, name: str, array=None, dataset=None):
    self.path, self.name = path, name
    self._array, self._dataset = array, dataset
    source = array if array is not None else dataset
    self.shape = tuple(source.shape) if array is not None else tuple(reversed(dataset.shape))
    self.dtype = source.dtype

  @property
  def ndim(self) -> int:
    return len(self.shape)

  def __getitem__(self, index) -> np.ndarray:
    index = index if isinstance(index, tuple) else (index,)
    index = index + (slice(None),) * (self.ndim - len(index))
    if self._array is not None:
      return np.asarray(self._array[index])
    try:
      block = self._dataset[tuple(reversed(index))]
    except (OSError, RuntimeError) as exc:
      raise ValueError(f"{self.path}: reading variable {self.name!r} failed (corrupt or"
                       f" truncated file?): {' '.join(str(exc).split())}; {DAMAGED_INPUT}") from None
    return np.asarray(block).T


class _MatFile:
  """Open a MATLAB v5 or v7.3 (HDF5) file read-only; ``get(name)`` -> :class:`_MatVariable`.

  A context manager; raises ValueError naming the file when it cannot be read.
  """

  def __init__(self, path: Path, names: Sequence[str]):
    self.path = path
    self.container = _container(path)
    self._h5 = None
    self._vars = {}
    if self.container == "mat5":
      try:
        self._vars = scipy.io.loadmat(path, variable_names=tuple(names))
      except MemoryError:
        raise
      except Exception as exc:
        raise ValueError(f"{path}: cannot be read as a MATLAB v5 file (corrupt, truncated or"
                         f" another format): {type(exc).__name__}: {exc}; {DAMAGED_INPUT}") from None
    elif self.container == "hdf5":
      try:
        self._h5 = h5py.File(path, "r")
      except OSError as exc:
        raise ValueError(f"{path}: cannot be read as an HDF5 / MATLAB v7.3 file (corrupt or"
                         f" truncated): {exc}; {DAMAGED_INPUT}") from None
    else:
      raise ValueError(f"{path}: neither a MATLAB v5 nor a MATLAB v7.3 / HDF5 file")

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  def close(self):
    if self._h5 is not None:
      self._h5.close()
      self._h5 = None

  def names(self) -> list[str]:
    if self._h5 is not None:
      return sorted(self._h5)
    return sorted(k for k in self._vars if not k.startswith("__"))

  def has(self, name: str) -> bool:
    if self._h5 is not None:
      return name in self._h5 and isinstance(self._h5[name], h5py.Dataset)
    return name in self._vars

  def get(self, name: str) -> _MatVariable:
    """The numeric variable ``name``; ValueError naming the file if absent or not numeric."""
    if not self.has(name):
      raise ValueError(f"{self.path}: no variable {name!r} (the file holds {self.names()})")
    if self._h5 is not None:
      var = _MatVariable(self.path, name, dataset=self._h5[name])
    else:
      var = _MatVariable(self.path, name, array=self._vars[name])
    if not isinstance(var.dtype, np.dtype) or var.dtype.kind not in "uif":
      raise ValueError(f"{self.path}: variable {name!r} must be a real numeric array, got dtype"
                       f" {var.dtype}")
    return var


def _check_counts(path: Path, name: str, counts: np.ndarray) -> None:
  """Raise ValueError naming the file unless ``counts`` are finite and >= 0."""
  if counts.dtype.kind == "f" and not np.isfinite(counts).all():
    bad = int(counts.size - np.count_nonzero(np.isfinite(counts)))
    raise ValueError(f"{path}: {name} holds {bad} NaN or infinite value(s); photon counts must be finite")
  if counts.dtype.kind in "if" and counts.size and counts.min() < 0:
    raise ValueError(f"{path}: {name} holds {int(np.count_nonzero(counts < 0))} negative value(s)"
                     f" (min {counts.min()}); photon counts must be >= 0")


def _time_plan(path: Path, raw_bins: int, zero_bins, bin_factor, num_bins, *,
               default_zero: int = 0, default_factor: int = 1,
               default_raw_keep: int | None = None) -> tuple[int, int, int]:
  """Validate ``(zero_bins, bin_factor, num_bins)`` against ``raw_bins``, filling defaults.

  ``default_raw_keep``: raw bins kept when ``num_bins`` is None (default: all).
  """
  zero_bins = default_zero if zero_bins is None else _int_arg(path, "zero_bins", zero_bins, 0)
  bin_factor = default_factor if bin_factor is None else _int_arg(path, "bin_factor", bin_factor, 1)
  if zero_bins >= raw_bins:
    raise ValueError(f"{path}: zero_bins={zero_bins} would zero all {raw_bins} time bins")
  if bin_factor > raw_bins // 2:
    raise ValueError(f"{path}: bin_factor={bin_factor} leaves fewer than 2 of {raw_bins} bins")
  available = raw_bins // bin_factor
  if num_bins is None:
    keep = raw_bins if default_raw_keep is None else min(default_raw_keep, raw_bins)
    num_bins = max(2, keep // bin_factor)
  else:
    num_bins = _int_arg(path, "num_bins", num_bins, 2)
  if num_bins > available:
    raise ValueError(
        f"{path}: num_bins={num_bins} but {raw_bins} raw bins summed in groups of"
        f" {bin_factor} give only {available}")
  return zero_bins, bin_factor, num_bins


def _bin_time(counts: np.ndarray, zero_bins: int, bin_factor: int, num_bins: int) -> np.ndarray:
  """``[..., T_raw]`` -> ``[..., num_bins]``: zero raw bins ``[0, zero_bins)``, sum groups of ``bin_factor``."""
  out = counts[..., :num_bins * bin_factor].astype(np.float64)
  out[..., :zero_bins] = 0.0
  return out.reshape(out.shape[:-1] + (num_bins, bin_factor)).sum(axis=-1)


def _frame_selection(path: Path, frame, num_frames: int):
  """``(indices, single)`` for a ``frame`` option over ``num_frames`` frames.

  ``frame``: an int (one frame; negative counts from the end), ``"all"``, or a
  sequence of ints. ``single`` is True for an int (the frame axis is dropped).
  """
  if isinstance(frame, str):
    if frame != "all":
      raise ValueError(f"{path}: frame must be an integer, a list of integers or 'all', got {frame!r}")
    return list(range(num_frames)), False
  if isinstance(frame, (int, np.integer)) and not isinstance(frame, bool):
    single, frames = True, [int(frame)]
  else:
    try:
      frames = [int(f) for f in frame]
    except (TypeError, ValueError):
      raise ValueError(f"{path}: frame must be an integer, a list of integers or 'all',"
                       f" got {frame!r}") from None
    if not frames or any(isinstance(f, bool) for f in frame):
      raise ValueError(f"{path}: frame must be a non-empty list of integers, got {frame!r}")
    single = False
  out = []
  for f in frames:
    g = f + num_frames if f < 0 else f
    if not 0 <= g < num_frames:
      raise ValueError(f"{path}: frame {f} out of range: the file holds {num_frames} frame(s)")
    out.append(g)
  return out, single


def _make_setup(path: Path, **fields) -> Setup:
  try:
    return Setup(**fields)
  except ValueError as exc:
    raise ValueError(f"{path}: {exc}") from None


def _positive_float(path: Path, name: str, value, default: float) -> float:
  if value is None:
    return default
  if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) \
      or not math.isfinite(float(value)) or float(value) <= 0:
    raise ValueError(f"{path}: {name} must be a finite positive number, got {value!r}")
  return float(value)

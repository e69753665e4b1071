"""Format ``"nlosjax_capture"``: nlosjax's single-capture HDF5 layout.

Written by :func:`save_capture` (and by ``python -m experiments.reconstruct``):
dataset ``transient`` ``[T, H, W]`` or ``[F, T, H, W]`` plus the Setup as root
attributes (``format = "nlosjax-capture"``, ``format_version``); read back by
:func:`~nlosjax.data.io.load_measurement`.
"""

from __future__ import annotations

import dataclasses
import errno
import io
import json
import os
from collections.abc import Mapping
from pathlib import Path

import h5py
import numpy as np

from nlosjax import files
from nlosjax.data.formats._common import _bin_time, _check_counts, _frame_selection, _make_setup, _open_hdf5, _time_plan
from nlosjax.data.formats.registry import DAMAGED_INPUT, _attr_value, _root_format, register_format
from nlosjax.physics.setup import Setup

# ---------------------------------------------------------- nlosjax formats

#: ``format`` attribute of a single-capture HDF5 file (:func:`save_capture`).
CAPTURE_FORMAT = "nlosjax-capture"
CAPTURE_FORMAT_VERSION = 1


def save_capture(path, transient, setup: Setup, *, overwrite: bool = False,
                 attrs: Mapping | None = None, **datasets) -> Path:
  """Write a capture in nlosjax's single-capture HDF5 layout (format ``"nlosjax_capture"``).

  Layout: root attributes ``format = "nlosjax-capture"``, ``format_version =
  1``, ``wall_size`` (m), ``grid`` ``[H, W]``, ``bin_width`` (s),
  ``num_bins``, ``depth_range`` ``[z_min, z_max]`` (m, only when set), plus
  ``attrs`` (strings, numbers or JSON-able values, stored as JSON strings
  when not scalar); dataset ``transient`` ``[T, H, W]`` or ``[F, T, H, W]``
  float32 (gzip); any ``datasets`` given (e.g. ``volume [Z, H, W]``,
  ``intensity [H, W]``, ``depth [H, W]``) stored as float32 arrays.
  ``transient=None`` writes no transient (e.g. reconstructions only; such a
  file is not readable by :func:`load_measurement`).

  The file is written to ``PATH.partial`` and renamed when complete, so a
  crash never leaves a half-written ``path`` or damages an existing one.

  Everything is checked before the file is opened, so a refused call leaves
  any existing ``path`` as it was.

  Raises:
    FileExistsError: ``path`` exists and ``overwrite`` is False.
    ValueError: a transient that does not match ``setup``, has no frame,
      or holds NaN, infinite or negative counts; a dataset that is empty or
      holds NaN or infinite values.
  """
  path = Path(path)
  if path.exists() and not overwrite:
    raise FileExistsError(errno.EEXIST, f"{path} exists (pass overwrite=True to replace it)", str(path))
  if transient is not None:
    transient = np.asarray(transient, np.float32)
    setup.check_transient(transient)
    if transient.ndim not in (3, 4):
      raise ValueError(f"transient must be [T, H, W] or [F, T, H, W], got shape {transient.shape}")
    if transient.size == 0:
      raise ValueError(f"{path}: the transient has no frame (shape {transient.shape}); nothing to save")
    if not np.all(np.isfinite(transient)):
      raise ValueError(f"{path}: the transient holds {int(np.sum(~np.isfinite(transient)))} NaN or"
                       " infinite values; counts must be finite")
    if np.any(transient < 0):
      raise ValueError(f"{path}: the transient holds {int(np.sum(transient < 0))} negative values;"
                       " photon counts must be >= 0")
  arrays = {}
  for key, value in datasets.items():
    arr = np.asarray(value, np.float32)
    if arr.size == 0:
      raise ValueError(f"{path}: dataset {key!r} is empty (shape {arr.shape})")
    if not np.all(np.isfinite(arr)):
      raise ValueError(f"{path}: dataset {key!r} holds NaN or infinite values")
    arrays[key] = arr
  # Built in memory, then written with Python: HDF5 (2.0) crashes the process when one of its own
  # writes fails, so it never writes to the disk here, and a full disk is a clean OSError.
  buf = io.BytesIO()
  with h5py.File(buf, "w", libver=("v110", "v110")) as f:
    # HDF5 1.10's format: its object headers and chunk indexes carry checksums; fletcher32: so does
    # every chunk. A flipped bit in a capture fails its read instead of changing a count.
    a = f.attrs
    a["format"] = CAPTURE_FORMAT
    a["format_version"] = CAPTURE_FORMAT_VERSION
    a["wall_size"] = setup.wall_size
    a["grid"] = np.asarray(setup.grid, np.int64)
    a["bin_width"] = setup.bin_width
    a["num_bins"] = setup.num_bins
    if setup.depth_range is not None:
      a["depth_range"] = np.asarray(setup.depth_range, np.float64)
    for key, value in (attrs or {}).items():
      if isinstance(value, (str, int, float, bool, np.number)):
        a[key] = value
      else:
        a[key] = json.dumps(value, default=str)
    if transient is not None:
      chunks = (1,) * (transient.ndim - 2) + transient.shape[-2:]
      f.create_dataset("transient", data=transient, chunks=chunks, compression="gzip",
                       compression_opts=4, shuffle=True, fletcher32=True)
    for key, arr in arrays.items():
      f.create_dataset(key, data=arr, compression="gzip" if arr.size > 4096 else None, fletcher32=True)
    files.seal_attrs(f)                # string attributes carry no HDF5 checksum: a digest of them all
  tmp = path.with_name(path.name + ".partial")
  try:
    tmp.write_bytes(buf.getbuffer())
    os.replace(tmp, path)
  except BaseException as e:
    tmp.unlink(missing_ok=True)
    if isinstance(e, OSError):         # a full disk, a read-only folder
      raise files.FileFault(path, files.describe(e, path), files.fault_errno(e)) from e
    raise
  return path


def _read_capture(path: Path, *, zero_bins=None, bin_factor=None, num_bins=None, frame=0):
  """Read nlosjax's single-capture layout (:func:`save_capture`)."""
  f = _open_hdf5(path)
  try:
    with f:
      list(f)                          # HDF5 checks its checksums here: a damaged file raises
      if files.attrs_intact(f) is False:
        raise ValueError(f"{path}: its attributes do not match the digest written with them (the file"
                         f" is damaged); {DAMAGED_INPUT}")
      a = f.attrs
      version = int(_attr_value(a.get("format_version", -1)))
      if version > CAPTURE_FORMAT_VERSION or version < 1:
        raise ValueError(f"{path}: format_version {version} of {CAPTURE_FORMAT!r} is not supported"
                         f" (this nlosjax reads 1..{CAPTURE_FORMAT_VERSION}); update nlosjax")
      missing = [k for k in ("wall_size", "bin_width") if k not in a]
      if missing:
        raise ValueError(f"{path}: missing Setup attribute(s) {missing} of format 'nlosjax_capture'")
      if "transient" not in f or not isinstance(f["transient"], h5py.Dataset):
        raise ValueError(f"{path}: no dataset 'transient' (the file holds {sorted(f)}); files holding"
                         " only reconstructions cannot be loaded as measurements")
      ds = f["transient"]
      if ds.ndim not in (3, 4) or ds.dtype.kind not in "uif":
        raise ValueError(f"{path}: transient must be a real [T, H, W] or [F, T, H, W] array, got"
                         f" shape {ds.shape} dtype {ds.dtype}")
      raw_bins, height, width_px = ds.shape[-3:]
      if "grid" in a and tuple(int(v) for v in np.ravel(a["grid"])) != (height, width_px):
        raise ValueError(f"{path}: attribute grid {tuple(np.ravel(a['grid']))} does not match the"
                         f" transient's scan grid {(height, width_px)}")
      if "num_bins" in a and int(_attr_value(a["num_bins"])) != raw_bins:
        raise ValueError(f"{path}: attribute num_bins {a['num_bins']} does not match the"
                         f" transient's {raw_bins} time bins")
      frames, single = _frame_selection(path, frame, ds.shape[0] if ds.ndim == 4 else 1)
      try:
        raw = ds[frames] if ds.ndim == 4 else ds[...][None]
      except (OSError, RuntimeError) as exc:
        raise ValueError(f"{path}: reading 'transient' failed (the file is damaged: "
                         f"{' '.join(str(exc).split())}); {DAMAGED_INPUT}") from None
      depth_range = tuple(float(v) for v in np.ravel(a["depth_range"])) if "depth_range" in a else None
      wall, native = float(_attr_value(a["wall_size"])), float(_attr_value(a["bin_width"]))
  except (OSError, KeyError, RuntimeError) as exc:     # a failed checksum, an object that does not open
    raise ValueError(f"{path}: reading it failed (the file is damaged: {' '.join(str(exc).split())});"
                     f" {DAMAGED_INPUT}") from None
  _check_counts(path, "transient", raw)
  zero_bins, bin_factor, num_bins = _time_plan(path, raw_bins, zero_bins, bin_factor, num_bins)
  counts = _bin_time(np.moveaxis(raw, 1, -1), zero_bins, bin_factor, num_bins)
  counts = np.moveaxis(counts, -1, 1)
  setup = _make_setup(path, wall_size=wall, grid=(height, width_px), bin_width=native * bin_factor,
                      num_bins=num_bins)
  if depth_range is not None:
    try:
      setup = dataclasses.replace(setup, depth_range=depth_range)
    except ValueError as exc:
      raise ValueError(f"{path}: attribute depth_range: {exc}") from None
  return (counts[0] if single else counts), setup


register_format(
    "nlosjax_capture", _read_capture, container="hdf5",
    accepts=lambda p: _root_format(p) == CAPTURE_FORMAT, options=("frame",),
    summary="HDF5 written by nlosjax.data.io.save_capture: transient [T, H, W] or [F, T, H, W]"
            " with Setup attributes (format 'nlosjax-capture')")

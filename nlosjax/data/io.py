"""Read measured confocal NLOS scans into ``(transient [T, H, W], Setup)``.

:func:`load_measurement` is the one entry point. It detects the file format
from the file's first bytes (or takes ``format=``), hands the file to that
format's reader, then optionally downsamples the scan grid and applies
``Setup`` overrides. Every reader returns photon counts in nlosjax's
conventions (see :mod:`nlosjax.physics.setup`): a transient ``[T, H, W]``
with ``t = 0`` when light reaches the wall, rows along y, columns along x, and
a :class:`~nlosjax.physics.setup.Setup` whose scan grid spans
``[-wall_size/2, wall_size/2]`` as ``numpy.linspace`` does.

Formats (the registry :data:`FORMATS`, name -> reader):

``"lct_mat"``
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

``"stanford_fk"``
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

``"nlost_mat"``
  The captures of Li et al., "NLOST: non-line-of-sight imaging with
  transformer", CVPR 2023 (public ``Depth2World/NLOST``): ``data`` ``[W, H, T]``,
  read by their code with ``scipy.io.loadmat`` and ``transpose([1, 0, 2])``,
  already aligned, 32 ps bins, 512 bins, 2 m x 2 m wall. Also the aligned f-k
  captures that USM/NLOST distribute (``final_meas`` ``[H, W, T]``, no
  transpose).

``"nlosjax_capture"``
  nlosjax's single-capture HDF5 layout, written by :func:`save_capture`
  (and by ``python -m experiments.reconstruct``): dataset ``transient``
  ``[T, H, W]`` or ``[F, T, H, W]`` plus the Setup as root attributes.

``"nlosjax_dataset"``
  One sequence of an nlosjax dynamic dataset (``nlosjax.data.dataset``; README,
  "Dynamic NLOS dataset").

Detection: the container (MATLAB v5 or HDF5, which includes MATLAB v7.3)
from the first bytes, then the first format whose ``accepts`` check passes
on the file's variables: ``rect_data`` or ``width`` -> ``lct_mat``, ``meas`` ->
``stanford_fk``, ``data`` or ``final_meas`` -> ``nlost_mat``, the root
attribute ``format`` -> the nlosjax layouts. A corrupt or unrecognised file
raises ``ValueError`` naming the file, the variables found and the
supported formats.

Adding a format: write ``reader(path, *, zero_bins, bin_factor, num_bins,
**options)`` returning ``(counts [T, H, W] or [F, T, H, W], Setup)``
(``None`` meaning the format's own default for each preparation step) and
:func:`register_format` it with the container(s) it lives in (``"mat5"``,
``"hdf5"`` or both), an ``accepts`` check when the container is shared, and
the names of its extra options.

Nothing here ever writes to the input file: readers open it read-only.
"""

from __future__ import annotations

import dataclasses
import errno
import functools
import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import h5py
import numpy as np
import scipy.io

from nlosjax.physics.setup import Setup

__all__ = [
    "CAPTURE_FORMAT",
    "FK_NATIVE_BIN_WIDTH",
    "FORMATS",
    "LCT_NATIVE_BIN_WIDTH",
    "NLOST_BIN_WIDTH",
    "SHIPPED_SCAN_NAME",
    "detect_format",
    "load_measurement",
    "register_format",
    "save_capture",
    "shipped_scan_path",
]

# ----------------------------------------------------------------- registry

Reader = Callable[..., tuple[np.ndarray, Setup]]


@dataclasses.dataclass(frozen=True)
class FormatSpec:
  """One registered measurement format.

  Attributes:
    reader: ``reader(path, *, zero_bins, bin_factor, num_bins, **options)`` ->
      ``(counts [T, H, W] or [F, T, H, W], Setup)``; ``None`` arguments take
      the format's defaults; ``options`` are the names in :attr:`options`.
    container: file container(s) the format lives in, as :func:`detect_format`
      recognises them: ``"mat5"`` (MATLAB v5/v6/v7) or ``"hdf5"`` (HDF5, which
      includes MATLAB v7.3), or a tuple of both.
    summary: one line for error messages and docs.
    accepts: optional ``accepts(path) -> bool`` content check, used only to
      choose between several formats sharing one container.
    options: extra keyword options the reader takes (passed through from
      :func:`load_measurement`). A reader without ``"frame"`` returns a single
      capture ``[T, H, W]`` and :func:`load_measurement` handles ``frame``.
  """

  reader: Reader
  container: str | tuple[str, ...]
  summary: str
  accepts: Callable[[Path], bool] | None = None
  options: tuple[str, ...] = ()

  @property
  def containers(self) -> tuple[str, ...]:
    return (self.container,) if isinstance(self.container, str) else tuple(self.container)


#: format name -> :class:`FormatSpec`; filled by :func:`register_format`.
FORMATS: dict[str, FormatSpec] = {}

_CONTAINERS = ("mat5", "hdf5")


def register_format(name: str, reader: Reader, *, container: str | tuple[str, ...], summary: str,
                    accepts: Callable[[Path], bool] | None = None,
                    options: tuple[str, ...] = ()) -> None:
  """Add (or replace) the format ``name`` in :data:`FORMATS`.

  ``container`` is ``"mat5"``, ``"hdf5"`` or a tuple of them; ``options``
  names the reader's extra keyword options (see :class:`FormatSpec`).
  """
  containers = (container,) if isinstance(container, str) else tuple(container)
  if not containers or any(c not in _CONTAINERS for c in containers):
    raise ValueError(f"container must be one of {_CONTAINERS} (or a tuple of them), got {container!r}")
  FORMATS[name] = FormatSpec(reader=reader, container=container, summary=summary, accepts=accepts,
                             options=tuple(options))


def _supported() -> str:
  return "; ".join(f"{name!r}: {spec.summary}" for name, spec in FORMATS.items())


# ---------------------------------------------------------------- detection

_MAT5_MAGIC = b"MATLAB 5.0 MAT-file"   # text header of MATLAB v5, v6 and v7 files
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"     # HDF5 superblock signature
_HDF5_OFFSETS = (0, 512, 1024, 2048)   # where a superblock may sit (v7.3: 512)


def _container(path: Path) -> str | None:
  """``"mat5"``, ``"hdf5"`` or ``None`` from the file's first bytes."""
  with open(path, "rb") as f:
    head = f.read(_HDF5_OFFSETS[-1] + len(_HDF5_MAGIC))
  if head.startswith(_MAT5_MAGIC):
    return "mat5"
  if any(head[o:o + len(_HDF5_MAGIC)] == _HDF5_MAGIC for o in _HDF5_OFFSETS):
    return "hdf5"
  return None


def detect_format(path) -> str:
  """Name of the registered format that reads ``path``, from its content.

  The container comes from the first bytes: the MATLAB v5 text header
  ``'MATLAB 5.0 MAT-file'`` or the HDF5 signature ``'\\x89HDF\\r\\n\\x1a\\n'``
  (at byte 0, or 512 for MATLAB v7.3). Among the formats living in that
  container, the first (in registration order) whose ``accepts`` check passes
  on the variables or attributes in the file wins (a lone candidate needs no
  check). The file name is never consulted.

  Raises:
    FileNotFoundError: if ``path`` does not exist.
    ValueError: naming the file and the supported formats, when no registered
      format lives in the file's container, the container cannot be read
      (corrupt or truncated), or no format recognises the content.
  """
  path = _existing_file(path)
  container = _container(path)
  if container is None:
    raise ValueError(
        f"{path}: unrecognised file content (neither a MATLAB v5 .mat nor an HDF5 file)."
        f" Supported formats: {_supported()}")
  candidates = [name for name, spec in FORMATS.items() if container in spec.containers]
  if len(candidates) == 1:
    return candidates[0]
  kind = "an HDF5 file (MATLAB v7.3 or HDF5)" if container == "hdf5" else "a MATLAB v5 file"
  if candidates:
    _listing(path, container)    # a corrupt container raises here, naming the problem
  for name in candidates:
    accepts = FORMATS[name].accepts
    if accepts is None or accepts(path):
      return name
  held = ""
  if candidates:
    names = sorted(_variables(path)[1])
    held = f" holding {names}" if names else " holding no variable"
  raise ValueError(
      f"{path}: {kind}{held}, but no registered format reads it"
      f"{'' if candidates else ' (no reader for this container yet)'}."
      f" Supported formats: {_supported()}")


def _stat_key(path: Path) -> tuple:
  st = path.stat()
  return (str(path.resolve()), st.st_mtime_ns, st.st_size)


class _Unreadable(Exception):
  """A container that cannot be listed; the message completes ``"{path}: "``."""


@functools.lru_cache(maxsize=32)
def _listing_cached(key: tuple, container: str) -> dict:
  path = key[0]
  if container == "mat5":
    try:
      return {name: tuple(shape) for name, shape, _ in scipy.io.whosmat(path)}
    except MemoryError:
      raise
    except Exception as exc:
      raise _Unreadable(f"cannot be read as a MATLAB v5 file (corrupt, truncated or another"
                        f" format): {type(exc).__name__}: {exc}") from None
  try:
    with h5py.File(path, "r") as f:
      out = {name: (tuple(reversed(obj.shape)) if isinstance(obj, h5py.Dataset) else None)
             for name, obj in f.items()}
      out["#attrs"] = {k: _attr_value(v) for k, v in f.attrs.items()
                       if k in ("format", "format_version", "MATLAB_class")}
      return out
  except MemoryError:
    raise
  except Exception as exc:
    raise _Unreadable(f"cannot be read as an HDF5 file (corrupt or truncated):"
                      f" {type(exc).__name__}: {exc}") from None


def _listing(path: Path, container: str) -> dict:
  """``variable name -> shape`` (MATLAB axis order) of a ``.mat``/HDF5 file's top level.

  HDF5 groups map to ``None``; the key ``"#attrs"`` of an HDF5 listing holds
  the root attributes ``format`` and ``format_version`` when present.
  Cached per (file, modification time, size).

  Raises:
    ValueError: naming the file when the container cannot be read.
  """
  try:
    out = dict(_listing_cached(_stat_key(path), container))
  except _Unreadable as exc:
    raise ValueError(f"{path}: {exc}") from None
  if container == "mat5":
    out.pop("#attrs", None)
  return out


def _variables(path: Path) -> tuple[str, dict]:
  """``(container, listing)`` of ``path``, without the attributes entry."""
  container = _container(path)
  if container is None:
    return None, {}
  listing = _listing(path, container)
  listing.pop("#attrs", None)
  return container, listing


def _root_format(path: Path) -> str | None:
  """The root ``format`` attribute of an HDF5 file (None if absent or not HDF5)."""
  if _container(path) != "hdf5":
    return None
  return _listing(path, "hdf5").get("#attrs", {}).get("format")


def _attr_value(value):
  if isinstance(value, bytes):
    return value.decode(errors="replace")
  if isinstance(value, np.ndarray) and value.dtype.kind in "SO" and value.size == 1:
    return _attr_value(value.ravel()[0])
  if isinstance(value, np.generic):
    return value.item()
  return value


def _existing_file(path) -> Path:
  path = Path(path)
  if not path.exists():
    raise FileNotFoundError(errno.ENOENT, f"measurement file not found: {path}", str(path))
  if not path.is_file():
    raise ValueError(f"{path}: not a regular file")
  return path


# -------------------------------------------------------------- arguments

def _int_arg(path: Path, name: str, value, minimum: int) -> int:
  if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
    raise ValueError(f"{path}: {name} must be an integer >= {minimum}, got {value!r}")
  return int(value)


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
        f" format): {type(exc).__name__}: {exc}.{hint}") from exc

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
    except OSError as exc:
      raise ValueError(f"{self.path}: reading variable {self.name!r} failed (corrupt or"
                       f" truncated file?): {exc}") from None
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
                         f" another format): {type(exc).__name__}: {exc}") from None
    elif self.container == "hdf5":
      try:
        self._h5 = h5py.File(path, "r")
      except OSError as exc:
        raise ValueError(f"{path}: cannot be read as an HDF5 / MATLAB v7.3 file (corrupt or"
                         f" truncated): {exc}") from None
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


# ---------------------------------------------------------------- nlost_mat

#: Bin width of the NLOST captures (Li et al., CVPR 2023), seconds.
NLOST_BIN_WIDTH = 32e-12
#: Side of the scanned square of the NLOST captures, metres.
NLOST_WALL_SIZE = 2.0


def _read_nlost(path: Path, *, zero_bins=None, bin_factor=None, num_bins=None, wall_size=None,
                bin_width=None):
  """Read an NLOST capture (Li et al., "NLOST", CVPR 2023) or an aligned f-k ``final_meas``.

  ``data`` is ``[W, H, T]`` in MATLAB order: the NLOST evaluation code reads it
  with ``scipy.io.loadmat`` and applies ``transpose([1, 0, 2])`` before using
  it as ``[H, W, T]``; so ``transient[t, y, x] = data(x, y, t)``. The
  aligned Stanford f-k captures distributed with USM/NLOST hold
  ``final_meas`` ``[H, W, T]`` used without a transpose:
  ``transient[t, y, x] = final_meas(y, x, t)``. Both are already aligned
  (bin 0 at the wall), 32 ps bins on a 2 m x 2 m wall, usually 512 bins.
  Preparation: zero ``[0, zero_bins)`` (default 0), sum ``bin_factor`` (1),
  keep ``num_bins`` (all).

  Args (beyond the shared ones):
    wall_size: side of the scanned square, metres (default 2; not in the file).
    bin_width: native bin width, seconds (default 32 ps; not in the file).
  """
  wall = _positive_float(path, "wall_size", wall_size, NLOST_WALL_SIZE)
  native = _positive_float(path, "bin_width", bin_width, NLOST_BIN_WIDTH)
  with _MatFile(path, ("data", "final_meas")) as mf:
    name = "data" if mf.has("data") else "final_meas" if mf.has("final_meas") else None
    if name is None:
      raise ValueError(f"{path}: missing variable 'data' (or 'final_meas') of format 'nlost_mat';"
                       f" the file holds {mf.names()}")
    var = mf.get(name)
    if var.ndim != 3:
      raise ValueError(f"{path}: {name} must be rank 3 ([W, H, T] for data, [H, W, T] for"
                       f" final_meas), got rank {var.ndim} shape {var.shape}")
    raw = var[...]
  _check_counts(path, name, raw)
  if name == "data":
    raw = raw.transpose(1, 0, 2)                                 # [H, W, T]
  height, width_px, raw_bins = raw.shape
  if height < 2 or width_px < 2:
    raise ValueError(f"{path}: {name} needs at least 2 x 2 scan points, got shape {var.shape}")
  zero_bins, bin_factor, num_bins = _time_plan(path, raw_bins, zero_bins, bin_factor, num_bins)
  counts = _bin_time(raw, zero_bins, bin_factor, num_bins).transpose(2, 0, 1)
  return counts, _make_setup(path, wall_size=wall, grid=(height, width_px),
                             bin_width=native * bin_factor, num_bins=num_bins)


def _accepts_nlost(path: Path) -> bool:
  if _root_format(path) is not None:
    return False
  _, names = _variables(path)
  return "data" in names or "final_meas" in names


register_format(
    "nlost_mat", _read_nlost, container=("mat5", "hdf5"), accepts=_accepts_nlost,
    options=("wall_size", "bin_width"),
    summary="MATLAB .mat with data [W, H, T] (transposed; NLOST captures, 32 ps, 2 m wall) or"
            " final_meas [H, W, T] (aligned f-k captures)")


# ---------------------------------------------------------- nlosjax formats

#: ``format`` attribute of a single-capture HDF5 file (:func:`save_capture`).
CAPTURE_FORMAT = "nlosjax-capture"
CAPTURE_FORMAT_VERSION = 1
_DATASET_FORMAT = "nlosjax-dynamic-nlos"    # nlosjax.data.dataset.FORMAT_NAME


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
  tmp = path.with_name(path.name + ".partial")
  try:
    with h5py.File(tmp, "w") as f:
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
                         compression_opts=4, shuffle=True)
      for key, arr in arrays.items():
        f.create_dataset(key, data=arr, compression="gzip" if arr.size > 4096 else None)
    os.replace(tmp, path)
  except BaseException:
    tmp.unlink(missing_ok=True)
    raise
  return path


def _read_capture(path: Path, *, zero_bins=None, bin_factor=None, num_bins=None, frame=0):
  """Read nlosjax's single-capture layout (:func:`save_capture`)."""
  try:
    f = h5py.File(path, "r")
  except OSError as exc:
    raise ValueError(f"{path}: cannot be read as an HDF5 file (corrupt or truncated): {exc}") from None
  with f:
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
    except OSError as exc:
      raise ValueError(f"{path}: reading 'transient' failed (corrupt file?): {exc}") from None
    depth_range = tuple(float(v) for v in np.ravel(a["depth_range"])) if "depth_range" in a else None
    wall, native = float(_attr_value(a["wall_size"])), float(_attr_value(a["bin_width"]))
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


def _read_dataset(path: Path, *, zero_bins=None, bin_factor=None, num_bins=None, frame=0,
                  split=None, sequence=None, key="measurement"):
  """Read frames of one sequence of an nlosjax dynamic dataset (README, "Dynamic NLOS dataset").

  Args (beyond the shared ones):
    split: ``"train"`` or ``"test"`` (default: any split).
    sequence: a sequence name (``"test-00003"``) or an index into the
      sequences of ``split`` (sorted by name); default 0, the first.
    frame: frame(s) of the sequence (default 0).
    key: ``"measurement"`` (SPAD counts, default) or ``"clean"``.
  """
  from nlosjax.data import dataset as ds_module
  if key not in ("measurement", "clean"):
    raise ValueError(f"{path}: key must be 'measurement' or 'clean', got {key!r}")
  with ds_module.open_dataset(path) as ds:
    names = ds.names(split)
    if not names:
      raise ValueError(f"{path}: no sequence in split {split!r}")
    if sequence is None:
      name = names[0]
    elif isinstance(sequence, str):
      if sequence not in names:
        raise ValueError(f"{path}: no sequence {sequence!r}"
                         f"{'' if split is None else f' in split {split!r}'}; it has {names[:6]}"
                         f"{' ...' if len(names) > 6 else ''}")
      name = sequence
    elif isinstance(sequence, (int, np.integer)) and not isinstance(sequence, bool):
      if not -len(names) <= sequence < len(names):
        raise ValueError(f"{path}: sequence index {sequence} out of range: {len(names)} sequence(s)"
                         f"{'' if split is None else f' in split {split!r}'}")
      name = names[int(sequence)]
    else:
      raise ValueError(f"{path}: sequence must be a name or an index, got {sequence!r}")
    frames, single = _frame_selection(path, frame, ds.num_frames(name))
    raw = ds.read(name, key, frames=frames, dtype=np.float64)          # [F, T, H, W]
    setup = ds.setup
  raw_bins = setup.num_bins
  zero_bins, bin_factor, num_bins = _time_plan(path, raw_bins, zero_bins, bin_factor, num_bins)
  counts = np.moveaxis(_bin_time(np.moveaxis(raw, 1, -1), zero_bins, bin_factor, num_bins), -1, 1)
  setup = _make_setup(path, wall_size=setup.wall_size, grid=setup.grid,
                      bin_width=setup.bin_width * bin_factor, num_bins=num_bins)
  return (counts[0] if single else counts), setup


register_format(
    "nlosjax_dataset", _read_dataset, container="hdf5",
    accepts=lambda p: _root_format(p) == _DATASET_FORMAT,
    options=("frame", "split", "sequence", "key"),
    summary="HDF5 dynamic NLOS dataset written by nlosjax.data.dataset (format"
            " 'nlosjax-dynamic-nlos'): one sequence's frames")


# ------------------------------------------------------- scan downsampling

def _downsample_scan(path: Path, counts: np.ndarray, setup: Setup, factor: int, mode: str):
  """Downsample the scan grid by ``factor``; returns ``(counts, setup)``."""
  if factor == 1:
    return counts, setup
  *lead, num_bins, height, width = counts.shape
  ys, xs = setup.scan_y, setup.scan_x
  if mode == "sum":
    if height % factor or width % factor:
      raise ValueError(
          f"{path}: spatial_factor={factor} with spatial_mode='sum' needs the grid"
          f" {setup.grid} to be divisible by {factor}")
    counts = counts.reshape(*lead, num_bins, height // factor, factor, width // factor,
                            factor).sum(axis=(-3, -1))
    ys = ys.reshape(-1, factor).mean(axis=1)
    xs = xs.reshape(-1, factor).mean(axis=1)
  else:  # "stride"
    counts = counts[..., ::factor, ::factor]
    ys, xs = ys[::factor], xs[::factor]
  if len(ys) < 2 or len(xs) < 2:
    raise ValueError(
        f"{path}: spatial_factor={factor} leaves a {len(ys)} x {len(xs)} grid from"
        f" {setup.grid}; at least 2 x 2 points are needed")
  extent_y, extent_x = ys[-1] - ys[0], xs[-1] - xs[0]
  if not math.isclose(extent_y, extent_x, rel_tol=1e-9):
    raise ValueError(
        f"{path}: spatial_factor={factor} ({mode}) on the {setup.grid} grid gives scan"
        f" points spanning {extent_y:.6g} m along y but {extent_x:.6g} m along x;"
        " a Setup has one wall_size for both axes")
  return counts, dataclasses.replace(setup, wall_size=float(extent_y), grid=(len(ys), len(xs)))


# ---------------------------------------------------------------- overrides

_FILE_FIELDS = {
    "wall_size": "the scan extent comes from the file",
    "grid": "use spatial_factor to change the grid",
    "bin_width": "use bin_factor to change the bin width",
    "num_bins": "use num_bins to change the number of bins",
}


def _check_overrides(path: Path, overrides) -> dict:
  if overrides is None:
    return {}
  if not isinstance(overrides, Mapping):
    raise ValueError(f"{path}: setup_overrides must be a dict of Setup fields, got {type(overrides).__name__}")
  fields = [f.name for f in dataclasses.fields(Setup)]
  unknown = sorted(set(overrides) - set(fields))
  if unknown:
    raise ValueError(f"{path}: setup_overrides has unknown field(s) {unknown}; Setup fields are {fields}")
  return dict(overrides)


def _same(name: str, ours, theirs) -> bool:
  if name == "grid":
    if isinstance(theirs, (int, np.integer)) and not isinstance(theirs, bool):
      theirs = (theirs, theirs)
    try:
      return len(theirs) == 2 and all(t == o for t, o in zip(theirs, ours))
    except TypeError:
      return False
  if name == "num_bins":
    return not isinstance(theirs, bool) and theirs == ours
  try:
    return math.isclose(float(theirs), ours, rel_tol=1e-6)
  except (TypeError, ValueError):
    return False


def _apply_overrides(path: Path, setup: Setup, overrides: dict, format_options=()) -> Setup:
  for name, hint in _FILE_FIELDS.items():
    if name in overrides and not _same(name, getattr(setup, name), overrides[name]):
      if name in format_options:
        hint = (f"this format does not record {name}; pass {name}= to load_measurement to set"
                " the capture's value")
      raise ValueError(
          f"{path}: setup_overrides[{name!r}] = {overrides[name]!r} contradicts the file,"
          f" which gives {name} = {getattr(setup, name)!r} ({hint})")
  if "depth_range" in overrides:
    try:
      setup = dataclasses.replace(setup, depth_range=overrides["depth_range"])
    except ValueError as exc:
      raise ValueError(f"{path}: setup_overrides['depth_range']: {exc}") from exc
  return setup


# ------------------------------------------------------------------ loading

def load_measurement(path, *, format: str | None = None, zero_bins: int | None = None,
                     bin_factor: int | None = None, num_bins: int | None = None,
                     spatial_factor: int = 1, spatial_mode: str = "sum", frame=0,
                     setup_overrides: Mapping | None = None,
                     **format_options) -> tuple[np.ndarray, Setup]:
  """Load a measured confocal scan as ``(transient [T, H, W] float32, Setup)``.

  Formats (detected from the content, see :func:`detect_format`; each
  reader's docstring has the details):

  * ``"lct_mat"``: O'Toole et al. 2018 ``rect_data``/``width`` (MATLAB v5). The
    defaults give the published preparation (``cnlos_reconstruction.m``):
    zero the first 600 raw 4 ps bins (the direct reflection off the wall),
    sum groups of 4 (16 ps), keep every full group (512 bins for the
    2048-bin scans); ``transient[t, y, x]`` from ``rect_data[x, y, :]``;
    ``Setup(wall_size=2 * width, grid=(H, W), bin_width=16e-12, num_bins=512)``.
  * ``"stanford_fk"``: Lindell et al. 2019 ``meas`` (MATLAB v7.3 or v5,
    ``[H, W, T]`` or video ``[F, H, W, T]``, 32 ps) aligned per scan point with
    ``tofgrid`` (ps; in the file, the sibling ``tof_<suffix>.mat`` /
    ``tof.mat``, or ``tofgrid=``), cropped to 512 raw bins by default; 2 m wall
    unless ``wall_size=``. Options ``tofgrid``, ``wall_size``, ``frame``.
  * ``"nlost_mat"``: NLOST (CVPR 2023) ``data`` ``[W, H, T]`` (transposed) or
    aligned f-k ``final_meas`` ``[H, W, T]``; 32 ps, 2 m wall unless
    ``bin_width=`` / ``wall_size=``.
  * ``"nlosjax_capture"``: :func:`save_capture`'s HDF5 layout (option ``frame``).
  * ``"nlosjax_dataset"``: a sequence of an nlosjax dynamic dataset
    (options ``split``, ``sequence``, ``frame``, ``key``).

  Args:
    path: file to read; never written to.
    format: a name in :data:`FORMATS`; ``None`` detects it from the file's
      content. A named format skips detection and the reader validates the
      content.
    zero_bins: raw time bins ``[0, zero_bins)`` set to zero before binning;
      ``None`` is the format's default (``lct_mat``: 600, others 0).
    bin_factor: raw bins summed into one output bin (temporal binning);
      ``None`` is the format's default (``lct_mat``: 4, others 1).
    num_bins: ``T``, output bins kept (the first ones; trimming); ``None``
      keeps every full group (``stanford_fk``: the first 512 raw bins).
    spatial_factor: ``k >= 1``, downsample the scan grid by ``k`` per axis.
    spatial_mode: ``"sum"`` sums ``k x k`` blocks of scan points (``H`` and
      ``W`` must be divisible by ``k``); the new points are the block centres,
      which span ``wall_size * (H - k) / (H - 1)``, centred as before.
      ``"stride"`` keeps rows and columns ``0, k, 2k, ...`` (interval sampling,
      as in under-scanning); the ``n = (H - 1) // k + 1`` kept points span
      ``(n - 1) * k`` old spacings, which is the full wall only when the last
      point ``H - 1`` is kept. In both modes the new ``wall_size`` is the true
      extent of the kept points, computed from their coordinates, so the new
      grid's spacing is ``k`` old spacings. Caveat for ``"stride"`` when the
      last point is not kept: the kept points are centred
      ``(H - 1 - (n - 1) * k) / 2`` old spacings below the wall centre, but a
      Setup places its grid centred, so reconstructions come out shifted
      laterally by that much (1.5 spacings, 1.9 cm, for 64 -> 16 on the 0.8 m
      exit-sign scan). The Setup has one ``wall_size``, so both axes must
      end up spanning the same extent.
    frame: which frame(s) of a multi-frame file (a video or a dataset
      sequence): an int (default 0) returns ``[T, H, W]``; ``"all"`` or a list
      of ints returns ``[F, T, H, W]``. A single capture has frame 0 only.
    setup_overrides: dict of Setup fields. ``depth_range`` (metres) is always
      applied; ``wall_size``, ``grid``, ``bin_width`` and ``num_bins`` come from
      the file (after binning and downsampling) and may only repeat those
      values (for a value the format does not record, such as the f-k wall
      size, pass the format option ``wall_size=`` instead).
    **format_options: options of the detected format (listed above); an
      option the format does not take raises ``ValueError``.

  Returns:
    ``(transient, setup)``: float32 ``[T, H, W]`` (or ``[F, T, H, W]``, see
    ``frame``) photon counts (summed, so whole numbers for counting formats;
    ``t = 0`` when light reaches the wall) and the matching
    :class:`~nlosjax.physics.setup.Setup` (metres, seconds).

  Raises:
    FileNotFoundError: if ``path`` (or a named tofgrid file) does not exist.
    ValueError: naming the file and the problem: unknown or unrecognised
      format, corrupt or truncated file, missing variables, wrong rank,
      negative, NaN or infinite counts, a missing or mismatched time-of-flight
      calibration, invalid preparation arguments or options, or an override
      contradicting the file.
  """
  path = _existing_file(path)
  spatial_factor = _int_arg(path, "spatial_factor", spatial_factor, 1)
  if spatial_mode not in ("sum", "stride"):
    raise ValueError(f"{path}: spatial_mode must be 'sum' or 'stride', got {spatial_mode!r}")
  overrides = _check_overrides(path, setup_overrides)
  if format is None:
    format = detect_format(path)
  elif format not in FORMATS:
    raise ValueError(f"{path}: unknown format {format!r}. Supported formats: {_supported()}")
  spec = FORMATS[format]
  unknown = sorted(set(format_options) - set(spec.options))
  if unknown:
    raise ValueError(f"{path}: format {format!r} takes no option(s) {unknown}; its options are"
                     f" {sorted(spec.options) or 'none'} (plus zero_bins, bin_factor, num_bins,"
                     " spatial_factor, spatial_mode, frame, setup_overrides)")
  options = dict(format_options)
  if "frame" in spec.options:
    options["frame"] = frame
  counts, setup = spec.reader(path, zero_bins=zero_bins, bin_factor=bin_factor, num_bins=num_bins,
                              **options)
  if "frame" not in spec.options:
    frames, single = _frame_selection(path, frame, 1)
    if not single:
      counts = np.stack([counts] * len(frames))
  counts, setup = _downsample_scan(path, counts, setup, spatial_factor, spatial_mode)
  setup = _apply_overrides(path, setup, overrides, spec.options)
  transient = np.ascontiguousarray(counts, dtype=np.float32)
  setup.check_transient(transient)
  return transient, setup


# -------------------------------------------------------------- shipped data

#: The measured scan shipped with the repository (see experiments/data/README.md).
SHIPPED_SCAN_NAME = "data_exit_sign.mat"
#: Every measured scan shipped with the repository: the exit sign and the letters S and U.
SHIPPED_SCAN_NAMES = (SHIPPED_SCAN_NAME, "data_s_u.mat")
_SHIPPED_DIR = Path(__file__).resolve().parents[2] / "experiments" / "data"


def shipped_scan_path(name: str = SHIPPED_SCAN_NAME) -> Path:
  """Path of a measured scan shipped in ``experiments/data/`` (default: the exit sign).

  The O'Toole et al. 2018 ``data_exit_sign.mat`` or ``data_s_u.mat``
  (``lct_mat``: 64 x 64 scan points, 0.8 or 0.7 m wall, 2048 bins of 4 ps),
  unchanged. They live in the source repository, not in the Python package.

  Args:
    name: one of :data:`SHIPPED_SCAN_NAMES`.
  Raises:
    ValueError: for another name.
    FileNotFoundError: if the file is absent, e.g. for a pip-installed
      package without the repository checkout.
  """
  if name not in SHIPPED_SCAN_NAMES:
    raise ValueError(f"shipped scans are {SHIPPED_SCAN_NAMES}, got {name!r}")
  path = _SHIPPED_DIR / name
  if not path.is_file():
    raise FileNotFoundError(
        errno.ENOENT,
        f"shipped scan not found at {path}: it lives in the nlosjax source"
        " repository (experiments/data/), not in an installed package; use a source"
        f" checkout or pass the path of a copy of {name} to load_measurement",
        str(path))
  return path

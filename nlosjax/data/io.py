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

Adding a format: write ``reader(path, *, zero_bins, bin_factor, num_bins)``
returning ``(counts [T, H, W] float64, Setup)`` (``None`` meaning the format's
own default for each preparation step) and :func:`register_format` it with
the container it lives in (``"mat5"`` or ``"hdf5"``), so that detection finds
it. MATLAB v7.3 files are HDF5 files behind a 512-byte text header; no HDF5
format is registered yet, so they are refused with a ``ValueError``.

Nothing here ever writes to the input file: readers open it read-only.
"""

from __future__ import annotations

import dataclasses
import errno
import math
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
import scipy.io

from nlosjax.physics.setup import Setup

__all__ = [
    "FORMATS",
    "LCT_NATIVE_BIN_WIDTH",
    "SHIPPED_SCAN_NAME",
    "detect_format",
    "load_measurement",
    "register_format",
    "shipped_scan_path",
]

# ----------------------------------------------------------------- registry

Reader = Callable[..., tuple[np.ndarray, Setup]]


@dataclasses.dataclass(frozen=True)
class FormatSpec:
  """One registered measurement format.

  Attributes:
    reader: ``reader(path, *, zero_bins, bin_factor, num_bins)`` ->
      ``(counts [T, H, W] float64, Setup)``; ``None`` arguments take the
      format's defaults.
    container: file container the format lives in, as :func:`detect_format`
      recognises it: ``"mat5"`` (MATLAB v5/v6/v7) or ``"hdf5"`` (HDF5, which
      includes MATLAB v7.3).
    summary: one line for error messages and docs.
    accepts: optional ``accepts(path) -> bool`` content check, used only to
      choose between several formats sharing one container.
  """

  reader: Reader
  container: str
  summary: str
  accepts: Callable[[Path], bool] | None = None


#: format name -> :class:`FormatSpec`; filled by :func:`register_format`.
FORMATS: dict[str, FormatSpec] = {}

_CONTAINERS = ("mat5", "hdf5")


def register_format(name: str, reader: Reader, *, container: str, summary: str,
                    accepts: Callable[[Path], bool] | None = None) -> None:
  """Add (or replace) the format ``name`` in :data:`FORMATS`."""
  if container not in _CONTAINERS:
    raise ValueError(f"container must be one of {_CONTAINERS}, got {container!r}")
  FORMATS[name] = FormatSpec(reader=reader, container=container, summary=summary, accepts=accepts)


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
  (at byte 0, or 512 for MATLAB v7.3). The file name is never consulted.

  Raises:
    FileNotFoundError: if ``path`` does not exist.
    ValueError: naming the file and the supported formats, when no registered
      format lives in the file's container or the content is unrecognised.
  """
  path = _existing_file(path)
  container = _container(path)
  if container is None:
    raise ValueError(
        f"{path}: unrecognised file content (neither a MATLAB v5 .mat nor an HDF5 file)."
        f" Supported formats: {_supported()}")
  candidates = [name for name, spec in FORMATS.items() if spec.container == container]
  for name in candidates:
    accepts = FORMATS[name].accepts
    if len(candidates) == 1 or accepts is None or accepts(path):
      return name
  kind = "an HDF5 file (MATLAB v7.3 or HDF5)" if container == "hdf5" else "a MATLAB v5 file"
  raise ValueError(
      f"{path}: {kind}, but no registered format reads it"
      f" (no reader for this container yet). Supported formats: {_supported()}")


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


register_format(
    "lct_mat", _read_lct_mat, container="mat5",
    summary="MATLAB v5 .mat with rect_data [H, W, T] (4 ps bins) and width (half wall side, m),"
            " the O'Toole et al. 2018 confocal LCT scans")


# ------------------------------------------------------- scan downsampling

def _downsample_scan(path: Path, counts: np.ndarray, setup: Setup, factor: int, mode: str):
  """Downsample the scan grid by ``factor``; returns ``(counts, setup)``."""
  if factor == 1:
    return counts, setup
  num_bins, height, width = counts.shape
  ys, xs = setup.scan_y, setup.scan_x
  if mode == "sum":
    if height % factor or width % factor:
      raise ValueError(
          f"{path}: spatial_factor={factor} with spatial_mode='sum' needs the grid"
          f" {setup.grid} to be divisible by {factor}")
    counts = counts.reshape(num_bins, height // factor, factor, width // factor, factor).sum(axis=(2, 4))
    ys = ys.reshape(-1, factor).mean(axis=1)
    xs = xs.reshape(-1, factor).mean(axis=1)
  else:  # "stride"
    counts = counts[:, ::factor, ::factor]
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


def _apply_overrides(path: Path, setup: Setup, overrides: dict) -> Setup:
  for name, hint in _FILE_FIELDS.items():
    if name in overrides and not _same(name, getattr(setup, name), overrides[name]):
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
                     spatial_factor: int = 1, spatial_mode: str = "sum",
                     setup_overrides: Mapping | None = None) -> tuple[np.ndarray, Setup]:
  """Load a measured confocal scan as ``(transient [T, H, W] float32, Setup)``.

  For ``"lct_mat"`` (O'Toole, Lindell, Wetzstein, Nature 2018; the recipe of
  ``cnlos_reconstruction.m`` in its supplementary code) the defaults give the
  published preparation: zero the first 600 raw 4 ps bins (the direct
  reflection off the wall), sum groups of 4 bins (16 ps), keep every full
  group (512 bins for the 2048-bin scans); then ``transient[t, y, x]`` is
  ``rect_data[y, x, :]`` prepared (rows along y, columns along x) and the
  Setup is ``Setup(wall_size=2 * width, grid=(H, W), bin_width=16e-12,
  num_bins=512)``.

  Args:
    path: file to read; never written to.
    format: a name in :data:`FORMATS` (``"lct_mat"``); ``None`` detects it from
      the file's content (:func:`detect_format`). A named format skips
      detection and the reader validates the content.
    zero_bins: raw time bins ``[0, zero_bins)`` set to zero before binning;
      ``None`` is the format's default (``lct_mat``: 600).
    bin_factor: raw bins summed into one output bin; ``None`` is the format's
      default (``lct_mat``: 4, so ``bin_width = 4 ps * 4 = 16 ps``).
    num_bins: ``T``, output bins kept (the first ones); ``None`` keeps every
      full group of ``bin_factor`` raw bins.
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
    setup_overrides: dict of Setup fields. ``depth_range`` (metres) is always
      applied; ``wall_size``, ``grid``, ``bin_width`` and ``num_bins`` come from
      the file (after binning and downsampling) and may only repeat those
      values.

  Returns:
    ``(transient, setup)``: float32 ``[T, H, W]`` photon counts (summed, so
    whole numbers for counting formats; ``t = 0`` when light reaches the
    wall) and the matching :class:`~nlosjax.physics.setup.Setup` (metres,
    seconds).

  Raises:
    FileNotFoundError: if ``path`` does not exist.
    ValueError: naming the file and the problem: unknown or unsupported
      format (HDF5/MATLAB v7.3 now), corrupt or truncated file, missing
      ``rect_data``/``width``, wrong rank, negative, NaN or infinite counts,
      invalid preparation arguments, or an override contradicting the file.
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

  counts, setup = FORMATS[format].reader(path, zero_bins=zero_bins, bin_factor=bin_factor, num_bins=num_bins)
  counts, setup = _downsample_scan(path, counts, setup, spatial_factor, spatial_mode)
  setup = _apply_overrides(path, setup, overrides)
  transient = np.ascontiguousarray(counts, dtype=np.float32)
  setup.check_transient(transient)
  return transient, setup


# -------------------------------------------------------------- shipped data

#: The measured scan shipped with the repository (see experiments/data/README.md).
SHIPPED_SCAN_NAME = "data_exit_sign.mat"
_SHIPPED_SCAN = Path(__file__).resolve().parents[2] / "experiments" / "data" / SHIPPED_SCAN_NAME


def shipped_scan_path() -> Path:
  """Path of the measured exit-sign scan shipped in ``experiments/data/``.

  The O'Toole et al. 2018 ``data_exit_sign.mat`` (``lct_mat``: 64 x 64 scan
  points, 0.8 m wall, 2048 bins of 4 ps), unchanged. It lives in the source
  repository, not in the Python package.

  Raises:
    FileNotFoundError: if the file is absent, e.g. for a pip-installed
      package without the repository checkout.
  """
  if not _SHIPPED_SCAN.is_file():
    raise FileNotFoundError(
        errno.ENOENT,
        f"shipped scan not found at {_SHIPPED_SCAN}: it lives in the nlosjax source"
        " repository (experiments/data/), not in an installed package; use a source"
        " checkout or pass the path of a copy of data_exit_sign.mat to load_measurement",
        str(_SHIPPED_SCAN))
  return _SHIPPED_SCAN

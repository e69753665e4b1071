"""Read measured confocal NLOS scans into ``(transient [T, H, W], Setup)``.

:func:`load_measurement` is the one entry point. It detects the file format
from the file's first bytes (or takes ``format=``), hands the file to that
format's reader, then optionally downsamples the scan grid and applies
``Setup`` overrides. Every reader returns photon counts in nlosjax's
conventions (see :mod:`nlosjax.physics.setup`): a transient ``[T, H, W]``
with ``t = 0`` when light reaches the wall, rows along y, columns along x, and
a :class:`~nlosjax.physics.setup.Setup` whose scan grid spans
``[-wall_size/2, wall_size/2]`` as ``numpy.linspace`` does.

Formats (the registry :data:`FORMATS`, name -> reader), one module each in
:mod:`nlosjax.data.formats`, whose docstring describes the file layout:

``"lct_mat"`` (:mod:`~nlosjax.data.formats.lct_mat`)
  O'Toole, Lindell and Wetzstein, Nature 2018: MATLAB v5 ``rect_data``
  ``[W, H, T]`` (4 ps bins) and ``width`` (half the wall side, metres).
``"stanford_fk"`` (:mod:`~nlosjax.data.formats.stanford_fk`)
  Lindell, Wetzstein and O'Toole, SIGGRAPH 2019: MATLAB v7.3 ``meas``
  ``[H, W, T]`` or ``[F, H, W, T]`` (32 ps bins), aligned with a ``tofgrid``.
``"nlost_mat"`` (:mod:`~nlosjax.data.formats.nlost_mat`)
  Li et al., NLOST, CVPR 2023: ``data`` ``[W, H, T]``; or the aligned f-k
  ``final_meas`` ``[H, W, T]``.
``"nlosjax_capture"`` (:mod:`~nlosjax.data.formats.capture`)
  nlosjax's single-capture HDF5 layout, written by :func:`save_capture`
  (and by ``python -m experiments.reconstruct``).
``"nlosjax_dataset"`` (:mod:`~nlosjax.data.formats.dataset_file`)
  One sequence of an nlosjax dynamic dataset (``nlosjax.data.dataset``;
  ``docs/dataset.md``).
``"tal"`` (:mod:`~nlosjax.data.formats.tal`)
  y-tal's HDF5 captures (``tal.io.read_capture``), confocal on a regular
  planar grid: ``H`` ``[T, Sx, Sy]`` or ``[T, Si]``, ``delta_t`` and
  ``t_start`` in metres of path, each scan point's histogram shifted to
  ``t = 0`` at the wall; written by :func:`save_tal`.

Where the pieces live: the registry (:class:`FormatSpec`,
:func:`register_format`, :data:`FORMATS`) and detection
(:func:`detect_format`: the container from the first bytes, then the first
format, in registration order, whose ``accepts`` check passes) in
:mod:`nlosjax.data.formats.registry`; the reading helpers every reader
shares in :mod:`nlosjax.data.formats._common`; each format's reader, its
constants and its :func:`register_format` call in its own module. This
module keeps scan downsampling, ``Setup`` overrides, :func:`load_measurement`
and the shipped scans (:func:`shipped_scan_path`), and re-exports the public
names of the format modules.

Adding a format: write ``reader(path, *, zero_bins, bin_factor, num_bins,
**options)`` returning ``(counts [T, H, W] or [F, T, H, W], Setup)``
(``None`` meaning the format's own default for each preparation step) and
:func:`register_format` it with the container(s) it lives in (``"mat5"``,
``"hdf5"`` or both), an ``accepts`` check when the container is shared, and
the names of its extra options; a module of :mod:`nlosjax.data.formats`
doing so is imported in that package's ``__init__`` (the order there is the
detection order).

Nothing here ever writes to the input file: readers open it read-only.
"""

from __future__ import annotations

import dataclasses
import errno
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from nlosjax.data.formats import registry
from nlosjax.data.formats._common import _frame_selection, _int_arg
from nlosjax.data.formats.capture import CAPTURE_FORMAT, CAPTURE_FORMAT_VERSION, save_capture
from nlosjax.data.formats.lct_mat import LCT_NATIVE_BIN_WIDTH
from nlosjax.data.formats.nlost_mat import NLOST_BIN_WIDTH, NLOST_WALL_SIZE
from nlosjax.data.formats.registry import (
  FORMATS,
  FormatSpec,
  Reader,
  _existing_file,
  _supported,
  detect_format,
  register_format,
)
from nlosjax.data.formats.registry import _container as _container  # re-exported: tests read io._container
from nlosjax.data.formats.stanford_fk import FK_CROP, FK_NATIVE_BIN_WIDTH, FK_WALL_SIZE
from nlosjax.data.formats.tal import save_tal
from nlosjax.physics.setup import Setup

__all__ = [
    "CAPTURE_FORMAT",
    "CAPTURE_FORMAT_VERSION",
    "FK_CROP",
    "FK_NATIVE_BIN_WIDTH",
    "FK_WALL_SIZE",
    "FORMATS",
    "LCT_NATIVE_BIN_WIDTH",
    "NLOST_BIN_WIDTH",
    "NLOST_WALL_SIZE",
    "SHIPPED_SCAN_NAME",
    "SHIPPED_SCAN_NAMES",
    "FormatSpec",
    "Reader",
    "detect_format",
    "load_measurement",
    "register_format",
    "save_capture",
    "save_tal",
    "shipped_scan_path",
]

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
  * ``"tal"``: a y-tal HDF5 capture (confocal, regular grid on a plane
    ``z = const``); ``bin_width = delta_t / c``, ``wall_size`` the extent of
    the scan points, rows along y and columns along x ascending, each point's
    histogram shifted by ``round((t_start - d_laser - d_spad) / delta_t)``
    bins (the legs only when ``t_accounts_first_and_last_bounces``);
    exhaustive, single-laser, frequency-domain or irregular captures raise
    ``ValueError``. :func:`save_tal` writes one.

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
  elif format not in registry.FORMATS:   # the registry's dict itself, the one detect_format consults
    raise ValueError(f"{path}: unknown format {format!r}. Supported formats: {_supported()}")
  spec = registry.FORMATS[format]
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

#: The measured scan shipped with the package (see nlosjax/data/scans/README.md).
SHIPPED_SCAN_NAME = "data_exit_sign.mat"
#: Every measured scan shipped with the repository: the exit sign and the letters S and U.
SHIPPED_SCAN_NAMES = (SHIPPED_SCAN_NAME, "data_s_u.mat")
_SHIPPED_DIR = Path(__file__).resolve().parent / "scans"


def shipped_scan_path(name: str = SHIPPED_SCAN_NAME) -> Path:
  """Path of a measured scan shipped in the package, ``nlosjax/data/scans/`` (default: the exit sign).

  The O'Toole et al. 2018 ``data_exit_sign.mat`` or ``data_s_u.mat``
  (``lct_mat``: 64 x 64 scan points, 0.8 or 0.7 m wall, 2048 bins of 4 ps),
  unchanged (their provenance: ``nlosjax/data/scans/README.md``).

  Args:
    name: one of :data:`SHIPPED_SCAN_NAMES`.
  Raises:
    ValueError: for another name.
    FileNotFoundError: if the file is absent (an install without its package data).
  """
  if name not in SHIPPED_SCAN_NAMES:
    raise ValueError(f"shipped scans are {SHIPPED_SCAN_NAMES}, got {name!r}")
  path = _SHIPPED_DIR / name
  if not path.is_file():
    raise FileNotFoundError(
        errno.ENOENT,
        f"shipped scan not found at {path}: the package data of this install are incomplete;"
        f" reinstall nlosjax or pass the path of a copy of {name} to load_measurement",
        str(path))
  return path

"""Format ``"tal"``: y-tal's HDF5 capture layout (TAL), read for confocal scans and written by :func:`save_tal`.

TAL, the Zaragoza group's "Transient Auxiliary Library" (PyPI ``y-tal``,
``tal.io.read_capture`` / ``tal.io.write_capture``), stores one capture as
top-level HDF5 datasets (no attributes), the fields of its ``NLOSCaptureData``:

* ``H``: the impulse response, time first. ``H_format`` (an integer, stored
  as an HDF5 enum) names its axes: ``T_Sx_Sy`` (1) ``[T, Sx, Sy]`` over a
  2D grid of sensor points, ``T_Si`` (3) ``[T, Si]`` over a list of them;
  ``T_Lx_Ly_Sx_Sy`` (2) and ``T_Li_Si`` (4) add laser axes (exhaustive
  captures); ``F_*`` (10-13) are frequency-domain versions.
* ``sensor_grid_xyz`` / ``laser_grid_xyz``: the points on the relay wall,
  metres, with ``{sensor|laser}_grid_format``: ``X_Y_3`` (2) ``[Sx, Sy, 3]``
  or ``N_3`` (1) ``[N, 3]``. ``*_grid_normals`` the same shapes.
  ``sensor_xyz`` / ``laser_xyz`` ``[3]``: the SPAD's and the laser's own
  positions. TAL's relay wall is the plane ``z = 0``, hidden scene at ``z > 0``.
* ``delta_t``: bin width as optical path length, metres (``c * seconds``).
  ``t_start``: the path length at the start of bin 0, metres.
  ``t_accounts_first_and_last_bounces``: whether the path lengths include
  the laser -> wall leg ``d1 = |laser_grid_xyz[p] - laser_xyz|`` and the wall
  -> SPAD leg ``d4 = |sensor_grid_xyz[p] - sensor_xyz|`` of each point ``p``.
  So ``H[i, p]`` holds paths in ``[t_start + i * delta_t, t_start + (i + 1) *
  delta_t)``, counted from the laser's emission (true) or from the light
  reaching the wall (false).
* ``scene_info``: a YAML string of free-form metadata; ``volume_format``.
  A field TAL leaves unset is an empty (null-dataspace) dataset.

What nlosjax reads (:func:`_read_tal`): confocal captures (the laser points
are the sensor points) in the time domain, ``T_Sx_Sy`` or ``T_Si``, with
either grid format, whose points form a regular grid in one plane
``z = const`` with rows and columns along x and y (in any order, either
direction, and for ``N_3`` in any order of points), spanning the same extent
along x and y (a :class:`~nlosjax.physics.setup.Setup` has one
``wall_size``). The transient is then ``transient[k, r, c]``: row ``r`` at the
``r``-th smallest y, column ``c`` at the ``c``-th smallest x, and time bin
``k`` = round-trip path from the wall in ``[k, k + 1) * delta_t``: point
``p``'s histogram is moved by ``round((t_start - d1[p] - d4[p]) / delta_t)``
bins (``d1 = d4 = 0`` when the legs are not included; halves round up), so
every scan point gets its own shift. Bins moved before the wall are dropped;
bins not recorded (before ``t_start``, or past a point's last bin) are 0;
``T`` runs to the last recorded bin of any point. ``bin_width = delta_t /
c``; ``wall_size`` = the extent of the scan points. A missing ``t_start`` is
0 and a missing ``t_accounts_first_and_last_bounces`` false, as TAL's
reconstructions take them. The normals, ``scene_info`` and where the grid
sits on the wall (its centre, its ``z``) are not kept: nlosjax's geometry is
relative to the scanned square.

Refused with a ``ValueError`` naming what is unsupported: exhaustive captures
(laser axes in ``H``), a single laser point (or any laser points other than the
sensor points), frequency-domain ``H``, complex or extra axes in ``H`` (e.g. a
polarized render's Stokes axis), grids not on one plane ``z = const``,
irregular or uneven grids, unequal extents along x and y, a
missing or non-positive ``delta_t``, and ``t_accounts_first_and_last_bounces``
without ``laser_xyz`` and ``sensor_xyz``.

:func:`save_tal` writes a ``[T, H, W]`` transient and its Setup as a confocal
TAL capture that ``tal.io.read_capture`` opens.
"""

from __future__ import annotations

import errno
import io
import json
import math
from pathlib import Path

import h5py
import numpy as np

from nlosjax import __version__, files
from nlosjax.data.formats._common import _bin_time, _check_counts, _make_setup, _open_hdf5, _time_plan
from nlosjax.data.formats.registry import DAMAGED_INPUT, _variables, register_format
from nlosjax.physics.setup import SPEED_OF_LIGHT, Setup

#: TAL's ``HFormat`` values (``tal.enums.HFormat``): integer -> name.
TAL_H_FORMATS = {0: "UNKNOWN", 1: "T_Sx_Sy", 2: "T_Lx_Ly_Sx_Sy", 3: "T_Si", 4: "T_Li_Si",
                 10: "F_Sx_Sy", 11: "F_Lx_Ly_Sx_Sy", 12: "F_Si", 13: "F_Li_Si"}
#: TAL's ``GridFormat`` values (``tal.enums.GridFormat``): integer -> name.
TAL_GRID_FORMATS = {0: "UNKNOWN", 1: "N_3", 2: "X_Y_3"}
#: The layouts nlosjax reads and writes: ``H_format`` -> the sensor grid format :func:`save_tal` writes with it.
TAL_LAYOUTS = {"T_Sx_Sy": "X_Y_3", "T_Si": "N_3"}
_EXHAUSTIVE = ("T_Lx_Ly_Sx_Sy", "T_Li_Si", "F_Lx_Ly_Sx_Sy", "F_Li_Si")
#: Every field of TAL's ``NLOSCaptureData`` (``read_capture`` refuses any other top-level name).
TAL_FIELDS = ("H", "H_format", "sensor_xyz", "sensor_grid_xyz", "sensor_grid_normals", "sensor_grid_format",
              "laser_xyz", "laser_grid_xyz", "laser_grid_normals", "laser_grid_format", "volume_format",
              "delta_t", "t_start", "t_accounts_first_and_last_bounces", "scene_info")


# ------------------------------------------------------------------ reading

def _dataset(f: h5py.File, key: str):
  """``f[key]`` read whole, or None where absent or empty (TAL writes an unset field as a null dataspace)."""
  if key not in f or not isinstance(f[key], h5py.Dataset) or f[key].shape is None:
    return None
  return f[key][()]


def _scalar(path: Path, f: h5py.File, key: str):
  value = _dataset(f, key)
  if value is None:
    return None
  value = np.asarray(value)
  if value.size != 1:
    raise ValueError(f"{path}: TAL field {key!r} must hold one value, got shape {value.shape}")
  return value.ravel()[0]


def _enum(path: Path, f: h5py.File, key: str, names: dict) -> str | None:
  """A TAL enum field as its name (stored as an HDF5 enum or an integer, or as its name)."""
  value = _scalar(path, f, key)
  if value is None:
    return None
  if isinstance(value, bytes):
    value = value.decode(errors="replace")
  if isinstance(value, str):
    if value not in names.values():
      raise ValueError(f"{path}: TAL field {key!r} = {value!r} is none of {sorted(names.values())}")
    return value
  if int(value) not in names:
    raise ValueError(f"{path}: TAL field {key!r} = {int(value)} is none of TAL's values {names}")
  return names[int(value)]


def _points(path: Path, f: h5py.File, key: str):
  """``(points [N, 3] float64, grid format)`` of a grid field, or ``(None, None)`` where it is unset."""
  grid = _dataset(f, key)
  if grid is None:
    return None, None
  grid = np.asarray(grid)
  fmt = _enum(path, f, key.replace("_xyz", "_format"), TAL_GRID_FORMATS)
  if fmt in (None, "UNKNOWN"):
    fmt = {3: "X_Y_3", 2: "N_3"}.get(grid.ndim, "UNKNOWN")
  expected = {"X_Y_3": 3, "N_3": 2}.get(fmt)
  if expected is None or grid.ndim != expected or grid.shape[-1] != 3 or grid.dtype.kind not in "uif":
    raise ValueError(f"{path}: TAL field {key!r} must be real [Sx, Sy, 3] (X_Y_3) or [N, 3] (N_3) metres;"
                     f" got shape {grid.shape} dtype {grid.dtype} with grid format {fmt}")
  points = grid.reshape(-1, 3).astype(np.float64)
  if not np.all(np.isfinite(points)):
    raise ValueError(f"{path}: TAL field {key!r} holds NaN or infinite positions")
  return points, fmt


def _grid_axis(values: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
  """``(index of each value among the distinct ones, the distinct values ascending)``; within ``tol`` is one."""
  order = np.argsort(values, kind="stable")
  ordered = values[order]
  sorted_labels = np.concatenate([[0], np.cumsum(np.diff(ordered) > tol)])
  labels = np.empty_like(sorted_labels)
  labels[order] = sorted_labels
  centres = np.bincount(sorted_labels, weights=ordered) / np.bincount(sorted_labels)
  return labels, centres


def _scan_grid(path: Path, points: np.ndarray):
  """Arrange TAL scan points ``[N, 3]`` on nlosjax's grid: ``(rows [N], cols [N], (H, W), wall_size)``.

  Row ``r`` is the ``r``-th smallest y, column ``c`` the ``c``-th smallest x.

  Raises:
    ValueError: points off one plane ``z = const``, not a full regular grid
      along x and y, fewer than 2 points per axis, or unequal extents.
  """
  n = len(points)
  scale = max(float(np.max(np.abs(points))), float(np.ptp(points[:, :2], axis=0).max()), 1e-3)
  tol = 1e-5 * scale                       # float32 positions are good to ~1e-7 of their size
  z_span = float(np.ptp(points[:, 2]))
  if z_span > tol:
    raise ValueError(
        f"{path}: the TAL scan points do not lie in one plane z = const (z spans {z_span:.6g} m): nlosjax"
        " reads relay walls in TAL's convention, the plane z = const scanned along x and y; a rotated or"
        " non-planar relay wall is not supported")
  cols, xs = _grid_axis(points[:, 0], tol)
  rows, ys = _grid_axis(points[:, 1], tol)
  height, width = len(ys), len(xs)
  if height * width != n or np.unique(rows * width + cols).size != n:
    raise ValueError(
        f"{path}: irregular TAL scan grid: its {n} points sit on {width} distinct x and {height} distinct"
        f" y positions, which is not a full {height} x {width} grid (each point once); only regular"
        " grids are supported")
  if height < 2 or width < 2:
    raise ValueError(f"{path}: the TAL scan grid is {height} x {width} points; at least 2 x 2 are needed")
  for name, values in (("x", xs), ("y", ys)):
    spacing = (values[-1] - values[0]) / (len(values) - 1)
    off = float(np.max(np.abs(values - np.linspace(values[0], values[-1], len(values)))))
    if off > max(1e-3 * spacing, tol):
      raise ValueError(
          f"{path}: unevenly spaced TAL scan grid along {name}: a column of points is {off / spacing:.3g}"
          f" spacings off the even grid from {values[0]:.6g} to {values[-1]:.6g} m; only regular grids"
          " are supported")
  extent_x, extent_y = np.ptp(points[:, 0]), np.ptp(points[:, 1])     # the values as stored, not cluster means
  if not math.isclose(extent_x, extent_y, rel_tol=1e-4):
    raise ValueError(
        f"{path}: the TAL scan points span {extent_x:.6g} m along x but {extent_y:.6g} m along y; a Setup"
        " has one wall_size for both axes (a square scanned area)")
  return rows, cols, (height, width), (extent_x + extent_y) / 2


def _read_tal(path: Path, *, zero_bins=None, bin_factor=None, num_bins=None):
  """Read a confocal TAL capture as ``(counts [T, H, W] float64, Setup)`` (see the module docstring)."""
  f = _open_hdf5(path)
  try:
    with f:
      h_format = _enum(path, f, "H_format", TAL_H_FORMATS)
      if h_format in (None, "UNKNOWN"):
        raise ValueError(f"{path}: TAL capture without an H_format (got {h_format}); its axes are unknown")
      if h_format in _EXHAUSTIVE:
        raise ValueError(
            f"{path}: exhaustive (non-confocal) TAL capture, H_format {h_format} (a laser grid times a sensor"
            " grid) is not supported: nlosjax reads confocal captures (H_format T_Sx_Sy or T_Si)")
      if h_format.startswith("F_"):
        raise ValueError(f"{path}: frequency-domain TAL capture (H_format {h_format}) is not supported:"
                         " nlosjax reads time-domain confocal captures (T_Sx_Sy or T_Si)")
      if "H" not in f or not isinstance(f["H"], h5py.Dataset) or f["H"].shape is None:
        raise ValueError(f"{path}: TAL capture without an impulse response H (fields {sorted(f)})")
      ds = f["H"]
      axes = 3 if h_format == "T_Sx_Sy" else 2
      if ds.ndim != axes or ds.dtype.kind not in "uif":
        raise ValueError(
            f"{path}: TAL H must be a real {'[T, Sx, Sy]' if axes == 3 else '[T, Si]'} array for H_format"
            f" {h_format}, got shape {ds.shape} dtype {ds.dtype} (complex data or extra axes, such as a"
            " polarized render's Stokes axis, are not supported)")
      sensor, _ = _points(path, f, "sensor_grid_xyz")
      laser, _ = _points(path, f, "laser_grid_xyz")
      if sensor is None or laser is None:
        raise ValueError(f"{path}: TAL capture without sensor_grid_xyz or laser_grid_xyz: the scan points"
                         " and whether the capture is confocal are unknown")
      scan_points = int(np.prod(ds.shape[1:]))
      if len(sensor) != scan_points:
        raise ValueError(f"{path}: TAL sensor_grid_xyz holds {len(sensor)} points but H {ds.shape} has"
                         f" {scan_points} ({h_format})")
      if len(laser) == 1 and scan_points > 1:
        raise ValueError(f"{path}: single-laser-point TAL capture (one laser point, {scan_points} sensor"
                         " points) is not supported: nlosjax reads confocal captures only")
      if laser.shape != sensor.shape or not np.allclose(laser, sensor):
        raise ValueError(f"{path}: non-confocal TAL capture: its {len(laser)} laser points are not its"
                         f" {len(sensor)} sensor points; nlosjax reads confocal captures only")
      delta_t = _scalar(path, f, "delta_t")
      t_start = _scalar(path, f, "t_start")
      accounts = _scalar(path, f, "t_accounts_first_and_last_bounces")
      laser_xyz, sensor_xyz = _dataset(f, "laser_xyz"), _dataset(f, "sensor_xyz")
      try:
        raw = ds[()]
      except (OSError, RuntimeError) as exc:
        raise ValueError(f"{path}: reading TAL H failed (the file is damaged: {' '.join(str(exc).split())});"
                         f" {DAMAGED_INPUT}") from None
  except (OSError, KeyError, RuntimeError) as exc:
    raise ValueError(f"{path}: reading it failed (the file is damaged: {' '.join(str(exc).split())});"
                     f" {DAMAGED_INPUT}") from None
  if delta_t is None or not np.isfinite(float(delta_t)) or float(delta_t) <= 0:
    raise ValueError(f"{path}: TAL delta_t (bin width, metres of path) must be a finite positive number,"
                     f" got {delta_t!r}")
  delta_t = float(delta_t)
  t_start = 0.0 if t_start is None else float(t_start)
  if not math.isfinite(t_start):
    raise ValueError(f"{path}: TAL t_start must be finite, got {t_start!r}")
  _check_counts(path, "H", raw)
  rows, cols, grid, wall_size = _scan_grid(path, sensor)
  # Path length from the wall at the start of each point's bin 0, then a whole-bin shift per point.
  start = np.full(len(sensor), t_start)
  if accounts is not None and bool(accounts):
    legs = []
    for name, origin, points in (("laser_xyz", laser_xyz, laser), ("sensor_xyz", sensor_xyz, sensor)):
      origin = None if origin is None else np.asarray(origin, np.float64).ravel()
      if origin is None or origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise ValueError(f"{path}: TAL t_accounts_first_and_last_bounces is true but {name} (a 3D position)"
                         f" is {'missing' if origin is None else f'shape {origin.shape}'}; the legs to the"
                         " wall cannot be removed")
      legs.append(np.linalg.norm(points - origin, axis=1))
    start = start - legs[0] - legs[1]
  shift = np.floor(start / delta_t + 0.5).astype(np.int64)
  raw_bins = raw.shape[0]
  histograms = raw.reshape(raw_bins, -1)
  total = int(np.max(raw_bins + shift))
  if total < 2:
    raise ValueError(f"{path}: every recorded TAL bin lies before light reaches the wall (t_start"
                     f" {t_start:.6g} m, {raw_bins} bins of {delta_t:.6g} m)")
  counts = np.zeros((total,) + grid, np.float64)
  for s in np.unique(shift):                 # the points sharing one shift, moved together
    points = np.flatnonzero(shift == s)
    src, dst = max(0, -int(s)), max(0, int(s))
    count = min(raw_bins - src, total - dst)
    if count > 0:
      counts[dst:dst + count, rows[points], cols[points]] = histograms[src:src + count, points]
  zero_bins, bin_factor, num_bins = _time_plan(path, total, zero_bins, bin_factor, num_bins)
  counts = np.moveaxis(_bin_time(np.moveaxis(counts, 0, -1), zero_bins, bin_factor, num_bins), -1, 0)
  setup = _make_setup(path, wall_size=wall_size, grid=grid, bin_width=delta_t / SPEED_OF_LIGHT * bin_factor,
                      num_bins=num_bins)
  return counts, setup


def _accepts_tal(path: Path) -> bool:
  names = _variables(path)[1]
  return "H" in names and "delta_t" in names


# ------------------------------------------------------------------ writing

def _delta_t(bin_width: float) -> float:
  """``c * bin_width`` (metres), the float64 neighbour that divides back to exactly ``bin_width`` where one does."""
  candidate = bin_width * SPEED_OF_LIGHT
  for step in range(4):
    for value in (candidate, np.nextafter(candidate, np.inf), np.nextafter(candidate, -np.inf)):
      if value / SPEED_OF_LIGHT == bin_width:
        return float(value)
    candidate = np.nextafter(candidate, np.inf if step % 2 else -np.inf)
  return float(bin_width * SPEED_OF_LIGHT)


def _tal_enum(f: h5py.File, key: str, names: dict, name: str) -> None:
  """An enum field as TAL writes it: a one-element HDF5 enum dataset of int32."""
  dt = h5py.enum_dtype({n: v for v, n in names.items()}, basetype="i4")
  ds = f.create_dataset(key, (1,), dtype=dt)
  ds[0] = next(v for v, n in names.items() if n == name)


def save_tal(path, transient, setup: Setup, *, layout: str = "T_Sx_Sy", laser_xyz=None, sensor_xyz=None,
             overwrite: bool = False) -> Path:
  """Write a confocal capture as a TAL HDF5 file (y-tal's ``tal.io.read_capture`` opens it).

  The scan points are nlosjax's grid, on TAL's relay wall ``z = 0``: point
  ``(row r, column c)`` at ``(x, y, z) = (setup.scan_x[c], setup.scan_y[r],
  0)`` metres (float64), normals ``(0, 0, 1)``, the laser points equal to
  them (confocal). Fields written (module docstring): ``H`` float32 (gzip);
  ``layout="T_Sx_Sy"`` (default): ``H [T, W, H]`` = ``transient[t, r, c]``
  at ``H[t, c, r]``, grids ``X_Y_3 [W, H, 3]``; ``layout="T_Si"``: ``H [T, W
  * H]`` (point ``c * H + r``), grids ``N_3 [W * H, 3]``; ``delta_t`` = ``c *
  bin_width`` (metres; the float64 that reads back as exactly ``bin_width``);
  ``t_start = 0``; ``t_accounts_first_and_last_bounces = false`` (``t = 0``
  when light reaches the wall, as in nlosjax); ``laser_xyz`` and
  ``sensor_xyz`` as given, else ``(0, 0, 0)`` (TAL's reconstructions read
  these fields even where, as here, the legs to the wall are not in the
  times, and fail on an unset one); ``volume_format`` unset (empty, as TAL
  writes an unknown field); ``scene_info`` a YAML (JSON) mapping naming the
  writer. A Setup's
  ``depth_range`` and ``aperture`` are not part of a TAL capture and are not
  written. :func:`~nlosjax.data.io.load_measurement` reads the file back as
  the same transient and Setup.

  The file is built in memory and written whole (a crash never leaves half a
  file; a refused call leaves an existing ``path`` as it was).

  Args:
    path: file to write.
    transient: ``[T, H, W]`` photon counts matching ``setup`` (one frame; TAL
      has no frame axis), finite and ``>= 0``.
    setup: the capture's geometry.
    layout: ``"T_Sx_Sy"`` or ``"T_Si"`` (:data:`TAL_LAYOUTS`).
    laser_xyz, sensor_xyz: the laser's and the SPAD's positions, metres, in
      the wall's frame above (recorded only: the times stay relative to the
      wall); default ``(0, 0, 0)``.
    overwrite: replace an existing ``path``.
  Returns:
    ``path`` as a :class:`~pathlib.Path`.
  Raises:
    FileExistsError: ``path`` exists and ``overwrite`` is False.
    ValueError: an unknown layout; a position that is not 3 finite numbers;
      a transient that is not ``[T, H, W]``, does not match ``setup``, or
      holds NaN, infinite or negative counts.
  """
  path = Path(path)
  if layout not in TAL_LAYOUTS:
    raise ValueError(f"layout must be one of {sorted(TAL_LAYOUTS)}, got {layout!r}")
  if path.exists() and not overwrite:
    raise FileExistsError(errno.EEXIST, f"{path} exists (pass overwrite=True to replace it)", str(path))
  transient = np.asarray(transient, np.float32)
  if transient.ndim != 3:
    raise ValueError(f"{path}: a TAL capture holds one [T, H, W] transient, got shape {transient.shape}"
                     " (save the frames of a video one file each)")
  setup.check_transient(transient)
  if not np.all(np.isfinite(transient)):
    raise ValueError(f"{path}: the transient holds {int(np.sum(~np.isfinite(transient)))} NaN or infinite"
                     " values; counts must be finite")
  if np.any(transient < 0):
    raise ValueError(f"{path}: the transient holds {int(np.sum(transient < 0))} negative values; photon"
                     " counts must be >= 0")
  origins = {}
  for name, value in (("laser_xyz", laser_xyz), ("sensor_xyz", sensor_xyz)):
    value = np.zeros(3) if value is None else np.asarray(value, np.float64)
    if value.shape != (3,) or not np.all(np.isfinite(value)):
      raise ValueError(f"{name} must be a finite (x, y, z) position in metres, got {value!r}")
    origins[name] = value
  height, width = setup.grid
  xyz = np.zeros((width, height, 3), np.float64)
  xyz[..., 0] = np.asarray(setup.scan_x, np.float64)[:, None]
  xyz[..., 1] = np.asarray(setup.scan_y, np.float64)[None, :]
  normals = np.zeros_like(xyz)
  normals[..., 2] = 1.0
  h = np.ascontiguousarray(transient.transpose(0, 2, 1))           # [T, W, H]: H[t, c, r]
  if layout == "T_Si":
    h, xyz, normals = h.reshape(setup.num_bins, -1), xyz.reshape(-1, 3), normals.reshape(-1, 3)
  grid_format = TAL_LAYOUTS[layout]
  scene_info = {"original_format": "nlosjax", "written_by": f"nlosjax {__version__} (nlosjax.data.io.save_tal)"}
  buf = io.BytesIO()
  with h5py.File(buf, "w") as f:
    f.create_dataset("H", data=h, compression="gzip", compression_opts=4, shuffle=True)
    _tal_enum(f, "H_format", TAL_H_FORMATS, layout)
    for role in ("sensor", "laser"):
      f[f"{role}_xyz"] = origins[f"{role}_xyz"]
      f[f"{role}_grid_xyz"] = xyz
      f[f"{role}_grid_normals"] = normals
      _tal_enum(f, f"{role}_grid_format", TAL_GRID_FORMATS, grid_format)
    f["volume_format"] = h5py.Empty("f8")
    f["delta_t"] = _delta_t(setup.bin_width)
    f["t_start"] = 0.0
    f["t_accounts_first_and_last_bounces"] = False
    f["scene_info"] = json.dumps(scene_info)        # JSON is YAML: TAL parses it with yaml.load
  files.write_bytes_atomic(path, buf.getvalue())
  return path


register_format(
    "tal", _read_tal, container="hdf5", accepts=_accepts_tal,
    summary="HDF5 TAL capture (y-tal's tal.io.read_capture layout): H [T, Sx, Sy] or [T, Si], confocal, on a"
            " regular planar grid, delta_t and t_start in metres of path")

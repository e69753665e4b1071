"""The capture geometry of a confocal NLOS scan: one frozen `Setup`.

Conventions (the public confocal datasets'; every module of nlosjax keeps them):

* The relay wall is the plane z = 0. Scan points lie on an ``H x W`` grid
  spanning ``[-wall_size/2, wall_size/2]`` in y (rows) and x (columns), as
  ``numpy.linspace`` does, so the spacing is ``wall_size / (H - 1)`` along y.
* ``t = 0`` is when light reaches the wall. Time bin ``k`` collects round-trip
  paths in ``[k, k + 1) * c * bin_width``.
* Volume depth bin ``k`` covers depths ``[k, k + 1) * c * bin_width / 2`` and
  its nominal depth is ``z_k = k * c * bin_width / 2``; so ``Z = T`` by
  default, and a scatterer at ``z_k`` straight in front of a scan point returns
  in time bin ``k``.
* Arrays: transient ``[..., T, H, W]``, volume ``[..., Z, H, W]``, image and
  depth map ``[..., H, W]``. The shape check cannot tell ``[T, H, W]`` from
  ``[H, W, T]`` when ``T = H = W``; the rule is that a cube is read as
  ``[T, H, W]``, with a :class:`LayoutWarning` saying so.
* Units: seconds and metres. A ``bin_width`` outside 1 ps-1 ns or a
  ``wall_size`` outside 5 cm-20 m is accepted with a :class:`UnitWarning`
  (a bin width above 1 us is refused: picoseconds passed as seconds).

A ``depth_range = (z_min, z_max)`` (metres) restricts reconstructions to the
depth bins ``k`` with ``z_min <= z_k <= z_max`` and the time bins that can hold
returns from them (see :attr:`Setup.time_bins`): cost follows the scene.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np

SPEED_OF_LIGHT = 299_792_458.0  # m/s

_EPS = 1e-9  # tolerance, in bins, for rounding depth-range ends onto the grid
#: Bin widths (s) and wall sizes (m) of real confocal captures; a Setup outside warns.
BIN_WIDTH_PLAUSIBLE = (1e-12, 1e-9)
WALL_SIZE_PLAUSIBLE = (0.05, 20.0)


class UnitWarning(UserWarning):
  """A Setup value far outside what captures have: probably a unit slip (ps for s, cm for m)."""


class LayoutWarning(UserWarning):
  """A cube-shaped transient (``T = H = W``): its shape cannot show that it is ``[T, H, W]``."""


@dataclasses.dataclass(frozen=True)
class Setup:
  """A confocal capture: wall, scan grid, time bins, optional depth range.

  Attributes:
    wall_size: side of the square scanned area on the wall, metres.
    grid: ``(H, W)`` number of scan points along y (rows) and x (columns).
    bin_width: duration of one time bin, seconds (e.g. ``32e-12``).
    num_bins: ``T``, number of time bins per histogram.
    depth_range: optional ``(z_min, z_max)`` in metres, ``0 <= z_min < z_max``;
      reconstructions return only the depth bins inside it.
    aperture: optional lateral reach of reconstructions, metres: returns from
      voxels more than ``aperture`` away (laterally) from a scan point are
      not modelled (the light cone is cut at that radius), so a gated window
      ends at ``hypot(z_max, aperture)`` instead of one wall diagonal away
      and cost follows the depth range. ``None``: the whole wall. The forward
      model (``render``) always uses the whole cone.

  Raises:
    ValueError: on a non-positive size, a grid with fewer than 2 points per
      axis, or a depth range outside ``[0, max_depth]`` or holding no bin.
  """

  wall_size: float
  grid: tuple[int, int]
  bin_width: float
  num_bins: int
  depth_range: tuple[float, float] | None = None
  aperture: float | None = None

  def __post_init__(self):
    def positive_number(name, value):
      if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        raise ValueError(f"Setup.{name} must be a number, got {value!r}")
      if not math.isfinite(value) or value <= 0:
        raise ValueError(f"Setup.{name} must be finite and > 0, got {value!r}")
      return float(value)

    object.__setattr__(self, "wall_size", positive_number("wall_size", self.wall_size))
    object.__setattr__(self, "bin_width", positive_number("bin_width", self.bin_width))
    if self.bin_width > 1e-6:
      raise ValueError(
          f"Setup.bin_width is in seconds and should be ~1e-12..1e-9, got {self.bin_width!r}"
          " (did you pass picoseconds?)")
    if not BIN_WIDTH_PLAUSIBLE[0] <= self.bin_width <= BIN_WIDTH_PLAUSIBLE[1]:
      warnings.warn(
          f"Setup.bin_width = {self.bin_width!r} s is outside the {BIN_WIDTH_PLAUSIBLE[0]:g}-"
          f"{BIN_WIDTH_PLAUSIBLE[1]:g} s of SPAD captures ({self.bin_width * 1e12:.4g} ps); check"
          " the unit (seconds)", UnitWarning, stacklevel=3)
    if not WALL_SIZE_PLAUSIBLE[0] <= self.wall_size <= WALL_SIZE_PLAUSIBLE[1]:
      warnings.warn(
          f"Setup.wall_size = {self.wall_size!r} m is outside the {WALL_SIZE_PLAUSIBLE[0]:g}-"
          f"{WALL_SIZE_PLAUSIBLE[1]:g} m of NLOS scans; check the unit (metres, the whole side)",
          UnitWarning, stacklevel=3)

    grid = self.grid
    if isinstance(grid, (int, np.integer)) and not isinstance(grid, bool):
      grid = (grid, grid)
    if (not isinstance(grid, (tuple, list)) or len(grid) != 2
        or any(isinstance(g, bool) or not isinstance(g, (int, np.integer)) or g < 2 for g in grid)):
      raise ValueError(f"Setup.grid must be two integers >= 2 (H, W), got {self.grid!r}")
    grid = (int(grid[0]), int(grid[1]))
    object.__setattr__(self, "grid", grid)

    if isinstance(self.num_bins, bool) or int(self.num_bins) != self.num_bins or self.num_bins < 2:
      raise ValueError(f"Setup.num_bins must be an integer >= 2, got {self.num_bins!r}")
    object.__setattr__(self, "num_bins", int(self.num_bins))

    if self.aperture is not None:
      object.__setattr__(self, "aperture", positive_number("aperture", self.aperture))
    if self.depth_range is not None:
      try:
        z_min, z_max = (float(v) for v in self.depth_range)
      except (TypeError, ValueError):
        raise ValueError(
            f"Setup.depth_range must be (z_min, z_max) in metres, got {self.depth_range!r}") from None
      if not (math.isfinite(z_min) and math.isfinite(z_max)):
        raise ValueError(f"Setup.depth_range must be finite, got {self.depth_range!r}")
      if not 0.0 <= z_min < z_max:
        raise ValueError(f"Setup.depth_range needs 0 <= z_min < z_max, got {self.depth_range!r}")
      if z_min >= self.max_depth:
        raise ValueError(
            f"Setup.depth_range starts at {z_min} m, beyond the maximum depth"
            f" {self.max_depth:.4f} m of {self.num_bins} bins of {self.bin_width} s")
      object.__setattr__(self, "depth_range", (z_min, z_max))
      k0, k1 = self.depth_bins
      if k1 <= k0:
        raise ValueError(
            f"Setup.depth_range {self.depth_range} holds no depth bin (bins are"
            f" {self.depth_bin_length:.4g} m apart)")

  def __repr__(self) -> str:
    # ``aperture`` only when set: the repr of an aperture-free Setup is unchanged
    # (checkpoint signatures embed it).
    items = [f"{f.name}={getattr(self, f.name)!r}" for f in dataclasses.fields(self)
             if f.name != "aperture" or self.aperture is not None]
    return f"Setup({', '.join(items)})"

  # ---------------------------------------------------------------- geometry
  @property
  def height(self) -> int:
    """``H``, scan points along y (rows)."""
    return self.grid[0]

  @property
  def width(self) -> int:
    """``W``, scan points along x (columns)."""
    return self.grid[1]

  @property
  def bin_length(self) -> float:
    """Round-trip path length of one time bin, metres (``c * bin_width``)."""
    return SPEED_OF_LIGHT * self.bin_width

  @property
  def depth_bin_length(self) -> float:
    """Depth spanned by one volume bin, metres (``c * bin_width / 2``)."""
    return 0.5 * self.bin_length

  @property
  def max_depth(self) -> float:
    """Largest depth the histogram can see straight ahead, metres (``T * c * dt / 2``)."""
    return self.num_bins * self.depth_bin_length

  @property
  def spacing(self) -> tuple[float, float]:
    """``(dy, dx)``: distance between neighbouring scan points, metres."""
    return (self.wall_size / (self.height - 1), self.wall_size / (self.width - 1))

  @property
  def scan_y(self) -> np.ndarray:
    """``[H]`` float64 y coordinate of each scan row, metres."""
    return np.linspace(-self.wall_size / 2, self.wall_size / 2, self.height)

  @property
  def scan_x(self) -> np.ndarray:
    """``[W]`` float64 x coordinate of each scan column, metres."""
    return np.linspace(-self.wall_size / 2, self.wall_size / 2, self.width)

  @property
  def scan_points(self) -> np.ndarray:
    """``[H, W, 3]`` float64 (x, y, 0) position of each scan point, metres."""
    y, x = np.meshgrid(self.scan_y, self.scan_x, indexing="ij")
    return np.stack([x, y, np.zeros_like(x)], axis=-1)

  @property
  def max_lateral_offset(self) -> float:
    """Largest lateral distance between a scan point and a voxel column that is modelled, metres.

    One wall diagonal (``sqrt(2) wall_size``), or the ``aperture`` if smaller.
    """
    diagonal = self.wall_size * math.sqrt(2.0)
    return diagonal if self.aperture is None else min(diagonal, self.aperture)

  # ------------------------------------------------------------ depth gating
  @property
  def depth_bins(self) -> tuple[int, int]:
    """``(k0, k1)``: the volume holds depth bins ``k0 <= k < k1``.

    ``(0, T)`` without a depth range; otherwise the bins with nominal depth
    ``z_k = k * depth_bin_length`` inside ``[z_min, z_max]``.
    """
    if self.depth_range is None:
      return (0, self.num_bins)
    z_min, z_max = self.depth_range
    k0 = math.ceil(z_min / self.depth_bin_length - _EPS)
    k1 = min(self.num_bins, math.floor(z_max / self.depth_bin_length + _EPS) + 1)
    return (k0, k1)

  @property
  def num_depth_bins(self) -> int:
    """``Z``, depth bins in the reconstructed volume."""
    k0, k1 = self.depth_bins
    return k1 - k0

  @property
  def depths(self) -> np.ndarray:
    """``[Z]`` float64 nominal depth of each volume bin, metres."""
    k0, k1 = self.depth_bins
    return np.arange(k0, k1) * self.depth_bin_length

  @property
  def time_bins(self) -> tuple[int, int]:
    """``(t0, t1)``: time bins that can hold returns from the depth range.

    The earliest return from ``z >= z_min`` is straight ahead (bin ``k0``);
    the latest from ``z <= z_max`` comes from a voxel one wall diagonal (or
    the ``aperture``) away, round-trip ``2 * hypot(z_max, max_lateral_offset)``.
    ``(0, T)`` without a depth range.
    """
    if self.depth_range is None:
      return (0, self.num_bins)
    k0, k1 = self.depth_bins
    z_last = (k1 - 1) * self.depth_bin_length
    r_last = math.hypot(z_last, self.max_lateral_offset)
    t1 = min(self.num_bins, math.floor(r_last / self.depth_bin_length) + 2)
    return (k0, t1)

  def ungated(self) -> "Setup":
    """The same capture without a depth range."""
    return dataclasses.replace(self, depth_range=None)

  def with_depth_range(self, z_min: float, z_max: float) -> "Setup":
    """The same capture restricted to depths ``[z_min, z_max]`` metres."""
    return dataclasses.replace(self, depth_range=(z_min, z_max))

  def with_aperture(self, aperture: float | None) -> "Setup":
    """The same capture with reconstructions limited to a lateral reach of ``aperture`` metres."""
    return dataclasses.replace(self, aperture=aperture)

  def check_transient(self, transient, name: str = "transient") -> None:
    """Raise ``ValueError`` unless ``transient`` is ``[..., T, H, W]`` for this Setup."""
    shape = tuple(getattr(transient, "shape", ()))
    if len(shape) < 3:
      raise ValueError(
          f"{name} must be [..., T, H, W] with (T, H, W) = {(self.num_bins, *self.grid)},"
          f" got rank {len(shape)} shape {shape}")
    if shape[-3:] != (self.num_bins, *self.grid):
      raise ValueError(
          f"{name} shape {shape} does not match the Setup: expected [..., T, H, W] ="
          f" [..., {self.num_bins}, {self.height}, {self.width}]")
    if self.num_bins == self.height == self.width:
      # The rule: nlosjax's layout is always [..., T, H, W] (time before the scan grid); a
      # cube passes as that, so an [H, W, T] array would be read with its axes swapped.
      warnings.warn(
          f"{name} is a cube ({self.num_bins} bins on a {self.height} x {self.width} grid): its"
          " shape cannot show the layout, so it is read as [..., T, H, W]; an [H, W, T] array"
          " needs np.moveaxis(x, -1, -3) first", LayoutWarning, stacklevel=3)

  def check_volume(self, volume, name: str = "volume") -> None:
    """Raise ``ValueError`` unless ``volume`` is ``[..., Z, H, W]`` for this Setup."""
    shape = tuple(getattr(volume, "shape", ()))
    expected = (self.num_depth_bins, *self.grid)
    if len(shape) < 3 or shape[-3:] != expected:
      raise ValueError(
          f"{name} shape {shape} does not match the Setup: expected [..., Z, H, W] ="
          f" [..., {expected[0]}, {expected[1]}, {expected[2]}]"
          + (f" (Z = depth bins in depth_range {self.depth_range})" if self.depth_range else ""))

"""Confocal transients of sampled hidden surfaces: exact paths, cosines, falloff, visibility.

The fast renderer (:func:`nlosjax.physics.render`) is the light-cone
operator that LCT inverts: voxels seen orthographically, ``r^-4`` without
cosines, every voxel visible from every scan point. This module is the
renderer that is *not* that operator, for training data with the mismatch a
real capture has. The hidden scene is a set of small surface patches
(:class:`SurfaceSamples`: position, unit normal, area, albedo, material);
for every scan point ``s`` on the wall and every patch ``p``, with ``v = p -
s``, ``r = |v|``, ``cos_p = n . (s - p) / r`` (the patch's Lambertian cosine
toward ``s``) and ``cos_w = v_z / r`` (the wall's):

* the out leg (the laser spot, a Lambertian point on the wall, lighting the
  patch) gives ``cos_w * cos_p / r^2``;
* a **diffuse** patch's way back is the same factor again (a Lambertian patch
  seen from the wall spot): ``albedo * area * cos_p^2 * cos_w^2 / r^4``;
* a **retroreflective** patch sends its light straight back to the spot (no
  second spread): ``albedo * area * cos_p * cos_w / r^2``;

divided by the wall's pixel area ``dy * dx``, so a fronto-parallel diffuse
patch straight in front of a scan point has the units of
:func:`~nlosjax.physics.render` for an albedo volume (m^-4 per unit albedo).
The return lands at round-trip path ``2 r``, in time bin ``floor(2 r /
bin_length)`` (bin ``k`` holds ``[k, k + 1) * bin_length``). Patches smaller
than a bin (:func:`default_spacing`) make each bin the integral of the
surface's returns over the bin's time interval (sub-bin integration), rather
than a sample at the bin's centre.

**Visibility** is per scan point: a patch contributes only if it faces ``s``
(``cos_p > 0``; two-sided patches use ``|cos_p|``) and nothing nearer lies on
the ray from ``s`` to it. Nearness is tested with a z-buffer per scan point
over gnomonic directions ``(v_x / v_z, v_y / v_z)``: cells of ``cell`` (in
gnomonic units), each holding the smallest ``r`` of the facing patches that
fall in it; a patch is hidden when the minimum over the 2 x 2 cells around
its position (so that gaps between an occluder's samples do not leak) lies
more than its tolerance in front of it (two patch spacings plus the range its
own surface spans across two cells at its tilt). Patches of one convex object never
hide each other beyond back-facing, so what the z-buffer decides is
occlusion between objects and within non-convex ones (a torus). Its error is
confined to about half a cell around an occluder's silhouette: measured
against exact ray-segment intersection for a plate half hiding another, 0.5 %
of the signal (L1) where ignoring occlusion is 9 % off (``tests/test_transport.py``).

Cost: ``O(H W P)`` per frame (``P`` patches), in chunks of scan points under
``jit``; see ``benchmarks/results/data.md``. ``tests/test_transport.py``
holds the slow reference: the same model as an explicit loop, with exact
visibility by ray-segment intersection.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.physics.setup import Setup

__all__ = ["SurfaceSamples", "default_spacing", "render_surfaces"]

_MIN_COS = 1e-3      # a patch seen more grazingly than this is treated as not facing
_MAX_CELLS = 512     # z-buffer cells per axis at most (the cell grows to fit)
_CELL_BUCKET = 128   # cells per axis are rounded up to a multiple of this (fewer compiles)
_PATCH_BUCKET = 2048  # patches are padded to 2048 * 2^k or 3072 * 2^k (fewer compiles)
# Each distinct (patches, cells) pair compiles the renderer anew (~0.3 s on an EPYC, longer
# on a slower CPU). Rounding cells to multiples of 128 (was 32) and patches to 2048 * 2^k or
# 3072 * 2^k (was multiples of 2048): the cpu preset's first 12 sequences compile 16 programs
# instead of 39, in 36.3 s instead of 38.1 s on 2 quiet EPYC cores (simulate_sequence of
# train sequences 0-11, one process, compiles included; powers of two for the cells compiled 7 programs but took
# 43.8 s: the per-scan-point z-buffer grows with the cells). The padding changes nothing
# computed: the cell size is an argument (the grid only has more empty cells), and padded
# patches face away and carry no light.


def _padded_patches(n: int) -> int:
  """The bucket ``n`` patches are padded to: the smallest ``2048 * 2^k`` or ``3072 * 2^k`` >= n."""
  size = _PATCH_BUCKET
  while True:
    for candidate in (size, size * 3 // 2):
      if candidate >= n:
        return candidate
    size *= 2


def _padded_cells(n: int) -> int:
  """Cells per axis for ``n`` needed: ``n`` rounded up to a multiple of ``_CELL_BUCKET``."""
  return -(-max(int(n), 1) // _CELL_BUCKET) * _CELL_BUCKET


@dataclasses.dataclass(frozen=True)
class SurfaceSamples:
  """Small patches of hidden surfaces (NumPy arrays, float64 unless said).

  Attributes:
    points: ``[P, 3]`` patch centres (x, y, z) in metres, ``z > 0``.
    normals: ``[P, 3]`` unit normals (outward for solids).
    area: ``[P]`` patch areas, m^2.
    albedo: ``[P]`` albedo in ``[0, 1]``.
    retroreflective: ``[P]`` bool, the patch's material (False: diffuse).
    two_sided: ``[P]`` bool: a thin sheet seen from either side (planar
      cut-outs); False: only the side the normal points to reflects.
    object_id: ``[P]`` int, which object a patch belongs to (bookkeeping).
  """

  points: np.ndarray
  normals: np.ndarray
  area: np.ndarray
  albedo: np.ndarray
  retroreflective: np.ndarray
  two_sided: np.ndarray
  object_id: np.ndarray

  def __post_init__(self):
    pts = np.asarray(self.points, np.float64).reshape(-1, 3)
    P = pts.shape[0]
    nrm = np.asarray(self.normals, np.float64).reshape(-1, 3)
    fields = {"points": pts, "normals": nrm}
    for name, dtype in (("area", np.float64), ("albedo", np.float64), ("retroreflective", bool),
                        ("two_sided", bool), ("object_id", np.int64)):
      fields[name] = np.broadcast_to(np.asarray(getattr(self, name), dtype), (P,)).copy()
    if nrm.shape[0] != P:
      raise ValueError(f"normals must be [P={P}, 3], got {np.shape(self.normals)}")
    for name in ("points", "normals", "area", "albedo"):
      if not np.all(np.isfinite(fields[name])):
        raise ValueError(f"SurfaceSamples.{name} must be finite")
    if P and np.any(pts[:, 2] <= 0):
      raise ValueError("SurfaceSamples.points must lie in front of the wall (z > 0)")
    if np.any(fields["area"] < 0) or np.any(fields["albedo"] < 0):
      raise ValueError("SurfaceSamples.area and albedo must be >= 0")
    norm = np.linalg.norm(nrm, axis=1)
    if P and np.any(np.abs(norm - 1) > 1e-6):
      raise ValueError("SurfaceSamples.normals must be unit vectors")
    for name, value in fields.items():
      object.__setattr__(self, name, value)

  def __len__(self) -> int:
    return self.points.shape[0]

  @classmethod
  def concatenate(cls, parts) -> "SurfaceSamples":
    """One set from several (e.g. one per object)."""
    parts = list(parts)
    if not parts:
      return cls(np.zeros((0, 3)), np.zeros((0, 3)), [], [], [], [], [])
    return cls(*[np.concatenate([getattr(p, f.name) for p in parts])
                 for f in dataclasses.fields(cls)])

  def moved(self, rotation, origin, to) -> "SurfaceSamples":
    """The patches turned by ``rotation`` ``[3, 3]`` about ``origin`` ``[3]``, which moves to ``to``."""
    R = np.asarray(rotation, np.float64)
    pts = (self.points - np.asarray(origin, np.float64)) @ R.T + np.asarray(to, np.float64)
    return dataclasses.replace(self, points=pts, normals=self.normals @ R.T)


def default_spacing(setup: Setup) -> float:
  """Patch side (metres) fine enough for :func:`render_surfaces` on ``setup``.

  Half a depth bin (so a patch's returns span at most one time bin even when
  tilted 60 degrees) and at most a quarter of the scan spacing.
  """
  return float(min(setup.depth_bin_length / 2, min(setup.spacing) / 4))


def _gnomonic_grid(points: np.ndarray, scan: np.ndarray, cell: float):
  """(origin [2], cell, cells per axis [2]) of the z-buffers.

  The cell lattice (origin and cell) covers every direction from every scan
  point to every patch, as one grid would; each scan point's z-buffer is the
  window of it that its own directions span, ``cells`` per axis. A direction's
  coordinate ``(p - s) / p_z`` is linear in the scan point ``s`` for each
  patch, so the span over the patches (a maximum of linear functions less a
  minimum) is convex in ``s`` and largest at an extreme scan point: the
  window is sized there.
  """
  z = points[:, 2]
  lo = np.array([np.min((points[:, k] - scan[:, k].max()) / z) for k in (0, 1)])
  hi = np.array([np.max((points[:, k] - scan[:, k].min()) / z) for k in (0, 1)])
  span = hi - lo
  cell = max(cell, float(span.max()) / (_MAX_CELLS - 3))
  own = np.array([max(np.ptp((points[:, k] - s) / z) for s in (scan[:, k].min(), scan[:, k].max()))
                  for k in (0, 1)])
  n = np.ceil(own / cell).astype(int) + 2            # +1 for the cells' alignment, +1 to spare
  return lo, cell, (_padded_cells(n[0]), _padded_cells(n[1]))


def _cell_index(fl, facing, n):
  """``[P]`` int32 z-buffer cell ``1..n`` along one axis from floored cell coordinates ``fl``.

  Counted from the first cell a facing patch falls in (0 where none faces), clipped to the
  window of ``n`` cells.
  """
  first = jnp.min(jnp.where(facing, fl, jnp.inf))
  first = jnp.where(jnp.isfinite(first), first, 0.0)
  return jnp.clip((fl - first).astype(jnp.int32), 0, n - 1) + 1


@functools.partial(jax.jit, static_argnames=("num_bins", "cells", "occlusion", "wall_cosine",
                                             "general"))
def _render_chunk(scan, s, origin, cell, bin_length, pixel_area, spacing, *, num_bins, cells,
                  occlusion, wall_cosine, general=False):
  """Histograms ``[S, T]`` for scan points ``scan`` ``[S, 3]`` (one chunk).

  ``general``: the material of each patch is ``s["power"]`` (falloff ``p``) and
  ``s["kappa"]`` (cosine power ``kappa``): ``(cos_w cos_p)^(kappa p / 2) / r^p``.
  """
  nx, ny = cells
  # Patches as one array per coordinate ([P] each, not [P, 3]): XLA:CPU vectorises the
  # per-patch arithmetic over P this way, 2-5x faster than reducing over an axis of 3.
  px, py, pz = s["points"].T
  mx, my, mz = s["normals"].T

  def one(sp):
    vx, vy, vz = px - sp[0], py - sp[1], pz - sp[2]          # v = p - s, [P] each
    r = jnp.sqrt(jnp.maximum(vx * vx + vy * vy + vz * vz, 1e-12))
    cos_p = -(vx * mx + vy * my + vz * mz) / r
    cos_p = jnp.where(s["two_sided"], jnp.abs(cos_p), cos_p)
    facing = cos_p > _MIN_COS
    cos_p = jnp.where(facing, cos_p, 0.0)
    cw = vz / r if wall_cosine else 1.0
    if general:   # out leg (cw cos_p)^kappa / r^2, back leg the same to the power (p - 2) / 2
      p = s["power"]
      w = jnp.where(facing, s["scale"] * jnp.power(jnp.maximum(cw * cos_p, 1e-12), 0.5 * s["kappa"] * p)
                    * jnp.power(r, -p) / pixel_area, 0.0)
    else:
      out_leg = cw * cos_p / (r * r)              # the wall spot's light reaching the patch
      back_leg = jnp.where(s["retro"], 1.0, cw * cos_p / (r * r))
      w = s["scale"] * out_leg * back_leg / pixel_area
    if occlusion:
      # Cells 1..n of a grid with a border of one empty cell. A patch is compared with the
      # nearest r in the 2 x 2 cells around its own position (its cell and the neighbours on
      # the side of the cell it lies nearer to), so gaps between an occluder's samples do not
      # leak while the occluder's silhouette grows by half a cell on average.
      # The lattice's cells, numbered from the first one this scan point's facing patches
      # fall in: the same cells as one grid over every direction, in a window of its own.
      cx = (vx / vz - origin[0]) / cell                       # gnomonic direction, in cells
      cy = (vy / vz - origin[1]) / cell
      fx, fy = jnp.floor(cx), jnp.floor(cy)
      ix = _cell_index(fx, facing, nx)
      iy = _cell_index(fy, facing, ny)
      sx = jnp.where(cx - fx < 0.5, -1, 1)
      sy = jnp.where(cy - fy < 0.5, -1, 1)
      stride = ny + 2
      flat = ix * stride + iy
      zbuf = jnp.full(((nx + 2) * stride,), jnp.inf, r.dtype).at[flat].min(
          jnp.where(facing, r, jnp.inf))
      near = jnp.minimum(jnp.minimum(zbuf[flat], zbuf[flat + sx * stride]),
                         jnp.minimum(zbuf[flat + sy], zbuf[flat + sx * stride + sy]))
      # The range a patch's own surface spans over two cells at its tilt, plus two spacings.
      cos_a = vz / r                                         # angle off the wall normal
      width = 2.0 * cell * cos_a * cos_a * r                 # gnomonic cells -> metres across
      tan_p = jnp.sqrt(jnp.maximum(1.0 - cos_p * cos_p, 0.0)) / jnp.maximum(cos_p, 0.1)
      tol = 2.0 * spacing + jnp.minimum(width * tan_p, 0.1)
      w = jnp.where(near >= r - tol, w, 0.0)
    k = jnp.floor(2.0 * r / bin_length).astype(jnp.int32)
    k = jnp.where(k < num_bins, k, num_bins)                 # beyond the last bin: dropped
    return jnp.zeros((num_bins + 1,), w.dtype).at[k].add(w)[:num_bins]

  return jax.vmap(one)(scan)


def render_surfaces(samples: SurfaceSamples, setup: Setup, *, occlusion: bool = True,
                    wall_cosine: bool = True, cell: float | None = None,
                    spacing: float | None = None, chunk: int = 16,
                    falloff_power=None, cosine_power: float | None = None) -> np.ndarray:
  """Noise-free confocal transient of surface patches (module docstring for the model).

  Args:
    samples: the hidden surfaces.
    setup: the capture (its grid, wall and bins; a depth range is ignored).
    occlusion: test visibility per scan point (False: every facing patch
      counts, as if alone).
    wall_cosine: include the relay wall's ``cos_w`` factors.
    falloff_power, cosine_power: a material model other than diffuse or
      retroreflective (both ``None``: ``samples.retroreflective`` decides).
      With either given, a patch returns ``albedo * area * (cos_w cos_p)^(kappa
      p / 2) / r^p`` per wall pixel area: ``falloff_power`` ``p`` per patch
      (``[P]`` or a scalar, in ``[2, 4]``; default 2 for retroreflective
      patches, 4 for diffuse ones) and ``cosine_power`` ``kappa >= 0`` (default
      1; 0: no cosines, an isotropic point scatterer that still only lights
      its facing side). ``p = 4, kappa = 1`` is the diffuse patch and ``p =
      2, kappa = 1`` the retroreflective one.
    cell: z-buffer cell in gnomonic units (default: 3/4 of the patch spacing
      over the nearest patch's distance).
    spacing: patch side in metres used for the visibility tolerance (default:
      the square root of the median patch area).
    chunk: scan points per compiled call (memory ``~ chunk * P``).
  Returns:
    ``[T, H, W]`` float32 NumPy transient, units of :func:`nlosjax.physics.render`
    (m^-4 per unit albedo for diffuse patches, m^-2 for retroreflective ones).
  """
  if not isinstance(samples, SurfaceSamples):
    raise ValueError(f"samples must be SurfaceSamples, got {type(samples).__name__}")
  if not isinstance(setup, Setup):
    raise ValueError(f"setup must be a nlosjax.physics.Setup, got {type(setup).__name__}")
  H, W = setup.grid
  T = setup.num_bins
  general = falloff_power is not None or cosine_power is not None
  if general:
    default = np.where(samples.retroreflective, 2.0, 4.0)
    power = default if falloff_power is None else np.broadcast_to(
        np.asarray(falloff_power, np.float64), (len(samples),))
    kappa = 1.0 if cosine_power is None else float(cosine_power)
    if not np.all(np.isfinite(power)) or np.any(power < 2) or np.any(power > 4):
      raise ValueError(f"falloff_power must lie in [2, 4], got {falloff_power!r}")
    if not (math.isfinite(kappa) and kappa >= 0):
      raise ValueError(f"cosine_power must be a finite number >= 0, got {cosine_power!r}")
  if len(samples) == 0:
    return np.zeros((T, H, W), np.float32)
  # Drop patches that cannot return light: zero albedo or area, or one-sided and facing away
  # from every point of the scanned wall (n . (c - p) is linear in c: its maximum is at a corner).
  half = setup.wall_size / 2
  corners = np.array([[x, y, 0.0] for x in (-half, half) for y in (-half, half)])
  reach = np.max(corners @ samples.normals.T - np.sum(samples.normals * samples.points, axis=1), axis=0)
  keep = (samples.albedo * samples.area > 0) & (samples.two_sided | (reach > 0))
  pts = samples.points[keep]
  if spacing is None:
    spacing = float(np.sqrt(np.median(samples.area[keep]))) if keep.any() else 0.0
  if cell is None:
    # 3/4 of the nearest patches' angular spacing: finer cells let an occluder's gaps leak,
    # coarser ones grow its silhouette (both measured against exact visibility in the tests).
    cell = 0.75 * max(spacing, 1e-4) / float(np.min(np.linalg.norm(pts, axis=1)) if pts.size else 1.0)
  scan = setup.scan_points.reshape(-1, 3)
  origin, cell, cells = _gnomonic_grid(pts if pts.size else samples.points, scan, float(cell))
  # Pad to a bucket with patches that face away from the wall and carry nothing.
  fill = _padded_patches(pts.shape[0]) - pts.shape[0]
  def padded(x, value):
    return np.concatenate([x, np.broadcast_to(value, (fill,) + x.shape[1:])])
  s = {"points": jnp.asarray(padded(pts, [0.0, 0.0, 1.0]), jnp.float32),
       "normals": jnp.asarray(padded(samples.normals[keep], [0.0, 0.0, 1.0]), jnp.float32),
       "two_sided": jnp.asarray(padded(samples.two_sided[keep], False)),
       "retro": jnp.asarray(padded(samples.retroreflective[keep], False)),
       "scale": jnp.asarray(padded((samples.albedo * samples.area)[keep], 0.0), jnp.float32)}
  if general:
    s["power"] = jnp.asarray(padded(power[keep], 4.0), jnp.float32)
    s["kappa"] = jnp.float32(kappa)
  dy, dx = setup.spacing
  chunk = max(1, int(chunk))
  pad = (-scan.shape[0]) % chunk
  scan_p = np.concatenate([scan, np.repeat(scan[-1:], pad, 0)]).astype(np.float32)
  out = []
  for start in range(0, scan_p.shape[0], chunk):
    out.append(np.asarray(_render_chunk(
        jnp.asarray(scan_p[start:start + chunk]), s, jnp.asarray(origin, jnp.float32),
        jnp.float32(cell), jnp.float32(setup.bin_length), jnp.float32(dy * dx),
        jnp.float32(spacing), num_bins=T, cells=cells, occlusion=bool(occlusion),
        wall_cosine=bool(wall_cosine), general=general)))
  hist = np.concatenate(out)[: H * W]                          # [H W, T]
  return np.ascontiguousarray(hist.T.reshape(T, H, W)).astype(np.float32)

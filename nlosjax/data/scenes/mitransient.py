"""Confocal captures of planar hidden patches rendered by mitransient, in our convention.

mitransient (a transient path tracer on Mitsuba 3) is a renderer we did not
write: many bounces, any material. This module turns planar rectangular
patches in front of the relay wall (:class:`Patch`: centre, in-plane axes,
half sizes, albedo; :func:`patches_from_frame` tiles one frame of our scenes,
objects at their depths with their albedo) and a
:class:`~nlosjax.physics.Setup` into a mitransient confocal scene, renders it,
and converts its output to our ``[T, H, W]`` convention; :func:`detect` then
applies our detector model (:func:`nlosjax.physics.noise.add_spad_noise`:
photon scale, Poisson noise, jitter, ambient and dark counts).

Only :func:`render_raw` (and :func:`render`, which calls it) needs mitsuba and
mitransient (``pip install "nlosjax[render]"``, plus Debian's ``libllvm19``
for Mitsuba's LLVM backend); they are imported inside it, so this module
imports without them. :func:`scene_description` and :func:`to_transient` are
plain NumPy.

Conversions (checked against :func:`nlosjax.physics.transport.render_surfaces`
in ``tests/test_mitransient.py``):

* the relay wall is a Mitsuba ``rectangle`` at ``z = 0`` facing ``+z``; its
  film of ``W x H`` pixels measures at pixel centres, so the rectangle is
  ``wall_size * W / (W - 1)`` wide (and likewise tall) to put those centres
  exactly on our ``linspace`` scan grid;
* time: ``start_opl = 0``, ``bin_width_opl = setup.bin_length`` and the first
  and last (laser-to-wall, wall-to-sensor) legs left out, so bin ``k`` holds
  round-trip paths ``[k, k + 1) * bin_length`` from the wall spot, as ours;
* layout: mitransient returns ``(H, W, T, channels)`` (row = film y);
  :func:`to_transient` averages the channels and moves time first;
* the laser leg: the laser sits at ``laser_origin`` and is aimed at each scan
  point in turn, so each spot's irradiance carries ``cos / d^2`` from the
  laser; :func:`to_transient` divides it out (a confocal scanner's spot has
  constant power).

The absolute scale is mitransient's radiance, not the units of our renderers;
:func:`detect`'s ``photons_per_point`` sets the photon budget either way.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from nlosjax.physics.setup import Setup

DEFAULT_LASER_ORIGIN = (-1.0, 0.0, 0.25)
"""Where the laser and sensor sit (metres): beside the wall, in front of it."""

DEFAULT_VARIANT = "llvm_ad_rgb"


@dataclasses.dataclass(frozen=True)
class Patch:
  """A planar rectangular diffuse patch in front of the wall.

  Attributes:
    centre: ``[3]`` (x, y, z) metres, ``z > 0``.
    half_size: ``(a, b)`` half extents (metres) along ``axes[0]`` and ``axes[1]``.
    axes: ``[2, 3]`` orthonormal in-plane directions (default: x and y, a
      patch parallel to the wall).
    albedo: diffuse reflectance in ``[0, 1]``.
  """

  centre: tuple
  half_size: tuple
  axes: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
  albedo: float = 1.0

  def __post_init__(self):
    c = np.asarray(self.centre, np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)) or c[2] <= 0:
      raise ValueError(f"Patch.centre must be a finite (x, y, z) with z > 0, got {self.centre}")
    h = np.asarray(self.half_size, np.float64)
    if h.shape != (2,) or not np.all(h > 0):
      raise ValueError(f"Patch.half_size must be two positive lengths, got {self.half_size}")
    a = np.asarray(self.axes, np.float64)
    if a.shape != (2, 3) or not np.allclose(a @ a.T, np.eye(2), atol=1e-6):
      raise ValueError(f"Patch.axes must be two orthonormal 3-vectors, got {self.axes}")
    if not 0.0 <= float(self.albedo) <= 1.0:
      raise ValueError(f"Patch.albedo must be in [0, 1], got {self.albedo}")

  def to_world(self) -> np.ndarray:
    """``[4, 4]`` map of Mitsuba's unit rectangle ([-1, 1]^2 at z = 0) onto the patch.

    The rectangle's normal (local +z) is turned toward the wall (-z side), so
    its lit face looks at the scan points.
    """
    u, v = (np.asarray(x, np.float64) for x in self.axes)
    n = np.cross(u, v)
    if n[2] > 0:                      # face the wall: normal toward -z
      v, n = -v, -n
    m = np.eye(4)
    m[:3, 0] = u * self.half_size[0]
    m[:3, 1] = v * self.half_size[1]
    m[:3, 2] = n
    m[:3, 3] = np.asarray(self.centre, np.float64)
    return m

  def samples(self, spacing: float):
    """Small square sub-patches (centres ``[P, 3]``, unit normal ``[3]``, area each) for our renderers."""
    u, v = (np.asarray(x, np.float64) for x in self.axes)
    na = max(1, int(np.ceil(2 * self.half_size[0] / spacing)))
    nb = max(1, int(np.ceil(2 * self.half_size[1] / spacing)))
    sa = (np.arange(na) + 0.5) / na * 2 - 1
    sb = (np.arange(nb) + 0.5) / nb * 2 - 1
    A, B = np.meshgrid(sa * self.half_size[0], sb * self.half_size[1], indexing="ij")
    pts = np.asarray(self.centre) + A.reshape(-1, 1) * u + B.reshape(-1, 1) * v
    n = np.cross(u, v)
    n = -n if n[2] > 0 else n
    area = 4 * self.half_size[0] * self.half_size[1] / (na * nb)
    return pts, n, area


def patches_from_frame(raster, setup: Setup, frame: int = 0, *, min_albedo: float = 1e-3) -> list[Patch]:
  """One frame of a rasterised scene of ours as fronto-parallel tiles at their depths.

  Each ray hit of :func:`nlosjax.data.scenes.rasterize` (``s x s`` rays per
  scan pixel) becomes a square tile of side ``spacing / s`` at the ray's
  ``(x, y)`` and hit depth, with the ray's shaded albedo: the frame's visible
  surfaces ("2.5-D", as our albedo volume) with their depths and albedo. A
  planar object facing the wall is reproduced; a tilted one becomes a
  staircase of tiles (its foreshortening is already in the shaded albedo).

  Args:
    raster: a :class:`~nlosjax.data.scenes.Rasterized` of ``setup``.
    setup: the capture it was rasterised on.
    frame: index into ``raster``'s frames.
    min_albedo: hits with less shaded albedo are left out.
  Returns:
    a list of :class:`Patch` (empty for an empty frame).
  """
  depth = np.asarray(raster.ray_depth[frame], np.float64)           # [S, H, W]
  albedo = np.asarray(raster.ray_albedo[frame], np.float64)
  S, H, W = depth.shape
  s = int(round(np.sqrt(S)))
  if s * s != S or (H, W) != tuple(setup.grid):
    raise ValueError(f"raster must hold s^2 rays per pixel on grid {setup.grid}, got {depth.shape}")
  dy, dx = setup.spacing
  sub = (np.arange(s) + 0.5) / s - 0.5
  # ray r = a * s + b sits at (x_j + sub[b] dx, y_i + sub[a] dy), as rasterize casts them
  a, b = np.divmod(np.arange(S), s)
  x = setup.scan_x[None, None, :] + (sub[b] * dx)[:, None, None]
  y = setup.scan_y[None, :, None] + (sub[a] * dy)[:, None, None]
  hit = np.isfinite(depth) & (depth > 0) & (albedo >= min_albedo)
  x, y = np.broadcast_to(x, depth.shape)[hit], np.broadcast_to(y, depth.shape)[hit]
  half = (dx / s / 2, dy / s / 2)
  return [Patch(centre=(float(px), float(py), float(pz)), half_size=half, albedo=float(min(pa, 1.0)))
          for px, py, pz, pa in zip(x, y, depth[hit], albedo[hit])]


def wall_half_extents(setup: Setup) -> tuple[float, float]:
  """Half width and half height of the relay-wall rectangle whose film pixel centres are our scan grid."""
  H, W = setup.grid
  if H < 2 or W < 2:
    raise ValueError(f"setup.grid must be at least 2 x 2 for a mitransient render, got {setup.grid}")
  return setup.wall_size * W / (W - 1) / 2, setup.wall_size * H / (H - 1) / 2


def scene_description(patches, setup: Setup, *, samples_per_point: int = 1024, max_depth: int = 4,
                      laser_origin=DEFAULT_LASER_ORIGIN, roulette: bool = False) -> dict:
  """The mitransient scene as plain data (4 x 4 matrices as NumPy arrays; no mitsuba).

  Args:
    patches: a sequence of :class:`Patch`.
    setup: the capture (wall size, grid, bin width, number of bins).
    samples_per_point: path samples per scan point.
    max_depth: longest path in bounces counted by Mitsuba (4: laser -> wall
      -> patch -> wall -> sensor, the third bounce; more adds inter-reflection
      only with ``roulette``).
    laser_origin: ``[3]`` position of laser and sensor, metres.
    roulette: at each path vertex choose hidden-geometry sampling or the
      material's at random (mitransient's ``do_rroulette``). Without it every
      direction is sampled toward a patch, so no path returns to the wall
      between patches and ``max_depth`` above 4 adds nothing; with it, paths
      past the third bounce are rendered, and the third bounce's scale differs
      from the default's (mitransient's two configurations do not agree on it).
  Returns:
    A nested dict in :func:`mitsuba.load_dict`'s form, with ``"to_world"``
    entries as ``[4, 4]`` arrays and ``"sensor_origin"`` a 3-tuple.
  """
  patches = list(patches)
  if not patches or not all(isinstance(p, Patch) for p in patches):
    raise ValueError("patches must be a non-empty sequence of Patch")
  if int(samples_per_point) < 1 or int(max_depth) < 2:
    raise ValueError(f"samples_per_point must be >= 1 and max_depth >= 2, got {samples_per_point}, {max_depth}")
  H, W = setup.grid
  wall = np.diag([*wall_half_extents(setup), 1.0, 1.0])
  laser = np.eye(4)
  laser[:3, 3] = np.asarray(laser_origin, np.float64)
  scene = {
      "type": "scene",
      "integrator": {"type": "transient_nlos_path", "max_depth": int(max_depth),
                     "nlos_laser_sampling": True, "nlos_hidden_geometry_sampling": True,
                     "nlos_hidden_geometry_sampling_do_rroulette": bool(roulette),
                     "account_first_and_last_bounces": False,
                     "capture_type": 2,              # confocal
                     "temporal_filter": "box"},
      "laser": {"type": "projector", "irradiance": 1.0, "fov": 0.2, "to_world": laser},
      "relay_wall": {
          "type": "rectangle", "to_world": wall,
          "bsdf": {"type": "diffuse", "reflectance": 1.0},
          "nlos_sensor": {
              "type": "nlos_capture_meter",
              "sampler": {"type": "independent", "sample_count": int(samples_per_point)},
              "sensor_origin": tuple(float(v) for v in laser_origin),
              "transient_film": {"type": "transient_hdr_film", "width": int(W), "height": int(H),
                                 "temporal_bins": int(setup.num_bins),
                                 "bin_width_opl": float(setup.bin_length), "start_opl": 0.0,
                                 "rfilter": {"type": "box"}}}},
  }
  for k, p in enumerate(patches):
    scene[f"patch_{k}"] = {"type": "rectangle", "to_world": p.to_world(),
                           "bsdf": {"type": "diffuse", "reflectance": float(p.albedo)}}
  return scene


def _to_mitsuba(node, mi):
  if isinstance(node, dict):
    out = {}
    for k, v in node.items():
      if k == "to_world":
        out[k] = mi.ScalarTransform4f(np.asarray(v, np.float64).tolist())
      elif k == "sensor_origin":
        out[k] = mi.ScalarPoint3f(*v)
      elif k == "reflectance" and isinstance(v, float):
        out[k] = {"type": "rgb", "value": [v, v, v]}
      else:
        out[k] = _to_mitsuba(v, mi)
    return out
  return node


def render_raw(patches, setup: Setup, *, variant: str = DEFAULT_VARIANT, seed: int = 0, **options):
  """Render with mitransient; returns ``(raw, seconds)``, ``raw`` its ``(H, W, T, C)`` float32 output.

  Needs ``mitsuba`` and ``mitransient`` (the ``render`` extra); with Debian's
  ``libllvm19`` point ``DRJIT_LIBLLVM_PATH`` at ``libLLVM-19.so`` if drjit
  finds an older LLVM first. ``options`` go to :func:`scene_description`.
  """
  try:
    import mitsuba as mi
  except ImportError as e:                      # the optional extra is missing
    raise ImportError('rendering with mitransient needs `pip install "nlosjax[render]"`') from e
  mi.set_variant(variant)
  import mitransient  # noqa: F401  (registers the transient plugins)

  scene = mi.load_dict(_to_mitsuba(scene_description(patches, setup, **options), mi))
  start = time.perf_counter()
  _, transient = mi.render(scene, seed=int(seed))
  raw = np.array(transient, dtype=np.float32)
  return raw, time.perf_counter() - start


def to_transient(raw, setup: Setup, *, laser_origin=DEFAULT_LASER_ORIGIN) -> np.ndarray:
  """mitransient's ``(H, W, T[, C])`` confocal output as our ``[T, H, W]`` float32 transient.

  Averages colour channels, moves time first, and divides out the laser
  leg's ``cos / d^2`` at each scan point (see the module docstring).
  """
  raw = np.asarray(raw, np.float64)
  H, W = setup.grid
  if raw.ndim == 4:
    raw = raw.mean(-1)
  if raw.shape != (H, W, setup.num_bins):
    raise ValueError(f"raw must be (H={H}, W={W}, T={setup.num_bins}[, C]), got {np.shape(raw)}")
  d = np.asarray(laser_origin, np.float64) - setup.scan_points          # [H, W, 3]
  r = np.linalg.norm(d, axis=-1)
  falloff = (d[..., 2] / r) / r ** 2                                      # cos / d^2
  return (np.moveaxis(raw, -1, 0) / falloff).astype(np.float32)


def render(patches, setup: Setup, **options) -> np.ndarray:
  """:func:`render_raw` then :func:`to_transient`: a noise-free ``[T, H, W]`` float32 transient."""
  laser = options.get("laser_origin", DEFAULT_LASER_ORIGIN)
  raw, _ = render_raw(patches, setup, **options)
  return to_transient(raw, setup, laser_origin=laser)


def detect(key, transient, setup: Setup, **detector):
  """Our detector model on a rendered transient: :func:`nlosjax.physics.noise.add_spad_noise`.

  ``detector`` takes its keywords (``photons_per_point`` or ``pulses``,
  ``efficiency``, ``ambient``, ``dark_counts``, ``jitter``).
  """
  from nlosjax.physics.noise import add_spad_noise

  return add_spad_noise(key, transient, setup, **detector)

"""The orthographic ray cast of a scene from the wall: albedo volume, intensity and depth (:func:`rasterize`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from nlosjax.data.scenes.params import BACKGROUND_DEPTH, PLANAR_KINDS
from nlosjax.data.scenes.scene import Scene, SceneObject
from nlosjax.data.scenes.shapes import inside_polygons, texture_albedo
from nlosjax.physics.setup import Setup

_TORUS_STEPS = 160     # sphere-tracing iterations for the torus
_TORUS_TOL = 1e-6      # metres: a ray whose SDF falls below this has hit


def _cast(obj: SceneObject, anchor: np.ndarray, ox: np.ndarray, oy: np.ndarray):
  """Nearest hits of rays ``(ox, oy, 0) + t (0, 0, 1)`` with ``obj`` at ``anchor``.

  Returns:
    ``(t [P], shaded albedo [P])`` float64; ``t = inf`` where the ray misses.
  """
  R = obj.rotation
  # Local ray: q(t) = q0 + t d, q0 = R^T (o - anchor), d = R^T e_z = R[2].
  rel = np.stack([ox - anchor[0], oy - anchor[1], np.full_like(ox, -anchor[2])], -1)
  q0 = rel @ R
  d = R[2].copy()
  t_hit = np.full(ox.shape, np.inf)
  shade = np.zeros(ox.shape)
  # Only rays passing within the bounding sphere can hit.
  b = q0 @ d
  disc = b * b - (np.einsum("pi,pi->p", q0, q0) - obj.radius ** 2)
  cand = np.nonzero(disc > 0)[0]
  if cand.size == 0:
    return t_hit, shade
  q0c = q0[cand]
  kind = obj.kind
  if kind in PLANAR_KINDS:
    if abs(d[2]) < 1e-9:
      return t_hit, shade
    t = -q0c[:, 2] / d[2]
    q = q0c + t[:, None] * d
    warp = obj.shape.get("warp")
    if warp is not None:    # back to the reference outline (and texture) of a deformed object
      q = np.concatenate([q[:, :2] @ np.linalg.inv(warp).T, q[:, 2:]], axis=1)
    hit = (t > 0) & inside_polygons(q[:, 0], q[:, 1], obj.shape["polygons"])
    cos = np.full(t.shape, abs(d[2]))
  elif kind == "sphere":
    r = obj.shape["radius"]
    bc = b[cand]
    dc = bc * bc - (np.einsum("pi,pi->p", q0c, q0c) - r * r)
    t = -bc - np.sqrt(np.maximum(dc, 0.0))
    hit = (dc > 0) & (t > 0)
    q = q0c + t[:, None] * d
    cos = np.abs(q @ d) / r
  elif kind in ("box", "bar"):
    h = obj.shape["half_extents"]
    dd = np.where(np.abs(d) < 1e-12, 1e-12, d)
    t1, t2 = (-h - q0c) / dd, (h - q0c) / dd
    tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
    t = tmin.max(1)
    hit = (t <= tmax.min(1)) & (t > 0)
    face = np.argmax(tmin, axis=1)
    q = q0c + t[:, None] * d
    cos = np.abs(d[face])
  elif kind == "torus":
    t, hit, q, cos = _cast_torus(q0c, d, b[cand], disc[cand], obj.shape["major"], obj.shape["minor"])
  else:
    raise ValueError(f"unknown kind {kind!r}")
  idx = cand[hit]
  t_hit[idx] = t[hit]
  shade[idx] = texture_albedo(obj.texture, q[hit]) * cos[hit]
  return t_hit, shade


def _torus_sdf(q, major, minor):
  rho = np.hypot(q[:, 0], q[:, 1])
  return np.hypot(rho - major, q[:, 2]) - minor


def _cast_torus(q0, d, b, disc, major, minor):
  """Sphere tracing of a torus about local z, from its bounding-sphere entry."""
  root = np.sqrt(disc)
  t = np.maximum(-b - root, 0.0)
  t_exit = -b + root
  hit = np.zeros(t.shape, bool)
  active = np.arange(t.size)
  for _ in range(_TORUS_STEPS):
    if active.size == 0:
      break
    q = q0[active] + t[active, None] * d
    s = _torus_sdf(q, major, minor)
    done = s < _TORUS_TOL
    hit[active[done]] = True
    t[active[~done]] += s[~done]
    keep = ~done & (t[active] <= t_exit[active])
    active = active[keep]
  q = q0 + t[:, None] * d
  hit &= t <= t_exit
  rho = np.maximum(np.hypot(q[:, 0], q[:, 1]), 1e-12)
  n = np.stack([q[:, 0] / rho * (rho - major), q[:, 1] / rho * (rho - major), q[:, 2]], -1)
  n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
  return t, hit, q, np.abs(n @ d)




@dataclasses.dataclass(frozen=True)
class Rasterized:
  """Per-frame maps of a scene on a Setup's scan grid (see the module docstring).

  Attributes:
    ray_depth: ``[F, S, H, W]`` float32 hit depth per ray (``S = s^2``),
      metres; ``inf`` where the ray misses.
    ray_albedo: ``[F, S, H, W]`` float32 shaded albedo per ray (0 on a miss).
    intensity: ``[F, H, W]`` float32 in ``[0, 1]``.
    depth: ``[F, H, W]`` float32 metres, :data:`BACKGROUND_DEPTH` where empty.
    frames: ``[F]`` int frame indices.
  """

  ray_depth: np.ndarray
  ray_albedo: np.ndarray
  intensity: np.ndarray
  depth: np.ndarray
  frames: np.ndarray

  def volume(self, setup: Setup, index=slice(None)) -> np.ndarray:
    """Albedo volume ``[F', Z, H, W]`` float32 of the frames ``self.frames[index]``.

    Each ray adds ``albedo / S`` at depth bin ``floor(z / depth_bin_length)``
    (less the Setup's first depth bin); bins outside ``[0, Z)`` are dropped.
    """
    z = self.ray_depth[index]
    a = self.ray_albedo[index]
    n, S, H, W = z.shape
    if (H, W) != setup.grid:
      raise ValueError(f"setup grid {setup.grid} does not match the rasterised grid {(H, W)}")
    k0 = setup.depth_bins[0]
    Z = setup.num_depth_bins
    with np.errstate(invalid="ignore"):
      k = np.floor(z.astype(np.float64) / setup.depth_bin_length) - k0
    ok = np.isfinite(k) & (k >= 0) & (k < Z) & (a > 0)
    f_idx = np.broadcast_to(np.arange(n)[:, None, None, None], z.shape)
    pix = np.broadcast_to(np.arange(H * W).reshape(1, 1, H, W), z.shape)
    flat = (f_idx[ok] * Z + k[ok].astype(np.int64)) * (H * W) + pix[ok]
    vol = np.bincount(flat, weights=a[ok].astype(np.float64) / S, minlength=n * Z * H * W)
    return vol.reshape(n, Z, H, W).astype(np.float32)


def _ray_origins(setup: Setup, s: int) -> tuple[np.ndarray, np.ndarray]:
  """``[H * s * W * s]`` ray origins, ordered ``(i, a, j, b)`` (pixel row, sub-row, ...)."""
  dy, dx = setup.spacing
  sub = (np.arange(s) + 0.5) / s - 0.5
  ys = (setup.scan_y[:, None] + sub[None] * dy).reshape(-1)
  xs = (setup.scan_x[:, None] + sub[None] * dx).reshape(-1)
  Y, X = np.meshgrid(ys, xs, indexing="ij")
  return X.reshape(-1), Y.reshape(-1)


def rasterize(scene: Scene, setup: Setup, *, frames=None, objects=None,
              supersample: int = 2) -> Rasterized:
  """Intensity, depth and per-ray hits of ``scene`` on the scan grid of ``setup``.

  Args:
    scene: from :func:`make_scene`.
    setup: the capture (its grid and wall; depth bins matter only for
      :meth:`Rasterized.volume`).
    frames: frame indices (default all ``F``).
    objects: indices into ``scene.objects`` to draw (default all); e.g.
      ``[scene.dynamic_index]`` draws the moving object alone.
    supersample: rays per pixel along each axis (``s``; the dataset uses the
      scene params' value).
  Returns:
    :class:`Rasterized`.
  """
  if not isinstance(setup, Setup):
    raise ValueError(f"setup must be a nlosjax.physics.Setup, got {type(setup).__name__}")
  if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) or supersample < 1:
    raise ValueError(f"supersample must be an integer >= 1, got {supersample!r}")
  frames = np.arange(scene.num_frames) if frames is None else np.asarray(frames, np.int64).reshape(-1)
  if frames.size and (frames.min() < 0 or frames.max() >= scene.num_frames):
    raise ValueError(f"frames must lie in [0, {scene.num_frames}), got {frames.tolist()}")
  objects = range(len(scene.objects)) if objects is None else list(objects)
  s = int(supersample)
  H, W = setup.grid
  ox, oy = _ray_origins(setup, s)
  static_hits = [_cast(scene.objects[i], scene.objects[i].anchor, ox, oy)
                 for i in objects if not scene.objects[i].dynamic]
  F = frames.size
  ray_depth = np.full((F, ox.size), np.inf)
  ray_albedo = np.zeros((F, ox.size))
  for n, f in enumerate(frames):
    hits = list(static_hits)
    posed = [scene.posed(i, int(f)) for i in objects if scene.objects[i].dynamic]
    hits += [_cast(o, o.anchor, ox, oy) for o in posed]
    for t, a in hits:
      nearer = t < ray_depth[n]
      ray_depth[n] = np.where(nearer, t, ray_depth[n])
      ray_albedo[n] = np.where(nearer, a, ray_albedo[n])
  # (F, i, a, j, b) -> (F, a, b, i, j) -> (F, S, H, W)
  def per_pixel(x):
    return x.reshape(F, H, s, W, s).transpose(0, 2, 4, 1, 3).reshape(F, s * s, H, W)
  ray_depth, ray_albedo = per_pixel(ray_depth), per_pixel(ray_albedo)
  covered = np.isfinite(ray_depth)
  raw = ray_albedo.mean(1)
  peak = raw.max(axis=(1, 2), keepdims=True)
  intensity = np.where(peak > 0, raw / np.where(peak > 0, peak, 1.0), 0.0)
  count = covered.sum(1)
  total = np.where(covered, ray_depth, 0.0).sum(1)
  depth = np.where(count > 0, total / np.maximum(count, 1), BACKGROUND_DEPTH)
  return Rasterized(ray_depth=ray_depth.astype(np.float32), ray_albedo=ray_albedo.astype(np.float32),
                    intensity=np.clip(intensity, 0.0, 1.0).astype(np.float32),
                    depth=depth.astype(np.float32), frames=frames)

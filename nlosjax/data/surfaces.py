"""Surface patches of scene objects, and transients of scenes by light transport.

Turns the objects of a :class:`nlosjax.data.scenes.Scene` into
:class:`nlosjax.physics.transport.SurfaceSamples` (their whole surfaces, not
the orthographic view the albedo volume holds) and renders a scene's frames
with :func:`nlosjax.physics.transport.render_surfaces`: exact path lengths,
Lambertian cosines, per-scan-point visibility, diffuse or retroreflective
materials. This is the dataset renderer ``renderer="transport"``
(:class:`nlosjax.data.DatasetSpec`), the one that is not the LCT operator.

Sampling, patch side ``a`` (metres): planar cut-outs (letters, digits,
polygons, plates, bar and dot charts) on an ``a``-grid of their plane, kept
inside their outline, two-sided (a deformed one, :meth:`Scene.deformation`,
sampled on its reference outline at ``a`` over its largest stretch, its
patches then mapped, albedo kept where the material was); boxes and bars per face on a grid of about ``a``; spheres on a
Fibonacci lattice of ``4 pi r^2 / a^2`` points; tori on a ``(theta, phi)`` grid
with exact area elements. Albedo is the object's texture at the patch
(:func:`nlosjax.data.scenes.texture_albedo`).

Materials: every object is diffuse unless drawn retroreflective with
probability ``retroreflective``, from a stream of its own (the scene's seed,
spawn key 3), so the scene itself (shapes, motion) is the same for any value.
"""

from __future__ import annotations

import math

import numpy as np

from nlosjax.data import scenes
from nlosjax.physics.setup import Setup
from nlosjax.physics.transport import SurfaceSamples, default_spacing, render_surfaces

__all__ = ["object_samples", "object_materials", "scene_samples", "render_scene"]


def _grid(lo: float, hi: float, a: float) -> tuple[np.ndarray, float]:
  """Cell centres covering ``[lo, hi]`` with cells of about ``a``; (centres, cell size)."""
  n = max(1, int(math.ceil((hi - lo) / a)))
  step = (hi - lo) / n
  return lo + (np.arange(n) + 0.5) * step, step


def _planar(obj, a):
  polys = obj.shape["polygons"]
  allp = np.concatenate(polys)
  us, du = _grid(allp[:, 0].min(), allp[:, 0].max(), a)
  vs, dv = _grid(allp[:, 1].min(), allp[:, 1].max(), a)
  U, V = np.meshgrid(us, vs, indexing="ij")
  U, V = U.ravel(), V.ravel()
  inside = scenes.inside_polygons(U, V, polys)
  q = np.stack([U[inside], V[inside], np.zeros(inside.sum())], -1)
  n = np.tile([0.0, 0.0, 1.0], (q.shape[0], 1))
  return q, n, np.full(q.shape[0], du * dv), True


def _box(obj, a):
  h = np.asarray(obj.shape["half_extents"], np.float64)
  qs, ns, areas = [], [], []
  for axis in range(3):
    u_ax, v_ax = [k for k in range(3) if k != axis]
    us, du = _grid(-h[u_ax], h[u_ax], a)
    vs, dv = _grid(-h[v_ax], h[v_ax], a)
    U, V = np.meshgrid(us, vs, indexing="ij")
    for sign in (-1.0, 1.0):
      q = np.zeros((U.size, 3))
      q[:, u_ax], q[:, v_ax], q[:, axis] = U.ravel(), V.ravel(), sign * h[axis]
      n = np.zeros_like(q)
      n[:, axis] = sign
      qs.append(q), ns.append(n), areas.append(np.full(U.size, du * dv))
  return np.concatenate(qs), np.concatenate(ns), np.concatenate(areas), False


def _sphere(obj, a):
  r = float(obj.shape["radius"])
  n = max(8, int(math.ceil(4 * math.pi * r * r / (a * a))))
  i = np.arange(n) + 0.5
  z = 1 - 2 * i / n
  phi = math.pi * (1 + math.sqrt(5)) * i
  rho = np.sqrt(1 - z * z)
  d = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], -1)
  return r * d, d, np.full(n, 4 * math.pi * r * r / n), False


def _torus(obj, a):
  R0, r0 = float(obj.shape["major"]), float(obj.shape["minor"])
  nt = max(8, int(math.ceil(2 * math.pi * (R0 + r0) / a)))
  nphi = max(8, int(math.ceil(2 * math.pi * r0 / a)))
  th = (np.arange(nt) + 0.5) * 2 * math.pi / nt
  ph = (np.arange(nphi) + 0.5) * 2 * math.pi / nphi
  TH, PH = np.meshgrid(th, ph, indexing="ij")
  TH, PH = TH.ravel(), PH.ravel()
  ring = R0 + r0 * np.cos(PH)
  q = np.stack([ring * np.cos(TH), ring * np.sin(TH), r0 * np.sin(PH)], -1)
  n = np.stack([np.cos(PH) * np.cos(TH), np.cos(PH) * np.sin(TH), np.sin(PH)], -1)
  area = ring * r0 * (2 * math.pi / nt) * (2 * math.pi / nphi)
  return q, n, area, False


_SAMPLERS = {"letter": _planar, "digit": _planar, "polygon": _planar, "plate": _planar,
             "bars": _planar, "dots": _planar, "box": _box, "bar": _box, "sphere": _sphere,
             "torus": _torus}


def object_samples(obj: scenes.SceneObject, spacing: float, *, anchor=None,
                   retroreflective: bool = False, object_id: int = 0) -> SurfaceSamples:
  """Surface patches of one object at ``anchor`` (default its own), patch side ``spacing`` m."""
  if not (isinstance(spacing, (int, float)) and spacing > 0 and math.isfinite(spacing)):
    raise ValueError(f"spacing must be a positive number of metres, got {spacing!r}")
  warp = obj.shape.get("warp")
  if warp is None:
    q, n, area, two_sided = _SAMPLERS[obj.kind](obj, float(spacing))
    albedo = scenes.texture_albedo(obj.texture, q)
  else:   # a deformed planar object: sample its reference outline finely enough, then map it
    warp = np.asarray(warp, np.float64)
    q, n, area, two_sided = _SAMPLERS[obj.kind](obj, float(spacing) / np.linalg.norm(warp, 2))
    albedo = scenes.texture_albedo(obj.texture, q)
    q = np.concatenate([q[:, :2] @ warp.T, q[:, 2:]], axis=1)
    area = area * abs(np.linalg.det(warp))
  anchor = obj.anchor if anchor is None else np.asarray(anchor, np.float64)
  R = obj.rotation
  pts = q @ R.T + anchor
  nrm = n @ R.T
  nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
  if two_sided:  # point the normal at the wall (either side reflects)
    nrm = np.where(nrm[:, 2:3] > 0, -nrm, nrm)
  return SurfaceSamples(pts, nrm, area, albedo, retroreflective, two_sided, object_id)


def object_materials(scene: scenes.Scene, retroreflective: float) -> np.ndarray:
  """``[num_objects]`` bool: which objects are retroreflective (probability ``retroreflective``)."""
  if not 0.0 <= float(retroreflective) <= 1.0:
    raise ValueError(f"retroreflective must be a probability in [0, 1], got {retroreflective!r}")
  rng = np.random.default_rng(np.random.SeedSequence(scene.seed, spawn_key=(3,)))
  return rng.uniform(size=len(scene.objects)) < float(retroreflective)


def scene_samples(scene: scenes.Scene, frame: int, spacing: float, *,
                  retroreflective: float = 0.0) -> SurfaceSamples:
  """Every object's patches at ``frame`` (the dynamic one at its pose of that frame)."""
  materials = object_materials(scene, retroreflective)
  return SurfaceSamples.concatenate(
      object_samples(scene.posed(i, frame), spacing, retroreflective=bool(materials[i]),
                     object_id=i)
      for i in range(len(scene.objects)))


def render_scene(scene: scenes.Scene, setup: Setup, *, frames=None, spacing: float | None = None,
                 retroreflective: float = 0.0, occlusion: bool = True,
                 falloff_power=None, cosine_power: float | None = None,
                 progress=None) -> np.ndarray:
  """Noise-free transients ``[F', T, H, W]`` float32 of ``scene``'s frames by light transport.

  Args:
    scene: from :func:`nlosjax.data.scenes.make_scene`.
    setup: the capture.
    frames: frame indices (default all).
    spacing: patch side, metres (default
      :func:`nlosjax.physics.transport.default_spacing`).
    retroreflective: probability that an object is retroreflective.
    occlusion: per-scan-point visibility (False: every facing patch counts).
    falloff_power: ``[num_objects]`` falloff exponent ``p`` of each object's
      return (``r^-p``, in ``[2, 4]``), or ``None`` (``retroreflective`` draws
      2 or 4 per object).
    cosine_power: exponent ``kappa`` of the cosines (``None``: 1, Lambertian);
      see :func:`nlosjax.physics.transport.render_surfaces`.
    progress: optional callable ``progress(done, total)`` after each frame.
  Units as :func:`nlosjax.physics.transport.render_surfaces`.
  """
  spacing = default_spacing(setup) if spacing is None else float(spacing)
  frames = np.arange(scene.num_frames) if frames is None else np.asarray(frames).reshape(-1)
  materials = object_materials(scene, retroreflective)
  if falloff_power is not None:
    falloff_power = np.asarray(falloff_power, np.float64).reshape(-1)
    if falloff_power.shape != (len(scene.objects),):
      raise ValueError(f"falloff_power must hold one exponent per object ({len(scene.objects)}),"
                       f" got shape {falloff_power.shape}")
  # Rigid objects: sample each once at its own pose, then move the patches per frame. A
  # deforming one (non-rigid motion) is sampled afresh at each frame's shape.
  deforming = {i for i, o in enumerate(scene.objects) if o.dynamic and scene.deforms}
  base = [None if i in deforming else
          object_samples(o, spacing, anchor=o.anchor, retroreflective=bool(materials[i]), object_id=i)
          for i, o in enumerate(scene.objects)]
  H, W = setup.grid
  out = np.empty((frames.size, setup.num_bins, H, W), np.float32)
  for n, f in enumerate(frames):
    parts = []
    for i, b in enumerate(base):
      o = scene.objects[i]
      if i in deforming:
        parts.append(object_samples(scene.posed(i, int(f)), spacing,
                                    retroreflective=bool(materials[i]), object_id=i))
        continue
      turn = scene.rotation(i, int(f)) @ o.rotation.T
      parts.append(b.moved(turn, o.anchor, scene.anchor(i, int(f))))
    samples = SurfaceSamples.concatenate(parts)
    out[n] = render_surfaces(samples, setup.ungated(), occlusion=occlusion, spacing=spacing,
                             falloff_power=(None if falloff_power is None
                                            else falloff_power[samples.object_id]),
                             cosine_power=cosine_power)
    if progress is not None:
      progress(n + 1, frames.size)
  return out

"""Procedural dynamic hidden scenes: shapes, textures, and one object on a 3-D helix.

A :class:`Scene` holds 1-3 static objects and one dynamic object whose anchor
(the origin of its local frame) follows a helix (:class:`Helix`) with random
radius, pitch, phase, angular speed and axis; frames are sampled at
``frame_rate`` Hz. Everything is drawn from ``numpy.random.default_rng(seed)``,
so a seed (and :data:`GENERATOR_VERSION`) fixes the scene; the scan grid does
not enter the draw, so one seed gives the same 3-D scene at any resolution.
Nothing is downloaded: letters and digits are outlines of matplotlib's bundled
DejaVu Sans Bold font (read from matplotlib's own data folder).

Shapes (:data:`KINDS`): planar ``letter`` (A-Z) and ``digit`` (0-9) cut-outs
(DejaVu Sans Bold, or with ``glyph_weights`` also the thinner-stroked DejaVu
Sans), planar ``polygon`` (regular, star or irregular, 3-8 corners), planar
``plate`` (rectangle, always textured), solid ``box``, ``sphere``, ``torus``
and thin ``bar`` (a long box); and the two resolution charts of measured
scans, planar ``bars`` (3-6 parallel bars, bars and gaps equally wide) and
planar ``dots`` (a 2 x 2 to 4 x 4 grid of discs), which a scene draws only
when its ``kinds`` name them (:data:`DEFAULT_KINDS` leaves them out, so the
default scenes are those of earlier versions). Planar objects face the wall,
their normal tilted from it by at most ``max_tilt`` degrees and spun in plane;
solids get a uniformly random orientation. Textures (:data:`TEXTURES`): ``uniform``,
``checker`` and ``stripes`` (3-D solid textures in the object's frame) and
``noise`` (a sum of random sinusoids); albedo in ``[0.1, 1]``.

Rasterisation (:func:`rasterize`) is an orthographic ray cast from the wall
along +z (the view of a confocal scanner): every scan pixel ``(i, j)`` at
``(scan_x[j], scan_y[i], 0)`` shoots ``s x s`` rays (``s = supersample``)
spread evenly over its footprint; each ray keeps the nearest hit (a z-buffer,
so objects occlude each other). A hit has depth ``z`` (metres, the ray
parameter) and *shaded albedo* ``a = texture * |n_z|`` (Lambertian
foreshortening toward the wall; ``n`` the unit surface normal). Per frame:

* albedo volume ``[Z, H, W]`` float32: each ray adds ``a / s^2`` to voxel
  ``(k, i, j)`` with ``k = floor(z / (c dt / 2))`` (depth bin ``k`` covers
  ``[k, k + 1) * c dt / 2``; hits beyond the last bin, or outside a Setup's
  depth range, are dropped). It is a visible-surface ("2.5-D") volume: hidden
  back faces carry no albedo, and its scale is the physical shaded albedo (not
  normalised).
* intensity ``[H, W]`` float32 in ``[0, 1]``: the pixel's mean shaded albedo
  over its ``s^2`` rays (misses count 0; equal to the volume's column sum),
  divided by its maximum over the frame (as the public datasets and
  :func:`nlosjax.physics.intensity_depth` normalise); an empty frame is all 0.
* depth ``[H, W]`` float32 metres: mean hit depth over the pixel's rays that
  hit something; :data:`BACKGROUND_DEPTH` (0 m, the public datasets' "no
  surface" value, and ``intensity_depth``'s default) where no ray hits.

Dynamic-object trajectory: ``Scene.trajectory`` ``[F, 3]`` (metres) is the
anchor position per frame, on the helix or, with ``motions`` including
``"line"``, a straight line; by default the object translates without turning,
so its orthographic footprint moves rigidly with the anchor's (x, y);
``spin_speed > 0`` turns it about a random axis as well (``Scene.rotation``).
Non-rigid motion (``deform``): a planar dynamic object stretches in its own
plane by ``exp(a sin(w t + phi))`` along a random in-plane direction and
shrinks by the inverse across it (an area-keeping 2 x 2 map,
``Scene.deformation``), its texture carried with the material; the outline,
the ray cast, the albedo volume and the transport renderer's patches all
follow it exactly (a linear map of a plane stays a plane).
"""

from nlosjax.data.scenes.motion import Helix, Line
from nlosjax.data.scenes.params import (
                                        BACKGROUND_DEPTH,
                                        CHART_KINDS,
                                        DEFAULT_KINDS,
                                        GENERATOR_VERSION,
                                        GLYPH_WEIGHTS,
                                        KINDS,
                                        MOTIONS,
                                        PLANAR_KINDS,
                                        TEXTURES,
                                        SceneParams,
)
from nlosjax.data.scenes.raster import Rasterized, rasterize
from nlosjax.data.scenes.scene import Scene, SceneObject, make_scene
from nlosjax.data.scenes.shapes import chart_polygons, glyph_polygons, inside_polygons, texture_albedo

__all__ = [
    "BACKGROUND_DEPTH",
    "CHART_KINDS",
    "DEFAULT_KINDS",
    "GENERATOR_VERSION",
    "GLYPH_WEIGHTS",
    "KINDS",
    "MOTIONS",
    "TEXTURES",
    "Helix",
    "Line",
    "Rasterized",
    "Scene",
    "SceneObject",
    "SceneParams",
    "PLANAR_KINDS",
    "chart_polygons",
    "glyph_polygons",
    "inside_polygons",
    "texture_albedo",
    "make_scene",
    "rasterize",
]

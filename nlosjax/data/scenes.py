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

from __future__ import annotations

import dataclasses
import functools
import math
import pathlib
from collections.abc import Mapping

import numpy as np

from nlosjax.physics.setup import Setup

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
    "glyph_polygons",
    "make_scene",
    "rasterize",
]

#: Version of the scene generator; bump whenever a seed would give another scene.
#: (Options added later, :data:`_LATER_FIELDS`, draw nothing at their defaults.)
GENERATOR_VERSION = "1.0"

#: Depth (metres) written at pixels where no ray hits an object.
BACKGROUND_DEPTH = 0.0

#: SceneParams fields added after files were written, with their defaults.
_LATER_FIELDS = {"albedo_range": (0.5, 1.0), "motions": ("helix",), "spin_speed": (0.0, 0.0),
                 "glyph_weights": ("bold",), "deform": (0.0, 0.0)}

#: Object kinds a scene draws from by default (those of generator 1.0's first files).
DEFAULT_KINDS = ("letter", "digit", "polygon", "plate", "box", "sphere", "torus", "bar")
#: Resolution charts, as in measured scans: parallel ``bars`` and a grid of ``dots``.
CHART_KINDS = ("bars", "dots")
#: Every object kind.
KINDS = DEFAULT_KINDS + CHART_KINDS
PLANAR_KINDS = ("letter", "digit", "polygon", "plate") + CHART_KINDS

#: Font weights of letters and digits: DejaVu Sans Bold (strokes about 1/6 of
#: the glyph's height) and DejaVu Sans (about 1/9), both bundled with matplotlib.
GLYPH_WEIGHTS = ("bold", "regular")
_FONT_FILES = {"bold": "DejaVuSans-Bold.ttf", "regular": "DejaVuSans.ttf"}
_DISC_CORNERS = 32     # corners of the polygon that outlines a chart's dot

#: Paths of the dynamic object (:attr:`SceneParams.motions`).
MOTIONS = ("helix", "line")

#: Albedo textures.
TEXTURES = ("uniform", "checker", "stripes", "noise")

_LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"
_DIGITS = "0123456789"
_TORUS_STEPS = 160     # sphere-tracing iterations for the torus
_TORUS_TOL = 1e-6      # metres: a ray whose SDF falls below this has hit
_MIN_ALBEDO = 0.1


# ------------------------------------------------------------------ params
def _pair(value, name, *, low=None, integer=False):
  try:
    lo, hi = value
  except (TypeError, ValueError):
    raise ValueError(f"{name} must be a (low, high) pair, got {value!r}") from None
  cast = int if integer else float
  try:
    lo, hi = cast(lo), cast(hi)
  except (TypeError, ValueError):
    raise ValueError(f"{name} must hold numbers, got {value!r}") from None
  if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
    raise ValueError(f"{name} must be finite with low <= high, got {value!r}")
  if low is not None and lo < low:
    raise ValueError(f"{name} must be >= {low}, got {value!r}")
  return (lo, hi)


@dataclasses.dataclass(frozen=True)
class SceneParams:
  """Distributions of a dynamic scene (lengths in metres, angles in radians).

  Attributes:
    num_static: ``(min, max)`` number of static objects, inclusive.
    depth_range: ``(z_min, z_max)``: every object's bounding sphere lies in
      these depths (the dynamic one along its whole path).
    lateral_extent: object anchors lie in ``|x|, |y| <= lateral_extent``.
    size_range: ``(min, max)`` object extent (largest dimension).
    kinds: object kinds to draw from (uniformly), a subset of :data:`KINDS`.
    dynamic_kinds: kinds for the dynamic object.
    texture_probability: chance that an object gets a non-uniform texture
      (plates always do).
    max_tilt: largest tilt of a planar object's normal from the wall normal.
    helix_radius: ``(min, max)`` helix radius.
    helix_pitch: ``(min, max)`` axial advance per turn (sign drawn at random:
      positive is a right-handed helix).
    helix_speed: ``(min, max)`` angular speed, rad/s (direction random).
    frame_rate: frames per second.
    supersample: rays per pixel along each axis (``s``).
    min_gap: smallest gap between bounding spheres of different objects
      (static vs static, static vs the dynamic one anywhere on its path).
    albedo_range: ``(min, max)`` of an object's base albedo (uniform); a low
      minimum gives dim objects beside bright ones.
    motions: the dynamic object's path, drawn uniformly per scene from
      ``"helix"`` (:class:`Helix`) and ``"line"`` (:class:`Line`: constant
      velocity between two points of the scene box).
    spin_speed: ``(min, max)`` rad/s of the dynamic object's rotation about a
      random axis through its anchor (direction random); ``(0, 0)``: it
      translates without turning.
    glyph_weights: font weights letters and digits are drawn in (uniformly),
      a subset of :data:`GLYPH_WEIGHTS`; ``("bold",)`` draws nothing.
    deform: ``(min, max)`` amplitude ``a`` (in ``[0, 0.5]``) of the planar
      dynamic object's non-rigid stretch (module docstring); its angular
      speed is drawn from ``helix_speed``. ``(0, 0)``: rigid. Solids are
      never deformed.

  The last five are left out of :meth:`to_dict` at their defaults and draw
  nothing there, so a scene drawn with the defaults is the one earlier
  versions drew. Motion, spin and deformation come from streams of their own
  (the seed, spawn keys 4 and 5); the font weight, with more than one, from
  the main stream right after the glyph's character, so the rest of such a
  scene differs from the one-weight scene of the same seed.
  """

  num_static: tuple[int, int] = (1, 3)
  depth_range: tuple[float, float] = (0.5, 1.5)
  lateral_extent: float = 0.5
  size_range: tuple[float, float] = (0.2, 0.6)
  kinds: tuple[str, ...] = DEFAULT_KINDS
  dynamic_kinds: tuple[str, ...] = DEFAULT_KINDS
  texture_probability: float = 0.5
  max_tilt: float = math.radians(35.0)
  helix_radius: tuple[float, float] = (0.05, 0.25)
  helix_pitch: tuple[float, float] = (0.05, 0.3)
  helix_speed: tuple[float, float] = (0.4, 1.6)
  frame_rate: float = 4.0
  supersample: int = 2
  min_gap: float = 0.02
  albedo_range: tuple[float, float] = (0.5, 1.0)
  motions: tuple[str, ...] = ("helix",)
  spin_speed: tuple[float, float] = (0.0, 0.0)
  glyph_weights: tuple[str, ...] = ("bold",)
  deform: tuple[float, float] = (0.0, 0.0)

  def __post_init__(self):
    ns = _pair(self.num_static, "num_static", low=0, integer=True)
    object.__setattr__(self, "num_static", ns)
    dr = _pair(self.depth_range, "depth_range", low=0.0)
    if dr[0] <= 0 or dr[0] >= dr[1]:
      raise ValueError(f"depth_range must be 0 < z_min < z_max, got {self.depth_range!r}")
    object.__setattr__(self, "depth_range", dr)
    sr = _pair(self.size_range, "size_range", low=0.0)
    if sr[0] <= 0:
      raise ValueError(f"size_range must be > 0, got {self.size_range!r}")
    if sr[1] > dr[1] - dr[0]:
      raise ValueError(f"size_range {sr} exceeds the depth_range span {dr[1] - dr[0]:.3g} m;"
                       " objects would not fit")
    object.__setattr__(self, "size_range", sr)
    for name in ("helix_radius", "helix_pitch", "helix_speed", "spin_speed", "deform"):
      object.__setattr__(self, name, _pair(getattr(self, name), name, low=0.0))
    if self.deform[1] > 0.5:
      raise ValueError(f"deform amplitudes must lie in [0, 0.5], got {self.deform!r}")
    weights = (self.glyph_weights,) if isinstance(self.glyph_weights, str) else tuple(self.glyph_weights)
    if not weights or any(w not in GLYPH_WEIGHTS for w in weights):
      raise ValueError(f"glyph_weights must be a non-empty subset of {GLYPH_WEIGHTS},"
                       f" got {self.glyph_weights!r}")
    object.__setattr__(self, "glyph_weights", weights)
    ar = _pair(self.albedo_range, "albedo_range", low=0.0)
    if ar[0] <= 0 or ar[1] > 1:
      raise ValueError(f"albedo_range must lie in (0, 1], got {self.albedo_range!r}")
    object.__setattr__(self, "albedo_range", ar)
    motions = (self.motions,) if isinstance(self.motions, str) else tuple(self.motions)
    if not motions or any(m not in MOTIONS for m in motions):
      raise ValueError(f"motions must be a non-empty subset of {MOTIONS}, got {self.motions!r}")
    object.__setattr__(self, "motions", motions)
    for name in ("kinds", "dynamic_kinds"):
      value = getattr(self, name)
      if isinstance(value, str):
        value = (value,)
      value = tuple(value)
      if not value or any(k not in KINDS for k in value):
        raise ValueError(f"{name} must be a non-empty subset of {KINDS}, got {getattr(self, name)!r}")
      object.__setattr__(self, name, value)
    for name, low, high in (("lateral_extent", 0.0, None), ("texture_probability", 0.0, 1.0),
                            ("max_tilt", 0.0, math.pi / 2), ("frame_rate", 0.0, None),
                            ("min_gap", 0.0, None)):
      v = getattr(self, name)
      if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or not math.isfinite(v):
        raise ValueError(f"{name} must be a finite number, got {v!r}")
      if v < low or (high is not None and v > high) or (name == "frame_rate" and v <= 0):
        raise ValueError(f"{name} out of range, got {v!r}")
      object.__setattr__(self, name, float(v))
    s = self.supersample
    if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or not 1 <= s <= 16:
      raise ValueError(f"supersample must be an integer in [1, 16], got {s!r}")
    object.__setattr__(self, "supersample", int(s))

  @classmethod
  def from_dict(cls, d: Mapping) -> "SceneParams":
    """Build from a plain dict (e.g. a config's ``data.scene``); unknown keys raise.

    ``max_tilt`` is read in **degrees** here (``max_tilt_deg``), everything else as in the
    attributes.
    """
    d = dict(d)
    if "max_tilt_deg" in d:
      d["max_tilt"] = math.radians(float(d.pop("max_tilt_deg")))
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - names)
    if unknown:
      raise ValueError(f"unknown scene parameter(s) {unknown}; known: {sorted(names)}")
    return cls(**d)

  def to_dict(self) -> dict:
    """Plain JSON-able dict (``max_tilt`` as ``max_tilt_deg``), inverse of :meth:`from_dict`."""
    d = dataclasses.asdict(self)
    d["max_tilt_deg"] = math.degrees(d.pop("max_tilt"))
    for name, default in _LATER_FIELDS.items():  # absent at defaults: older files keep their keys
      if d[name] == default:
        d.pop(name)
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

  def check_setup(self, setup: Setup) -> None:
    """Raise ``ValueError`` if the scenes cannot fit the capture ``setup``."""
    if self.depth_range[1] >= setup.max_depth:
      raise ValueError(f"scene depth_range {self.depth_range} m reaches beyond the Setup's"
                       f" maximum depth {setup.max_depth:.3f} m; use more or wider time bins")
    if self.lateral_extent > setup.wall_size / 2:
      raise ValueError(f"scene lateral_extent {self.lateral_extent} m exceeds half the wall"
                       f" ({setup.wall_size / 2} m)")


# ----------------------------------------------------------------- objects
@dataclasses.dataclass(frozen=True, eq=False)
class SceneObject:
  """One rigid object.

  Attributes:
    kind: one of :data:`KINDS`.
    anchor: ``[3]`` world position (metres) of the local origin; for the
      dynamic object, its position at time 0 is ``Scene.helix`` at ``t = 0``.
    rotation: ``[3, 3]`` local-to-world rotation (columns: local axes in world).
    size: extent, metres.
    radius: bounding-sphere radius about the anchor, metres.
    shape: kind parameters: ``half_extents [3]`` (box, bar), ``radius``
      (sphere), ``major``/``minor`` (torus), ``polygons`` (tuple of ``[N, 2]``
      local outlines, even-odd rule; planar kinds), ``char`` (letter, digit).
    texture: ``{"name": ..., ...}`` (see :data:`TEXTURES`).
    dynamic: whether it follows the helix.
  """

  kind: str
  anchor: np.ndarray
  rotation: np.ndarray
  size: float
  radius: float
  shape: dict
  texture: dict
  dynamic: bool = False

  def describe(self) -> dict:
    """JSON-able summary (no outlines)."""
    shape = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.shape.items()
             if k != "polygons"}
    texture = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.texture.items()}
    return {"kind": self.kind, "dynamic": self.dynamic, "anchor": self.anchor.tolist(),
            "rotation": self.rotation.tolist(), "size": self.size, "radius": self.radius,
            "shape": shape, "texture": texture}


@dataclasses.dataclass(frozen=True)
class Helix:
  """A helical path ``p(t) = center + r (cos th u + sin th v) + pitch * (th - phase) / (2 pi) * axis``.

  with ``th = phase + angular_speed * t`` (``t`` seconds) and ``v = axis x u``.

  Attributes:
    center: ``[3]`` a point on the helix axis, metres.
    axis: ``[3]`` unit axis direction.
    ref: ``[3]`` unit vector orthogonal to ``axis`` (``th = 0`` direction).
    radius: metres.
    pitch: axial advance per turn (signed), metres.
    phase: ``th`` at ``t = 0``, radians.
    angular_speed: radians per second (signed).
  """

  center: np.ndarray
  axis: np.ndarray
  ref: np.ndarray
  radius: float
  pitch: float
  phase: float
  angular_speed: float

  def positions(self, times) -> np.ndarray:
    """``[N, 3]`` float64 positions (metres) at ``times`` ``[N]`` (seconds)."""
    t = np.asarray(times, np.float64).reshape(-1)
    swept = self.angular_speed * t
    th = self.phase + swept
    v = np.cross(self.axis, self.ref)
    return (self.center[None] + self.radius * (np.cos(th)[:, None] * self.ref[None]
                                               + np.sin(th)[:, None] * v[None])
            + (self.pitch * swept / (2 * math.pi))[:, None] * self.axis[None])

  def describe(self) -> dict:
    return {"center": self.center.tolist(), "axis": self.axis.tolist(), "ref": self.ref.tolist(),
            "radius": self.radius, "pitch": self.pitch, "phase": self.phase,
            "angular_speed": self.angular_speed}


@dataclasses.dataclass(frozen=True)
class Line:
  """A straight path at constant velocity: ``p(t) = start + (end - start) t / duration``.

  Attributes:
    start, end: ``[3]`` positions at ``t = 0`` and ``t = duration``, metres.
    duration: seconds (0 for a one-frame scene: the path is ``start``).
  """

  start: np.ndarray
  end: np.ndarray
  duration: float

  def positions(self, times) -> np.ndarray:
    """``[N, 3]`` float64 positions (metres) at ``times`` ``[N]`` (seconds)."""
    t = np.asarray(times, np.float64).reshape(-1)
    u = t / self.duration if self.duration > 0 else np.zeros_like(t)
    return self.start[None] + u[:, None] * (self.end - self.start)[None]

  def describe(self) -> dict:
    return {"start": self.start.tolist(), "end": self.end.tolist(), "duration": self.duration}


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
  """Static objects plus one dynamic object on a path, over ``num_frames`` frames.

  Attributes:
    objects: the static objects, then the dynamic one (last).
    helix: the helix drawn for the dynamic object (its path unless ``line``).
    num_frames: ``F``.
    frame_rate: frames per second (frame ``f`` at ``t = f / frame_rate``).
    seed: the seed it was drawn from.
    line: the dynamic object's straight path, when its motion is ``"line"``.
    spin_axis, spin_speed: the dynamic object turns about ``spin_axis``
      ``[3]`` (unit, through its anchor) at ``spin_speed`` rad/s (0: it does not).
    deform_amplitude, deform_angle, deform_speed, deform_phase: the planar
      dynamic object's stretch ``exp(a sin(w t + phi))`` along the in-plane
      direction at ``deform_angle`` (radians from its local x axis), ``w``
      in rad/s; amplitude 0: rigid (:meth:`deformation`).
  """

  objects: tuple[SceneObject, ...]
  helix: Helix
  num_frames: int
  frame_rate: float
  seed: int
  line: Line | None = None
  spin_axis: np.ndarray | None = None
  spin_speed: float = 0.0
  deform_amplitude: float = 0.0
  deform_angle: float = 0.0
  deform_speed: float = 0.0
  deform_phase: float = 0.0

  @property
  def deforms(self) -> bool:
    """Whether the dynamic object changes shape over the sequence (non-rigid motion)."""
    return self.deform_amplitude > 0.0

  @property
  def motion(self) -> str:
    """``"line"`` or ``"helix"``."""
    return "helix" if self.line is None else "line"

  @property
  def path(self) -> Helix | Line:
    """The dynamic object's path."""
    return self.helix if self.line is None else self.line

  @property
  def dynamic_index(self) -> int:
    """Index of the dynamic object in :attr:`objects`."""
    return next(i for i, o in enumerate(self.objects) if o.dynamic)

  @property
  def times(self) -> np.ndarray:
    """``[F]`` float64 frame times, seconds."""
    return np.arange(self.num_frames) / self.frame_rate

  @property
  def trajectory(self) -> np.ndarray:
    """``[F, 3]`` float64 anchor position of the dynamic object per frame, metres."""
    return self.path.positions(self.times)

  def anchor(self, index: int, frame: int) -> np.ndarray:
    """``[3]`` world position of object ``index`` at ``frame``."""
    obj = self.objects[index]
    if obj.dynamic:
      return self.path.positions([frame / self.frame_rate])[0]
    return obj.anchor

  def rotation(self, index: int, frame: int) -> np.ndarray:
    """``[3, 3]`` local-to-world rotation of object ``index`` at ``frame``."""
    obj = self.objects[index]
    if not obj.dynamic or self.spin_speed == 0.0:
      return obj.rotation
    return _axis_angle(self.spin_axis, self.spin_speed * frame / self.frame_rate) @ obj.rotation

  def deformation(self, index: int, frame: int) -> np.ndarray:
    """``[2, 2]`` in-plane map of object ``index`` at ``frame`` (local x, y; identity if rigid).

    ``M = R(angle) diag(e^s, e^-s) R(angle)^T`` with ``s = a sin(w t + phi)``:
    symmetric, determinant 1 (areas kept), singular values ``e^|s| <= e^a``.
    """
    obj = self.objects[index]
    if not obj.dynamic or not self.deforms:
      return np.eye(2)
    stretch = self.deform_amplitude * math.sin(self.deform_speed * frame / self.frame_rate
                                               + self.deform_phase)
    c, s = math.cos(self.deform_angle), math.sin(self.deform_angle)
    rot = np.array([[c, -s], [s, c]])
    return rot @ np.diag([math.exp(stretch), math.exp(-stretch)]) @ rot.T

  def posed(self, index: int, frame: int) -> SceneObject:
    """Object ``index`` at its anchor, rotation and (planar, non-rigid) deformation of ``frame``.

    A deformed object's ``shape`` gains ``"warp"``: the ``[2, 2]``
    :meth:`deformation` that maps its reference outline (``polygons``) and
    texture coordinates to the frame's.
    """
    obj = self.objects[index]
    if not obj.dynamic:
      return obj
    posed = dataclasses.replace(obj, anchor=self.anchor(index, frame),
                                rotation=self.rotation(index, frame))
    if self.deforms:
      posed = dataclasses.replace(posed, shape={**obj.shape, "warp": self.deformation(index, frame)})
    return posed

  def describe(self) -> dict:
    """JSON-able summary of the scene (objects, path, frames)."""
    d = {"generator_version": GENERATOR_VERSION, "seed": self.seed,
         "num_frames": self.num_frames, "frame_rate": self.frame_rate,
         "helix": self.helix.describe(), "objects": [o.describe() for o in self.objects]}
    if self.line is not None:
      d["line"] = self.line.describe()
    if self.spin_speed:
      d["spin"] = {"axis": self.spin_axis.tolist(), "speed": self.spin_speed}
    if self.deforms:
      d["deform"] = {"amplitude": self.deform_amplitude, "angle": self.deform_angle,
                     "speed": self.deform_speed, "phase": self.deform_phase}
    return d


# ----------------------------------------------------------------- glyphs
@functools.lru_cache(maxsize=128)
def glyph_polygons(char: str, weight: str = "bold") -> tuple[np.ndarray, ...]:
  """Outlines of ``char`` in DejaVu Sans Bold (``weight="bold"``) or DejaVu Sans (``"regular"``).

  Centred, largest side 1.

  Returns:
    tuple of ``[N, 2]`` float64 closed outlines (x along scan columns, y
    along scan rows, so the glyph reads upright with row 0 on top); a point is
    inside the glyph when it is inside an odd number of them (holes included).
  """
  if not isinstance(char, str) or len(char) != 1 or char not in _LETTERS + _DIGITS:
    raise ValueError(f"char must be one of A-Z or 0-9, got {char!r}")
  if weight not in GLYPH_WEIGHTS:
    raise ValueError(f"weight must be one of {GLYPH_WEIGHTS}, got {weight!r}")
  import matplotlib
  from matplotlib.font_manager import FontProperties
  from matplotlib.textpath import TextPath
  font = pathlib.Path(matplotlib.get_data_path()) / "fonts" / "ttf" / _FONT_FILES[weight]
  path = TextPath((0, 0), char, size=1.0, prop=FontProperties(fname=str(font)))
  polys = [np.asarray(p, np.float64) for p in path.to_polygons(closed_only=True) if len(p) >= 3]
  pts = np.concatenate(polys)
  lo, hi = pts.min(0), pts.max(0)
  centre, scale = (lo + hi) / 2, float(np.max(hi - lo))
  # Flip y so that the glyph reads upright in an image whose row 0 is the
  # first scan row (y = -wall/2), as ``imshow`` shows it by default.
  out = tuple((p - centre) / scale * np.array([1.0, -1.0]) for p in polys)
  for p in out:
    p.setflags(write=False)
  return out


def inside_polygons(u: np.ndarray, v: np.ndarray, polygons) -> np.ndarray:
  """Even-odd point-in-polygon test of points ``(u, v)`` ``[P]`` against outlines."""
  inside = np.zeros(u.shape, bool)
  for poly in polygons:
    x1, y1 = poly[:, 0], poly[:, 1]
    x2, y2 = np.roll(x1, -1), np.roll(y1, -1)
    for a, b, c, d in zip(x1, y1, x2, y2):
      if b == d:
        continue
      crosses = (b > v) != (d > v)
      x_cross = a + (v - b) * (c - a) / (d - b)
      inside ^= crosses & (u < x_cross)
  return inside


# -------------------------------------------------------------- sampling
def _random_rotation(rng) -> np.ndarray:
  """Uniform random rotation matrix (from a unit quaternion)."""
  q = rng.normal(size=4)
  w, x, y, z = q / np.linalg.norm(q)
  return np.array([
      [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
  ])


def _axis_angle(axis, angle) -> np.ndarray:
  axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
  k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
  return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def _facing_rotation(rng, max_tilt) -> np.ndarray:
  """In-plane spin, then a tilt of the normal (local z) by at most ``max_tilt`` from world z."""
  spin = _axis_angle([0, 0, 1], rng.uniform(-math.pi / 6, math.pi / 6))
  phi = rng.uniform(0, 2 * math.pi)
  tilt = _axis_angle([math.cos(phi), math.sin(phi), 0.0], rng.uniform(0, max_tilt))
  return tilt @ spin


def _texture(rng, size, force: bool, probability: float, albedo_range=(0.5, 1.0)) -> dict:
  base = float(rng.uniform(*albedo_range))
  if not force and rng.uniform() >= probability:
    return {"name": "uniform", "albedo": base}
  name = str(rng.choice(TEXTURES[1:]))
  period = float(size * rng.uniform(0.15, 0.35))
  low = float(base * rng.uniform(0.2, 0.6))
  if name == "checker":
    return {"name": name, "albedo": base, "low": low, "period": period,
            "offset": rng.uniform(0, period, 3)}
  if name == "stripes":
    k = rng.normal(size=3)
    return {"name": name, "albedo": base, "low": low, "period": period,
            "direction": k / np.linalg.norm(k)}
  waves = rng.normal(size=(3, 3))
  waves *= (2 * math.pi / (size * rng.uniform(0.2, 0.6, 3)))[:, None] / np.linalg.norm(waves, axis=1,
                                                                                     keepdims=True)
  return {"name": "noise", "albedo": base, "low": low, "waves": waves,
          "phases": rng.uniform(0, 2 * math.pi, 3)}


def _disc(centre, radius) -> np.ndarray:
  """``[_DISC_CORNERS, 2]`` regular polygon inscribed in the circle, with the circle's area."""
  ang = np.arange(_DISC_CORNERS) * 2 * math.pi / _DISC_CORNERS
  n = _DISC_CORNERS
  r = radius * math.sqrt(2 * math.pi / (n * math.sin(2 * math.pi / n)))   # same area as the disc
  return np.asarray(centre, np.float64) + r * np.stack([np.cos(ang), np.sin(ang)], -1)


def chart_polygons(kind: str, count: int, size: float, fill: float) -> tuple[np.ndarray, ...]:
  """Outlines of a resolution chart ``kind`` (``"bars"`` or ``"dots"``), centred, in metres.

  ``bars``: ``count`` bars of width ``size / (2 count - 1)`` (bars and gaps
  equally wide, so the chart spans ``size`` along x) and height ``fill *
  size``. ``dots``: a ``count x count`` grid of pitch ``size / count``, discs
  of radius ``fill * pitch / 2`` (each a polygon of the disc's area).
  Returns ``[N, 2]`` outlines (local x, y), disjoint.
  """
  if kind == "bars":
    width = size / (2 * count - 1)
    h = fill * size / 2
    left = -size / 2 + 2 * width * np.arange(count)
    return tuple(np.array([[x, -h], [x + width, -h], [x + width, h], [x, h]]) for x in left)
  if kind == "dots":
    pitch = size / count
    centres = -size / 2 + pitch * (np.arange(count) + 0.5)
    return tuple(_disc((x, y), fill * pitch / 2) for y in centres for x in centres)
  raise ValueError(f"chart kind must be one of {CHART_KINDS}, got {kind!r}")


def _shape(rng, kind, size, weights=("bold",)) -> tuple[dict, float]:
  """(kind parameters, bounding radius) for an object of extent ``size``."""
  if kind in ("letter", "digit"):
    char = str(rng.choice(list(_LETTERS if kind == "letter" else _DIGITS)))
    weight = str(rng.choice(list(weights))) if len(weights) > 1 else weights[0]
    polys = tuple(p * size for p in glyph_polygons(char, weight))
    shape = {"char": char, "polygons": polys}
    if weight != "bold":
      shape["weight"] = weight
    return shape, size / math.sqrt(2)
  if kind == "bars":
    count, fill = int(rng.integers(3, 7)), float(rng.uniform(0.6, 1.0))
    return ({"count": count, "fill": fill, "polygons": chart_polygons(kind, count, size, fill)},
            math.hypot(size, fill * size) / 2)
  if kind == "dots":
    count, fill = int(rng.integers(2, 5)), float(rng.uniform(0.5, 0.8))
    return ({"count": count, "fill": fill, "polygons": chart_polygons(kind, count, size, fill)},
            size / math.sqrt(2))
  if kind == "polygon":
    n = int(rng.integers(3, 9))
    style = str(rng.choice(["regular", "star", "irregular"]))
    if style == "star":
      n = max(n, 5)
      ang = np.arange(2 * n) * math.pi / n
      rad = np.where(np.arange(2 * n) % 2 == 0, 1.0, rng.uniform(0.4, 0.6))
    elif style == "regular":
      ang = np.arange(n) * 2 * math.pi / n
      rad = np.ones(n)
    else:
      ang = np.sort(rng.uniform(0, 2 * math.pi, n))
      rad = rng.uniform(0.6, 1.0, n)
    ang = ang + rng.uniform(0, 2 * math.pi)
    poly = (size / 2) * np.stack([rad * np.cos(ang), rad * np.sin(ang)], -1)
    return {"style": style, "corners": n, "polygons": (poly,)}, size / 2
  if kind == "plate":
    w, h = size, size * rng.uniform(0.5, 1.0)
    poly = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
    return {"width": w, "height": h, "polygons": (poly,)}, math.hypot(w, h) / 2
  if kind == "box":
    half = size / 2 * rng.uniform(0.5, 1.0, 3)
    half[rng.integers(3)] = size / 2
    return {"half_extents": half}, float(np.linalg.norm(half))
  if kind == "bar":
    thick = size * rng.uniform(0.06, 0.15) / 2
    half = np.array([size / 2, thick, thick])
    return {"half_extents": half}, float(np.linalg.norm(half))
  if kind == "sphere":
    return {"radius": size / 2}, size / 2
  if kind == "torus":
    minor_ratio = rng.uniform(0.25, 0.45)
    major = size / 2 / (1 + minor_ratio)
    return {"major": major, "minor": major * minor_ratio}, size / 2
  raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")


def _scale_texture(texture: dict, k: float) -> dict:
  """``texture`` for an object whose lengths were multiplied by ``k`` (patterns scale with it)."""
  out = dict(texture)
  for name in ("period", "offset"):
    if name in out:
      out[name] = out[name] * k
  if "waves" in out:
    out["waves"] = out["waves"] / k
  return out


def _scale_shape(shape: dict, k: float) -> dict:
  """``shape`` with every length multiplied by ``k``."""
  out = dict(shape)
  for name in ("half_extents", "radius", "major", "minor", "width", "height"):
    if name in out:
      out[name] = out[name] * k
  if "polygons" in out:
    out["polygons"] = tuple(p * k for p in out["polygons"])
  return out


def _make_object(rng, params: SceneParams, kinds, dynamic: bool) -> SceneObject:
  kind = str(rng.choice(list(kinds)))
  size = float(rng.uniform(*params.size_range))
  shape, radius = _shape(rng, kind, size, params.glyph_weights)
  cap = 0.49 * (params.depth_range[1] - params.depth_range[0])
  if radius > cap:  # the bounding sphere must fit the depth range
    shape, size, radius = _scale_shape(shape, cap / radius), size * cap / radius, cap
  if kind in PLANAR_KINDS:
    rotation = _facing_rotation(rng, params.max_tilt)
  else:
    rotation = _random_rotation(rng)
  texture = _texture(rng, size, force=kind == "plate", probability=params.texture_probability,
                     albedo_range=params.albedo_range)
  return SceneObject(kind=kind, anchor=np.zeros(3), rotation=rotation, size=size, radius=radius,
                     shape=shape, texture=texture, dynamic=dynamic)


def _orthonormal(axis) -> np.ndarray:
  """A unit vector orthogonal to ``axis``."""
  e = np.eye(3)[int(np.argmin(np.abs(axis)))]
  u = np.cross(axis, e)
  return u / np.linalg.norm(u)


def _make_helix(rng, params: SceneParams, obj_radius: float, duration: float) -> Helix:
  """A random helix whose path (over ``duration`` s) keeps the object inside the scene box."""
  axis = rng.normal(size=3)
  axis /= np.linalg.norm(axis)
  ref = _orthonormal(axis)
  radius = float(rng.uniform(*params.helix_radius))
  pitch = float(rng.uniform(*params.helix_pitch)) * float(rng.choice([-1.0, 1.0]))
  phase = float(rng.uniform(0, 2 * math.pi))
  speed = float(rng.uniform(*params.helix_speed)) * float(rng.choice([-1.0, 1.0]))
  L = params.lateral_extent
  z_lo, z_hi = params.depth_range[0] + obj_radius, params.depth_range[1] - obj_radius
  box_lo, box_hi = np.array([-L, -L, z_lo]), np.array([L, L, z_hi])
  times = np.linspace(0.0, duration, 256) if duration > 0 else np.zeros(1)
  # Shrink radius and pitch until the path fits the box; then place its centre uniformly.
  for _ in range(60):
    path = Helix(np.zeros(3), axis, ref, radius, pitch, phase, speed).positions(times)
    lo, hi = path.min(0), path.max(0)
    slack = (box_hi - box_lo) - (hi - lo)
    if np.all(slack >= 0):
      break
    radius *= 0.8
    pitch *= 0.8
  else:
    raise ValueError("cannot fit the helix into the scene box; widen depth_range or lateral_extent")
  center = rng.uniform(box_lo - lo, np.maximum(box_hi - hi, box_lo - lo))
  return Helix(center, axis, ref, radius, pitch, phase, speed)


def _make_line(rng, params: SceneParams, obj_radius: float, duration: float) -> Line:
  """A straight path between two uniform points of the scene box (the object stays inside)."""
  L = params.lateral_extent
  lo = np.array([-L, -L, params.depth_range[0] + obj_radius])
  hi = np.array([L, L, params.depth_range[1] - obj_radius])
  return Line(rng.uniform(lo, hi), rng.uniform(lo, hi), float(duration))


def make_scene(seed: int, params: SceneParams | Mapping | None = None, num_frames: int = 32,
               setup: Setup | None = None) -> Scene:
  """Draw a dynamic scene.

  Args:
    seed: integer seed (``numpy.random.default_rng(seed)`` draws everything).
    params: :class:`SceneParams` or a dict of its fields (default: defaults).
    num_frames: ``F >= 1`` frames, at ``params.frame_rate``.
    setup: optional capture to check the scene box against (depth and wall).
  Returns:
    a :class:`Scene` with ``U{num_static}`` static objects and one dynamic object.
  Raises:
    ValueError: for a bad argument, or scene bounds that do not fit ``setup``.
  """
  if params is None:
    params = SceneParams()
  elif isinstance(params, Mapping):
    params = SceneParams.from_dict(params)
  elif not isinstance(params, SceneParams):
    raise ValueError(f"params must be a SceneParams or dict, got {type(params).__name__}")
  if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or num_frames < 1:
    raise ValueError(f"num_frames must be an integer >= 1, got {num_frames!r}")
  if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
    raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
  if setup is not None:
    params.check_setup(setup)
  rng = np.random.default_rng(int(seed))
  duration = (num_frames - 1) / params.frame_rate

  dyn = _make_object(rng, params, params.dynamic_kinds, dynamic=True)
  # Non-rigid stretch, from a stream of its own; its bounding sphere grows by the largest stretch.
  deform = {}
  if params.deform[1] > 0 and dyn.kind in PLANAR_KINDS:
    deform_rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(5,)))
    deform = {"deform_amplitude": float(deform_rng.uniform(*params.deform)),
              "deform_angle": float(deform_rng.uniform(0, math.pi)),
              "deform_speed": float(deform_rng.uniform(*params.helix_speed)),
              "deform_phase": float(deform_rng.uniform(0, 2 * math.pi))}
    grown = dyn.radius * math.exp(deform["deform_amplitude"])
    cap = 0.49 * (params.depth_range[1] - params.depth_range[0])
    if grown > cap:   # as _make_object: the (stretched) bounding sphere must fit the depth range
      k = cap / grown
      dyn = dataclasses.replace(dyn, shape=_scale_shape(dyn.shape, k), size=dyn.size * k,
                                radius=dyn.radius * k, texture=_scale_texture(dyn.texture, k))
    dyn = dataclasses.replace(dyn, radius=dyn.radius * math.exp(deform["deform_amplitude"]))
  helix = _make_helix(rng, params, dyn.radius, duration)
  # Motion and spin come from a stream of their own: the default scenes stay as they were.
  motion_rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(4,)))
  motion = str(motion_rng.choice(list(params.motions))) if len(params.motions) > 1 else params.motions[0]
  line = _make_line(motion_rng, params, dyn.radius, duration) if motion == "line" else None
  spin_axis, spin_speed = None, 0.0
  if params.spin_speed[1] > 0:
    spin_axis = motion_rng.normal(size=3)
    spin_axis /= np.linalg.norm(spin_axis)
    spin_speed = float(motion_rng.uniform(*params.spin_speed)) * float(motion_rng.choice([-1.0, 1.0]))
  moving = line if line is not None else helix
  path = moving.positions(np.linspace(0.0, duration, 256) if duration > 0 else np.zeros(1))
  dyn = dataclasses.replace(dyn, anchor=moving.positions([0.0])[0])

  statics = []
  n_static = int(rng.integers(params.num_static[0], params.num_static[1] + 1))
  L = params.lateral_extent
  for _ in range(n_static):
    obj = _make_object(rng, params, params.kinds, dynamic=False)
    z_lo, z_hi = params.depth_range[0] + obj.radius, params.depth_range[1] - obj.radius
    anchor = None
    for _ in range(100):  # rejection sampling of a non-overlapping place
      anchor = np.array([rng.uniform(-L, L), rng.uniform(-L, L), rng.uniform(z_lo, z_hi)])
      ok = np.min(np.linalg.norm(path - anchor, axis=1)) > obj.radius + dyn.radius + params.min_gap
      ok = ok and all(np.linalg.norm(o.anchor - anchor) > obj.radius + o.radius + params.min_gap
                      for o in statics)
      if ok:
        break
    statics.append(dataclasses.replace(obj, anchor=anchor))
  return Scene(objects=tuple(statics) + (dyn,), helix=helix, num_frames=int(num_frames),
               frame_rate=params.frame_rate, seed=int(seed), line=line, spin_axis=spin_axis,
               spin_speed=spin_speed, **deform)


# ------------------------------------------------------------- ray casting
def texture_albedo(tex: dict, q: np.ndarray) -> np.ndarray:
  """Texture albedo ``[P]`` at local points ``q`` ``[P, 3]``."""
  name, base = tex["name"], tex["albedo"]
  if name == "uniform":
    return np.full(q.shape[0], base)
  if name == "checker":
    cells = np.floor((q + tex["offset"]) / tex["period"]).astype(np.int64).sum(1)
    return np.where(cells % 2 == 0, base, tex["low"])
  if name == "stripes":
    phase = (q @ tex["direction"]) / tex["period"]
    return np.where(phase - np.floor(phase) < 0.5, base, tex["low"])
  s = np.sin(q @ tex["waves"].T + tex["phases"]).mean(1)  # in [-1, 1]
  return tex["low"] + (base - tex["low"]) * 0.5 * (1 + s)


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


# ------------------------------------------------------------ rasterising
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

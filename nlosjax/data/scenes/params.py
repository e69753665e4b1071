"""Scene parameters (:class:`SceneParams`), the generator version and the kinds, textures and motions."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from nlosjax.physics.setup import Setup

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

#: Paths of the dynamic object (:attr:`SceneParams.motions`).
MOTIONS = ("helix", "line")

#: Albedo textures.
TEXTURES = ("uniform", "checker", "stripes", "noise")



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

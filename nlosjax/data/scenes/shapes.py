"""Object shapes and textures: glyph and chart outlines, point-in-polygon, shape and texture draws, albedo."""

from __future__ import annotations

import functools
import math
import pathlib

import numpy as np

from nlosjax.data.scenes.params import CHART_KINDS, GLYPH_WEIGHTS, KINDS, TEXTURES

_FONT_FILES = {"bold": "DejaVuSans-Bold.ttf", "regular": "DejaVuSans.ttf"}
_DISC_CORNERS = 32     # corners of the polygon that outlines a chart's dot
_LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"
_DIGITS = "0123456789"


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

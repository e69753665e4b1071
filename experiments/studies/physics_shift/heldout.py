"""The held-out renderer: dynamic test sequences from physics no training renderer shares code with.

Written for :mod:`experiments.studies.physics_shift` with NumPy and h5py only (no
:mod:`nlosjax.data`, no :mod:`nlosjax.physics`); the planar shapes come from
:func:`experiments.independent_set.shape_mask` (stroke-font letters, charts,
rings, crosses, ellipses, triangles, L-shapes), themselves written apart from
the training generator. Per frame, each object is a fronto-parallel planar
shape at its own depth, rasterised on ``supersample`` x ``supersample``
sub-pixel rays per scan pixel and z-buffered; every ray that hits is a point
``(x, y, z)`` with albedo ``a`` and a ``1 / s^2`` share of the pixel, and adds

    a / s^2 * (z / r)^(cosines * p) / r^p    at time bin floor(2 r / bin_length)

to each scan point's histogram (:func:`point_returns`; ``r`` the exact
distance, ``p`` the falloff, ``cosines`` 1 for Lambertian cosines at the wall
and the object, 0 for none). The dynamic object translates at constant
velocity, spins in its plane and oscillates in depth. Counts: the clean
transient scaled to a photon budget ``S`` per scan point per frame (mean
over the sequence), blurred by a Gaussian of FWHM ``jitter`` (its own
kernel), plus flat ambient light and dark counts, then Poisson.

:data:`CONDITIONS` are the test sets, each a change from ``base`` (objects
0.5-1.5 m away, 0.25-0.6 m across, anchored within 0.4 m of the wall centre,
no cosines, ``r^-4``, a 60 ps Gaussian jitter, the preset's photon, ambient
and dark-count ranges).
"""

from __future__ import annotations

import json
import math
import pathlib

import h5py
import numpy as np

__all__ = ["CONDITIONS", "GENERATOR_VERSION", "point_returns", "make_sequence", "write_condition",
           "ensure_condition"]

GENERATOR_VERSION = "experiments.studies.physics_shift.heldout/1"

#: Test conditions: name -> changes from the base condition (``depth``/``size`` in m;
#: ``photons``/``ambient`` scale the preset's ranges).
#: A condition's seed stream is its position here: new conditions go last.
CONDITIONS = {
    "base": {},
    "far": {"depth": (0.9, 1.8)},
    "tenth": {"photons": 0.1, "ambient": 0.1},
    "ambient": {"ambient": 5.0},
    "cosines": {"cosines": 1},
    "cosines_ambient": {"cosines": 1, "ambient": 5.0},
    "retro": {"power": 2},
    "bright": {"photons": 10.0},
    "dark": {"ambient": 0.0, "dark": 0.0},
    "far_dark": {"depth": (0.9, 1.8), "ambient": 0.0, "dark": 0.0},
    "sharp": {"jitter": 0.0},
    "wide": {"lateral": 0.8},
    "small": {"size": (0.1, 0.25)},
    "large": {"size": (0.6, 1.0)},
}
BASE = {"depth": (0.5, 1.5), "size": (0.25, 0.6), "lateral": 0.4, "cosines": 0, "power": 4,
        "photons": 1.0, "ambient": 1.0, "dark": 1.0, "jitter": 60e-12}


def condition(name: str) -> dict:
  """The full parameters of a condition of :data:`CONDITIONS`."""
  if name not in CONDITIONS:
    raise ValueError(f"condition must be one of {tuple(CONDITIONS)}, got {name!r}")
  return {**BASE, **CONDITIONS[name]}


def point_returns(x, y, z, weight, scan_x, scan_y, bin_length: float, num_bins: int, *,
                  power: float = 4.0, cosines: float = 0.0) -> np.ndarray:
  """``[T, H, W]`` float64 confocal histograms of points (module docstring for the model).

  Args:
    x, y, z: ``[P]`` point coordinates, metres (``z > 0``).
    weight: ``[P]`` albedo times the point's share of a pixel.
    scan_x: ``[W]``, scan_y: ``[H]`` scan point coordinates on the wall (m).
    bin_length: metres of round-trip path per bin.
    num_bins: ``T``; later returns are dropped.
    power: falloff ``p`` of ``r^-p``.
    cosines: exponent of ``(z / r)^p``: 1 Lambertian at wall and object, 0 none.
  """
  x, y, z, weight = (np.asarray(v, np.float64).reshape(-1) for v in (x, y, z, weight))
  H, W = len(scan_y), len(scan_x)
  out = np.zeros(num_bins * H * W)
  cols = np.arange(W)[:, None]
  for i in range(H):
    d2 = (x[None, :] - np.asarray(scan_x)[:, None]) ** 2 + (y[None, :] - scan_y[i]) ** 2 + z[None, :] ** 2
    r = np.sqrt(d2)
    value = weight[None, :] * (z[None, :] / r) ** (cosines * power) / r ** power
    k = np.floor(2.0 * r / bin_length).astype(np.int64)
    ok = k < num_bins
    flat = (k * H + i) * W + cols
    out += np.bincount(flat[ok], weights=value[ok], minlength=num_bins * H * W)
  return out.reshape(num_bins, H, W)


def _gaussian(bin_width: float, fwhm: float) -> np.ndarray:
  if fwhm <= 0:
    return np.ones(1)
  sigma = fwhm / (2 * math.sqrt(2 * math.log(2))) / bin_width
  half = max(1, int(math.ceil(4 * sigma)))
  k = np.exp(-0.5 * (np.arange(-half, half + 1) / max(sigma, 1e-6)) ** 2)
  return k / k.sum()


def _objects(rng, cond: dict) -> list[dict]:
  from experiments.independent_set import BARS_RANGE, DOTS_RANGE, GLYPHS, KIND_MIX, SHAPES, STROKE_RANGE
  out = []
  for _ in range(int(rng.integers(1, 3)) + 1):              # 1-2 static + the dynamic one (last)
    kind = SHAPES[int(rng.choice(len(SHAPES), p=list(KIND_MIX.values())))]
    o = dict(kind=kind, size=float(rng.uniform(*cond["size"])), angle=float(rng.uniform(0, 2 * np.pi)),
             albedo=float(rng.uniform(0.3, 1.0)), pos=rng.uniform(-cond["lateral"], cond["lateral"], 2),
             z=float(rng.uniform(*cond["depth"])))
    if kind == "letter":
      o["glyph"] = str(rng.choice(list(GLYPHS)))
      o["stroke"] = float(rng.uniform(*STROKE_RANGE))
    elif kind in ("bars", "dots"):
      o["count"] = int(rng.integers(*(BARS_RANGE if kind == "bars" else DOTS_RANGE), endpoint=True))
    out.append(o)
  return out


def make_sequence(rng: np.random.Generator, grid, wall_size: float, bin_width: float, num_bins: int,
                  frames: int, cond: dict, *, supersample: int = 3) -> dict:
  """One scene under condition ``cond`` (:func:`condition`): clean transient and ground truth.

  Returns:
    ``{"clean": [F, T, H, W] float64 (arbitrary units), "intensity": [F, H, W]
    float32 in [0, 1], "depth": [F, H, W] float32 m (0 = empty), "objects": JSON-ready list,
    "trajectory": [F, 3] float64 the dynamic object's centre (x, y, z) per frame, m}``.
  """
  from experiments.independent_set import shape_mask
  H, W = grid
  pitch = wall_size / np.asarray(grid, np.float64)
  scan_y = -wall_size / 2 + (np.arange(H) + 0.5) * pitch[0]
  scan_x = -wall_size / 2 + (np.arange(W) + 0.5) * pitch[1]
  sub = (np.arange(supersample) + 0.5) / supersample - 0.5
  Y, X = np.meshgrid((scan_y[:, None] + sub * pitch[0]).ravel(),
                     (scan_x[:, None] + sub * pitch[1]).ravel(), indexing="ij")
  objects = _objects(rng, cond)
  velocity = rng.uniform(0.02, 0.1, 2) * rng.choice([-1, 1], 2)        # m per frame
  z_amp, z_freq = float(rng.uniform(0.02, 0.1)), float(rng.uniform(0.3, 0.8))
  spin = float(rng.uniform(-0.2, 0.2))                                 # rad per frame
  lo, hi = cond["depth"]
  bin_length = 299792458.0 * bin_width
  clean = np.zeros((frames, num_bins, H, W))
  inten = np.zeros((frames, H, W), np.float32)
  depth = np.zeros((frames, H, W), np.float32)
  trajectory = np.zeros((frames, 3))

  def pix(a):
    return a.reshape(H, supersample, W, supersample).mean(axis=(1, 3))

  for f in range(frames):
    zbuf = np.full(Y.shape, np.inf)
    alb = np.zeros(Y.shape)
    for i, o in enumerate(objects):
      pos, z, angle = o["pos"], o["z"], o["angle"]
      if i == len(objects) - 1:
        pos = pos + velocity * f
        edge = cond["lateral"] + 0.05                                # bounce inside |x|, |y| <= edge
        pos = edge - np.abs((pos + edge) % (4 * edge) - 2 * edge)
        z = float(np.clip(z + z_amp * math.sin(z_freq * f), lo, hi))
        angle = angle + spin * f
        trajectory[f] = (pos[1], pos[0], z)
      m = shape_mask(o["kind"], X - pos[1], Y - pos[0], o["size"], angle,
                     **{k: o[k] for k in ("glyph", "stroke", "count") if k in o})
      hit = m & (z < zbuf)
      zbuf = np.where(hit, z, zbuf)
      alb = np.where(hit, o["albedo"], alb)
    hit = np.isfinite(zbuf)
    clean[f] = point_returns(X[hit], Y[hit], zbuf[hit], alb[hit] / supersample ** 2, scan_x, scan_y,
                             bin_length, num_bins, power=cond["power"], cosines=cond["cosines"])
    shaded = pix(alb)
    inten[f] = shaded / shaded.max() if shaded.max() > 0 else 0
    cover = pix(hit.astype(float))
    depth[f] = np.where(cover > 0, pix(np.where(hit, zbuf, 0.0)) / np.maximum(cover, 1e-12), 0.0)
  described = [{**o, "pos": [float(v) for v in o["pos"]], "dynamic": i == len(objects) - 1}
               for i, o in enumerate(objects)]
  return {"clean": clean, "intensity": inten, "depth": depth, "objects": described,
          "trajectory": trajectory}


def condition_attr(data: dict, name: str) -> str:
  """The ``condition`` attribute (JSON) a file of condition ``name`` for preset ``data`` holds."""
  cond = condition(name)
  photons = [cond["photons"] * float(p) for p in data["photons"]]
  ambient = [cond["ambient"] * float(a) for a in data["ambient"]]
  capture = {k: data[k] for k in ("wall_size", "grid", "bin_width", "num_bins", "efficiency", "dark_counts")}
  return json.dumps({"name": name, **cond, "photons": photons, "ambient": ambient, "capture": capture},
                    sort_keys=True, default=list)


def ensure_condition(path, data: dict, name: str, sequences: int, frames: int, seed: int) -> pathlib.Path:
  """``path`` if it holds condition ``name`` for ``data`` (else written there); refuses another set's file."""
  path = pathlib.Path(path)
  if path.exists():
    with h5py.File(path, "r") as f:
      same = (f.attrs.get("generator_version") == GENERATOR_VERSION and bool(f.attrs.get("complete"))
              and f.attrs.get("condition") == condition_attr(data, name)
              and int(f.attrs.get("num_test", -1)) == sequences and int(f.attrs.get("seed", -1)) == seed)
    if not same:
      raise ValueError(f"{path} holds another held-out set (version, condition, capture, detector, count "
                       f"or seed differ); delete it to write {name!r} for this preset")
    return path
  return write_condition(path, data, name, sequences, frames, seed)


def write_condition(path, data: dict, name: str, sequences: int = 8, frames: int = 8,
                    seed: int = 0, *, progress: bool = True) -> pathlib.Path:
  """Write condition ``name``'s test sequences for the preset ``data`` section to ``path`` (HDF5).

  The layout of :mod:`experiments.independent_set` (``measurement`` uint32,
  ``clean``, ``intensity``, ``depth``, ``trajectory`` per ``test-<i>`` group), readable by
  :func:`nlosjax.evaluation.protocol.evaluate`; written to ``path.partial``
  and renamed when complete. The seed stream is ``(seed, condition index)``.
  """
  cond = condition(name)
  grid = (int(data["grid"]),) * 2 if np.isscalar(data["grid"]) else tuple(int(g) for g in data["grid"])
  wall, bw, T = float(data["wall_size"]), float(data["bin_width"]), int(data["num_bins"])
  rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(list(CONDITIONS).index(name),)))
  path = pathlib.Path(path)
  tmp = path.with_suffix(path.suffix + ".partial")
  path.parent.mkdir(parents=True, exist_ok=True)
  taps = _gaussian(bw, cond["jitter"])
  c = taps.size // 2
  photons = tuple(cond["photons"] * float(p) for p in data["photons"])
  ambient = tuple(cond["ambient"] * float(a) for a in data["ambient"])
  it = range(sequences)
  if progress:
    from tqdm import tqdm
    it = tqdm(it, desc=f"held-out renderer, {name}", unit="seq")
  with h5py.File(tmp, "w") as f:
    f.attrs.update({"format": "nlosjax-dynamic-nlos", "format_version": 1,
                    "generator_version": GENERATOR_VERSION, "wall_size": wall,
                    "grid": np.asarray(grid), "bin_width": bw, "num_bins": T, "seed": seed,
                    "num_train": 0, "num_test": sequences, "background_depth": 0.0,
                    "condition": condition_attr(data, name),
                    "complete": False})
    group = f.create_group("sequences")
    for i in it:
      scene = make_sequence(rng, grid, wall, bw, T, frames, cond)
      S = float(np.exp(rng.uniform(*np.log(photons))))
      clean = scene["clean"] * (S / float(np.mean(np.sum(scene["clean"], axis=1))))
      efficiency = float(rng.uniform(*data["efficiency"]))
      amb = float(np.exp(rng.uniform(*np.log(ambient)))) / T if ambient[1] > 0 else 0.0
      blurred = np.apply_along_axis(lambda h: np.convolve(h, taps)[c:c + T], 1, clean)
      rate = efficiency * (blurred + amb) + cond["dark"] * float(data["dark_counts"]) / T
      g = group.create_group(f"test-{i:05d}")
      g.attrs.update({"split": "test", "index": i, "efficiency": efficiency, "photons": S,
                      "objects": json.dumps(scene["objects"])})
      g["measurement"] = rng.poisson(np.maximum(rate, 0.0)).astype(np.uint32)
      g["clean"] = clean.astype(np.float32)
      g["intensity"] = scene["intensity"]
      g["depth"] = scene["depth"]
      g["trajectory"] = scene["trajectory"]
    f.attrs["complete"] = True
  tmp.replace(path)
  return path

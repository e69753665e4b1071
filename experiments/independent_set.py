"""An independent test set: dynamic sequences that share no code path with the training generator.

The main job (``python -m experiments.train``) scores its models on this set
beside its own test split (``results/table1_independent.md``), and
``python -m experiments.studies.independent_test`` scores any run on it.

The training data come from :mod:`nlosjax.data.scenes` (letters and digits
cut from font outlines, polygons, plates, boxes, spheres, tori, bars, and
charts where a preset names them, on helices or lines) rendered by
:func:`nlosjax.physics.render` (the light-cone operator) or
:mod:`nlosjax.data.surfaces`, with noise from :mod:`nlosjax.data.dataset`.
This file is written without any of them, with plain NumPy and h5py, in the
documented HDF5 layout (``docs/dataset.md``):

* **shapes** (:data:`SHAPES`, drawn with the shares of :data:`KIND_MIX`):
  fronto-parallel **letters and digits** of a hand-written single-stroke font
  (:data:`GLYPHS`: L T H N Z X V A E F K Y M 1 4 7 as polylines in a unit box,
  a point is inside when its distance to the nearest stroke segment is at most
  half the stroke width, drawn per object at 8-18 % of the glyph height; about
  a third of all objects), the two resolution charts of measured scans, a
  ``bars`` chart (3-5 parallel bars, bars and gaps equally wide) and a ``dots``
  chart (a 2 x 2 to 4 x 4 grid of discs), and rings, crosses, ellipses,
  triangles and L-shapes. These are constructions of their own (strokes, not
  the training generator's font outlines; no matplotlib). Letters and charts
  are 0.35-0.6 m across, the plain shapes 0.25-0.5 m (:data:`SIZE_RANGES`). All
  are rotated in plane, rasterised on the scan grid with ``supersample`` x ``supersample``
  sub-pixel rays, with uniform or radial-gradient albedo; 1-2 static objects
  and one dynamic object, each at its own depth, one of them possibly dim
  (albedo contrast). Each sequence stores its objects' parameters as JSON in
  its ``objects`` attribute;
* **motion**: the dynamic object moves on a straight line that bounces off
  the edges of a 0.9 m square, spins in plane, and its depth oscillates
  sinusoidally (no helix);
* **renderer**: every sub-pixel hit is a point with its exact distance ``r``
  to every scan point (not the light-cone operator): a fronto-parallel
  diffuse patch returns ``albedo * (z / r)^4 / r^4`` (cosines at the patch and
  the wall) in time bin ``floor(2 r / bin_length)``, summed by ``np.bincount``;
* **detector**: the run's detector ranges (efficiency, photon budget, ambient
  light, dark counts) and its jitter (a Gaussian or the shipped measured
  curve, convolved here with NumPy), then NumPy Poisson counts.

:data:`GENERATOR_VERSION` is stored in the file; a file written by another
version is refused rather than silently reused (version 3 added the letters
and the charts; version 2 drew the five plain shapes only).
"""

from __future__ import annotations

import json
import math
import pathlib

import h5py
import numpy as np

__all__ = ["GENERATOR_VERSION", "SHAPES", "KIND_MIX", "GLYPHS", "SIZE_RANGES", "STROKE_RANGE",
           "shape_mask", "glyph_mask", "draw_object", "make_sequence", "point_transient",
           "write_independent_set", "ensure_independent_set"]

GENERATOR_VERSION = "experiments.independent_set/3"

# The shape kinds and the share of objects each gets (summing to 1): stroke-font letters
# and digits about a third, the two resolution charts a tenth each, the five plain shapes
# of version 2 the rest.
KIND_MIX = {"letter": 0.34, "bars": 0.10, "dots": 0.10, "ring": 0.092, "cross": 0.092,
            "ellipse": 0.092, "triangle": 0.092, "ell": 0.092}
SHAPES = tuple(KIND_MIX)

# Object extent (m) per kind, drawn uniformly: letters and charts are drawn larger, so
# that their thin strokes, bars and dots span sub-pixel rays on the cpu preset's grid.
SIZE_RANGES = {**{k: (0.25, 0.5) for k in SHAPES}, "letter": (0.35, 0.6), "bars": (0.35, 0.6),
               "dots": (0.35, 0.6)}
STROKE_RANGE = (0.08, 0.18)     # letter stroke width, as a fraction of the glyph height
BARS_RANGE = (3, 5)             # number of bars in a bars chart (inclusive)
DOTS_RANGE = (2, 4)             # dots per side of a dots chart (inclusive)
DOT_RADIUS = 0.3                # disc radius, as a fraction of the dots chart's pitch

# A single-stroke font: each glyph is a tuple of polylines, vertices (x, y) in units of
# the glyph height, the glyph box x in [-0.3, 0.3], y in [-0.5, 0.5] (y up in the rotated
# frame). Strokes are drawn with round caps and joins (a capsule per segment).
GLYPHS = {
    "L": (((-0.3, 0.5), (-0.3, -0.5), (0.3, -0.5)),),
    "T": (((-0.3, 0.5), (0.3, 0.5)), ((0.0, 0.5), (0.0, -0.5))),
    "H": (((-0.3, -0.5), (-0.3, 0.5)), ((0.3, -0.5), (0.3, 0.5)), ((-0.3, 0.0), (0.3, 0.0))),
    "N": (((-0.3, -0.5), (-0.3, 0.5), (0.3, -0.5), (0.3, 0.5)),),
    "Z": (((-0.3, 0.5), (0.3, 0.5), (-0.3, -0.5), (0.3, -0.5)),),
    "X": (((-0.3, 0.5), (0.3, -0.5)), ((-0.3, -0.5), (0.3, 0.5))),
    "V": (((-0.3, 0.5), (0.0, -0.5), (0.3, 0.5)),),
    "A": (((-0.3, -0.5), (0.0, 0.5), (0.3, -0.5)), ((-0.15, 0.0), (0.15, 0.0))),
    "E": (((0.3, 0.5), (-0.3, 0.5), (-0.3, -0.5), (0.3, -0.5)), ((-0.3, 0.0), (0.2, 0.0))),
    "F": (((0.3, 0.5), (-0.3, 0.5), (-0.3, -0.5)), ((-0.3, 0.0), (0.2, 0.0))),
    "K": (((-0.3, 0.5), (-0.3, -0.5)), ((0.3, 0.5), (-0.3, 0.0), (0.3, -0.5))),
    "Y": (((-0.3, 0.5), (0.0, 0.0), (0.3, 0.5)), ((0.0, 0.0), (0.0, -0.5))),
    "M": (((-0.3, -0.5), (-0.3, 0.5), (0.0, 0.0), (0.3, 0.5), (0.3, -0.5)),),
    "1": (((-0.15, 0.3), (0.05, 0.5), (0.05, -0.5)), ((-0.15, -0.5), (0.25, -0.5))),
    "4": (((0.15, -0.5), (0.15, 0.5), (-0.3, -0.15), (0.3, -0.15)),),
    "7": (((-0.3, 0.5), (0.3, 0.5), (-0.1, -0.5)),),
}


def glyph_mask(glyph: str, p: np.ndarray, q: np.ndarray, height: float, stroke: float) -> np.ndarray:
  """Boolean mask of a stroke-font glyph: within half a stroke of one of its segments.

  Args:
    glyph: a key of :data:`GLYPHS`.
    p, q: local coordinates (m), any equal shape; ``q`` up the glyph, origin its centre.
    height: glyph height (m); the glyph is ``0.6 * height`` wide (plus the stroke).
    stroke: stroke width as a fraction of ``height`` (the distance threshold is
      ``stroke * height / 2``).

  Returns:
    bool mask, ``p``'s shape.
  """
  if glyph not in GLYPHS:
    raise ValueError(f"glyph must be one of {tuple(GLYPHS)}, got {glyph!r}")
  half2 = (stroke * height / 2) ** 2
  out = np.zeros(np.broadcast(p, q).shape, bool)
  for line in GLYPHS[glyph]:
    v = np.asarray(line, np.float64) * height
    for (ax, ay), (bx, by) in zip(v[:-1], v[1:]):
      dx, dy = bx - ax, by - ay
      t = np.clip(((p - ax) * dx + (q - ay) * dy) / (dx * dx + dy * dy), 0.0, 1.0)
      out |= (p - ax - t * dx) ** 2 + (q - ay - t * dy) ** 2 <= half2
  return out


def shape_mask(kind: str, u: np.ndarray, v: np.ndarray, size: float, angle: float, *,
               glyph: str = "L", stroke: float = 0.12, count: int = 4) -> np.ndarray:
  """Boolean mask of a planar shape of extent ``size`` (m) at local coords ``u, v`` (m).

  Args:
    kind: one of :data:`SHAPES`.
    u, v: local coordinates (m), any equal shape, origin at the shape's centre.
    size: the shape's extent (m): a ring's or ellipse's diameter, a letter's height,
      a chart's side.
    angle: in-plane rotation (rad).
    glyph, stroke: the ``letter`` kind's glyph (:data:`GLYPHS`) and stroke width (a
      fraction of ``size``).
    count: the ``bars`` chart's number of bars (``size / (2 count - 1)`` wide, gaps as
      wide, ``size`` long) or the ``dots`` chart's discs per side (pitch
      ``size / count``, radius ``DOT_RADIUS * pitch``).

  Returns:
    bool mask, ``u``'s shape.
  """
  c, s = math.cos(angle), math.sin(angle)
  p, q = c * u + s * v, -s * u + c * v
  r = size / 2
  if kind == "ring":
    d = np.hypot(p, q)
    return (d <= r) & (d >= 0.55 * r)
  if kind == "cross":
    w = 0.3 * r
    return ((np.abs(p) <= r) & (np.abs(q) <= w)) | ((np.abs(q) <= r) & (np.abs(p) <= w))
  if kind == "ellipse":
    return (p / r) ** 2 + (q / (0.55 * r)) ** 2 <= 1
  if kind == "triangle":        # equilateral, pointing up in the rotated frame
    return (q >= -0.5 * r) & (q <= r - math.sqrt(3) * np.abs(p))
  if kind == "ell":
    w = 0.35 * r
    return ((np.abs(p) <= r) & (q >= -r) & (q <= -r + 2 * w)) | \
           ((p >= -r) & (p <= -r + 2 * w) & (np.abs(q) <= r))
  if kind == "letter":
    return glyph_mask(glyph, p, q, size, stroke)
  if kind == "bars":            # bar j spans p in [-r + 2 j w, -r + (2 j + 1) w]
    if count < 1:
      raise ValueError(f"count must be >= 1 for bars, got {count}")
    w = size / (2 * count - 1)
    k = np.floor((p + r) / w)
    return (np.abs(q) <= r) & (k >= 0) & (k <= 2 * count - 2) & (k % 2 == 0)
  if kind == "dots":            # disc centres at -r + (j + 1/2) pitch, j < count, both axes
    if count < 1:
      raise ValueError(f"count must be >= 1 for dots, got {count}")
    pitch = size / count
    cp = (np.clip(np.floor((p + r) / pitch), 0, count - 1) + 0.5) * pitch - r
    cq = (np.clip(np.floor((q + r) / pitch), 0, count - 1) + 0.5) * pitch - r
    return (p - cp) ** 2 + (q - cq) ** 2 <= (DOT_RADIUS * pitch) ** 2
  raise ValueError(f"kind must be one of {SHAPES}, got {kind!r}")


def draw_object(rng: np.random.Generator) -> dict:
  """One object's parameters: ``kind`` drawn from :data:`KIND_MIX`, then its own.

  Returns:
    dict with ``kind``, ``size`` (m), ``angle`` (rad), ``albedo``, ``gradient`` (bool),
    ``pos`` (``[2]`` (y, x) m), ``z`` (m), and for letters ``glyph`` and ``stroke``
    (fraction of ``size``), for charts ``count``.
  """
  kind = SHAPES[int(rng.choice(len(SHAPES), p=list(KIND_MIX.values())))]
  o = dict(kind=kind, size=float(rng.uniform(*SIZE_RANGES[kind])),
           angle=float(rng.uniform(0, 2 * np.pi)),
           albedo=float(rng.uniform(0.4, 1.0)), gradient=bool(rng.random() < 0.5),
           pos=rng.uniform(-0.35, 0.35, 2), z=float(rng.uniform(0.6, 1.4)))
  if kind == "letter":
    o["glyph"] = str(rng.choice(list(GLYPHS)))
    o["stroke"] = float(rng.uniform(*STROKE_RANGE))
  elif kind in ("bars", "dots"):
    o["count"] = int(rng.integers(*(BARS_RANGE if kind == "bars" else DOTS_RANGE), endpoint=True))
  return o


def point_transient(x, y, z, albedo, setup) -> np.ndarray:
  """``[T, H, W]`` float64 transient of fronto-parallel diffuse points (exact distances).

  Args:
    x, y, z: ``[P]`` point coordinates, metres (``z > 0``).
    albedo: ``[P]`` albedo times the point's share of a scan pixel's area.
    setup: the capture (grid, bins).
  """
  H, W = setup.grid
  T = setup.num_bins
  out = np.zeros(T * H * W)
  sx, sy = setup.scan_x, setup.scan_y
  for i in range(H):                        # one scan row at a time: [W, P] arrays
    d2 = (x[None, :] - sx[:, None]) ** 2 + (y[None, :] - sy[i]) ** 2 + z[None, :] ** 2
    r = np.sqrt(d2)
    value = albedo[None, :] * (z[None, :] / r) ** 4 / d2 ** 2
    k = np.floor(2.0 * r / setup.bin_length).astype(np.int64)
    ok = k < T
    flat = (k * H + i) * W + np.arange(W)[:, None]
    out += np.bincount(flat[ok], weights=value[ok], minlength=T * H * W)
  return out.reshape(T, H, W)


def make_sequence(rng: np.random.Generator, setup, frames: int, *, supersample: int = 4) -> dict:
  """One scene of 2-3 objects (:func:`draw_object`), the last one moving.

  Args:
    rng: the scene's generator (advanced).
    setup: the capture (grid, bins, wall size).
    frames: number of frames ``F``.
    supersample: sub-pixel rays per scan pixel along each axis.

  Returns:
    dict with ``clean`` ``[F, T, H, W]`` float64 (arbitrary units), ``intensity``
    ``[F, H, W]`` float32 in ``[0, 1]``, ``depth`` ``[F, H, W]`` float32 (m, 0 where
    empty), and ``objects``: per object a JSON-ready dict of its parameters
    (:func:`draw_object`) with ``dynamic`` (bool) and ``rays`` (``[F]`` number of
    sub-pixel rays its own mask covers per frame, before occlusion); ``trajectory``
    ``[F, 3]`` float64, the dynamic object's centre ``(x, y, z)`` per frame (m), as the
    training data store theirs.
  """
  H, W = setup.grid
  sub = (np.arange(supersample) + 0.5) / supersample - 0.5
  ys = (setup.scan_y[:, None] + sub[None, :] * setup.spacing[0]).reshape(-1)    # [H s]
  xs = (setup.scan_x[:, None] + sub[None, :] * setup.spacing[1]).reshape(-1)    # [W s]
  Y, X = np.meshgrid(ys, xs, indexing="ij")
  objects = []
  for _ in range(int(rng.integers(1, 3)) + 1):          # 1-2 static + the dynamic one (last)
    objects.append(draw_object(rng))
  if rng.random() < 0.5:                                 # albedo contrast: one dim object
    objects[int(rng.integers(len(objects)))]["albedo"] *= 0.3
  velocity = rng.uniform(0.05, 0.15, 2) * rng.choice([-1, 1], 2)      # m per frame
  z_amp, z_freq = float(rng.uniform(0.05, 0.2)), float(rng.uniform(0.2, 0.6))
  spin = float(rng.uniform(-0.3, 0.3))                                # rad per frame
  T = setup.num_bins
  area = [[] for _ in objects]
  clean = np.zeros((frames, T, H, W), np.float64)
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
      if i == len(objects) - 1:                           # bounce inside |x|, |y| <= 0.45
        pos = pos + velocity * f
        pos = 0.45 - np.abs((pos + 0.45) % 1.8 - 0.9)
        z = z + z_amp * math.sin(z_freq * f)
        angle = angle + spin * f
        trajectory[f] = (pos[1], pos[0], z)
      m = shape_mask(o["kind"], X - pos[1], Y - pos[0], o["size"], angle,
                     **{k: o[k] for k in ("glyph", "stroke", "count") if k in o})
      area[i].append(int(m.sum()))
      a = o["albedo"] * (1 - 0.6 * np.hypot(X - pos[1], Y - pos[0]) / o["size"] if o["gradient"] else 1)
      hit = m & (z < zbuf)
      zbuf = np.where(hit, z, zbuf)
      alb = np.where(hit, np.clip(a, 0.03, 1.0), alb)
    hit = np.isfinite(zbuf)
    clean[f] = point_transient(X[hit], Y[hit], zbuf[hit], alb[hit] / supersample ** 2, setup)
    cover = pix(hit.astype(float))
    shaded = pix(alb)
    inten[f] = shaded / shaded.max() if shaded.max() > 0 else 0
    zsum = pix(np.where(hit, zbuf, 0.0))
    depth[f] = np.where(cover > 0, zsum / np.maximum(cover, 1e-12), 0.0)
  described = [{**o, "pos": [float(x) for x in o["pos"]], "dynamic": i == len(objects) - 1,
                 "rays": area[i]} for i, o in enumerate(objects)]
  return {"clean": clean, "intensity": inten, "depth": depth, "objects": described,
          "trajectory": trajectory}


def _jitter_taps(setup, jitter) -> tuple[np.ndarray, int]:
  """(taps summing to 1, index of zero delay) on the Setup's bins, centred on the peak.

  The measured curve (the shipped file) is sampled at 9 points per bin and
  averaged; a Gaussian of FWHM ``jitter`` seconds is sampled at bin centres.
  """
  if jitter is None:
    return np.ones(1), 0
  dt = setup.bin_width
  if jitter == "measured":
    from nlosjax.physics.noise import load_measured_jitter  # reads the shipped measured file
    t, density = load_measured_jitter()
    peak = t[int(np.argmax(density))]
    k = np.arange(math.floor((t[0] - peak) / dt + 0.5), math.floor((t[-1] - peak) / dt + 0.5) + 1)
    sub = (np.arange(9) + 0.5) / 9 - 0.5
    taps = np.interp(peak + (k[:, None] + sub[None, :]) * dt, t, density, left=0, right=0).mean(1)
    centre = int(-k[0])
  else:
    sigma = float(jitter) / (2 * math.sqrt(2 * math.log(2))) / dt
    half = max(1, int(math.ceil(4 * sigma)))
    taps = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    centre = half
  return taps / taps.sum(), centre


DETECTOR_KEYS = ("efficiency", "photons", "ambient", "dark_counts", "jitter")


def _detector(data: dict) -> str:
  """The config's detector ranges as the JSON string stored in the file (``detector`` attr)."""
  return json.dumps({k: data.get(k) for k in DETECTOR_KEYS}, sort_keys=True, default=list)


def write_independent_set(path, data: dict, sequences: int = 8, frames: int = 8,
                          seed: int = 2026, *, progress: bool = True) -> pathlib.Path:
  """Write ``sequences`` test sequences for the config ``data`` section to ``path`` (HDF5).

  Each sequence group holds ``measurement`` ``[F, T, H, W]`` uint32 counts, ``clean``
  ``[F, T, H, W]`` float32 (expected photons before the detector), ``intensity`` and
  ``depth`` ``[F, H, W]`` float32 (depth in m), ``trajectory`` ``[F, 3]`` float64 (the
  dynamic object's centre, m; files written before it was stored lack it), ``F = frames``,
  and the attributes
  ``efficiency``, ``photons`` and ``objects`` (JSON, :func:`make_sequence`). The file is
  written to ``path.partial`` and renamed when complete.
  """
  from nlosjax.data.dataset import DatasetSpec
  setup = DatasetSpec.from_config(data).setup
  rng = np.random.default_rng(seed)
  path = pathlib.Path(path)
  tmp = path.with_suffix(path.suffix + ".partial")
  path.parent.mkdir(parents=True, exist_ok=True)
  T = setup.num_bins
  taps, centre = _jitter_taps(setup, data.get("jitter"))
  it = range(sequences)
  if progress:
    from tqdm import tqdm
    it = tqdm(it, desc="independent test sequences", unit="seq")
  from nlosjax import files
  from nlosjax.data.dataset.file import LIBVER, reserve_space, trim_reserved
  with files.writing(tmp), h5py.File(tmp, "w", libver=LIBVER) as f:
    # Each sequence's space is reserved before HDF5 writes it (HDF5 crashes the process when one of
    # its writes fails: a full disk is then a clean error here); fletcher32 checksums every chunk.
    reserve_space(f, tmp)
    a = f.attrs
    a.update({"format": "nlosjax-dynamic-nlos", "format_version": 1,
              "generator_version": GENERATOR_VERSION, "wall_size": setup.wall_size,
              "grid": np.asarray(setup.grid), "bin_width": setup.bin_width, "num_bins": T,
              "seed": seed, "num_train": 0, "num_test": sequences, "background_depth": 0.0,
              "detector": _detector(data), "complete": False})
    group = f.create_group("sequences")
    for i in it:
      scene = make_sequence(rng, setup, frames)
      clean = scene["clean"]
      photons = float(np.exp(rng.uniform(*np.log(data["photons"]))))
      clean = clean * (photons / float(np.mean(np.sum(clean, axis=1))))
      efficiency = float(rng.uniform(*data["efficiency"]))
      amb = data["ambient"]
      ambient = (0.0 if amb[1] == 0 else float(np.exp(rng.uniform(*np.log(amb))))) / T
      blurred = np.apply_along_axis(lambda h: np.convolve(h, taps)[centre:centre + T], 1, clean)
      rate = efficiency * (blurred + ambient) + float(data["dark_counts"]) / T
      counts = rng.poisson(np.maximum(rate, 0.0))
      arrays = {"measurement": counts.astype(np.uint32), "clean": clean.astype(np.float32),
                "intensity": np.asarray(scene["intensity"]), "depth": np.asarray(scene["depth"]),
                "trajectory": np.asarray(scene["trajectory"])}
      reserve_space(f, tmp, sum(v.nbytes for v in arrays.values()))
      g = group.create_group(f"test-{i:05d}")
      g.attrs.update({"split": "test", "index": i, "efficiency": efficiency, "photons": photons,
                      "objects": json.dumps(scene["objects"])})
      for key, value in arrays.items():
        g.create_dataset(key, data=value, chunks=True, fletcher32=True)
      f.flush()
    reserve_space(f, tmp)
    a["complete"] = True
  with files.writing(path):
    trim_reserved(tmp)
    tmp.replace(path)
  return path


def ensure_independent_set(path, data: dict, sequences: int = 8, frames: int = 8,
                           seed: int = 2026, *, log=print) -> pathlib.Path:
  """``path`` if it holds this generator's set for ``data``'s grid, else write it there.

  Raises:
    ValueError: ``path`` exists but was written by another generator version
      or for another Setup (delete it, or choose another path).
  """
  path = pathlib.Path(path)
  if path.exists():
    from nlosjax.data.dataset import DatasetSpec
    setup = DatasetSpec.from_config(data).setup
    try:
      with h5py.File(path, "r") as f:
        version = f.attrs.get("generator_version")
        grid = tuple(int(g) for g in f.attrs.get("grid", ()))
        complete = bool(f.attrs.get("complete", False))
        detector = f.attrs.get("detector")
    except (OSError, KeyError, RuntimeError) as e:
      raise ValueError(f"{path}: the independent test set cannot be read (truncated or damaged:"
                       f" {' '.join(str(e).split())}); delete it: the main job writes it again") from None
    if version != GENERATOR_VERSION or grid != setup.grid or not complete:
      raise ValueError(f"{path} holds another independent set (generator {version!r}, grid {grid},"
                       f" complete {complete}); this run needs {GENERATOR_VERSION!r} on"
                       f" {setup.grid}: delete the file or set independent.path elsewhere")
    if detector != _detector(data):
      raise ValueError(f"{path} was made for other detector ranges ({detector}); this run's are"
                       f" {_detector(data)}: delete the file or set independent.path elsewhere")
    return path
  log(f"writing the independent test set {path} ({sequences} x {frames} frames) ...")
  return write_independent_set(path, data, sequences, frames, seed)

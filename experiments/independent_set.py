"""An independent test set: dynamic sequences that share no code path with the training generator.

The main job (``python -m experiments.train``) scores its models on this set
beside its own test split (``results/table1_independent.md``), and
``python -m benchmarks.independent_test`` scores any run on it.

The training data come from :mod:`nlosjax.data.scenes` (letters, digits,
polygons, plates, boxes, spheres, tori, bars on helices) rendered by
:func:`nlosjax.physics.render` (the light-cone operator) or
:mod:`nlosjax.data.surfaces`, with noise from :mod:`nlosjax.data.dataset`.
This file is written without any of them, with plain NumPy and h5py, in the
documented HDF5 layout (README, "Dynamic NLOS dataset"):

* **shapes**: fronto-parallel rings, crosses, ellipses, triangles and
  L-shapes, rasterised on the scan grid with ``supersample`` x
  ``supersample`` sub-pixel rays, uniform or radial-gradient albedo; 1-2
  static objects and one dynamic object, each at its own depth, one of them
  possibly dim (albedo contrast);
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
version is refused rather than silently reused.
"""

from __future__ import annotations

import json
import math
import pathlib

import h5py
import numpy as np

__all__ = ["GENERATOR_VERSION", "SHAPES", "shape_mask", "make_sequence", "point_transient",
           "write_independent_set", "ensure_independent_set"]

GENERATOR_VERSION = "experiments.independent_set/2"
SHAPES = ("ring", "cross", "ellipse", "triangle", "ell")


def shape_mask(kind: str, u: np.ndarray, v: np.ndarray, size: float, angle: float) -> np.ndarray:
  """Boolean mask of a planar shape of extent ``size`` (m) at local coords ``u, v`` (m)."""
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
  raise ValueError(f"kind must be one of {SHAPES}, got {kind!r}")


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
  """One scene: ``clean`` ``[F, T, H, W]`` (arbitrary units), ``intensity``, ``depth`` ``[F, H, W]``."""
  H, W = setup.grid
  sub = (np.arange(supersample) + 0.5) / supersample - 0.5
  ys = (setup.scan_y[:, None] + sub[None, :] * setup.spacing[0]).reshape(-1)    # [H s]
  xs = (setup.scan_x[:, None] + sub[None, :] * setup.spacing[1]).reshape(-1)    # [W s]
  Y, X = np.meshgrid(ys, xs, indexing="ij")
  objects = []
  for _ in range(int(rng.integers(1, 3)) + 1):          # 1-2 static + the dynamic one (last)
    objects.append(dict(kind=str(rng.choice(SHAPES)), size=float(rng.uniform(0.25, 0.5)),
                        angle=float(rng.uniform(0, 2 * np.pi)),
                        albedo=float(rng.uniform(0.4, 1.0)), gradient=bool(rng.random() < 0.5),
                        pos=rng.uniform(-0.35, 0.35, 2), z=float(rng.uniform(0.6, 1.4))))
  if rng.random() < 0.5:                                 # albedo contrast: one dim object
    objects[int(rng.integers(len(objects)))]["albedo"] *= 0.3
  velocity = rng.uniform(0.05, 0.15, 2) * rng.choice([-1, 1], 2)      # m per frame
  z_amp, z_freq = float(rng.uniform(0.05, 0.2)), float(rng.uniform(0.2, 0.6))
  spin = float(rng.uniform(-0.3, 0.3))                                # rad per frame
  T = setup.num_bins
  clean = np.zeros((frames, T, H, W), np.float64)
  inten = np.zeros((frames, H, W), np.float32)
  depth = np.zeros((frames, H, W), np.float32)

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
      m = shape_mask(o["kind"], X - pos[1], Y - pos[0], o["size"], angle)
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
  return {"clean": clean, "intensity": inten, "depth": depth}


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
  """Write ``sequences`` test sequences for the config ``data`` section to ``path`` (HDF5)."""
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
  with h5py.File(tmp, "w") as f:
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
      g = group.create_group(f"test-{i:05d}")
      g.attrs.update({"split": "test", "index": i, "efficiency": efficiency, "photons": photons})
      g["measurement"] = counts.astype(np.uint32)
      g["clean"] = clean.astype(np.float32)
      g["intensity"] = scene["intensity"]
      g["depth"] = scene["depth"]
    a["complete"] = True
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
    with h5py.File(path, "r") as f:
      version = f.attrs.get("generator_version")
      grid = tuple(int(g) for g in f.attrs.get("grid", ()))
      complete = bool(f.attrs.get("complete", False))
      detector = f.attrs.get("detector")
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

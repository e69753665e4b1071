"""Dynamic NLOS datasets: simulate sequences, store them in HDF5, load frame triplets.

Generation (:func:`simulate_sequence`, :func:`write_dataset`): each sequence
is drawn from its own seed, ``sequence_seed(base_seed, split, index)``; its
scene (:mod:`nlosjax.data.scenes`) is rasterised per frame into an albedo
volume, intensity and depth maps; :func:`nlosjax.physics.render` gives the
noise-free transient (gated to the scene's depth range, :func:`render_setup`),
or, with ``renderer="transport"``, :func:`nlosjax.data.surfaces.render_scene`
renders the objects' whole surfaces by light transport;
the SPAD counts follow :func:`nlosjax.physics.expected_counts` with
per-sequence efficiency ``eta ~ U(efficiency)``, photon budget ``S`` and
ambient light log-uniform in their ranges, dark counts and timing jitter,
drawn by NumPy's Poisson sampler (or :func:`nlosjax.physics.add_spad_noise`
with ``noise_sampler="jax"``).

Units. ``clean`` is the expected number of *incident* signal photons per time
bin: ``signal_scale * render(albedo)``, with ``signal_scale`` chosen so that
the mean over frames and scan points of ``sum_t clean`` is ``S`` (the budget
is per sequence, so a frame where the object comes closer is brighter). It is
stored with 12 mantissa bits (relative rounding <= 1.2e-4) and values below
1e-6 of its peak set to 0, which makes files 3x smaller; the measurement is
drawn from the stored values. The measurement is ``Poisson(eta * (clean (*)
g + ambient) + dark_counts)`` per bin (``g`` the jitter kernel; ``ambient``
and ``dark_counts`` per bin), i.e. :func:`measurement_rate`.

HDF5 layout (:data:`FORMAT_NAME`, version :data:`FORMAT_VERSION`)::

  /                                  attrs: format, format_version, generator_version,
                                     nlosjax_version, wall_size (m), grid [H, W],
                                     bin_width (s), num_bins, spec (JSON of the DatasetSpec),
                                     seed, num_train, num_test, num_val, background_depth (m),
                                     complete, created
  /sequences/<split>-<index:05d>/    attrs: split ("train" | "test" | "val"), index, seed, efficiency,
                                     photons, signal_scale, ambient (per bin), dark_counts
                                     (per bin), jitter, frame_rate (Hz), helix_center [3],
                                     helix_axis [3], helix_ref [3], helix_radius, helix_pitch,
                                     helix_phase, helix_angular_speed (rad/s), dynamic_index,
                                     render_depth_range [2], kinds (JSON list), scene (JSON),
                                     complete; with a non-default motion also motion
                                     ("helix" | "line"; helix_* then describe the unused
                                     helix, the path is in scene) and spin_speed (rad/s)
      measurement  [F, T, H, W] uint16 (uint32 when a count exceeds 65535) SPAD counts
      clean        [F, T, H, W] float32 expected incident signal photons (optional)
      albedo       [F, T, H, W] float32 shaded albedo volume (optional)
      intensity    [F, H, W]    float32 in [0, 1]
      depth        [F, H, W]    float32 metres; background_depth (0) where empty
      trajectory   [F, 3]       float64 dynamic object's anchor per frame, metres

Transient-shaped datasets are chunked one frame and one scan row at a time
(``[1, T, 1, W]``) and compressed (gzip + shuffle by default): reading a frame
touches its ``H`` chunks only, an under-scanned read (every ``stride``-th row)
only ``H / stride`` of them. Maps are chunked per frame.

Under-scanning (paper: every 8th scan point, 128 -> 16) happens at load time
(:func:`undersample`: ``x[..., offset::stride, offset::stride]``), so one file
serves several input densities. The under-scanned points are the full grid's
points ``offset, offset + stride, ...``; see :func:`undersampled_positions`.

Triplets (:class:`TripletLoader`): an example is a middle frame ``m`` of a
sequence with input frames ``(m - 1, m, m + 1)``. At sequence ends, ``ends =
"valid"`` (default) uses only ``1 <= m <= F - 2``; ``"replicate"`` uses every
``m`` and repeats the end frame (``(0, 0, 1)`` and ``(F - 2, F - 1, F -
1)``). Batches are ``{"measurement": [B, 3, T, h, w], "transient": [B, T, H,
W], "intensity": [B, H, W], "depth": [B, H, W], "sequence": [B], "frame":
[B], "efficiency": [B]}``; the loader's position is one integer, the global
step (epoch = step // steps_per_epoch; the order within an epoch is a
permutation drawn from ``(seed, epoch)``), so resuming is ``iterate(step)``.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import datetime
import json
import math
import multiprocessing
import os
import pathlib
import queue
import threading
import warnings
from collections.abc import Iterator, Mapping

import h5py
import numpy as np

from nlosjax.data import scenes
from nlosjax.physics.setup import Setup

__all__ = [
    "DATASETS",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "RENDERERS",
    "SPLITS",
    "DatasetSpec",
    "DynamicDataset",
    "TripletLoader",
    "WriteResult",
    "open_dataset",
    "prefetch",
    "measurement_rate",
    "render_setup",
    "sequence_name",
    "sequence_seed",
    "simulate_sequence",
    "undersample",
    "undersampled_positions",
    "undersampled_setup",
    "write_dataset",
    "extend_dataset",
]

#: Value of the root ``format`` attribute.
FORMAT_NAME = "nlosjax-dynamic-nlos"
#: Layout version; readers refuse newer files.
FORMAT_VERSION = 1
#: Renderers of the noise-free transient (:attr:`DatasetSpec.renderer`).
RENDERERS = ("lct", "transport")
#: Split names (group-name prefixes and the ``split`` attribute). ``val`` is
#: the validation split every choice is made on (classic-method settings,
#: checkpoints, hyperparameters); ``test`` only writes final tables. The order
#: fixes each split's seed stream (:func:`sequence_seed`): new splits go last.
SPLITS = ("train", "test", "val")
#: Per-sequence datasets: name -> whether every file has it.
DATASETS = {"measurement": True, "clean": False, "albedo": False, "intensity": True,
            "depth": True, "trajectory": True}

# Keys of a config's ``data`` section that concern loading, not generation.
_LOAD_KEYS = ("input_stride", "input_offset", "loader", "path")


# -------------------------------------------------------------------- spec
def _range(value, name, *, low=None, high=None, positive=False):
  try:
    lo, hi = (float(v) for v in value)
  except (TypeError, ValueError):
    raise ValueError(f"{name} must be a (low, high) pair of numbers, got {value!r}") from None
  if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
    raise ValueError(f"{name} must be finite with low <= high, got {value!r}")
  if (low is not None and lo < low) or (high is not None and hi > high) or (positive and lo <= 0):
    raise ValueError(f"{name} must lie in {'(' if positive else '['}{low}, {high}], got {value!r}")
  return (lo, hi)


@dataclasses.dataclass(frozen=True)
class DatasetSpec:
  """Everything that determines a generated dataset (a config's ``data`` section).

  Attributes:
    setup: the full-resolution capture (ungated).
    frames: ``F`` frames per sequence.
    num_train, num_test, num_val: sequences per split (``val``: validation,
      with its own seeds; 0 in files written before the split existed).
    seed: base seed.
    efficiency: ``(low, high)`` detection efficiency, uniform per sequence.
    photons: ``(low, high)`` signal budget ``S`` (mean incident signal photons
      per scan point per frame), log-uniform per sequence.
    ambient: ``(low, high)`` incident ambient photons per scan point over the
      whole histogram (spread evenly over the ``T`` bins), log-uniform; ``(0,
      0)`` for none.
    dark_counts: dark counts per scan point over the whole histogram.
    jitter: ``"measured"``, a Gaussian FWHM in seconds, or ``None``.
    falloff: radiometric falloff of the rendered returns, ``"diffuse"``
      (``r^-4``, the default) or ``"retroreflective"`` (``r^-2``, the measured
      scans of O'Toole et al. 2018); see :func:`nlosjax.physics.render`.
      ``renderer="lct"`` only (the transport renderer draws materials per object).
    renderer: ``"lct"`` (default: :func:`nlosjax.physics.render`, the
      light-cone operator that LCT and the network's physics layer invert, on
      the orthographic albedo volume) or ``"transport"``
      (:func:`nlosjax.data.surfaces.render_scene`: whole object surfaces,
      exact path lengths, Lambertian cosines, per-scan-point visibility; ~20x
      slower, see ``benchmarks/results/data.md``). Ground-truth maps are the same.
    retroreflective: probability that an object is retroreflective (``r^-2``)
      rather than diffuse, ``renderer="transport"`` only.
    store_clean: store the noise-free ``clean`` transients.
    store_albedo: store the albedo volumes.
    compression: ``"gzip"``, ``"lzf"`` or ``None``.
    compression_level: gzip level 0-9.
    render_batch: frames rendered per call of :func:`nlosjax.physics.render`
      (part of the spec: batching may change float round-off).
    noise_sampler: ``"numpy"`` (default: :func:`measurement_rate`, i.e.
      :func:`nlosjax.physics.expected_counts`, then ``Generator.poisson`` per
      frame; exact at any rate and ~50x faster than jax's sampler on CPU) or
      ``"jax"`` (:func:`nlosjax.physics.add_spad_noise` per frame, same model).
    scene: the :class:`~nlosjax.data.scenes.SceneParams`.
  """

  setup: Setup
  frames: int = 8
  num_train: int = 32
  num_test: int = 8
  num_val: int = 0
  seed: int = 0
  efficiency: tuple[float, float] = (0.01, 0.30)
  photons: tuple[float, float] = (1e3, 1e4)
  ambient: tuple[float, float] = (50.0, 500.0)
  dark_counts: float = 0.5
  jitter: str | float | None = "measured"
  falloff: str = "diffuse"
  store_clean: bool = True
  store_albedo: bool = False
  compression: str | None = "gzip"
  compression_level: int = 4
  render_batch: int = 8
  noise_sampler: str = "numpy"
  scene: scenes.SceneParams = scenes.SceneParams()
  renderer: str = "lct"
  retroreflective: float = 0.0

  def __post_init__(self):
    if not isinstance(self.setup, Setup):
      raise ValueError(f"setup must be a nlosjax.physics.Setup, got {type(self.setup).__name__}")
    if self.setup.depth_range is not None:
      raise ValueError("setup must not have a depth_range: datasets store every time bin")
    for name, low in (("frames", 1), ("num_train", 0), ("num_test", 0), ("num_val", 0),
                      ("seed", 0),
                      ("render_batch", 1), ("compression_level", 0)):
      v = getattr(self, name)
      if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {v!r}")
      object.__setattr__(self, name, int(v))
    if self.compression_level > 9:
      raise ValueError(f"compression_level must be in [0, 9], got {self.compression_level!r}")
    object.__setattr__(self, "efficiency", _range(self.efficiency, "efficiency", low=0.0, high=1.0,
                                                  positive=True))
    object.__setattr__(self, "photons", _range(self.photons, "photons", positive=True))
    object.__setattr__(self, "ambient", _range(self.ambient, "ambient", low=0.0))
    if self.ambient[0] == 0.0 and self.ambient[1] > 0.0:
      raise ValueError(f"ambient must be (0, 0) or strictly positive for a log-uniform draw,"
                       f" got {self.ambient!r}")
    dc = self.dark_counts
    if isinstance(dc, bool) or not isinstance(dc, (int, float, np.number)) or not math.isfinite(dc) or dc < 0:
      raise ValueError(f"dark_counts must be a finite number >= 0, got {dc!r}")
    object.__setattr__(self, "dark_counts", float(dc))
    if self.jitter is not None and not isinstance(self.jitter, str):
      object.__setattr__(self, "jitter", float(self.jitter))
    from nlosjax.physics.noise import jitter_kernel
    if self.jitter is not None:
      jitter_kernel(self.setup, self.jitter)  # validates
    from nlosjax.physics.operators import check_falloff
    check_falloff(self.falloff)
    if self.renderer not in RENDERERS:
      raise ValueError(f"renderer must be one of {RENDERERS}, got {self.renderer!r}")
    r = self.retroreflective
    if isinstance(r, bool) or not isinstance(r, (int, float, np.number)) or not 0 <= r <= 1:
      raise ValueError(f"retroreflective must be a probability in [0, 1], got {r!r}")
    object.__setattr__(self, "retroreflective", float(r))
    if self.renderer == "lct" and self.retroreflective:
      raise ValueError("retroreflective is drawn per object by renderer='transport';"
                       " with renderer='lct' use falloff='retroreflective'")
    if self.renderer == "transport" and self.falloff != "diffuse":
      raise ValueError("renderer='transport' draws each object's material: set"
                       " retroreflective=1.0 instead of falloff='retroreflective'")
    if self.noise_sampler not in ("numpy", "jax"):
      raise ValueError(f'noise_sampler must be "numpy" or "jax", got {self.noise_sampler!r}')
    if self.compression not in ("gzip", "lzf", None):
      raise ValueError(f'compression must be "gzip", "lzf" or None, got {self.compression!r}')
    for name in ("store_clean", "store_albedo"):
      if not isinstance(getattr(self, name), bool):
        raise ValueError(f"{name} must be a bool, got {getattr(self, name)!r}")
    if isinstance(self.scene, Mapping):
      object.__setattr__(self, "scene", scenes.SceneParams.from_dict(self.scene))
    if not isinstance(self.scene, scenes.SceneParams):
      raise ValueError(f"scene must be a SceneParams or dict, got {type(self.scene).__name__}")
    self.scene.check_setup(self.setup)

  @classmethod
  def from_config(cls, data: Mapping, **overrides) -> "DatasetSpec":
    """Build from a config's ``data`` section (plain dicts); ``overrides`` replace keys.

    ``overrides`` may name config keys (``grid``, ``num_bins``, ...) or fields
    (``num_train``, ``frames``, ...).

    Reads ``wall_size``, ``grid`` (int or ``[H, W]``), ``bin_width``,
    ``num_bins``, ``num_sequences`` (``{"train": n, "test": m, "val": k}``,
    ``val`` optional) and the
    fields of this class; ignores the load-time keys ``input_stride``,
    ``input_offset``, ``loader`` and ``path``; raises on unknown keys.
    """
    if not isinstance(data, Mapping):
      raise ValueError(f"data config must be a mapping, got {type(data).__name__}")
    d = {k: v for k, v in data.items() if k not in _LOAD_KEYS}
    setup_keys = ("wall_size", "grid", "bin_width", "num_bins")
    d.update({k: v for k, v in overrides.items() if k in setup_keys})
    overrides = {k: v for k, v in overrides.items() if k not in setup_keys}
    try:
      setup = Setup(wall_size=d.pop("wall_size"), grid=_grid(d.pop("grid")),
                    bin_width=d.pop("bin_width"), num_bins=d.pop("num_bins"))
    except KeyError as e:
      raise ValueError(f"data config lacks {e.args[0]!r}") from None
    counts = d.pop("num_sequences", None)
    if counts is not None:
      if not isinstance(counts, Mapping) or set(counts) - set(SPLITS):
        raise ValueError(f"num_sequences must be {{'train': n, 'test': m, 'val': k}}, got {counts!r}")
      d["num_train"] = counts.get("train", 0)
      d["num_test"] = counts.get("test", 0)
      d["num_val"] = counts.get("val", 0)
    d.update(overrides)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - names)
    if unknown:
      raise ValueError(f"unknown data config key(s) {unknown}; known: {sorted(names | set(_LOAD_KEYS))}")
    if isinstance(d.get("scene"), Mapping):
      d["scene"] = scenes.SceneParams.from_dict(d["scene"])
    return cls(setup=setup, **d)

  def to_dict(self) -> dict:
    """JSON-able dict (the file's ``spec`` attribute), inverse of :meth:`from_config`."""
    s = self.setup
    return {"wall_size": s.wall_size, "grid": list(s.grid), "bin_width": s.bin_width,
            "num_bins": s.num_bins, "frames": self.frames,
            "num_sequences": {"train": self.num_train, "test": self.num_test,
                              **({"val": self.num_val} if self.num_val else {})},
            "seed": self.seed, "efficiency": list(self.efficiency), "photons": list(self.photons),
            "ambient": list(self.ambient), "dark_counts": self.dark_counts, "jitter": self.jitter,
            "store_clean": self.store_clean, "store_albedo": self.store_albedo,
            "compression": self.compression, "compression_level": self.compression_level,
            "render_batch": self.render_batch, "noise_sampler": self.noise_sampler,
            "scene": self.scene.to_dict(),
            # Only when set: files written before the field existed keep their key.
            **({} if self.falloff == "diffuse" else {"falloff": self.falloff}),
            **({} if self.renderer == "lct" else {"renderer": self.renderer,
                                                  "retroreflective": self.retroreflective})}

  def generation_key(self) -> dict:
    """What decides the content of a sequence: everything but the sequence counts."""
    d = self.to_dict()
    d.pop("num_sequences")
    return d

  def count(self, split: str) -> int:
    """Number of sequences of ``split``."""
    return {"train": self.num_train, "test": self.num_test,
            "val": self.num_val}[_check_split(split)]

  @property
  def num_sequences(self) -> int:
    """Sequences of every split."""
    return self.num_train + self.num_test + self.num_val


def _grid(value):
  if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
    return (int(value), int(value))
  return tuple(value)


def _check_split(split):
  if split not in SPLITS:
    raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
  return split


def sequence_name(split: str, index: int) -> str:
  """Group name of a sequence, e.g. ``"train-00007"``."""
  return f"{_check_split(split)}-{int(index):05d}"


def sequence_seed(base_seed: int, split: str, index: int) -> int:
  """The seed of sequence ``index`` of ``split``: independent streams per (split, index).

  ``SeedSequence(base_seed, spawn_key=(split_code, index))`` reduced to 31
  bits; adding sequences to a split never changes the existing ones.
  """
  code = SPLITS.index(_check_split(split))
  ss = np.random.SeedSequence(int(base_seed), spawn_key=(code, int(index)))
  return int(ss.generate_state(1, np.uint32)[0] & 0x7FFFFFFF)


# --------------------------------------------------------------- simulate
def _log_uniform(rng, lo, hi):
  if lo == hi:
    return float(lo)
  return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def render_setup(spec: DatasetSpec) -> Setup:
  """The gated Setup used to render: the scene's depth range widened by 2 bins.

  Objects' bounding spheres lie inside ``spec.scene.depth_range``, so gating
  to it loses no albedo and renders 2-3x faster at paper scale (the
  transient keeps all ``T`` bins; see :func:`nlosjax.physics.render`).
  """
  s = spec.setup
  dz = s.depth_bin_length
  z0, z1 = spec.scene.depth_range
  return s.with_depth_range(max(0.0, z0 - 2 * dz), min(s.max_depth - dz / 2, z1 + 2 * dz))


def measurement_rate(clean, setup: Setup, *, efficiency: float, ambient: float, dark_counts: float,
                     jitter) -> np.ndarray:
  """Expected SPAD counts ``eta * (clean (*) g + ambient) + dark_counts`` per bin.

  Args:
    clean: ``[..., T, H, W]`` expected incident signal photons per bin.
    setup: the full-resolution capture.
    efficiency: detection efficiency in ``(0, 1]``.
    ambient: incident ambient photons per bin per scan point.
    dark_counts: dark counts per bin per scan point.
    jitter: ``"measured"``, a FWHM in seconds, or ``None``.
  Returns:
    ``[..., T, H, W]`` float32 (:func:`nlosjax.physics.expected_counts` with ``pulses=1``).
  """
  from nlosjax.physics.noise import expected_counts
  return np.asarray(expected_counts(clean, setup, pulses=1.0, efficiency=efficiency,
                                    ambient=ambient, dark_counts=dark_counts, jitter=jitter))


#: ``clean`` keeps this many mantissa bits (relative rounding error <= 2**-13)
#: and zeroes values below ``_CLEAN_FLOOR`` times its peak: 3x smaller files.
_CLEAN_BITS = 12
_CLEAN_FLOOR = 1e-6


def _compact(x: np.ndarray) -> np.ndarray:
  """float32 ``x`` rounded to ``_CLEAN_BITS`` mantissa bits, tiny values zeroed."""
  x = np.where(x > _CLEAN_FLOOR * float(x.max(initial=0.0)), x, 0.0).astype(np.float32)
  drop = 23 - _CLEAN_BITS
  u = x.view(np.uint32)
  u = (u + np.uint32(1 << (drop - 1))) & np.uint32((0xFFFFFFFF >> drop) << drop)
  return u.view(np.float32)


def simulate_sequence(spec: DatasetSpec, split: str, index: int) -> dict:
  """Simulate one sequence (deterministic in ``spec``, ``split`` and ``index``).

  Returns:
    ``{"name", "arrays": {dataset name -> numpy array}, "attrs": {...}}``
    with the datasets and attributes of the HDF5 layout (module docstring):
    ``measurement [F, T, H, W]`` uint16/uint32, ``clean [F, T, H, W]``
    float32 (if ``spec.store_clean``), ``albedo [F, T, H, W]`` float32 (if
    ``spec.store_albedo``), ``intensity``/``depth`` ``[F, H, W]`` float32,
    ``trajectory [F, 3]`` float64.
  """
  import jax

  from nlosjax.physics.forward import render
  from nlosjax.physics.noise import add_spad_noise

  setup = spec.setup
  seed = sequence_seed(spec.seed, split, index)
  scene = scenes.make_scene(seed, spec.scene, spec.frames, setup=setup)
  rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1,)))
  efficiency = float(rng.uniform(*spec.efficiency))
  photons = _log_uniform(rng, *spec.photons)
  ambient_total = 0.0 if spec.ambient[1] == 0 else _log_uniform(rng, *spec.ambient)
  T = setup.num_bins
  ambient, dark = ambient_total / T, spec.dark_counts / T

  maps = scenes.rasterize(scene, setup, supersample=spec.scene.supersample)
  gated = render_setup(spec)
  k0, k1 = gated.depth_bins
  F = spec.frames
  clean = np.empty((F, T) + setup.grid, np.float32)
  albedo = np.empty((F, T) + setup.grid, np.float32) if spec.store_albedo else None
  transport = spec.renderer == "transport"
  if transport:  # every frame in one call: the objects are sampled once per sequence
    from nlosjax.data import surfaces
    clean[:] = surfaces.render_scene(scene, setup, retroreflective=spec.retroreflective)
  for start in range(0, F, spec.render_batch):
    stop = min(F, start + spec.render_batch)
    if transport and albedo is None:
      continue
    vol = maps.volume(setup, slice(start, stop))
    if albedo is not None:
      albedo[start:stop] = vol
    if transport:
      continue
    if np.any(vol[:, :k0]) or np.any(vol[:, k1:]):  # cannot happen for valid scenes
      clean[start:stop] = np.asarray(render(vol, setup, falloff=spec.falloff))
    else:
      clean[start:stop] = np.asarray(render(vol[:, k0:k1], gated, falloff=spec.falloff))
  energy = float(np.mean(np.sum(clean, axis=1, dtype=np.float64)))
  if not energy > 0:
    raise ValueError(f"sequence {sequence_name(split, index)} (seed {seed}) renders no signal")
  scale = photons / energy
  clean = _compact(clean * np.float32(scale))

  counts = np.empty(clean.shape, np.float32)
  if spec.noise_sampler == "jax":
    key = jax.random.key(seed)
    for f in range(F):
      counts[f] = np.asarray(add_spad_noise(
          jax.random.fold_in(key, f), clean[f], setup, pulses=1.0, efficiency=efficiency,
          ambient=ambient, dark_counts=dark, jitter=spec.jitter))
  else:
    for start in range(0, F, spec.render_batch):
      stop = min(F, start + spec.render_batch)
      lam = measurement_rate(clean[start:stop], setup, efficiency=efficiency, ambient=ambient,
                             dark_counts=dark, jitter=spec.jitter)
      for f in range(start, stop):
        frame_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2, f)))
        counts[f] = frame_rng.poisson(lam[f - start])
  peak = float(counts.max()) if counts.size else 0.0
  measurement = counts.astype(np.uint16 if peak <= np.iinfo(np.uint16).max else np.uint32)

  helix = scene.helix
  arrays = {"measurement": measurement, "intensity": maps.intensity, "depth": maps.depth,
            "trajectory": scene.trajectory}
  if spec.store_clean:
    arrays["clean"] = clean
  if albedo is not None:
    arrays["albedo"] = albedo
  attrs = {
      "split": split, "index": int(index), "seed": seed, "efficiency": efficiency,
      "photons": photons, "signal_scale": scale, "ambient": ambient, "dark_counts": dark,
      "jitter": "none" if spec.jitter is None else str(spec.jitter),
      "frame_rate": scene.frame_rate, "helix_center": helix.center, "helix_axis": helix.axis,
      "helix_ref": helix.ref, "helix_radius": helix.radius, "helix_pitch": helix.pitch,
      "helix_phase": helix.phase, "helix_angular_speed": helix.angular_speed,
      "dynamic_index": scene.dynamic_index, "render_depth_range": np.asarray(gated.depth_range),
      "kinds": json.dumps([o.kind for o in scene.objects]),
      "scene": json.dumps(scene.describe()),
  }
  if scene.motion != "helix" or scene.spin_speed:  # options added later: absent by default
    attrs["motion"] = scene.motion
    attrs["spin_speed"] = scene.spin_speed
  return {"name": sequence_name(split, index), "arrays": arrays, "attrs": attrs}


# ------------------------------------------------------------------ write
def _chunks(name, shape):
  if name in ("measurement", "clean", "albedo"):
    return (1, shape[1], 1, shape[3])
  if name in ("intensity", "depth"):
    return (1,) + tuple(shape[1:])
  return None


def _write_sequence(f: h5py.File, spec: DatasetSpec, seq: dict) -> None:
  group = f.require_group("sequences")
  name = seq["name"]
  if name in group:
    del group[name]
  g = group.create_group(name)
  g.attrs["complete"] = False
  for key, arr in seq["arrays"].items():
    chunks = _chunks(key, arr.shape)
    kw = {}
    if chunks is not None and spec.compression is not None:
      kw = dict(compression=spec.compression, shuffle=True)
      if spec.compression == "gzip":
        kw["compression_opts"] = spec.compression_level
    g.create_dataset(key, data=arr, chunks=chunks, **kw)
  for key, value in seq["attrs"].items():
    g.attrs[key] = value
  g.attrs["complete"] = True
  f.flush()


def _version() -> str:
  try:
    from importlib.metadata import version
    return version("nlosjax")
  except Exception:  # noqa: BLE001 - not installed
    return "unknown"


def _init_file(f: h5py.File, spec: DatasetSpec) -> None:
  s = spec.setup
  a = f.attrs
  a["format"] = FORMAT_NAME
  a["format_version"] = FORMAT_VERSION
  a["generator_version"] = scenes.GENERATOR_VERSION
  a["nlosjax_version"] = _version()
  a["wall_size"] = s.wall_size
  a["grid"] = np.asarray(s.grid, np.int64)
  a["bin_width"] = s.bin_width
  a["num_bins"] = s.num_bins
  a["spec"] = json.dumps(spec.to_dict())
  a["seed"] = spec.seed
  a["background_depth"] = scenes.BACKGROUND_DEPTH
  a["complete"] = False
  a["created"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
  f.require_group("sequences")


def _partial_path(path: pathlib.Path) -> pathlib.Path:
  return path.with_name(path.name + ".partial")


def _open_partial(tmp: pathlib.Path, spec: DatasetSpec, overwrite: bool) -> h5py.File:
  """Open (resume) or create the temp file; drop half-written sequences."""
  if tmp.exists():
    try:
      f = h5py.File(tmp, "a")
    except OSError as e:
      if "lock" in str(e).lower():
        raise ValueError(f"{tmp}: is locked; another process is writing this dataset") from e
      warnings.warn(f"{tmp}: unreadable leftover of an interrupted run ({e}); starting over",
                    stacklevel=2)
      tmp.unlink()
    else:
      same = (f.attrs.get("format") == FORMAT_NAME
              and f.attrs.get("generator_version") == scenes.GENERATOR_VERSION
              and _generation_key(f.attrs.get("spec")) == spec.generation_key())
      if same:
        for name in list(f.get("sequences", {})):
          if not f["sequences"][name].attrs.get("complete", False):
            del f["sequences"][name]  # half-written: redo it
        return f
      f.close()
      if not overwrite:
        raise ValueError(f"{tmp}: a leftover partial dataset made with another configuration or"
                         " generator version; pass overwrite=True (--overwrite) to replace it")
      tmp.unlink()
  f = h5py.File(tmp, "w")
  _init_file(f, spec)
  return f


def _generation_key(spec_json):
  try:
    d = json.loads(spec_json)
    d.pop("num_sequences", None)
    return d
  except (TypeError, ValueError):
    return None


def _simulate_job(spec_dict, split, index):
  """Worker entry point (process pools pickle a plain dict, not the Setup)."""
  return simulate_sequence(DatasetSpec.from_config(spec_dict), split, index)


@dataclasses.dataclass(frozen=True)
class WriteResult:
  """What :func:`write_dataset` did: the file, sequences simulated now, sequences kept."""

  path: pathlib.Path
  generated: int
  resumed: int


def write_dataset(path, spec: DatasetSpec, *, overwrite: bool = False, workers: int = 1,
                  progress: bool = True) -> WriteResult:
  """Simulate every sequence of ``spec`` into the HDF5 file ``path``.

  Crash safety: the data go to ``<path>.partial`` first, flushed after each
  sequence, and the file is renamed to ``path`` only when complete, so an
  existing ``path`` survives a crash. A rerun after a crash resumes the
  partial file: finished sequences are kept, a half-written one is redone.

  Args:
    path: output file.
    spec: the :class:`DatasetSpec`.
    overwrite: replace an existing ``path`` (and a leftover partial file of
      another configuration); without it an existing ``path`` raises.
    workers: processes simulating sequences in parallel (``1``: in this
      process; more use ``spawn``ed processes; the writing stays here).
    progress: show a tqdm progress bar.
  Returns:
    :class:`WriteResult` (``path``, sequences ``generated`` in this call,
    sequences ``resumed`` from a partial file).
  Raises:
    FileExistsError: ``path`` exists and ``overwrite`` is false.
    ValueError: bad arguments, or a partial file that cannot be resumed.
  """
  if not isinstance(spec, DatasetSpec):
    raise ValueError(f"spec must be a DatasetSpec, got {type(spec).__name__}")
  if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
    raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
  path = pathlib.Path(path)
  if path.exists() and not overwrite:
    raise FileExistsError(f"{path}: exists; pass overwrite=True (--overwrite) to replace it")
  if path.is_dir():
    raise ValueError(f"path {path} is a directory")
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = _partial_path(path)
  f = _open_partial(tmp, spec, overwrite)
  try:
    done = set(f["sequences"])
    jobs = [(split, i) for split in SPLITS for i in range(spec.count(split))
            if sequence_name(split, i) not in done]
    from tqdm.auto import tqdm
    total = spec.num_sequences
    bar = tqdm(total=total, initial=total - len(jobs), unit="seq", desc=f"writing {path.name}",
               disable=not progress)
    if workers == 1 or len(jobs) <= 1:
      for split, i in jobs:
        _write_sequence(f, spec, simulate_sequence(spec, split, i))
        bar.update()
    else:
      ctx = multiprocessing.get_context("spawn")
      spec_dict = spec.to_dict()
      with concurrent.futures.ProcessPoolExecutor(max_workers=int(workers), mp_context=ctx) as pool:
        pending = set()
        queue_ = list(jobs)
        while queue_ or pending:
          while queue_ and len(pending) < 2 * workers:
            pending.add(pool.submit(_simulate_job, spec_dict, *queue_.pop(0)))
          finished, pending = concurrent.futures.wait(
              pending, return_when=concurrent.futures.FIRST_COMPLETED)
          for fut in finished:
            _write_sequence(f, spec, fut.result())
            bar.update()
    bar.close()
    f.attrs["num_train"] = spec.num_train
    f.attrs["num_test"] = spec.num_test
    f.attrs["num_val"] = spec.num_val
    f.attrs["spec"] = json.dumps(spec.to_dict())    # the counts of a resumed or extended file
    f.attrs["complete"] = True
    f.flush()
  finally:
    f.close()
  os.replace(tmp, path)
  return WriteResult(path=path, generated=len(jobs), resumed=len(done))


def extend_dataset(path, spec: DatasetSpec, *, workers: int = 1, progress: bool = True) -> WriteResult:
  """Add to the complete file ``path`` the sequences ``spec`` has and it lacks.

  For a file made before a split existed (e.g. ``val``) or with fewer
  sequences: the stored sequences are kept byte for byte (a sequence depends
  on its seed, not on the counts), the missing ones are simulated, and the
  file is replaced atomically as :func:`write_dataset` does (the original
  stays untouched until the extended file is complete).

  Returns:
    :class:`WriteResult` (``generated`` 0 when nothing was missing).
  Raises:
    ValueError: ``path`` was made with another generation configuration, or
      holds more sequences of a split than ``spec`` asks for.
  """
  import shutil
  path = pathlib.Path(path)
  with h5py.File(path, "r") as f:
    if _generation_key(f.attrs.get("spec")) != spec.generation_key() or \
        f.attrs.get("generator_version") != scenes.GENERATOR_VERSION:
      raise ValueError(f"{path}: made with another data configuration or generator version; "
                       "move it away (or point data.path elsewhere) to generate this one")
    have = {split: sum(1 for n in f["sequences"] if n.startswith(split + "-")) for split in SPLITS}
  more = {s: have[s] for s in SPLITS if have[s] > spec.count(s)}
  if more:
    raise ValueError(f"{path}: holds more sequences than the config asks for ({more}); "
                     "use a config with at least these counts")
  if all(have[s] == spec.count(s) for s in SPLITS):
    return WriteResult(path=path, generated=0, resumed=sum(have.values()))
  tmp = _partial_path(path)
  if not tmp.exists():
    shutil.copyfile(path, tmp)
  return write_dataset(path, spec, overwrite=True, workers=workers, progress=progress)


# ------------------------------------------------------------ under-scanning
def _check_stride(stride, offset):
  if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
    raise ValueError(f"stride must be an integer >= 1, got {stride!r}")
  if isinstance(offset, bool) or not isinstance(offset, (int, np.integer)) or not 0 <= offset < stride:
    raise ValueError(f"offset must be an integer in [0, stride={stride}), got {offset!r}")
  return int(stride), int(offset)


def undersample(x, stride: int, offset: int = 0):
  """Interval sampling of the scan grid: ``x[..., offset::stride, offset::stride]``.

  Args:
    x: ``[..., H, W]`` array (transient ``[..., T, H, W]`` or map).
    stride: keep every ``stride``-th scan point along rows and columns.
    offset: index of the first kept point, ``0 <= offset < stride``.
  Returns:
    ``[..., ceil((H - offset) / stride), ceil((W - offset) / stride)]`` view.
  """
  stride, offset = _check_stride(stride, offset)
  if np.ndim(x) < 2:
    raise ValueError(f"x must be at least [H, W], got shape {np.shape(x)}")
  return x[..., offset::stride, offset::stride]


def undersampled_positions(setup: Setup, stride: int, offset: int = 0):
  """``(y [h], x [w])`` float64 positions (metres) of the under-scanned points."""
  stride, offset = _check_stride(stride, offset)
  return setup.scan_y[offset::stride], setup.scan_x[offset::stride]


def undersampled_setup(setup: Setup, stride: int, offset: int = 0) -> Setup:
  """A Setup for the under-scanned grid: its spacing, ``(h, w)`` points, same bins.

  Its ``wall_size`` is ``(h - 1) * stride * spacing``; its grid is centred on
  the wall while the kept points are shifted by ``offset * spacing - (wall -
  new wall) / 2`` (e.g. -3.5 spacings for 128 -> 16 with offset 0); reconstructions
  on it are displaced by that much. Needs equal row and column spacing.
  """
  stride, offset = _check_stride(stride, offset)
  ys, xs = undersampled_positions(setup, stride, offset)
  if len(ys) < 2 or len(xs) < 2:
    raise ValueError(f"stride {stride} leaves fewer than 2 points per axis of grid {setup.grid}")
  span_y, span_x = ys[-1] - ys[0], xs[-1] - xs[0]
  if not math.isclose(span_y, span_x, rel_tol=1e-9):
    raise ValueError(f"under-scanned grid spans {span_y:.4g} m x {span_x:.4g} m; a Setup needs a"
                     " square span")
  return dataclasses.replace(setup, wall_size=float(span_x), grid=(len(ys), len(xs)))


# ------------------------------------------------------------------- read
class DynamicDataset:
  """Read access to a dataset file written by :func:`write_dataset`.

  Args:
    path: the HDF5 file.
    setup: optional expected full-resolution :class:`Setup` (e.g. the
      model's); a mismatch raises.

  Raises:
    FileNotFoundError: ``path`` does not exist.
    ValueError: naming the file, when it is not HDF5 (truncated or
      foreign), not an nlosjax dynamic dataset, of a newer format version,
      unfinished, or its Setup differs from ``setup``.
  """

  def __init__(self, path, setup: Setup | None = None):
    self.path = pathlib.Path(path)
    if not self.path.exists():
      raise FileNotFoundError(f"{self.path}: no such dataset file")
    try:
      self._file = h5py.File(self.path, "r")
    except OSError as e:
      raise ValueError(f"{self.path}: cannot be read as HDF5 (truncated, corrupt or not an HDF5"
                       f" file): {e}") from None
    try:
      self._check()
      if setup is not None:
        self.check_setup(setup)
    except BaseException:
      self._file.close()
      raise

  def _check(self):
    a = self._file.attrs
    fmt = a.get("format")
    if isinstance(fmt, bytes):
      fmt = fmt.decode()
    if fmt != FORMAT_NAME:
      raise ValueError(f"{self.path}: an HDF5 file but not an nlosjax dynamic NLOS dataset"
                       f" (attribute 'format' is {fmt!r}, expected {FORMAT_NAME!r})")
    version = int(a.get("format_version", -1))
    if version > FORMAT_VERSION or version < 1:
      raise ValueError(f"{self.path}: format_version {version} is not supported (this nlosjax"
                       f" reads versions 1..{FORMAT_VERSION}); update nlosjax")
    if not bool(a.get("complete", False)):
      raise ValueError(f"{self.path}: the dataset was not finished (interrupted writer?)")
    missing = [k for k in ("wall_size", "grid", "bin_width", "num_bins") if k not in a]
    if missing or "sequences" not in self._file:
      raise ValueError(f"{self.path}: malformed dataset; missing {missing or ['/sequences']}")
    try:
      self.setup = Setup(wall_size=float(a["wall_size"]), grid=tuple(int(v) for v in a["grid"]),
                         bin_width=float(a["bin_width"]), num_bins=int(a["num_bins"]))
    except ValueError as e:
      raise ValueError(f"{self.path}: invalid Setup attributes: {e}") from None
    self.attrs = dict(a)
    self._names = sorted(self._file["sequences"])
    self._handles = {}

  # -- context manager
  def close(self):
    self._file.close()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  @property
  def generator_version(self) -> str:
    return str(self.attrs.get("generator_version"))

  def check_setup(self, setup: Setup) -> None:
    """Raise ``ValueError`` naming the file if its Setup differs from ``setup``."""
    if not isinstance(setup, Setup):
      raise ValueError(f"setup must be a nlosjax.physics.Setup, got {type(setup).__name__}")
    mine, theirs = self.setup, setup.ungated()
    diffs = []
    for field in ("wall_size", "grid", "bin_width", "num_bins"):
      a, b = getattr(mine, field), getattr(theirs, field)
      same = a == b if field in ("grid", "num_bins") else math.isclose(a, b, rel_tol=1e-9)
      if not same:
        diffs.append(f"{field} {a!r} in the file vs {b!r} expected")
    if diffs:
      raise ValueError(f"{self.path}: dataset Setup does not match: " + "; ".join(diffs))

  def names(self, split: str | None = None) -> list[str]:
    """Sequence names (sorted), all or those of ``split``."""
    if split is None:
      return list(self._names)
    _check_split(split)
    return [n for n in self._names if self._group(n).attrs.get("split") == split]

  def _group(self, name):
    try:
      return self._file["sequences"][name]
    except (KeyError, TypeError):
      raise ValueError(f"{self.path}: no sequence {name!r}") from None

  def sequence_attrs(self, name: str) -> dict:
    """Attributes of sequence ``name`` (numpy scalars/arrays, strings)."""
    return dict(self._group(name).attrs)

  def has(self, name: str, key: str) -> bool:
    return key in self._group(name)

  def num_frames(self, name: str) -> int:
    return int(self._dataset(name, "measurement").shape[0])

  def _dataset(self, name, key):
    ds = self._handles.get((name, key))
    if ds is None:
      ds = self._handles[(name, key)] = self._open_dataset(name, key)
    return ds

  def _open_dataset(self, name, key):
    g = self._group(name)
    if key not in g:
      raise ValueError(f"{self.path}: sequence {name!r} has no dataset {key!r} (it has"
                       f" {sorted(g)})")
    ds = g[key]
    H, W = self.setup.grid
    T = self.setup.num_bins
    expected = {"measurement": (T, H, W), "clean": (T, H, W), "albedo": (T, H, W),
                "intensity": (H, W), "depth": (H, W), "trajectory": (3,)}.get(key)
    if expected is not None and tuple(ds.shape[1:]) != expected:
      raise ValueError(f"{self.path}: {name}/{key} has shape {ds.shape}, expected [F, "
                       f"{', '.join(map(str, expected))}] for the file's Setup")
    return ds

  def read(self, name: str, key: str, frames=slice(None), stride: int = 1, offset: int = 0,
           dtype=None) -> np.ndarray:
    """Read ``key`` of sequence ``name``.

    Args:
      name: sequence name (see :meth:`names`).
      key: one of :data:`DATASETS`.
      frames: an int, a slice, or a list of frame indices.
      stride, offset: under-scanning of the scan grid (not for ``trajectory``).
      dtype: cast to this dtype (default: as stored).
    Returns:
      numpy array, ``[F', ...]`` (``[...]`` for an int frame).
    """
    stride, offset = _check_stride(stride, offset)
    ds = self._dataset(name, key)
    if key == "trajectory" and stride != 1:
      raise ValueError("stride applies to scan-grid datasets, not 'trajectory'")
    index = frames
    if isinstance(frames, (int, np.integer)) and not isinstance(frames, bool):
      if not 0 <= frames < ds.shape[0]:
        raise ValueError(f"frames {frames} out of range [0, {ds.shape[0]}) of {name}/{key}")
      index = int(frames)
    elif not isinstance(frames, slice):
      index = np.asarray(frames, np.int64)
    try:
      if isinstance(index, np.ndarray):
        uniq, inverse = np.unique(index, return_inverse=True)
        if uniq.size and (uniq[0] < 0 or uniq[-1] >= ds.shape[0]):
          raise ValueError(f"frames {index.tolist()} out of range [0, {ds.shape[0]})")
        lo, hi = (int(uniq[0]), int(uniq[-1]) + 1) if uniq.size else (0, 0)
        out = self._read_grid(ds, slice(lo, hi), stride, offset)[uniq - lo][inverse]
      else:
        out = self._read_grid(ds, index, stride, offset)
    except OSError as e:
      raise ValueError(f"{self.path}: reading {name}/{key} failed (corrupt file?): {e}") from None
    return out if dtype is None else out.astype(dtype)


  @staticmethod
  def _read_grid(ds, frames, stride, offset):
    """``ds[frames]`` under-scanned; transients are read one kept scan row at a time.

    HDF5 strided selections are slow (per-element bookkeeping); rows are
    whole chunks (``[1, T, 1, W]``), so reading the kept rows and slicing
    the columns in numpy is 5-20x faster and decompresses ``1 / stride`` of the data.
    """
    if ds.ndim < 3 or stride == 1:
      return ds[frames]
    if ds.ndim == 3:
      return ds[frames][..., offset::stride, offset::stride]
    rows = range(offset, ds.shape[2], stride)
    out = np.stack([ds[frames, :, r, :] for r in rows], axis=-2)
    return out[..., offset::stride]


def open_dataset(path, setup: Setup | None = None) -> DynamicDataset:
  """Open a dataset file for reading; see :class:`DynamicDataset`."""
  return DynamicDataset(path, setup)


# ----------------------------------------------------------------- loader
def prefetch(iterator, size: int = 2) -> Iterator:
  """Run ``iterator`` in a background thread, ``size`` items ahead.

  Exceptions in the producer are re-raised in the consumer; closing the
  returned generator (or dropping it) stops the producer.
  """
  if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
    raise ValueError(f"size must be an integer >= 1, got {size!r}")
  q: queue.Queue = queue.Queue(maxsize=int(size))
  stop = threading.Event()
  done = object()

  def put(item):
    while not stop.is_set():
      try:
        q.put(item, timeout=0.05)
        return True
      except queue.Full:
        continue
    return False

  def produce():
    try:
      for item in iterator:
        if not put((None, item)):
          return
      put((done, None))
    except BaseException as e:  # noqa: BLE001 - handed to the consumer
      put((e, None))

  thread = threading.Thread(target=produce, daemon=True, name="nlosjax-prefetch")
  thread.start()

  def consume():
    try:
      while True:
        tag, item = q.get()
        if tag is done:
          return
        if tag is not None:
          raise tag
        yield item
    finally:
      stop.set()

  return consume()


class TripletLoader:
  """Batches of three adjacent under-scanned frames and the middle frame's targets.

  Args:
    dataset: a path or an open :class:`DynamicDataset`.
    split: ``"train"``, ``"test"`` or ``"val"``.
    batch_size: examples per batch ``B``.
    stride, offset: under-scanning of the input (:func:`undersample`).
    seed: shuffling seed.
    shuffle: permute examples every epoch (else file order: sequence, frame).
    drop_remainder: drop the last incomplete batch of an epoch.
    ends: ``"valid"`` or ``"replicate"`` (module docstring).
    target: ``"clean"`` (the noise-free transient; the file must store it)
      or ``"measurement"`` (the full-resolution noisy counts) for ``transient``.
    in_memory: read everything the loader needs once, at construction.
    setup: optional expected full-resolution Setup (checked).
    prefetch_size: default of :meth:`iterate`'s ``prefetch_size``.
    shard: ``(index, count)``: :meth:`batch` returns rows ``index * B / count``
      to ``(index + 1) * B / count`` of every global batch and reads only
      those (one process of ``count`` in multi-process training; ``B`` must
      divide by ``count``). With ``in_memory`` a sharded loader keeps the
      sequences it has read instead of reading every one at construction.

  Batch (numpy, float32 unless noted): ``measurement [B, 3, T, h, w]``,
  ``transient [B, T, H, W]``, ``intensity [B, H, W]``, ``depth [B, H, W]``
  (metres), ``sequence [B]`` int32 (index into :attr:`names`), ``frame
  [B]`` int32 (middle frame), ``efficiency [B]``.
  """

  def __init__(self, dataset, *, split: str = "train", batch_size: int = 4, stride: int = 1,
               offset: int = 0, seed: int = 0, shuffle: bool = True, drop_remainder: bool = True,
               ends: str = "valid", target: str = "clean", in_memory: bool = False,
               setup: Setup | None = None, prefetch_size: int = 0,
               shard: tuple[int, int] = (0, 1)):
    index, count = (int(v) for v in shard)
    if not (count >= 1 and 0 <= index < count):
      raise ValueError(f"shard must be (index, count) with 0 <= index < count, got {shard!r}")
    self.shard = (index, count)
    self._owns = not isinstance(dataset, DynamicDataset)
    self.dataset = open_dataset(dataset, setup) if self._owns else dataset
    if not self._owns and setup is not None:
      self.dataset.check_setup(setup)
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
      raise ValueError(f"batch_size must be an integer >= 1, got {batch_size!r}")
    if ends not in ("valid", "replicate"):
      raise ValueError(f'ends must be "valid" or "replicate", got {ends!r}')
    if target not in ("clean", "measurement"):
      raise ValueError(f'target must be "clean" or "measurement", got {target!r}')
    self.stride, self.offset = _check_stride(stride, offset)
    self.split, self.batch_size, self.seed = _check_split(split), int(batch_size), int(seed)
    if self.batch_size % count:
      raise ValueError(f"batch_size {batch_size} does not split into {count} shards")
    self.shuffle, self.drop_remainder, self.ends, self.target = shuffle, drop_remainder, ends, target
    if (isinstance(prefetch_size, bool) or not isinstance(prefetch_size, (int, np.integer))
        or prefetch_size < 0):
      raise ValueError(f"prefetch_size must be an integer >= 0, got {prefetch_size!r}")
    self.prefetch_size = int(prefetch_size)
    self.names = self.dataset.names(split)
    if not self.names:
      raise ValueError(f"{self.dataset.path}: no {split!r} sequences")
    if target == "clean" and not self.dataset.has(self.names[0], "clean"):
      raise ValueError(f"{self.dataset.path}: stores no 'clean' transients; use"
                       " target='measurement' or regenerate with store_clean")
    self.setup = self.dataset.setup
    self.input_shape = undersample(np.empty((1, 1) + self.setup.grid), self.stride, self.offset).shape
    examples = []
    self._efficiency = []
    self._num_frames = []
    for s, name in enumerate(self.names):
      F = self.dataset.num_frames(name)
      self._num_frames.append(F)
      middles = range(1, F - 1) if ends == "valid" else range(F)
      examples += [(s, m) for m in middles]
      self._efficiency.append(float(self.dataset.sequence_attrs(name)["efficiency"]))
    if not examples:
      raise ValueError(f"{self.dataset.path}: {split!r} sequences are too short for triplets"
                       f" with ends={ends!r}")
    self.examples = np.asarray(examples, np.int64)
    self.steps_per_epoch = (len(examples) // self.batch_size if drop_remainder
                            else -(-len(examples) // self.batch_size))
    if self.steps_per_epoch == 0:
      raise ValueError(f"batch_size {batch_size} exceeds the {len(examples)} {split!r} examples"
                       " with drop_remainder=True")
    self._cache = None
    if in_memory:
      self._cache = ([self._load_sequence(name) for name in self.names] if count == 1
                     else [None] * len(self.names))

  @classmethod
  def from_config(cls, data: Mapping, *, split: str = "train", batch_size: int = 4, seed: int = 0,
                  path=None, shuffle: bool | None = None, setup: Setup | None = None,
                  **overrides) -> "TripletLoader":
    """A loader set up by a config's ``data`` section.

    Reads ``path`` (unless given), ``input_stride``, ``input_offset`` and
    ``loader`` (``ends``, ``target``, ``in_memory``, ``prefetch``). ``shuffle``
    defaults to ``split == "train"``; the test split keeps every batch
    (``drop_remainder=False``). ``overrides`` go to the constructor.
    """
    if not isinstance(data, Mapping):
      raise ValueError(f"data config must be a mapping, got {type(data).__name__}")
    opts = dict(data.get("loader", {}))
    unknown = sorted(set(opts) - {"ends", "target", "in_memory", "prefetch"})
    if unknown:
      raise ValueError(f"unknown data.loader key(s) {unknown}")
    path = path if path is not None else data.get("path")
    if path is None:
      raise ValueError("no dataset path: give path= or set data.path")
    kwargs = dict(split=split, batch_size=batch_size, seed=seed,
                  stride=int(data.get("input_stride", 1)), offset=int(data.get("input_offset", 0)),
                  shuffle=(split == "train") if shuffle is None else shuffle,
                  drop_remainder=split == "train", ends=opts.get("ends", "valid"),
                  target=opts.get("target", "clean"), in_memory=bool(opts.get("in_memory", False)),
                  prefetch_size=int(opts.get("prefetch", 0)), setup=setup)
    kwargs.update(overrides)
    return cls(path, **kwargs)

  def close(self):
    if self._owns:
      self.dataset.close()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  def __len__(self):
    return self.steps_per_epoch

  def _load_sequence(self, name):
    ds = self.dataset
    return {"measurement": ds.read(name, "measurement", stride=self.stride, offset=self.offset),
            "transient": ds.read(name, self.target),
            "intensity": ds.read(name, "intensity"), "depth": ds.read(name, "depth")}

  def triplet_frames(self, middle: int, num_frames: int) -> np.ndarray:
    """``[3]`` input frame indices of the example with middle frame ``middle``."""
    return np.clip(np.arange(middle - 1, middle + 2), 0, num_frames - 1)

  def order(self, epoch: int) -> np.ndarray:
    """Example indices in the order of ``epoch``."""
    n = len(self.examples)
    if not self.shuffle:
      return np.arange(n)
    return np.random.default_rng([self.seed, int(epoch)]).permutation(n)

  def batch(self, step: int) -> dict:
    """The batch of global step ``step`` (epoch ``step // len(self)``); deterministic.

    A sharded loader returns its rows of that batch (``shard``).
    """
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 0:
      raise ValueError(f"step must be an integer >= 0, got {step!r}")
    epoch, within = divmod(int(step), self.steps_per_epoch)
    idx = self.order(epoch)[within * self.batch_size:(within + 1) * self.batch_size]
    index, count = self.shard
    if count > 1:
      rows = len(idx) // count if self.drop_remainder else -(-len(idx) // count)
      idx = idx[index * rows:(index + 1) * rows]
    out = {k: [] for k in ("measurement", "transient", "intensity", "depth")}
    for s, m in self.examples[idx]:
      name = self.names[s]
      if self._cache is not None:
        if self._cache[s] is None:
          self._cache[s] = self._load_sequence(name)
        seq = self._cache[s]
        frames = self.triplet_frames(m, seq["measurement"].shape[0])
        out["measurement"].append(seq["measurement"][frames])
        for k in ("transient", "intensity", "depth"):
          out[k].append(seq[k][m])
      else:
        frames = self.triplet_frames(m, self._num_frames[s])
        out["measurement"].append(self.dataset.read(name, "measurement", frames, self.stride,
                                                    self.offset))
        out["transient"].append(self.dataset.read(name, self.target, int(m)))
        out["intensity"].append(self.dataset.read(name, "intensity", int(m)))
        out["depth"].append(self.dataset.read(name, "depth", int(m)))
    batch = {k: np.stack(v).astype(np.float32) for k, v in out.items()}
    batch["sequence"] = self.examples[idx, 0].astype(np.int32)
    batch["frame"] = self.examples[idx, 1].astype(np.int32)
    batch["efficiency"] = np.asarray([self._efficiency[s] for s in self.examples[idx, 0]], np.float32)
    return batch

  def iterate(self, start_step: int = 0, num_steps: int | None = None,
              prefetch_size: int | None = None) -> Iterator[dict]:
    """Yield ``batch(start_step)``, ``batch(start_step + 1)``, ... (forever if ``num_steps`` is None).

    Resume from a checkpointed step ``k`` with ``iterate(k)``. With
    ``prefetch_size > 0`` (default: the constructor's) batches are read that
    many ahead in a background thread.
    """
    if prefetch_size is None:
      prefetch_size = self.prefetch_size
    if isinstance(start_step, bool) or not isinstance(start_step, (int, np.integer)) or start_step < 0:
      raise ValueError(f"start_step must be an integer >= 0, got {start_step!r}")
    if num_steps is not None and (not isinstance(num_steps, (int, np.integer)) or num_steps < 0):
      raise ValueError(f"num_steps must be None or an integer >= 0, got {num_steps!r}")

    def gen():
      step = int(start_step)
      while num_steps is None or step < start_step + num_steps:
        yield self.batch(step)
        step += 1

    if prefetch_size:
      return prefetch(gen(), prefetch_size)
    return gen()

  def epoch(self, epoch: int, prefetch_size: int | None = None) -> Iterator[dict]:
    """The batches of one epoch."""
    return self.iterate(int(epoch) * self.steps_per_epoch, self.steps_per_epoch, prefetch_size)

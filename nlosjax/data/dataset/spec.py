"""The dataset spec: :class:`DatasetSpec` (a config's ``data`` section), splits and per-sequence seeds.

Everything that determines a generated dataset, validated at construction;
:func:`sequence_seed` gives each ``(split, index)`` its own seed stream and
:func:`sequence_name` its group name in the file (:mod:`nlosjax.data.dataset`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from nlosjax.data import scenes
from nlosjax.data.dataset.physics import PhysicsMix
from nlosjax.physics.setup import Setup

#: Renderers of the noise-free transient (:attr:`DatasetSpec.renderer`); ``"mix"`` draws
#: one per sequence from :attr:`DatasetSpec.physics`.
RENDERERS = ("lct", "transport", "mix")
#: Split names (group-name prefixes and the ``split`` attribute). ``val`` is
#: the validation split every choice is made on (classic-method settings,
#: checkpoints, hyperparameters); ``test`` only writes final tables. The order
#: fixes each split's seed stream (:func:`sequence_seed`): new splits go last.
SPLITS = ("train", "test", "val")

#: Keys of a config's ``data`` section that build its :class:`~nlosjax.physics.Setup`.
SETUP_KEYS = ("wall_size", "grid", "bin_width", "num_bins")
#: Keys of a config's ``data`` section that concern loading, not generation.
LOAD_KEYS = ("input_stride", "input_offset", "loader", "path")


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
    physics: with ``renderer="mix"`` (and only then), the
      :class:`~nlosjax.data.dataset.physics.PhysicsMix` each sequence's forward
      model is drawn from: renderer family, falloffs, cosines, impulse response
      (replacing ``jitter``), background shape, dark counts, gain and time-zero
      offset (a dict from a config is converted).
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
  physics: PhysicsMix | None = None

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
    if self.renderer in ("transport", "mix") and self.falloff != "diffuse":
      raise ValueError(f"renderer={self.renderer!r} draws each object's material: set"
                       " retroreflective=1.0 (or data.physics) instead of falloff='retroreflective'")
    if isinstance(self.physics, Mapping):
      object.__setattr__(self, "physics", PhysicsMix.from_dict(self.physics))
    if (self.renderer == "mix") != (self.physics is not None):
      raise ValueError("renderer='mix' and physics go together: set data.physics (a PhysicsMix) with"
                       f" renderer='mix', got renderer={self.renderer!r}, physics={self.physics!r}")
    if self.physics is not None and not isinstance(self.physics, PhysicsMix):
      raise ValueError(f"physics must be a PhysicsMix or dict, got {type(self.physics).__name__}")
    if self.renderer == "mix" and self.retroreflective:
      raise ValueError("renderer='mix' draws materials from data.physics.retroreflective;"
                       " leave data.retroreflective at 0")
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
    d = {k: v for k, v in data.items() if k not in LOAD_KEYS}
    d.update({k: v for k, v in overrides.items() if k in SETUP_KEYS})
    overrides = {k: v for k, v in overrides.items() if k not in SETUP_KEYS}
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
      raise ValueError(f"unknown data config key(s) {unknown}; known: {sorted(names | set(LOAD_KEYS))}")
    if isinstance(d.get("scene"), Mapping):
      d["scene"] = scenes.SceneParams.from_dict(d["scene"])
    if isinstance(d.get("physics"), Mapping):
      d["physics"] = PhysicsMix.from_dict(d["physics"])
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
                                                  "retroreflective": self.retroreflective}),
            **({} if self.physics is None else {"physics": self.physics.to_dict()})}

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


"""The forward model as a random variable of a dataset: :class:`PhysicsMix` and its draws.

A :class:`PhysicsMix` (a config's ``data.physics``) is a distribution over
forward models; :meth:`PhysicsMix.draw` gives one sequence's
:class:`ForwardModel` from a stream of its own (the sequence's seed, spawn
key 6), so a dataset without ``physics`` draws exactly what it drew before.
Per sequence:

* **renderer family** (:data:`FAMILIES`, uniform over ``families``):
  ``"lct"`` (the light-cone operator on the orthographic albedo volume, no
  cosines, one falloff for the whole scene), ``"transport"`` (whole
  surfaces, exact paths, per-scan-point visibility, cosines to the power
  ``kappa``) and ``"points"`` (the same patches as isotropic point scatterers:
  no cosines, no visibility);
* **falloff** ``r^-p`` per object (``lct``: one per sequence): ``p = 2``
  (retroreflective) with probability ``retroreflective``, else uniform in
  ``falloff_power``;
* **impulse response** ``g [K]`` (zero delay at ``K // 2``): the measured SPAD
  curve with its time axis stretched log-uniformly in ``jitter_stretch``, or
  with probability ``gaussian_jitter`` a Gaussian of FWHM in ``jitter_fwhm``;
  with probability ``tail`` part of it (``tail_weight``) delayed by an
  exponential of time constant ``tail_decay``;
* **background** per histogram: the spec's ambient light, of which with
  probability ``decay`` a share ``decay_fraction`` decays from ``t = 0`` as
  ``exp(-t / decay_time)`` (the rest flat), and dark counts log-uniform in
  ``dark_counts``;
* **gain** per scan point ``[H, W]`` (mean 1): ``exp(sigma z)`` with ``z``
  i.i.d. standard normal, ``sigma ~ U(gain_sigma)``, times a vignetting
  ``1 - v (d / d_max)^2`` about a random centre, ``v ~ U(vignetting)``; it
  scales signal and ambient light (light the optics collect), not dark counts;
* **time-zero offset**: the signal shifted by an integer number of bins in
  ``[-time_shift, time_shift]`` (a calibration error: ``clean``, the training
  target, is not shifted);
* **early gate**: with probability ``gate``, every count before a time drawn
  uniformly in ``gate_time`` is removed, as published preparations of measured
  scans zero the direct reflection off the wall (O'Toole et al. 2018: the
  first 2.4 ns);
* **scanner sweep**: with probability ``sweep``, the galvo mirrors are still
  moving while the detector counts (TransiT, ICCV 2025: ~0.4 ms to settle), so
  each histogram is the mean of the ideal histograms along the last ``L``
  full-resolution scan steps of the raster path that arrives at its scan point,
  ``L`` uniform in ``sweep_length`` (:func:`sweep_smear`); the raster runs
  along the columns (``W``, the fast axis), row after row, and with
  probability ``sweep_serpentine`` it reverses direction every row. Like the
  time-zero offset it changes the measurement, not ``clean``.

Times in seconds, lengths in metres.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping

import numpy as np

from nlosjax.physics.setup import Setup

__all__ = ["FAMILIES", "ForwardModel", "PhysicsMix", "background_profile", "gain_map",
           "impulse_kernel", "sweep_smear", "sweep_weights"]

#: Renderer families a :class:`PhysicsMix` draws from.
FAMILIES = ("lct", "transport", "points")
#: Per-object falloff exponents drawn per sequence (objects beyond this share the last).
_MAX_OBJECTS = 8
#: Longest scanner sweep, full-resolution scan steps (:func:`sweep_weights`).
_MAX_SWEEP = 4.0
_SWEEP_FIELDS = ("sweep", "sweep_length", "sweep_serpentine")
#: Spawn key of the physics stream under a sequence's seed (scenes use 3-5, simulation 1-2).
SPAWN_KEY = 6


def _pair(value, name, *, low=None, high=None):
  try:
    lo, hi = (float(v) for v in value)
  except (TypeError, ValueError):
    raise ValueError(f"PhysicsMix.{name} must be a (low, high) pair of numbers, got {value!r}") from None
  if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
    raise ValueError(f"PhysicsMix.{name} must be finite with low <= high, got {value!r}")
  if (low is not None and lo < low) or (high is not None and hi > high):
    raise ValueError(f"PhysicsMix.{name} must lie in [{low}, {high}], got {value!r}")
  return (lo, hi)


def _probability(value, name):
  if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) or not 0 <= value <= 1:
    raise ValueError(f"PhysicsMix.{name} must be a probability in [0, 1], got {value!r}")
  return float(value)


def _log_uniform(rng, lo, hi):
  return float(lo) if lo == hi else float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


@dataclasses.dataclass(frozen=True)
class PhysicsMix:
  """A distribution over forward models (module docstring); every field a range or a probability.

  Attributes:
    families: renderer families drawn uniformly per sequence, a subset of :data:`FAMILIES`.
    retroreflective: probability that an object (``lct``: the scene) returns as ``r^-2``.
    falloff_power: ``(low, high)`` of the falloff exponent ``p`` otherwise, in ``[2, 4]``.
    cosine_power: ``(low, high)`` of ``kappa``, the power of the cosines (``transport``).
    jitter_stretch: ``(low, high)`` log-uniform factor on the measured curve's time axis.
    gaussian_jitter: probability of a Gaussian impulse response instead.
    jitter_fwhm: ``(low, high)`` of its FWHM, seconds.
    tail: probability of an exponential tail.
    tail_weight: ``(low, high)`` share of the response in the tail.
    tail_decay: ``(low, high)`` log-uniform time constant of the tail, seconds.
    decay: probability that part of the ambient light decays from ``t = 0``.
    decay_fraction: ``(low, high)`` share of the ambient light that decays.
    decay_time: ``(low, high)`` log-uniform decay time, seconds.
    dark_counts: ``(low, high)`` log-uniform dark counts per histogram (``(0, 0)``: the spec's).
    gain_sigma: ``(low, high)`` of the per-scan-point log-gain's standard deviation.
    vignetting: ``(low, high)`` of the gain's fall at the far corner, in ``[0, 1)``.
    time_shift: largest time-zero offset, bins.
    gate: probability that the early bins are zeroed.
    gate_time: ``(low, high)`` of the time before which they are, seconds.
    sweep: probability that the scanner sweeps while counting (module docstring).
    sweep_length: ``(low, high)`` of the swept path, full-resolution scan steps, in ``[0, 4]``.
    sweep_serpentine: probability that the raster reverses direction every row.
  """

  families: tuple[str, ...] = FAMILIES
  retroreflective: float = 0.2
  falloff_power: tuple[float, float] = (2.0, 4.0)
  cosine_power: tuple[float, float] = (0.5, 2.0)
  jitter_stretch: tuple[float, float] = (0.7, 2.0)
  gaussian_jitter: float = 0.25
  jitter_fwhm: tuple[float, float] = (30e-12, 200e-12)
  tail: float = 0.5
  tail_weight: tuple[float, float] = (0.05, 0.3)
  tail_decay: tuple[float, float] = (50e-12, 500e-12)
  decay: float = 0.5
  decay_fraction: tuple[float, float] = (0.2, 0.9)
  decay_time: tuple[float, float] = (0.3e-9, 3e-9)
  dark_counts: tuple[float, float] = (0.5, 20.0)
  gain_sigma: tuple[float, float] = (0.0, 0.3)
  vignetting: tuple[float, float] = (0.0, 0.4)
  time_shift: int = 2
  gate: float = 0.5
  gate_time: tuple[float, float] = (0.5e-9, 2.4e-9)
  # Fields added later go last and are drawn last: mixes without them draw what they drew before.
  sweep: float = 0.0
  sweep_length: tuple[float, float] = (0.0, 1.0)
  sweep_serpentine: float = 0.5

  def __post_init__(self):
    fams = (self.families,) if isinstance(self.families, str) else tuple(self.families)
    if not fams or any(f not in FAMILIES for f in fams) or len(set(fams)) != len(fams):
      raise ValueError(f"PhysicsMix.families must be distinct names from {FAMILIES}, got {self.families!r}")
    object.__setattr__(self, "families", fams)
    for name in ("retroreflective", "gaussian_jitter", "tail", "decay", "gate", "sweep",
                 "sweep_serpentine"):
      object.__setattr__(self, name, _probability(getattr(self, name), name))
    bounds = {"falloff_power": (2.0, 4.0), "cosine_power": (0.0, 8.0), "jitter_stretch": (0.05, 20.0),
              "jitter_fwhm": (0.0, 1e-8), "tail_weight": (0.0, 1.0), "tail_decay": (1e-13, 1e-8),
              "decay_fraction": (0.0, 1.0), "decay_time": (1e-12, 1e-6), "dark_counts": (0.0, None),
              "gain_sigma": (0.0, 2.0), "vignetting": (0.0, 0.95), "gate_time": (0.0, 1e-7),
              "sweep_length": (0.0, _MAX_SWEEP)}
    for name, (lo, hi) in bounds.items():
      object.__setattr__(self, name, _pair(getattr(self, name), name, low=lo, high=hi))
    dc = self.dark_counts
    if dc[0] == 0.0 and dc[1] > 0.0:
      raise ValueError(f"PhysicsMix.dark_counts must be (0, 0) or strictly positive, got {dc!r}")
    ts = self.time_shift
    if isinstance(ts, bool) or not isinstance(ts, (int, np.integer)) or ts < 0:
      raise ValueError(f"PhysicsMix.time_shift must be an integer >= 0, got {ts!r}")
    object.__setattr__(self, "time_shift", int(ts))

  @classmethod
  def from_dict(cls, d: Mapping) -> "PhysicsMix":
    """From a config's ``data.physics`` (unknown keys raise, naming the known ones)."""
    if not isinstance(d, Mapping):
      raise ValueError(f"data.physics must be a mapping, got {type(d).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - names)
    if unknown:
      raise ValueError(f"unknown data.physics key(s) {unknown}; known: {sorted(names)}")
    return cls(**d)

  def to_dict(self) -> dict:
    """JSON-ready dict, the inverse of :meth:`from_dict`.

    The sweep fields appear only when ``sweep > 0``, so files written before
    they existed keep their spec.
    """
    d = {f.name: list(v) if isinstance(v, tuple) else v
         for f in dataclasses.fields(self) for v in [getattr(self, f.name)]}
    if self.sweep == 0:
      for name in _SWEEP_FIELDS:
        d.pop(name)
    return d

  def restricted(self, families) -> "PhysicsMix":
    """The same mix over ``families`` only (e.g. all but a held-out one)."""
    return dataclasses.replace(self, families=tuple(families))

  def _falloff(self, rng) -> float:
    retro = rng.uniform() < self.retroreflective
    p = float(rng.uniform(*self.falloff_power))
    return 2.0 if retro else p

  def draw(self, seed: int, setup: Setup) -> "ForwardModel":
    """The forward model of the sequence with seed ``seed`` (deterministic)."""
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(SPAWN_KEY,)))
    family = self.families[int(rng.integers(len(self.families)))]
    kappa = float(rng.uniform(*self.cosine_power))
    powers = tuple(self._falloff(rng) for _ in range(_MAX_OBJECTS + 1))
    gaussian = rng.uniform() < self.gaussian_jitter
    fwhm = float(rng.uniform(*self.jitter_fwhm))
    stretch = _log_uniform(rng, *self.jitter_stretch)
    tail = rng.uniform() < self.tail
    tail_weight = float(rng.uniform(*self.tail_weight))
    tail_decay = _log_uniform(rng, *self.tail_decay)
    decay = rng.uniform() < self.decay
    decay_fraction = float(rng.uniform(*self.decay_fraction))
    decay_time = _log_uniform(rng, *self.decay_time)
    dark = 0.0 if self.dark_counts[1] == 0 else _log_uniform(rng, *self.dark_counts)
    sigma = float(rng.uniform(*self.gain_sigma))
    vignetting = float(rng.uniform(*self.vignetting))
    centre = tuple(float(c) for c in rng.uniform(-0.5, 0.5, 2) * setup.wall_size / 2)
    shift = int(rng.integers(-self.time_shift, self.time_shift + 1))
    gain_seed = int(rng.integers(2 ** 31))
    gate = rng.uniform() < self.gate
    gate_time = float(rng.uniform(*self.gate_time))
    sweep = rng.uniform() < self.sweep                  # drawn last (PhysicsMix fields)
    sweep_length = float(rng.uniform(*self.sweep_length))
    serpentine = bool(rng.uniform() < self.sweep_serpentine)
    return ForwardModel(
        family=family, cosine_power=0.0 if family != "transport" else kappa,
        scene_falloff=powers[0], falloff_power=powers[1:],
        jitter_fwhm=fwhm if gaussian else None, jitter_stretch=None if gaussian else stretch,
        tail_weight=tail_weight if tail else 0.0, tail_decay=tail_decay,
        decay_fraction=decay_fraction if decay else 0.0, decay_time=decay_time,
        dark_counts=None if self.dark_counts[1] == 0 else dark,
        gain_sigma=sigma, vignetting=vignetting, vignetting_centre=centre, gain_seed=gain_seed,
        time_shift=shift, gate_time=gate_time if gate else 0.0,
        sweep_length=sweep_length if sweep else 0.0, sweep_serpentine=serpentine if sweep else False)


@dataclasses.dataclass(frozen=True)
class ForwardModel:
  """One draw of a :class:`PhysicsMix`: the physics of one sequence (module docstring).

  Attributes:
    family: ``"lct"``, ``"transport"`` or ``"points"``.
    cosine_power: ``kappa`` of the transport renderer (0 for the other families).
    scene_falloff: the ``lct`` family's exponent ``p`` for the whole scene.
    falloff_power: ``p`` per object (object ``i`` takes entry ``min(i, len - 1)``).
    jitter_fwhm: a Gaussian impulse response's FWHM (s), or ``None``: the measured curve.
    jitter_stretch: the measured curve's time-axis factor (``None`` with a Gaussian).
    tail_weight, tail_decay: the exponential tail's share and time constant (s); weight 0: none.
    decay_fraction, decay_time: the decaying share of the ambient light and its decay time (s).
    dark_counts: dark counts per histogram, or ``None``: the spec's.
    gain_sigma, vignetting, vignetting_centre, gain_seed: the gain map (:func:`gain_map`).
    time_shift: time-zero offset of the measurement, bins (positive: later).
    gate_time: counts before this time (s) are removed (0: none).
    sweep_length: the scanner's swept path per histogram, scan steps (0: none; :func:`sweep_smear`).
    sweep_serpentine: whether the raster reverses direction every row.
  """

  family: str
  cosine_power: float
  scene_falloff: float
  falloff_power: tuple[float, ...]
  jitter_fwhm: float | None
  jitter_stretch: float | None
  tail_weight: float
  tail_decay: float
  decay_fraction: float
  decay_time: float
  dark_counts: float | None
  gain_sigma: float
  vignetting: float
  vignetting_centre: tuple[float, float]
  gain_seed: int
  time_shift: int
  gate_time: float = 0.0
  sweep_length: float = 0.0
  sweep_serpentine: bool = False

  def object_powers(self, num_objects: int) -> np.ndarray:
    """``[num_objects]`` falloff exponents, one per object."""
    idx = np.minimum(np.arange(num_objects), len(self.falloff_power) - 1)
    return np.asarray(self.falloff_power, np.float64)[idx]

  def describe(self) -> str:
    """JSON of the draw (a sequence's ``physics`` attribute)."""
    return json.dumps(dataclasses.asdict(self))


def _centred(kernel: np.ndarray, zero: int) -> np.ndarray:
  """``kernel`` zero-padded to odd length with its zero-delay entry ``zero`` at the centre."""
  n = kernel.size
  left, right = zero, n - 1 - zero
  half = max(left, right)
  return np.concatenate([np.zeros(half - left), kernel, np.zeros(half - right)])


def impulse_kernel(setup: Setup, fm: ForwardModel) -> np.ndarray:
  """The impulse response of ``fm`` on ``setup``'s bins: ``[K]`` float64, odd ``K``, sum 1, zero delay at ``K // 2``.

  A measured curve stretched by ``s`` on bins of width ``dt`` is the curve on
  bins of width ``dt / s`` (:func:`nlosjax.physics.jitter_kernel`).
  """
  from nlosjax.physics.noise import jitter_kernel
  if fm.jitter_fwhm is not None:
    base = np.asarray(jitter_kernel(setup.bin_width, float(fm.jitter_fwhm)), np.float64)
  else:
    base = np.asarray(jitter_kernel(setup.bin_width / float(fm.jitter_stretch), "measured"), np.float64)
  if fm.tail_weight > 0:
    n = max(2, int(math.ceil(6 * fm.tail_decay / setup.bin_width)) + 1)
    k = np.arange(n)
    tail = np.exp(-k * setup.bin_width / fm.tail_decay)
    tail /= tail.sum()
    delayed = np.convolve(base, tail)                  # zero delay stays at base's centre
    c = base.size // 2
    padded = np.concatenate([base, np.zeros(n - 1)])
    base = _centred((1 - fm.tail_weight) * padded + fm.tail_weight * delayed, c)
  return base / base.sum()


def background_profile(setup: Setup, fm: ForwardModel, ambient_total: float) -> np.ndarray:
  """``[T]`` incident ambient photons per bin summing to ``ambient_total``: flat, plus a decaying share."""
  T = setup.num_bins
  flat = np.full(T, 1.0 / T)
  if fm.decay_fraction <= 0:
    return ambient_total * flat
  t = (np.arange(T) + 0.5) * setup.bin_width
  decaying = np.exp(-t / fm.decay_time)
  decaying /= decaying.sum()
  return ambient_total * ((1 - fm.decay_fraction) * flat + fm.decay_fraction * decaying)


def gain_map(setup: Setup, fm: ForwardModel) -> np.ndarray:
  """``[H, W]`` float64 per-scan-point gain, mean 1 (module docstring)."""
  rng = np.random.default_rng(fm.gain_seed)
  z = rng.standard_normal(setup.grid)
  cx, cy = fm.vignetting_centre
  scan = setup.scan_points
  d2 = (scan[..., 0] - cx) ** 2 + (scan[..., 1] - cy) ** 2
  g = np.exp(fm.gain_sigma * z) * (1.0 - fm.vignetting * d2 / max(float(d2.max()), 1e-12))
  return g / g.mean()


def _hat_integral(u):
  """``int_{-inf}^u max(0, 1 - |s|) ds``, elementwise."""
  u = np.clip(np.asarray(u, np.float64), -1.0, 1.0)
  return np.where(u < 0, (u + 1) ** 2 / 2, 1 - (1 - u) ** 2 / 2)


def sweep_weights(length: float) -> np.ndarray:
  """``[ceil(length) + 1]`` float64 weights, sum 1: the mean over ``s`` in ``[0, length]`` of
  the linear interpolation at ``s`` scan steps behind a scan point, as weights on the point
  (entry 0) and the ``k``-th point behind it (entry ``k``).

  ``w_k = (1 / L) int_0^L max(0, 1 - |s - k|) ds``; ``length = 0`` gives ``[1]``.
  """
  L = float(length)
  if not (math.isfinite(L) and 0 <= L <= _MAX_SWEEP):
    raise ValueError(f"sweep length must be a number of scan steps in [0, {_MAX_SWEEP}], got {length!r}")
  if L == 0:
    return np.ones(1)
  k = np.arange(int(math.ceil(L)) + 1)
  w = (_hat_integral(L - k) - _hat_integral(-k)) / L
  return w / w.sum()


def sweep_smear(x, length: float, serpentine: bool = False) -> np.ndarray:
  """The histograms of a scanner that sweeps while counting (module docstring): ``[..., H, W]`` float64.

  Each scan point's value becomes the mean of the values along the last
  ``length`` scan steps of the raster path that arrives at it, the path
  linearly interpolated between neighbouring scan points. The raster runs
  along ``W`` (``+x``: each point is reached from the one at ``j - 1``); with
  ``serpentine``, odd rows run the other way (``-x``: reached from ``j + 1``).
  The first point of a row is reached from outside the grid: the path there
  holds the edge value (edge-replicating padding).

  Args:
    x: ``[..., H, W]`` any values linear in the scan point (e.g. a transient ``[F, T, H, W]``).
    length: swept path, full-resolution scan steps, in ``[0, 4]``.
    serpentine: reverse the direction on odd rows.
  """
  x = np.asarray(x, np.float64)
  if x.ndim < 2:
    raise ValueError(f"sweep_smear needs x of shape [..., H, W], got shape {x.shape}")
  w = sweep_weights(length)
  if w.size == 1:
    return x.copy()
  n = w.size - 1
  W = x.shape[-1]
  fwd = np.concatenate([np.repeat(x[..., :1], n, axis=-1), x], axis=-1)     # point j at j + n
  out = sum(w[k] * fwd[..., n - k:n - k + W] for k in range(n + 1))
  if serpentine:
    bwd = np.concatenate([x, np.repeat(x[..., -1:], n, axis=-1)], axis=-1)
    rev = sum(w[k] * bwd[..., k:k + W] for k in range(n + 1))
    out[..., 1::2, :] = rev[..., 1::2, :]
  return out

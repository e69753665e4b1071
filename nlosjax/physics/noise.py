"""SPAD detector model: photon budget, efficiency, jitter, background, Poisson counts.

The measured histogram of a confocal scan point is modelled as (the paper's
Eq. 2; O'Toole et al. 2018, supplement; the reference notes, section 5)::

    tau ~ Poisson(lam),   lam = eta * (s * (tau_hat (*) g) + ambient) + dark_counts

per scan point and time bin, where

* ``tau_hat [..., T, H, W]`` is the noise-free transient (for example from
  :mod:`nlosjax.physics.forward`) and ``s`` its signal scale, set either by a
  number of laser pulses ``N`` (``tau_hat`` is then in photons per pulse per
  bin) or by a photon budget ``S`` (the mean number of incident signal
  photons per scan point, before efficiency);
* ``(*)`` is a convolution along time with the SPAD timing-jitter kernel ``g``
  (a Gaussian of given FWHM or the measured curve shipped in
  ``nlosjax/physics/data/spad_jitter.mat``);
* ``eta`` is the photon detection efficiency: detecting each incident photon
  independently with probability ``eta`` thins ``Poisson(mu)`` to
  ``Poisson(eta * mu)``, so it multiplies signal and ambient light but not the
  dark counts;
* ``ambient`` and ``dark_counts`` are expected counts per time bin per scan
  point over the whole exposure.

Units. Everything in ``lam`` is an expected number of counts per time bin per
scan point for the whole exposure. With ``N`` pulses and rates in counts per
second, ``ambient = N * ambient_rate * bin_width`` (``ambient_rate``: incident
ambient photons per second) and ``dark_counts = N * dark_count_rate *
bin_width``. E.g. 16,000 pulses (20 MHz x 800 us), 32 ps bins, 100 dark
counts/s give ``dark_counts = 5.1e-5``; ``1e6`` ambient photons/s give
``ambient = 0.51``.

Scope. This is the low-flux model: every photon is counted independently.
Pile-up and dead time (Coates), afterpulsing and crosstalk are not modelled;
keep the detected signal below about 0.05 photons per pulse per scan point.
Hernandez et al. 2017 simulate those effects photon by photon.

Sampling. Counts are drawn with :func:`jax.random.poisson` where
``lam < LARGE_RATE_THRESHOLD`` (``1e4``). Above it a rounded Gaussian
``round(N(lam, lam))`` clamped at 0 is used instead: jax's float32 rejection
sampler returns the right mean but a wrong variance from about ``lam = 3e5``
(+2.5 % at ``1e6``, +60 % at ``1e9``) and saturates at the int32 limit
(``2**31 - 1``) beyond ``2.1e9``. At ``lam >= 1e4`` the Gaussian's missing
skewness (``lam ** -0.5 <= 0.01``) is negligible. Rates are clamped to
``[0, MAX_RATE]`` and non-finite rates (possible only for traced inputs;
concrete inputs are validated) are mapped to 0 (NaN) or ``MAX_RATE`` (+inf)
before sampling, so the counts are always finite and non-negative. Counts are
returned as floats holding integers (exactly representable up to ``2**24``;
beyond that float32 rounds them, far below the Poisson spread).

References:
  M. O'Toole, D. B. Lindell, G. Wetzstein, "Confocal non-line-of-sight
  imaging based on the light-cone transform", Nature 555, 338-341 (2018).
  Q. Hernandez, D. Gutierrez, A. Jarabo, "A computational model of a
  single-photon avalanche diode sensor for transient imaging",
  arXiv:1702.02058 (2017).
"""

from __future__ import annotations

import functools
import math
import pathlib

import h5py
import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.physics import _validate
from nlosjax.physics.setup import Setup

__all__ = [
    "FWHM_TO_SIGMA",
    "LARGE_RATE_THRESHOLD",
    "MAX_RATE",
    "MEASURED_JITTER_PATH",
    "add_spad_noise",
    "expected_counts",
    "jitter_kernel",
    "load_measured_jitter",
]

#: FWHM of a Gaussian divided by its standard deviation, ``2 sqrt(2 ln 2)``.
FWHM_TO_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))  # 2.35482...

#: Rates at or above this are sampled as ``round(N(lam, lam))`` (see module doc).
LARGE_RATE_THRESHOLD = 1e4

#: Upper clamp of the rate before sampling (keeps float32 arithmetic finite).
MAX_RATE = 1e30

#: The measured SPAD jitter curve shipped with the package (see data/README.md).
MEASURED_JITTER_PATH = pathlib.Path(__file__).resolve().parent / "data" / "spad_jitter.mat"

# Kernels at most this long are applied by shift-and-add (exact, no round-off
# below zero); longer ones through a zero-padded real FFT.
_DIRECT_CONV_MAX_TAPS = 33


# ------------------------------------------------------------------- jitter
@functools.lru_cache(maxsize=1)
def load_measured_jitter() -> tuple[np.ndarray, np.ndarray]:
  """The shipped measured SPAD jitter curve: ``(t, counts)``, float64 ``[901]`` each.

  ``t`` in seconds (increasing, peak at ``t = 0``), ``counts`` a photon-count
  histogram (peak scaled to 65535). Read-only arrays; cached.
  """
  with h5py.File(MEASURED_JITTER_PATH, "r") as f:
    t = np.asarray(f["t_1"], dtype=np.float64).ravel()
    counts = np.asarray(f["counts_1"], dtype=np.float64).ravel()
  if t.shape != counts.shape or t.size < 2 or not np.all(np.diff(t) > 0):
    raise ValueError(f"{MEASURED_JITTER_PATH} is not a valid jitter curve")
  t.setflags(write=False)
  counts.setflags(write=False)
  return t, counts


def _piecewise_linear_cdf(t: np.ndarray, density: np.ndarray, x: np.ndarray) -> np.ndarray:
  """Exact integral from ``t[0]`` to ``x`` of the linear interpolant of ``density``."""
  x = np.clip(x, t[0], t[-1])
  h = np.diff(t)
  cum = np.concatenate([[0.0], np.cumsum(0.5 * h * (density[1:] + density[:-1]))])
  i = np.clip(np.searchsorted(t, x, side="right") - 1, 0, t.size - 2)
  d = x - t[i]
  slope = (density[i + 1] - density[i]) / h[i]
  return cum[i] + density[i] * d + 0.5 * slope * d * d


def _measured_kernel(bin_width: float) -> np.ndarray:
  t, counts = load_measured_jitter()
  peak = t[int(np.argmax(counts))]
  # Bin k (k bins from the peak) covers [peak + (k - 1/2) dt, peak + (k + 1/2) dt].
  k_lo = math.floor((t[0] - peak) / bin_width + 0.5)
  k_hi = math.floor((t[-1] - peak) / bin_width + 0.5)
  half = max(-k_lo, k_hi, 0)
  edges = peak + (np.arange(-half, half + 2) - 0.5) * bin_width
  prob = np.diff(_piecewise_linear_cdf(t, counts, edges))
  return np.maximum(prob, 0.0)


def _gaussian_kernel(bin_width: float, fwhm: float) -> np.ndarray:
  sigma = fwhm / FWHM_TO_SIGMA / bin_width  # in bins
  half = max(1, math.ceil(4.0 * sigma))
  edges = (np.arange(-half, half + 2) - 0.5) / (sigma * math.sqrt(2.0))
  cdf = 0.5 * np.array([math.erf(e) for e in edges])
  # Tiny sigma puts all the mass in the centre bin; float round-off may leave
  # a -0.0 or 1e-17 residue in the side bins.
  return np.maximum(np.diff(cdf), 0.0)


@functools.lru_cache(maxsize=64)
def _cached_kernel(bin_width: float, spec) -> np.ndarray:
  kind = spec[0]
  if kind == "gaussian":
    kernel = np.ones(1) if spec[1] == 0.0 else _gaussian_kernel(bin_width, spec[1])
  elif kind == "measured":
    kernel = _measured_kernel(bin_width)
  else:  # "array"
    kernel = np.asarray(spec[1], dtype=np.float64)
  kernel = (kernel / kernel.sum()).astype(np.float32)
  kernel.setflags(write=False)
  return kernel


def _bin_width_of(setup_or_bin_width) -> float:
  if isinstance(setup_or_bin_width, Setup):
    return setup_or_bin_width.bin_width
  if isinstance(setup_or_bin_width, bool) or not isinstance(
      setup_or_bin_width, (int, float, np.integer, np.floating)):
    raise ValueError(
        f"setup_or_bin_width must be a Setup or a bin width in seconds, got {setup_or_bin_width!r}")
  bw = float(setup_or_bin_width)
  if not math.isfinite(bw) or bw <= 0 or bw > 1e-6:
    raise ValueError(f"bin width must be in seconds, finite, in (0, 1e-6], got {bw!r}")
  return bw


def _jitter_spec(jitter):
  """A hashable description of ``jitter`` (validated), for the kernel cache."""
  if isinstance(jitter, str):
    if jitter != "measured":
      raise ValueError(f'jitter must be a FWHM in seconds, "measured" or a kernel array, got {jitter!r}')
    return ("measured",)
  if isinstance(jitter, bool) or jitter is None:
    raise ValueError(f'jitter must be a FWHM in seconds, "measured" or a kernel array, got {jitter!r}')
  if isinstance(jitter, (int, float, np.integer, np.floating)):
    fwhm = float(jitter)
    if not math.isfinite(fwhm) or fwhm < 0:
      raise ValueError(f"jitter FWHM must be finite and >= 0 seconds, got {jitter!r}")
    if fwhm > 1e-6:
      raise ValueError(f"jitter FWHM is in seconds and should be ~1e-11..1e-9, got {jitter!r}")
    return ("gaussian", fwhm)
  if not _validate.is_concrete(jitter):
    raise ValueError("jitter must be a concrete kernel array, not a traced value")
  try:
    arr = np.asarray(jitter, dtype=np.float64)
  except (TypeError, ValueError):
    raise ValueError(f"jitter kernel must be a real 1-D array, got {type(jitter).__name__}") from None
  if arr.ndim != 1 or arr.size == 0:
    raise ValueError(f"jitter kernel must be a non-empty 1-D array, got shape {arr.shape}")
  if arr.size % 2 == 0:
    raise ValueError(
        f"jitter kernel must have odd length (its centre index is zero delay), got {arr.size}")
  if not np.all(np.isfinite(arr)):
    raise ValueError("jitter kernel holds NaN or infinite values")
  if np.any(arr < 0):
    raise ValueError("jitter kernel holds negative values")
  if not arr.sum() > 0:
    raise ValueError("jitter kernel must have a positive sum")
  return ("array", tuple(arr.tolist()))


def jitter_kernel(setup_or_bin_width, jitter) -> np.ndarray:
  """The SPAD timing-jitter kernel ``g`` on the time-bin grid.

  Args:
    setup_or_bin_width: a :class:`~nlosjax.physics.setup.Setup` or a bin width
      in seconds.
    jitter: one of

      * a float: FWHM of a Gaussian jitter, seconds (``sigma = FWHM /
        2.3548``). Entry ``k`` is the Gaussian's integral over bin ``k``
        (``[k - 1/2, k + 1/2]`` bins from the true arrival time), truncated at
        ``+-ceil(4 sigma)`` bins (at least one bin each side) and
        renormalised; its variance is thus about ``sigma**2 + dt**2 / 12``.
        ``0.0`` gives the one-tap identity kernel ``[1.0]``.
      * ``"measured"``: the measured SPAD curve shipped with nlosjax
        (``data/spad_jitter.mat``, FWHM ~37 ps, long tail; see
        ``data/README.md``). Its counts, taken as a piecewise-linear density,
        are integrated exactly over bins of width ``dt`` centred on the curve's
        peak, so entry ``k`` is the probability of being recorded ``k - K // 2``
        bins from the peak; the whole tail is kept, the early side zero-padded
        to centre the peak, and the result renormalised.
      * a 1-D array: a kernel already on the bin grid, odd length, its centre
        index being zero delay. Must be finite, non-negative, with a positive
        sum; it is normalised to sum 1.

  Returns:
    ``[K]`` float32 numpy array, ``K`` odd, summing to 1, zero delay at index
    ``K // 2`` (where the Gaussian and measured kernels peak). Cached
    (``functools.lru_cache``) and read-only: copy it before modifying.

  Raises:
    ValueError: on an invalid bin width or ``jitter``.
  """
  return _cached_kernel(_bin_width_of(setup_or_bin_width), _jitter_spec(jitter))


def _next_fast_len(n: int) -> int:
  """Smallest ``2**a * 3**b * 5**c >= n``."""
  best = 1 << max(0, (n - 1).bit_length())
  p5 = 1
  while p5 < best:
    p35 = p5
    while p35 < best:
      m = p35
      while m < n:
        m *= 2
      best = min(best, m)
      p35 *= 3
    p5 *= 5
  return best


def _convolve_time(x: jax.Array, kernel: jax.Array) -> jax.Array:
  """Zero-padded 'same' convolution of ``x [..., T, H, W]`` with ``kernel [K]`` along T.

  ``out[t] = sum_j kernel[j] * x[t - (j - K // 2)]``: a photon at bin ``t0``
  is spread over ``t0 - K // 2 ... t0 + K // 2``, and what lands outside
  ``[0, T)`` is lost. Short kernels use shift-and-add (exact; a delta kernel
  is the identity), long ones a real FFT of length ``n >= T + K // 2``, which
  keeps the circular wrap-around out of the returned window.
  """
  taps = kernel.shape[0]
  c = taps // 2
  T = x.shape[-3]
  pad = [(0, 0)] * x.ndim
  if taps <= _DIRECT_CONV_MAX_TAPS:
    pad[-3] = (c, c)
    xp = jnp.pad(x, pad)
    out = kernel[taps - 1] * xp[..., 0:T, :, :]
    for j in range(taps - 2, -1, -1):
      s = taps - 1 - j
      out = out + kernel[j] * xp[..., s:s + T, :, :]
    return out
  n = _next_fast_len(T + c)
  spec = jnp.fft.rfft(x, n=n, axis=-3) * jnp.fft.rfft(kernel, n=n)[:, None, None]
  out = jnp.fft.irfft(spec, n=n, axis=-3)[..., c:c + T, :, :]
  return out.astype(x.dtype)


# --------------------------------------------------------------- the model
@functools.partial(jax.jit, static_argnames=("normalise", "dtype"))
def _rate_core(transient, scale, efficiency, kernel, ambient, dark, *, normalise, dtype):
  """lam for validated inputs. ``None`` arguments are absent terms (not traced)."""
  x = transient.astype(dtype)
  scale = jnp.asarray(scale, dtype)
  if normalise:
    # s = S / mean_{points} sum_t tau_hat, per example; s = 0 for an empty transient.
    total = jnp.mean(jnp.sum(x, axis=-3, keepdims=True), axis=(-2, -1), keepdims=True)
    positive = total > 0
    scale = jnp.where(positive, scale / jnp.where(positive, total, 1.0), 0.0)
  if kernel is not None:
    x = _convolve_time(x, kernel.astype(dtype))
  gain = scale if efficiency is None else scale * jnp.asarray(efficiency, dtype)
  lam = x * gain
  if ambient is not None or dark is not None:
    background = jnp.zeros((), dtype)
    if ambient is not None:
      background = jnp.asarray(ambient, dtype)
      if efficiency is not None:
        background = background * jnp.asarray(efficiency, dtype)
    if dark is not None:
      background = background + jnp.asarray(dark, dtype)
    lam = lam + background
  # Guard: FFT round-off can dip below 0; traced inputs may be non-finite.
  lam = jnp.nan_to_num(lam, nan=0.0, posinf=MAX_RATE, neginf=0.0)
  return jnp.clip(lam, 0.0, MAX_RATE)


@jax.jit
def _sample_counts(key, lam):
  """Poisson(lam) below LARGE_RATE_THRESHOLD, round(N(lam, lam)) >= 0 above."""
  key_poisson, key_normal = jax.random.split(key)
  small = lam < LARGE_RATE_THRESHOLD
  lam32 = lam.astype(jnp.float32)
  poisson = jax.random.poisson(key_poisson, jnp.where(small, lam32, 0.0), dtype=jnp.int32)
  normal = jax.random.normal(key_normal, lam.shape, lam.dtype)
  gaussian = jnp.maximum(jnp.round(lam + jnp.sqrt(lam) * normal), 0.0)
  return jnp.where(small, poisson.astype(lam.dtype), gaussian)


def _scalar(value, name: str, *, low: float, low_inclusive: bool, high: float | None = None):
  """Validate a concrete real scalar; tracers pass through unchecked."""
  if not _validate.is_concrete(value):
    return value
  if isinstance(value, bool):
    raise ValueError(f"{name} must be a number, got {value!r}")
  try:
    arr = np.asarray(value)
    ok = arr.ndim == 0 and (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer))
  except Exception:  # noqa: BLE001 - anything that is not a number
    ok = False
  if not ok:
    raise ValueError(f"{name} must be a real scalar, got {value!r}")
  v = float(arr)
  if not math.isfinite(v):
    raise ValueError(f"{name} must be finite, got {value!r}")
  if v < low or (v == low and not low_inclusive) or (high is not None and v > high):
    interval = ("[" if low_inclusive else "(") + f"{low:g}, " + (f"{high:g}]" if high is not None else "inf)")
    raise ValueError(f"{name} must be in {interval}, got {value!r}")
  return v


def _is_zero(value) -> bool:
  return _validate.is_concrete(value) and value == 0.0


def _prepare(transient, setup, photons_per_point, pulses, efficiency, ambient, dark_counts,
             jitter, dtype):
  """Validate everything (concrete values only); return the core's arguments."""
  if not isinstance(setup, Setup):
    raise ValueError(f"setup must be a nlosjax.physics.Setup, got {type(setup).__name__}")
  if not hasattr(transient, "shape"):
    transient = np.asarray(transient)
  setup.check_transient(transient, "transient")
  _validate.check_counts(transient, "transient")
  try:
    out_dtype = jnp.dtype(dtype)
  except TypeError:
    raise ValueError(f"dtype must be a floating dtype, got {dtype!r}") from None
  if not jnp.issubdtype(out_dtype, jnp.floating):
    raise ValueError(f"dtype must be a floating dtype, got {dtype!r}")
  compute = jax.dtypes.canonicalize_dtype(
      jnp.float64 if out_dtype == jnp.float64 else jnp.float32)
  out_dtype = jax.dtypes.canonicalize_dtype(out_dtype)  # float64 -> float32 without x64

  if (photons_per_point is None) == (pulses is None):
    raise ValueError("give exactly one of photons_per_point (photon budget) or pulses (count);"
                     f" got photons_per_point={photons_per_point!r}, pulses={pulses!r}")
  normalise = photons_per_point is not None
  if normalise:
    scale = _scalar(photons_per_point, "photons_per_point", low=0.0, low_inclusive=False)
  else:
    scale = _scalar(pulses, "pulses", low=0.0, low_inclusive=False)
  efficiency = _scalar(efficiency, "efficiency", low=0.0, low_inclusive=False, high=1.0)
  ambient = _scalar(ambient, "ambient", low=0.0, low_inclusive=True)
  dark_counts = _scalar(dark_counts, "dark_counts", low=0.0, low_inclusive=True)

  kernel = None
  if jitter is not None and not (isinstance(jitter, (int, float)) and not isinstance(jitter, bool)
                                 and jitter == 0):
    k = jitter_kernel(setup, jitter)
    if k.size > 1:
      kernel = jnp.asarray(k)
  args = (jnp.asarray(transient), scale,
          None if (_validate.is_concrete(efficiency) and efficiency == 1.0) else efficiency,
          kernel,
          None if _is_zero(ambient) else ambient,
          None if _is_zero(dark_counts) else dark_counts)
  return args, dict(normalise=normalise, dtype=compute), out_dtype


def expected_counts(transient, setup: Setup, *, photons_per_point=None, pulses=None,
                    efficiency=1.0, ambient=0.0, dark_counts=0.0, jitter=None,
                    dtype=jnp.float32) -> jax.Array:
  """The noise-free SPAD mean ``lam = eta * (s * (tau_hat (*) g) + ambient) + dark_counts``.

  The rate whose Poisson draw :func:`add_spad_noise` returns (the paper's
  Eq. 2); see the module docstring for the model, units and references.

  Args:
    transient: ``[..., T, H, W]`` noise-free transient ``tau_hat``, finite and
      non-negative; ``(T, H, W)`` must match ``setup``.
    setup: the capture :class:`~nlosjax.physics.setup.Setup` (shape check,
      bin width of the jitter kernel).
    photons_per_point: photon budget ``S > 0``: the signal scale is ``s = S /
      mean_{scan points} sum_t tau_hat``, per example along the leading batch
      dims, so the mean incident signal per scan point is ``S`` photons (before
      efficiency and jitter; ``s = 0`` for an all-zero example).
    pulses: number of laser pulses ``N > 0``; ``tau_hat`` is then in photons
      per pulse per bin and ``s = N``. Give exactly one of the two.
    efficiency: detection efficiency ``eta`` in ``(0, 1]``; scales signal and
      ambient, not dark counts.
    ambient: expected incident ambient photons per bin per scan point over the
      exposure, ``>= 0`` (``N * ambient_rate * bin_width``).
    dark_counts: expected dark counts per bin per scan point over the exposure,
      ``>= 0`` (``N * dark_count_rate * bin_width``).
    jitter: ``None`` (none), a Gaussian FWHM in seconds, ``"measured"``, or a
      kernel array; see :func:`jitter_kernel`. The kernel is applied along
      time, centred (index ``K // 2`` is zero delay), with zero padding: a
      delta kernel leaves the transient unchanged and the signal is preserved
      except what is pushed out of ``[0, T)``. Kernels of up to 33 taps are
      applied by shift-and-add, longer ones by FFT (round-off ~1e-7 of the
      peak, negatives clamped to 0).
    dtype: floating output dtype (computed in float32, or in float64 when
      asked for and ``jax_enable_x64`` is on; float64 without x64 gives float32).

  Terms that are ``None``/0 (and ``efficiency == 1``) are left out of the
  compiled program. Scalars may be traced (under an outer ``jit``/``vmap``);
  then they are neither validated nor skipped. ``jitter`` must be concrete.

  Returns:
    ``[..., T, H, W]`` expected counts, finite, clamped to ``[0, MAX_RATE]``.

  Raises:
    ValueError: naming the offending argument, for a transient of the wrong
      shape or holding NaN/inf/negative values (when concrete), both or
      neither of ``photons_per_point``/``pulses``, a non-positive budget or
      pulse count, ``efficiency`` outside ``(0, 1]``, negative ``ambient`` or
      ``dark_counts``, an invalid ``jitter`` or ``dtype``.
  """
  args, static, out_dtype = _prepare(transient, setup, photons_per_point, pulses, efficiency,
                                     ambient, dark_counts, jitter, dtype)
  return _rate_core(*args, **static).astype(out_dtype)


def add_spad_noise(key, transient, setup: Setup, *, photons_per_point=None, pulses=None,
                   efficiency=1.0, ambient=0.0, dark_counts=0.0, jitter=None,
                   dtype=jnp.float32) -> jax.Array:
  """Simulated SPAD counts ``tau ~ Poisson(eta * (s * (tau_hat (*) g) + ambient) + dark_counts)``.

  The paper's Eq. 2 (O'Toole et al. 2018; Hernandez et al. 2017 for SPAD
  modelling): ``add_spad_noise(key, x, setup, **opts)`` is a Poisson draw of
  ``expected_counts(x, setup, **opts)``. Rates ``>= 1e4`` are drawn as
  ``round(N(lam, lam))`` clamped at 0, because ``jax.random.poisson`` gets the
  variance wrong from ~3e5 and saturates at ``2**31 - 1``; see the module
  docstring.

  Args:
    key: a ``jax.random`` key (typed or raw ``uint32[2]``). The same key gives
      the same draw.
    transient, setup, photons_per_point, pulses, efficiency, ambient,
    dark_counts, jitter, dtype: as in :func:`expected_counts`.

  Returns:
    ``[..., T, H, W]`` counts, ``dtype`` (default float32) holding
    non-negative integers, always finite.

  Raises:
    ValueError: as :func:`expected_counts`.
  """
  args, static, out_dtype = _prepare(transient, setup, photons_per_point, pulses, efficiency,
                                     ambient, dark_counts, jitter, dtype)
  if not jnp.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key):
    key = jax.random.wrap_key_data(key)  # raw uint32[2]: same stream, one compiled sampler
  # Two compiled pieces (fused under an outer jit): the sampler, the costly one
  # to compile, is then reused across options for a given shape.
  return _sample_counts(key, _rate_core(*args, **static)).astype(out_dtype)

"""The phasor-field illumination wavelet ``P(t) = exp(i Omega t) exp(-t^2 / (2 sigma^2))``.

One definition, used by the ``phasor`` and ``rsd`` reconstructions and (later)
by the phasor-field loss and the network's feature transform.

Parameters follow the public phasor-field code (nlos-fk ``waveconv.m``, LFE,
USM, NLOST): virtual wavelength ``lambda_v = 2 * sampling_coeff * Delta``
(``Delta`` the coarser scan spacing; ``lambda_v >= 4 Delta`` avoids spatial
aliasing), ``cycles`` periods under the envelope, a Gaussian envelope with
``sigma = 0.15 (L - 1)`` samples (MATLAB ``gausswin(L, 1/0.3)``). ``lambda_v``
lives on the round-trip path axis, so in depth its wavelength is ``lambda_v / 2``.

Difference from the public code (:func:`illumination_wavelet`): ``L`` is made
odd and the samples are centred on ``t = 0`` so a ``"same"`` convolution has
no +-1-bin delay. :func:`public_wavelet` keeps the public length and envelope
(even ``L`` allowed, MATLAB rounding), for ``phasor(..., variant="public")``.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import scipy.fft

from nlosjax import platforms
from nlosjax.physics.setup import SPEED_OF_LIGHT, Setup


@dataclasses.dataclass(frozen=True)
class Wavelet:
  """A sampled illumination wavelet.

  Attributes:
    wavelength: virtual wavelength ``lambda_v``, metres of round-trip path.
    omega: carrier angular frequency ``Omega = 2 pi c / lambda_v``, rad/s.
    sigma: envelope standard deviation, seconds.
    bin_width: sample spacing, seconds.
    num_samples: ``L``; sample ``k`` sits at ``t = (k - L // 2) * bin_width``.
    envelope_centre: time of the envelope's peak, seconds (0, or ``-bin_width / 2``
      for the public code's even ``L``, whose ``gausswin`` peaks between samples).
  """

  wavelength: float
  omega: float
  sigma: float
  bin_width: float
  num_samples: int
  envelope_centre: float = 0.0

  @property
  def times(self) -> np.ndarray:
    """``[L]`` float64 sample times, seconds, centred on 0."""
    return (np.arange(self.num_samples) - self.num_samples // 2) * self.bin_width

  @property
  def samples(self) -> np.ndarray:
    """``[L]`` complex128 values ``P(t_k)`` (peak modulus 1)."""
    t = self.times
    return np.exp(1j * self.omega * t) * np.exp(-0.5 * ((t - self.envelope_centre) / self.sigma) ** 2)

  def spectrum(self, omega) -> np.ndarray:
    """``|P_hat(omega)|`` of the continuous wavelet, normalised to peak 1.

    ``P_hat(w) = int P(t) exp(-i w t) dt = sigma sqrt(2 pi) exp(-sigma^2 (w - Omega)^2 / 2)``.
    """
    omega = np.asarray(omega, np.float64)
    return np.exp(-0.5 * (self.sigma * (omega - self.omega)) ** 2)

  def frequencies(self, num_bins: int, ratio: float = 0.1) -> np.ndarray:
    """Angular frequencies ``2 pi k / (num_bins * bin_width)`` where the spectrum exceeds ``ratio``."""
    if not 0 < ratio < 1:
      raise ValueError(f"ratio must be in (0, 1), got {ratio!r}")
    step = 2 * math.pi / (num_bins * self.bin_width)
    k = np.arange(1, num_bins // 2 + 1)
    w = k * step
    return w[self.spectrum(w) > ratio]


@functools.lru_cache(maxsize=64)
def illumination_wavelet(setup: Setup, *, cycles: float = 5.0, sampling_coeff: float = 2.0) -> Wavelet:
  """The virtual illumination wavelet for a Setup.

  Args:
    setup: the capture (scan spacing and bin width set the wavelet).
    cycles: periods under the envelope (public codes: 4-6; nlos-fk 5).
    sampling_coeff: ``lambda_v = 2 * sampling_coeff * Delta``; 2 (nlos-fk
      default), 3 for noisy scenes. Must be >= 1 (Nyquist).
  Returns:
    A :class:`Wavelet`.
  """
  if not cycles > 0:
    raise ValueError(f"cycles must be > 0, got {cycles!r}")
  if not sampling_coeff >= 1:
    raise ValueError(f"sampling_coeff must be >= 1 (lambda_v >= 2 x scan spacing), got {sampling_coeff!r}")
  spacing = max(setup.spacing)
  wavelength = 2.0 * sampling_coeff * spacing
  length = max(3, int(round(cycles * wavelength / setup.bin_length)))
  length += 1 - length % 2
  omega = 2 * math.pi * SPEED_OF_LIGHT / wavelength
  sigma = 0.15 * (length - 1) * setup.bin_width
  if omega * setup.bin_width >= math.pi:
    raise ValueError(
        f"the wavelet's carrier ({wavelength:.4g} m) is not resolved by bins of"
        f" {setup.bin_length:.4g} m; raise sampling_coeff or use finer bins")
  return Wavelet(wavelength, omega, sigma, setup.bin_width, length)


@functools.lru_cache(maxsize=64)
def public_wavelet(setup: Setup, *, cycles: float = 5.0, sampling_coeff: float = 2.0) -> Wavelet:
  """The wavelet of nlos-fk ``waveconv.m``: ``L = round(cycles lambda_v / bin_length)`` samples.

  MATLAB rounding (halves away from zero), ``L`` even or odd, carrier
  ``exp(2 pi i ncyc k / L)`` (``ncyc = L bin_length / lambda_v``: the same
  ``Omega`` as :func:`illumination_wavelet`, up to a constant phase, which no
  modulus sees) under ``gausswin(L, 1/0.3)`` (``sigma = 0.15 (L - 1)`` samples,
  peak at sample ``(L - 1) / 2``). With :func:`convolve_time` (output from
  sample ``L // 2`` of the full convolution) it reproduces MATLAB's
  ``conv(..., 'same')``. Same arguments and checks as :func:`illumination_wavelet`.
  """
  base = illumination_wavelet(setup, cycles=cycles, sampling_coeff=sampling_coeff)
  length = int(math.floor(cycles * base.wavelength / setup.bin_length + 0.5))
  if length < 2:
    raise ValueError(f"the public wavelet is {length} sample(s) long at cycles={cycles}; "
                     "raise cycles or sampling_coeff")
  centre = ((length - 1) / 2 - length // 2) * setup.bin_width
  return dataclasses.replace(base, sigma=0.15 * (length - 1) * setup.bin_width,
                             num_samples=length, envelope_centre=centre)


def resolved_sampling_coeff(setup: Setup, sampling_coeff: float = 2.0,
                            bins_per_period: float = 3.0) -> float:
  """``sampling_coeff``, raised where needed so the carrier spans ``bins_per_period`` time bins.

  The virtual wavelength ``2 sampling_coeff Delta`` follows the scan spacing
  ``Delta``; on a fine scan with coarse bins (a 0.6 m wall, 64 x 64, 64 ps) the
  default is under two bins and :func:`illumination_wavelet` refuses it.
  Returns ``max(sampling_coeff, bins_per_period * bin_length / (2 Delta))``
  (dimensionless, as ``sampling_coeff``).
  """
  if not sampling_coeff >= 1:
    raise ValueError(f"sampling_coeff must be >= 1 (lambda_v >= 2 x scan spacing), got {sampling_coeff!r}")
  if not bins_per_period > 2:
    raise ValueError(f"bins_per_period must be > 2 (Nyquist), got {bins_per_period!r}")
  return max(float(sampling_coeff), bins_per_period * setup.bin_length / (2.0 * max(setup.spacing)))


def convolve_time(x: jax.Array, wavelet: Wavelet, axis: int = -3) -> jax.Array:
  """``(P * x)`` along ``axis`` ("same" length, centred kernel), complex.

  Args:
    x: real or complex array, e.g. a transient ``[..., T, H, W]`` (axis -3).
    wavelet: the kernel.
    axis: time axis.
  Returns:
    complex array of ``x``'s shape: ``y[t] = sum_k P(t_k) x[t - k + L // 2]``
    with zeros outside the window.

  The linear convolution by FFTs of any length at least ``T + L - 1`` (no wrap-around);
  the length is chosen by the platform the program is lowered for (:mod:`nlosjax.platforms`,
  :func:`convolution_fft_lengths`): SciPy's fast length on the CPU, a length whose prime
  factors are at most 7 elsewhere. Both are :func:`convolve_time_at`.
  """
  n = x.shape[axis]
  cpu, other = convolution_fft_lengths(n, wavelet.num_samples)
  if cpu == other:
    return convolve_time_at(x, wavelet, cpu, axis)
  return platforms.by_platform(x, cpu=lambda v: convolve_time_at(v, wavelet, cpu, axis),
                               other=lambda v: convolve_time_at(v, wavelet, other, axis))


def convolution_fft_lengths(n: int, length: int) -> tuple[int, int]:
  """``(cpu, other)`` FFT lengths of :func:`convolve_time` for ``n`` samples and a ``length``-tap kernel.

  ``cpu``: ``scipy.fft.next_fast_len(n + length - 1)`` (prime factors up to 11, which
  PocketFFT runs fast); ``other``: :func:`next_smooth_length` of the same, prime factors up
  to 7 (the radices cuFFT documents as its fastest).
  """
  full = n + length - 1
  return scipy.fft.next_fast_len(full), next_smooth_length(full)


def next_smooth_length(n: int, primes: tuple[int, ...] = (2, 3, 5, 7)) -> int:
  """The smallest integer ``>= n`` whose prime factors are all in ``primes``."""
  if n < 1:
    raise ValueError(f"n must be >= 1, got {n!r}")
  m = n
  while True:
    r = m
    for p in primes:
      while r % p == 0:
        r //= p
    if r == 1:
      return m
    m += 1


def convolve_time_at(x: jax.Array, wavelet: Wavelet, nfft: int, axis: int = -3) -> jax.Array:
  """:func:`convolve_time` with FFTs of length ``nfft`` (at least ``T + L - 1``: the linear convolution)."""
  x = jnp.moveaxis(x, axis, -1)
  n = x.shape[-1]
  length = wavelet.num_samples
  if nfft < n + length - 1:
    raise ValueError(f"nfft {nfft} < {n} + {length} - 1: the circular convolution would wrap around")
  cdtype = jnp.complex128 if x.real.dtype == jnp.float64 else jnp.complex64
  kernel = jnp.asarray(np.fft.fft(wavelet.samples, nfft), cdtype)
  y = jnp.fft.ifft(jnp.fft.fft(x.astype(cdtype), nfft) * kernel)
  y = y[..., length // 2:length // 2 + n]
  return jnp.moveaxis(y, -1, axis)

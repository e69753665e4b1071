"""Classic confocal NLOS reconstructions: FBP, LCT, f-k, phasor fields, RSD.

Every method maps a transient ``[..., T, H, W]`` (counts, non-negative) to a
non-negative volume ``[..., Z, H, W]`` on the Setup's depth grid (``Z`` =
``setup.num_depth_bins``; depth bin ``k`` at ``z = k c dt / 2``). Every method
honours ``setup.depth_range``: it reads only the time bins that can hold
returns from that range (``setup.time_bins``) and computes only its depth
bins, so cost falls with the range. All are jit-compiled, batched over the
leading axes with ``vmap``, and build their operators once per Setup.

``lct``, ``fbp`` and ``phasor`` take ``variant``. ``"public"`` (the default)
is the public algorithm's operators: O'Toole's resampling matrix and
one-voxel cone PSF on the full ``(2T, 2H, 2W)`` circular box (every time bin
read; a depth range only crops), so a Wiener ``snr`` carries over from the
public code and gives its image. ``"refined"`` is ours: a cone averaged over
each voxel's footprint on the true scan spacing, linear convolution, gating,
``oversample`` (see ``operators``); its measured benefit on point scatterers
and measured scans is in ``benchmarks/results/physics.md``.

Where each differs from the public reference code (nlos-fk, O'Toole's LCT,
nlos3d, LFE/USM):

* ``fbp``: the public code filters the backprojection with ``+LoG``, which is
  negative on objects, and clamps -- keeping only halos. We use ``-LoG``
  (5x5x5, sigma = 1 voxel, replicate padding) and do not normalise by the maximum.
* ``lct``: none with ``variant="public"``; see above for ``"refined"``.
* ``fk``: the Stolt interpolation is done on physical frequencies (any grid
  aspect and spacing), from a one-sided (``rfft``) temporal spectrum; the
  output is ``albedo^2`` like the public code. ``variant="public"`` (default)
  uses the public code's implied scan spacing ``wall_size / N``;
  ``"refined"`` the Setup's ``wall_size / (N - 1)``.
* ``phasor``: none with ``variant="public"`` (MATLAB ``conv(..., 'same')``
  with the public wavelet, even length allowed). ``"refined"``: the wavelet is
  odd-length and centred (no +-1-bin shift), and time is resampled to ``v`` by
  plain bin averaging; the public ``mtx`` also weights by ``1/t``, which tilts
  the long wavelet envelope (139 bins on a 16 x 16, 1 m, 32 ps scan) and pulls
  peaks 3-6 bins toward the wall at 0.5 m.
* ``rsd``: the confocal adaptation of Liu et al. 2019 (round-trip wavenumber
  ``2 omega / c``, no source-phase term), propagated with the exact
  angular-spectrum transfer function of Rayleigh-Sommerfeld diffraction
  rather than a sampled ``exp(ikd)/d`` kernel (no ``1/d`` singularity at
  ``z = 0``, no kernel FFTs); frequencies are the DFT frequencies of the full
  window whose wavelet spectrum exceeds ``ratio``. The sum over frequencies
  at every depth plane is a type-1 non-uniform FFT (``O(K + Z log Z)`` per
  lateral frequency instead of ``O(K Z)``; float32-exact, the direct sum
  stays available as ``depth_sum="direct"``).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.fft

from nlosjax.physics import _validate
from nlosjax.physics.operators import (
  check_falloff,
  check_variant,
  lct_apply,
  lct_filter,
  lct_operators,
  public_lct_operators,
  to_depth,
)
from nlosjax.physics.setup import SPEED_OF_LIGHT, Setup
from nlosjax.physics.wavelet import Wavelet, illumination_wavelet, public_wavelet

METHODS = ("fbp", "lct", "fk", "phasor", "rsd")


# ----------------------------------------------------------------------- LCT
@_validate.cached_operators(maxsize=4)   # a filter is [Lv, 2H, W+1] complex: ~0.3 GB at 128^2
def _lct_problem(setup: Setup, power: float, snr: float | None, z_margin: int, oversample: int,
                 dtype, variant: str = "refined") -> tuple:
  """``(operators, frequency-domain filter)`` of one LCT problem, built once and cached.

  ``power`` is the refined operators' ``v^{power/2}`` resampling (3 diffuse, 1
  retroreflective, 0 plain); the public ones multiply by ``t_n^{power + 1}``
  (``t_n^0`` for 0) as the public code. The filter is ``None`` for a
  backprojection (``snr=None``): :func:`lct_apply` then conjugates the PSF
  spectrum inside the reconstruction's own jit.
  """
  if oversample not in (1, 2, 3, 4):
    raise ValueError(f"oversample must be 1, 2, 3 or 4, got {oversample!r}")
  if check_variant(variant) == "public":
    if oversample != 1:
      raise ValueError(f"oversample={oversample} needs variant='refined' (the public grid has 1)")
    ops = public_lct_operators(setup, int(power) + 1 if power else 0, z_margin=z_margin,
                               dtype=dtype)
    return ops, (None if snr is None else jax.jit(lct_filter, static_argnums=1)(ops, snr))
  # The depth margin (FBP's -LoG taps) needs the time bins of its returns too.
  # A backprojection convolves with the cone itself: the FFT box need only span its reach.
  ops = lct_operators(setup, power, t_margin=z_margin, z_margin=z_margin, oversample=oversample,
                      dtype=dtype, fft_length="full" if snr is not None else "cone")
  return ops, (None if snr is None else jax.jit(lct_filter, static_argnums=1)(ops, snr))


@jax.jit
def _lct_batch(x, ops, filt):
  t0, t1 = ops.domain.t

  def one(xi):
    return jnp.maximum(to_depth(lct_apply(xi[t0:t1], ops, filt), ops), 0.0)

  return jax.vmap(one)(x)


def lct(transient, setup: Setup, *, snr: float = 0.1, falloff: str = "diffuse",
        variant: str = "public", oversample: int = 1) -> jax.Array:
  """Light-cone transform with a Wiener filter (O'Toole et al., Nature 2018).

  ``vol = max(R_z^-1 F^-1[ F[R_t tau] conj(H) / (|H|^2 + 1/snr) ], 0)`` with
  ``R_t`` the ``v^{q/2}`` time resampling and ``H`` the unit-norm cone PSF.

  Args:
    transient: ``[..., T, H, W]`` photon counts (float or int, >= 0).
    setup: the capture.
    snr: Wiener signal-to-noise ratio, > 0 (public defaults: 0.1 nlos-fk, LFE,
      USM; 0.8 O'Toole retroreflective scenes).
    falloff: ``"diffuse"`` (t^4) or ``"retroreflective"`` (t^2).
    variant: ``"public"`` (the public code's operators: the same ``snr``
      gives the same image) or ``"refined"`` (footprint-averaged cone on the
      true spacing, linear convolution, gated time; see the module docstring).
    oversample: ``variant="refined"`` only: v-bins per time bin of the LCT
      grid. 1 is the public algorithm's grid; 2 halves the resampling error
      near the wall (finer u-grid, sharper off-grid points) at twice the FFT
      cost. See ``benchmarks/results/physics.md`` for the measured trade.
  Returns:
    ``[..., Z, H, W]`` float32 volume, >= 0.
  """
  q = check_falloff(falloff)
  snr = _validate.check_positive(snr, "snr")
  x, batch = _validate.prepare_transient(transient, setup)
  ops, filt = _lct_problem(setup, float(q), snr, 0, oversample, x.dtype, variant)
  return _validate.unbatch(_lct_batch(x, ops, filt), batch)


# ----------------------------------------------------------------------- FBP
def _neg_log_kernel(size: int = 5, sigma: float = 1.0) -> np.ndarray:
  """``[size]*3`` float64 negative Laplacian-of-Gaussian, zero mean (positive at the centre).

  The dense kernel; :func:`neg_log_filter` applies it separably. Kept as the
  reference the tests compare against.
  """
  r = np.arange(size) - size // 2
  r2 = r[:, None, None] ** 2 + r[None, :, None] ** 2 + r[None, None, :] ** 2
  g = np.exp(-r2 / (2 * sigma ** 2))
  g /= g.sum()
  w = g * (r2 - 3 * sigma ** 2) / sigma ** 4
  return -(w - w.mean())


def _taps(size: int, sigma: float) -> tuple[tuple[float, ...], tuple[float, ...], float]:
  """1D factors of :func:`_neg_log_kernel`: ``(g, a, mean)``.

  The normalised 3D Gaussian is ``g(z) g(y) g(x)`` and ``r^2 - 3 sigma^2`` is
  ``sum_i (x_i^2 - sigma^2)``, so the LoG is ``sum_i a(x_i) prod_{j != i} g(x_j)``
  with ``a = g (x^2 - sigma^2) / sigma^4``; ``mean`` is its mean over the cube.
  """
  r = np.arange(size) - size // 2
  g = np.exp(-r ** 2 / (2 * sigma ** 2))
  g /= g.sum()
  a = g * (r ** 2 - sigma ** 2) / sigma ** 4
  mean = 3 * a.sum() * g.sum() ** 2 / size ** 3
  return tuple(g.tolist()), tuple(a.tolist()), float(mean)


def _correlate_axis(x: jax.Array, taps: tuple[float, ...], axis: int) -> jax.Array:
  """'valid' correlation of ``x`` with constant ``taps`` along ``axis`` (shifted slices; XLA fuses them)."""
  n = x.shape[axis] - len(taps) + 1
  out = None
  for i, c in enumerate(taps):
    term = c * jax.lax.slice_in_dim(x, i, i + n, axis=axis)
    out = term if out is None else out + term
  return out


def neg_log_filter(volume: jax.Array, size: int = 5, sigma: float = 1.0) -> jax.Array:
  """``-LoG`` filter of a ``[Z, H, W]`` volume with replicate (edge) padding, same shape out.

  Separable: three products of 1D ``size``-tap filters plus a box term for
  the zero mean, instead of a dense ``size^3`` 3D convolution (XLA's CPU 3D
  convolution was 20x slower than the NumPy twin). Equal to correlating with
  :func:`_neg_log_kernel` (the tests check against ``scipy.ndimage``).
  """
  g, a, mean = _taps(size, sigma)
  r = size // 2
  p = jnp.pad(volume, r, mode="edge")
  gz, az = _correlate_axis(p, g, 0), _correlate_axis(p, a, 0)
  gzgy = _correlate_axis(gz, g, 1)
  log = (_correlate_axis(_correlate_axis(az, g, 1) + _correlate_axis(gz, a, 1), g, 2)
         + _correlate_axis(gzgy, a, 2))
  ones = (1.0,) * size
  box = _correlate_axis(_correlate_axis(_correlate_axis(p, ones, 0), ones, 1), ones, 2)
  return mean * box - log


@functools.partial(jax.jit, static_argnames=("crop",))
def _fbp_batch(x, ops, filt, crop):
  t0, t1 = ops.domain.t
  lo, hi = crop

  def one(xi):
    bp = to_depth(lct_apply(xi[t0:t1], ops, filt), ops)
    # Replicate padding (as LFE): zero padding makes the -LoG ring at the scan border.
    return jnp.maximum(neg_log_filter(bp)[lo:hi], 0.0)

  return jax.vmap(one)(x)


def fbp(transient, setup: Setup, *, falloff: str = "diffuse", variant: str = "public",
        oversample: int = 1) -> jax.Array:
  """Filtered backprojection: LCT backprojection (``conj(H)``) then a ``-LoG`` filter.

  The public code (nlos-fk, LFE, USM) uses ``+LoG``, negative on objects;
  clamping then keeps only halos. We negate it (5x5x5, sigma = 1 voxel).

  Args:
    transient: ``[..., T, H, W]`` counts >= 0.
    setup: the capture.
    falloff: time weighting of the backprojection, ``"diffuse"`` (t^4, as
      the public FBP) or ``"retroreflective"`` (t^2).
    variant: backprojection operators, ``"public"`` or ``"refined"`` (see :func:`lct`).
    oversample: ``variant="refined"`` only: v-bins per time bin (see :func:`lct`).
  Returns:
    ``[..., Z, H, W]`` float32, >= 0.
  """
  q = check_falloff(falloff)
  x, batch = _validate.prepare_transient(transient, setup)
  margin = 2
  ops, filt = _lct_problem(setup, float(q), None, margin, oversample, x.dtype, variant)
  k0, k1 = setup.depth_bins
  lo = k0 - ops.domain.z[0]
  return _validate.unbatch(_fbp_batch(x, ops, filt, (lo, lo + k1 - k0)), batch)


# ------------------------------------------------------------------------ FK
@_validate.cached_operators(maxsize=16)
def _fk_grid(setup: Setup, dtype, variant: str = "refined"):
  """Static sizes and small arrays of the Stolt migration for ``setup``.

  ``variant="public"``: the public code's lateral frequencies (its
  ``a = N range / (4 M width)`` implies a scan spacing of ``wall_size / N``)
  and time weight ``t_n^2``, ``t_n = linspace(0, 1, T)``; ``"refined"``: the
  Setup's spacing ``wall_size / (N - 1)`` and the bin-centre weight ``((t + 1/2) / T)^2``.
  """
  T = setup.num_bins
  t0, t1 = setup.time_bins
  n_t = t1                                   # f-k needs the time axis from t = 0
  l_t = scipy.fft.next_fast_len(2 * n_t, real=True)
  l_t += l_t % 2
  H, W = setup.grid
  t = np.arange(n_t)
  if check_variant(variant) == "public":
    dy, dx = setup.wall_size / H, setup.wall_size / W
    t_n = t / max(T - 1, 1)
  else:
    dy, dx = setup.spacing
    t_n = (t + 0.5) / T
  weight = np.where(t >= t0, t_n ** 2, 0.0)                  # gating: bins before t0 dropped
  ky = np.fft.fftfreq(2 * H, d=dy)           # cycles / m
  kx = np.fft.fftfreq(2 * W, d=dx)
  kperp = (l_t * setup.depth_bin_length) ** 2 * (ky[:, None] ** 2 + kx[None, :] ** 2)
  return l_t, jnp.asarray(kperp, dtype), jnp.asarray(weight, dtype)


@functools.partial(jax.jit, static_argnames=("n_t", "l_t", "crop"))
def _fk_batch(x, kperp, weight, n_t, l_t, crop):
  h, w = x.shape[-2:]
  n_f = l_t // 2 + 1
  m = jnp.arange(n_f, dtype=kperp.dtype)[:, None, None]
  src = jnp.sqrt(m * m + kperp[None])                      # source frequency index
  lo_idx = jnp.floor(src)
  frac = src - lo_idx
  lo_idx = lo_idx.astype(jnp.int32)
  valid = (m > 0) & (lo_idx + 1 <= n_f - 1)
  jac = jnp.where(valid, m / jnp.maximum(src, 1e-6), 0.0)
  lo_c = jnp.minimum(lo_idx, n_f - 1)
  hi_c = jnp.minimum(lo_idx + 1, n_f - 1)

  def one(xi):
    a = xi[:n_t] * weight[:, None, None]
    psi = jnp.sqrt(jnp.where(a > 0, a, 0.0))
    spec = jnp.fft.rfft(psi, n=l_t, axis=0)                 # [n_f, H, W]
    spec = jnp.fft.fft2(spec, s=(2 * h, 2 * w), axes=(1, 2))
    phi = (jnp.take_along_axis(spec, lo_c, axis=0) * (1 - frac)
           + jnp.take_along_axis(spec, hi_c, axis=0) * frac) * jac
    field = jnp.fft.ifft2(phi, axes=(1, 2))[:, :h, :w]
    field = jnp.fft.ifft(field, n=l_t, axis=0)[crop[0]:crop[1]]
    return jnp.real(field) ** 2 + jnp.imag(field) ** 2

  return jax.vmap(one)(x)


def fk(transient, setup: Setup, *, variant: str = "public") -> jax.Array:
  """f-k (Stolt) migration (Lindell, Wetzstein, O'Toole, SIGGRAPH 2019).

  ``psi = sqrt(tau t^2)``; ``Phi(kx, ky, kz) = kz / f * Psi(kx, ky, f)`` with
  ``f = sqrt(kx^2 + ky^2 + kz^2)`` (cycles/m; time as depth ``c t / 2``),
  linear interpolation along ``f``, ``kz > 0`` only; ``vol = |F^-1 Phi|^2``.

  Args:
    transient: ``[..., T, H, W]`` counts >= 0.
    setup: the capture.
    variant: ``"public"``: the public code's lateral frequencies (scan spacing
      ``wall_size / N``) and ``t_n^2`` weight, so its image; ``"refined"``: the
      Setup's spacing ``wall_size / (N - 1)`` (see ``_fk_grid``).
  Returns:
    ``[..., Z, H, W]`` float32 volume, >= 0, proportional to albedo squared
    (as the public code; take ``sqrt`` to compare linearly).
  """
  x, batch = _validate.prepare_transient(transient, setup)
  l_t, kperp, weight = _fk_grid(setup, x.dtype, variant)
  return _validate.unbatch(
      _fk_batch(x, kperp, weight, n_t=setup.time_bins[1], l_t=l_t, crop=setup.depth_bins), batch)


# -------------------------------------------------------------------- phasor
def wavelet_matrix(wavelet: Wavelet, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
  """``[R, C]`` complex128: :func:`~nlosjax.physics.wavelet.convolve_time` as a matrix.

  ``field[t] = sum_s M[t - r0, s - c0] x[s]`` for ``t`` in ``rows``, ``x`` read
  on ``cols`` (zero outside): ``M[t, s] = P[t - s + L // 2]`` where that index
  is in ``[0, L)``.
  """
  samples = wavelet.samples
  t = np.arange(*rows)[:, None]
  s = np.arange(*cols)[None, :]
  k = t - s + wavelet.num_samples // 2
  inside = (k >= 0) & (k < wavelet.num_samples)
  return np.where(inside, samples[np.clip(k, 0, wavelet.num_samples - 1)], 0.0)


@_validate.cached_operators(maxsize=8)
def _phasor_problem(setup: Setup, wavelet: Wavelet, variant: str, oversample: int, dtype):
  """``(ops_re, ops_im)``: the LCT operators with the wavelet convolution folded into ``to_v``.

  Both the time convolution and the ``t -> v`` resampling act along time, so
  ``to_v conv(x) = (to_v M) x`` with :func:`wavelet_matrix` ``M``: one dense
  ``[Nv, Nt]`` product per part (real, imaginary) replaces the convolution's
  complex FFTs along time and the transposes around them.

  Returns ``(ops_re, ops_im)``: ``to_v`` the real and imaginary parts of the fused
  ``[Nv, Nt]`` product; ``domain.t`` the window it reads (``setup.time_bins``
  widened by half the wavelet).
  """
  ops, _ = _lct_problem(setup, 0.0, None, 0, oversample, dtype, variant)
  t0, t1 = ops.domain.t
  half = wavelet.num_samples // 2
  window = (max(0, t0 - half), min(setup.num_bins, t1 + half))
  fused = np.asarray(ops.to_v, np.float64) @ wavelet_matrix(wavelet, (t0, t1), window)
  dom = dataclasses.replace(ops.domain, t=window)
  # The fused product is banded, not sparse: the dense form (to_v_sparse reset).
  return tuple(dataclasses.replace(ops, domain=dom, to_v=jnp.asarray(part, dtype), to_v_sparse=None)
               for part in (fused.real, fused.imag))


@jax.jit
def _phasor_batch(x, ops_re, ops_im):
  a, b = ops_re.domain.t

  def one(xi):
    # Two real backprojections: one complex pipeline with the PSF's full spectrum
    # (BP(re) + i BP(im)) measured 1.3x slower on CPU (no half-spectrum saving), and
    # batching the two into one call of each FFT no faster.
    re = lct_apply(xi[a:b], ops_re, None)
    im = lct_apply(xi[a:b], ops_im, None)
    return jnp.maximum(to_depth(jnp.sqrt(re * re + im * im), ops_re), 0.0)

  return jax.vmap(one)(x)


def phasor(transient, setup: Setup, *, cycles: float = 5.0, sampling_coeff: float = 2.0,
           variant: str = "public", oversample: int = 1) -> jax.Array:
  """Phasor-field virtual wave via fast LCT backprojection (nlos-fk, Lindell 2019, alg. 3).

  Convolve each histogram with the complex wavelet ``P(t)``, backproject the
  real and imaginary parts with the light-cone PSF (no ``t^4``, no filter),
  take the modulus, resample to depth.

  Args:
    transient: ``[..., T, H, W]`` counts >= 0.
    setup: the capture.
    cycles, sampling_coeff: wavelet parameters (see ``illumination_wavelet``).
    variant: ``"public"``: nlos-fk's wavelet (:func:`~nlosjax.physics.wavelet.public_wavelet`)
      and operators (its ``mtx`` weights by ``1/t``). ``"refined"``: the odd,
      centred :func:`~nlosjax.physics.wavelet.illumination_wavelet` and our
      operators with plain bin averaging (see the module docstring).
    oversample: ``variant="refined"`` only: v-bins per time bin (see :func:`lct`).
  Returns:
    ``[..., Z, H, W]`` float32, >= 0.
  """
  x, batch = _validate.prepare_transient(transient, setup)
  make = public_wavelet if check_variant(variant) == "public" else illumination_wavelet
  wl = make(setup, cycles=cycles, sampling_coeff=sampling_coeff)
  ops_re, ops_im = _phasor_problem(setup, wl, variant, oversample, x.dtype)
  return _validate.unbatch(_phasor_batch(x, ops_re, ops_im), batch)


# ----------------------------------------------------------------------- RSD
def _rsd_window(setup: Setup, wavelet: Wavelet) -> tuple[int, int]:
  """Time bins RSD reads: ``setup.time_bins`` widened by half the wavelet (as ``phasor``).

  The virtual wave at depth ``z`` is the data convolved with ``P(t)`` around
  ``t = 2 z / c``, so bins up to half a wavelet outside the range contribute.
  """
  t0, t1 = setup.time_bins
  half = wavelet.num_samples // 2
  return (max(0, t0 - half), min(setup.num_bins, t1 + half))


@_validate.cached_operators(maxsize=16)
def _rsd_operators(setup: Setup, cycles: float, sampling_coeff: float, ratio: float, dtype):
  """``(dtft [K, Nt], kz [K, 2H, 2W], mask [K, 2H, 2W])``: the wall-field DTFT and axial wavenumbers."""
  wl = illumination_wavelet(setup, cycles=cycles, sampling_coeff=sampling_coeff)
  omega = wl.frequencies(setup.num_bins, ratio)               # [K] rad/s
  if omega.size == 0:
    raise ValueError(f"no frequency of the wavelet spectrum exceeds ratio={ratio}")
  t0, t1 = _rsd_window(setup, wl)
  t = np.arange(t0, t1) * setup.bin_width
  dtft = np.exp(-1j * omega[:, None] * t[None, :]) * wl.spectrum(omega)[:, None]   # [K, Nt]
  H, W = setup.grid
  dy, dx = setup.spacing
  ky = 2 * np.pi * np.fft.fftfreq(2 * H, d=dy)
  kx = 2 * np.pi * np.fft.fftfreq(2 * W, d=dx)
  k = 2 * omega / SPEED_OF_LIGHT                              # round-trip wavenumber, rad/m
  kz2 = k[:, None, None] ** 2 - ky[None, :, None] ** 2 - kx[None, None, :] ** 2
  kz = np.sqrt(np.maximum(kz2, 0.0))
  mask = (kz2 > 0).astype(np.float64)
  cdtype = jnp.complex128 if jnp.dtype(dtype) == jnp.float64 else jnp.complex64
  return (jnp.asarray(dtft, cdtype), jnp.asarray(kz, dtype), jnp.asarray(mask, dtype))


# Width (grid cells) and shape of the "exponential of semicircle" spreading
# kernel of the depth NUFFT (Barnett, Magland, af Klinteberg 2019), on a grid
# oversampled 2x. Measured against the direct sum in float64: 7 taps 1.2e-6,
# 8 taps 2.3e-7 (relative to the peak plane) -- below float32 resolution.
_NUFFT_TAPS = 8
_NUFFT_BETA = 2.30 * _NUFFT_TAPS


def _es_kernel(t, xp=np):
  """The spreading kernel at offsets ``t`` (grid cells, any shape), zero outside ``|t| < taps / 2``.

  ``xp`` is ``numpy`` (the plan's quadrature, float64) or ``jax.numpy`` (the
  spreading weights inside the jitted reconstruction, in ``t``'s dtype).
  """
  z = 2.0 * t / _NUFFT_TAPS
  inside = xp.abs(z) < 1.0
  return xp.where(inside, xp.exp(_NUFFT_BETA * (xp.sqrt(xp.where(inside, 1.0 - z * z, 0.0)) - 1.0)),
                  0.0)


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["dtft", "source", "column", "row", "offset", "phase", "deconv"],
                   meta_fields=["grid", "num_depths", "fft_len", "num_rows"])
@dataclasses.dataclass(frozen=True)
class RSDPlan:
  """Operators of RSD with the depth sum done by a type-1 NUFFT (see :func:`rsd`).

  The field at depth plane ``j`` (``z_j = z_first + j dz``) and lateral
  frequency ``f`` is ``sum_k U[k, f] exp(i z_j kz[k, f])``: for each ``f`` a
  sum of ``K`` exponentials with non-uniform frequencies ``x = dz kz`` in
  ``[0, pi]``, evaluated on uniform ``j``. It is spread onto a uniform grid of
  ``fft_len >= 2 Z`` cells with an ``_NUFFT_TAPS``-wide kernel, inverse-FFT'd
  along the grid, and divided by the kernel's Fourier transform: ``O(K taps +
  M log M)`` per ``f`` instead of ``O(K Z)``. Only the ``P`` propagating
  ``(k, f)`` pairs are spread.

  Attributes:
    grid: ``(H, W)`` scan grid (static).
    num_depths: ``Z`` depth planes (static).
    fft_len: ``M`` grid cells along the depth-frequency axis (static).
    num_rows: grid cells that receive any weight (static); they are stored
      from cell ``-taps / 2`` on (sources lie in ``[0, M / 2]``).
    dtft: ``[K, Nt]`` complex, wall field per frequency from the time window.
    source: ``[P]`` int32, flat index ``k * 4HW + f`` of each propagating pair.
    column: ``[P]`` int32, its lateral frequency ``f``.
    row: ``[P]`` int32, first stored cell the pair spreads to.
    offset: ``[P]`` float, its position minus its first cell, in cells.
    phase: ``[P]`` complex, ``exp(i kz (z_first + Zc dz))`` (``Zc = Z // 2``, the
      grid is centred on plane ``Zc``).
    deconv: ``[Z]`` complex, ``M / kernel_hat`` for each plane times the
      phase that undoes the ``taps / 2`` cell shift of the stored grid.
  """

  grid: tuple[int, int]
  num_depths: int
  fft_len: int
  num_rows: int
  dtft: jax.Array
  source: jax.Array
  column: jax.Array
  row: jax.Array
  offset: jax.Array
  phase: jax.Array
  deconv: jax.Array


@_validate.cached_operators(maxsize=16)
def _rsd_plan(setup: Setup, cycles: float, sampling_coeff: float, ratio: float, dtype) -> RSDPlan:
  """Build (once per Setup and options) the NUFFT operators of :func:`rsd`."""
  dtft, kz, mask = _rsd_operators(setup, cycles, sampling_coeff, ratio, dtype)
  kz = np.asarray(kz, np.float64)
  k0, k1 = setup.depth_bins
  n_z = k1 - k0
  dz = setup.depth_bin_length
  z_first = k0 * dz
  centre = n_z // 2
  # >= 2x oversampled, and long enough that the kernel's support never wraps onto itself
  fft_len = scipy.fft.next_fast_len(max(2 * n_z, 4 * _NUFFT_TAPS))
  cell_len = 2 * np.pi / fft_len
  kk, ff = np.nonzero(np.asarray(mask).reshape(kz.shape[0], -1))
  kzp = kz.reshape(kz.shape[0], -1)[kk, ff]                   # [P] rad/m
  pos = dz * kzp / cell_len                                   # [P] grid position, cells
  cell = np.ceil(pos - _NUFFT_TAPS / 2).astype(np.int64)
  offset = pos - cell                                         # in (taps/2 - 1, taps/2]
  # Fourier transform of the kernel at each centred plane index by Gauss-Legendre
  # quadrature (the kernel is smooth inside its support, 64 nodes are exact to 1e-15).
  nodes, weights = np.polynomial.legendre.leggauss(64)
  t = nodes * _NUFFT_TAPS / 2
  j = np.arange(n_z) - centre
  kernel_hat = (np.cos(j[:, None] * cell_len * t[None, :]) * (_es_kernel(t) * weights)[None, :]
                ).sum(1) * _NUFFT_TAPS / 2
  phase = np.exp(1j * kzp * (z_first + centre * dz))
  # Stored row r holds cell r - shift; the inverse FFT of the stored rows is
  # the grid's times exp(2 pi i j shift / M), undone in deconv.
  shift = _NUFFT_TAPS // 2
  row = cell + shift
  num_rows = int(row.max(initial=0)) + _NUFFT_TAPS
  if row.min(initial=0) < 0 or num_rows > fft_len:
    raise AssertionError("NUFFT sources outside [0, pi]")  # x = omega dt <= pi by construction
  deconv = fft_len / kernel_hat * np.exp(-2j * np.pi * j * shift / fft_len)
  cdtype = jnp.complex128 if jnp.dtype(dtype) == jnp.float64 else jnp.complex64
  flat = kk * kz[0].size + ff
  if max(flat.max(initial=0), num_rows * kz[0].size) >= 2 ** 31:
    raise ValueError(f"{setup}: RSD problem too large for 32-bit indices; use fewer scan points")
  return RSDPlan(setup.grid, n_z, fft_len, num_rows, dtft, jnp.asarray(flat, jnp.int32),
                 jnp.asarray(ff, jnp.int32), jnp.asarray(row, jnp.int32),
                 jnp.asarray(offset, dtype), jnp.asarray(phase, cdtype),
                 jnp.asarray(deconv, cdtype))


def _rsd_wall_spectrum(xi: jax.Array, dtft: jax.Array) -> jax.Array:
  """``[Nt, H, W]`` time window -> ``[K, 2H, 2W]`` lateral spectra of the wall field per frequency."""
  h, w = xi.shape[-2:]
  fields = jnp.einsum("kt,thw->khw", dtft, xi.astype(dtft.dtype), precision="highest")
  return jnp.fft.fft2(fields, s=(2 * h, 2 * w))


@functools.partial(jax.jit, static_argnames=("window",))
def _rsd_nufft_batch(x, plan: RSDPlan, window):
  t0, t1 = window
  h, w = plan.grid
  n_f = 4 * h * w
  n_z, m, rows = plan.num_depths, plan.fft_len, plan.num_rows
  centre = n_z // 2
  taps = jnp.arange(_NUFFT_TAPS, dtype=plan.offset.dtype)
  kern = _es_kernel(taps[:, None] - plan.offset[None, :], jnp)         # [taps, P]
  row = plan.row[None, :] + jnp.arange(_NUFFT_TAPS, dtype=jnp.int32)[:, None]
  target = (row * n_f + plan.column[None, :]).reshape(-1)             # [taps * P]

  def one(xi):
    spec = _rsd_wall_spectrum(xi[t0:t1], plan.dtft).reshape(-1)       # [K * 4HW]
    values = spec[plan.source] * plan.phase                           # [P]
    grid = jnp.zeros((rows * n_f,), values.dtype).at[target].add(
        (kern.astype(values.dtype) * values[None, :]).reshape(-1))
    # The lateral inverse FFT and the one along the grid are separable: do the
    # lateral one first and crop to the scan grid, so the grid FFT and the
    # transposes around it touch a quarter of the data.
    g = jnp.fft.ifft2(grid.reshape(rows, 2 * h, 2 * w))[:, :h, :w]    # [rows, H, W]
    g = jnp.fft.ifft(g.reshape(rows, h * w).T, n=m, axis=-1)          # [HW, M]
    # centred plane index j - centre, wrapped onto the grid
    planes = jnp.concatenate([g[:, m - centre:], g[:, :n_z - centre]], axis=1) * plan.deconv
    return jnp.abs(planes).T.reshape(n_z, h, w)

  return jax.vmap(one)(x)


@functools.partial(jax.jit, static_argnames=("window", "depths", "chunk"))
def _rsd_direct_batch(x, dtft, kz, mask, window, depths, chunk):
  t0, t1 = window
  z_first, dz, n_z = depths
  n_chunks = -(-n_z // chunk)
  h, w = x.shape[-2:]
  steps = jnp.exp(1j * (jnp.arange(chunk, dtype=kz.dtype) * dz)[:, None, None, None] * kz[None])
  advance = jnp.exp(1j * (chunk * dz) * kz)

  def one(xi):
    spec = _rsd_wall_spectrum(xi[t0:t1], dtft) * mask                  # [K, 2H, 2W]

    def body(phase, _):
      # sum_k U_k exp(i z kz_k) in real arithmetic: XLA's CPU complex einsum
      # here was a batched matvec per lateral frequency, 4x slower.
      f = spec * phase
      fr, fi = jnp.real(f)[None], jnp.imag(f)[None]
      sr, si = jnp.real(steps), jnp.imag(steps)
      planes = jax.lax.complex(jnp.sum(fr * sr - fi * si, axis=1), jnp.sum(fr * si + fi * sr, axis=1))
      vol = jnp.abs(jnp.fft.ifft2(planes)[:, :h, :w])
      return phase * advance, vol

    phase0 = jnp.exp(1j * z_first * kz)
    _, vol = jax.lax.scan(body, phase0, None, length=n_chunks)
    return vol.reshape((n_chunks * chunk, h, w))[:n_z]

  return jax.vmap(one)(x)


def rsd(transient, setup: Setup, *, cycles: float = 3.0, sampling_coeff: float = 2.0,
        ratio: float = 0.1, depth_sum: str = "nufft", chunk: int = 8) -> jax.Array:
  """Rayleigh-Sommerfeld diffraction of the phasor field (Liu et al., Nature 2019), confocal.

  For each frequency ``omega`` where the wavelet spectrum exceeds ``ratio``:
  the wall field ``P_w(x, y) = sum_t tau(t) exp(-i w t) P_hat(w)`` is
  propagated to depth ``z`` with the angular-spectrum transfer function
  ``exp(i z sqrt(k^2 - kx^2 - ky^2))``, ``k = 2 w / c`` (round trip);
  the volume is ``|sum_w U_w(x, y, z)|``.

  The sum over ``w`` at every depth costs ``K Z`` per lateral frequency when
  done directly (``depth_sum="direct"``, as the public code and our NumPy
  twin do). For uniformly spaced depth planes it is a type-1 non-uniform FFT,
  ``depth_sum="nufft"`` (default): the same numbers to 2.3e-7 of the peak in
  float64 (the kernel's error); in float32 the two differ by 6.3e-6 of the
  peak at 128 x 128 x 512 (both in float32 round-off), in ``O(K + Z log Z)``
  per lateral frequency.
  Measured at 128 x 128 x 512: see ``benchmarks/results/physics.md``.

  Args:
    transient: ``[..., T, H, W]`` counts >= 0.
    setup: the capture.
    cycles, sampling_coeff: wavelet parameters. ``cycles`` defaults to 3
      (public codes use 4-6): the magnitude peak of a point sits early by
      about ``0.5 * cycles`` depth bins near 0.5 m on coarse grids (measured:
      up to -6 bins with 5 cycles on a 16 x 16, 1 m scan), so a shorter
      envelope keeps depth within 3 bins.
    ratio: keep frequencies whose spectrum exceeds this fraction of its peak.
    depth_sum: ``"nufft"`` or ``"direct"`` (the exact sum; slow reference).
    chunk: depth planes per scan step of ``"direct"`` (memory vs. speed).
  Returns:
    ``[..., Z, H, W]`` float32, >= 0.
  """
  x, batch = _validate.prepare_transient(transient, setup)
  if depth_sum not in ("nufft", "direct"):
    raise ValueError(f"depth_sum must be 'nufft' or 'direct', got {depth_sum!r}")
  if not (isinstance(chunk, int) and chunk >= 1):
    raise ValueError(f"chunk must be a positive integer, got {chunk!r}")
  options = (float(cycles), float(sampling_coeff), float(ratio))
  window = _rsd_window(setup, illumination_wavelet(setup, cycles=options[0],
                                                   sampling_coeff=options[1]))
  if depth_sum == "nufft":
    plan = _rsd_plan(setup, *options, x.dtype)
    return _validate.unbatch(_rsd_nufft_batch(x, plan, window).astype(x.dtype), batch)
  dtft, kz, mask = _rsd_operators(setup, *options, x.dtype)
  k0, k1 = setup.depth_bins
  depths = (k0 * setup.depth_bin_length, setup.depth_bin_length, k1 - k0)
  chunk = min(chunk, k1 - k0)
  return _validate.unbatch(
      _rsd_direct_batch(x, dtft, kz, mask, window, depths, chunk).astype(x.dtype), batch)


# ------------------------------------------------------------------ dispatch
_FUNCTIONS = {"fbp": fbp, "lct": lct, "fk": fk, "phasor": phasor, "rsd": rsd}


def reconstruct(transient, setup: Setup, method: str, *, depth_range=None, **options) -> jax.Array:
  """Reconstruct a hidden volume with one of the classic methods.

  Args:
    transient: ``[..., T, H, W]`` counts >= 0 (t = 0 at the wall).
    setup: the capture; its ``depth_range`` gates time and crops the volume.
    method: ``"fbp"``, ``"lct"``, ``"fk"``, ``"phasor"`` or ``"rsd"``.
    depth_range: ``None`` (the Setup's), ``(z_min, z_max)`` metres, or
      ``"auto"``: estimated from the capture
      (:func:`nlosjax.physics.depth_range.auto_depth_range`; the volume's depth
      bins are that Setup's ``depth_bins``; concrete input only).
    **options: passed to the method (e.g. ``snr``, ``falloff`` for ``lct``).
  Returns:
    ``[..., Z, H, W]`` float32 volume, >= 0 (``fk``: albedo squared).
  Raises:
    ValueError: unknown method or option, bad shapes or values.
  """
  if method not in _FUNCTIONS:
    raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
  if isinstance(depth_range, str):
    if depth_range != "auto":
      raise ValueError(f"depth_range must be None, (z_min, z_max) or 'auto', got {depth_range!r}")
    from nlosjax.physics.depth_range import auto_depth_range
    setup = auto_depth_range(transient, setup)
  elif depth_range is not None:
    setup = setup.ungated().with_depth_range(*depth_range)
  fn = _FUNCTIONS[method]
  try:
    return fn(transient, setup, **options)
  except TypeError as e:
    if "unexpected keyword" in str(e):
      raise ValueError(f"method {method!r} does not take option(s) {sorted(options)}: {e}") from None
    raise

"""NumPy/SciPy twins of the public confocal NLOS reconstructions.

These are plain NumPy/SciPy ports of the algorithms in the public reference
code (nlos-fk ``cnlos_reconstruction.m`` and O'Toole's LCT code), written from
their published formulas. They serve two
purposes:

* the baseline that ``benchmarks/physics/`` times the JAX methods against
  (operators prebuilt, ``scipy.fft`` on all cores, single precision), and
* our stand-in for "the public reference implementation" when checking the JAX
  reconstructions on measured scans.

So they keep the public code's conventions, not nlosjax's where the two differ:

* half wall ``width = wall_size / 2``; the LCT PSF spans the padded
  ``2N x 2N`` grid with ``linspace(-1, 1, 2N)``, which implies a scan spacing
  of ``wall_size / N`` (nlosjax's ``Setup`` uses ``wall_size / (N - 1)``);
* ``t_n = linspace(0, 1, M)`` for the radiometric scaling;
* the MATLAB ``resamplingOperator`` (closed form below) and ``definePsf``;
* full complex ``fftn`` on ``(2M, 2N, 2N)`` arrays.

The one constant taken from nlosjax is the speed of light (the Setup's exact
value rather than the MATLAB code's 3e8, 0.07 % apart), so that bins line up
with the JAX side.

API: every method ``m`` in :data:`METHODS` has ``build_<m>(setup, **options)``,
which returns the prebuilt operators, and ``<m>(transient, ops)``, which maps a
``[T, H, W]`` transient to a non-negative float32 ``[Z, H, W]`` volume
(``Z = T``, or the Setup's depth bins when it has a ``depth_range``: the twins
always reconstruct every bin and crop at the end). :func:`build` and
:func:`reconstruct` dispatch by name.

All methods except ``rsd`` need a square scan grid (``H == W``), as the public
code does.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import numpy as np
import scipy.fft
import scipy.sparse

from nlosjax.physics.setup import SPEED_OF_LIGHT, Setup

METHODS = ("fbp", "lct", "fk", "phasor", "rsd")

_FALLOFF_POWER = {"diffuse": 4, "retroreflective": 2}


# ------------------------------------------------------------------ helpers
def _square_grid(setup: Setup, method: str) -> tuple[int, int]:
  """``(M, N)`` for a square-grid method; raise on a rectangular grid."""
  h, w = setup.grid
  if h != w:
    raise ValueError(
        f"numpy twin '{method}' follows the public code and needs a square scan grid,"
        f" got grid {setup.grid}")
  return setup.num_bins, h


def _as_transient(transient, setup: Setup) -> np.ndarray:
  """The transient as a float32 ``[T, H, W]`` array (no batch axes)."""
  x = np.asarray(transient)
  if x.ndim != 3:
    raise ValueError(f"numpy twins take one [T, H, W] transient, got shape {x.shape}")
  setup.check_transient(x)
  return x.astype(np.float32, copy=False)


def _crop_depth(vol: np.ndarray, setup: Setup) -> np.ndarray:
  """Keep the Setup's depth bins (all of them without a ``depth_range``)."""
  k0, k1 = setup.depth_bins
  if (k0, k1) == (0, vol.shape[0]):
    return vol
  return np.ascontiguousarray(vol[k0:k1])


def _falloff_scale(num_bins: int, falloff: str) -> np.ndarray:
  """``t_n ** 4`` (diffuse) or ``t_n ** 2`` (retroreflective), ``[M, 1, 1]`` float32."""
  if falloff not in _FALLOFF_POWER:
    raise ValueError(f"falloff must be one of {sorted(_FALLOFF_POWER)}, got {falloff!r}")
  t_n = np.linspace(0.0, 1.0, num_bins)
  return (t_n ** _FALLOFF_POWER[falloff]).astype(np.float32)[:, None, None]


def _apply_rows(mat: scipy.sparse.csr_matrix, vol: np.ndarray) -> np.ndarray:
  """``mat @ vol`` along the first axis of a ``[M, ...]`` array."""
  m = vol.shape[0]
  return np.asarray(mat @ vol.reshape(m, -1)).reshape((mat.shape[0],) + vol.shape[1:])


# ---------------------------------------------------------- LCT operators
def resampling_operator(num_bins: int) -> tuple[scipy.sparse.csr_matrix, scipy.sparse.csr_matrix]:
  """``(mtx, mtxi)``: the MATLAB ``resamplingOperator`` as float32 CSR matrices.

  The MATLAB code puts ``1/sqrt(x)`` at ``(x, ceil(sqrt(x)))`` of an
  ``M^2 x M`` matrix and averages pairs of rows ``log2(M)`` times. That is the
  closed form ``mtx[i, j] = (1/M) * sum over x in [i*M + 1, (i+1)*M] with
  ceil(sqrt(x)) == j + 1 of 1/sqrt(x)``, and ``mtxi = mtx.T``. The closed form
  works for any ``M`` (the halving needs a power of two). ``mtx`` is rank
  deficient (early t-bins share a v-bin): never invert it.
  """
  m = int(num_bins)
  x = np.arange(1, m * m + 1, dtype=np.float64)
  rows = (np.arange(m * m) // m).astype(np.int64)
  # sqrt is correctly rounded in float64, so ceil is exact on perfect squares.
  cols = (np.ceil(np.sqrt(x)) - 1).astype(np.int64)
  vals = 1.0 / (np.sqrt(x) * m)
  mtx = scipy.sparse.coo_matrix((vals, (rows, cols)), shape=(m, m)).tocsr()  # sums duplicates
  mtx.sum_duplicates()
  mtx = mtx.astype(np.float32)
  return mtx, mtx.T.tocsr()


def define_psf(num_bins: int, n: int, slope: float) -> np.ndarray:
  """The LCT blur kernel of ``definePsf``: float64 ``[2M, 2N, 2N]``.

  ``x_n, y_n = linspace(-1, 1, 2N)``, ``z_n = linspace(0, 2, 2M)``; each
  ``(y, x)`` column holds a single one at the ``z`` nearest to the cone
  ``(4 slope)^2 (x_n^2 + y_n^2)``. The public code finds it with a float
  equality ``psf == min`` (ties would give two ones); we take the first argmin.

  Trap handled here: when ``slope > 0.25`` (e.g. 128 bins of 32 ps on a 2 m
  wall) the cone leaves the z-range and the public code puts a spurious one in
  the last slice of every such column. Columns whose cone misses the grid by
  more than half a z-step are left empty instead.

  Then: divide by the centre column's sum (one here), by the L2 norm, and
  roll by ``+N`` in ``y`` and ``x`` so that the apex sits at index 0.
  """
  m2, n2 = 2 * num_bins, 2 * n
  xy = np.linspace(-1.0, 1.0, n2)
  z_n = np.linspace(0.0, 2.0, m2)
  dz = z_n[1] - z_n[0]
  cone = (4.0 * slope) ** 2 * (xy[:, None] ** 2 + xy[None, :] ** 2)  # [2N, 2N] (y, x)
  # argmin over the linspace grid: only the neighbours of cone/dz can win.
  guess = np.floor(cone / dz).astype(np.int64)
  best = np.clip(guess - 1, 0, m2 - 1)
  best_dist = np.abs(cone - z_n[best])
  for shift in (0, 1, 2):
    cand = np.clip(guess + shift, 0, m2 - 1)
    dist = np.abs(cone - z_n[cand])
    better = dist < best_dist  # strict: the first (lowest) index wins ties
    best = np.where(better, cand, best)
    best_dist = np.where(better, dist, best_dist)
  inside = best_dist <= 0.5 * dz * (1.0 + 1e-9)
  psf = np.zeros((m2, n2, n2), dtype=np.float64)
  yy, xx = np.nonzero(inside)
  psf[best[yy, xx], yy, xx] = 1.0
  psf /= psf[:, n - 1, n - 1].sum()  # MATLAB psf(:, U, U), 1-based
  psf /= np.linalg.norm(psf)
  return np.roll(psf, (n, n), axis=(1, 2))


def _lct_geometry(setup: Setup, method: str) -> tuple[int, int, float]:
  """``(M, N, slope)`` with ``slope = width / range`` of the public code."""
  m, n = _square_grid(setup, method)
  width = setup.wall_size / 2.0
  range_ = m * setup.bin_length
  return m, n, width / range_


def _psf_spectrum(m: int, n: int, slope: float) -> np.ndarray:
  """``fftn(psf)`` computed in float64, returned as complex64."""
  return scipy.fft.fftn(define_psf(m, n, slope), workers=-1).astype(np.complex64)


def _lct_filter(data: np.ndarray, mtx, mtxi, invpsf: np.ndarray) -> np.ndarray:
  """Resample, pad to ``(2M, 2N, 2N)``, filter with ``invpsf``, crop, resample back.

  Returns ``real(mtxi @ crop(ifftn(fftn(pad(mtx @ data)) * invpsf)))`` as
  float32 (unclamped). ``mtxi`` is real, so taking the real part before it is
  the same as after.
  """
  m, n1, n2 = data.shape
  padded = np.zeros((2 * m, 2 * n1, 2 * n2), dtype=np.float32)
  padded[:m, :n1, :n2] = _apply_rows(mtx, data)
  spec = scipy.fft.fftn(padded, workers=-1)
  del padded
  spec *= invpsf
  tvol = scipy.fft.ifftn(spec, workers=-1, overwrite_x=True)
  cropped = np.ascontiguousarray(tvol[:m, :n1, :n2].real)
  del tvol, spec
  return _apply_rows(mtxi, cropped)


# --------------------------------------------------------------------- LCT
@dataclasses.dataclass(frozen=True)
class LCTOps:
  setup: Setup
  mtx: scipy.sparse.csr_matrix
  mtxi: scipy.sparse.csr_matrix
  invpsf: np.ndarray  # complex64 [2M, 2N, 2N]
  scale: np.ndarray   # float32 [M, 1, 1], t_n^4 or t_n^2


def build_lct(setup: Setup, snr: float = 0.1, falloff: str = "diffuse") -> LCTOps:
  """Operators of the LCT with the Wiener filter ``conj(F) / (|F|^2 + 1/snr)``.

  ``snr`` 0.1 is nlos-fk's default; O'Toole used 0.8 for the retroreflective
  scenes and 0.08 for diffuse ones. ``falloff`` is ``"diffuse"`` (``t^4``) or
  ``"retroreflective"`` (``t^2``).
  """
  if not snr > 0:
    raise ValueError(f"snr must be > 0, got {snr!r}")
  m, n, slope = _lct_geometry(setup, "lct")
  fpsf = _psf_spectrum(m, n, slope)
  # |F|^2 has exact zeros: only ever the regularised inverse.
  invpsf = (np.conj(fpsf) / (np.abs(fpsf) ** 2 + np.float32(1.0 / snr))).astype(np.complex64)
  mtx, mtxi = resampling_operator(m)
  return LCTOps(setup, mtx, mtxi, invpsf, _falloff_scale(m, falloff))


def lct(transient, ops: LCTOps) -> np.ndarray:
  """Light-cone transform with the Wiener filter: float32 ``[Z, H, W]``, >= 0."""
  data = _as_transient(transient, ops.setup) * ops.scale
  vol = _lct_filter(data, ops.mtx, ops.mtxi, ops.invpsf)
  np.maximum(vol, 0.0, out=vol)
  return _crop_depth(vol, ops.setup)


# --------------------------------------------------------------------- FBP
def log_kernel(size: int = 5, sigma: float = 1.0) -> np.ndarray:
  """nlos-fk ``filterLaplacian`` weights: ``G (r^2 - 3 sigma^2) / sigma^4``, zero mean.

  ``G`` is the normalised Gaussian (entries below ``eps * max`` zeroed). This is
  ``+Laplacian(G)``, negative on a blob; see :func:`build_fbp` for the sign.
  """
  lim = (size - 1) // 2
  ax = np.arange(-lim, lim + 1, dtype=np.float64)
  z, y, x = np.meshgrid(ax, ax, ax, indexing="ij")
  r2 = x * x + y * y + z * z
  var = sigma ** 2
  g = np.exp(-r2 / (2.0 * var))
  g[g < np.finfo(np.float64).eps * g.max()] = 0.0
  g /= g.sum()
  w = g * (r2 - 3.0 * var) / var ** 2
  return w - w.sum() / size ** 3


@dataclasses.dataclass(frozen=True)
class FBPOps:
  setup: Setup
  mtx: scipy.sparse.csr_matrix
  mtxi: scipy.sparse.csr_matrix
  bp_psf: np.ndarray     # complex64 [2M, 2N, 2N], conj(F)
  scale: np.ndarray      # float32 [M, 1, 1]
  log_shape: tuple[int, int, int]  # FFT size of the linear LoG convolution
  log_spec: np.ndarray   # complex64 rfftn of -LoG
  log_half: int          # (size - 1) // 2
  padding: str           # "edge" (replicate) or "zero"


def build_fbp(setup: Setup, falloff: str = "diffuse", padding: str = "edge",
              log_size: int = 5, log_sigma: float = 1.0) -> FBPOps:
  """Operators of filtered backprojection (LCT pipeline with ``conj(F)``, then -LoG).

  Sign trap: the public code (nlos-fk, LFE, USM) convolves with ``+LoG``
  (:func:`log_kernel`), which is negative on objects, so the final clamp keeps
  only the halos. We convolve with ``-LoG`` instead.

  Boundary trap that the sign fix exposes: the clamped backprojection is a
  large positive plateau that is brightest at the lateral edges, so a
  zero-padded ``-LoG`` (MATLAB ``convn(..., 'same')``, ``padding="zero"``)
  turns the volume's border into a bright frame that outshines the scene on
  measured data (the public ``+LoG`` makes that frame negative, and the clamp
  hides it). The default ``padding="edge"`` replicates the border voxels, as
  LFE does.
  """
  if padding not in ("edge", "zero"):
    raise ValueError(f"padding must be 'edge' or 'zero', got {padding!r}")
  m, n, slope = _lct_geometry(setup, "fbp")
  bp_psf = np.conj(_psf_spectrum(m, n, slope))
  mtx, mtxi = resampling_operator(m)
  kernel = -log_kernel(log_size, log_sigma)  # SIGN FIXED (public code: +LoG)
  half = (log_size - 1) // 2
  # Circular wrap-around then only touches indices below 2 * half, which we drop.
  shape = tuple(scipy.fft.next_fast_len(s + 2 * half, real=True) for s in (m, n, n))
  log_spec = scipy.fft.rfftn(kernel, s=shape, workers=-1).astype(np.complex64)
  return FBPOps(setup, mtx, mtxi, bp_psf, _falloff_scale(m, falloff), shape, log_spec, half,
                padding)


def fbp(transient, ops: FBPOps) -> np.ndarray:
  """Backprojection, clamp, ``-LoG`` ('same' size), ``max(v / max v, 0)``."""
  data = _as_transient(transient, ops.setup) * ops.scale
  vol = _lct_filter(data, ops.mtx, ops.mtxi, ops.bp_psf)
  np.maximum(vol, 0.0, out=vol)
  m, n1, n2 = vol.shape
  h = ops.log_half
  if ops.padding == "edge":
    vol = np.pad(vol, h, mode="edge")
    start = 2 * h  # 'same' output of the padded volume's full convolution
  else:
    start = h
  spec = scipy.fft.rfftn(vol, s=ops.log_shape, workers=-1)
  del vol
  spec *= ops.log_spec
  full = scipy.fft.irfftn(spec, s=ops.log_shape, workers=-1, overwrite_x=True)
  out = np.ascontiguousarray(full[start:start + m, start:start + n1, start:start + n2],
                             dtype=np.float32)
  peak = out.max()
  if peak > 0:
    out /= peak
  np.maximum(out, 0.0, out=out)
  return _crop_depth(out, ops.setup)


# --------------------------------------------------------------------- f-k
@dataclasses.dataclass(frozen=True)
class FKOps:
  setup: Setup
  scale: np.ndarray  # float32 [M, 1, 1], t_n^2
  src: np.ndarray    # int32 [M-1, 4N^2], flat index of the lower kz neighbour
  frac: np.ndarray   # float32 [M-1, 4N^2], linear weight of the upper neighbour
  gain: np.ndarray   # float32 [M-1, 4N^2], kz>0 mask * Jacobian * in-grid mask


def build_fk(setup: Setup) -> FKOps:
  """Stolt-interpolation tables of f-k migration (nlos-fk alg 2).

  The public code works on ``fftshift``-ed spectra with grids
  ``kz = (-M..M-1)/M`` and ``kx, ky = (-N..N-1)/N``; it maps
  ``Phi(kz) = 1[kz > 0] |kz| / max(kz', 1e-6) Psi(kz')`` with
  ``kz' = sqrt(a^2 (kx^2 + ky^2) + kz^2)``, ``a = N range / (4 M width)``,
  linear interpolation along kz only and zero outside the grid. The shifts in
  kx and ky are a permutation that the final ``ifftshift`` undoes, and only
  ``kz > 0`` survives (reading ``kz' >= kz > 0``), so we work on the unshifted
  spectrum: output planes ``j = 1..M-1`` (``kz = j/M``) read input planes
  ``floor(kz' M)`` and the next one, valid while ``kz' M <= M - 1`` (the last
  shifted grid point).
  """
  m, n = _square_grid(setup, "fk")
  width = setup.wall_size / 2.0
  range_ = m * setup.bin_length
  a = n * range_ / (4.0 * m * width)
  k_lat = np.fft.fftfreq(2 * n, d=1.0 / (2 * n)) / n  # (-N..N-1)/N, unshifted order
  lat2 = (k_lat[:, None] ** 2 + k_lat[None, :] ** 2).reshape(-1)  # [4N^2]
  kz = (np.arange(1, m, dtype=np.float64) / m)[:, None]  # [M-1, 1]
  kz_src = np.sqrt(a * a * lat2[None, :] + kz * kz)       # [M-1, 4N^2]
  pos = kz_src * m
  valid = pos <= (m - 1) * (1.0 + 1e-12)
  lower = np.minimum(np.floor(pos), m - 1)
  frac = np.where(valid, pos - lower, 0.0)
  lower = np.where(valid, lower, 0)
  plane = 4 * n * n
  src = (lower.astype(np.int64) * plane + np.arange(plane)[None, :]).astype(np.int32)
  gain = np.where(valid, kz / np.maximum(kz_src, 1e-6), 0.0)
  return FKOps(setup, (np.linspace(0.0, 1.0, m) ** 2).astype(np.float32)[:, None, None],
               src, frac.astype(np.float32), gain.astype(np.float32))


def fk(transient, ops: FKOps) -> np.ndarray:
  """f-k migration; like the public code the output is albedo squared."""
  data = _as_transient(transient, ops.setup) * ops.scale
  m, n, _ = data.shape
  padded = np.zeros((2 * m, 2 * n, 2 * n), dtype=np.float32)
  padded[:m, :n, :n] = np.sqrt(np.maximum(data, 0.0))
  psi = scipy.fft.fftn(padded, workers=-1)
  del padded
  flat = psi.reshape(-1)
  plane = 4 * n * n
  lo = flat.take(ops.src)                 # Psi at the lower kz neighbour
  hi = flat[plane:].take(ops.src)         # ... and at the next plane up
  hi -= lo
  hi *= ops.frac
  lo += hi
  lo *= ops.gain
  del hi
  psi[0] = 0.0
  psi[m:] = 0.0
  psi[1:m] = lo.reshape(m - 1, 2 * n, 2 * n)
  del lo
  tvol = scipy.fft.ifftn(psi, workers=-1, overwrite_x=True)
  del psi
  cropped = tvol[:m, :n, :n]
  vol = (cropped.real ** 2 + cropped.imag ** 2).astype(np.float32)
  return _crop_depth(vol, ops.setup)


# ------------------------------------------------------------------ phasor
def phasor_wavelength(setup: Setup, sampling_coeff: float = 2.0) -> float:
  """Virtual wavelength ``lambda_v = 2 * sampling_coeff * Delta`` (path length, m).

  ``Delta = wall_size / (N - 1)`` as in nlos-fk (the larger spacing for a
  rectangular grid).
  """
  delta = max(setup.wall_size / (g - 1) for g in setup.grid)
  return 2.0 * sampling_coeff * delta


def phasor_wavelet(setup: Setup, sampling_coeff: float = 2.0,
                   cycles: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
  """``(cos_wave, sin_wave)`` of nlos-fk ``waveconv.m``, float32 ``[L]`` each.

  ``L = round(cycles * lambda_v / bin_len)`` samples, ``ncyc = L bin_len /
  lambda_v``, carrier ``2 pi ncyc k / L`` for ``k = 1..L``, window
  ``gausswin(L, 1/0.3)`` (``sigma = 0.15 (L - 1)`` samples).
  """
  lam = phasor_wavelength(setup, sampling_coeff)
  length = max(1, int(math.floor(cycles * lam / setup.bin_length + 0.5)))  # MATLAB round
  ncyc = length * setup.bin_length / lam
  k = np.arange(1, length + 1, dtype=np.float64)
  phase = 2.0 * np.pi * ncyc * k / length
  if length > 1:
    half = (length - 1) / 2.0
    window = np.exp(-0.5 * ((1.0 / 0.3) * (np.arange(length) - half) / half) ** 2)
  else:
    window = np.ones(1)
  return ((np.cos(phase) * window).astype(np.float32),
          (np.sin(phase) * window).astype(np.float32))


@dataclasses.dataclass(frozen=True)
class PhasorOps:
  setup: Setup
  mtx: scipy.sparse.csr_matrix
  mtxi: scipy.sparse.csr_matrix
  bp_psf: np.ndarray  # complex64 [2M, 2N, 2N], conj(F)
  n_fft: int          # FFT length of the linear time convolution
  wave_cos: np.ndarray  # complex64 rfft of the cos wavelet
  wave_sin: np.ndarray  # complex64 rfft of the sin wavelet
  offset: int           # MATLAB conv(..., 'same') start: floor(L / 2)


def build_phasor(setup: Setup, sampling_coeff: float = 2.0, cycles: float = 5.0) -> PhasorOps:
  """Operators of nlos-fk alg 3 (phasor field via fast backprojection)."""
  m, n, slope = _lct_geometry(setup, "phasor")
  cos_w, sin_w = phasor_wavelet(setup, sampling_coeff, cycles)
  length = cos_w.shape[0]
  n_fft = scipy.fft.next_fast_len(m + length - 1, real=True)
  mtx, mtxi = resampling_operator(m)
  return PhasorOps(
      setup, mtx, mtxi, np.conj(_psf_spectrum(m, n, slope)), n_fft,
      scipy.fft.rfft(cos_w, n_fft).astype(np.complex64),
      scipy.fft.rfft(sin_w, n_fft).astype(np.complex64),
      length // 2)


def phasor(transient, ops: PhasorOps) -> np.ndarray:
  """Phasor-field reconstruction (nlos-fk alg 3): float32 ``[Z, H, W]``, >= 0.

  Each histogram is convolved with the cos and sin wavelets (MATLAB ``'same'``:
  the full convolution from index ``floor(L/2)``; numpy's ``'same'`` starts at
  ``(L-1)//2``, one bin off for even ``L``). Both go through the LCT
  backprojection (``conj(F)``, no ``t^4``). The backprojection of a real
  array is real, so we pack cos + i sin into one complex array and backproject
  it once: the real and imaginary parts are the two backprojections. Then
  ``sqrt(BP_cos^2 + BP_sin^2)``, ``mtxi`` and a clamp.
  """
  data = _as_transient(transient, ops.setup)
  m, n1, n2 = data.shape
  spec = scipy.fft.rfft(data.reshape(m, -1), ops.n_fft, axis=0, workers=-1)
  sl = slice(ops.offset, ops.offset + m)
  conv_cos = scipy.fft.irfft(spec * ops.wave_cos[:, None], ops.n_fft, axis=0, workers=-1)[sl]
  conv_sin = scipy.fft.irfft(spec * ops.wave_sin[:, None], ops.n_fft, axis=0, workers=-1)[sl]
  del spec
  packed = np.zeros((2 * m, 2 * n1, 2 * n2), dtype=np.complex64)
  packed[:m, :n1, :n2].real = (ops.mtx @ conv_cos).reshape(m, n1, n2)
  packed[:m, :n1, :n2].imag = (ops.mtx @ conv_sin).reshape(m, n1, n2)
  del conv_cos, conv_sin
  spec3 = scipy.fft.fftn(packed, workers=-1, overwrite_x=True)
  del packed
  spec3 *= ops.bp_psf
  tvol = scipy.fft.ifftn(spec3, workers=-1, overwrite_x=True)
  del spec3
  cropped = tvol[:m, :n1, :n2]
  mag = np.sqrt(cropped.real ** 2 + cropped.imag ** 2).astype(np.float32)
  del tvol
  vol = _apply_rows(ops.mtxi, mag)
  np.maximum(vol, 0.0, out=vol)
  return _crop_depth(vol, ops.setup)


# --------------------------------------------------------------------- RSD
@dataclasses.dataclass(frozen=True)
class RSDOps:
  setup: Setup
  freq_index: np.ndarray  # int64 [K], rfft bins k (omega_k = 2 pi k / (T dt))
  weight: np.ndarray      # float32 [K], |P_hat(omega_k)| / max
  kz: np.ndarray          # float32 [K, 2H, 2W], axial wavenumber (0 where evanescent)
  mask: np.ndarray        # bool [K, 2H, 2W], propagating components
  step: np.ndarray        # complex64 [K, 2H, 2W], exp(i dz kz) * mask
  dz: float               # depth step c dt / 2, metres
  chunk: int              # depths per chunk


def build_rsd(setup: Setup, sampling_coeff: float = 2.0, cycles: float = 5.0,
              ratio: float = 0.1, chunk: int = 64) -> RSDOps:
  """Operators of confocal phasor-field RSD by the angular spectrum method.

  Wavelet ``P(t) = exp(i Omega t) exp(-t^2 / (2 sigma^2))`` with
  ``Omega = 2 pi c / lambda_v`` and ``sigma = 0.15 (L - 1) dt`` (the same
  ``lambda_v`` and ``L`` as :func:`phasor_wavelet`). Its spectrum (``e^{-i w t}``
  convention) is a Gaussian ``exp(-(w - Omega)^2 sigma^2 / 2)`` up to a
  constant; we keep the DFT frequencies ``w_k = 2 pi k / (T dt)`` where it
  exceeds ``ratio`` of its maximum. For the round trip the wavenumber is
  ``2 w / c``: ``kz = sqrt((2 w / c)^2 - kx^2 - ky^2)`` on the ``(2H, 2W)``
  zero-padded lateral grid, evanescent components dropped.
  """
  if not 0 < ratio < 1:
    raise ValueError(f"ratio must be in (0, 1), got {ratio!r}")
  h, w = setup.grid
  t, dt = setup.num_bins, setup.bin_width
  lam = phasor_wavelength(setup, sampling_coeff)
  length = max(1, int(math.floor(cycles * lam / setup.bin_length + 0.5)))
  sigma = 0.15 * max(length - 1, 1) * dt
  omega_c = 2.0 * np.pi * SPEED_OF_LIGHT / lam
  k = np.arange(t // 2 + 1)
  omega = 2.0 * np.pi * k / (t * dt)
  gauss = np.exp(-0.5 * ((omega - omega_c) * sigma) ** 2)
  keep = gauss > ratio
  if not keep.any():
    raise ValueError(
        f"no DFT frequency of {t} bins of {dt} s lies in the wavelet's band"
        f" (lambda_v = {lam:.4g} m); use more bins or a longer wavelength")
  dy, dx = setup.spacing
  ky = 2.0 * np.pi * np.fft.fftfreq(2 * h, dy)
  kx = 2.0 * np.pi * np.fft.fftfreq(2 * w, dx)
  kwave = 2.0 * omega[keep] / SPEED_OF_LIGHT
  kz2 = kwave[:, None, None] ** 2 - ky[None, :, None] ** 2 - kx[None, None, :] ** 2
  mask = kz2 > 0
  kz = np.sqrt(np.where(mask, kz2, 0.0))
  dz = setup.depth_bin_length
  step = np.where(mask, np.exp(1j * dz * kz), 0.0).astype(np.complex64)
  return RSDOps(setup, k[keep], gauss[keep].astype(np.float32), kz.astype(np.float32), mask,
                step, dz, int(max(1, chunk)))


def rsd(transient, ops: RSDOps) -> np.ndarray:
  """Confocal phasor-field RSD (angular spectrum): ``|field|`` at every depth bin.

  ``P_w(y, x) = sum_t tau[t, y, x] exp(-i w t dt) P_hat(w)`` (an rfft along
  t), zero-padded to ``(2H, 2W)`` and 2D-FFT'd; at depth ``z_j = j dz`` the
  field is ``ifft2(sum_w U_w exp(+i z_j kz))`` cropped to ``(H, W)``. Depths
  go in chunks: at a chunk start the phase is computed directly, inside the
  chunk it advances by one ``exp(i dz kz)`` per depth.
  """
  setup = ops.setup
  data = _as_transient(transient, setup)
  t, h, w = data.shape
  spec_t = scipy.fft.rfft(data, axis=0, workers=-1)[ops.freq_index]
  spec_t *= ops.weight[:, None, None]
  field = scipy.fft.fft2(spec_t, s=(2 * h, 2 * w), axes=(1, 2), workers=-1)
  del spec_t
  field *= ops.mask
  out = np.empty((t, h, w), dtype=np.float32)
  planes = np.empty((min(ops.chunk, t), 2 * h, 2 * w), dtype=np.complex64)
  for z0 in range(0, t, ops.chunk):
    zc = min(ops.chunk, t - z0)
    phase = (z0 * ops.dz) * ops.kz
    acc = field * (np.cos(phase) + 1j * np.sin(phase)).astype(np.complex64)
    del phase
    for i in range(zc):
      np.sum(acc, axis=0, out=planes[i])
      if i + 1 < zc:
        acc *= ops.step
    del acc
    vol = scipy.fft.ifft2(planes[:zc], axes=(1, 2), workers=-1)[:, :h, :w]
    out[z0:z0 + zc] = np.abs(vol)
  return _crop_depth(out, setup)


# ---------------------------------------------------------------- dispatch
BUILDERS: dict[str, Callable[..., Any]] = {
    "fbp": build_fbp, "lct": build_lct, "fk": build_fk, "phasor": build_phasor, "rsd": build_rsd,
}
RUNNERS: dict[str, Callable[[Any, Any], np.ndarray]] = {
    "fbp": fbp, "lct": lct, "fk": fk, "phasor": phasor, "rsd": rsd,
}


def load_published(path) -> tuple[np.ndarray, Setup]:
  """O'Toole et al.'s ``rect_data`` scan with the public code's preparation, read by SciPy alone.

  ``cnlos_reconstruction.m``: zero the first 600 raw 4 ps bins (the direct reflection), sum
  groups of 4 (16 ps). Returns ``(transient [T, H, W] float32, Setup)`` with
  ``transient[t, y, x]`` from ``rect_data[x, y, :]`` and a wall of ``2 * width``; written apart
  from :func:`nlosjax.data.io.load_measurement` so that the twins check it.
  """
  import scipy.io
  raw = scipy.io.loadmat(path, variable_names=("rect_data", "width"))
  rect = raw["rect_data"].astype(np.float32)                     # [x, y, t], 4 ps bins
  rect[:, :, :600] = 0
  x = np.ascontiguousarray(rect.reshape(rect.shape[0], rect.shape[1], -1, 4).sum(-1).transpose(2, 1, 0))
  setup = Setup(wall_size=2 * float(np.squeeze(raw["width"])), grid=x.shape[1:], bin_width=16e-12,
                num_bins=x.shape[0])
  return x, setup


def build(setup: Setup, method: str, **options):
  """Prebuilt operators of ``method`` (one of :data:`METHODS`)."""
  if method not in BUILDERS:
    raise ValueError(f"unknown method {method!r}; expected one of {METHODS}")
  return BUILDERS[method](setup, **options)


def run(transient, method: str, ops) -> np.ndarray:
  """Apply ``method`` with operators from :func:`build`."""
  if method not in RUNNERS:
    raise ValueError(f"unknown method {method!r}; expected one of {METHODS}")
  return RUNNERS[method](transient, ops)


def reconstruct(transient, setup: Setup, method: str, **options) -> np.ndarray:
  """Build the operators and reconstruct in one call (mirrors ``nlosjax.physics.reconstruct``)."""
  return run(transient, method, build(setup, method, **options))

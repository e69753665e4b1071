"""Rayleigh-Sommerfeld diffraction of the phasor field (``rsd``), with its depth-sum NUFFT.

How ``rsd`` differs from the public code (the confocal wavenumber, the exact
angular-spectrum transfer function, the NUFFT depth sum) is described in the
docstring of :mod:`nlosjax.physics.reconstruct`.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.fft

from nlosjax.physics import _validate
from nlosjax.physics.setup import SPEED_OF_LIGHT, Setup
from nlosjax.physics.wavelet import Wavelet, illumination_wavelet


def _rsd_window(setup: Setup, wavelet: Wavelet) -> tuple[int, int]:
  """Time bins RSD reads: ``setup.time_bins`` widened by half the wavelet (as ``phasor``).

  The virtual wave at depth ``z`` is the data convolved with ``P(t)`` around
  ``t = 2 z / c``, so bins up to half a wavelet outside the range contribute.
  """
  t0, t1 = setup.time_bins
  half = wavelet.num_samples // 2
  return (max(0, t0 - half), min(setup.num_bins, t1 + half))


def _rsd_frequencies(setup: Setup, cycles: float, sampling_coeff: float,
                     ratio: float) -> tuple[Wavelet, np.ndarray]:
  """``(wavelet, omega [K] rad/s)``: the frequencies RSD propagates, ``rfft`` bins of ``setup.num_bins``."""
  wl = illumination_wavelet(setup, cycles=cycles, sampling_coeff=sampling_coeff)
  omega = wl.frequencies(setup.num_bins, ratio)
  if omega.size == 0:
    raise ValueError(f"no frequency of the wavelet spectrum exceeds ratio={ratio}")
  return wl, omega


@_validate.cached_operators(maxsize=16)
def _rsd_operators(setup: Setup, cycles: float, sampling_coeff: float, ratio: float, dtype):
  """``(dtft [K, Nt], kz [K, 2H, 2W], mask [K, 2H, 2W])``: the wall-field DTFT and axial wavenumbers."""
  wl, omega = _rsd_frequencies(setup, cycles, sampling_coeff, ratio)
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
                   data_fields=["bins", "weight", "source", "column", "row", "offset", "phase",
                                "deconv"],
                   meta_fields=["grid", "num_depths", "fft_len", "num_rows", "num_bins"])
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
    num_bins: ``T``, the capture's time bins (static): the frequencies are bins of
      its ``rfft``.
    bins: ``[K]`` int32, the ``rfft`` bin ``k`` of each frequency ``omega_k = 2 pi k / (T dt)``.
    weight: ``[K]`` complex, ``P_hat(omega_k) exp(-i omega_k t0 dt)``: the wall field
      per frequency is ``weight * rfft(x[t0:t1], n=T)[bins]`` (the DTFT of the
      time window, by FFT).
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
  num_bins: int
  bins: jax.Array
  weight: jax.Array
  source: jax.Array
  column: jax.Array
  row: jax.Array
  offset: jax.Array
  phase: jax.Array
  deconv: jax.Array


@_validate.cached_operators(maxsize=16)
def _rsd_plan(setup: Setup, cycles: float, sampling_coeff: float, ratio: float, dtype) -> RSDPlan:
  """Build (once per Setup and options) the NUFFT operators of :func:`rsd`."""
  _, kz, mask = _rsd_operators(setup, cycles, sampling_coeff, ratio, dtype)
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
  wl, omega = _rsd_frequencies(setup, cycles, sampling_coeff, ratio)
  bins = np.rint(omega * setup.num_bins * setup.bin_width / (2 * np.pi)).astype(np.int64)
  if not np.allclose(bins * 2 * np.pi / (setup.num_bins * setup.bin_width), omega, rtol=1e-12):
    raise AssertionError("internal: the RSD frequencies are not rfft bins")
  t0 = _rsd_window(setup, wl)[0]
  weight = wl.spectrum(omega) * np.exp(-2j * np.pi * bins * t0 / setup.num_bins)
  return RSDPlan(setup.grid, n_z, fft_len, num_rows, setup.num_bins, jnp.asarray(bins, jnp.int32),
                 jnp.asarray(weight, cdtype), jnp.asarray(flat, jnp.int32),
                 jnp.asarray(ff, jnp.int32), jnp.asarray(row, jnp.int32),
                 jnp.asarray(offset, dtype), jnp.asarray(phase, cdtype),
                 jnp.asarray(deconv, cdtype))


def _rsd_wall_spectrum(xi: jax.Array, dtft: jax.Array) -> jax.Array:
  """``[Nt, H, W]`` time window -> ``[K, 2H, 2W]`` lateral spectra of the wall field per frequency.

  The DTFT as a ``[K, Nt]`` matrix product (the direct sum's reference path);
  :func:`_rsd_wall_spectrum_fft` is the same by FFT.
  """
  h, w = xi.shape[-2:]
  fields = jnp.einsum("kt,thw->khw", dtft, xi.astype(dtft.dtype), precision="highest")
  return jnp.fft.fft2(fields, s=(2 * h, 2 * w))


def _rsd_wall_spectrum_fft(xi: jax.Array, plan: RSDPlan) -> jax.Array:
  """As :func:`_rsd_wall_spectrum`, the DTFT taken from ``rfft`` bins: ``[Nt, H, W]`` -> ``[K, 2H, 2W]``.

  The frequencies are ``rfft`` bins of the capture's ``T``, so the DTFT of the
  window is its length-``T`` ``rfft`` at those bins times ``plan.weight`` (2.5x
  faster than the ``[K, Nt]`` product at 128 x 128 x 512, K = 117).
  """
  h, w = xi.shape[-2:]
  spec = jnp.fft.rfft(jnp.moveaxis(xi, 0, -1), n=plan.num_bins, axis=-1)   # [H, W, T // 2 + 1]
  fields = jnp.moveaxis(spec[..., plan.bins] * plan.weight.astype(spec.dtype), -1, 0)
  return jnp.fft.fft2(fields, s=(2 * h, 2 * w))


@functools.partial(jax.jit, static_argnames=("window",))
def _rsd_nufft_batch(x, plan: RSDPlan, window):
  t0, t1 = window
  h, w = plan.grid
  n_f = 4 * h * w
  n_z, m, rows = plan.num_depths, plan.fft_len, plan.num_rows
  centre = n_z // 2
  taps = jnp.arange(_NUFFT_TAPS, dtype=plan.offset.dtype)
  kern = _es_kernel(taps[None, :] - plan.offset[:, None], jnp)         # [P, taps]
  start = jnp.stack([plan.column, plan.row], axis=1)                  # [P, 2] into [4HW, rows]
  # Each pair adds a window of `taps` consecutive cells of its column: one scatter
  # of P windows into the column-major grid (contiguous windows), then one
  # transpose; scattering taps * P single cells was 1.5x slower on CPU.
  spread = jax.lax.ScatterDimensionNumbers(update_window_dims=(1,), inserted_window_dims=(0,),
                                           scatter_dims_to_operand_dims=(0, 1))

  def one(xi):
    spec = _rsd_wall_spectrum_fft(xi[t0:t1], plan).reshape(-1)        # [K * 4HW]
    values = spec[plan.source] * plan.phase                           # [P]
    grid = jax.lax.scatter_add(jnp.zeros((n_f, rows), values.dtype), start,
                               kern.astype(values.dtype) * values[:, None], spread,
                               mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS).T   # [rows, 4HW]
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


"""Light-cone-transform (LCT) operators, built once per Setup and reused.

The confocal forward model (O'Toole et al. 2018)

    tau(x, y, t) = iiint rho(x', y', z) r^-4 delta(2 r - c t) dx' dy' dz

becomes a shift-invariant 3-D convolution after resampling time to
``v = (c t / 2)^2`` and depth to ``u = z^2``:

    v^{q/2} tau(x, y, 2 sqrt(v) / c) = h * [rho(x', y', sqrt(u)) / (2 sqrt(u))]

with ``q = 3`` for diffuse (``r^-4``) and ``q = 1`` for retroreflective
(``r^-2``) scenes, and ``h`` the light cone ``v - u = (x - x')^2 + (y - y')^2``.

Everything here is in *bin units*: a time bin ``t_b`` is one ``depth_bin_length``
of depth, ``v_b = t_b^2 / T`` and ``u_b = z_b^2 / T`` so that the v- and u-axes
also have ``T`` bins over the Setup's full range (as in the public code).

Differences from the public MATLAB code (documented, deliberate):

* Resampling matrices are built by averaging ``S`` mid-point sub-samples per
  bin (the public closed form uses the same sub-sampling with ``S = T``), for
  any ``T`` (no power-of-two requirement) and any window of bins (gating).
* The PSF places each cone column's weight on the two v-bins around the exact
  offset ``r_b^2 / T`` (linear interpolation: the exact overlap of a box-shaped
  u-bin with a box-shaped v-bin) instead of one nearest voxel; the lateral
  offsets use the true scan spacing ``wall_size / (N - 1)``.
* Convolutions are linear, not circular: the FFT length along v is at least
  ``Nv + Nu - 1`` and cone entries that can only land outside the measured
  window are dropped (no spurious ones in the last slice when the cone leaves
  the range). Data and PSF are real, so ``rfftn`` halves the memory.
* The PSF is scaled to unit L2 norm (as in the public code), so Wiener ``snr``
  values carry over.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import scipy.fft

from nlosjax.physics.setup import Setup

FALLOFF_POWER = {"diffuse": 3, "retroreflective": 1}


def check_falloff(falloff: str) -> int:
  """Return the LCT time power ``q`` of a falloff name, or raise ValueError."""
  if falloff not in FALLOFF_POWER:
    raise ValueError(f"falloff must be one of {sorted(FALLOFF_POWER)}, got {falloff!r}")
  return FALLOFF_POWER[falloff]


@dataclasses.dataclass(frozen=True)
class LCTDomain:
  """Bin windows of a (possibly gated) LCT problem; all ranges half-open.

  Attributes:
    t: ``(t0, t1)`` time bins read from the transient.
    v: ``(v0, v1)`` v-bins (resampled time) they cover.
    z: ``(k0, k1)`` depth bins of the output volume.
    u: ``(u0, u1)`` u-bins (resampled depth) they cover.
    fft_shape: ``(Lv, 2H, 2W)`` real-FFT shape of the linear convolution.
  """

  t: tuple[int, int]
  v: tuple[int, int]
  z: tuple[int, int]
  u: tuple[int, int]
  fft_shape: tuple[int, int, int]

  @property
  def num_v(self) -> int:
    return self.v[1] - self.v[0]

  @property
  def num_u(self) -> int:
    return self.u[1] - self.u[0]


def lct_domain(setup: Setup, *, t_margin: int = 0, z_margin: int = 0) -> LCTDomain:
  """The bin windows for ``setup`` (its depth range), widened by margins.

  Args:
    setup: the capture.
    t_margin: extra time bins on each side (for a temporal filter).
    z_margin: extra depth bins on each side (for a depth filter).
  """
  T = setup.num_bins
  t0, t1 = setup.time_bins
  k0, k1 = setup.depth_bins
  t0, t1 = max(0, t0 - t_margin), min(T, t1 + t_margin)
  k0, k1 = max(0, k0 - z_margin), min(T, k1 + z_margin)
  v0, v1 = (t0 * t0) // T, min(T, -(-(t1 * t1) // T))
  u0, u1 = (k0 * k0) // T, min(T, -(-(k1 * k1) // T))
  lv = scipy.fft.next_fast_len(v1 - v0 + u1 - u0 - 1, real=True)
  return LCTDomain((t0, t1), (v0, v1), (k0, k1), (u0, u1), (lv, 2 * setup.height, 2 * setup.width))


def _midpoints(lo: int, hi: int, samples: int) -> np.ndarray:
  """``[(hi - lo) * samples]`` mid-point sub-samples of bins lo..hi-1."""
  return (np.arange((hi - lo) * samples, dtype=np.float64) + 0.5) / samples + lo


def squared_axis_matrix(T: int, rows: tuple[int, int], cols: tuple[int, int], *,
                        power: float, samples: int | None = None) -> np.ndarray:
  """``[R, C]`` float64: rows on the squared axis (v or u), columns on the linear one (t or z).

  ``M[i, j] = mean over sub-samples s of v-bin i of [floor(t_s) = j] (t_s / T)^power``
  with ``t_s = sqrt(T v_s)``: applied to a histogram it returns the bin average
  of ``(t/T)^power tau(t)`` on the v-grid (``power = 3``: the diffuse LCT
  ``v^{3/2}``; ``power = -1``: the public code's plain ``mtx``, up to ``T``).
  """
  samples = samples or max(T, 64)
  r0, r1 = rows
  c0, c1 = cols
  v = _midpoints(r0, r1, samples)
  t = np.sqrt(v * T)
  j = np.floor(t).astype(np.int64)
  keep = (j >= c0) & (j < c1)
  i = (np.arange(v.size) // samples)[keep]
  w = (t[keep] / T) ** power / samples
  out = np.zeros((r1 - r0, c1 - c0))
  np.add.at(out, (i, j[keep] - c0), w)
  return out


def linear_axis_matrix(T: int, rows: tuple[int, int], cols: tuple[int, int], *,
                       power: float, samples: int = 64) -> np.ndarray:
  """``[R, C]`` float64: rows on the linear axis (t or z), columns on the squared one.

  ``M[j, i] = mean over sub-samples s of t-bin j of [floor(t_s^2 / T) = i] (t_s / T)^power``:
  the bin average on the t-grid of ``(t/T)^power g(v)`` for a function ``g``
  on the v-grid (``power = 0``: plain averaging, the public ``(T/2) mtxi``).
  """
  r0, r1 = rows
  c0, c1 = cols
  t = _midpoints(r0, r1, samples)
  i = np.floor(t * t / T).astype(np.int64)
  keep = (i >= c0) & (i < c1)
  j = (np.arange(t.size) // samples)[keep]
  w = (t[keep] / T) ** power / samples
  out = np.zeros((r1 - r0, c1 - c0))
  np.add.at(out, (j, i[keep] - c0), w)
  return out


def cone_psf(setup: Setup, domain: LCTDomain) -> np.ndarray:
  """``[Lv, 2H, 2W]`` float64 light-cone PSF laid out for the domain's linear convolution.

  Entry ``[m, p, q]`` weights a u-bin ``u`` into the v-bin ``u + m + (v0 - u0)``
  of the scan point ``p`` rows and ``q`` columns away (indices modulo the FFT
  shape). Unit L2 norm over the ungated cone.
  """
  T = setup.num_bins
  H, W = setup.grid
  dy, dx = setup.spacing
  lv = domain.fft_shape[0]
  p = np.arange(-(H - 1), H)
  q = np.arange(-(W - 1), W)
  r2 = ((p[:, None] * dy) ** 2 + (q[None, :] * dx) ** 2) / setup.depth_bin_length ** 2
  s = r2 / T                                  # exact v-offset of each cone column, v-bins
  s0 = np.floor(s).astype(np.int64)
  frac = s - s0
  # Unit L2 norm of the ungated cone (offsets that fit in T v-bins).
  w_lo = np.where(s0 < T, 1.0 - frac, 0.0)
  w_hi = np.where(s0 + 1 < T, frac, 0.0)
  norm = math.sqrt(float(np.sum(w_lo ** 2 + w_hi ** 2)))
  psf = np.zeros(domain.fft_shape)
  shift = domain.v[0] - domain.u[0]
  pp, qq = np.broadcast_to(p[:, None], s.shape), np.broadcast_to(q[None, :], s.shape)
  for offset, weight in ((s0, w_lo), (s0 + 1, w_hi)):
    m = offset - shift
    keep = (m > -domain.num_u) & (m < domain.num_v) & (weight > 0)
    np.add.at(psf, (m[keep] % lv, pp[keep] % (2 * H), qq[keep] % (2 * W)), weight[keep] / norm)
  return psf


@functools.partial(jax.tree_util.register_dataclass, data_fields=["psf_fft", "to_v", "to_z"],
                   meta_fields=["domain"])
@dataclasses.dataclass(frozen=True)
class LCTOperators:
  """Device arrays of one LCT problem (see :func:`lct_operators`).

  Attributes:
    domain: the bin windows (static).
    psf_fft: ``[Lv, 2H, W + 1]`` complex, ``rfftn`` of :func:`cone_psf`.
    to_v: ``[Nv, Nt]`` time -> v resampling with the falloff power.
    to_z: ``[Z, Nu]`` u -> depth averaging.
  """

  domain: LCTDomain
  psf_fft: jax.Array
  to_v: jax.Array
  to_z: jax.Array


@functools.lru_cache(maxsize=16)
def lct_operators(setup: Setup, power: float, *, t_margin: int = 0, z_margin: int = 0,
                  dtype=jnp.float32) -> LCTOperators:
  """Build (once, cached) the operators to backproject or invert the LCT for ``setup``.

  Args:
    setup: the capture (its depth range selects the bins).
    power: time power of the t -> v resampling (3 diffuse, 1 retroreflective,
      -1 plain, as the phasor method uses).
    t_margin, z_margin: widen the windows (see :func:`lct_domain`).
    dtype: float dtype of the real operators (complex counterpart for the PSF).
  """
  dom = lct_domain(setup, t_margin=t_margin, z_margin=z_margin)
  T = setup.num_bins
  cdtype = jnp.complex128 if jnp.dtype(dtype) == jnp.float64 else jnp.complex64
  psf_fft = np.fft.rfftn(cone_psf(setup, dom))
  to_v = squared_axis_matrix(T, dom.v, dom.t, power=power)
  to_z = linear_axis_matrix(T, dom.z, dom.u, power=0.0)
  return LCTOperators(dom, jnp.asarray(psf_fft, cdtype), jnp.asarray(to_v, dtype),
                      jnp.asarray(to_z, dtype))


def lct_filter(ops: LCTOperators, snr: float | None) -> jax.Array:
  """``[Lv, 2H, W + 1]``: ``conj(F)`` (backprojection, ``snr=None``) or the Wiener ``conj(F)/(|F|^2 + 1/snr)``."""
  f = ops.psf_fft
  if snr is None:
    return jnp.conj(f)
  return jnp.conj(f) / (jnp.abs(f) ** 2 + jnp.asarray(1.0 / snr, f.real.dtype))


def lct_apply(x: jax.Array, ops: LCTOperators, filt: jax.Array) -> jax.Array:
  """One gated LCT backprojection / inversion, before the depth resampling.

  Args:
    x: ``[Nt, H, W]`` real time window ``transient[t0:t1]``.
    ops: operators of the problem.
    filt: ``[Lv, 2H, W + 1]`` complex frequency-domain filter.
  Returns:
    ``[Nu, H, W]`` real, on the u-grid.
  """
  dom = ops.domain
  h, w = x.shape[-2:]
  data_v = jnp.einsum("vt,thw->vhw", ops.to_v, x, precision="highest")
  spec = jnp.fft.rfftn(data_v, s=dom.fft_shape)
  out = jnp.fft.irfftn(spec * filt, s=dom.fft_shape)
  return out[:dom.num_u, :h, :w]


def to_depth(vol_u: jax.Array, ops: LCTOperators) -> jax.Array:
  """``[Nu, H, W]`` u-grid -> ``[Z, H, W]`` depth grid (bin averages)."""
  return jnp.einsum("zu,uhw->zhw", ops.to_z, vol_u, precision="highest")

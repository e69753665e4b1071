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

from nlosjax.physics import _validate
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
    oversample: v- and u-bins per time bin (``v_b = oversample t_b^2 / T``).
  """

  t: tuple[int, int]
  v: tuple[int, int]
  z: tuple[int, int]
  u: tuple[int, int]
  fft_shape: tuple[int, int, int]
  oversample: int = 1

  @property
  def num_v(self) -> int:
    return self.v[1] - self.v[0]

  @property
  def num_u(self) -> int:
    return self.u[1] - self.u[0]


def cone_reach(setup: Setup, oversample: int = 1) -> int:
  """Largest v-offset (v-bins) of the confocal light cone over the scan grid: ``k_max``.

  A footprint sample at lateral distance ``r`` from the scan point lands
  ``oversample r^2 / (T dz^2)`` v-bins after its u-bin (``dz`` the depth bin
  length), split between that bin's floor and the next. :func:`cone_psf`'s
  samples lie within half a scan spacing of a grid point, so ``r`` is at most
  ``(H - 1/2) dy`` by ``(W - 1/2) dx`` (or the aperture); capped at the last
  v-bin.
  """
  T, tv = setup.num_bins, oversample * setup.num_bins
  dy, dx = setup.spacing
  reach2 = ((setup.height - 0.5) * dy) ** 2 + ((setup.width - 0.5) * dx) ** 2
  if setup.aperture is not None:
    reach2 = min(reach2, setup.aperture ** 2)
  return min(tv - 1, int(math.floor(reach2 / setup.depth_bin_length ** 2 * oversample / T)) + 1)


FFT_LENGTHS = ("full", "cone")


def lct_domain(setup: Setup, *, t_margin: int = 0, z_margin: int = 0,
               oversample: int = 1, fft_length: str = "full") -> LCTDomain:
  """The bin windows for ``setup`` (its depth range), widened by margins.

  Args:
    setup: the capture.
    t_margin: extra time bins on each side (for a temporal filter).
    z_margin: extra depth bins on each side (for a depth filter).
    oversample: v- and u-bins per time bin. The u-grid is coarse near the
      wall (one u-bin spans ``T / (2 oversample k)`` depth bins at bin ``k``),
      which biases LCT depths close to the wall; 2 halves that.
    fft_length: time length of the FFT box. ``"full"``: ``num_v + num_u - 1``
      (rounded up to a fast length), the public algorithm's padding, needed by
      the Wiener inverse, whose kernel is not compact. ``"cone"``: only as long
      as the light cone's reach needs for an exact linear convolution or
      correlation with the cone itself (backprojection, phasor, the forward
      model): shorter where the wall is small beside the depth range.
  """
  if not (isinstance(oversample, int) and oversample >= 1):
    raise ValueError(f"oversample must be a positive integer, got {oversample!r}")
  if fft_length not in FFT_LENGTHS:
    raise ValueError(f"fft_length must be one of {FFT_LENGTHS}, got {fft_length!r}")
  T = setup.num_bins
  t0, t1 = setup.time_bins
  k0, k1 = setup.depth_bins
  t0, t1 = max(0, t0 - t_margin), min(T, t1 + t_margin)
  k0, k1 = max(0, k0 - z_margin), min(T, k1 + z_margin)
  os, tv = oversample, oversample * T
  v0, v1 = (t0 * t0 * os) // T, min(tv, -(-(t1 * t1 * os) // T))
  u0, u1 = (k0 * k0 * os) // T, min(tv, -(-(k1 * k1 * os) // T))
  nv, nu, shift = v1 - v0, u1 - u0, v0 - u0
  # FFT length of the linear convolution: a scatterer at u-bin u returns at
  # v-bins u + k, k in [0, k_max] (the cone's v-offsets, see cone_psf), stored
  # at offsets d = k - shift of the v-window from the u-window. Pairs of a
  # v- and a u-bin span d in [-(nu - 1), nv - 1]; none outside the kernel's
  # offsets [lo, hi] may wrap onto them, which takes Lv > max(nv - 1 - lo,
  # hi + nu - 1): at most the full nv + nu - 1, less where the wall is small
  # beside the depth range (the cone stops at the wall's diagonal). Exact for
  # the cone itself, not for the Wiener inverse (fft_length="full").
  length = nv + nu - 1
  if fft_length == "cone":
    lo, hi = max(-shift, 1 - nu), min(cone_reach(setup, os) - shift, nv - 1)
    length = min(length, max(nv - 1 - lo, hi + nu - 1) + 1)
  lv = scipy.fft.next_fast_len(length, real=True)
  return LCTDomain((t0, t1), (v0, v1), (k0, k1), (u0, u1),
                   (lv, 2 * setup.height, 2 * setup.width), oversample)


def _midpoints(lo: int, hi: int, samples: int) -> np.ndarray:
  """``[(hi - lo) * samples]`` mid-point sub-samples of bins lo..hi-1."""
  return (np.arange((hi - lo) * samples, dtype=np.float64) + 0.5) / samples + lo


def squared_axis_matrix(T: int, rows: tuple[int, int], cols: tuple[int, int], *,
                        power: float, samples: int | None = None,
                        oversample: int = 1) -> np.ndarray:
  """``[R, C]`` float64: rows on the squared axis (v or u), columns on the linear one (t or z).

  ``M[i, j] = mean over sub-samples s of v-bin i of [floor(t_s) = j] (t_s / T)^power``
  with ``t_s = sqrt(T v_s / oversample)``: applied to a histogram it returns the bin average
  of ``(t/T)^power tau(t)`` on the v-grid (``power = 3``: the diffuse LCT
  ``v^{3/2}``; ``power = -1``: the public code's plain ``mtx``, up to ``T``).
  """
  samples = samples or max(T, 64)
  r0, r1 = rows
  c0, c1 = cols
  v = _midpoints(r0, r1, samples)
  t = np.sqrt(v * T / oversample)
  j = np.floor(t).astype(np.int64)
  keep = (j >= c0) & (j < c1)
  i = (np.arange(v.size) // samples)[keep]
  w = (t[keep] / T) ** power / samples
  out = np.zeros((r1 - r0, c1 - c0))
  np.add.at(out, (i, j[keep] - c0), w)
  return out


def linear_axis_matrix(T: int, rows: tuple[int, int], cols: tuple[int, int], *,
                       power: float, samples: int = 64, oversample: int = 1) -> np.ndarray:
  """``[R, C]`` float64: rows on the linear axis (t or z), columns on the squared one.

  ``M[j, i] = mean over sub-samples s of t-bin j of [floor(oversample t_s^2 / T) = i] (t_s / T)^power``:
  the bin average on the t-grid of ``(t/T)^power g(v)`` for a function ``g``
  on the v-grid (``power = 0``: plain averaging, the public ``(T/2) mtxi``).
  """
  r0, r1 = rows
  c0, c1 = cols
  t = _midpoints(r0, r1, samples)
  i = np.floor(t * t * oversample / T).astype(np.int64)
  keep = (i >= c0) & (i < c1)
  j = (np.arange(t.size) // samples)[keep]
  w = (t[keep] / T) ** power / samples
  out = np.zeros((r1 - r0, c1 - c0))
  np.add.at(out, (j, i[keep] - c0), w)
  return out


def cone_psf(setup: Setup, domain: LCTDomain, *, lateral_samples: int = 4,
             dtype=np.float64) -> np.ndarray:
  """``[Lv, 2H, 2W]`` light-cone PSF laid out for the domain's linear convolution.

  Entry ``[m, p, q]`` weights a u-bin ``u`` into the v-bin ``u + m + (v0 - u0)``
  of the scan point ``p`` rows and ``q`` columns away (indices modulo the FFT
  shape). Each cone column averages ``lateral_samples^2`` positions across
  the voxel's footprint (a scatterer anywhere in the pixel, not only at its
  centre; without it the steep cone flanks are under-sampled and an off-grid
  point smears in depth), each split linearly between the two v-bins around
  its exact offset ``oversample r_b^2 / T``. Unit L2 norm over the ungated cone.
  With ``setup.aperture``, samples laterally farther than it are dropped.
  The cone is summed and normalised in float64 and returned as ``dtype``
  (float32 halves the memory and the time of the spectrum of a float32 problem).
  """
  T = setup.num_bins
  H, W = setup.grid
  dy, dx = setup.spacing
  lv = domain.fft_shape[0]
  tv = domain.oversample * T
  p = np.arange(-(H - 1), H)
  q = np.arange(-(W - 1), W)
  pp, qq = np.meshgrid(p, q, indexing="ij")
  sub = (np.arange(lateral_samples) + 0.5) / lateral_samples - 0.5
  shift = domain.v[0] - domain.u[0]
  cone = np.zeros((tv + 1,) + pp.shape)       # ungated cone on the full v-axis (+1 spill bin)
  for sy in sub:
    for sx in sub:
      lateral2 = ((pp + sy) * dy) ** 2 + ((qq + sx) * dx) ** 2
      r2 = lateral2 / setup.depth_bin_length ** 2
      s = r2 * domain.oversample / T          # exact v-offset, v-bins
      s0 = np.minimum(np.floor(s).astype(np.int64), tv)
      if setup.aperture is not None:          # beyond the aperture: into the dropped spill bin
        s0 = np.where(lateral2 > setup.aperture ** 2, tv, s0)
      frac = s - np.floor(s)
      np.add.at(cone, (s0, pp + H - 1, qq + W - 1), np.where(s0 < tv, 1.0 - frac, 0.0))
      s1 = np.minimum(s0 + 1, tv)
      np.add.at(cone, (s1, pp + H - 1, qq + W - 1), np.where(s0 + 1 < tv, frac, 0.0))
  cone = cone[:tv]
  row_energy = np.einsum("kpq,kpq->k", cone, cone)   # one pass: the norm and the v-offsets reached
  energy = float(row_energy.sum())
  if energy == 0.0:
    # Every footprint sample of every cone column lies beyond the last bin: the
    # PSF is empty, and dividing by its norm would fill every volume with NaN.
    raise ValueError(
        f"{setup}: no part of the light cone fits in the {T} time bins (scan spacing"
        f" {dy:.4g} x {dx:.4g} m, maximum depth {setup.max_depth:.4g} m); use more or wider"
        " bins, or a finer scan grid")
  cone /= math.sqrt(energy)
  psf = np.zeros(domain.fft_shape, dtype)
  m = np.arange(tv) - shift
  keep = (m > -domain.num_u) & (m < domain.num_v)
  reached = np.flatnonzero(keep & (row_energy > 0))
  if reached.size and not (lv > max(domain.num_v - 1 - m[reached[0]], m[reached[-1]] + domain.num_u - 1)):
    raise AssertionError(f"internal: the cone's v-offsets {m[reached[0]]}..{m[reached[-1]]} wrap around"
                         f" the FFT length {lv} (lct_domain's cone_reach is too small)")
  # Distinct targets: the kept offsets span fewer than Lv v-bins, the lateral
  # offsets fewer than 2H and 2W (so one assignment, no accumulation needed).
  psf[np.ix_(m[keep] % lv, p % (2 * H), q % (2 * W))] = cone[keep]
  return psf


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["psf_fft", "to_v", "to_z", "to_v_sparse", "to_z_sparse"],
                   meta_fields=["domain"])
@dataclasses.dataclass(frozen=True)
class LCTOperators:
  """Device arrays of one LCT problem (see :func:`lct_operators`).

  Attributes:
    domain: the bin windows (static).
    psf_fft: ``[2H, W + 1, Lv]`` complex, ``rfftn`` of :func:`cone_psf` with its v axis
      moved last (time-minor): :func:`lct_apply` then transforms, filters and
      inverts along v with no transposes of the padded spectrum (measured at
      128 x 128 x 512: 15 % faster than the ``[Lv, 2H, W + 1]`` layout, the
      same numbers).
    to_v: ``[Nv, Nt]`` time -> v resampling with the falloff power.
    to_z: ``[Z, Nu]`` u -> depth averaging.
    to_v_sparse, to_z_sparse: ``(rows, cols, weights)`` of the same matrices
      when they are mostly zeros (:func:`sparse_rows`), else None; the
      resampling then gathers the few time bins each row reads instead of a
      dense product. Set only by :func:`public_lct_operators` (the public
      ``mtx`` has at most ``2T`` non-zeros in ``T^2``); replacing ``to_v`` or
      ``to_z`` with :func:`dataclasses.replace` must reset them.
  """

  domain: LCTDomain
  psf_fft: jax.Array
  to_v: jax.Array
  to_z: jax.Array
  to_v_sparse: tuple | None = None
  to_z_sparse: tuple | None = None


def sparse_rows(matrix: np.ndarray, max_density: float = 0.05) -> tuple | None:
  """``(rows, cols, weights)`` int32/int32/float32 of a mostly-zero ``[R, C]`` matrix, row-major; None when denser.

  Used when at most ``max_density`` of the entries are non-zero: then a
  gather of the non-zero columns and a sorted segment sum
  (:func:`apply_axis_matrix`) moves far fewer bytes than the dense product.
  """
  matrix = np.asarray(matrix)
  rows, cols = np.nonzero(matrix)
  if rows.size > max_density * matrix.size:
    return None
  return (jnp.asarray(rows, jnp.int32), jnp.asarray(cols, jnp.int32),
          jnp.asarray(matrix[rows, cols], matrix.dtype))


def apply_axis_matrix(dense: jax.Array, sparse: tuple | None, x: jax.Array) -> jax.Array:
  """``[R, C] @ [C, H, W] -> [R, H, W]``: the dense product, or the same sums from ``sparse``."""
  if sparse is None:
    return jnp.einsum("rc,chw->rhw", dense, x, precision="highest")
  rows, cols, weights = sparse
  taken = weights.astype(x.dtype)[:, None, None] * x[cols]              # [nnz, H, W]
  return jax.ops.segment_sum(taken, rows, num_segments=dense.shape[0], indices_are_sorted=True)


@_validate.cached_operators(maxsize=16)
def lct_operators(setup: Setup, power: float, *, t_margin: int = 0, z_margin: int = 0,
                  oversample: int = 2, dtype=jnp.float32, fft_length: str = "full") -> LCTOperators:
  """Build (once, cached) the operators to backproject or invert the LCT for ``setup``.

  Args:
    setup: the capture (its depth range selects the bins).
    power: time power of the t -> v resampling (3 diffuse, 1 retroreflective,
      0 plain averaging, as the phasor method uses).
    t_margin, z_margin: widen the windows (see :func:`lct_domain`).
    oversample: v- and u-bins per time bin (see :func:`lct_domain`).
    dtype: float dtype of the real operators (complex counterpart for the PSF).
    fft_length: ``"full"`` (any filter) or ``"cone"`` (backprojection only:
      ``lct_apply(..., filt=None)``); see :func:`lct_domain`.
  """
  dom = lct_domain(setup, t_margin=t_margin, z_margin=z_margin, oversample=oversample,
                   fft_length=fft_length)
  T = setup.num_bins
  cdtype = jnp.complex128 if jnp.dtype(dtype) == jnp.float64 else jnp.complex64
  real = np.float64 if jnp.dtype(dtype) == jnp.float64 else np.float32
  psf_fft = _time_minor(scipy.fft.rfftn(cone_psf(setup, dom, dtype=real), workers=-1))   # all cores
  to_v = squared_axis_matrix(T, dom.v, dom.t, power=power, oversample=oversample)
  to_z = linear_axis_matrix(T, dom.z, dom.u, power=0.0, oversample=oversample)
  return LCTOperators(dom, jnp.asarray(psf_fft, cdtype), jnp.asarray(to_v, dtype),
                      jnp.asarray(to_z, dtype))


def _time_minor(spectrum: np.ndarray) -> np.ndarray:
  """``[Lv, 2H, W + 1]`` -> ``[2H, W + 1, Lv]``, contiguous (the layout of ``LCTOperators.psf_fft``)."""
  return np.ascontiguousarray(np.moveaxis(spectrum, 0, -1))


def lct_filter(ops: LCTOperators, snr: float | None) -> jax.Array:
  """``[2H, W + 1, Lv]``: ``conj(F)`` (backprojection, ``snr=None``) or the Wiener ``conj(F)/(|F|^2 + 1/snr)``."""
  f = ops.psf_fft
  if snr is None:
    return jnp.conj(f)
  return jnp.conj(f) / (jnp.abs(f) ** 2 + jnp.asarray(1.0 / snr, f.real.dtype))


def lct_apply(x: jax.Array, ops: LCTOperators, filt: jax.Array | None) -> jax.Array:
  """One gated LCT backprojection / inversion, before the depth resampling.

  Args:
    x: ``[Nt, H, W]`` real time window ``transient[t0:t1]``.
    ops: operators of the problem.
    filt: ``[2H, W + 1, Lv]`` complex frequency-domain filter
      (:func:`lct_filter`), or ``None`` for the backprojection ``conj(F)``
      taken inside the product (no second spectrum-sized array, nothing to
      compile beforehand).
  Returns:
    ``[Nu, H, W]`` real, on the u-grid.
  """
  dom = ops.domain
  h, w = x.shape[-2:]
  _, h2, w2 = dom.fft_shape
  data_v = apply_axis_matrix(ops.to_v, ops.to_v_sparse, x)
  # rfftn / irfftn one axis at a time, skipping the zero padding going in and
  # the discarded rows going out: the same numbers as the full transforms
  # with about 20% fewer FLOPs (the data fills an eighth of the FFT box).
  spec = jnp.fft.rfft(data_v, n=w2, axis=2)                 # [Nv, H, W + 1]
  spec = jnp.fft.fft(spec, n=h2, axis=1)                    # [Nv, 2H, W + 1]
  out = filter_v_axis(spec, lct_filter(ops, None) if filt is None else filt, dom, axis=0)
  out = jnp.fft.ifft(out, axis=1)[:, :h]                    # [Nu, H, W + 1]
  return jnp.fft.irfft(out, n=w2, axis=2)[:, :, :w]         # [Nu, H, W]


def filter_v_axis(spec: jax.Array, filt: jax.Array, domain: LCTDomain, axis: int) -> jax.Array:
  """The v-axis step of :func:`lct_apply`: FFT along v, the filter, inverse FFT, first ``Nu`` rows.

  Args:
    spec: complex lateral spectra ``[..., Nv, ..., 2H, W + 1]`` with the ``Nv`` v-bins on ``axis``.
    filt: ``[2H, W + 1, Lv]`` complex (:func:`lct_filter`; v last, as ``LCTOperators.psf_fft``).
    domain: the problem's windows (``Lv = fft_shape[0]``, ``Nu = num_u``).
    axis: the v axis of ``spec``.
  Returns:
    complex, ``spec``'s shape with ``Nu`` on ``axis``. v is moved last once each way, so
    the FFT, the filter and the inverse run on the minor axis (XLA:CPU transposes around
    an FFT of any other axis).
  """
  spec = jnp.moveaxis(spec, axis, -1)
  out = jnp.fft.ifft(jnp.fft.fft(spec, n=domain.fft_shape[0], axis=-1) * filt, axis=-1)
  return jnp.moveaxis(out[..., :domain.num_u], -1, axis)


def to_depth(vol_u: jax.Array, ops: LCTOperators) -> jax.Array:
  """``[Nu, H, W]`` u-grid -> ``[Z, H, W]`` depth grid (bin averages)."""
  return apply_axis_matrix(ops.to_z, ops.to_z_sparse, vol_u)


# ------------------------------------------------------- the public algorithm
# ``variant="public"`` of the LCT-based reconstructions: the operators of the
# public MATLAB code (O'Toole's ``resamplingOperator`` and ``definePsf``,
# nlos-fk's reuse of them), so that a Wiener ``snr`` gives the same image as
# there. Written from the formulas of that public code (O'Toole et al. 2018's LCT release).
OPERATOR_VARIANTS = ("public", "refined")


def check_variant(variant: str) -> str:
  """Return ``variant`` if it names an LCT operator variant, else raise ValueError."""
  if variant not in OPERATOR_VARIANTS:
    raise ValueError(f"variant must be one of {OPERATOR_VARIANTS}, got {variant!r}")
  return variant


def public_time_power(power: float, oversample: int = 1) -> int:
  """The public operators' ``t_n`` exponent for a refined ``v^{power/2}`` falloff ``power``.

  The public code multiplies each time bin by ``t_n^{power + 1}`` (``t_n^0``
  for ``power`` 0: no falloff) on its single v-grid, so ``oversample`` must be 1.
  :func:`public_lct_operators` takes the result. Raises ValueError for another
  ``oversample`` or a ``power`` that is not a whole number >= 0.
  """
  if oversample != 1:
    raise ValueError(f"oversample={oversample} needs variant='refined' (the public grid has 1)")
  if not (power >= 0 and float(power) == int(power)):
    raise ValueError(f"power must be a whole number >= 0 for the public operators, got {power!r}")
  return int(power) + 1 if power else 0


def public_resampling_matrix(num_bins: int) -> np.ndarray:
  """``[T, T]`` float64: the public ``mtx`` (rows v-bins, columns t-bins), any ``T``.

  ``mtx[i, j] = (1/T) sum over integers x in [i T + 1, (i + 1) T] with
  ceil(sqrt(x)) = j + 1 of 1 / sqrt(x)``: the closed form of the MATLAB
  construction (an ``T^2 x T`` matrix of ``1/sqrt(x)`` halved ``log2 T``
  times). The public inverse resampling ``mtxi`` is its transpose.
  """
  T = int(num_bins)
  x = np.arange(1, T * T + 1, dtype=np.int64)
  # ceil(sqrt(x)) - 1 == isqrt(x - 1) for integers x >= 1; correct the float root exactly.
  j = np.floor(np.sqrt((x - 1).astype(np.float64))).astype(np.int64)
  j -= (j * j > x - 1)
  j += ((j + 1) * (j + 1) <= x - 1)
  out = np.zeros((T, T))
  np.add.at(out, ((x - 1) // T, j), 1.0 / (T * np.sqrt(x.astype(np.float64))))
  return out


def public_cone_psf(setup: Setup, dtype=np.float64) -> np.ndarray:
  """``[2T, 2H, 2W]`` the public one-voxel-per-column light cone, apex at index 0.

  As ``definePsf``: ``y_n = linspace(-1, 1, 2H)``, ``x_n = linspace(-1, 1, 2W)``,
  ``z_n = linspace(0, 2, 2T)``; each column holds a single one at the ``z_n``
  nearest to ``(4 slope)^2 (x_n^2 + y_n^2)``, ``slope = (wall_size / 2) /
  (T bin_length)`` (so the implied scan spacing is ``wall_size / N`` and the
  apex sits half a spacing off the grid); unit L2 norm; rolled by ``(H, W)``.
  Columns whose cone lies beyond the last slice by more than half a step stay
  empty (the public code puts a spurious one in the last slice there, which
  only happens when ``slope > 1/4``). With ``setup.aperture``, columns laterally
  farther than it (at the public code's implied positions) stay empty too.
  """
  T = setup.num_bins
  H, W = setup.grid
  slope = (setup.wall_size / 2.0) / (T * setup.bin_length)
  y = np.linspace(-1.0, 1.0, 2 * H)
  x = np.linspace(-1.0, 1.0, 2 * W)
  dz = 2.0 / (2 * T - 1)
  cone = (4.0 * slope) ** 2 * (y[:, None] ** 2 + x[None, :] ** 2)
  k = np.ceil(cone / dz - 0.5).astype(np.int64)       # nearest slice, ties to the lower one
  keep = k <= 2 * T - 1
  if setup.aperture is not None:             # x_n spans 2N spacings of wall / N: x_n wall_size metres
    keep &= setup.wall_size ** 2 * (y[:, None] ** 2 + x[None, :] ** 2) <= setup.aperture ** 2
  rows, cols = np.nonzero(keep)
  if rows.size == 0:
    raise ValueError(f"{setup}: no part of the light cone fits in the {T} time bins")
  psf = np.zeros((2 * T, 2 * H, 2 * W))
  psf[k[rows, cols], rows, cols] = 1.0 / math.sqrt(rows.size)
  return np.roll(psf, (H, W), axis=(1, 2)).astype(dtype)


@_validate.cached_operators(maxsize=8)
def public_lct_domain(setup: Setup, *, z_margin: int = 0) -> LCTDomain:
  """The :class:`LCTDomain` of the public pipeline: every bin, the full ``(2T, 2H, 2W)`` box.

  Time, v- and u-bins are all ``(0, T)`` (the public code does not gate and has
  one v-bin per time bin); the output depths are the Setup's ``depth_bins``
  widened by ``z_margin`` (an integer >= 0) on each side, clipped to ``(0, T)``.
  """
  if isinstance(z_margin, bool) or not (isinstance(z_margin, (int, np.integer)) and z_margin >= 0):
    raise ValueError(f"z_margin must be an integer >= 0, got {z_margin!r}")
  T = setup.num_bins
  H, W = setup.grid
  k0, k1 = setup.depth_bins
  z = (max(0, k0 - z_margin), min(T, k1 + z_margin))
  return LCTDomain((0, T), (0, T), z, (0, T), (2 * T, 2 * H, 2 * W), 1)


def public_lct_operators(setup: Setup, time_power: int, *, z_margin: int = 0,
                         dtype=jnp.float32) -> LCTOperators:
  """Operators of the public LCT pipeline, in :class:`LCTOperators` form for :func:`lct_apply`.

  ``vol = mtx^T crop(ifftn(fftn(pad(mtx (t_n^p tau))) filt))`` on the full
  ``(2T, 2H, 2W)`` circular box with ``t_n = linspace(0, 1, T)``: ``p = 4``
  diffuse LCT and FBP, ``2`` retroreflective, ``0`` the phasor method's plain
  ``mtx``. Reads every time bin (the public code does not gate); a
  ``depth_range`` only crops the output depths (widened by ``z_margin``).

  Args:
    setup: the capture.
    time_power: ``p`` above, an integer >= 0.
    z_margin: extra depth bins on each side of the Setup's (FBP's filter taps).
    dtype: float dtype of the real operators.
  """
  if not (isinstance(time_power, int) and time_power >= 0):
    raise ValueError(f"time_power must be an integer >= 0, got {time_power!r}")
  dom = public_lct_domain(setup, z_margin=z_margin)
  T, z = setup.num_bins, dom.z
  mtx = public_resampling_matrix(T)
  t_n = np.linspace(0.0, 1.0, T)
  cdtype = jnp.complex128 if jnp.dtype(dtype) == jnp.float64 else jnp.complex64
  psf_fft = _time_minor(scipy.fft.rfftn(public_cone_psf(setup), workers=-1))
  real = np.float64 if jnp.dtype(dtype) == jnp.float64 else np.float32
  to_v = (mtx * t_n[None, :] ** time_power).astype(real)
  to_z = np.ascontiguousarray(mtx.T[z[0]:z[1]]).astype(real)
  return LCTOperators(dom, jnp.asarray(psf_fft, cdtype), jnp.asarray(to_v), jnp.asarray(to_z),
                      sparse_rows(to_v), sparse_rows(to_z))

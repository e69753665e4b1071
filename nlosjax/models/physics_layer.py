"""The physics layer of the network (paper Sec. 4.3): :class:`FeatureTransform` and its geometry.

Per feature channel, the phasor-field (or LCT) reconstruction of
:mod:`nlosjax.physics`, with its operators built once per Setup and reused; no
parameters unless asked (a learned wavelet or LCT filter). Also the time-coarsened
Setup the layer works on (:func:`coarsen_setup`), the depth window it
reconstructs (:func:`physics_window`, :func:`volume_window`), depth resampling
and the soft projection of a volume to intensity and depth
(:func:`soft_projection`). Layout ``[B, T, H, W, C] -> [B, Z, H, W, C]``,
float32 / complex64 whatever the network's dtype.
"""


import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from nlosjax import platforms
from nlosjax.physics import operator_args
from nlosjax.physics.operators import (
  check_falloff,
  check_variant,
  lct_apply,
  lct_filter,
  lct_operators,
  public_lct_operators,
  public_time_power,
  to_depth,
)
from nlosjax.physics.setup import Setup
from nlosjax.physics.wavelet import convolve_time, illumination_wavelet, public_wavelet

PHYSICS_METHODS = ("phasor", "lct")
_TINY = 1e-12  # guard of every data-dependent normalisation (all-zero input gives zeros, not NaN)



# ------------------------------------------------------------------- physics
def coarsen_setup(setup: Setup, time_stride: int) -> Setup:
  """The Setup of a transient whose bins are ``time_stride`` bins of ``setup`` merged.

  Bin width ``time_stride * bin_width``, ``ceil(T / time_stride)`` bins, same
  wall, grid and depth range; coarse bin ``k`` spans fine bins
  ``[k r, (k + 1) r)`` so its nominal depth ``k r c dt / 2`` is the fine one's.
  """
  if time_stride == 1:
    return setup
  return dataclasses.replace(setup, bin_width=setup.bin_width * time_stride,
                             num_bins=-(-setup.num_bins // time_stride))


def physics_window(setup: Setup, method: str, *, cycles: float = 5.0,
                   sampling_coeff: float = 2.0, variant: str = "refined") -> tuple[int, int]:
  """``(a, b)``: the time bins of ``setup`` that :class:`FeatureTransform` reads.

  LCT: ``setup.time_bins`` (the bins that can hold returns from the depth
  range). Phasor: those widened by half the wavelet on each side, as
  :func:`nlosjax.physics.phasor` convolves them. ``variant="public"``: every
  bin, ``(0, T)`` (the public operators do not gate).
  """
  if method not in PHYSICS_METHODS:
    raise ValueError(f"method must be one of {PHYSICS_METHODS}, got {method!r}")
  if check_variant(variant) == "public":
    if method == "phasor":      # the wavelet must be buildable on these bins (raises if not)
      public_wavelet(setup, cycles=cycles, sampling_coeff=sampling_coeff)
    return (0, setup.num_bins)
  t0, t1 = setup.time_bins
  if method == "lct":
    return (t0, t1)
  half = illumination_wavelet(setup, cycles=cycles, sampling_coeff=sampling_coeff).num_samples // 2
  return (max(0, t0 - half), min(setup.num_bins, t1 + half))


def volume_window(setup: Setup, time_stride: int, method: str, *, cycles: float = 5.0,
                  sampling_coeff: float = 2.0, variant: str = "refined") -> tuple[int, int]:
  """``(a, b)``: time bins of ``setup`` that :class:`VolumeReconstruction` reads.

  The :func:`physics_window` of ``coarsen_setup(setup, time_stride)`` in fine
  bins: ``a`` is a multiple of ``time_stride``, ``(0, T)`` without a depth range
  or with ``variant="public"``.
  """
  ca, cb = physics_window(coarsen_setup(setup, time_stride), method, cycles=cycles,
                          sampling_coeff=sampling_coeff, variant=variant)
  return (ca * time_stride, min(setup.num_bins, cb * time_stride))


def physics_fft_length(method: str) -> str:
  """``lct_domain``'s ``fft_length`` of the physics layer: ``"cone"`` for "phasor" (a
  backprojection), ``"full"`` for the Wiener inverse of "lct"."""
  return "full" if method == "lct" else "cone"


class FeatureTransform(nn.Module):
  """The physics layer: each feature channel -> its phasor-field / LCT volume.

  For every ``(b, c)`` the feature ``x[b, :, :, :, c]``, read as a transient
  on ``capture``'s time bins, goes through exactly the computation of
  :func:`nlosjax.physics.phasor` (``method="phasor"``: convolve with the
  illumination wavelet ``P(t) = exp(i Omega t) exp(-t^2 / 2 sigma^2)``,
  resample ``t -> v``, FFT, multiply by ``conj(PSF)``, inverse FFT, modulus,
  ``u -> z``) or :func:`nlosjax.physics.lct` (``method="lct"``: ``t^4``-weighted
  resampling, Wiener filter ``conj(F) / (|F|^2 + 1/snr)``), both clamped at 0,
  with that function's ``variant``. ``"refined"``: operators from
  :func:`~nlosjax.physics.operators.lct_operators` and
  :func:`~nlosjax.physics.wavelet.illumination_wavelet`; only
  ``capture.time_bins`` (plus the wavelet's half-length) are read.
  ``"public"``: :func:`~nlosjax.physics.operators.public_lct_operators` and
  :func:`~nlosjax.physics.wavelet.public_wavelet`; every bin is read. Either
  way the operators are cached per Setup and are constants, not parameters,
  so the same weights run on another Setup by building the module with it;
  only the depth range is produced.

  Gradients: the modulus uses a guarded square root (gradient 0 where the
  field is exactly 0, instead of NaN).

  Attributes:
    capture: the Setup the features live on (their time bins are its bins;
      named ``capture`` because ``setup`` is reserved by Flax).
    method: "phasor" (the paper) or "lct".
    snr: Wiener SNR of "lct".
    falloff: "diffuse" or "retroreflective" ("lct").
    cycles, sampling_coeff: wavelet of "phasor" (see ``illumination_wavelet``).
    oversample: LCT v-bins per time bin (``oversample`` of
      ``nlosjax.physics.lct``/``phasor``; 1 is their default and the public grid).
    chunk: transform this many ``(b, c)`` slices at a time (``jax.lax.map``;
      bounds the FFT memory); None transforms all at once (``vmap``). Heeded in a
      program lowered for the CPU only: for another platform (:mod:`nlosjax.platforms`)
      every slice is transformed at once, the FFTs batched over them.
    variant: the operators, as ``variant`` of ``nlosjax.physics.phasor`` /
      ``lct``: ``"refined"`` (ours: gated, linear convolution, centred
      wavelet) or ``"public"`` (the public code's: its resampling matrix and
      wavelet, every bin read, the full circular box; ``oversample`` 1).

  Args of ``__call__``:
    x: ``[B, Nt, H, W, C]`` real, time bins ``[time_offset, time_offset + Nt)``
      of ``capture``, covering :meth:`window`.
    time_offset: first time bin of ``x`` (static int).
  Returns:
    ``[B, Z, H, W, C]`` float32 >= 0, on ``capture.depths`` (``Z = capture.num_depth_bins``).
  """

  capture: Setup
  method: str = "phasor"
  snr: float = 0.1
  falloff: str = "diffuse"
  cycles: float = 5.0
  sampling_coeff: float = 2.0
  oversample: int = 1
  chunk: int | None = None
  variant: str = "refined"

  def window(self) -> tuple[int, int]:
    """``(a, b)``: time bins of ``capture`` that the transform reads."""
    return physics_window(self.capture, self.method, cycles=self.cycles,
                          sampling_coeff=self.sampling_coeff, variant=self.variant)

  def operators(self):
    """The :class:`~nlosjax.physics.operators.LCTOperators` of this layer.

    The cached constants, or, inside a function jitted by
    :func:`nlosjax.physics.operator_args.bind`, the same operators as its argument.
    """
    power = float(check_falloff(self.falloff)) if self.method == "lct" else 0.0
    if check_variant(self.variant) == "public":
      time_power = public_time_power(power, self.oversample)   # as nlosjax.physics.lct / phasor

      def build():
        with jax.ensure_compile_time_eval():
          return public_lct_operators(self.capture, time_power, dtype=jnp.float32)
      return operator_args.lookup(("public_lct_operators", self.capture, time_power), build)

    def build():
      # Built eagerly even when called inside a trace: the cache must hold arrays, not tracers.
      with jax.ensure_compile_time_eval():
        return lct_operators(self.capture, power, oversample=self.oversample, dtype=jnp.float32,
                             fft_length=self.fft_length)
    key = ("lct_operators", self.capture, power, self.oversample, self.fft_length)
    return operator_args.lookup(key, build)

  @property
  def fft_length(self) -> str:
    return physics_fft_length(self.method)

  def __call__(self, x, time_offset: int = 0):
    if not isinstance(self.capture, Setup):
      raise ValueError(f"capture must be a nlosjax.physics.Setup, got {type(self.capture).__name__}")
    if x.ndim != 5 or tuple(x.shape[2:4]) != self.capture.grid:
      raise ValueError(f"x must be [B, Nt, H, W, C] with (H, W) = {self.capture.grid},"
                       f" got shape {x.shape}")
    a, b = self.window()
    nt = x.shape[1]
    if not (time_offset <= a and b <= time_offset + nt):
      raise ValueError(f"x covers time bins [{time_offset}, {time_offset + nt}) but the physics"
                       f" layer reads [{a}, {b}) of {self.capture}")
    ops = self.operators()
    t0, t1 = ops.domain.t
    bsz, _, H, W, C = x.shape
    xs = jnp.moveaxis(x[:, a - time_offset:b - time_offset].astype(jnp.float32), -1, 1)
    xs = xs.reshape((bsz * C, b - a, H, W))
    if self.method == "phasor":
      make = public_wavelet if self.variant == "public" else illumination_wavelet
      wavelet = make(self.capture, cycles=self.cycles, sampling_coeff=self.sampling_coeff)
      filt = None                                    # lct_apply's backprojection conj(F)

      def one(xi):
        field = convolve_time(xi, wavelet, axis=0)[t0 - a:t1 - a]
        re = lct_apply(jnp.real(field), ops, filt)
        im = lct_apply(jnp.imag(field), ops, filt)
        m2 = re * re + im * im
        pos = m2 > 0
        mag = jnp.where(pos, jnp.sqrt(jnp.where(pos, m2, 1.0)), 0.0)
        return jnp.maximum(to_depth(mag, ops), 0.0)
    else:
      filt = lct_filter(ops, self.snr)

      def one(xi):
        return jnp.maximum(to_depth(lct_apply(xi[t0 - a:t1 - a], ops, filt), ops), 0.0)

    if self.chunk is None:
      vol = jax.vmap(one)(xs)
    else:                              # off the CPU all slices at once: batched FFTs, no loop
      vol = platforms.by_platform(xs, cpu=lambda v: jax.lax.map(one, v, batch_size=self.chunk),
                                  other=jax.vmap(one))
    vol = vol.reshape((bsz, C) + vol.shape[1:])
    return jnp.moveaxis(vol, 1, -1)


def resample_depth(volume: jax.Array, source: Setup, target: Setup) -> jax.Array:
  """Linear interpolation of ``[B, Zs, H, W]`` from ``source.depths`` to ``target.depths``.

  Depths outside the source grid take the nearest end value. Returns
  ``[B, Zt, H, W]`` (the input unchanged when the depth grids are equal). Chosen by the
  platform the program is lowered for (:mod:`nlosjax.platforms`): on the CPU
  :func:`resample_depth_gather` (two gathered rows per output depth, its gradient a
  scatter-add), elsewhere :func:`resample_depth_dense` (one product with the ``[Zt, Zs]``
  interpolation matrix, forward and backward, no gather or scatter). The same sums.
  """
  zs, zt = source.depths, target.depths
  if zs.shape == zt.shape and np.allclose(zs, zt):
    return volume
  return platforms.by_platform(volume, cpu=lambda v: resample_depth_gather(v, source, target),
                               other=lambda v: resample_depth_dense(v, source, target))


def depth_interpolation(source: Setup, target: Setup) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """``(lo, hi, frac)`` ``[Zt]`` each: target depth ``k`` is ``(1 - frac) zs[lo] + frac zs[hi]``."""
  zs, zt = source.depths, target.depths
  step = source.depth_bin_length
  pos = np.clip((zt - zs[0]) / step, 0.0, zs.size - 1.0)
  lo = np.minimum(np.floor(pos).astype(np.int64), zs.size - 1)
  hi = np.minimum(lo + 1, zs.size - 1)
  return lo, hi, pos - lo


def resample_depth_gather(volume: jax.Array, source: Setup, target: Setup) -> jax.Array:
  """:func:`resample_depth` by gathering each target depth's two source rows: ``[B, Zs, H, W] -> [B, Zt, H, W]``."""
  lo, hi, frac = depth_interpolation(source, target)
  frac = jnp.asarray(frac, volume.dtype)[None, :, None, None]
  return volume[:, lo] * (1.0 - frac) + volume[:, hi] * frac


def interpolation_matrix(source: Setup, target: Setup) -> np.ndarray:
  """``[Zt, Zs]`` float64: the weights of :func:`depth_interpolation`, at most two non-zeros a row, summing to 1."""
  lo, hi, frac = depth_interpolation(source, target)
  rows = np.arange(lo.size)
  m = np.zeros((lo.size, source.depths.size))
  np.add.at(m, (rows, lo), 1.0 - frac)
  np.add.at(m, (rows, hi), frac)
  return m


def resample_depth_dense(volume: jax.Array, source: Setup, target: Setup) -> jax.Array:
  """:func:`resample_depth` as one product with :func:`interpolation_matrix`: ``[B, Zs, H, W] -> [B, Zt, H, W]``.

  ``precision="highest"``: full float32 products where the platform would round them
  (TF32 on recent NVIDIA GPUs).
  """
  m = jnp.asarray(interpolation_matrix(source, target), volume.dtype)
  return jnp.einsum("tz,bzhw->bthw", m, volume, precision="highest")


def soft_projection(volume: jax.Array, depths, *, temperature: float = 0.05,
                    threshold: float = 0.1, softness: float = 0.02,
                    background_depth: float = 0.0) -> tuple[jax.Array, jax.Array]:
  """Differentiable intensity image and depth map of a volume.

  * intensity: ``I = max_z v / max_{x,y} max_z v`` with ``v = max(volume, 0)``
    (the max-projection of :func:`nlosjax.physics.intensity_depth`), in [0, 1];
    gradients reach the maximal voxel of each column.
  * depth: soft-argmax along depth of each column normalised by its own
    maximum, ``p_k = softmax_k(v_k / (max_k v_k * temperature))``,
    ``d_fg = sum_k p_k z_k`` (metres; ``temperature -> 0`` gives the argmax
    depth); gradients reach every voxel of the column. Pixels whose intensity
    falls below ``threshold`` blend to ``background_depth`` through the soft mask
    ``m = sigmoid((I - threshold) / softness)``: ``d = m d_fg + (1 - m) d_bg``
    (the hard rule of ``intensity_depth`` as ``softness -> 0``).

  An all-zero volume gives zero intensity and ``background_depth`` (up to
  ``sigmoid(-threshold / softness)``), never NaN, and zero gradients (an image
  or column whose maximum is at most 1e-12 counts as dark).

  Args:
    volume: ``[..., Z, H, W]`` real.
    depths: ``[Z]`` depth of each bin, metres.
    temperature: softmax temperature relative to the column maximum, > 0.
    threshold: intensity below which a pixel is background, in [0, 1).
    softness: width of the background blend, > 0.
    background_depth: depth of background pixels, metres.
  Returns:
    ``(intensity [..., H, W] float32 in [0, 1], depth [..., H, W] float32 metres)``.
  """
  v = jnp.maximum(volume.astype(jnp.float32), 0.0)
  mip = jnp.max(v, axis=-3)
  peak = jnp.max(mip, axis=(-2, -1), keepdims=True)
  # An all-dark image (column) is 0 with gradient 0: dividing by max(peak, _TINY)
  # instead gives gradients of 1 / _TINY = 1e12 there (an all-zero volume, e.g.
  # a zero-photon frame through the initialised network).
  lit = peak > _TINY
  intensity = jnp.where(lit, jnp.clip(mip / jnp.where(lit, peak, 1.0), 0.0, 1.0), 0.0)
  seen = (mip > _TINY)[..., None, :, :]
  col = jnp.where(seen, v / jnp.where(seen, mip[..., None, :, :], 1.0), 0.0)
  p = jax.nn.softmax(col / temperature, axis=-3)
  z = jnp.asarray(depths, jnp.float32)[:, None, None]
  d_fg = jnp.sum(p * z, axis=-3)
  m = jax.nn.sigmoid((intensity - threshold) / softness)
  return intensity, m * d_fg + (1.0 - m) * jnp.float32(background_depth)

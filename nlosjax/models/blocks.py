"""The convolutional blocks of the ST-Mamba network (paper Sec. 4.1 and 4.3).

Layout: activations are channels-last, ``[B, T, H, W, C]`` before the physics
layer (time bins, scan rows, scan columns, channels) and ``[B, Z, H, W, C]``
after it (depth bins). float32 by default; ``dtype`` sets the activation dtype
of the learned layers (parameters stay float32). Every 3-D convolution is a
:class:`nlosjax.models.conv.Conv3D` (``conv_impl`` chooses how it is computed);
the physics layer is :mod:`nlosjax.models.physics_layer`.

Blocks (our reading of the paper where it is silent; the choices are also listed
in ``benchmarks/results/model.md``):

* :class:`ResBlock3D` -- two 3x3x3 convs, LeakyReLU(0.2), a residual
  connection (USM's ``ResConv3D``); optionally strided in time, the shortcut
  then averages the same bins.
* :class:`InterlacedResBlock` -- parallel 3x3x3 convs with different
  *temporal* dilations whose channels are interlaced and fused by a 1x1x1
  conv (receptive field 3..9 bins at the cost of one conv), plus the shortcut.
* :class:`InterleavedExtraction` -- time downsampled losslessly by
  interleaving ``r`` consecutive bins into channels, then 3-D convs and
  interlaced residual blocks.
* :class:`TransientSpreading` -- stride-2 transposed convs (sub-pixel,
  :class:`~nlosjax.models.conv.Upsample3D`) plus interpolation to the full scan
  grid, added to a bilinear interpolation of the measured frame: the recovered
  full-resolution transient.
* :class:`VolumeReconstruction` -- feature extraction (three residual blocks,
  time downsampled) -> :class:`~nlosjax.models.physics_layer.FeatureTransform`
  -> refinement (three convs and three interlaced residual blocks) -> volume,
  intensity and depth.
"""

from __future__ import annotations

import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.models.conv import Upsample3D, _conv, _log2_int, leaky_relu, maybe_remat, time_pool
from nlosjax.models.physics_layer import (
  _TINY,
  FeatureTransform,
  coarsen_setup,
  resample_depth,
  soft_projection,
  volume_window,
)
from nlosjax.physics.setup import Setup


# ------------------------------------------------------------------ residual
class ResBlock3D(nn.Module):
  """``y = LReLU(conv(LReLU(conv_s(x))) + shortcut(x))``, 3x3x3 convs (USM ``ResConv3D``).

  Attributes:
    features: output channels.
    time_stride: temporal stride of the first conv (1: none); the shortcut
      averages the same ``time_stride`` bins (and a 1x1x1 conv matches channels).

  Input ``[B, T, H, W, C]`` -> ``[B, ceil(T / time_stride), H, W, features]``.
  """

  features: int
  time_stride: int = 1
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32
  conv_impl: str = "fold"

  @nn.compact
  def __call__(self, x):
    kw = dict(dtype=self.dtype, param_dtype=self.param_dtype, conv_impl=self.conv_impl)
    y = leaky_relu(_conv(self.features, time_stride=self.time_stride, name="conv1", **kw)(x))
    y = _conv(self.features, name="conv2", **kw)(y)
    shortcut = time_pool(x, self.time_stride)
    if shortcut.shape[-1] != self.features:
      shortcut = _conv(self.features, (1, 1, 1), name="shortcut", **kw)(shortcut)
    return leaky_relu(y + shortcut.astype(y.dtype))


class InterlacedResBlock(nn.Module):
  """Residual block of parallel dilated 3x3x3 convs with interlaced channels.

  ``y = LReLU(fuse(interlace_d LReLU(conv_{d}(x))) + x)`` where ``conv_d`` is a
  3x3x3 conv with dilation ``(d, 1, 1)`` (first axis: time or depth) producing
  ``ceil(features / len(dilations))`` channels, ``interlace`` orders the
  branch outputs channel by channel (``[c0 of d0, c0 of d1, ..., c1 of d0,
  ...]``) and ``fuse`` is a 1x1x1 conv back to ``features``.

  Input ``[B, T, H, W, features]`` -> same shape.
  """

  features: int
  dilations: tuple[int, ...] = (1, 2, 4)
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32
  conv_impl: str = "fold"

  @nn.compact
  def __call__(self, x):
    if x.shape[-1] != self.features:
      raise ValueError(f"x must have {self.features} channels, got shape {x.shape}")
    kw = dict(dtype=self.dtype, param_dtype=self.param_dtype, conv_impl=self.conv_impl)
    per = -(-self.features // len(self.dilations))
    branches = [_conv(per, time_dilation=d, name=f"branch{i}_d{d}", **kw)(x)
                for i, d in enumerate(self.dilations)]
    y = jnp.stack(branches, axis=-1).reshape(x.shape[:-1] + (per * len(self.dilations),))
    y = _conv(self.features, (1, 1, 1), name="fuse", **kw)(leaky_relu(y))
    return leaky_relu(y + x.astype(y.dtype))


# ---------------------------------------------------------------- extraction
class InterleavedExtraction(nn.Module):
  """Interleaved extraction: lossless temporal downsampling, then interlaced dilated convs.

  Attributes:
    width: output channels ``C``.
    time_stride: ``r`` (power of two): time bins interleaved into channels.
    num_blocks: interlaced residual blocks after the first conv.
    dilations: temporal dilations of the interlaced blocks.

  Input ``[N, T, h, w]`` (normalised counts of one frame each) ->
  ``[N, ceil(T / r), h, w, width]``; ``T`` is zero-padded to a multiple of ``r``.
  """

  width: int
  time_stride: int = 4
  num_blocks: int = 2
  dilations: tuple[int, ...] = (1, 2, 4)
  remat: bool = False
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32
  conv_impl: str = "fold"

  @nn.compact
  def __call__(self, x):
    if x.ndim != 4:
      raise ValueError(f"x must be [N, T, h, w], got shape {x.shape}")
    r = self.time_stride
    _log2_int(r, "time_stride")
    n, t, h, w = x.shape
    tc = -(-t // r)
    x = jnp.pad(x, ((0, 0), (0, tc * r - t), (0, 0), (0, 0)))
    # Polyphase split: bin tc * r + j of the input becomes channel j of coarse bin tc.
    x = x.reshape(n, tc, r, h, w).transpose(0, 1, 3, 4, 2).astype(self.dtype)
    kw = dict(dtype=self.dtype, param_dtype=self.param_dtype, conv_impl=self.conv_impl)
    y = leaky_relu(_conv(self.width, name="stem", **kw)(x))
    block = maybe_remat(InterlacedResBlock, self.remat)
    for i in range(self.num_blocks):
      y = block(self.width, self.dilations, name=f"interlaced{i}", **kw)(y)
    return y


# ----------------------------------------------------------------- spreading
def underscan_indices(n: int, stride: int) -> np.ndarray:
  """Full-grid indices of the under-scanned points along one axis: ``stride // 2 + stride * i``.

  The convention of USM (rows ``{4, 12, ..., 124}`` of 128 for stride 8).
  ``[ceil((n - stride // 2) / stride)]`` int64.
  """
  if not (isinstance(stride, int) and 1 <= stride <= n):
    raise ValueError(f"stride must be an integer in [1, {n}], got {stride!r}")
  return np.arange(stride // 2, n, stride)


def interpolation_matrix(n_out: int, stride: int) -> np.ndarray:
  """``[n_out, n_in]`` float64 linear interpolation from the under-scanned points to the full axis.

  Output index ``r`` reads the fractional input index ``(r - stride // 2) / stride``
  (clamped to the first/last sample: constant extrapolation at the borders).
  """
  idx = underscan_indices(n_out, stride)
  n_in = idx.size
  pos = np.clip((np.arange(n_out) - stride // 2) / stride, 0.0, n_in - 1.0)
  lo = np.minimum(np.floor(pos).astype(np.int64), n_in - 1)
  hi = np.minimum(lo + 1, n_in - 1)
  frac = pos - lo
  m = np.zeros((n_out, n_in))
  np.add.at(m, (np.arange(n_out), lo), 1.0 - frac)
  np.add.at(m, (np.arange(n_out), hi), frac)
  return m


class TransientSpreading(nn.Module):
  """Features on the under-scanned grid -> recovered full-resolution transient.

  ``out = gain * interp(skip) + resize(conv1x1(Up_n(... Up_1(f))))``: ``n =
  max(floor(log2 stride), log2 time_stride)`` learned x2 upsamplings
  (:class:`Upsample3D`, the stride-2 transposed convolution) + LeakyReLU,
  each doubling space (while below the stride) and time (while below the
  extraction stride), channels halving from ``C`` down to ``min_width``;
  a 1x1x1 conv to one channel; cropping of padded time bins and linear
  interpolation to the exact grid ``(H, W)`` where the stride is not a power
  of two; plus the measured frame ``skip`` interpolated bilinearly from its
  scan points (:func:`interpolation_matrix`) times a learned gain.

  Attributes:
    grid: ``(H, W)`` full scan grid.
    stride: under-scan stride (input grid ``(h, w)`` per :func:`underscan_indices`).
    time_stride: temporal downsampling to undo (power of two).
    min_width: smallest channel count of the transposed convs.

  Args of ``__call__``:
    features: ``[B, T', h, w, C]`` with ``T' = ceil(Tw / time_stride)``.
    skip: ``[B, Tw, h, w]`` the normalised measured frame (time window).
  Returns:
    ``[B, Tw, H, W]`` float32 recovered transient (normalised units, not clamped).
  """

  grid: tuple[int, int]
  stride: int
  time_stride: int
  min_width: int = 4
  remat: bool = False
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32
  conv_impl: str = "fold"

  @nn.compact
  def __call__(self, features, skip):
    H, W = self.grid
    b, tw, h, w = skip.shape
    n_t = _log2_int(self.time_stride, "time_stride")
    n_s = int(math.floor(math.log2(self.stride))) if self.stride > 1 else 0
    if features.shape[:4] != (b, -(-tw // self.time_stride), h, w):
      raise ValueError(f"features {features.shape} do not match skip {skip.shape} at time stride"
                       f" {self.time_stride}")
    kw = dict(dtype=self.dtype, param_dtype=self.param_dtype, conv_impl=self.conv_impl)
    up = maybe_remat(Upsample3D, self.remat)
    y = features.astype(self.dtype)
    c = features.shape[-1]
    for i in range(max(n_s, n_t)):
      st = (2 if i < n_t else 1, 2 if i < n_s else 1, 2 if i < n_s else 1)
      c = max(c // 2, self.min_width)
      y = leaky_relu(up(c, st, name=f"up{i}", **kw)(y))
    y = _conv(1, (1, 1, 1), name="to_transient", **kw)(y)[..., 0].astype(jnp.float32)
    y = y[:, :tw]
    if y.shape[2:] != (H, W):
      y = jax.image.resize(y, (b, tw, H, W), "linear")
    my = jnp.asarray(interpolation_matrix(H, self.stride), jnp.float32)
    mx = jnp.asarray(interpolation_matrix(W, self.stride), jnp.float32)
    base = jnp.einsum("Yy,btyx,Xx->btYX", my, skip.astype(jnp.float32), mx)
    gain = self.param("skip_gain", nn.initializers.ones, (), jnp.float32)
    return gain * base + y



# -------------------------------------------------------- volume reconstruction
class FeatureExtraction(nn.Module):
  """Shallow features of the recovered transient: a 3x3x3 conv and three :class:`ResBlock3D`.

  The first ``num_down`` blocks halve time. ``[B, T, H, W, 1] -> [B, ceil(T / 2^num_down), H, W,
  features]``.
  """

  features: int
  num_down: int = 1
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32
  conv_impl: str = "fold"

  @nn.compact
  def __call__(self, x):
    kw = dict(dtype=self.dtype, param_dtype=self.param_dtype, conv_impl=self.conv_impl)
    y = leaky_relu(_conv(self.features, name="stem", **kw)(x.astype(self.dtype)))
    for i in range(3):
      y = ResBlock3D(self.features, time_stride=2 if i < self.num_down else 1, name=f"res{i}",
                     **kw)(y)
    return y


class Refinement(nn.Module):
  """Three times (3x3x3 conv + LeakyReLU, :class:`InterlacedResBlock`), then a 1x1x1 conv.

  ``[B, Z, H, W, C] -> [B, Z, H, W]`` float32 (the volume correction).
  """

  features: int
  dilations: tuple[int, ...] = (1, 2, 4)
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32
  conv_impl: str = "fold"

  @nn.compact
  def __call__(self, x):
    kw = dict(dtype=self.dtype, param_dtype=self.param_dtype, conv_impl=self.conv_impl)
    y = x.astype(self.dtype)
    for i in range(3):
      y = leaky_relu(_conv(self.features, name=f"conv{i}", **kw)(y))
      y = InterlacedResBlock(self.features, self.dilations, name=f"interlaced{i}", **kw)(y)
    return _conv(1, (1, 1, 1), name="to_volume", **kw)(y)[..., 0].astype(jnp.float32)


#: ``softplus(k x) / k`` of the "softplus" volume activation: ``log(2) / k = 0.035`` at 0.
SOFTPLUS_SHARPNESS = 20.0


class VolumeReconstruction(nn.Module):
  """Recovered transient -> hidden volume, intensity image and depth map (paper Sec. 4.3).

  1. Feature extraction at the full grid (:class:`FeatureExtraction`): a
     3x3x3 conv to ``features - 1`` channels and three :class:`ResBlock3D`, the
     first ``log2(time_stride)`` of them halving time; channel 0 is the transient itself averaged over the
     same bins (the "interpolation" path, which makes the physics channel of
     the output the classic reconstruction of the recovered transient).
  2. :class:`FeatureTransform` on ``coarsen_setup(capture, time_stride)``, each
     channel then divided by its maximum over the volume (guarded).
  3. Refinement (:class:`Refinement`): three times (3x3x3 conv to
     ``refine_width`` + LeakyReLU, one :class:`InterlacedResBlock` with
     dilations along depth), a 1x1x1 conv to one channel; plus the normalised
     physics channel 0, made non-negative by ``activation``: ``"relu"`` (clamp
     at 0: a column pushed below 0 gets no gradient again) or ``"softplus"``
     (``softplus(20 x) / 20``: within 0.035 of the clamp, gradients everywhere).
  With ``remat``, the extraction and the refinement are each recomputed as a
  whole in the backward pass (only their inputs are kept).
  4. The volume is interpolated linearly from the coarse depth grid to
     ``capture.depths`` (:func:`resample_depth`) and projected by
     :func:`soft_projection`.

  Attributes:
    capture: the full-resolution Setup (output grid, bins, depth range).
    time_stride: temporal downsampling before the physics layer (power of 2).
    features: feature channels entering the physics layer (>= 1).
    refine_width: channels of the refinement.
    method, snr, cycles, sampling_coeff, oversample, chunk, variant: of the physics layer.
    depth_temperature, depth_threshold, depth_softness, background_depth: of
      :func:`soft_projection`.

  Args of ``__call__``:
    transient: ``[B, Nt, H, W]`` recovered transient on time bins
      :meth:`window` ``= [a, b)`` of ``capture`` (``Nt = b - a``).
  Returns:
    dict with ``volume [B, Z, H, W]`` (>= 0, on ``capture.depths``),
    ``intensity [B, H, W]`` in [0, 1] and ``depth [B, H, W]`` metres, float32.
  """

  capture: Setup
  time_stride: int = 2
  features: int = 4
  refine_width: int = 8
  dilations: tuple[int, ...] = (1, 2, 4)
  method: str = "phasor"
  snr: float = 0.1
  cycles: float = 5.0
  sampling_coeff: float = 2.0
  oversample: int = 1
  chunk: int | None = None
  depth_temperature: float = 0.05
  depth_threshold: float = 0.1
  depth_softness: float = 0.02
  background_depth: float = 0.0
  remat: bool = False
  activation: str = "relu"
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32
  conv_impl: str = "fold"
  variant: str = "refined"

  @property
  def coarse_setup(self) -> Setup:
    return coarsen_setup(self.capture, self.time_stride)

  def window(self) -> tuple[int, int]:
    """``(a, b)``: time bins of ``capture`` this stage reads (see :func:`volume_window`)."""
    return volume_window(self.capture, self.time_stride, self.method, cycles=self.cycles,
                         sampling_coeff=self.sampling_coeff, variant=self.variant)

  def _transform(self) -> FeatureTransform:
    return FeatureTransform(self.coarse_setup, self.method, snr=self.snr, cycles=self.cycles,
                            sampling_coeff=self.sampling_coeff, oversample=self.oversample,
                            chunk=self.chunk, variant=self.variant, name="transform")

  @nn.compact
  def __call__(self, transient):
    n_down = _log2_int(self.time_stride, "time_stride")
    if self.features < 1:
      raise ValueError(f"features must be >= 1, got {self.features!r}")
    a, b = self.window()
    H, W = self.capture.grid
    if transient.ndim != 4 or tuple(transient.shape[1:]) != (b - a, H, W):
      raise ValueError(f"transient must be [B, {b - a}, {H}, {W}] (time bins [{a}, {b}) of the"
                       f" Setup), got shape {transient.shape}")
    kw = dict(dtype=self.dtype, param_dtype=self.param_dtype, conv_impl=self.conv_impl)
    x = transient[..., None]
    pooled = time_pool(x.astype(jnp.float32), self.time_stride)
    feats = [pooled]
    if self.features > 1:
      extract = maybe_remat(FeatureExtraction, self.remat)
      y = extract(self.features - 1, n_down, name="extract", **kw)(x)
      feats.append(y.astype(jnp.float32))
    feats = jnp.concatenate(feats, axis=-1)                      # [B, Nc, H, W, F]
    vol = self._transform()(feats, time_offset=a // self.time_stride)  # [B, Zc, H, W, F]
    vol = vol / jnp.maximum(jnp.max(vol, axis=(1, 2, 3), keepdims=True), _TINY)
    refine = maybe_remat(Refinement, self.remat)
    y = refine(self.refine_width, self.dilations, name="refine", **kw)(vol)
    coarse = y + vol[..., 0]                                     # [B, Zc, H, W]
    if self.activation == "relu":
      coarse = jnp.maximum(coarse, 0.0)
    elif self.activation == "softplus":
      coarse = jax.nn.softplus(SOFTPLUS_SHARPNESS * coarse) / SOFTPLUS_SHARPNESS
    else:
      raise ValueError(f"activation must be 'relu' or 'softplus', got {self.activation!r}")
    volume = resample_depth(coarse, self.coarse_setup, self.capture)
    intensity, depth = soft_projection(
        volume, self.capture.depths, temperature=self.depth_temperature,
        threshold=self.depth_threshold, softness=self.depth_softness,
        background_depth=self.background_depth)
    return {"volume": volume, "intensity": intensity, "depth": depth}

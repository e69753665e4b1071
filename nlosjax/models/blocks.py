"""Convolutional and physics blocks of the ST-Mamba network (paper Sec. 4.1 and 4.3).

Layout: activations are channels-last, ``[B, T, H, W, C]`` before the physics
layer (time bins, scan rows, scan columns, channels) and ``[B, Z, H, W, C]``
after it (depth bins). float32 by default; ``dtype`` sets the activation dtype
of the learned layers (parameters stay float32); the physics layer always
computes in float32 / complex64.

Every 3-D convolution is a :class:`Conv3D` (computed as a 2-D convolution of
time-folded channels: the same sums, several times faster on XLA:CPU; with
``conv_impl="auto"``, the network's default, the unstrided few-channel ones as
fused sums of shifted slices, :func:`direct_conv3d`). Every block with
convolutions takes ``conv_impl`` (default "fold", the reference).

Blocks (our reading of the paper where it is silent; the choices are also listed
in ``benchmarks/results/model.md``):

* :class:`ResBlock3D` -- two 3x3x3 convs, LeakyReLU(0.2), a residual
  connection (USM's ``ResConv3D``); optionally strided in time, the shortcut
  then averages the same bins.
* :class:`InterlacedResBlock` -- the "interlaced" residual block: parallel
  3x3x3 convs with different *temporal* dilations whose channels are
  interlaced and fused by a 1x1x1 conv (receptive field 3..9 bins at the cost
  of one conv), plus the shortcut.
* :class:`InterleavedExtraction` -- time is downsampled losslessly by
  interleaving ``r`` consecutive bins into channels (polyphase split), then
  3-D convs and interlaced (dilated) residual blocks extract features.
* :class:`TransientSpreading` -- stride-2 3-D transposed convs (x2 in space per
  stage, x2 in time while time is still coarse; computed as sub-pixel
  convolutions, :class:`Upsample3D`) plus interpolation to the full
  scan grid, added to a bilinear interpolation of the measured frame itself;
  the output is the recovered full-resolution transient.
* :class:`FeatureTransform` -- the physics layer: per feature channel, the
  phasor-field (or LCT) reconstruction of :mod:`nlosjax.physics`, with its
  operators (:func:`~nlosjax.physics.operators.lct_operators`,
  :func:`~nlosjax.physics.wavelet.illumination_wavelet`) built once per Setup
  and reused; honours the Setup's depth range; no parameters.
* :class:`VolumeReconstruction` -- feature extraction (three residual blocks,
  time downsampled) -> :class:`FeatureTransform` -> refinement (three convs
  and three interlaced residual blocks) -> volume, intensity and depth.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

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


def leaky_relu(x: jax.Array) -> jax.Array:
  """LeakyReLU with slope 0.2 (USM's activation)."""
  return jax.nn.leaky_relu(x, 0.2)


def maybe_remat(module_cls, enabled: bool):
  """``nn.remat(module_cls)`` (recompute activations in the backward pass) when ``enabled``."""
  return nn.remat(module_cls) if enabled else module_cls


def same_padding(size: int, kernel: int, stride: int = 1, dilation: int = 1) -> tuple[int, int, int]:
  """``(out, lo, hi)`` of XLA's "SAME" padding along one axis."""
  k_eff = (kernel - 1) * dilation + 1
  out = -(-size // stride)
  total = max((out - 1) * stride + k_eff - size, 0)
  return out, total // 2, total - total // 2


CONV_IMPLS = ("auto", "fold", "direct", "xla")
#: ``impl="auto"`` runs a 3-D convolution as ``"direct"`` shifted sums when it is unstrided and
#: ``Cin * features`` is at most this. Measured on 2 shared EPYC cores, forward + backward: the cpu
#: preset's refinement ([4, 64, 32, 32] voxels, 1-2 channels) 410 -> 277 ms against "fold" (the
#: forward 6x faster, the kernel gradient most of what is left); 4 -> 8 channels at
#: [4, 64, 16, 16] slower than "fold" (4.3 ms against 3.8 ms forward).
DIRECT_MAX_CHANNEL_PRODUCT = 4


def resolve_conv_impl(impl: str, kernel_size, cin: int, features: int, time_stride: int) -> str:
  """The concrete :class:`Conv3D` implementation ``impl`` stands for.

  "auto": "direct" for an unstrided kernel other than 1x1x1 with ``cin * features <=``
  :data:`DIRECT_MAX_CHANNEL_PRODUCT`, else "fold". Other values pass through.
  """
  if impl not in CONV_IMPLS:
    raise ValueError(f"impl must be one of {CONV_IMPLS}, got {impl!r}")
  if impl != "auto":
    return impl
  if tuple(kernel_size) == (1, 1, 1) or time_stride != 1 or cin * features > DIRECT_MAX_CHANNEL_PRODUCT:
    return "fold"
  return "direct"


def _shifted_sum(xp, kernel, dilation: int, out_shape) -> jax.Array:
  """``y[n, t, h, w, f] = sum_{a, b, c, i} xp[n, t + a d, h + b, w + c, i] kernel[a, b, c, i, f]``.

  Elementwise products of shifted slices, one fused loop per output channel (no im2col copy).
  """
  kt, kh, kw, cin, feats = kernel.shape
  t, h, w = out_shape
  d = dilation
  outs = []
  for o in range(feats):
    y = None
    for a in range(kt):
      for b in range(kh):
        for c in range(kw):
          s = xp[:, a * d:a * d + t, b:b + h, c:c + w]
          for i in range(cin):
            term = s[..., i] * kernel[a, b, c, i, o]
            y = term if y is None else y + term
    outs.append(y)
  return jnp.stack(outs, axis=-1)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def direct_conv3d(x, kernel, dilation: int, pads) -> jax.Array:
  """Unstrided 3-D correlation of ``x [N, T, H, W, Cin]`` with ``kernel [kt, kh, kw, Cin, F]``.

  ``pads = ((lo, hi), (ph_lo, ph_hi), (pw_lo, pw_hi))`` zero padding; temporal dilation
  ``dilation``. The same sums as ``lax.conv_general_dilated`` (for few channels, many times
  faster on XLA:CPU); its VJP: the input gradient is the same shifted sum of the padded
  cotangent with the flipped, transposed kernel, the kernel gradient one small 2-D
  convolution per time tap (batch and time contracted).
  """
  return _direct_fwd(x, kernel, dilation, pads)[0]


def _direct_out_shape(x, kernel, dilation, pads):
  kt, kh, kw = kernel.shape[:3]
  (lo, hi), (hl, hh), (wl, wh) = pads
  return (x.shape[1] + lo + hi - (kt - 1) * dilation, x.shape[2] + hl + hh - (kh - 1),
          x.shape[3] + wl + wh - (kw - 1))


def _direct_fwd(x, kernel, dilation, pads):
  xp = jnp.pad(x, ((0, 0),) + tuple(pads) + ((0, 0),))
  return _shifted_sum(xp, kernel, dilation, _direct_out_shape(x, kernel, dilation, pads)), (x, kernel)


def _direct_bwd(dilation, pads, res, g):
  x, kernel = res
  kt, kh, kw, cin, feats = kernel.shape
  d = dilation
  n, t_in, h_in, w_in, _ = x.shape
  t, h, w = g.shape[1:4]
  (lo, hi), (hl, hh), (wl, wh) = pads
  # dx[s] = sum_a g[s + lo - a d] k[a]^T: the correlation of g padded by the complementary amounts.
  gpads = (((kt - 1) * d - lo, (kt - 1) * d - hi), (kh - 1 - hl, kh - 1 - hh), (kw - 1 - wl, kw - 1 - wh))
  gp = jnp.pad(g, ((0, 0),) + gpads + ((0, 0),))
  kflip = jnp.swapaxes(kernel[::-1, ::-1, ::-1], 3, 4)
  dx = _shifted_sum(gp, kflip, d, (t_in, h_in, w_in)).astype(x.dtype)
  # dk[a, b, c, i, f] = sum_{n, t, h, w} xp[n, t + a d, h + b, w + c, i] g[n, t, h, w, f]: per time
  # tap a 2-D convolution whose "batch" is (n, t), contracted, and whose "kernel" is g.
  xp = jnp.pad(x, ((0, 0),) + tuple(pads) + ((0, 0),))
  rhs = g.reshape((n * t, h, w, feats))
  taps = []
  for a in range(kt):
    lhs = xp[:, a * d:a * d + t].reshape((n * t,) + xp.shape[2:])
    taps.append(jax.lax.conv_general_dilated(lhs, rhs, (1, 1), "VALID",
                                             dimension_numbers=("CHWN", "IHWO", "HWNC")))
  dk = jnp.stack(taps).astype(kernel.dtype)                    # [kt, kh, kw, Cin, F]
  return dx, dk


direct_conv3d.defvjp(_direct_fwd, _direct_bwd)


class Conv3D(nn.Module):
  """3-D convolution with "SAME" zero padding, strided and dilated along the first axis only.

  ``[N, T, H, W, Cin] -> [N, ceil(T / time_stride), H, W, features]``; the
  kernel is ``[kt, kh, kw, Cin, features]`` (as :class:`flax.linen.Conv`, same
  LeCun-normal init, zero bias), ``kh`` and ``kw`` odd.

  ``impl="fold"`` (default) computes it as one 2-D convolution over ``(H, W)``
  of the ``kt`` (strided, dilated) time taps stacked on the channel axis: the
  same sums as the 3-D convolution, 2.5-6x faster than XLA:CPU's 3-D
  convolution at this network's widths (4-16 channels), forward and
  backward, at the price of a ``kt``-fold copy of the input. ``impl="xla"``
  calls ``lax.conv_general_dilated`` in 3-D (the reference the tests use).
  ``impl="direct"`` (unstrided only) sums the products of shifted slices in one
  fused loop, with its own VJP (:func:`direct_conv3d`): for 1-2 channels in and
  out, where XLA:CPU's convolutions are slow, several times faster than "fold".
  ``impl="auto"`` picks "direct" or "fold" by shape (:func:`resolve_conv_impl`).
  1x1x1 kernels are a matmul (every impl but "xla").

  ``padding="edge"`` pads by repeating the border values (PyTorch's
  ``padding_mode="replicate"``, USM's ``ResConv3D``) instead of zeros, with
  the same amounts as "SAME".
  """

  features: int
  kernel_size: tuple[int, int, int] = (3, 3, 3)
  time_stride: int = 1
  time_dilation: int = 1
  use_bias: bool = True
  impl: str = "fold"
  padding: str = "zero"
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x):
    kt, kh, kw = self.kernel_size
    if kh % 2 == 0 or kw % 2 == 0:
      raise ValueError(f"kernel_size must be odd in H and W, got {self.kernel_size}")
    if x.ndim != 5:
      raise ValueError(f"x must be [N, T, H, W, C], got shape {x.shape}")
    if self.impl not in CONV_IMPLS:
      raise ValueError(f"impl must be one of {CONV_IMPLS}, got {self.impl!r}")
    if self.padding not in ("zero", "edge"):
      raise ValueError(f"padding must be 'zero' or 'edge', got {self.padding!r}")
    cin = x.shape[-1]
    kernel = self.param("kernel", nn.initializers.lecun_normal(), (kt, kh, kw, cin, self.features),
                        self.param_dtype)
    bias = (self.param("bias", nn.initializers.zeros, (self.features,), self.param_dtype)
            if self.use_bias else None)
    x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
    s, d = self.time_stride, self.time_dilation
    n, t, h, w, _ = x.shape
    out, lo, hi = same_padding(t, kt, s, d)          # "SAME" amounts; (kh // 2, kw // 2) in space
    ph, pw = kh // 2, kw // 2
    if self.padding == "edge":                       # pad by the border values, then no padding
      x = jnp.pad(x, ((0, 0), (lo, hi), (ph, ph), (pw, pw), (0, 0)), mode="edge")
      lo = hi = ph = pw = 0
    impl = resolve_conv_impl(self.impl, self.kernel_size, cin, self.features, s)
    if impl == "direct":
      if s != 1:
        raise ValueError(f"impl='direct' is unstrided, got time_stride {s}")
      y = direct_conv3d(x, kernel, d, ((lo, hi), (ph, ph), (pw, pw)))
    elif impl == "xla":
      y = jax.lax.conv_general_dilated(x, kernel, (s, 1, 1), ((lo, hi), (ph, ph), (pw, pw)),
                                       rhs_dilation=(d, 1, 1),
                                       dimension_numbers=("NDHWC", "DHWIO", "NDHWC"))
    elif (kt, kh, kw) == (1, 1, 1):
      y = jnp.einsum("nthwc,cf->nthwf", x[:, ::s], kernel[0, 0, 0])
    else:
      xp = jnp.pad(x, ((0, 0), (lo, hi), (0, 0), (0, 0), (0, 0)))
      taps = [xp[:, i * d:i * d + (out - 1) * s + 1:s] for i in range(kt)]
      folded = jnp.concatenate(taps, axis=-1).reshape((n * out,) + xp.shape[2:4] + (kt * cin,))
      k2 = jnp.transpose(kernel, (1, 2, 0, 3, 4)).reshape(kh, kw, kt * cin, self.features)
      y = jax.lax.conv_general_dilated(folded, k2, (1, 1), ((ph, ph), (pw, pw)),
                                       dimension_numbers=("NHWC", "HWIO", "NHWC"))
      y = y.reshape(n, out, h, w, self.features)
    if bias is not None:
      y = y + bias
    return y


def _conv(features: int, kernel=(3, 3, 3), *, time_stride: int = 1, time_dilation: int = 1,
          dtype=jnp.float32, param_dtype=jnp.float32, conv_impl: str = "fold", name=None) -> Conv3D:
  return Conv3D(features, tuple(kernel), time_stride, time_dilation, impl=conv_impl, dtype=dtype,
                param_dtype=param_dtype, name=name)


class Upsample3D(nn.Module):
  """Learned upsampling by ``factors`` (each 1 or 2): the stride-2 transposed convolution.

  Computed as a sub-pixel convolution (Shi et al. 2016, arXiv:1609.05158,
  1609.07009): a 3x3x3 :class:`Conv3D` to ``features * prod(factors)``
  channels, then each voxel's channel groups are laid out on its
  ``ft x fh x fw`` output cell (depth-to-space). A stride-2, 4-tap transposed
  convolution is this with some taps fixed to zero, so the family contains it;
  unlike XLA:CPU's transposed 3-D convolution it runs as one 2-D convolution.

  ``[N, T, H, W, C] -> [N, ft T, fh H, fw W, features]``.
  """

  features: int
  factors: tuple[int, int, int] = (2, 2, 2)
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32
  conv_impl: str = "fold"

  @nn.compact
  def __call__(self, x):
    ft, fh, fw = self.factors
    n, t, h, w, _ = x.shape
    y = _conv(self.features * ft * fh * fw, dtype=self.dtype, param_dtype=self.param_dtype,
              conv_impl=self.conv_impl, name="conv")(x)
    y = y.reshape(n, t, h, w, ft, fh, fw, self.features)
    y = y.transpose(0, 1, 4, 2, 5, 3, 6, 7)
    return y.reshape(n, t * ft, h * fh, w * fw, self.features)


def time_pool(x: jax.Array, factor: int) -> jax.Array:
  """Average groups of ``factor`` time bins: ``[B, T, ...] -> [B, ceil(T / factor), ...]``.

  The last group is zero-padded (so it is the sum of its bins over ``factor``).
  """
  if factor == 1:
    return x
  t = x.shape[1]
  n = -(-t // factor)
  pad = [(0, 0)] * x.ndim
  pad[1] = (0, n * factor - t)
  x = jnp.pad(x, pad)
  return x.reshape((x.shape[0], n, factor) + x.shape[2:]).mean(axis=2)


def _log2_int(value: int, name: str) -> int:
  if not (isinstance(value, int) and value >= 1 and value & (value - 1) == 0):
    raise ValueError(f"{name} must be a power of two >= 1, got {value!r}")
  return value.bit_length() - 1


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
      bounds the FFT memory); None transforms all at once (``vmap``).
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
    else:
      vol = jax.lax.map(one, xs, batch_size=self.chunk)
    vol = vol.reshape((bsz, C) + vol.shape[1:])
    return jnp.moveaxis(vol, 1, -1)


def resample_depth(volume: jax.Array, source: Setup, target: Setup) -> jax.Array:
  """Linear interpolation of ``[B, Zs, H, W]`` from ``source.depths`` to ``target.depths``.

  Depths outside the source grid take the nearest end value. Returns
  ``[B, Zt, H, W]`` (the input unchanged when the depth grids are equal).
  """
  zs, zt = source.depths, target.depths
  if zs.shape == zt.shape and np.allclose(zs, zt):
    return volume
  step = source.depth_bin_length
  pos = np.clip((zt - zs[0]) / step, 0.0, zs.size - 1.0)
  lo = np.minimum(np.floor(pos).astype(np.int64), zs.size - 1)
  hi = np.minimum(lo + 1, zs.size - 1)
  frac = jnp.asarray(pos - lo, volume.dtype)[None, :, None, None]
  return volume[:, lo] * (1.0 - frac) + volume[:, hi] * frac


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

"""3-D convolutions of the network: :class:`Conv3D` and its implementations, upsampling, pooling.

Layout channels-last, ``[B, T, H, W, C]``. Every 3-D convolution of the
network is a :class:`Conv3D`: computed as a 2-D convolution of time-folded
channels ("fold", the reference: the same sums, several times faster on
XLA:CPU), as fused sums of shifted slices (:func:`direct_conv3d`, "direct"),
or by XLA's own 3-D convolution ("xla"); ``"auto"`` picks per layer
(:func:`resolve_conv_impl`). Also the activation every block uses
(:func:`leaky_relu`) and :func:`maybe_remat`.
"""


import functools
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from nlosjax import platforms


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
  cotangent with the flipped, transposed kernel, the kernel gradient one 2-D convolution
  of the time taps stacked as channels, batch and time contracted (:func:`conv2d_kernel_grad`).
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
  xp = jnp.pad(x, ((0, 0),) + tuple(pads) + ((0, 0),))
  return dx, _direct_kernel_grad(xp, g, kt, d).astype(kernel.dtype)


def _direct_kernel_grad(xp, g, kt: int, d: int) -> jax.Array:
  """``dk[a, b, c, i, f] = sum_{n, t, h, w} xp[n, t + a d, h + b, w + c, i] g[n, t, h, w, f]``.

  ``xp [N, T + (kt - 1) d, H + kh - 1, W + kw - 1, Cin]`` (the padded input), ``g [N, T, H,
  W, F]`` -> ``[kt, kh, kw, Cin, F]``: the kernel gradient of the 2-D convolution of the
  ``kt`` time taps stacked as channels (:func:`conv2d_kernel_grad`).
  """
  n, t, h, w, feats = g.shape
  cin = xp.shape[-1]
  taps = jnp.concatenate([xp[:, a * d:a * d + t] for a in range(kt)], axis=-1)
  taps = taps.reshape((n * t,) + xp.shape[2:4] + (kt * cin,))
  dk = conv2d_kernel_grad(taps, g.reshape((n * t, h, w, feats)))          # [kh, kw, kt Cin, F]
  return jnp.moveaxis(dk.reshape(dk.shape[:2] + (kt, cin, feats)), 2, 0)


def conv2d_kernel_grad(lhs, g) -> jax.Array:
  """``dk[b, c, i, f] = sum_{p, y, x} lhs[p, y + b, x + c, i] g[p, y, x, f]``: a VALID 2-D kernel gradient.

  ``lhs [P, H + kh - 1, W + kw - 1, C]`` (padded input), ``g [P, H, W, F]`` -> ``[kh, kw, C,
  F]``. Chosen by the platform the program is lowered for (:mod:`nlosjax.platforms`): on the
  CPU :func:`conv2d_kernel_grad_cpu` (small kernels as a forward convolution whose window is
  the input), elsewhere :func:`conv2d_kernel_grad_xla` (JAX's own kernel gradient, which
  XLA:GPU computes as a backward-filter convolution). The same sums.
  """
  return platforms.by_platform(lhs, g, cpu=conv2d_kernel_grad_cpu, other=conv2d_kernel_grad_xla)


def conv2d_kernel_grad_xla(lhs, g) -> jax.Array:
  """:func:`conv2d_kernel_grad` as JAX's VJP of the VALID convolution with respect to its kernel.

  ``lhs [P, H + kh - 1, W + kw - 1, C]``, ``g [P, H, W, F]`` -> ``[kh, kw, C, F]``. Its window
  is the cotangent ``[H, W]`` and its output the kernel: the form XLA:GPU rewrites into a cuDNN
  backward-filter call.
  """
  p, h, w, feats = g.shape
  kh, kw = lhs.shape[1] - h + 1, lhs.shape[2] - w + 1
  dtype = jnp.result_type(lhs, g)
  zero = jnp.zeros((kh, kw, lhs.shape[-1], feats), dtype)
  _, vjp = jax.vjp(lambda k: jax.lax.conv_general_dilated(lhs.astype(dtype), k, (1, 1), "VALID",
                                                          dimension_numbers=("NHWC", "HWIO", "NHWC")), zero)
  return vjp(g.astype(dtype))[0]


def conv2d_kernel_grad_cpu(lhs, g) -> jax.Array:
  """:func:`conv2d_kernel_grad` as tuned on XLA:CPU.

  ``lhs [P, H + kh - 1, W + kw - 1, C]`` (padded input), ``g [P, H, W, F]`` -> ``[kh, kw, C,
  F]``. XLA's own kernel gradient is a 2-D convolution whose "batch" is ``C``; for kernels of at
  most 3 x 3 with ``F <= C`` it is computed the other way round instead: the cotangent,
  padded by ``(kh - 1, kw - 1)``, convolved with the input as the kernel (batch ``F``; the
  output runs backwards in ``b, c``). The same sums; measured alone on 2 EPYC cores
  (P = 256 of 32 x 32): C 6 -> F 1 in 5.7 ms against 48.7 ms, 6 -> 2 (P 512) 46 against 112,
  21 -> 2 200 against 396, 24 -> 8 (16 x 16) 17 against 59; with larger kernels it lost
  (3 -> 2 at 9 x 9: 565 against 472 ms; 28 -> 8 at 7 x 7: 550 against 334), and with
  ``F > C`` too (2 -> 6: 61 against 16).
  """
  p, h, w, feats = g.shape
  kh, kw = lhs.shape[1] - h + 1, lhs.shape[2] - w + 1
  if feats <= lhs.shape[-1] and kh * kw <= 9:
    gp = jnp.pad(g, ((0, 0), (kh - 1, kh - 1), (kw - 1, kw - 1), (0, 0)))
    out = jax.lax.conv_general_dilated(gp, lhs, (1, 1), "VALID",
                                       dimension_numbers=("CHWN", "IHWO", "NHWC"))   # [F, kh, kw, C]
    return jnp.transpose(out[:, ::-1, ::-1], (1, 2, 3, 0))
  return jax.lax.conv_general_dilated(lhs, g, (1, 1), "VALID",
                                      dimension_numbers=("CHWN", "IHWO", "HWNC"))     # [kh, kw, C, F]


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv2d(x, kernel, pads) -> jax.Array:
  """``lax.conv_general_dilated(x, kernel, (1, 1), pads)``, NHWC / HWIO, with the kernel gradient of
  :func:`conv2d_kernel_grad` (the input gradient is XLA's). ``pads = ((lo, hi), (lo, hi))``."""
  return _conv2d(x, kernel, pads)


def _conv2d(x, kernel, pads):
  return jax.lax.conv_general_dilated(x, kernel, (1, 1), tuple(pads),
                                      dimension_numbers=("NHWC", "HWIO", "NHWC"))


def _conv2d_fwd(x, kernel, pads):
  return _conv2d(x, kernel, pads), (x, kernel)


def _conv2d_bwd(pads, res, g):
  x, kernel = res
  dx = jax.vjp(lambda v: _conv2d(v, kernel, pads), x)[1](g)[0]
  xp = jnp.pad(x, ((0, 0),) + tuple(tuple(q) for q in pads) + ((0, 0),))
  return dx, conv2d_kernel_grad(xp, g).astype(kernel.dtype)


conv2d.defvjp(_conv2d_fwd, _conv2d_bwd)


direct_conv3d.defvjp(_direct_fwd, _direct_bwd)


def strided_conv3d(x, kernel, stride: int = 2) -> jax.Array:
  """VALID 3-D correlation with ``stride`` on every axis, as an unstrided one over polyphase channels.

  ``x [N, T, H, W, Cin]``, ``kernel [kt, kh, kw, Cin, F]`` -> ``[N, (T - kt) // s + 1, ...,
  F]``: the same sums as ``lax.conv_general_dilated(x, kernel, (s, s, s), "VALID")``. Each
  axis is split into its ``s`` phases (``x[s t + p]`` -> channel ``p``) and the kernel into
  ``ceil(k / s)`` taps per phase (zero where ``s a + p >= k``), then convolved without a
  stride by the time-folded 2-D convolution (:func:`conv2d`). So the input gradient is an
  ordinary convolution too: XLA:CPU computes a strided convolution's input gradient as a
  base-dilated one, which at USM's extraction ([4, 130, 34, 34] voxels, 1 channel) took
  0.7 s of a 3.6 s training step.
  """
  n, _, _, _, cin = x.shape
  ks = kernel.shape[:3]
  feats = kernel.shape[-1]
  out = tuple((size - k) // stride + 1 for size, k in zip(x.shape[1:4], ks))
  taps = tuple(-(-k // stride) for k in ks)
  if min(out) < 1:
    raise ValueError(f"strided_conv3d: input {x.shape[1:4]} is smaller than the kernel {ks}")
  # Phases: x[n, s t + p, s h + q, s w + r, i] -> xs[n, t, h, w, (p, q, r, i)], each axis padded
  # (with zeros, read only by zero taps) to s (out + taps - 1) samples.
  size = tuple(stride * (o + a - 1) for o, a in zip(out, taps))
  x = x[:, :size[0], :size[1], :size[2]]
  x = jnp.pad(x, ((0, 0),) + tuple((0, z - have) for z, have in zip(size, x.shape[1:4])) + ((0, 0),))
  m = tuple(z // stride for z in size)
  xs = x.reshape(n, m[0], stride, m[1], stride, m[2], stride, cin)
  xs = xs.transpose(0, 1, 3, 5, 2, 4, 6, 7).reshape(n, m[0], m[1], m[2], stride ** 3 * cin)
  # kernel[s a + p, s b + q, s c + r, i, f] -> kp[a, b, c, (p, q, r, i), f]
  kpad = jnp.pad(kernel, tuple((0, stride * a - k) for a, k in zip(taps, ks)) + ((0, 0), (0, 0)))
  kp = kpad.reshape(taps[0], stride, taps[1], stride, taps[2], stride, cin, feats)
  kp = kp.transpose(0, 2, 4, 1, 3, 5, 6, 7).reshape(taps + (stride ** 3 * cin, feats))
  # Unstrided VALID over the phases, time taps folded into channels.
  folded = jnp.concatenate([xs[:, a:a + out[0]] for a in range(taps[0])], axis=-1)
  folded = folded.reshape((n * out[0],) + m[1:] + (taps[0] * stride ** 3 * cin,))
  k2 = jnp.transpose(kp, (1, 2, 0, 3, 4)).reshape(taps[1], taps[2], -1, feats)
  y = conv2d(folded, k2, ((0, 0), (0, 0)))
  return y.reshape(n, out[0], out[1], out[2], feats)


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
      y = conv2d(folded, k2, ((ph, ph), (pw, pw)))
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

"""USM, the under-scanning network the paper compares with (Li et al., NeurIPS 2023), in Flax linen.

One static frame; no Mamba, no temporal path. The architecture is that of the
public code (``EmbedFeatureModel_MUL_gray_former_mask_refine`` of the authors' release), in
this project's conventions
(channels-last activations, shapes from the :class:`Setup`):

1. **Zero fill** (:func:`zero_fill`): the ``h x w`` under-scanned counts
   (divided by their per-sample root mean square, as Ours) are placed on the
   full ``H x W`` grid at scan points ``stride // 2 + stride * i`` (USM's mask:
   rows 4, 12, ..., 124 of 128 for stride 8), zeros elsewhere.
2. **Transient recovery** (multi-kernel): parallel branches, each a
   ``3 x k x k`` conv (zero padding) to ``trn_width`` channels + LeakyReLU(0.2)
   + one replicate-padded residual block (``ResConv3D``), for each
   ``k`` in ``trn_kernels``; beside them the nearest-neighbour upsampling of
   the samples (output pixel ``i`` reads sample ``i // stride``). Concatenated
   ``[nearest, branches in ascending k]`` and fused by conv + LeakyReLU +
   residual block to each of ``fusion_widths`` and then to 1 channel: the
   recovered full-grid transient (not clamped; may be negative).
3. **Feature extraction** on the min-max normalised transient: a learnable
   ``3 x 3 x 3`` stride-2 kernel initialised to ``2 x 2 x 2`` averaging (zero
   padding), beside a replicate-padded stride-2 conv to ``extract_width``
   channels + two residual blocks: ``[B, T/2, H/2, W/2, 1 + extract_width]``.
   Time and space are halved here and only here.
4. **LCT feature transform**: each channel through
   :class:`~nlosjax.models.physics_layer.FeatureTransform` (``method="lct"``: the
   ``nlosjax.physics.lct`` computation, Wiener ``snr``, ``t^4`` weighting) on
   the half-resolution Setup (:func:`half_setup`), clamped at 0, min-max
   normalised per channel.
5. **Refinement**: conv (kernel ``k``) + LeakyReLU + residual block for each
   ``(width, k)`` of ``refine`` (USM: (8, 7), (8, 5), (C, 3)); the last width is
   the channel count ``C = 1 + extract_width``. This is the volume ``V`` the
   regularisers act on.
6. **Projection**: max over depth (``C`` intensity features) and
   ``(Z - 1 - argmax) / (Z - 1)`` (``C`` depth features: nearer is larger; no
   gradient through argmax).
7. **Two rendering heads** (intensity, depth), each: base image = a bias-free
   ``1 x 1`` conv of ``[intensity feature 0, depth feature 0]`` upsampled x2
   (bilinear, half-pixel centres), initialised to ``[1, 0]`` (intensity) or
   ``[0, 1]`` (depth); residual = reflect-padded conv to ``render_widths[0]``
   + two 2-D residual blocks at half resolution, bilinear x2, concatenated
   with the base image, reflect-padded conv to ``render_widths[1]`` + two
   residual blocks, reflect-padded conv to 1 channel. Output = base +
   residual, not clamped (the evaluation clamps intensities to [0, 1], as
   USM's metrics do).

At the published widths (:meth:`USMConfig.published`) the parameter count is
USM's 115,042. Differences from the public code, each for a reason:

* Flax's default initialisation (LeCun normal, zero bias), not PyTorch's;
* the input is divided by its root mean square (USM fed LFE's [0, 4] video
  unscaled; our counts span orders of magnitude, and Ours gets the same
  normalisation);
* no 200-of-256 depth crop: the Setup's ``depth_range`` does the cropping;
* ``"volume"`` (the output a user reads) is ``relu(V[..., 0])`` moved to the
  full grid (bilinear x2) and to ``setup.depths``; the regularisers act on
  ``"feature_volume"``, ``V`` itself, all channels, as USM's.

The published training recipe (losses and weights, AdamW lr 1e-4, weight
decay 1e-4, no schedule, no clipping) is :data:`PUBLISHED_OPTIM` and
:data:`PUBLISHED_LOSS`; the main job can train USM with it or with Ours' recipe
(a config's ``usm.recipe``, see :func:`nlosjax.train.training_recipe`).
"""

from __future__ import annotations

import dataclasses
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.models import blocks, conv, physics_layer
from nlosjax.models.network import INPUT_NORMS, ScanInputConfig, input_scale
from nlosjax.physics import _validate
from nlosjax.physics.operators import check_falloff, lct_domain
from nlosjax.physics.setup import Setup

__all__ = ["USMConfig", "USMNet", "zero_fill", "scan_mask", "half_setup", "minmax_normalise", "upsample2",
           "project_and_render", "HalfResolutionShapes",
           "PUBLISHED_OPTIM", "PUBLISHED_LOSS"]

#: USM's optimiser (train.sh): AdamW, lr 1e-4, weight decay 1e-4, no schedule, no clipping
#: (fields of :class:`nlosjax.train.OptimConfig`).
PUBLISHED_OPTIM = {"learning_rate": 1e-4, "weight_decay": 1e-4, "warmup_steps": 0, "cosine": False,
                   "clip_norm": None}
#: USM's loss (train.sh): transient RMSE 1, intensity RMSE 1, depth 0 (the depth head is never
#: trained), local similarity 1e-5, 3-D TV 1e-6, no phasor-field term (fields of
#: :class:`nlosjax.losses.LossWeights`: ``gamma * local_similarity = 1e-5``,
#: ``gamma * alpha3 = 1e-6``).
PUBLISHED_LOSS = {"phasor_field": 0.0, "alpha1": 1.0, "alpha2": 0.0, "alpha3": 0.1, "beta": 1.0,
                  "gamma": 1e-5, "intensity": 1.0, "local_similarity": 1.0,
                  "object_intensity": 0.0}

_TINY = 1e-12


def _positive_ints(value, name: str) -> tuple[int, ...]:
  try:
    out = tuple(int(v) for v in value)
  except TypeError:
    raise ValueError(f"USMConfig.{name} must be a tuple of positive integers, got {value!r}") from None
  if not out or any(v < 1 for v in out) or any(int(v) != v for v in value):
    raise ValueError(f"USMConfig.{name} must be a non-empty tuple of positive integers, got {value!r}")
  return out


class HalfResolutionShapes:
  """Shapes of a network that halves time and space once before its physics layer (USM, LFE).

  Needs ``setup`` and ``extract_width``; ``physics`` names the layer's method ("lct" unless
  the config has the field).
  """

  physics = "lct"
  # What nlosjax.inference.for_capture reads: time is halved once, before the physics layer.
  extract_time_stride = 1
  volume_time_stride = 2

  @property
  def channels(self) -> int:
    """``C``: feature channels through the physics layer (the pooled transient + ``extract_width``)."""
    return 1 + int(self.extract_width)

  @property
  def time_window(self) -> tuple[int, int]:
    """``(0, T)``: every bin is read."""
    return (0, self.setup.num_bins)

  @property
  def coarse_setup(self) -> Setup:
    """The Setup of the physics layer: :func:`half_setup` of ``setup``."""
    return half_setup(self.setup)

  def analytic_flops(self, batch: int) -> tuple[float, float]:
    """``(fft, 0)``: FLOPs of the physics layer's FFTs (``2.5 N log2 N`` per real FFT), no scan."""
    dom = lct_domain(self.coarse_setup, fft_length=physics_layer.physics_fft_length(self.physics))
    n = math.prod(dom.fft_shape)
    return batch * self.channels * 2 * 2.5 * n * math.log2(n), 0.0


@dataclasses.dataclass(frozen=True)
class USMConfig(HalfResolutionShapes, ScanInputConfig):
  """Every hyper-parameter of :class:`USMNet` (frozen, hashable).

  Attributes:
    setup: the full-resolution capture (square grid, ``H``, ``W`` and ``T`` even).
    stride: under-scan stride (input scan points ``stride // 2 + stride * i``).
    frames: always 1 (USM reconstructs one static frame).
    trn_width: channels of each multi-kernel branch (USM ``temp_chans`` 8).
    trn_kernels: spatial kernel sizes of the branches, odd (USM 3, 5, 9, 17 at stride 8).
    fusion_widths: channels of the fusion convs before the last one (to 1; USM 16, 8).
    extract_width: conv channels of the feature extraction (USM ``nf0`` 3).
    refine: ``(width, kernel)`` of each refinement conv; the last width must be
      ``1 + extract_width`` (USM (8, 7), (8, 5), (4, 3)).
    render_widths: the rendering heads' two conv widths (USM 8, 16).
    lct_snr: Wiener SNR of the LCT layer (USM 0.1).
    falloff: radiometric falloff of the LCT layer ("diffuse": ``t^4``, USM's).
    input_norm: per-sample scale of the counts (as :class:`~nlosjax.models.network.ModelConfig`).
    wavelet_cycles, wavelet_sampling: the illumination wavelet of the
      phasor-field loss when USM is trained with Ours' loss (not used by the model).
  """

  setup: Setup
  stride: int = 8
  frames: int = 1
  trn_width: int = 8
  trn_kernels: tuple[int, ...] = (3, 5, 9, 17)
  fusion_widths: tuple[int, ...] = (16, 8)
  extract_width: int = 3
  refine: tuple[tuple[int, int], ...] = ((8, 7), (8, 5), (4, 3))
  render_widths: tuple[int, int] = (8, 16)
  lct_snr: float = 0.1
  falloff: str = "diffuse"
  input_norm: str = "rms"
  wavelet_cycles: float = 5.0
  wavelet_sampling: float = 2.0

  def __post_init__(self):
    if not isinstance(self.setup, Setup):
      raise ValueError(f"USMConfig.setup must be a nlosjax.physics.Setup, got {self.setup!r}")
    H, W = self.setup.grid
    if H != W or H % 2 or self.setup.num_bins % 2:
      raise ValueError("USM halves time and space once and needs a square grid: H = W even and T"
                       f" even, got grid {self.setup.grid} and {self.setup.num_bins} bins")
    if isinstance(self.stride, bool) or not isinstance(self.stride, (int, np.integer)) \
        or not 1 <= self.stride <= H:
      raise ValueError(f"USMConfig.stride must be an integer in [1, {H}], got {self.stride!r}")
    if self.frames != 1:
      raise ValueError(f"USMConfig.frames must be 1 (USM reconstructs one frame), got {self.frames!r}")
    for name in ("trn_width", "extract_width"):
      v = getattr(self, name)
      if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise ValueError(f"USMConfig.{name} must be a positive integer, got {v!r}")
    kernels = _positive_ints(self.trn_kernels, "trn_kernels")
    if any(k % 2 == 0 for k in kernels):
      raise ValueError(f"USMConfig.trn_kernels must be odd, got {self.trn_kernels!r}")
    object.__setattr__(self, "trn_kernels", tuple(sorted(kernels)))
    object.__setattr__(self, "fusion_widths", tuple(_positive_ints(self.fusion_widths, "fusion_widths"))
                       if len(self.fusion_widths) else ())
    render = _positive_ints(self.render_widths, "render_widths")
    if len(render) != 2:
      raise ValueError(f"USMConfig.render_widths must be two widths, got {self.render_widths!r}")
    object.__setattr__(self, "render_widths", render)
    try:
      refine = tuple((int(w), int(k)) for w, k in self.refine)
    except (TypeError, ValueError):
      raise ValueError(f"USMConfig.refine must be (width, kernel) pairs, got {self.refine!r}") from None
    if not refine or any(w < 1 or k < 1 or k % 2 == 0 for w, k in refine):
      raise ValueError(f"USMConfig.refine needs positive widths and odd kernels, got {self.refine!r}")
    if refine[-1][0] != self.channels:
      raise ValueError(f"USMConfig.refine must end at {self.channels} channels (1 + extract_width),"
                       f" got {refine[-1][0]}")
    object.__setattr__(self, "refine", refine)
    _validate.check_positive(self.lct_snr, "USMConfig.lct_snr")
    check_falloff(self.falloff)
    if self.input_norm not in INPUT_NORMS:
      raise ValueError(f"USMConfig.input_norm must be one of {INPUT_NORMS}, got {self.input_norm!r}")

  # -------------------------------------------------------------- presets
  @classmethod
  def published(cls, setup: Setup | None = None, **overrides) -> "USMConfig":
    """USM as published: 128 x 128 x 512 (2 m wall, 33 ps bins), stride 8, 115,042 parameters."""
    setup = setup or Setup(wall_size=2.0, grid=(128, 128), bin_width=33e-12, num_bins=512)
    return cls(setup=setup, **{"stride": 8, **overrides})

  def module(self) -> "USMNet":
    """The Flax module of this config."""
    return USMNet(self)



def half_setup(setup: Setup) -> Setup:
  """The Setup after USM's stride-2 extraction: ``2 x 2`` scan points and 2 bins merged.

  Each coarse scan point is the mean of a ``2 x 2`` block, so it sits at the
  block's centre: the coarse grid spans the wall less one fine spacing
  (``wall (H - 2) / (H - 1)``) with twice the spacing; bins are twice as wide.
  """
  H, W = setup.grid
  if H != W or H % 2 or H < 4:
    raise ValueError(f"half_setup needs a square grid with an even side >= 4, got {setup.grid}")
  return dataclasses.replace(setup, wall_size=setup.wall_size * (H - 2) / (H - 1),
                             grid=(H // 2, W // 2), bin_width=2 * setup.bin_width,
                             num_bins=-(-setup.num_bins // 2))


def scan_mask(grid: tuple[int, int], stride: int) -> np.ndarray:
  """``[H, W]`` float32: 1 at the scan points ``stride // 2 + stride * i`` (both axes), else 0."""
  H, W = grid
  m = np.zeros((H, W), np.float32)
  m[np.ix_(blocks.underscan_indices(H, stride), blocks.underscan_indices(W, stride))] = 1.0
  return m


def zero_fill(x: jax.Array, grid: tuple[int, int], stride: int) -> jax.Array:
  """USM's input: ``[..., T, h, w]`` samples -> ``[..., T, H, W]``, zeros off the scan points.

  Equals the full transient times :func:`scan_mask` when the samples are that
  transient's scan points.
  """
  H, W = grid
  rows, cols = blocks.underscan_indices(H, stride), blocks.underscan_indices(W, stride)
  if tuple(x.shape[-2:]) != (rows.size, cols.size):
    raise ValueError(f"samples must be [..., T, {rows.size}, {cols.size}] for grid {grid} at stride"
                     f" {stride}, got shape {x.shape}")
  out = jnp.zeros(x.shape[:-2] + (H, W), x.dtype)
  return out.at[..., rows[0]::stride, cols[0]::stride].set(x)


def _nearest_fill(x: jax.Array, grid: tuple[int, int], stride: int) -> jax.Array:
  """``[..., h, w] -> [..., H, W]``: pixel ``i`` reads sample ``min(i // stride, h - 1)`` (USM ``simple_up``)."""
  H, W = grid
  h, w = x.shape[-2:]
  ri = np.minimum(np.arange(H) // stride, h - 1)
  ci = np.minimum(np.arange(W) // stride, w - 1)
  return x[..., ri, :][..., ci]


def minmax_normalise(x: jax.Array, axes: tuple[int, ...]) -> jax.Array:
  """``(x - min) / (max - min)`` over ``axes`` (USM ``normalize``), guarded against a flat input."""
  lo = jnp.min(x, axis=axes, keepdims=True)
  hi = jnp.max(x, axis=axes, keepdims=True)
  return (x - lo) / jnp.maximum(hi - lo, _TINY)


def _lrelu(x):
  return conv.leaky_relu(x)


class ResConv3D(nn.Module):
  """USM's ``ResConv3D``: ``y = LReLU(conv(LReLU(conv(x))) + x)``, 3x3x3, replicate padding, bias.

  ``[N, T, H, W, C] -> [N, T, H, W, C]``.
  """

  @nn.compact
  def __call__(self, x):
    c = x.shape[-1]
    y = _lrelu(conv.Conv3D(c, padding="edge", name="conv1")(x))
    y = conv.Conv3D(c, padding="edge", name="conv2")(y)
    return _lrelu(y + x)


class ResConv2D(nn.Module):
  """USM's ``ResConv2D``: the 2-D version of :class:`ResConv3D`. ``[N, H, W, C]`` -> same."""

  @nn.compact
  def __call__(self, x):
    c = x.shape[-1]
    pad = ((0, 0), (1, 1), (1, 1), (0, 0))
    y = _lrelu(nn.Conv(c, (3, 3), padding="VALID", name="conv1")(jnp.pad(x, pad, mode="edge")))
    y = nn.Conv(c, (3, 3), padding="VALID", name="conv2")(jnp.pad(y, pad, mode="edge"))
    return _lrelu(y + x)


def _reflect_conv(features: int, name: str):
  """Reflection pad 1 + 3x3 conv (valid) on ``[N, H, W, C]``."""
  conv = nn.Conv(features, (3, 3), padding="VALID", name=name)
  return lambda x: conv(jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="reflect"))


def upsample2(x: jax.Array) -> jax.Array:
  """Bilinear x2 with half-pixel centres (PyTorch ``align_corners=False``): ``[N, h, w, C] -> [N, 2h, 2w, C]``."""
  n, h, w, c = x.shape
  return jax.image.resize(x, (n, 2 * h, 2 * w, c), "linear")


class TransientRecovery(nn.Module):
  """USM's multi-kernel transient recovery: zero-filled ``[N, T, H, W]`` + samples -> ``[N, T, H, W]``."""

  config: USMConfig

  @nn.compact
  def __call__(self, filled, samples):
    cfg = self.config
    x = filled[..., None]
    branches = [_nearest_fill(samples, cfg.setup.grid, cfg.stride)[..., None]]
    for k in cfg.trn_kernels:
      y = _lrelu(conv.Conv3D(cfg.trn_width, (3, k, k), name=f"branch_k{k}")(x))
      branches.append(ResConv3D(name=f"branch_k{k}_res")(y))
    y = jnp.concatenate(branches, axis=-1)
    for i, width in enumerate(tuple(cfg.fusion_widths) + (1,)):
      y = _lrelu(conv.Conv3D(width, name=f"fuse{i}")(y))
      y = ResConv3D(name=f"fuse{i}_res")(y)
    return y[..., 0]


class Extraction(nn.Module):
  """USM's ``Transient2volumn``: ``[N, T, H, W]`` -> ``[N, T/2, H/2, W/2, 1 + width]``, stride 2 everywhere."""

  width: int

  @nn.compact
  def __call__(self, x):
    x = x[..., None]

    def pool_init(key, shape, dtype=jnp.float32):
      k = np.zeros(shape, np.float32)
      k[1:, 1:, 1:] = 1.0 / 8.0
      return jnp.asarray(k, dtype)

    kernel = self.param("pool", pool_init, (3, 3, 3, 1, 1), jnp.float32)
    # Both stride-2 convolutions run as unstrided ones over polyphase channels
    # (conv.strided_conv3d: the same sums, an input gradient without base dilation).
    pooled = conv.strided_conv3d(jnp.pad(x, ((0, 0),) + ((1, 1),) * 3 + ((0, 0),)), kernel)
    xp = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (1, 1), (0, 0)), mode="edge")
    conv_k = self.param("conv_kernel", nn.initializers.lecun_normal(), (3, 3, 3, 1, self.width),
                        jnp.float32)
    conv_b = self.param("conv_bias", nn.initializers.zeros, (self.width,), jnp.float32)
    y = conv.strided_conv3d(xp, conv_k) + conv_b
    for i in range(2):
      y = ResConv3D(name=f"res{i}")(y)
    return jnp.concatenate([pooled, y], axis=-1)


class Rendering(nn.Module):
  """USM's rendering head: ``[N, h, w, 2C]`` features -> ``[N, 2h, 2w]`` image.

  Attributes:
    widths: the two conv widths.
    base: ``"intensity"`` (base image initialised to intensity feature 0) or
      ``"depth"`` (to depth feature 0).
  """

  widths: tuple[int, int]
  base: str

  @nn.compact
  def __call__(self, feats):
    c = feats.shape[-1] // 2
    pair = jnp.stack([feats[..., 0], feats[..., c]], axis=-1)          # [N, h, w, 2]
    init = np.array([[1.0], [0.0]] if self.base == "intensity" else [[0.0], [1.0]], np.float32)
    w_base = self.param("base", lambda *_: jnp.asarray(init), (2, 1))
    base = upsample2(pair) @ w_base                                    # [N, H, W, 1]
    y = _reflect_conv(self.widths[0], "conv0")(feats)
    for i in range(2):
      y = ResConv2D(name=f"res0_{i}")(y)
    y = jnp.concatenate([upsample2(y), base], axis=-1)
    y = _reflect_conv(self.widths[1], "conv1")(y)
    for i in range(2):
      y = ResConv2D(name=f"res1_{i}")(y)
    y = _reflect_conv(1, "conv2")(y)
    return (base + y)[..., 0]


def scaled_input(config: ScanInputConfig, frames) -> tuple[jax.Array, jax.Array]:
  """The input USM, LFE and I-K share: ``frames [B, 1, T, h, w]`` counts -> ``(x, scale)``.

  Checks the shape and dtype (``config.check_frames``) and, outside ``jit``, the counts
  (no NaN, none negative); ``x [B, T, h, w]`` float32 is the frame in units of its
  per-sample ``scale [B]`` (:func:`nlosjax.models.network.input_scale`, ``config.input_norm``).
  """
  config.check_frames(frames)
  _validate.check_counts(frames, "frames")
  x = jnp.asarray(frames, jnp.float32)[:, 0]                          # [B, T, h, w]
  scale = input_scale(x, config.input_norm)
  return x / scale[:, None, None, None], scale


def transformed_features(transient: jax.Array, extract_width: int, transform) -> jax.Array:
  """The features USM, LFE and I-K share: ``transient [B, T, H, W]`` -> ``[B, Zc, H/2, W/2, C]``.

  Min-max normalised, through :class:`Extraction` (submodule ``extract`` of the calling
  module, so call it inside a compact ``__call__``), the feature transform ``transform``
  (a :class:`~nlosjax.models.physics_layer.FeatureTransform` of the calling module) on its
  time window, min-max normalised again.
  """
  feats = Extraction(extract_width, name="extract")(minmax_normalise(transient, (1, 2, 3)))
  a, b = transform.window()
  return minmax_normalise(transform(feats[:, a:b], time_offset=a), (1, 2, 3))


def project_and_render(vol: jax.Array, render_widths: tuple[int, int], coarse: Setup, setup: Setup):
  """The heads USM, LFE and I-K share: ``vol [B, Zc, h2, w2, C]`` on ``coarse`` -> ``(intensity, depth, volume)``.

  Projection (max over depth: ``C`` intensity features; ``(Z - 1 - argmax) / (Z - 1)``:
  ``C`` depth features, no gradient through argmax), the two :class:`Rendering` heads
  (``[B, H, W]`` each; submodules ``render_intensity`` and ``render_depth`` of the
  calling module, so call it inside a compact ``__call__``), and ``relu(vol[..., 0])``
  on ``setup.depths`` and the full grid (``[B, Z, H, W]``, bilinear x2).
  """
  z = vol.shape[1]
  inten_f = jnp.max(vol, axis=1)                                        # [B, h2, w2, C]
  arg = jax.lax.stop_gradient(jnp.argmax(vol, axis=1)).astype(jnp.float32)
  depth_f = (z - 1 - arg) / max(z - 1, 1)
  proj = jnp.concatenate([inten_f, depth_f], axis=-1)                   # [B, h2, w2, 2C]
  intensity = Rendering(render_widths, "intensity", name="render_intensity")(proj)
  depth = Rendering(render_widths, "depth", name="render_depth")(proj)
  v0 = jnp.maximum(vol[..., 0], 0.0)                                    # [B, Zc, h2, w2]
  v0 = physics_layer.resample_depth(v0, coarse, setup)                  # [B, Z, h2, w2]
  return intensity, depth, jnp.moveaxis(upsample2(jnp.moveaxis(v0, 1, -1)), -1, 1)


class USMNet(nn.Module):
  """USM for one under-scanned frame (see the module docstring).

  Attributes:
    config: a :class:`USMConfig`.

  Args of ``__call__``:
    frames: ``[B, 1, T, h, w]`` photon counts (float or int, >= 0).
  Returns:
    dict of float32 arrays:

    * ``"transient"`` ``[B, T, H, W]``: recovered full-grid transient, in
      units of ``scale``;
    * ``"volume"`` ``[B, Z, H, W]``: ``relu(V[..., 0])`` on ``setup.depths``
      and the full grid (bilinear);
    * ``"feature_volume"`` ``[B, Zc, H/2, W/2, C]``: the refined volume ``V``
      on :func:`half_setup`'s depths (what the regularisers act on);
    * ``"intensity"`` ``[B, H, W]``: the intensity head (not clamped);
    * ``"depth"`` ``[B, H, W]``: the depth head (in the units it was trained
      in: metres with Ours' loss; untrained with the published loss);
    * ``"scale"`` ``[B]``: the per-sample input scale.
  Raises:
    ValueError: frames of the wrong shape or dtype, or (outside jit) NaN or
      negative counts.
  """

  config: USMConfig

  @nn.compact
  def __call__(self, frames):
    cfg = self.config
    x, scale = scaled_input(cfg, frames)                                # [B, T, h, w], [B]
    transient = TransientRecovery(cfg, name="trn")(zero_fill(x, cfg.setup.grid, cfg.stride), x)
    coarse = cfg.coarse_setup
    transform = physics_layer.FeatureTransform(coarse, "lct", snr=cfg.lct_snr, falloff=cfg.falloff,
                                               name="lct")
    vol = transformed_features(transient, cfg.extract_width, transform)   # [B, Zc, h2, w2, C]
    for i, (width, k) in enumerate(cfg.refine):
      vol = _lrelu(conv.Conv3D(width, (k, k, k), name=f"refine{i}")(vol))
      vol = ResConv3D(name=f"refine{i}_res")(vol)
    intensity, depth, volume = project_and_render(vol, cfg.render_widths, coarse, cfg.setup)
    return {"transient": transient, "volume": volume,
            "feature_volume": vol, "intensity": intensity, "depth": depth, "scale": scale}


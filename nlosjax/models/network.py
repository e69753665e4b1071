"""The full ST-Mamba network (paper Sec. 4, Fig. 3): config, model, summary.

Pipeline for a batch of ``F`` adjacent under-scanned frames ``[B, F, T, h, w]``
(``F = 3``: frames t-1, t, t+1, the middle one is the target -- "Ours";
``F = 1``: "Ours-S"):

1. normalise the counts by a per-sample scale (``input_norm``; guarded, so an
   all-zero input gives zeros) and keep the time window the physics layer
   needs (:attr:`ModelConfig.time_window`: all bins without a depth range);
2. :class:`~nlosjax.models.blocks.InterleavedExtraction` per frame (shared
   weights) -> ``st_depth`` :class:`~nlosjax.models.stmamba.STMambaBlock` per
   frame (shared weights) -> for every neighbour, ``cross_depth``
   :class:`~nlosjax.models.stmamba.CrossSTMambaBlock` aligning it to the
   target (own weights per neighbour offset); enhanced = target + mean of the
   aligned features;
3. :class:`~nlosjax.models.blocks.TransientSpreading` -> recovered transient on
   the full grid (zero outside the time window); its skip is the measured
   middle frame (``skip_frames="middle"``) or a learned convex combination of
   all ``F`` frames (``"weighted"``: softmax weights, uniform at init, so the
   neighbours' photons reach the output directly);
4. :class:`~nlosjax.models.blocks.VolumeReconstruction` (feature extraction,
   physics layer on the model's Setup, refinement) -> volume, intensity, depth.

Every shape derives from :class:`ModelConfig` and its :class:`Setup`; no
parameter shape depends on the Setup (only on the widths, the stride and the
strides in time), so trained weights run on another wall size, bin width,
bin count or depth range by ``config.with_setup(other)`` (the physics
operators are rebuilt for it; they are constants, not parameters).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.models import blocks, conv, physics_layer
from nlosjax.models.stmamba import BLOCK_MIXERS, CrossSTMambaBlock, STMambaBlock
from nlosjax.physics import _validate, operator_args
from nlosjax.physics.operators import OPERATOR_VARIANTS, check_variant, lct_domain, public_lct_domain
from nlosjax.physics.setup import Setup
from nlosjax.ssm import resolve_method

INPUT_NORMS = ("rms", "mean", "max")
SKIP_FRAMES = ("middle", "weighted")
DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}


def _positive_int(value, name: str) -> int:
  if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
    raise ValueError(f"ModelConfig.{name} must be a positive integer, got {value!r}")
  return int(value)


def _power_of_two(value, name: str) -> int:
  value = _positive_int(value, name)
  if value & (value - 1):
    raise ValueError(f"ModelConfig.{name} must be a power of two, got {value!r}")
  return value


@functools.lru_cache(maxsize=16)
def _traced_init(config):
  """``(parameter shapes, OperatorTable)`` of ``config``'s module, from one shape-only trace of its init."""
  x = jax.ShapeDtypeStruct(tuple(config.input_shape(1)), jnp.float32)
  variables, table = operator_args.traced_with_operators(config.module().init, jax.random.key(0), x)
  return variables["params"], table


class ScanInputConfig:
  """What every model config derives from its ``setup``, ``stride`` and ``frames`` fields.

  The under-scanned input (``input_grid``, ``input_shape``, ``check_frames``)
  and the dataclass copies (``with_setup``, ``replace``), shared by
  :class:`ModelConfig` and :class:`~nlosjax.models.usm.USMConfig` (frozen
  dataclasses with those three fields).
  """

  #: Whether the parameter tree's shapes depend on ``setup`` (the model then runs on its
  #: training Setup only). Declared per model family so that moving a model to a capture
  #: costs no trace; ``tests/test_pretrained.py`` checks each declaration against the
  #: traced parameter trees at two Setups.
  params_depend_on_setup: ClassVar[bool] = False

  def with_setup(self, setup: Setup):
    """The same architecture (same parameter tree) for another capture."""
    return dataclasses.replace(self, setup=setup)

  def physics_operators(self):
    """The physics operators this config's module reads, as an
    :class:`~nlosjax.physics.operator_args.OperatorTable` (traced on shapes; cached).

    Pass it to :func:`~nlosjax.physics.operator_args.bind` or
    :func:`~nlosjax.physics.checks.checked` (``operators=``) so a jitted forward
    or train step takes the operators as an argument instead of constants.
    """
    return _traced_init(self)[1]

  def param_shapes(self):
    """The parameter tree this config's module initialises, as ``jax.ShapeDtypeStruct`` leaves
    (the Flax ``params`` collection; traced on shapes, nothing computed; cached, and shared
    with :meth:`physics_operators`' trace)."""
    return _traced_init(self)[0]

  def replace(self, **changes):
    return dataclasses.replace(self, **changes)

  @property
  def scan_offset(self) -> int:
    """Full-grid index of the first under-scanned point along each axis (``stride // 2``)."""
    return self.stride // 2

  @property
  def input_grid(self) -> tuple[int, int]:
    """``(h, w)`` of the under-scanned input."""
    H, W = self.setup.grid
    return (blocks.underscan_indices(H, self.stride).size, blocks.underscan_indices(W, self.stride).size)

  def input_shape(self, batch: int = 1) -> tuple[int, int, int, int, int]:
    """``(B, F, T, h, w)`` of the network input."""
    return (batch, self.frames, self.setup.num_bins) + self.input_grid

  def check_frames(self, frames, name: str = "frames") -> None:
    """Raise ``ValueError`` naming the mismatch unless ``frames`` is ``[B, F, T, h, w]`` for this config."""
    shape = tuple(getattr(frames, "shape", ()))
    expected = self.input_shape()[1:]
    kind = type(self).__name__
    what = (f"[B, F, T, h, w] = [B, {expected[0]}, {expected[1]}, {expected[2]}, {expected[3]}]"
            f" ({self.frames} frames, {self.setup.num_bins} bins, the {self.setup.grid} grid"
            f" under-scanned by stride {self.stride})")
    if len(shape) != 5:
      raise ValueError(f"{name} must be {what}, got rank {len(shape)} shape {shape}")
    if shape[1] != self.frames:
      raise ValueError(f"{name} has {shape[1]} frames (axis 1) but {kind}.frames is"
                       f" {self.frames}; expected {what}")
    if shape[2] != self.setup.num_bins:
      raise ValueError(f"{name} has {shape[2]} time bins (axis 2) but the Setup has num_bins ="
                       f" {self.setup.num_bins}; expected {what}")
    if shape[3:] != self.input_grid:
      raise ValueError(f"{name} scan grid {shape[3:]} (axes 3, 4) does not match the input grid"
                       f" {self.input_grid}; expected {what}")
    dtype = getattr(frames, "dtype", None)
    if dtype is None or not (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)):
      raise ValueError(f"{name} must be a real array of counts, got dtype {dtype}")


@dataclasses.dataclass(frozen=True)
class ModelConfig(ScanInputConfig):
  """Every hyper-parameter of :class:`STMambaNet` (frozen, hashable: a static module attribute).

  Attributes:
    setup: the full-resolution capture the model reconstructs: output scan
      grid ``(H, W)``, ``T`` bins of ``bin_width``, wall size, optional depth
      range (gates time, crops the volume).
    stride: under-scan stride; the input grid is scan points
      ``stride // 2 + stride * i`` of the Setup's grid (:func:`underscan`).
    frames: ``F`` input frames, odd; the middle one is reconstructed
      (3 = "Ours", 1 = "Ours-S": no cross ST-Mamba).
    variant: SSMs of every block: "st" (temporal then spatial, the paper),
      "s", "t", "tt", "ss" (the ablations of the paper's Table 2), "none" (the
      no-SSM control: every SSM replaced by the identity; each block keeps its
      LayerNorm, projections and SiLU gate).
    temporal_causal: the temporal SSM is causal (False: bidirectional, the
      "causality" ablation of the paper's Table 3).
    width: feature channels ``C`` of stage 1 (ST-Mamba ``d_model``).
    extract_time_stride: time bins merged by interleaved extraction (power of 2).
    extract_blocks: interlaced residual blocks in the extraction.
    dilations: temporal dilations of every interlaced block.
    st_depth: ST-Mamba blocks per frame.
    cross_depth: cross ST-Mamba blocks per neighbour.
    d_state, d_conv, expand, dt_rank: Mamba's ``N``, conv taps, ``d_inner / d_model``,
      dt rank ("auto" = ``ceil(width / 16)``).
    scan_method, scan_chunk: selective-scan kernel ("auto" | "sequential" |
      "associative" | "chunked") and its chunk size (None: the kernel default).
    spread_min_width: smallest channel count of the transposed convs.
    volume_time_stride: time bins merged before the physics layer (power of 2).
    volume_features: channels through the physics layer (channel 0 is the
      recovered transient itself).
    refine_width: channels of the refinement.
    physics: "phasor" (the paper) or "lct".
    lct_snr: Wiener SNR of "lct".
    wavelet_cycles, wavelet_sampling: the phasor wavelet (``cycles``,
      ``sampling_coeff`` of ``illumination_wavelet``).
    physics_oversample: LCT v-bins per time bin (``oversample`` of ``physics.phasor``).
    physics_chunk: feature channels transformed at once (None: all).
    input_norm: per-sample scale of the counts: "rms" (root mean square over
      the frames' time window, the default), "mean" or "max".
    depth_temperature, depth_threshold, depth_softness, background_depth:
      the soft depth projection (:func:`~nlosjax.models.physics_layer.soft_projection`).
    remat: recompute block activations in the backward pass (less memory).
    volume_activation: how the refined volume is made non-negative, "relu"
      (the clamp) or "softplus" (smooth; no dead columns), see
      :class:`~nlosjax.models.blocks.VolumeReconstruction`.
    dtype: activation dtype of the learned layers, "float32" or "bfloat16"
      (parameters, scan state, physics layer and outputs stay float32).
    skip_frames: the measured transient skipped into the spreading stage:
      "middle" (the target frame's counts) or "weighted" (``sum_f w_f x_f``
      over the ``F`` normalised frames, ``w = softmax(skip_frame_logits)``,
      a learned ``[F]`` parameter initialised to zeros, i.e. the frames'
      mean; with ``F = 1`` both are the middle frame and add no parameter).
    conv_impl: how every 3-D convolution is computed (the same sums, float32
      rounding apart): "auto" (the default: "direct" shifted sums for the
      few-channel convolutions -- at the cpu preset the refinement's, a batch-4
      training step 1.2-1.3x faster -- and "fold" elsewhere;
      :func:`~nlosjax.models.conv.resolve_conv_impl`),
      "fold" (the reference: every conv a time-folded 2-D convolution), "direct"
      or "xla" (see :class:`~nlosjax.models.conv.Conv3D`).
    physics_variant: the physics layer's operators, as ``variant`` of
      ``nlosjax.physics.phasor`` / ``lct``: "refined" (ours, the default:
      gated, linear convolution, centred wavelet) or "public" (the public
      code's resampling matrix and wavelet, every bin read; needs
      ``physics_oversample`` 1). On the measured scans of ``real.md``, on the
      networks' 64 ps input, the public phasor scores about 1.2 dB above the
      refined one at 16 x 16 and 0.2 dB at 8 x 8. Added after checkpoints were
      written: those match it at its default (:func:`nlosjax.train.compare_model`).
  """

  setup: Setup
  stride: int = 8
  frames: int = 3
  variant: str = "st"
  temporal_causal: bool = True
  width: int = 32
  extract_time_stride: int = 4
  extract_blocks: int = 2
  dilations: tuple[int, ...] = (1, 2, 4)
  st_depth: int = 2
  cross_depth: int = 1
  d_state: int = 16
  d_conv: int = 4
  expand: int = 2
  dt_rank: int | str = "auto"
  scan_method: str = "auto"
  scan_chunk: int | None = None
  spread_min_width: int = 4
  volume_time_stride: int = 2
  volume_features: int = 4
  refine_width: int = 8
  physics: str = "phasor"
  lct_snr: float = 0.1
  wavelet_cycles: float = 5.0
  wavelet_sampling: float = 2.0
  physics_oversample: int = 1
  physics_chunk: int | None = None
  input_norm: str = "rms"
  depth_temperature: float = 0.05
  depth_threshold: float = 0.1
  depth_softness: float = 0.02
  background_depth: float = 0.0
  remat: bool = False
  dtype: str = "float32"
  volume_activation: str = "relu"
  skip_frames: str = "middle"
  conv_impl: str = "auto"
  physics_variant: str = "refined"

  def __post_init__(self):
    if not isinstance(self.setup, Setup):
      raise ValueError(f"ModelConfig.setup must be a nlosjax.physics.Setup, got {self.setup!r}")
    H, W = self.setup.grid
    stride = _positive_int(self.stride, "stride")
    if stride > min(H, W):
      raise ValueError(f"ModelConfig.stride {stride} exceeds the Setup's grid {self.setup.grid}")
    frames = _positive_int(self.frames, "frames")
    if frames % 2 == 0:
      raise ValueError(f"ModelConfig.frames must be odd (the middle frame is the target), got {frames}")
    if self.variant not in BLOCK_MIXERS:
      raise ValueError(f"ModelConfig.variant must be one of {sorted(BLOCK_MIXERS)}, got {self.variant!r}")
    for name in ("width", "extract_blocks", "st_depth", "d_state", "d_conv", "expand",
                 "spread_min_width", "volume_features", "refine_width"):
      _positive_int(getattr(self, name), name)
    if isinstance(self.cross_depth, bool) or not isinstance(self.cross_depth, int) or self.cross_depth < 0:
      raise ValueError(f"ModelConfig.cross_depth must be an integer >= 0, got {self.cross_depth!r}")
    _power_of_two(self.extract_time_stride, "extract_time_stride")
    _power_of_two(self.volume_time_stride, "volume_time_stride")
    if not self.dilations or any(not isinstance(d, int) or d < 1 for d in self.dilations):
      raise ValueError(f"ModelConfig.dilations must be positive integers, got {self.dilations!r}")
    object.__setattr__(self, "dilations", tuple(self.dilations))
    if self.physics not in physics_layer.PHYSICS_METHODS:
      raise ValueError(f"ModelConfig.physics must be one of {physics_layer.PHYSICS_METHODS}, got {self.physics!r}")
    try:
      check_variant(self.physics_variant)
    except ValueError:
      raise ValueError(f"ModelConfig.physics_variant must be one of {OPERATOR_VARIANTS}, got"
                       f" {self.physics_variant!r}") from None
    if self.physics_variant == "public" and self.physics_oversample != 1:
      raise ValueError("ModelConfig.physics_variant='public' needs physics_oversample=1, got"
                       f" {self.physics_oversample!r}")
    if self.volume_activation not in ("relu", "softplus"):
      raise ValueError("ModelConfig.volume_activation must be 'relu' or 'softplus',"
                       f" got {self.volume_activation!r}")
    if self.skip_frames not in SKIP_FRAMES:
      raise ValueError(f"ModelConfig.skip_frames must be one of {SKIP_FRAMES}, got {self.skip_frames!r}")
    if self.conv_impl not in conv.CONV_IMPLS:
      raise ValueError(f"ModelConfig.conv_impl must be one of {conv.CONV_IMPLS}, got {self.conv_impl!r}")
    if self.input_norm not in INPUT_NORMS:
      raise ValueError(f"ModelConfig.input_norm must be one of {INPUT_NORMS}, got {self.input_norm!r}")
    dtype = self.dtype if isinstance(self.dtype, str) else jnp.dtype(self.dtype).name
    if dtype not in DTYPES:
      raise ValueError(f"ModelConfig.dtype must be one of {sorted(DTYPES)}, got {self.dtype!r}")
    object.__setattr__(self, "dtype", dtype)
    for name in ("depth_temperature", "depth_softness", "lct_snr", "wavelet_cycles"):
      _validate.check_positive(getattr(self, name), f"ModelConfig.{name}")
    if not 0.0 <= self.depth_threshold < 1.0:
      raise ValueError(f"ModelConfig.depth_threshold must be in [0, 1), got {self.depth_threshold!r}")
    # Builds the coarse Setup and the wavelet: a depth range too narrow for the
    # coarse bins, or a wavelet the bins cannot resolve, fails here.
    try:
      _ = self.time_window
    except ValueError as e:
      raise ValueError(f"ModelConfig: the physics layer cannot be built for this Setup: {e}") from None

  # -------------------------------------------------------------- presets
  @classmethod
  def from_setup(cls, setup: Setup, stride: int, **overrides) -> "ModelConfig":
    """A config for ``setup`` under-scanned by ``stride``, defaults elsewhere (see :meth:`paper`)."""
    return cls(setup=setup, stride=stride, **overrides)

  @classmethod
  def paper(cls, setup: Setup | None = None, **overrides) -> "ModelConfig":
    """The paper's shapes: 16 x 16 x 512 in, 128 x 128 out (2 m wall, 33 ps bins), stride 8.

    Widths are ours (the paper gives none): C = 32, N = 16, two ST-Mamba
    blocks, one cross block per neighbour, extraction time stride 4,
    phasor physics at time stride 2 with 4 feature channels, refinement
    width 4 (8 needs ~3 GiB more in the backward pass at 128 x 128 x 256,
    which breaks the 16 GiB CPU budget), rematerialisation on, the physics
    layer one channel at a time: one forward + backward pass fits in 16 GiB
    on CPU (``benchmarks/results/model.md``).
    """
    setup = setup or Setup(wall_size=2.0, grid=(128, 128), bin_width=33e-12, num_bins=512)
    kw = dict(stride=8, frames=3, width=32, extract_time_stride=4, st_depth=2, cross_depth=1,
              d_state=16, volume_time_stride=2, volume_features=4, refine_width=4,
              physics_chunk=1, remat=True)
    kw.update(overrides)
    return cls(setup=setup, **kw)

  @classmethod
  def cpu(cls, setup: Setup | None = None, **overrides) -> "ModelConfig":
    """A small model for tests and examples: 8 x 8 x 128 in, 32 x 32 out (1 m wall, 64 ps bins), stride 4.

    C = 16, N = 8, one ST-Mamba block, one cross block per neighbour,
    extraction time stride 2, phasor physics at time stride 2 on 2 feature
    channels, refinement width 4: one forward + backward pass of a batch of 4
    takes about 1-3 s on 2 CPU cores. Not the ``cpu`` preset's model, which is
    narrower (C = 8, N = 4; ``experiments/configs/cpu.py``).
    """
    setup = setup or Setup(wall_size=1.0, grid=(32, 32), bin_width=64e-12, num_bins=128)
    kw = dict(stride=4, frames=3, width=16, extract_time_stride=2, extract_blocks=1, st_depth=1,
              cross_depth=1, d_state=8, volume_time_stride=2, volume_features=2, refine_width=4)
    kw.update(overrides)
    return cls(setup=setup, **kw)

  # --------------------------------------------------------------- shapes
  @property
  def mixers(self) -> tuple[str, ...]:
    return BLOCK_MIXERS[self.variant]

  @property
  def activation_dtype(self):
    return DTYPES[self.dtype]

  @property
  def coarse_setup(self) -> Setup:
    """The Setup of the physics layer (time merged by ``volume_time_stride``)."""
    return physics_layer.coarsen_setup(self.setup, self.volume_time_stride)

  @property
  def time_window(self) -> tuple[int, int]:
    """``(a, b)``: the time bins the network reads and recovers (``(0, T)`` without a depth range
    or with the public operators)."""
    return physics_layer.volume_window(self.setup, self.volume_time_stride, self.physics,
                                cycles=self.wavelet_cycles, sampling_coeff=self.wavelet_sampling,
                                variant=self.physics_variant)

  def volume_kwargs(self) -> dict:
    """Fields of the :class:`~nlosjax.models.blocks.VolumeReconstruction` stage."""
    return dict(capture=self.setup, time_stride=self.volume_time_stride,
                features=self.volume_features, refine_width=self.refine_width,
                dilations=self.dilations, method=self.physics, snr=self.lct_snr,
                cycles=self.wavelet_cycles, sampling_coeff=self.wavelet_sampling,
                oversample=self.physics_oversample, chunk=self.physics_chunk,
                depth_temperature=self.depth_temperature, depth_threshold=self.depth_threshold,
                depth_softness=self.depth_softness, background_depth=self.background_depth,
                remat=self.remat, activation=self.volume_activation,
                dtype=self.activation_dtype, conv_impl=self.conv_impl,
                variant=self.physics_variant)

  def module(self) -> "STMambaNet":
    """The Flax module of this config."""
    return STMambaNet(self)

  def analytic_flops(self, batch: int) -> tuple[float, float]:
    """``(fft, scan)`` FLOPs of one forward pass that XLA's cost analysis misses."""
    return _analytic_flops(self, batch)


def underscan(transient, stride: int) -> jax.Array:
  """Keep the scan points the model reads: ``[..., T, H, W] -> [..., T, h, w]``.

  Rows and columns ``stride // 2 + stride * i`` (USM's convention: rows 4, 12,
  ..., 124 of 128 for stride 8); matches :attr:`ModelConfig.input_grid`.
  """
  x = jnp.asarray(transient)
  if x.ndim < 3:
    raise ValueError(f"transient must be [..., T, H, W], got shape {x.shape}")
  rows = blocks.underscan_indices(x.shape[-2], stride)
  cols = blocks.underscan_indices(x.shape[-1], stride)
  return x[..., rows[0]::stride, cols[0]::stride][..., :rows.size, :cols.size]


def triplets(frames: np.ndarray, num_frames: int) -> np.ndarray:
  """``[F, T, h, w] -> [F, num_frames, T, h, w]``: each frame with its neighbours, ends replicated.

  Frame ``m`` gets frames ``m - n//2 .. m + n//2`` clipped to ``[0, F - 1]``
  (a static capture, ``F = 1``, repeats its only frame), as the dataset
  loader's ``ends="replicate"``.
  """
  f = frames.shape[0]
  half = num_frames // 2
  idx = np.clip(np.arange(f)[:, None] + np.arange(-half, half + 1)[None, :], 0, f - 1)
  return frames[idx]


def input_scale(x: jax.Array, mode: str) -> jax.Array:
  """Per-sample scale ``[B]`` of counts ``[B, ...]``: root mean square, mean or max.

  Returns 1 where the statistic is 0 (all-zero input), so ``x / scale`` never
  divides by zero; stops gradients (the scale is a statistic of the data).
  """
  x = jax.lax.stop_gradient(x.astype(jnp.float32))
  axes = tuple(range(1, x.ndim))
  if mode == "rms":
    s = jnp.sqrt(jnp.mean(jnp.square(x), axis=axes))
  elif mode == "mean":
    s = jnp.mean(jnp.abs(x), axis=axes)
  elif mode == "max":
    s = jnp.max(jnp.abs(x), axis=axes)
  else:
    raise ValueError(f"mode must be one of {INPUT_NORMS}, got {mode!r}")
  return jnp.where(s > 0, s, 1.0)


class STMambaNet(nn.Module):
  """The ST-Mamba network for dynamic confocal NLOS (see the module docstring).

  Attributes:
    config: a :class:`ModelConfig`.

  Args of ``__call__``:
    frames: ``[B, F, T, h, w]`` photon counts (float or int, >= 0) of ``F``
      adjacent under-scanned frames (:meth:`ModelConfig.input_shape`); the
      middle frame is reconstructed.
  Returns:
    dict of float32 arrays:

    * ``"transient"`` ``[B, T, H, W]``: the recovered full-grid transient of
      the middle frame, in units of ``scale`` (multiply by ``scale`` for
      counts), zero outside :attr:`ModelConfig.time_window`;
    * ``"volume"`` ``[B, Z, H, W]``: hidden volume >= 0 on ``setup.depths``
      (``Z = setup.num_depth_bins``, the depth range only);
    * ``"intensity"`` ``[B, H, W]``: max-projection normalised to [0, 1];
    * ``"depth"`` ``[B, H, W]``: metres, soft-argmax over depth (differentiable;
      ``background_depth`` where the intensity is below ``depth_threshold``);
    * ``"scale"`` ``[B]``: the per-sample input scale (counts per unit).
  Raises:
    ValueError: frames of the wrong rank, frame count, bin count or grid
      (naming which), a non-numeric dtype, or (outside jit) NaN/negative counts.
  """

  config: ModelConfig

  @nn.compact
  def __call__(self, frames):
    cfg = self.config
    cfg.check_frames(frames)
    _validate.check_counts(frames, "frames")
    B, F, T, h, w = frames.shape
    dtype = cfg.activation_dtype
    a, b = cfg.time_window
    x = jnp.asarray(frames, jnp.float32)[:, :, a:b]              # [B, F, Tw, h, w]
    scale = input_scale(x, cfg.input_norm)
    x = x / scale[:, None, None, None, None]
    tw = b - a

    extract = blocks.InterleavedExtraction(cfg.width, cfg.extract_time_stride, cfg.extract_blocks,
                                           cfg.dilations, remat=cfg.remat, dtype=dtype,
                                           conv_impl=cfg.conv_impl, name="extract")
    f = extract(x.reshape(B * F, tw, h, w))                       # [B F, T', h, w, C]
    n_res = cfg.st_depth + (cfg.cross_depth if F > 1 else 0)
    mamba_kw = dict(d_state=cfg.d_state, d_conv=cfg.d_conv, expand=cfg.expand,
                    dt_rank=cfg.dt_rank, mixers=cfg.mixers,
                    temporal_direction="causal" if cfg.temporal_causal else "bidirectional",
                    scan_method=cfg.scan_method, chunk_size=cfg.scan_chunk, n_residuals=n_res,
                    dtype=dtype)
    st_block = conv.maybe_remat(STMambaBlock, cfg.remat)
    for i in range(cfg.st_depth):
      f = st_block(cfg.width, name=f"st_mamba{i}", **mamba_kw)(f)
    f = f.reshape((B, F) + f.shape[1:])
    mid = F // 2
    target = f[:, mid]
    if F > 1 and cfg.cross_depth > 0:
      cross_block = conv.maybe_remat(CrossSTMambaBlock, cfg.remat)
      aligned = []
      for j in range(F):
        if j == mid:
          continue
        tag = f"{'prev' if j < mid else 'next'}{abs(j - mid)}"
        y = target
        for k in range(cfg.cross_depth):
          y = cross_block(cfg.width, name=f"cross_{tag}_{k}", **mamba_kw)(y, f[:, j])
        aligned.append(y.astype(jnp.float32))
      target = target.astype(jnp.float32) + sum(aligned) / len(aligned)

    spread = blocks.TransientSpreading(cfg.setup.grid, cfg.stride, cfg.extract_time_stride,
                                       cfg.spread_min_width, remat=cfg.remat, dtype=dtype,
                                       conv_impl=cfg.conv_impl, name="spread")
    transient_w = spread(target, self._skip(x))                    # [B, Tw, H, W]
    out = blocks.VolumeReconstruction(**cfg.volume_kwargs(), name="volume")(transient_w)
    transient = jnp.pad(transient_w, ((0, 0), (a, T - b), (0, 0), (0, 0)))
    return {"transient": transient, "volume": out["volume"], "intensity": out["intensity"],
            "depth": out["depth"], "scale": scale}


  def _skip(self, x):
    """The measured transient of the spreading stage's skip: ``[B, F, Tw, h, w] -> [B, Tw, h, w]``."""
    F = x.shape[1]
    if self.config.skip_frames == "middle" or F == 1:
      return x[:, F // 2]
    logits = self.param("skip_frame_logits", nn.initializers.zeros, (F,), jnp.float32)
    return jnp.einsum("f,bfthw->bthw", jax.nn.softmax(logits), x)


# ------------------------------------------------------------------ summary
def count_params(params) -> int:
  """Number of scalars in a parameter tree (arrays or ShapeDtypeStructs)."""
  return int(sum(math.prod(v.shape) for v in jax.tree_util.tree_leaves(params)))


def flop_counts(cost, config, batch: int, *, backward: bool) -> tuple[float, float, float]:
  """``(xla, fft, scan)`` FLOPs of one call of ``config``'s model on ``batch`` examples.

  Args:
    cost: ``cost_analysis()`` of the lowered or compiled call (a dict, a
      one-element list of dicts, or None).
    config: the model config (its ``analytic_flops`` adds what XLA does not
      count: FFTs, ``lax.scan`` bodies).
    batch: examples per call.
    backward: the call is a forward + backward pass (FFTs x2, scans x3).
  Returns:
    XLA's count and the FFT and scan estimates, for the whole call.
  """
  if isinstance(cost, (list, tuple)):
    cost = cost[0] if cost else {}
  xla = float((cost or {}).get("flops", 0.0))
  fft, scan = config.analytic_flops(batch)
  if backward:
    fft, scan = 2 * fft, 3 * scan
  return xla, fft, scan


def model_summary(config: ModelConfig, setup: Setup | None = None, *, batch: int = 1,
                  backward: bool = False) -> dict:
  """Parameter count and FLOPs of one forward pass per reconstructed frame, without allocating.

  Any model config with ``module()`` and ``analytic_flops(batch)``
  (:class:`ModelConfig`, :class:`~nlosjax.models.usm.USMConfig`).

  Parameters come from ``jax.eval_shape(model.init, ...)``; FLOPs from XLA's
  cost analysis of the lowered (not compiled, not run) ``apply``, divided by
  ``batch``. XLA counts convolutions, matmuls and elementwise ops; it does
  not count FFTs (custom calls) -- ``fft_flops`` adds them as
  ``2.5 N log2 N`` per real FFT of ``N`` points -- and counts a
  ``lax.scan`` body once (the "sequential" and "chunked" selective scans:
  ``scan_flops`` adds ``9 L D N`` per scan direction, Mamba's count; 0 for
  "associative", which XLA counts). Estimates, not measurements.

  Args:
    config: the model.
    setup: summarise the same weights on this Setup instead of ``config.setup``.
    batch: batch size to lower with (results are per frame).
    backward: also count a backward pass (``value_and_grad`` of the output sum).
  Returns:
    dict with ``params``, ``flops`` (XLA + FFT + scan estimates, per frame),
    ``xla_flops``, ``fft_flops``, ``scan_flops``, ``input_shape``,
    ``output_shapes``, ``time_window`` and ``config``.
  """
  if setup is not None:
    config = config.with_setup(setup)
  model = config.module()
  x = jax.ShapeDtypeStruct(config.input_shape(batch), jnp.float32)
  variables = jax.eval_shape(model.init, jax.random.key(0), x)
  outputs = jax.eval_shape(model.apply, variables, x)

  if backward:
    def fn(v, xx):
      def loss(p):
        o = model.apply({**v, "params": p}, xx)
        return sum(jnp.sum(o[k]) for k in ("transient", "volume", "intensity", "depth"))
      return jax.value_and_grad(loss)(v["params"])
  else:
    fn = model.apply
  lowered = jax.jit(fn).lower(variables, x)
  xla, fft, scan = flop_counts(lowered.cost_analysis(), config, batch, backward=backward)
  return {
      "params": count_params(variables["params"]),
      "flops": (xla + fft + scan) / batch,
      "xla_flops": xla / batch,
      "fft_flops": fft / batch,
      "scan_flops": scan / batch,
      "input_shape": tuple(x.shape),
      "output_shapes": {k: tuple(v.shape) for k, v in outputs.items()},
      "time_window": config.time_window,
      "config": config,
  }


def _analytic_flops(config: ModelConfig, batch: int) -> tuple[float, float]:
  """FFT and selective-scan FLOPs of one forward pass that XLA's cost analysis misses."""
  cs = config.coarse_setup
  if config.physics_variant == "public":                     # the public full circular box
    dom = public_lct_domain(cs)
  else:
    dom = lct_domain(cs, oversample=config.physics_oversample,
                     fft_length=physics_layer.physics_fft_length(config.physics))
  n = math.prod(dom.fft_shape)
  per_apply = 2 * 2.5 * n * math.log2(n)                     # rfftn + irfftn
  applies = 2 if config.physics == "phasor" else 1
  fft = batch * config.volume_features * applies * per_apply
  a, b = config.time_window
  tw = b - a
  tp = -(-tw // config.extract_time_stride)
  h, w = config.input_grid
  d_inner, N = config.expand * config.width, config.d_state
  tokens = batch * tp * h * w
  per_block = sum(1 if m == "temporal" and config.temporal_causal else 2 for m in config.mixers)
  n_blocks = config.frames * config.st_depth + 2 * (config.frames - 1) * config.cross_depth
  scan = 9.0 * tokens * d_inner * N * per_block * n_blocks
  method = resolve_method(config.scan_method, size=tokens * d_inner * N)
  if method == "associative":                                # no lax.scan: XLA counts it
    scan = 0.0
  return fft, scan


def format_summary(summary: dict) -> str:
  """One line per figure of :func:`model_summary`, for logs."""
  cfg = summary["config"]
  variant = f"; variant {cfg.variant}" if hasattr(cfg, "variant") else ""
  return "\n".join([
      f"{type(cfg.module()).__name__}: {summary['params']:,} parameters;"
      f" {summary['flops'] / 1e9:.2f} GFLOP per frame"
      f" (XLA {summary['xla_flops'] / 1e9:.2f}, FFT {summary['fft_flops'] / 1e9:.2f},"
      f" scan {summary['scan_flops'] / 1e9:.2f})",
      f"  input {summary['input_shape']} -> "
      + ", ".join(f"{k} {v}" for k, v in summary["output_shapes"].items()),
      f"  setup {cfg.setup}; stride {cfg.stride}; frames {cfg.frames}{variant};"
      f" time window {summary['time_window']}",
  ])

"""LFE, the learned feature embeddings of Chen et al. (SIGGRAPH Asia 2020), in Flax linen.

A baseline of the paper's Table 1, run as the paper runs it: not made for
under-scanned scans, it reads the sparse scan interpolated to the full grid
(as the classic methods do). One static frame; no temporal path. The
architecture is that of the public code (``DeepVoxels`` of the authors'
``DL_inference/network7_256``), built from the parts USM took from it
(:mod:`nlosjax.models.usm`: USM is LFE with a transient recovery network in
front and a refinement after the transform), in this project's conventions:

1. **Interpolation**: the ``h x w`` under-scanned counts (divided by their
   per-sample root mean square, as Ours and USM) are interpolated bilinearly
   onto the full ``H x W`` grid (:func:`nlosjax.models.blocks.interpolation_matrix`,
   the classic methods' interpolation in the paper's protocol).
2. **Feature extraction** on the min-max normalised transient
   (:class:`~nlosjax.models.usm.Extraction`, LFE's ``Transient2volumn``): a
   learnable ``3 x 3 x 3`` stride-2 kernel initialised to ``2 x 2 x 2``
   averaging beside a stride-2 conv to ``extract_width`` channels + two
   residual blocks: ``[B, T/2, H/2, W/2, 1 + extract_width]``.
3. **Feature transform**: each channel through
   :class:`~nlosjax.models.physics_layer.FeatureTransform` (``method``: LFE's
   ``diffmodule`` offers LCT, f-k and phasor; default LCT, Wiener ``snr``,
   ``t^4``) on :func:`~nlosjax.models.usm.half_setup`, clamped at 0, min-max
   normalised per channel. Nothing is refined after it (LFE's ``VisibleNet``
   with ``layernum = 0``).
4. **Projection**: max over depth (``C`` intensity features) and
   ``(Z - 1 - argmax) / (Z - 1)`` (``C`` depth features, nearer is larger, no
   gradient through argmax).
5. **Two rendering heads** (:class:`~nlosjax.models.usm.Rendering`, LFE's
   ``Rendering``): widths ``2 C`` and ``4 C`` as LFE's ``nf0`` and ``2 nf0``.
   The intensity is clamped to ``[0, 1]`` as LFE's forward clamps it; the
   depth head is not (it is trained in metres with Ours' loss).

At ``extract_width = 3`` the parameter count is 28,413: the extraction's
1,095 and two heads of 13,659 (the counts of USM's same parts). Differences
from the public code, each for a reason: Flax's default initialisation; the
input divided by its root mean square; no fixed 100/128 depth crop (the
Setup's ``depth_range`` crops); the interpolated input in place of LFE's full
scan, as the paper's protocol feeds every baseline not made for sparse scans.
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.models import blocks, physics_layer
from nlosjax.models.network import INPUT_NORMS, ScanInputConfig
from nlosjax.models.usm import HalfResolutionShapes, project_and_render, scaled_input, transformed_features
from nlosjax.physics import _validate
from nlosjax.physics.operators import check_falloff
from nlosjax.physics.setup import Setup

__all__ = ["LFEConfig", "LFENet", "PHYSICS", "interpolate_scan"]

#: Feature transforms LFE's ``diffmodule`` offers that our physics layer computes.
PHYSICS = ("lct", "phasor")


@dataclasses.dataclass(frozen=True)
class LFEConfig(HalfResolutionShapes, ScanInputConfig):
  """Every hyper-parameter of :class:`LFENet` (frozen, hashable).

  Attributes:
    setup: the full-resolution capture (square grid, ``H``, ``W`` and ``T`` even).
    stride: under-scan stride (input scan points ``stride // 2 + stride * i``).
    frames: always 1 (LFE reconstructs one static frame).
    extract_width: conv channels of the feature extraction (LFE ``nf0``; 3 as USM).
    physics: the feature transform, ``"lct"`` or ``"phasor"``.
    lct_snr: Wiener SNR of the LCT transform (0.1, as LFE and USM).
    falloff: radiometric falloff of the LCT transform ("diffuse": ``t^4``).
    input_norm: per-sample scale of the counts (as :class:`~nlosjax.models.network.ModelConfig`).
    wavelet_cycles, wavelet_sampling: the illumination wavelet of the phasor
      transform and of the phasor-field loss.
  """

  setup: Setup
  stride: int = 4
  frames: int = 1
  extract_width: int = 3
  physics: str = "lct"
  lct_snr: float = 0.1
  falloff: str = "diffuse"
  input_norm: str = "rms"
  wavelet_cycles: float = 5.0
  wavelet_sampling: float = 2.0

  def __post_init__(self):
    if not isinstance(self.setup, Setup):
      raise ValueError(f"LFEConfig.setup must be a nlosjax.physics.Setup, got {self.setup!r}")
    H, W = self.setup.grid
    if H != W or H % 2 or H < 4 or self.setup.num_bins % 2:
      raise ValueError("LFE halves time and space once and needs a square grid: H = W even (>= 4)"
                       f" and T even, got grid {self.setup.grid} and {self.setup.num_bins} bins")
    if isinstance(self.stride, bool) or not isinstance(self.stride, (int, np.integer)) \
        or not 1 <= self.stride <= H // 2:
      raise ValueError(f"LFEConfig.stride must be an integer in [1, {H // 2}] (two scan points a"
                       f" side to interpolate between), got {self.stride!r}")
    if self.frames != 1:
      raise ValueError(f"LFEConfig.frames must be 1 (LFE reconstructs one frame), got {self.frames!r}")
    v = self.extract_width
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
      raise ValueError(f"LFEConfig.extract_width must be a positive integer, got {v!r}")
    if self.physics not in PHYSICS:
      raise ValueError(f"LFEConfig.physics must be one of {PHYSICS}, got {self.physics!r}")
    _validate.check_positive(self.lct_snr, "LFEConfig.lct_snr")
    check_falloff(self.falloff)
    if self.input_norm not in INPUT_NORMS:
      raise ValueError(f"LFEConfig.input_norm must be one of {INPUT_NORMS}, got {self.input_norm!r}")

  def module(self) -> "LFENet":
    """The Flax module of this config."""
    return LFENet(self)

  @property
  def render_widths(self) -> tuple[int, int]:
    """The rendering heads' conv widths, ``(2 C, 4 C)`` (LFE's ``nf0`` and ``2 nf0``)."""
    return (2 * self.channels, 4 * self.channels)



def interpolate_scan(x: jax.Array, grid: tuple[int, int], stride: int) -> jax.Array:
  """``[..., T, h, w] -> [..., T, H, W]``: bilinear from the scan points, nearest sample past the ends."""
  my = jnp.asarray(blocks.interpolation_matrix(grid[0], stride), jnp.float32)
  mx = jnp.asarray(blocks.interpolation_matrix(grid[1], stride), jnp.float32)
  if tuple(x.shape[-2:]) != (my.shape[1], mx.shape[1]):
    raise ValueError(f"samples must be [..., T, {my.shape[1]}, {mx.shape[1]}] for grid {grid} at"
                     f" stride {stride}, got shape {x.shape}")
  return jnp.einsum("Hh,...hw,Ww->...HW", my, x, mx)


class LFENet(nn.Module):
  """LFE for one under-scanned frame (see the module docstring).

  Attributes:
    config: an :class:`LFEConfig`.

  Args of ``__call__``:
    frames: ``[B, 1, T, h, w]`` photon counts (float or int, >= 0).
  Returns:
    dict of float32 arrays:

    * ``"transient"`` ``[B, T, H, W]``: the interpolated input, in units of
      ``scale`` (what the network reads; nothing learned produces it);
    * ``"volume"`` ``[B, Z, H, W]``: feature channel 0's volume (the pooled
      transient through the transform) on ``setup.depths`` and the full grid;
    * ``"feature_volume"`` ``[B, Zc, H/2, W/2, C]``: the normalised transformed
      features on :func:`~nlosjax.models.usm.half_setup`'s depths;
    * ``"intensity"`` ``[B, H, W]``: the intensity head, clamped to ``[0, 1]``;
    * ``"depth"`` ``[B, H, W]``: the depth head (not clamped);
    * ``"scale"`` ``[B]``: the per-sample input scale.
  Raises:
    ValueError: frames of the wrong shape or dtype, or (outside jit) NaN or
      negative counts.
  """

  config: LFEConfig

  @nn.compact
  def __call__(self, frames):
    cfg = self.config
    x, scale = scaled_input(cfg, frames)                                # [B, T, h, w], [B]
    dense = interpolate_scan(x, cfg.setup.grid, cfg.stride)
    coarse = cfg.coarse_setup
    transform = physics_layer.FeatureTransform(
        coarse, cfg.physics, snr=cfg.lct_snr, falloff=cfg.falloff, cycles=cfg.wavelet_cycles,
        sampling_coeff=cfg.wavelet_sampling, name="transform")
    vol = transformed_features(dense, cfg.extract_width, transform)     # [B, Zc, h2, w2, C]
    intensity, depth, volume = project_and_render(vol, cfg.render_widths, coarse, cfg.setup)
    return {"transient": dense, "volume": volume, "feature_volume": vol,
            "intensity": jnp.clip(intensity, 0.0, 1.0), "depth": depth, "scale": scale}

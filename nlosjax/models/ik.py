"""I-K, the learnable inverse kernel with attention of Yu et al. (ICCV 2023): an approximation in Flax linen.

A baseline of the paper's Table 1 ("physics-based", 23.22 dB there). Its code
and full text are not available to this project; what is public is its
abstract and project page: a 3D CNN turns the raw transient into downsampled
spatio-temporal features; these are mapped to the Fourier domain and
multiplied by a learnable inverse kernel, a Fourier volume initialised from a
physics kernel, giving spatial features for the rendering that follows; an
attention mechanism steers the kernel's learning toward the high frequencies
a network learns last. This module builds that pipeline from this project's
parts, so it is **an approximation labelled as one**, not a reimplementation.
It reads the sparse scan interpolated to the full grid, as the paper feeds
every baseline not made for sparse scans, and shares LFE's ends
(:mod:`nlosjax.models.lfe`):

1. **Interpolation** and **feature extraction** as LFE's: ``[B, T/2, H/2, W/2, C]``
   with ``C = 1 + extract_width``.
2. **The learnable inverse kernel** (:class:`LearnableInverseKernel`): each
   feature channel goes through LCT's ``t^4``-weighted resampling ``t -> v``,
   the 3D FFT, a multiplication by the kernel ``K``, the inverse FFT and the
   resampling to depth, clamped at 0 (LCT's computation with ``K`` in place of
   its Wiener filter). ``K = K_phys + s * (d_re + i d_im)``: ``K_phys`` is LCT's
   Wiener filter ``conj(F) / (|F|^2 + 1/snr)`` on the coarse Setup, ``s`` its
   largest modulus, and ``d`` a learnable Fourier volume ``[2H', W' + 1, Lv]``
   initialised to 0 (so the kernel starts as the physics one, and the
   optimiser's weight decay pulls it back toward it; every frequency can be
   learned, including those the Wiener filter suppresses).
3. **Attention over frequency bands** (our reading of the attention-guided
   kernel learning): from each sample's features (mean and maximum of every
   channel), a two-layer MLP gives each channel a gain in ``(0, 2)`` for each of
   ``bands`` radial frequency bands (hat functions over the normalised frequency
   radius, summing to 1); the channel's kernel is multiplied by that gain
   profile. The last layer starts at 0: every gain starts at 1.
4. **Projection and rendering heads** as LFE's, the intensity clamped to ``[0, 1]``.

At the ``cpu`` preset (``extract_width`` 3, coarse grid 16 x 16 over 64 bins)
the kernel volume holds most of the parameters (:func:`IKConfig.kernel_shape`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.models import physics_layer
from nlosjax.models.lfe import LFEConfig, interpolate_scan
from nlosjax.models.usm import project_and_render, scaled_input, transformed_features
from nlosjax.physics.operators import lct_apply, lct_filter, to_depth
from nlosjax.physics.setup import Setup

__all__ = ["IKConfig", "IKNet", "LearnableInverseKernel", "band_weights"]


@dataclasses.dataclass(frozen=True)
class IKConfig(LFEConfig):
  """Every hyper-parameter of :class:`IKNet` (frozen, hashable): :class:`~nlosjax.models.lfe.LFEConfig`'s and

  Attributes:
    bands: radial frequency bands of the attention (>= 2).
    attention_width: hidden units of the attention MLP.

  ``physics`` must be ``"lct"`` (the kernel learned is LCT's inverse filter).
  """

  bands: int = 4
  attention_width: int = 8

  #: The learned kernel is a Fourier volume of the coarse grid and bins (:meth:`kernel_shape`).
  params_depend_on_setup: ClassVar[bool] = True

  def __post_init__(self):
    super().__post_init__()
    if self.physics != "lct":
      raise ValueError(f"IKConfig.physics must be 'lct' (I-K learns LCT's inverse kernel), got {self.physics!r}")
    for name, low in (("bands", 2), ("attention_width", 1)):
      v = getattr(self, name)
      if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
        raise ValueError(f"IKConfig.{name} must be an integer >= {low}, got {v!r}")

  def module(self) -> "IKNet":
    """The Flax module of this config."""
    return IKNet(self)

  def kernel_shape(self) -> tuple[int, int, int]:
    """``(2 H', W' + 1, Lv)``: the learnable kernel volume's shape on the coarse Setup."""
    return tuple(_transform(self).operators().psf_fft.shape)


def band_weights(shape: tuple[int, int, int], bands: int) -> np.ndarray:
  """``[bands, *shape]`` float32 hat functions of the normalised frequency radius of a filter grid.

  ``shape = (2H, W + 1, Lv)``: a full FFT of length ``2H``, a real FFT of length ``2W``
  and a full FFT of length ``Lv`` (the layout of LCT's filters). The radius is
  ``sqrt(fy^2 + fx^2 + fv^2)`` in cycles per sample, divided by its largest value
  ``sqrt(3) / 2``: 0 at the DC term, 1 at the corner. Band ``k`` peaks at radius
  ``k / (bands - 1)``; at every frequency the weights sum to 1.
  """
  h2, wr, lv = shape
  fy = np.fft.fftfreq(h2)[:, None, None]
  fx = np.fft.rfftfreq(2 * (wr - 1))[None, :, None]
  fv = np.fft.fftfreq(lv)[None, None, :]
  radius = np.sqrt(fy ** 2 + fx ** 2 + fv ** 2) / (math.sqrt(3.0) / 2)
  centres = np.linspace(0.0, 1.0, bands)[:, None, None, None]
  return np.maximum(0.0, 1.0 - np.abs(radius[None] - centres) * (bands - 1)).astype(np.float32)


class LearnableInverseKernel(physics_layer.FeatureTransform):
  """LCT with a learnable inverse kernel and per-sample band gains (module docstring, steps 2 and 3).

  Attributes (beyond :class:`~nlosjax.models.physics_layer.FeatureTransform`'s, whose
  ``method`` is ``"lct"`` here and whose ``variant`` must be ``"refined"``):
    bands: radial frequency bands of the attention.
    attention_width: hidden units of the attention MLP.

  Args of ``__call__``:
    x: ``[B, Nt, H, W, C]`` real features on ``capture``'s time bins
      ``[time_offset, time_offset + Nt)``, covering :meth:`window`.
    time_offset: first time bin of ``x`` (static int).
  Returns:
    ``[B, Z, H, W, C]`` float32 >= 0 on ``capture.depths``.
  Params:
    ``kernel_re``, ``kernel_im`` ``[2H, W + 1, Lv]`` (the learned part ``d``, zeros at
    init), and the attention MLP's ``attention_hidden`` and ``attention_gain``.
  """

  method: str = "lct"
  bands: int = 4
  attention_width: int = 8

  @nn.compact
  def __call__(self, x, time_offset: int = 0):
    if self.method != "lct" or self.variant != "refined":
      raise ValueError("LearnableInverseKernel learns the refined LCT's filter: method 'lct',"
                       f" variant 'refined', got {self.method!r}, {self.variant!r}")
    if not isinstance(self.capture, Setup):
      raise ValueError(f"capture must be a nlosjax.physics.Setup, got {type(self.capture).__name__}")
    if x.ndim != 5 or tuple(x.shape[2:4]) != self.capture.grid:
      raise ValueError(f"x must be [B, Nt, H, W, C] with (H, W) = {self.capture.grid}, got shape {x.shape}")
    a, b = self.window()
    if not (time_offset <= a and b <= time_offset + x.shape[1]):
      raise ValueError(f"x covers time bins [{time_offset}, {time_offset + x.shape[1]}) but the"
                       f" kernel reads [{a}, {b}) of {self.capture}")
    ops = self.operators()
    t0, t1 = ops.domain.t
    bsz, _, H, W, C = x.shape
    physics = lct_filter(ops, self.snr)                               # [2H, W + 1, Lv] complex
    scale = jnp.max(jnp.abs(physics))
    d_re = self.param("kernel_re", nn.initializers.zeros, physics.shape, jnp.float32)
    d_im = self.param("kernel_im", nn.initializers.zeros, physics.shape, jnp.float32)
    kernel = physics + scale * jax.lax.complex(d_re, d_im)
    # Attention: per sample and channel, a gain in (0, 2) per frequency band (1 at init).
    x = x.astype(jnp.float32)
    pooled = jnp.concatenate([jnp.mean(x, axis=(1, 2, 3)), jnp.max(x, axis=(1, 2, 3))], axis=-1)   # [B, 2C]
    hidden = nn.relu(nn.Dense(self.attention_width, name="attention_hidden")(pooled))
    logits = nn.Dense(C * self.bands, kernel_init=nn.initializers.zeros, name="attention_gain")(hidden)
    gains = 2.0 * jax.nn.sigmoid(logits.reshape((bsz * C, self.bands)))        # [B C, bands]
    weights = jnp.asarray(band_weights(tuple(physics.shape), self.bands))       # [bands, 2H, W + 1, Lv]
    xs = jnp.moveaxis(x[:, a - time_offset:b - time_offset], -1, 1).reshape((bsz * C, b - a, H, W))

    def one(xi, gain):
      profile = jnp.tensordot(gain, weights, axes=1)                  # [2H, W + 1, Lv] real
      return jnp.maximum(to_depth(lct_apply(xi[t0 - a:t1 - a], ops, kernel * profile), ops), 0.0)

    vol = jax.vmap(one)(xs, gains)                                    # [B C, Z, H, W]
    return jnp.moveaxis(vol.reshape((bsz, C) + vol.shape[1:]), 1, -1)


def _transform(cfg: IKConfig, name: str | None = None) -> LearnableInverseKernel:
  return LearnableInverseKernel(cfg.coarse_setup, snr=cfg.lct_snr, falloff=cfg.falloff,
                                bands=cfg.bands, attention_width=cfg.attention_width, name=name)


class IKNet(nn.Module):
  """I-K (approximation) for one under-scanned frame (see the module docstring).

  Attributes:
    config: an :class:`IKConfig`.

  Args of ``__call__``:
    frames: ``[B, 1, T, h, w]`` photon counts (float or int, >= 0).
  Returns:
    dict of float32 arrays, as :class:`~nlosjax.models.lfe.LFENet`'s: ``"transient"``
    ``[B, T, H, W]`` (the interpolated input in units of ``scale``), ``"volume"``
    ``[B, Z, H, W]``, ``"feature_volume"`` ``[B, Zc, H/2, W/2, C]``, ``"intensity"``
    ``[B, H, W]`` in ``[0, 1]``, ``"depth"`` ``[B, H, W]``, ``"scale"`` ``[B]``.
  Raises:
    ValueError: frames of the wrong shape or dtype, or (outside jit) NaN or negative counts.
  """

  config: IKConfig

  @nn.compact
  def __call__(self, frames):
    cfg = self.config
    x, scale = scaled_input(cfg, frames)                                # [B, T, h, w], [B]
    dense = interpolate_scan(x, cfg.setup.grid, cfg.stride)
    vol = transformed_features(dense, cfg.extract_width, _transform(cfg, name="transform"))
    intensity, depth, volume = project_and_render(vol, cfg.render_widths, cfg.coarse_setup, cfg.setup)
    return {"transient": dense, "volume": volume, "feature_volume": vol,
            "intensity": jnp.clip(intensity, 0.0, 1.0), "depth": depth, "scale": scale}

"""Spatial-temporal Mamba blocks (paper Sec. 4.2, Fig. 4).

Activations are ``[B, T, h, w, C]`` (time steps, scan rows, scan columns,
channels). Two kinds of SSM act on them, both Mamba v1 selective scans
(:func:`nlosjax.ssm.selective_scan`) with Mamba's parametrisation and
initialisation (:mod:`nlosjax.ssm.mamba`):

* the *temporal* SSM runs along ``T`` for every scan point, causally (a causal
  depthwise conv then a causal scan): output step ``t`` depends on steps
  ``<= t`` only, as a histogram is causal;
* the *spatial* SSM runs over the ``h * w`` scan points of every time step,
  flattened row-major, bidirectionally (Vision Mamba v2: a forward and a
  reverse branch with their own conv, projections, ``A`` and ``D``, averaged),
  since scan points have no causal order.

:class:`STMambaBlock` (Fig. 4a): ``x + out_proj(SSM_s(SSM_t(xs)) * SiLU(z))``
with ``(xs, z) = in_proj(LayerNorm(x))``: one input projection, the temporal
SSM, the spatial SSM, one gate from the input, one output projection. The
ablations of the paper's Table 2 replace the pair (temporal, spatial) by
(spatial,), (temporal,), (temporal, temporal) or (spatial, spatial).

:class:`CrossSTMambaBlock` (Fig. 4b): the reference features and the
neighbour features each run through their own projection and SSM chain; both
outputs are modulated by the *same* gate ``SiLU(z_ref)`` from the reference
input, averaged (the Vim halving that keeps magnitudes), projected, and added
to the reference (shortcut).

Properties that hold by construction (and are tested): the temporal path is
causal in time when ``temporal_direction="causal"`` (LayerNorm, projections
and gate are per position, the spatial SSM mixes only within a time step); a
block is equivariant to the 180-degree rotation of the scan grid (the reversal
of the row-major sequence) when the forward and reverse spatial branches swap
parameters (:func:`mirror_spatial_params`).
"""

from __future__ import annotations

import math
from typing import Any

import flax.linen as nn
import jax.numpy as jnp

from nlosjax.ssm.mamba import MixerWidths, SelectiveSSM, mirror_params, torch_default_init

MIXERS = ("temporal", "spatial", "identity")
# The SSMs of each ST-Mamba block, by ``ModelConfig.variant``.
BLOCK_MIXERS = {
    "st": ("temporal", "spatial"),   # the paper: T-Mamba then S-Mamba
    "s": ("spatial",),               # Table 2 "S-Mamba -"
    "t": ("temporal",),              # Table 2 "- T-Mamba"
    "tt": ("temporal", "temporal"),  # Table 2 "T-Mamba T-Mamba"
    "ss": ("spatial", "spatial"),    # Table 2 "S-Mamba S-Mamba"
    "none": ("identity",),           # control: every SSM replaced by the identity
}


def apply_temporal(ssm: SelectiveSSM, x):
  """Run ``ssm`` along time: ``[B, T, h, w, D]`` as ``B h w`` sequences of length ``T``."""
  y = ssm(jnp.moveaxis(x, 1, -2))             # [B, h, w, T, D]
  return jnp.moveaxis(y, -2, 1)


def apply_spatial(ssm: SelectiveSSM, x):
  """Run ``ssm`` over the scan grid: ``[B, T, h, w, D]`` as ``B T`` row-major sequences of ``h w``."""
  b, t, h, w, d = x.shape
  return ssm(x.reshape(b, t, h * w, d)).reshape(b, t, h, w, d)


class _SSMChain(nn.Module):
  """The SSMs of one branch in order (``mixers``), each a :class:`SelectiveSSM`."""

  d_inner: int
  mixers: tuple[str, ...]
  d_state: int
  d_conv: int
  dt_rank: int
  temporal_direction: str
  scan_method: str
  chunk_size: int | None
  dtype: Any
  param_dtype: Any

  @nn.compact
  def __call__(self, x):
    for i, kind in enumerate(self.mixers):
      if kind not in MIXERS:
        raise ValueError(f"mixers must be drawn from {MIXERS}, got {self.mixers!r}")
      if kind == "identity":  # the no-SSM control: the block keeps its norm, projections and gate
        continue
      direction = self.temporal_direction if kind == "temporal" else "bidirectional"
      ssm = SelectiveSSM(self.d_inner, d_state=self.d_state, d_conv=self.d_conv, dt_rank=self.dt_rank,
                         direction=direction, scan_method=self.scan_method, chunk_size=self.chunk_size,
                         dtype=self.dtype, param_dtype=self.param_dtype, name=f"{kind}{i}")
      x = apply_temporal(ssm, x) if kind == "temporal" else apply_spatial(ssm, x)
    return x


class _BlockBase(MixerWidths):
  """Fields shared by the two blocks (their widths: :class:`~nlosjax.ssm.mamba.MixerWidths`)."""

  mixers: tuple[str, ...] = ("temporal", "spatial")
  temporal_direction: str = "causal"
  scan_method: str = "auto"
  chunk_size: int | None = None
  n_residuals: int = 1
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32

  def _check(self, x, name: str):
    if x.ndim != 5 or x.shape[-1] != self.d_model:
      raise ValueError(f"{name} must be [B, T, h, w, C={self.d_model}], got shape {x.shape}")
    if not self.mixers or any(m not in MIXERS for m in self.mixers):
      raise ValueError(f"mixers must be a non-empty sequence drawn from {MIXERS}, got {self.mixers!r}")
    if self.temporal_direction not in ("causal", "bidirectional"):
      raise ValueError("temporal_direction must be 'causal' or 'bidirectional',"
                       f" got {self.temporal_direction!r}")

  def _chain(self, name: str) -> _SSMChain:
    return _SSMChain(self.d_inner, tuple(self.mixers), self.d_state, self.d_conv, self.rank,
                     self.temporal_direction, self.scan_method, self.chunk_size, self.dtype,
                     self.param_dtype, name=name)

  def _dense(self, features: int, name: str, scale: float = 1.0) -> nn.Dense:
    return nn.Dense(features, use_bias=False, kernel_init=torch_default_init(scale),
                    dtype=self.dtype, param_dtype=self.param_dtype, name=name)


class STMambaBlock(_BlockBase):
  """ST-Mamba block: ``x + out_proj(SSMs(xs) * SiLU(z))``, ``(xs, z) = in_proj(LayerNorm(x))``.

  Attributes:
    d_model: channels ``C``.
    d_state, d_conv, expand, dt_rank: Mamba's (``d_inner = expand C``; dt_rank
      "auto" is ``ceil(C / 16)``).
    mixers: the SSMs in order, from "temporal" and "spatial" (see ``BLOCK_MIXERS``).
    temporal_direction: "causal" (the paper) or "bidirectional" (the
      non-causal ablation of the paper's Table 3).
    scan_method, chunk_size: of :func:`nlosjax.ssm.selective_scan`.
    n_residuals: the output projection's init is divided by ``sqrt(n_residuals)``.

  ``[B, T, h, w, C] -> [B, T, h, w, C]`` in ``dtype`` (scan state float32).
  """

  @nn.compact
  def __call__(self, x):
    self._check(x, "x")
    h = nn.LayerNorm(dtype=self.dtype, param_dtype=self.param_dtype, name="norm")(x)
    xs, z = jnp.split(self._dense(2 * self.d_inner, "in_proj")(h), 2, axis=-1)
    y = self._chain("ssm")(xs)
    y = y * nn.silu(z)
    out = self._dense(self.d_model, "out_proj", 1.0 / math.sqrt(self.n_residuals))(y)
    return x.astype(out.dtype) + out


class CrossSTMambaBlock(_BlockBase):
  """Cross ST-Mamba block: align neighbour features to the reference through a shared gate.

  ``y = out_proj(((SSMs_r(xr) + SSMs_n(xn)) / 2) * SiLU(z))`` with ``(xr, z) =
  in_proj_ref(LayerNorm_r(ref))`` and ``xn = in_proj_nb(LayerNorm_n(nb))``;
  returns ``ref + y``. Fields as :class:`STMambaBlock`.

  ``(ref, nb)`` both ``[B, T, h, w, C]`` -> ``[B, T, h, w, C]``.
  """

  @nn.compact
  def __call__(self, ref, nb):
    self._check(ref, "ref")
    self._check(nb, "nb")
    if ref.shape != nb.shape:
      raise ValueError(f"ref and nb must have the same shape, got {ref.shape} and {nb.shape}")
    kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
    hr = nn.LayerNorm(name="norm_ref", **kw)(ref)
    hn = nn.LayerNorm(name="norm_nb", **kw)(nb)
    xr, z = jnp.split(self._dense(2 * self.d_inner, "in_proj_ref")(hr), 2, axis=-1)
    xn = self._dense(self.d_inner, "in_proj_nb")(hn)
    yr = self._chain("ssm_ref")(xr)
    yn = self._chain("ssm_nb")(xn)
    y = (0.5 * (yr.astype(jnp.float32) + yn.astype(jnp.float32))).astype(yr.dtype) * nn.silu(z)
    out = self._dense(self.d_model, "out_proj", 1.0 / math.sqrt(self.n_residuals))(y)
    return ref.astype(out.dtype) + out


def mirror_spatial_params(params):
  """Swap the forward and reverse parameters of every bidirectional SSM in a param tree.

  With the swapped parameters, a block applied to the 180-degree-rotated scan
  grid (``x[:, :, ::-1, ::-1]``) returns the rotated output of the original
  block and parameters (:func:`nlosjax.ssm.mamba.mirror_params`). Causal SSMs are
  left as they are. Returns plain dicts.
  """
  return mirror_params(params)

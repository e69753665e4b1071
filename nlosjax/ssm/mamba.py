"""Flax linen Mamba v1: :class:`SelectiveSSM` (the SSM, the library's one) and :class:`MambaMixer`.

:class:`MambaMixer` is Mamba's block: projections and gate around a :class:`SelectiveSSM`
(its parameters ``in_proj``, ``ssm/...``, ``out_proj``). For an input ``u`` ``[..., L, d_model]``
(``d_inner = expand * d_model``):

    x, z   = split(in_proj(u))                          # [..., L, d_inner] each
    x'     = SiLU(conv(x))                              # depthwise, d_conv taps
    d, B, C = split(x_proj(x'))                         # dt_rank, N, N
    dt     = softplus(d W_dt + b_dt)                    # float32
    y      = selective_scan(x', dt, -exp(A_log), B, C, D)
    out    = out_proj(y * SiLU(z))

``direction="bidirectional"`` runs a second branch with ``reverse=True`` (its
conv anti-causal) and averages the two before the gate, exactly Vision Mamba's
``bimamba_type="v2"`` with ``if_divide_out=True`` (Zhu et al. 2024,
arXiv:2401.09417): separate conv, x_proj, dt_proj, A_log and D per direction,
shared in_proj and out_proj (``share_params=True`` shares all of them).

Initialisation follows Mamba (state-spaces/mamba ``mamba_simple.py`` and
``mixer_seq_simple._init_weights``), not Flax defaults:

* in_proj, x_proj and the depthwise conv: PyTorch's default ``U(+-1/sqrt(fan_in))``
  (fan_in of the conv = d_conv); in_proj/out_proj biases (``bias=True``) zero; the
  conv bias ``U(+-1/sqrt(d_conv))``.
* dt_proj kernel ``U(+-dt_rank^-0.5 dt_scale)`` (``dt_init="random"``) or that
  constant; dt_proj bias ``softplus^-1(dt)``, ``dt`` log-uniform in
  ``[dt_min, dt_max]`` floored at ``dt_init_floor`` (so ``softplus(bias)`` lies in
  ``[1e-3, 0.1]`` by default).
* ``A_log[d, n] = log(n + 1)`` (S4D-real: ``A = -(1..N)``); ``D = 1``.
* out_proj ``U(+-1/sqrt(d_inner))`` (kaiming_uniform(a=sqrt 5)) divided by
  ``sqrt(n_residuals)`` (Mamba's ``rescale_prenorm_residual`` with
  ``n_residuals = n_layer * n_residuals_per_layer``).

``A_log``, ``D`` and the dt bias are float32 whatever ``param_dtype`` is, and dt is
computed in float32, as Mamba keeps them (bf16/AMP NaNs: state-spaces/mamba README).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.ssm.scan import selective_scan

DIRECTIONS = ("causal", "bidirectional")
CONVS = ("directional", "centered")


def resolve_dt_rank(d_model: int, dt_rank: int | str) -> int:
  """Mamba's dt rank: ``ceil(d_model / 16)`` for ``"auto"``, else ``int(dt_rank)``."""
  return math.ceil(d_model / 16) if dt_rank == "auto" else int(dt_rank)


def torch_default_init(scale: float = 1.0):
  """PyTorch's Linear/Conv default ``U(+-1/sqrt(fan_in))`` times ``scale``.

  For Flax kernels ``[..., in, out]`` (fan_in from the input axis).
  """
  return nn.initializers.variance_scaling(scale ** 2 / 3.0, "fan_in", "uniform")


def _uniform(bound: float):
  def init(key, shape, dtype=jnp.float32):
    return jax.random.uniform(key, shape, dtype, -bound, bound)
  return init


def mamba_dt_bias_init(dt_min: float = 1e-3, dt_max: float = 0.1, dt_init_floor: float = 1e-4):
  """Initialiser of the dt bias: ``softplus^-1(dt)``, ``dt`` log-uniform in ``[dt_min, dt_max]``.

  ``dt = exp(U(0, 1) (ln dt_max - ln dt_min) + ln dt_min)``, clamped below at
  ``dt_init_floor``; the bias is ``dt + log(-expm1(-dt))`` so that
  ``softplus(bias) = dt``. Returns ``init(key, shape, dtype) -> [shape]``.
  """
  if not 0 < dt_min <= dt_max:
    raise ValueError(f"dt_min and dt_max must satisfy 0 < dt_min <= dt_max, got {dt_min}, {dt_max}")

  def init(key, shape, dtype=jnp.float32):
    u = jax.random.uniform(key, shape, jnp.float32)
    dt = jnp.exp(u * (math.log(dt_max) - math.log(dt_min)) + math.log(dt_min))
    dt = jnp.maximum(dt, dt_init_floor)
    return (dt + jnp.log(-jnp.expm1(-dt))).astype(dtype)
  return init


def s4d_real_a_log_init(key, shape, dtype=jnp.float32):
  """``A_log`` ``[d_inner, N]`` with ``A_log[d, n] = log(n + 1)`` (S4D-real, ``A = -(1..N)``)."""
  del key
  d_inner, n = shape
  a_log = np.log(np.arange(1, n + 1, dtype=np.float64))    # correctly rounded in any dtype
  return jnp.asarray(np.broadcast_to(a_log, (d_inner, n)), dtype)


def depthwise_conv(x, kernel, bias=None, *, mode: str = "causal"):
  """Depthwise 1-D convolution along the sequence axis.

  Args:
    x: ``[..., L, Dch]``.
    kernel: ``[K, Dch]`` taps (PyTorch's ``conv1d.weight[:, 0, :].T``).
    bias: ``[Dch]`` or None.
    mode: "causal" (``y_t = sum_k w_k x_{t-K+1+k}``, PyTorch ``padding=K-1`` cut to
      ``L``), "anticausal" (the causal conv of the flipped sequence, flipped back:
      ``y_t = sum_k w_k x_{t+K-1-k}``) or "centered" (``y_t = sum_k w_k
      x_{t+k-(K-1)//2}``). Zero padding.

  Returns:
    ``[..., L, Dch]`` in the promoted dtype of ``x`` and ``kernel``.
  """
  K = kernel.shape[0]
  L = x.shape[-2]
  if mode == "causal":
    left, right, taps = K - 1, 0, kernel
  elif mode == "anticausal":
    left, right, taps = 0, K - 1, kernel[::-1]
  elif mode == "centered":
    left, right, taps = (K - 1) // 2, K // 2, kernel
  else:
    raise ValueError(f"mode must be 'causal', 'anticausal' or 'centered', got {mode!r}")
  pad = [(0, 0)] * (x.ndim - 2) + [(left, right), (0, 0)]
  xp = jnp.pad(x, pad)
  y = sum(xp[..., k:k + L, :] * taps[k] for k in range(K))
  if bias is not None:
    y = y + bias
  return y


#: The suffix of a bidirectional SSM's reverse-branch parameter names.
REVERSE_SUFFIX = "_b"
#: The parameter names of one scan direction; the reverse branch's carry :data:`REVERSE_SUFFIX`
#: at ``{}`` or, where a name has none, at its end (``dt_proj_b_kernel``, ``A_log_b``).
BRANCH_PARAMS = ("conv_kernel", "conv_bias", "x_proj", "dt_proj{}_kernel", "dt_proj{}_bias", "A_log", "D")


def branch_param_name(template: str, suffix: str) -> str:
  """The name of parameter ``template`` (of :data:`BRANCH_PARAMS`) in the branch of ``suffix``."""
  return template.format(suffix) if "{}" in template else template + suffix


def mirror_params(params) -> dict:
  """Swap the forward and reverse parameters of every bidirectional :class:`SelectiveSSM` in a tree.

  With them, a bidirectional SSM run on the reversed sequence returns the reversal of its
  output on the original one (with a ``conv="centered"`` SSM, also reverse its shared conv's
  taps). Causal SSMs are left as they are. Returns plain nested dicts.
  """
  def visit(tree):
    if not isinstance(tree, dict):
      return tree
    out = {k: visit(v) for k, v in tree.items()}
    if "A_log" in out and "A_log" + REVERSE_SUFFIX in out:
      for template in BRANCH_PARAMS:
        f, b = branch_param_name(template, ""), branch_param_name(template, REVERSE_SUFFIX)
        if f in out and b in out:
          out[f], out[b] = out[b], out[f]
    return out

  return visit(dict_of(params))


def dict_of(tree):
  """Plain nested dicts of a (possibly frozen) Flax variable tree."""
  if hasattr(tree, "unfreeze"):
    tree = tree.unfreeze()
  if isinstance(tree, dict):
    return {k: dict_of(v) for k, v in tree.items()}
  return tree


class SelectiveSSM(nn.Module):
  """Mamba's selective SSM, without its projections and gate: ``[..., L, D] -> [..., L, D]``.

  The one SSM of the library: :class:`MambaMixer` wraps it in its projections and gate, and
  the network's ST-Mamba blocks (:mod:`nlosjax.models.stmamba`) chain it along time and
  over the scan grid. Per direction: ``x' = SiLU(conv(x))`` (depthwise, ``d_conv`` taps,
  causal along the scan direction), ``(d, B, C) = x_proj(x')``, ``dt = softplus(d W_dt +
  b_dt)`` (float32), ``y = selective_scan(x', dt, -exp(A_log), B, C, D)``.
  ``direction="bidirectional"`` adds a reverse branch (parameter names per
  :data:`BRANCH_PARAMS`, its conv anti-causal) and returns the mean of the two.

  Attributes:
    d_inner: channels ``D``.
    d_state: ``N``, states per channel.
    d_conv: taps of the depthwise conv.
    dt_rank: rank of the dt projection ``R``.
    direction: "causal" (step t sees steps <= t) or "bidirectional".
    conv: "directional" (each branch's conv causal along its own direction, Mamba/Vim) or
      "centered" (one non-causal conv before both branches, as VMamba's 2-D conv;
      bidirectional only).
    share_params: bidirectional only: the reverse branch uses the forward one's parameters.
    scan_method, chunk_size: of :func:`nlosjax.ssm.selective_scan`.
    dt_min, dt_max, dt_init, dt_scale, dt_init_floor: dt initialisation (Mamba's names).
    conv_bias: the conv has a bias.
    dtype: computation dtype of the conv and x_proj (the scan state and dt stay float32).
    param_dtype: dtype of the conv and projection weights (``A_log``, ``D`` and the dt bias
      are always float32).
  """

  d_inner: int
  d_state: int = 16
  d_conv: int = 4
  dt_rank: int = 1
  direction: str = "causal"
  conv: str = "directional"
  share_params: bool = False
  scan_method: str = "auto"
  chunk_size: int | None = None
  dt_min: float = 1e-3
  dt_max: float = 0.1
  dt_init: str = "random"
  dt_scale: float = 1.0
  dt_init_floor: float = 1e-4
  conv_bias: bool = True
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32

  def _check(self, x):
    if self.direction not in DIRECTIONS:
      raise ValueError(f"direction must be one of {DIRECTIONS}, got {self.direction!r}")
    if self.conv not in CONVS:
      raise ValueError(f"conv must be one of {CONVS}, got {self.conv!r}")
    if self.conv == "centered" and self.direction == "causal":
      raise ValueError("conv='centered' is non-causal; use it with direction='bidirectional'")
    if self.dt_init not in ("random", "constant"):
      raise ValueError(f"dt_init must be 'random' or 'constant', got {self.dt_init!r}")
    if not (isinstance(self.dt_rank, int) and self.dt_rank >= 1):
      raise ValueError(f"dt_rank must be a positive integer, got {self.dt_rank!r}")
    if x.ndim < 2 or x.shape[-1] != self.d_inner:
      raise ValueError(f"x must be [..., L, {self.d_inner}], got shape {x.shape}")

  def _conv_params(self, suffix: str):
    bound = 1.0 / math.sqrt(self.d_conv)
    kernel = self.param(f"conv_kernel{suffix}", _uniform(bound), (self.d_conv, self.d_inner),
                        self.param_dtype)
    bias = (self.param(f"conv_bias{suffix}", _uniform(bound), (self.d_inner,), self.param_dtype)
            if self.conv_bias else None)
    return kernel, bias

  def _branch_params(self, suffix: str, with_conv: bool) -> dict:
    """Parameters of one scan direction (names per :data:`BRANCH_PARAMS`)."""
    N, R, D = self.d_state, self.dt_rank, self.d_inner
    p = {}
    if with_conv:
      p["conv"] = self._conv_params(suffix)
    p["x_proj"] = nn.Dense(R + 2 * N, use_bias=False, kernel_init=torch_default_init(),
                           dtype=self.dtype, param_dtype=self.param_dtype, name=f"x_proj{suffix}")
    dt_std = R ** -0.5 * self.dt_scale
    dt_kernel_init = _uniform(dt_std) if self.dt_init == "random" else nn.initializers.constant(dt_std)
    p["w_dt"] = self.param(f"dt_proj{suffix}_kernel", dt_kernel_init, (R, D), self.param_dtype)
    p["b_dt"] = self.param(f"dt_proj{suffix}_bias",
                           mamba_dt_bias_init(self.dt_min, self.dt_max, self.dt_init_floor), (D,), jnp.float32)
    p["A_log"] = self.param(f"A_log{suffix}", s4d_real_a_log_init, (D, N), jnp.float32)
    p["D"] = self.param(f"D{suffix}", nn.initializers.ones, (D,), jnp.float32)
    return p

  def _branch(self, x, p: dict, *, reverse: bool):
    """One scan direction: conv (if it has one), SiLU, x_proj, dt, scan. ``[..., L, d_inner]``."""
    if "conv" in p:
      kernel, bias = nn.dtypes.promote_dtype(*p["conv"], dtype=self.dtype)
      x = nn.silu(depthwise_conv(x, kernel, bias, mode="anticausal" if reverse else "causal"))
    N, R = self.d_state, self.dt_rank
    delta, B, C = jnp.split(p["x_proj"](x), [R, R + N], axis=-1)
    dt = jax.nn.softplus(delta.astype(jnp.float32) @ p["w_dt"].astype(jnp.float32) + p["b_dt"])
    return selective_scan(x, dt, -jnp.exp(p["A_log"]), B, C, p["D"], reverse=reverse,
                          method=self.scan_method, chunk_size=self.chunk_size)

  @nn.compact
  def __call__(self, x):
    """``x`` ``[..., L, d_inner]`` -> ``[..., L, d_inner]`` in ``dtype``."""
    self._check(x)
    directional = self.conv == "directional"
    if not directional:
      kernel, bias = nn.dtypes.promote_dtype(*self._conv_params(""), dtype=self.dtype)
      x = nn.silu(depthwise_conv(x, kernel, bias, mode="centered"))
    p = self._branch_params("", directional)
    y = self._branch(x, p, reverse=False)
    if self.direction == "bidirectional":
      p_b = p if self.share_params else self._branch_params(REVERSE_SUFFIX, directional)
      y_b = self._branch(x, p_b, reverse=True)
      y = (0.5 * (y.astype(jnp.float32) + y_b.astype(jnp.float32))).astype(y.dtype)
    return y


#: The :class:`SelectiveSSM` fields a :class:`MambaMixer` passes on unchanged, by name (its
#: ``d_inner`` and ``dt_rank`` it derives): a field added to the SSM and not to the mixer fails
#: at the mixer's first call instead of silently keeping its default.
SHARED_SSM_FIELDS = tuple(f.name for f in dataclasses.fields(SelectiveSSM)
                          if f.name not in ("parent", "name", "d_inner", "dt_rank"))


class MixerWidths(nn.Module):
  """The widths every Mamba-style mixer shares (:class:`MambaMixer`, the network's blocks).

  Attributes:
    d_model: width in and out; ``d_inner = expand * d_model`` inside (:attr:`d_inner`).
    d_state: ``N``, states per channel; d_conv: taps of the depthwise conv.
    dt_rank: rank of the dt projection, or "auto" (``ceil(d_model / 16)``; :attr:`rank`).
  """

  d_model: int
  d_state: int = 16
  d_conv: int = 4
  expand: int = 2
  dt_rank: int | str = "auto"

  @property
  def d_inner(self) -> int:
    return self.expand * self.d_model

  @property
  def rank(self) -> int:
    return resolve_dt_rank(self.d_model, self.dt_rank)


class MambaMixer(MixerWidths):
  """Mamba v1 mixer: ``[..., L, d_model] -> [..., L, d_model]`` (see module docstring).

  ``in_proj``, a :class:`SelectiveSSM` named ``ssm``, the gate and ``out_proj``.

  Attributes:
    d_model: model width.
    d_state: ``N``, states per channel.
    d_conv: taps of the depthwise conv.
    expand: ``d_inner = expand * d_model``.
    dt_rank: rank of the dt projection, or "auto" (``ceil(d_model / 16)``).
    direction: "causal" (step t sees steps <= t) or "bidirectional" (forward +
      reverse branch, averaged; every step sees the whole sequence).
    conv: "directional" (each branch's conv is causal along its own scan direction,
      Mamba/Vim) or "centered" (one non-causal conv shared by the branches, as
      VMamba's 2-D conv; only with ``direction="bidirectional"``).
    share_params: bidirectional only: share conv, x_proj, dt_proj, A_log and D
      between directions (default False: separate, Vim v2).
    scan_method: selective-scan method ("auto" | "sequential" | "blockwise" | "chunked" | "associative").
    chunk_size: selective-scan chunk size (None: the kernel's default).
    dt_min, dt_max, dt_init, dt_scale, dt_init_floor: dt initialisation (Mamba's names).
    conv_bias: conv has a bias.
    bias: in_proj and out_proj have biases.
    n_residuals: out_proj init is divided by ``sqrt(n_residuals)``.
    dtype: activation/computation dtype of the projections and the conv (the scan
      state and dt stay float32).
    param_dtype: dtype of the projection and conv weights (``A_log``, ``D`` and the
      dt bias are always float32).
  """

  direction: str = "causal"
  conv: str = "directional"
  share_params: bool = False
  scan_method: str = "auto"
  chunk_size: int | None = None
  dt_min: float = 1e-3
  dt_max: float = 0.1
  dt_init: str = "random"
  dt_scale: float = 1.0
  dt_init_floor: float = 1e-4
  conv_bias: bool = True
  bias: bool = False
  n_residuals: int = 1
  dtype: Any = jnp.float32
  param_dtype: Any = jnp.float32

  def _check(self, u):
    """The mixer's own fields (the SSM's are checked by :class:`SelectiveSSM`)."""
    if not (self.dt_rank == "auto" or (isinstance(self.dt_rank, int) and self.dt_rank >= 1)):
      raise ValueError(f"dt_rank must be 'auto' or a positive integer, got {self.dt_rank!r}")
    for name in ("d_model", "d_state", "d_conv", "expand", "n_residuals"):
      v = getattr(self, name)
      if not (isinstance(v, int) and v >= 1):
        raise ValueError(f"{name} must be a positive integer, got {v!r}")
    if u.ndim < 2 or u.shape[-1] != self.d_model:
      raise ValueError(f"x must have shape [..., L, d_model={self.d_model}], got {u.shape}")

  @nn.compact
  def __call__(self, x):
    """``x`` ``[..., L, d_model]`` -> ``[..., L, d_model]`` in ``dtype``."""
    self._check(x)
    xz = nn.Dense(2 * self.d_inner, use_bias=self.bias, kernel_init=torch_default_init(),
                  dtype=self.dtype, param_dtype=self.param_dtype, name="in_proj")(x)
    xs, z = jnp.split(xz, 2, axis=-1)
    y = SelectiveSSM(d_inner=self.d_inner, dt_rank=self.rank,
                     **{f: getattr(self, f) for f in SHARED_SSM_FIELDS}, name="ssm")(xs)
    y = y * nn.silu(z)
    return nn.Dense(self.d_model, use_bias=self.bias,
                    kernel_init=torch_default_init(1.0 / math.sqrt(self.n_residuals)),
                    dtype=self.dtype, param_dtype=self.param_dtype, name="out_proj")(y)

"""Light-cone transform with a Wiener filter (``lct``), and the LCT problem FBP and phasor share.

:func:`_lct_problem` builds the LCT operators and filter of a Setup once and
caches them; :mod:`~nlosjax.physics.methods.fbp` and
:mod:`~nlosjax.physics.methods.phasor` backproject with the operators it
builds. The ``variant`` options and how ``lct`` relates to the public code
are described in the docstring of :mod:`nlosjax.physics.reconstruct` (the
"module docstring" the docstrings below refer to).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from nlosjax.physics import _validate
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


@_validate.cached_operators(maxsize=4)   # a filter is [Lv, 2H, W+1] complex: ~0.3 GB at 128^2
def _lct_problem(setup: Setup, power: float, snr: float | None, z_margin: int, oversample: int,
                 dtype, variant: str = "refined") -> tuple:
  """``(operators, frequency-domain filter)`` of one LCT problem, built once and cached.

  ``power`` is the refined operators' ``v^{power/2}`` resampling (3 diffuse, 1
  retroreflective, 0 plain); the public ones multiply by ``t_n^{power + 1}``
  (``t_n^0`` for 0) as the public code. The filter is ``None`` for a
  backprojection (``snr=None``): :func:`lct_apply` then conjugates the PSF
  spectrum inside the reconstruction's own jit.
  """
  if oversample not in (1, 2, 3, 4):
    raise ValueError(f"oversample must be 1, 2, 3 or 4, got {oversample!r}")
  if check_variant(variant) == "public":
    ops = public_lct_operators(setup, public_time_power(power, oversample), z_margin=z_margin,
                               dtype=dtype)
    return ops, (None if snr is None else jax.jit(lct_filter, static_argnums=1)(ops, snr))
  # The depth margin (FBP's -LoG taps) needs the time bins of its returns too.
  # A backprojection convolves with the cone itself: the FFT box need only span its reach.
  ops = lct_operators(setup, power, t_margin=z_margin, z_margin=z_margin, oversample=oversample,
                      dtype=dtype, fft_length="full" if snr is not None else "cone")
  return ops, (None if snr is None else jax.jit(lct_filter, static_argnums=1)(ops, snr))


@jax.jit
def _lct_batch(x, ops, filt):
  t0, t1 = ops.domain.t

  def one(xi):
    return jnp.maximum(to_depth(lct_apply(xi[t0:t1], ops, filt), ops), 0.0)

  return jax.vmap(one)(x)


def lct(transient, setup: Setup, *, snr: float = 0.1, falloff: str = "diffuse",
        variant: str = "public", oversample: int = 1) -> jax.Array:
  """Light-cone transform with a Wiener filter (O'Toole et al., Nature 2018).

  ``vol = max(R_z^-1 F^-1[ F[R_t tau] conj(H) / (|H|^2 + 1/snr) ], 0)`` with
  ``R_t`` the ``v^{q/2}`` time resampling and ``H`` the unit-norm cone PSF.

  Args:
    transient: ``[..., T, H, W]`` photon counts (float or int, >= 0).
    setup: the capture.
    snr: Wiener signal-to-noise ratio, > 0 (public defaults: 0.1 nlos-fk, LFE,
      USM; 0.8 O'Toole retroreflective scenes).
    falloff: ``"diffuse"`` (t^4) or ``"retroreflective"`` (t^2).
    variant: ``"public"`` (the public code's operators: the same ``snr``
      gives the same image) or ``"refined"`` (footprint-averaged cone on the
      true spacing, linear convolution, gated time; see the module docstring).
    oversample: ``variant="refined"`` only: v-bins per time bin of the LCT
      grid. 1 is the public algorithm's grid; 2 halves the resampling error
      near the wall (finer u-grid, sharper off-grid points) at twice the FFT
      cost. See ``benchmarks/results/physics.md`` for the measured trade.
  Returns:
    ``[..., Z, H, W]`` float32 volume, >= 0.
  """
  q = check_falloff(falloff)
  snr = _validate.check_positive(snr, "snr")
  x, batch = _validate.prepare_transient(transient, setup)
  ops, filt = _lct_problem(setup, float(q), snr, 0, oversample, x.dtype, variant)
  return _validate.unbatch(_lct_batch(x, ops, filt), batch)


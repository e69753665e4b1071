"""f-k (Stolt) migration (``fk``).

How ``fk`` differs from the public code (the Stolt interpolation on physical
frequencies, the ``variant`` scan spacing) is described in the docstring of
:mod:`nlosjax.physics.reconstruct`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.fft

from nlosjax.physics import _validate
from nlosjax.physics.operators import check_variant
from nlosjax.physics.setup import Setup


@_validate.cached_operators(maxsize=16)
def _fk_grid(setup: Setup, dtype, variant: str = "refined"):
  """Static sizes and small arrays of the Stolt migration for ``setup``.

  ``variant="public"``: the public code's lateral frequencies (its
  ``a = N range / (4 M width)`` implies a scan spacing of ``wall_size / N``)
  and time weight ``t_n^2``, ``t_n = linspace(0, 1, T)``; ``"refined"``: the
  Setup's spacing ``wall_size / (N - 1)`` and the bin-centre weight ``((t + 1/2) / T)^2``.
  """
  T = setup.num_bins
  t0, t1 = setup.time_bins
  n_t = t1                                   # f-k needs the time axis from t = 0
  l_t = scipy.fft.next_fast_len(2 * n_t, real=True)
  l_t += l_t % 2
  H, W = setup.grid
  t = np.arange(n_t)
  if check_variant(variant) == "public":
    dy, dx = setup.wall_size / H, setup.wall_size / W
    t_n = t / max(T - 1, 1)
  else:
    dy, dx = setup.spacing
    t_n = (t + 0.5) / T
  weight = np.where(t >= t0, t_n ** 2, 0.0)                  # gating: bins before t0 dropped
  ky = np.fft.fftfreq(2 * H, d=dy)           # cycles / m
  kx = np.fft.fftfreq(2 * W, d=dx)
  kperp = (l_t * setup.depth_bin_length) ** 2 * (ky[:, None] ** 2 + kx[None, :] ** 2)
  return l_t, jnp.asarray(kperp, dtype), jnp.asarray(weight, dtype)


@functools.partial(jax.jit, static_argnames=("n_t", "l_t", "crop"))
def _fk_batch(x, kperp, weight, n_t, l_t, crop):
  h, w = x.shape[-2:]
  n_f = l_t // 2 + 1
  m = jnp.arange(n_f, dtype=kperp.dtype)[:, None, None]
  src = jnp.sqrt(m * m + kperp[None])                      # source frequency index
  lo_idx = jnp.floor(src)
  frac = src - lo_idx
  lo_idx = lo_idx.astype(jnp.int32)
  valid = (m > 0) & (lo_idx + 1 <= n_f - 1)
  jac = jnp.where(valid, m / jnp.maximum(src, 1e-6), 0.0)
  lo_c = jnp.minimum(lo_idx, n_f - 1)
  hi_c = jnp.minimum(lo_idx + 1, n_f - 1)

  def one(xi):
    a = xi[:n_t] * weight[:, None, None]
    psi = jnp.sqrt(jnp.where(a > 0, a, 0.0))
    spec = jnp.fft.rfft(psi, n=l_t, axis=0)                 # [n_f, H, W]
    spec = jnp.fft.fft2(spec, s=(2 * h, 2 * w), axes=(1, 2))
    phi = (jnp.take_along_axis(spec, lo_c, axis=0) * (1 - frac)
           + jnp.take_along_axis(spec, hi_c, axis=0) * frac) * jac
    field = jnp.fft.ifft2(phi, axes=(1, 2))[:, :h, :w]
    field = jnp.fft.ifft(field, n=l_t, axis=0)[crop[0]:crop[1]]
    return jnp.real(field) ** 2 + jnp.imag(field) ** 2

  return jax.vmap(one)(x)


def fk(transient, setup: Setup, *, variant: str = "public") -> jax.Array:
  """f-k (Stolt) migration (Lindell, Wetzstein, O'Toole, SIGGRAPH 2019).

  ``psi = sqrt(tau t^2)``; ``Phi(kx, ky, kz) = kz / f * Psi(kx, ky, f)`` with
  ``f = sqrt(kx^2 + ky^2 + kz^2)`` (cycles/m; time as depth ``c t / 2``),
  linear interpolation along ``f``, ``kz > 0`` only; ``vol = |F^-1 Phi|^2``.

  Args:
    transient: ``[..., T, H, W]`` counts >= 0.
    setup: the capture.
    variant: ``"public"``: the public code's lateral frequencies (scan spacing
      ``wall_size / N``) and ``t_n^2`` weight, so its image; ``"refined"``: the
      Setup's spacing ``wall_size / (N - 1)`` (see ``_fk_grid``).
  Returns:
    ``[..., Z, H, W]`` float32 volume, >= 0, proportional to albedo squared
    (as the public code; take ``sqrt`` to compare linearly).
  """
  x, batch = _validate.prepare_transient(transient, setup)
  l_t, kperp, weight = _fk_grid(setup, x.dtype, variant)
  return _validate.unbatch(
      _fk_batch(x, kperp, weight, n_t=setup.time_bins[1], l_t=l_t, crop=setup.depth_bins), batch)


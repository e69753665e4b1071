"""Filtered backprojection (``fbp``): the LCT backprojection, then a separable ``-LoG`` filter.

The backprojection's operators come from :mod:`~nlosjax.physics.methods.lct`.
How ``fbp`` differs from the public code (the sign of the Laplacian) is
described in the docstring of :mod:`nlosjax.physics.reconstruct`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.physics import _validate
from nlosjax.physics.methods.lct import _lct_problem
from nlosjax.physics.operators import check_falloff, lct_apply, to_depth
from nlosjax.physics.setup import Setup


def _neg_log_kernel(size: int = 5, sigma: float = 1.0) -> np.ndarray:
  """``[size]*3`` float64 negative Laplacian-of-Gaussian, zero mean (positive at the centre).

  The dense kernel; :func:`neg_log_filter` applies it separably. Kept as the
  reference the tests compare against.
  """
  r = np.arange(size) - size // 2
  r2 = r[:, None, None] ** 2 + r[None, :, None] ** 2 + r[None, None, :] ** 2
  g = np.exp(-r2 / (2 * sigma ** 2))
  g /= g.sum()
  w = g * (r2 - 3 * sigma ** 2) / sigma ** 4
  return -(w - w.mean())


def _taps(size: int, sigma: float) -> tuple[tuple[float, ...], tuple[float, ...], float]:
  """1D factors of :func:`_neg_log_kernel`: ``(g, a, mean)``.

  The normalised 3D Gaussian is ``g(z) g(y) g(x)`` and ``r^2 - 3 sigma^2`` is
  ``sum_i (x_i^2 - sigma^2)``, so the LoG is ``sum_i a(x_i) prod_{j != i} g(x_j)``
  with ``a = g (x^2 - sigma^2) / sigma^4``; ``mean`` is its mean over the cube.
  """
  r = np.arange(size) - size // 2
  g = np.exp(-r ** 2 / (2 * sigma ** 2))
  g /= g.sum()
  a = g * (r ** 2 - sigma ** 2) / sigma ** 4
  mean = 3 * a.sum() * g.sum() ** 2 / size ** 3
  return tuple(g.tolist()), tuple(a.tolist()), float(mean)


def _correlate_axis(x: jax.Array, taps: tuple[float, ...], axis: int) -> jax.Array:
  """'valid' correlation of ``x`` with constant ``taps`` along ``axis`` (shifted slices; XLA fuses them)."""
  n = x.shape[axis] - len(taps) + 1
  out = None
  for i, c in enumerate(taps):
    term = c * jax.lax.slice_in_dim(x, i, i + n, axis=axis)
    out = term if out is None else out + term
  return out


def neg_log_filter(volume: jax.Array, size: int = 5, sigma: float = 1.0) -> jax.Array:
  """``-LoG`` filter of a ``[Z, H, W]`` volume with replicate (edge) padding, same shape out.

  Separable: three products of 1D ``size``-tap filters plus a box term for
  the zero mean, instead of a dense ``size^3`` 3D convolution (XLA's CPU 3D
  convolution was 20x slower than the NumPy twin). Equal to correlating with
  :func:`_neg_log_kernel` (the tests check against ``scipy.ndimage``).
  """
  g, a, mean = _taps(size, sigma)
  r = size // 2
  p = jnp.pad(volume, r, mode="edge")
  gz, az = _correlate_axis(p, g, 0), _correlate_axis(p, a, 0)
  gzgy = _correlate_axis(gz, g, 1)
  log = (_correlate_axis(_correlate_axis(az, g, 1) + _correlate_axis(gz, a, 1), g, 2)
         + _correlate_axis(gzgy, a, 2))
  ones = (1.0,) * size
  box = _correlate_axis(_correlate_axis(_correlate_axis(p, ones, 0), ones, 1), ones, 2)
  return mean * box - log


@functools.partial(jax.jit, static_argnames=("crop",))
def _fbp_batch(x, ops, filt, crop):
  t0, t1 = ops.domain.t
  lo, hi = crop

  def one(xi):
    bp = to_depth(lct_apply(xi[t0:t1], ops, filt), ops)
    # Replicate padding (as LFE): zero padding makes the -LoG ring at the scan border.
    return jnp.maximum(neg_log_filter(bp)[lo:hi], 0.0)

  return jax.vmap(one)(x)


def fbp(transient, setup: Setup, *, falloff: str = "diffuse", variant: str = "public",
        oversample: int = 1) -> jax.Array:
  """Filtered backprojection: LCT backprojection (``conj(H)``) then a ``-LoG`` filter.

  The public code (nlos-fk, LFE, USM) uses ``+LoG``, negative on objects;
  clamping then keeps only halos. We negate it (5x5x5, sigma = 1 voxel).

  Args:
    transient: ``[..., T, H, W]`` counts >= 0.
    setup: the capture.
    falloff: time weighting of the backprojection, ``"diffuse"`` (t^4, as
      the public FBP) or ``"retroreflective"`` (t^2).
    variant: backprojection operators, ``"public"`` or ``"refined"`` (see :func:`lct`).
    oversample: ``variant="refined"`` only: v-bins per time bin (see :func:`lct`).
  Returns:
    ``[..., Z, H, W]`` float32, >= 0.
  """
  q = check_falloff(falloff)
  x, batch = _validate.prepare_transient(transient, setup)
  margin = 2
  ops, filt = _lct_problem(setup, float(q), None, margin, oversample, x.dtype, variant)
  k0, k1 = setup.depth_bins
  lo = k0 - ops.domain.z[0]
  return _validate.unbatch(_fbp_batch(x, ops, filt, (lo, lo + k1 - k0)), batch)


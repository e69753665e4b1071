"""CSA: the compressed-sensing reconstruction of an under-scanned confocal capture (iterative).

After Ye, Huang, Li and Xu, "Compressed sensing for active non-line-of-sight
imaging" (Optics Express 29(2), 2021): a sparse scan is a masked full-grid
scan, and a sparsity prior on the hidden volume fills in what the mask hides.
The paper's text gives the idea (5 x 5 scan points, a 64 x 64 volume), not a
solver we could read, so the choices it leaves open follow the public LCT
release's iterative code and its authors' group's public code (both pose the
problem in the LCT's resampled domain, with non-negativity and an l1 prior):

    min_{u >= 0}  1/2 || M (A u) - b ||^2 + tau ||u||_1,     b = M R_t tau_meas,

* ``u`` ``[Nu, H, W]``: the hidden volume on the u-grid (``u = z^2``),
  returned as ``R_z u`` on the depth grid (the bin averages ``lct`` uses);
* ``R_t``: the LCT's ``t -> v`` resampling with the ``v^{q/2}`` falloff
  weight (``q`` 3 diffuse, 1 retroreflective), so the model is a convolution;
* ``A``: linear convolution with the unit-norm light-cone PSF over ``(v, y, x)``
  (the refined operators of :mod:`nlosjax.physics.operators`, FFT box
  ``"cone"``); ``A^T`` is the LCT backprojection (``lct_apply(..., None)``
  without its resampling), and ``A`` its exact adjoint;
* ``M``: the scan mask ``[H, W]`` (1 where a point was scanned), the same for
  every v-bin: unscanned points of ``transient`` are never read;
* ``tau = tau_rel * max(A^T b)``: at ``tau_rel >= 1`` the solution is ``u = 0``
  (the l1 problem's threshold), so ``tau_rel`` is free of the photon scale and
  ``csa(k x) = k csa(x)`` for any ``k > 0``.

Solver: FISTA (Beck and Teboulle 2009) with the non-negative soft threshold
``max(y - (grad + tau) / L, 0)`` and a fixed step ``1 / L``, ``L`` = 1.1 times
``||M A||^2`` estimated by ``power_iterations`` power iterations on
``A^T M A`` (the factor covers the estimate's shortfall). It stops after
``iterations`` steps or when the step is small: ``||u_k - u_{k-1}|| <= tol
||u_k||``. Cost per iteration: one ``A`` and one ``A^T``, each an FFT
convolution over the ``(Lv, 2H, 2W)`` box, so about two LCT backprojections;
:func:`csa_solve` returns the iteration count and the objective.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.physics import _validate
from nlosjax.physics.operators import (
  LCTOperators,
  apply_axis_matrix,
  check_falloff,
  filter_v_axis,
  lct_operators,
  to_depth,
)
from nlosjax.physics.setup import Setup

#: How much above the power-iteration estimate of ``||M A||^2`` the step's ``L`` is set.
LIPSCHITZ_MARGIN = 1.1


def csa_operators(setup: Setup, falloff: str = "retroreflective", *, oversample: int = 1,
                  dtype=jnp.float32) -> LCTOperators:
  """The operators of :func:`csa` for ``setup`` (cached; the refined LCT operators, FFT box ``"cone"``)."""
  q = check_falloff(falloff)
  return lct_operators(setup, float(q), oversample=oversample, dtype=dtype, fft_length="cone")


def _lateral_spectrum(x: jax.Array, ops: LCTOperators) -> jax.Array:
  """``[N, H, W]`` real -> ``[N, 2H, W + 1]`` complex: the lateral FFT on the zero-padded box."""
  _, h2, w2 = ops.domain.fft_shape
  return jnp.fft.fft(jnp.fft.rfft(x, n=w2, axis=2), n=h2, axis=1)


def _lateral_inverse(spec: jax.Array, ops: LCTOperators, h: int, w: int) -> jax.Array:
  """``[N, 2H, W + 1]`` complex -> ``[N, H, W]`` real: the inverse, cropped to the scan grid."""
  w2 = ops.domain.fft_shape[2]
  return jnp.fft.irfft(jnp.fft.ifft(spec, axis=1)[:, :h], n=w2, axis=2)[:, :, :w]


def forward_v(u: jax.Array, ops: LCTOperators) -> jax.Array:
  """``A``: ``[Nu, H, W]`` u-grid volume -> ``[Nv, H, W]`` v-grid data (linear convolution with the cone)."""
  dom = ops.domain
  h, w = u.shape[-2:]
  spec = jnp.moveaxis(_lateral_spectrum(u, ops), 0, -1)                  # [2H, W + 1, Nu]
  out = jnp.fft.ifft(jnp.fft.fft(spec, n=dom.fft_shape[0], axis=-1) * ops.psf_fft, axis=-1)
  return _lateral_inverse(jnp.moveaxis(out[..., :dom.num_v], -1, 0), ops, h, w)


def adjoint_v(r: jax.Array, ops: LCTOperators) -> jax.Array:
  """``A^T``: ``[Nv, H, W]`` -> ``[Nu, H, W]``, the LCT backprojection of v-grid data."""
  h, w = r.shape[-2:]
  out = filter_v_axis(_lateral_spectrum(r, ops), jnp.conj(ops.psf_fft), ops.domain, axis=0)
  return _lateral_inverse(out, ops, h, w)


def interval_mask(height: int, width: int, stride: int) -> np.ndarray:
  """``[H, W]`` float32 scan mask: 1 at the points ``stride // 2 + stride i`` (the network's sparse scan)."""
  if not (isinstance(stride, (int, np.integer)) and stride >= 1):
    raise ValueError(f"stride must be a positive integer, got {stride!r}")
  mask = np.zeros((height, width), np.float32)
  mask[stride // 2::stride, stride // 2::stride] = 1.0
  return mask


def sparse_on_grid(transient, grid: tuple[int, int], stride: int) -> jax.Array:
  """``[..., T, h, w]`` under-scanned counts -> ``[..., T, H, W]`` zeros but at their scan points.

  Sample ``i`` goes to ``stride // 2 + stride * i`` (:func:`interval_mask`'s points); CSA never
  reads the zeros between them. Jittable.
  """
  mask = interval_mask(grid[0], grid[1], stride)       # validates stride
  o = stride // 2
  h, w = mask[o::stride, 0].size, mask[0, o::stride].size
  if tuple(transient.shape[-2:]) != (h, w):
    raise ValueError(f"under-scanned grid {tuple(transient.shape[-2:])} does not match grid {tuple(grid)} "
                     f"at stride {stride} ({h}, {w})")
  x = jnp.asarray(transient)
  return jnp.zeros(x.shape[:-2] + tuple(grid), x.dtype).at[..., o::stride, o::stride].set(x)


def _solve_one(x, mask, ops, tau_rel, iterations, tol, power_iterations):
  """One capture ``[Nt, H, W]``: ``(u [Nu, H, W], iterations run, objective)``."""
  t0, t1 = ops.domain.t
  b = mask * apply_axis_matrix(ops.to_v, ops.to_v_sparse, x[t0:t1])       # [Nv, H, W]
  # The problem is scale-free (tau follows the data): solve it for b / max(b), then scale back,
  # so that neither saturated nor single-photon counts leave float32's range.
  scale = jnp.max(jnp.abs(b))
  b = b / jnp.where(scale > 0, scale, 1.0)

  def normal(v):
    return adjoint_v(mask * forward_v(v, ops), ops)

  def power_step(_, v):
    w = normal(v)
    return w / jnp.maximum(jnp.linalg.norm(w), jnp.finfo(w.dtype).tiny)

  shape = (ops.domain.num_u,) + x.shape[-2:]
  v = jax.lax.fori_loop(0, power_iterations, power_step,
                        jnp.full(shape, 1.0 / np.sqrt(np.prod(shape)), x.dtype))
  lip = LIPSCHITZ_MARGIN * jnp.vdot(v, normal(v))
  lip = jnp.where(lip > 0, lip, 1.0)                      # no scanned point reaches the volume
  atb = adjoint_v(b, ops)
  tau = tau_rel * jnp.max(atb)

  def cond(state):
    k, _, _, _, change = state
    return (k < iterations) & (change > tol)

  def body(state):
    k, u, y, t, _ = state
    grad = adjoint_v(mask * forward_v(y, ops), ops) - atb
    u_new = jnp.maximum(y - (grad + tau) / lip, 0.0)
    t_new = 0.5 * (1.0 + jnp.sqrt(1.0 + 4.0 * t * t))
    y_new = u_new + ((t - 1.0) / t_new) * (u_new - u)
    size = jnp.linalg.norm(u_new)
    change = jnp.where(size > 0, jnp.linalg.norm(u_new - u) / jnp.where(size > 0, size, 1.0), 0.0)
    return k + 1, u_new, y_new, t_new, change

  zero = jnp.zeros(shape, x.dtype)
  k, u, _, _, _ = jax.lax.while_loop(
      cond, body, (jnp.int32(0), zero, zero, jnp.asarray(1.0, x.dtype), jnp.asarray(jnp.inf, x.dtype)))
  residual = mask * forward_v(u, ops) - b
  objective = 0.5 * jnp.sum(residual ** 2) + tau * jnp.sum(u)
  return u * scale, k, objective


@functools.partial(jax.jit, static_argnames=("iterations", "power_iterations"))
def _csa_batch(x, mask, ops, tau_rel, tol, *, iterations, power_iterations):
  def one(xi):
    u, k, obj = _solve_one(xi, mask, ops, tau_rel, iterations, tol, power_iterations)
    return jnp.maximum(to_depth(u, ops), 0.0), k, obj

  return jax.vmap(one)(x)


def _checked_mask(mask, setup: Setup, dtype) -> jax.Array:
  if mask is None:
    return jnp.ones((setup.height, setup.width), dtype)
  m = np.asarray(mask)
  if m.shape != (setup.height, setup.width):
    raise ValueError(f"mask must be [H, W] = {(setup.height, setup.width)} (the Setup's scan grid),"
                     f" got shape {m.shape}")
  if not np.all(np.isfinite(m.astype(np.float64))) or np.any((m != 0) & (m != 1)):
    raise ValueError("mask must hold only 0 (not scanned) and 1 (scanned)")
  if not np.any(m):
    raise ValueError("mask scans no point")
  return jnp.asarray(m, dtype)


def csa_solve(transient, setup: Setup, *, mask=None, tau_rel: float = 0.05, iterations: int = 200,
              tol: float = 1e-4, falloff: str = "retroreflective", oversample: int = 1,
              power_iterations: int = 30) -> dict:
  """:func:`csa` with what the solver did: ``{"volume", "iterations", "objective"}``.

  Returns:
    ``volume`` ``[..., Z, H, W]`` float32 >= 0; ``iterations`` ``[...]`` int32, the FISTA
    steps each capture ran (``< iterations`` when ``tol`` stopped it); ``objective``
    ``[...]``, ``1/2 ||M (A u) - b||^2 + tau ||u||_1`` at the returned ``u``, for the data
    scaled to ``max |b| = 1`` (the solver works at that scale: the result is scaled back).
  """
  check_falloff(falloff)
  tau_rel = _validate.check_positive(tau_rel, "tau_rel")
  if not (isinstance(iterations, (int, np.integer)) and iterations >= 1):
    raise ValueError(f"iterations must be a positive integer, got {iterations!r}")
  if not (isinstance(power_iterations, (int, np.integer)) and power_iterations >= 1):
    raise ValueError(f"power_iterations must be a positive integer, got {power_iterations!r}")
  if not (float(tol) >= 0 and np.isfinite(float(tol))):
    raise ValueError(f"tol must be a finite number >= 0, got {tol!r}")
  x, batch = _validate.prepare_transient(transient, setup)
  m = _checked_mask(mask, setup, x.dtype)
  ops = csa_operators(setup, falloff, oversample=oversample, dtype=x.dtype)
  vol, k, obj = _csa_batch(x, m, ops, jnp.asarray(tau_rel, x.dtype), jnp.asarray(float(tol), x.dtype),
                           iterations=int(iterations), power_iterations=int(power_iterations))
  return {"volume": _validate.unbatch(vol, batch), "iterations": k.reshape(batch),
          "objective": obj.reshape(batch)}


def csa(transient, setup: Setup, *, mask=None, tau_rel: float = 0.05, iterations: int = 200,
        tol: float = 1e-4, falloff: str = "retroreflective", oversample: int = 1,
        power_iterations: int = 30) -> jax.Array:
  """Compressed-sensing reconstruction of a (masked) confocal scan: FISTA on the LCT model.

  Args:
    transient: ``[..., T, H, W]`` counts >= 0 on the Setup's full scan grid; points
      where ``mask`` is 0 are never read (zeros are fine).
    setup: the capture (its full grid and depth range; the volume is on its depth grid).
    mask: ``[H, W]`` 0/1, 1 at the scanned points (:func:`interval_mask` for an interval
      scan); ``None``: every point.
    tau_rel: the l1 weight as a share of ``max(A^T b)``, > 0 (>= 1 gives an empty volume).
    iterations: the most FISTA steps; tol: stop when the relative step is at most this.
    falloff: ``"retroreflective"`` (t^2) or ``"diffuse"`` (t^4), as ``lct``'s.
    oversample: v- and u-bins per time bin (``lct``'s ``variant="refined"`` grid).
    power_iterations: steps of the power iteration that sets the step size.
  Returns:
    ``[..., Z, H, W]`` float32 volume, >= 0.
  Raises:
    ValueError: bad shapes, counts, mask or options.
  """
  return csa_solve(transient, setup, mask=mask, tau_rel=tau_rel, iterations=iterations, tol=tol,
                   falloff=falloff, oversample=oversample, power_iterations=power_iterations)["volume"]

"""Noise-free confocal transients: the fast LCT-form renderer and a brute-force reference.

``render`` runs the light-cone transform forward (O'Toole et al. 2018):
depth -> u resampling with the ``1 / (2 sqrt(u))`` Jacobian, 3-D FFT
convolution with the light-cone PSF, v -> time resampling, and division by
``v^{q/2}`` (``q = 3`` diffuse, ``1`` retroreflective). It shares its
operators with the LCT reconstruction (an "inverse crime" if used alone), so
``render_points`` -- an explicit loop over 3-D points and scan points -- is the
independent reference the tests check both against.

Scale: ``render_points`` returns ``sum albedo / r^4`` (or ``/ r^2``) per bin,
in units of m^-4 (m^-2); ``render`` is calibrated to the same units for a
voxel treated as a point at its nominal depth, up to the discretisation
(see the tests). Normalise to a photon budget with ``add_spad_noise``.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.physics import _validate
from nlosjax.physics.operators import (
  LCTDomain,
  check_falloff,
  cone_psf,
  lct_domain,
  linear_axis_matrix,
  squared_axis_matrix,
)
from nlosjax.physics.setup import Setup


@functools.partial(jax.tree_util.register_dataclass, data_fields=["psf_fft", "to_u", "to_t"],
                   meta_fields=["domain"])
@dataclasses.dataclass(frozen=True)
class RenderOperators:
  """Device arrays of the forward model (see :func:`render_operators`).

  Attributes:
    domain: bin windows (static).
    psf_fft: ``[Lv, 2H, W + 1]`` complex PSF spectrum.
    to_u: ``[Nu, Z]`` depth -> u resampling with the Jacobian ``1 / z``.
    to_t: ``[Nt, Nv]`` v -> time averaging divided by ``(t / T)^q``.
  """

  domain: LCTDomain
  psf_fft: jax.Array
  to_u: jax.Array
  to_t: jax.Array


def render_operators(setup: Setup, falloff: str = "diffuse", dtype=jnp.float32,
                     oversample: int = 2) -> RenderOperators:
  """The forward-model operators of ``setup`` (built once per capture and cached).

  ``setup.aperture`` is dropped first: it limits reconstructions, never the
  physics, so a Setup with and without one share the same operators.
  """
  return _render_operators(setup.with_aperture(None), falloff, jnp.dtype(dtype), int(oversample))


@_validate.cached_operators(maxsize=16)
def _render_operators(setup: Setup, falloff: str, dtype, oversample: int) -> RenderOperators:
  q = check_falloff(falloff)
  dom = lct_domain(setup, oversample=oversample, fft_length="cone")   # a convolution with the cone
  T = setup.num_bins
  cdtype = jnp.complex128 if jnp.dtype(dtype) == jnp.float64 else jnp.complex64
  psf = cone_psf(setup, dom)
  # z -> u with the Jacobian 1/(2 sqrt(u)) = 1/(2 z); power -1 on the z/T axis.
  to_u = squared_axis_matrix(T, dom.u, dom.z, power=-1.0, oversample=oversample)
  # v -> t bin average divided by (t/T)^q.
  to_t = linear_axis_matrix(T, dom.t, dom.v, power=-float(q), oversample=oversample)
  # Calibrate to brute-force units: a unit voxel at depth z straight below a
  # scan point returns 1 / z^4 (or 1 / z^2) summed over its time bins.
  scale = _calibration(setup, q, psf, to_u, to_t, dom)
  return RenderOperators(dom, jnp.asarray(np.fft.rfftn(psf) * scale, cdtype),
                         jnp.asarray(to_u, dtype), jnp.asarray(to_t, dtype))


def _calibration(setup, q, psf, to_u, to_t, dom) -> float:
  """Scale that maps the LCT chain onto ``albedo / r^(q+1)`` units (numpy, float64)."""
  k0, k1 = dom.z
  k = (k0 + k1) // 2
  z = k * setup.depth_bin_length
  # Straight below the scan point only the PSF column at offset 0 matters.
  col = psf[:, 0, 0]
  u = to_u[:, k - k0]
  conv = np.real(np.fft.ifft(np.fft.fft(u, col.size) * np.fft.fft(col)))[:dom.num_v]
  ttrace = to_t @ conv
  model = float(np.sum(ttrace))
  return (1.0 / z ** (q + 1)) / model if model > 0 else 1.0


def _render_one(rho: jax.Array, ops: RenderOperators, num_bins: int) -> jax.Array:
  """``[Z, H, W]`` albedo -> ``[T, H, W]`` transient (one example)."""
  dom = ops.domain
  h, w = rho.shape[-2:]
  rho_u = jnp.einsum("uz,zhw->uhw", ops.to_u, rho, precision="highest")
  spec = jnp.fft.rfftn(rho_u, s=dom.fft_shape)
  data_v = jnp.fft.irfftn(spec * ops.psf_fft, s=dom.fft_shape)[:dom.num_v, :h, :w]
  trans = jnp.einsum("tv,vhw->thw", ops.to_t, data_v, precision="highest")
  t0, t1 = dom.t
  trans = jnp.pad(trans, ((t0, num_bins - t1), (0, 0), (0, 0)))
  # Causality: nothing returns before the nearest occupied depth bin. Dividing
  # by (t/T)^q amplifies FFT round-off at early t by up to T^q; this bound
  # removes it instead of a threshold (less 2 bins: the discretised cone
  # spreads a voxel's return over its neighbouring bins).
  occupied = jnp.any(rho > 0, axis=(1, 2))
  first = dom.z[0] + jnp.argmax(occupied) - 2
  causal = jnp.arange(num_bins) >= first
  return jnp.where(causal[:, None, None], jnp.maximum(trans, 0.0), 0.0)


@functools.partial(jax.jit, static_argnames=("num_bins",))
def _render_batch(rho, ops, num_bins):
  return jax.vmap(_render_one, in_axes=(0, None, None))(rho, ops, num_bins)


def render(albedo, setup: Setup, *, falloff: str = "diffuse") -> jax.Array:
  """Noise-free confocal transient of an albedo volume, in the LCT form.

  Args:
    albedo: ``[..., Z, H, W]`` non-negative albedo per voxel; voxel
      ``(k, i, j)`` sits at ``(scan_x[j], scan_y[i], depths[k])`` (``Z`` =
      ``setup.num_depth_bins``: the depth range's bins when one is set).
    setup: the capture.
    falloff: ``"diffuse"`` (``r^-4``) or ``"retroreflective"`` (``r^-2``).
  Returns:
    ``[..., T, H, W]`` float32 transient, in the units of
    :func:`render_points` (``sum albedo / r^4`` per bin), zero outside the
    bins the volume can reach. Jit-compiled; operators cached per Setup.
  Raises:
    ValueError: wrong shape for the Setup, NaN or negative albedo, unknown falloff.
  """
  check_falloff(falloff)
  if not isinstance(setup, Setup):
    raise ValueError(f"setup must be a nlosjax.physics.Setup, got {type(setup).__name__}")
  setup.check_volume(albedo, "albedo")
  _validate.check_counts(albedo, "albedo")
  x = jnp.asarray(albedo)
  x = x.astype(_validate.working_dtype(x))
  batch = x.shape[:-3]
  ops = render_operators(setup, falloff, x.dtype)
  out = _render_batch(x.reshape((-1,) + x.shape[-3:]), ops, setup.num_bins)
  return _validate.unbatch(out, batch)


def render_points(points, albedos, setup: Setup, *, falloff: str = "diffuse") -> np.ndarray:
  """Brute-force confocal transient of explicit 3-D points (slow, obviously correct).

  For every scan point ``s`` and scene point ``p`` with distance
  ``r = |p - s|``, adds ``albedo / r^4`` (``/ r^2`` retroreflective) to the
  time bin ``floor(2 r / bin_length)`` (bin ``k`` holds round-trip paths in
  ``[k, k + 1) * bin_length``); returns beyond the last bin are dropped.

  Args:
    points: ``[P, 3]`` (x, y, z) metres, z > 0 in front of the wall.
    albedos: ``[P]`` or scalar, non-negative.
    setup: the capture.
    falloff: ``"diffuse"`` or ``"retroreflective"``.
  Returns:
    ``[T, H, W]`` float64 NumPy transient.
  """
  q = check_falloff(falloff)
  points = np.asarray(points, np.float64).reshape(-1, 3)
  albedos = np.broadcast_to(np.asarray(albedos, np.float64), points.shape[:1])
  if np.any(points[:, 2] <= 0):
    raise ValueError("points must lie in front of the wall (z > 0)")
  H, W = setup.grid
  T = setup.num_bins
  out = np.zeros((T, H, W))
  scan = setup.scan_points                        # [H, W, 3]
  for p, a in zip(points, albedos):
    for i in range(H):
      for j in range(W):
        r = float(np.linalg.norm(p - scan[i, j]))
        k = int(np.floor(2.0 * r / setup.bin_length))
        if k < T:
          out[k, i, j] += a / r ** (q + 1)
  return out

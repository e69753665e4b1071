"""The benchmark's capture: a synthetic transient of a few point scatterers, and each method's FFT floor.

Shapes: transients ``[T, H, W]`` float32 photon counts; 2 m wall, 32 ps bins.
"""

from __future__ import annotations

import numpy as np

from nlosjax.physics.forward import render_points
from nlosjax.physics.setup import Setup

WALL_SIZE = 2.0      # m
BIN_WIDTH = 32e-12   # s
# The synthetic scene: (x, y) as fractions of the half wall, depth as a
# fraction of the deepest bin, albedo.
SCENE_POINTS = (
    (-0.45, -0.30, 0.35, 1.0),
    (0.35, 0.20, 0.45, 1.0),
    (0.00, 0.50, 0.55, 0.8),
    (-0.15, 0.05, 0.30, 0.6),
    (0.50, -0.45, 0.50, 1.0),
)
SIGNAL_PHOTONS = 200.0  # mean signal photons per scan point
BACKGROUND = 0.02       # mean background counts per bin


def make_setup(n: int, bins: int) -> Setup:
  """The benchmark capture: 2 m wall, ``n x n`` scan points, ``bins`` bins of 32 ps."""
  return Setup(wall_size=WALL_SIZE, grid=(n, n), bin_width=BIN_WIDTH, num_bins=bins)


def synthetic_transient(setup: Setup, seed: int = 0) -> np.ndarray:
  """Float32 ``[T, H, W]`` photon counts of :data:`SCENE_POINTS` with Poisson noise."""
  half, depth = setup.wall_size / 2.0, setup.max_depth
  pts = np.array([(x * half, y * half, z * depth) for x, y, z, _ in SCENE_POINTS])
  albedo = np.array([a for *_, a in SCENE_POINTS])
  clean = render_points(pts, albedo, setup)
  clean *= SIGNAL_PHOTONS * setup.height * setup.width / max(clean.sum(), 1e-30)
  rng = np.random.default_rng(seed)
  return rng.poisson(clean + BACKGROUND).astype(np.float32)


def fft_floor(method: str, setup: Setup):
  """A jittable ``x [T, H, W] -> array`` doing only the FFTs ``method`` needs, at their sizes.

  * ``lct``, ``fbp``: ``rfftn`` and ``irfftn`` of the padded ``(2T, 2H, 2W)`` volume
    (the public algorithm's box);
  * ``phasor``: the time convolution with the wavelet (complex FFT pair along
    ``t``) and the box's FFT pair for its real and imaginary parts;
  * ``fk``: ``rfft`` along ``t`` (length ``2T``), ``fft2`` on ``(2H, 2W)``, and
    back (``ifft2``, ``ifft``);
  * ``rsd``: ``rfft`` along ``t`` (the wall fields' DTFT), ``fft2`` of the ``K``
    wall fields on ``(2H, 2W)``, ``ifft2`` of the NUFFT grid's rows, ``ifft`` along
    its ``M`` cells (sizes from the plan).
  """
  import jax.numpy as jnp

  T, (H, W) = setup.num_bins, setup.grid
  box = (2 * T, 2 * H, 2 * W)

  def box_pair(v):
    return jnp.fft.irfftn(jnp.fft.rfftn(v, s=box), s=box)[:T, :H, :W]

  if method in ("lct", "fbp"):
    return box_pair
  if method == "phasor":
    from nlosjax.physics.wavelet import public_wavelet
    n = T + public_wavelet(setup).num_samples - 1

    def phasor_floor(v):
      field = jnp.fft.ifft(jnp.fft.fft(v, n=n, axis=0), axis=0)[:T]
      return box_pair(field.real) + box_pair(field.imag)
    return phasor_floor
  if method == "fk":
    def fk_floor(v):
      spec = jnp.fft.fft2(jnp.fft.rfft(v, n=2 * T, axis=0), s=(2 * H, 2 * W))
      return jnp.fft.ifft(jnp.fft.ifft2(spec)[:, :H, :W], n=2 * T, axis=0)[:T]
    return fk_floor
  if method == "rsd":
    import importlib
    recon = importlib.import_module("nlosjax.physics.reconstruct")   # the module, not the function
    plan = recon._rsd_plan(setup, 3.0, 2.0, 0.1, jnp.float32)
    k, rows, m = plan.bins.shape[0], plan.num_rows, plan.fft_len

    def rsd_floor(v):
      spec = jnp.fft.rfft(jnp.moveaxis(v, 0, -1), axis=-1)[..., :k]        # the wall fields' DTFT
      fields = jnp.fft.fft2(jnp.moveaxis(spec, -1, 0), s=(2 * H, 2 * W))
      grid = jnp.resize(fields, (rows, 2 * H, 2 * W))
      g = jnp.fft.ifft2(grid)[:, :H, :W].reshape(rows, H * W)
      return jnp.fft.ifft(g.T, n=m, axis=-1)
    return rsd_floor
  raise ValueError(f"unknown method {method!r}")

"""Tests of the NumPy/SciPy twins of the public reconstructions (experiments/numpy_twins.py)."""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

from experiments import numpy_twins as tw
from nlosjax.physics.setup import Setup
from tests.xla_options import xla_optimizations


@pytest.fixture(scope="module", autouse=True)
def _optimised_xla():
  # Programs here run long (full captures, samplers, renderers): XLA's optimisations pay for
  # their compile time. The suite turns them off by default (conftest.py).
  with xla_optimizations(True):
    yield


# The measured exit-sign scan ships in the package (nlosjax/data/scans/README.md says where it is from).
EXIT_SIGN = pathlib.Path(__file__).resolve().parents[1] / "nlosjax" / "data" / "scans" / "data_exit_sign.mat"

# 16 x 16 scan, 128 bins of 32 ps: T c dt = 1.23 m >= 2 * wall, so the LCT cone stays in range.
SMALL = Setup(wall_size=0.5, grid=(16, 16), bin_width=32e-12, num_bins=128)


def brute_force_point(setup: Setup, iy: int, ix: int, k: int, albedo: float = 1.0) -> np.ndarray:
  """Transient of one point scatterer in front of scan point (iy, ix), in depth bin k.

  For every scan point: distance r to the scatterer, albedo / r^4 deposited in
  time bin floor(2 r / (c dt)).
  """
  point = np.array([setup.scan_x[ix], setup.scan_y[iy], (k + 0.5) * setup.depth_bin_length])
  tau = np.zeros((setup.num_bins, *setup.grid))
  for i, y in enumerate(setup.scan_y):
    for j, x in enumerate(setup.scan_x):
      r = math.sqrt((point[0] - x) ** 2 + (point[1] - y) ** 2 + point[2] ** 2)
      b = int(math.floor(2.0 * r / setup.bin_length))
      if b < setup.num_bins:
        tau[b, i, j] += albedo / r ** 4
  return tau.astype(np.float32)


# ------------------------------------------------------------------ operators
@pytest.mark.parametrize("m", [16, 64])
def test_resampling_operator_matches_matlab_halving(m):
  # The MATLAB construction: 1/sqrt(x) at (x, ceil(sqrt(x))), mtxi = mtx', then halve log2(M) times.
  x = np.arange(1, m * m + 1)
  big = np.zeros((m * m, m))
  big[x - 1, np.ceil(np.sqrt(x)).astype(int) - 1] = 1.0 / np.sqrt(x)
  mtx_ref, mtxi_ref = big, big.T
  for _ in range(int(round(math.log2(m)))):
    mtx_ref = 0.5 * (mtx_ref[0::2] + mtx_ref[1::2])
    mtxi_ref = 0.5 * (mtxi_ref[:, 0::2] + mtxi_ref[:, 1::2])
  mtx, mtxi = tw.resampling_operator(m)
  np.testing.assert_allclose(mtx.toarray(), mtx_ref, rtol=1e-6, atol=1e-9)
  np.testing.assert_allclose(mtxi.toarray(), mtxi_ref, rtol=1e-6, atol=1e-9)


def test_psf_one_voxel_per_column_and_unit_spectrum():
  m, n = 64, 8
  psf = tw.define_psf(m, n, slope=0.2)
  assert psf.shape == (2 * m, 2 * n, 2 * n)
  assert np.all((psf > 0).sum(axis=0) == 1)
  np.testing.assert_allclose(psf[psf > 0], 1.0 / (2 * n))
  assert psf[0, 0, 0] > 0  # apex rolled to the origin
  power = np.abs(np.fft.fftn(psf)) ** 2
  np.testing.assert_allclose(power.mean(), 1.0, rtol=1e-9)
  np.testing.assert_allclose(power.max(), power[0, 0, 0])
  np.testing.assert_allclose(power[0, 0, 0], 4 * n * n, rtol=1e-9)


def test_psf_drops_columns_whose_cone_leaves_the_range():
  # slope > 0.25: the public code would put spurious ones in the last slice.
  m, n, slope = 32, 8, 0.6
  psf = tw.define_psf(m, n, slope)
  cols = (psf > 0).sum(axis=0)
  assert cols.max() == 1 and 0 < cols.sum() < (2 * n) ** 2
  assert not np.any(psf[-1] > 0)
  np.testing.assert_allclose(np.linalg.norm(psf), 1.0)


# -------------------------------------------------------- point reconstruction
@pytest.mark.parametrize("method", tw.METHODS)
def test_point_scatterer_is_found(method):
  for iy, ix, k in [(7, 9, 75), (5, 10, 60)]:
    vol = tw.reconstruct(brute_force_point(SMALL, iy, ix, k), SMALL, method)
    assert vol.shape == (128, 16, 16) and vol.dtype == np.float32
    assert np.all(np.isfinite(vol)) and vol.min() >= 0 and vol.max() > 0
    z, y, x = np.unravel_index(np.argmax(vol), vol.shape)
    assert abs(y - iy) <= 1 and abs(x - ix) <= 1, (method, (iy, ix), (y, x))
    assert abs(z - k) <= 3, (method, k, z)


def test_depth_range_crops_the_full_volume():
  tau = brute_force_point(SMALL, 7, 9, 75)
  gated = SMALL.with_depth_range(0.2, 0.45)
  k0, k1 = gated.depth_bins
  for method in ("lct", "rsd"):
    full = tw.reconstruct(tau, SMALL, method)
    part = tw.reconstruct(tau, gated, method)
    assert part.shape == (gated.num_depth_bins, 16, 16)
    np.testing.assert_array_equal(part, full[k0:k1])


def test_rectangular_grid_rejected_by_square_methods():
  rect = Setup(wall_size=0.5, grid=(8, 12), bin_width=32e-12, num_bins=64)
  with pytest.raises(ValueError, match="square"):
    tw.build_lct(rect)
  vol = tw.reconstruct(np.ones((64, 8, 12), np.float32), rect, "rsd")  # RSD has no such limit
  assert vol.shape == (64, 8, 12)


# ------------------------------------------- shortcuts equal the plain algorithm
def test_fk_matches_public_style_shifted_stolt():
  """The twin's unshifted, table-driven Stolt step equals the public fftshift/interpn version."""
  setup = Setup(wall_size=0.4, grid=(6, 6), bin_width=32e-12, num_bins=32)
  tau = np.random.default_rng(0).random((32, 6, 6)).astype(np.float32)
  m, n = 32, 6
  width, range_ = setup.wall_size / 2, m * setup.bin_length
  data = np.sqrt(tau * np.linspace(0, 1, m)[:, None, None] ** 2)
  padded = np.zeros((2 * m, 2 * n, 2 * n))
  padded[:m, :n, :n] = data
  psi = np.fft.fftshift(np.fft.fftn(padded))
  z, y, x = np.meshgrid(np.arange(-m, m) / m, np.arange(-n, n) / n, np.arange(-n, n) / n,
                        indexing="ij")
  a = n * range_ / (4 * m * width)
  kz_src = np.sqrt(a ** 2 * (x ** 2 + y ** 2) + z ** 2)
  grid = np.arange(-m, m) / m
  phi = np.zeros_like(psi)
  for i in range(2 * n):
    for j in range(2 * n):
      q = kz_src[:, i, j]
      phi[:, i, j] = (np.interp(q, grid, psi[:, i, j].real, left=0, right=0)
                      + 1j * np.interp(q, grid, psi[:, i, j].imag, left=0, right=0))
  phi *= (z > 0) * np.abs(z) / np.maximum(kz_src, 1e-6)
  ref = np.abs(np.fft.ifftn(np.fft.ifftshift(phi))) ** 2
  ref = ref[:m, :n, :n]
  out = tw.fk(tau, tw.build_fk(setup))
  np.testing.assert_allclose(out, ref, rtol=2e-4, atol=2e-5 * ref.max())


def test_phasor_matches_two_separate_backprojections():
  """Packing cos + i sin into one backprojection equals the public two-pass version."""
  setup = Setup(wall_size=0.2, grid=(8, 8), bin_width=32e-12, num_bins=64)
  tau = np.random.default_rng(1).random((64, 8, 8)).astype(np.float32)
  cos_w, sin_w = tw.phasor_wavelet(setup)
  length = cos_w.shape[0]
  assert length % 2 == 0  # exercises MATLAB's 'same' offset for even lengths
  m, n = 64, 8

  def same(sig, w):  # MATLAB conv(u, v, 'same')
    return np.convolve(sig, w)[length // 2:length // 2 + m]

  mtx, mtxi = (a.toarray().astype(np.float64) for a in tw.resampling_operator(m))
  fpsf = np.fft.fftn(tw.define_psf(m, n, (setup.wall_size / 2) / (m * setup.bin_length)))

  def backproject(vol):
    padded = np.zeros((2 * m, 2 * n, 2 * n))
    padded[:m, :n, :n] = (mtx @ vol.reshape(m, -1)).reshape(m, n, n)
    return np.fft.ifftn(np.fft.fftn(padded) * np.conj(fpsf))[:m, :n, :n]

  conv_c = np.apply_along_axis(same, 0, tau.astype(np.float64), cos_w.astype(np.float64))
  conv_s = np.apply_along_axis(same, 0, tau.astype(np.float64), sin_w.astype(np.float64))
  mag = np.sqrt(backproject(conv_c) ** 2 + backproject(conv_s) ** 2)
  ref = np.maximum(np.real((mtxi @ mag.reshape(m, -1)).reshape(m, n, n)), 0)
  out = tw.phasor(tau, tw.build_phasor(setup))
  np.testing.assert_allclose(out, ref, rtol=1e-3, atol=1e-4 * ref.max())


def test_rsd_matches_direct_propagation():
  """The chunked phase recurrence equals exp(+i z kz) computed per depth."""
  setup = Setup(wall_size=0.3, grid=(6, 8), bin_width=32e-12, num_bins=64)
  tau = np.random.default_rng(2).random((64, 6, 8)).astype(np.float32)
  ops = tw.build_rsd(setup, chunk=5)
  spec = np.fft.rfft(tau.astype(np.float64), axis=0)[ops.freq_index] * ops.weight[:, None, None]
  field = np.fft.fft2(spec, s=(12, 16), axes=(1, 2)) * ops.mask
  kz = ops.kz.astype(np.float64)
  ref = np.empty((64, 6, 8))
  for j in range(64):
    plane = (field * np.exp(1j * j * ops.dz * kz)).sum(axis=0)
    ref[j] = np.abs(np.fft.ifft2(plane)[:6, :8])
  for chunk in (5, 64):
    out = tw.rsd(tau, tw.build_rsd(setup, chunk=chunk))
    np.testing.assert_allclose(out, ref, rtol=1e-3, atol=1e-4 * ref.max())


# ------------------------------------------------------------- measured data
def test_exit_sign_reconstructs_to_a_compact_object():
  tau, setup = tw.load_published(EXIT_SIGN)          # 16 ps, 512 bins, direct reflection zeroed
  assert tau.shape == (512, 64, 64)
  options = {"lct": {"snr": 0.8, "falloff": "retroreflective"},
             "fbp": {"falloff": "retroreflective"}}
  for method in tw.METHODS:
    vol = tw.reconstruct(tau, setup, method, **options.get(method, {}))
    assert vol.shape == (512, 64, 64) and np.all(np.isfinite(vol)) and vol.min() >= 0
    mip = vol.max(axis=0)
    energy = (mip / mip.max()) ** 2
    # The sign fills the middle of the scan: its 48 x 48 central box (56 % of
    # the area) holds ~0.8-0.9 of the MIP energy; uniform noise gives 0.56,
    # and a zero-padded -LoG FBP's bright border frame 0.04.
    central = energy[8:56, 8:56].sum() / energy.sum()
    assert central > 0.72, (method, central)


@pytest.mark.parametrize("method", tw.METHODS)
def test_benchmark_fft_floor_runs_the_methods_ffts(method):
  """``benchmarks.physics.fft_floor``: each method's FFTs alone compile and give finite numbers,
  and the goal line calls a method met only when both ratios hold."""
  import jax.numpy as jnp

  from benchmarks import physics as bench
  setup = Setup(wall_size=1.0, grid=(8, 8), bin_width=32e-12, num_bins=64)
  x = jnp.asarray(np.random.default_rng(0).poisson(1.0, (64, 8, 8)), jnp.float32)
  out = np.asarray(bench.fft_floor(method, setup)(x))
  assert np.all(np.isfinite(out))
  rows = [{"method": "a", "n": 64, "speedup": 1.2, "over_floor": 1.1},
          {"method": "b", "n": 64, "speedup": 0.9, "over_floor": 1.1},
          {"method": "c", "n": 64, "speedup": 2.0, "over_floor": 1.5}]
  line = bench.goal_summary(rows)[0]
  assert line.startswith("- 64²: met by a;") and "b (1.10× floor, 0.90× twin)" in line and "c (1.50×" in line


def test_published_preparation_twin_matches_the_library_reader():
  """The twins' SciPy reading of the exit-sign scan equals ``load_measurement``'s, array and Setup."""
  from nlosjax.data import load_measurement
  tau, setup = tw.load_published(EXIT_SIGN)
  ours, ours_setup = load_measurement(EXIT_SIGN)
  np.testing.assert_array_equal(ours, tau)
  assert (ours_setup.wall_size, ours_setup.grid, ours_setup.bin_width, ours_setup.num_bins) == \
      (setup.wall_size, setup.grid, setup.bin_width, setup.num_bins)

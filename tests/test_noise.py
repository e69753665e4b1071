"""Tests of the SPAD detector model (nlosjax.physics.noise)."""

from __future__ import annotations

import math

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nlosjax.physics.noise import (
  LARGE_RATE_THRESHOLD,
  MEASURED_JITTER_PATH,
  add_spad_noise,
  expected_counts,
  jitter_kernel,
  load_measured_jitter,
)
from nlosjax.physics.setup import Setup
from tests.xla_options import xla_optimizations


@pytest.fixture(scope="module", autouse=True)
def _optimised_xla():
  # Programs here run long (full captures, samplers, renderers): XLA's optimisations pay for
  # their compile time. The suite turns them off by default (conftest.py).
  with xla_optimizations(True):
    yield


SETUP = Setup(1.0, (4, 4), 32e-12, 64)
T, H, W = 64, 4, 4
# Statistical tests draw M examples at once. They share the shape [M, T, H, W]
# and the others [T, H, W], so the Poisson sampler compiles only twice.
M = 1000


def _fwhm(kernel, bin_width):
  """FWHM in seconds of a single-peaked curve, half-max crossings linearly interpolated."""
  k = np.asarray(kernel, np.float64)
  i = int(np.argmax(k))
  half = k[i] / 2
  left = np.nonzero(k[:i] < half)[0][-1]          # k[left] < half <= k[left + 1]
  right = i + np.nonzero(k[i:] < half)[0][0]      # k[right - 1] >= half > k[right]
  x_left = left + (half - k[left]) / (k[left + 1] - k[left])
  x_right = right - 1 + (k[right - 1] - half) / (k[right - 1] - k[right])
  return (x_right - x_left) * bin_width


def _reference_rate(transient, kernel, gain, background):
  """Independent numpy model: gain * (transient (*) kernel) + background, 'same' window."""
  x = np.asarray(transient, np.float64)
  if kernel is not None:
    k = np.asarray(kernel, np.float64)
    c = len(k) // 2
    x = np.apply_along_axis(lambda v: np.convolve(v, k)[c:c + x.shape[-3]], -3, x)
  return gain * x + background


def _moment_z_scores(samples, lam):
  """Per-bin z-scores of the sample mean and (unbiased) variance against Poisson(lam)."""
  s = np.asarray(samples, np.float64)
  m = s.shape[0]
  lam = np.asarray(lam, np.float64)
  z_mean = (s.mean(0) - lam) / np.sqrt(lam / m)
  # Var of the sample variance of Poisson(lam): (mu4 - sigma^4) / m = (lam + 2 lam^2) / m.
  z_var = (s.var(0, ddof=1) - lam) / np.sqrt((lam + 2 * lam**2) / m)
  return z_mean, z_var


def _check_poisson_moments(samples, lam, z_max=5.5):
  z_mean, z_var = _moment_z_scores(samples, lam)
  n = z_mean.size
  assert np.abs(z_mean).max() < z_max, np.abs(z_mean).max()
  assert np.abs(z_var).max() < z_max, np.abs(z_var).max()
  # Pooled over bins: the average z is ~ N(0, 1/n).
  assert abs(z_mean.mean()) < 5 / math.sqrt(n), z_mean.mean()
  assert abs(z_var.mean()) < 5 / math.sqrt(n), z_var.mean()


# ------------------------------------------------------------------ counts
def test_counts_mean_and_variance_match_rate():
  rng = np.random.default_rng(0)
  # Rates from ~0.03 to ~5e3 counts per bin, all below the Gaussian threshold.
  per_pulse = 10.0 ** rng.uniform(-2.0, 3.2, size=(T, H, W)).astype(np.float32)
  batch = np.broadcast_to(per_pulse, (M, T, H, W))
  opts = dict(pulses=2.0, efficiency=0.6, ambient=0.05, dark_counts=0.01, jitter=70e-12)
  lam = np.asarray(expected_counts(per_pulse, SETUP, **opts), np.float64)
  assert lam.max() < LARGE_RATE_THRESHOLD
  counts = np.asarray(add_spad_noise(jax.random.key(1), batch, SETUP, **opts))
  assert counts.dtype == np.float32 and counts.shape == (M, T, H, W)
  assert np.all(counts == np.round(counts)) and counts.min() >= 0
  _check_poisson_moments(counts, lam)


def test_large_rates_have_poisson_mean_and_variance():
  # The Gaussian branch (lam >= 1e4). jax.random.poisson alone has a variance
  # 2.5 % too high at 1e6 and 60 % at 1e9, which the pooled test detects.
  rates = np.repeat(np.array([2e4, 1e6, 1e8, 1e9], np.float32), T * H * W // 4).reshape(T, H, W)
  counts = np.asarray(add_spad_noise(jax.random.key(2), np.broadcast_to(rates, (M, T, H, W)),
                                     SETUP, pulses=1.0))
  assert np.all(np.isfinite(counts)) and counts.min() >= 0
  for value in np.unique(rates):
    sel = rates == value
    _check_poisson_moments(counts[:, sel], rates[sel])


def test_expected_counts_match_independent_reference():
  rng = np.random.default_rng(1)
  x = rng.random((2, T, H, W)).astype(np.float32)
  for jitter in (None, 70e-12, "measured", np.array([0.2, 0.5, 0.3])):
    lam = np.asarray(expected_counts(x, SETUP, pulses=50.0, efficiency=0.4, ambient=0.3,
                                     dark_counts=0.02, jitter=jitter), np.float64)
    kernel = None if jitter is None else jitter_kernel(SETUP, jitter)
    ref = _reference_rate(x, kernel, 0.4 * 50.0, 0.4 * 0.3 + 0.02)
    np.testing.assert_allclose(lam, ref, rtol=2e-6, atol=1e-5 * ref.max())


def test_photons_per_point_normalisation_per_example():
  rng = np.random.default_rng(2)
  scales = np.array([1e-6, 1.0, 3e4], np.float32)[:, None, None, None]
  x = rng.random((3, T, H, W)).astype(np.float32) * scales
  for budget, eta in ((100.0, 0.4), (1.0, 1.0)):
    lam = np.asarray(expected_counts(x, SETUP, photons_per_point=budget, efficiency=eta),
                     np.float64)
    per_point = lam.sum(axis=-3).mean(axis=(-2, -1))
    np.testing.assert_allclose(per_point, budget * eta, rtol=1e-5)
  # With background: the signal part still carries S * eta photons per point.
  lam = np.asarray(expected_counts(x, SETUP, photons_per_point=100.0, efficiency=0.5,
                                   ambient=0.2, dark_counts=0.1), np.float64)
  signal = lam - (0.5 * 0.2 + 0.1)
  np.testing.assert_allclose(signal.sum(axis=-3).mean(axis=(-2, -1)), 50.0, rtol=1e-5)


def test_pulses_scale_is_linear_and_unnormalised():
  x = np.full((T, H, W), 0.25, np.float32)
  lam = np.asarray(expected_counts(x, SETUP, pulses=8.0, efficiency=0.5))
  np.testing.assert_allclose(lam, 1.0, rtol=1e-6)


# ------------------------------------------------------------------ jitter
@pytest.mark.parametrize("fwhm", [70e-12, 100e-12, 300e-12])
def test_gaussian_kernel_fwhm_and_shape(fwhm):
  bin_width = 4e-12
  k = jitter_kernel(bin_width, fwhm)
  sigma_bins = fwhm / 2.3548 / bin_width
  assert k.dtype == np.float32 and k.ndim == 1 and len(k) % 2 == 1
  assert len(k) // 2 == math.ceil(4 * sigma_bins)        # truncated at +-4 sigma
  assert int(np.argmax(k)) == len(k) // 2
  assert abs(float(k.sum(dtype=np.float64)) - 1) < 1e-6
  np.testing.assert_allclose(k, k[::-1], atol=1e-7)
  assert _fwhm(k, bin_width) == pytest.approx(fwhm, rel=0.01)


def test_narrow_gaussian_kernel_keeps_one_bin_each_side():
  k = jitter_kernel(SETUP, 1e-12)
  assert len(k) == 3 and k[1] == pytest.approx(1.0) and np.all(k >= 0)
  assert np.array_equal(jitter_kernel(SETUP, 0.0), np.ones(1, np.float32))


def test_kernel_is_cached_and_read_only():
  a = jitter_kernel(SETUP, 70e-12)
  assert a is jitter_kernel(32e-12, 70e-12)
  assert jitter_kernel(SETUP, "measured") is jitter_kernel(SETUP, "measured")
  with pytest.raises(ValueError):
    a[0] = 1.0


def test_measured_curve_file():
  assert MEASURED_JITTER_PATH.is_file()
  with h5py.File(MEASURED_JITTER_PATH, "r") as f:
    assert f["t_1"].shape == (1, 901) and f["counts_1"].shape == (1, 901)
  t, counts = load_measured_jitter()
  assert t[int(np.argmax(counts))] == pytest.approx(0.0, abs=1e-12)
  assert 30e-12 < _fwhm_curve(t, counts) < 45e-12


def _fwhm_curve(t, counts):
  i = int(np.argmax(counts))
  half = counts[i] / 2
  left = np.nonzero(counts[:i] < half)[0][-1]
  right = i + np.nonzero(counts[i:] < half)[0][0]
  t_left = np.interp(half, counts[left:left + 2], t[left:left + 2])
  t_right = np.interp(half, counts[right - 1:right + 1][::-1], t[right - 1:right + 1][::-1])
  return t_right - t_left


def test_measured_kernel_at_4ps():
  bin_width = 4e-12
  k = jitter_kernel(bin_width, "measured")
  c = len(k) // 2
  assert k.dtype == np.float32 and len(k) % 2 == 1 and int(np.argmax(k)) == c
  assert abs(float(k.sum(dtype=np.float64)) - 1) < 1e-6 and k.min() >= 0
  assert 25e-12 <= _fwhm(k, bin_width) <= 50e-12
  # The long tail is kept: several percent of the mass beyond +100 ps.
  delay = (np.arange(len(k)) - c) * bin_width
  assert k[delay > 100e-12].sum() > 0.02
  assert (k * delay).sum() > 10e-12   # mean delay after the peak (~19 ps)


def test_measured_kernel_matches_binned_samples():
  # Independent binning: each raw sample's counts go to the bin nearest its time.
  t, counts = load_measured_jitter()
  bin_width = 32e-12
  k = jitter_kernel(SETUP, "measured")
  c = len(k) // 2
  idx = np.round((t - t[np.argmax(counts)]) / bin_width).astype(int) + c
  hist = np.bincount(idx, weights=counts * np.gradient(t), minlength=len(k))
  hist /= hist.sum()
  assert len(hist) == len(k)
  np.testing.assert_allclose(k, hist, atol=0.01)
  assert int(np.argmax(k)) == c and abs(float(k.sum(dtype=np.float64)) - 1) < 1e-6


def test_user_kernel_is_normalised_and_validated():
  k = jitter_kernel(SETUP, [1.0, 2.0, 1.0])
  np.testing.assert_allclose(k, [0.25, 0.5, 0.25], rtol=1e-7)
  for bad in ([1.0, np.nan, 1.0], [1.0, -0.1, 1.0], [0.0, 0.0, 0.0], [1.0, 1.0],
              np.ones((3, 3)), []):
    with pytest.raises(ValueError, match="jitter"):
      jitter_kernel(SETUP, bad)
  for bad in ("gaussian", -1e-12, float("nan"), 70.0):
    with pytest.raises(ValueError, match="jitter"):
      jitter_kernel(SETUP, bad)


@pytest.mark.parametrize("jitter, bin_width", [(70e-12, 32e-12), ("measured", 32e-12),
                                               ("measured", 4e-12)])
def test_delta_convolution_reproduces_kernel(jitter, bin_width):
  # Short Gaussian (shift-and-add), and measured kernels of 41 and 325 taps (FFT);
  # at 4 ps the kernel is much longer than the 64-bin window.
  setup = Setup(1.0, (4, 4), bin_width, T)
  k = jitter_kernel(setup, jitter).astype(np.float64)
  c = len(k) // 2
  for t0 in (0, 20, T - 1):
    x = np.zeros((T, H, W), np.float32)
    x[t0, 1, 2] = 1.0
    lam = np.asarray(expected_counts(x, setup, pulses=1.0, jitter=jitter), np.float64)
    delta = np.zeros(T)
    delta[t0] = 1.0
    expected = np.convolve(delta, k)[c:c + T]
    np.testing.assert_allclose(lam[:, 1, 2], expected, atol=1e-6)
    lam[:, 1, 2] = 0
    assert np.all(lam == 0)


def test_delta_kernel_is_identity_and_energy_is_preserved():
  rng = np.random.default_rng(3)
  x = rng.random((T, H, W)).astype(np.float32)
  for kernel in ([1.0], [0.0, 1.0, 0.0]):
    lam = np.asarray(expected_counts(x, SETUP, pulses=1.0, jitter=np.array(kernel)))
    np.testing.assert_array_equal(lam, x)
  # A pulse far from the window's edges keeps all its energy.
  x = np.zeros((T, H, W), np.float32)
  x[30:34] = 1.0
  lam = np.asarray(expected_counts(x, SETUP, pulses=1.0, jitter=100e-12), np.float64)
  np.testing.assert_allclose(lam.sum(axis=0), 4.0, rtol=1e-6)
  assert not np.allclose(lam, x)


# -------------------------------------------------------------- background
def test_ambient_and_dark_counts_add_the_right_level():
  x = np.zeros((T, H, W), np.float32)
  lam = np.asarray(expected_counts(x, SETUP, pulses=100.0, efficiency=0.6, ambient=0.3,
                                   dark_counts=0.05))
  np.testing.assert_allclose(lam, 0.6 * 0.3 + 0.05, rtol=1e-6)
  counts = np.asarray(add_spad_noise(jax.random.key(4), np.zeros((M, T, H, W), np.float32),
                                     SETUP, pulses=100.0, efficiency=0.6, ambient=0.3,
                                     dark_counts=0.05), np.float64)
  level, n = 0.6 * 0.3 + 0.05, counts.size
  assert abs(counts.mean() - level) < 5 * math.sqrt(level / n)
  assert abs(counts.var() - level) < 5 * math.sqrt((level + 2 * level**2) / n)
  # Dark counts alone are not scaled by the efficiency.
  lam = np.asarray(expected_counts(x, SETUP, pulses=1.0, efficiency=0.1, dark_counts=0.7))
  np.testing.assert_allclose(lam, 0.7, rtol=1e-6)


def test_zero_photon_input_gives_exact_zeros():
  x = np.zeros((T, H, W), np.float32)
  for opts in (dict(photons_per_point=100.0), dict(pulses=1e6, jitter="measured"),
               dict(photons_per_point=5.0, jitter=70e-12, efficiency=0.3)):
    lam = np.asarray(expected_counts(x, SETUP, **opts))
    counts = np.asarray(add_spad_noise(jax.random.key(5), x, SETUP, **opts))
    assert not np.any(np.isnan(lam)) and not np.any(np.isnan(counts))
    assert np.all(lam == 0) and np.all(counts == 0)


def test_single_photon():
  x = np.zeros((M, T, H, W), np.float32)
  x[:, 10, 2, 3] = 1.0
  counts = np.asarray(add_spad_noise(jax.random.key(6), x, SETUP, pulses=1.0))
  assert np.all(np.isfinite(counts)) and counts.min() >= 0
  assert np.all(counts == np.round(counts))
  mask = np.ones((T, H, W), bool)
  mask[10, 2, 3] = False
  assert np.all(counts[:, mask] == 0)
  hits = counts[:, 10, 2, 3]      # one draw of Poisson(1) per example
  assert abs(hits.mean() - 1.0) < 5 * math.sqrt(1.0 / M)
  assert abs(hits.var() - 1.0) < 5 * math.sqrt(3.0 / M)
  # ... and the same single photon in one example: a finite count in that bin only.
  one = np.asarray(add_spad_noise(jax.random.key(6), x[0], SETUP, pulses=1.0))
  assert np.all(np.isfinite(one)) and one.min() >= 0 and np.all(one[mask] == 0)


def test_huge_rates_give_finite_sane_counts():
  x = np.full((T, H, W), 1e9, np.float32)
  counts = np.asarray(add_spad_noise(jax.random.key(7), x, SETUP, pulses=1.0), np.float64)
  assert np.all(np.isfinite(counts)) and counts.min() >= 0
  assert np.abs(counts - 1e9).max() < 6 * math.sqrt(1e9)
  assert counts.std() > 0.5 * math.sqrt(1e9)            # noisy, not a constant
  # Beyond int32 (where jax.random.poisson saturates at 2**31 - 1).
  counts = np.asarray(add_spad_noise(jax.random.key(8), x, SETUP, pulses=10.0), np.float64)
  assert np.abs(counts - 1e10).max() < 6 * math.sqrt(1e10)
  # An overflowing rate is clamped, not propagated as inf or NaN.
  counts = np.asarray(add_spad_noise(jax.random.key(9), np.full((T, H, W), 1e30, np.float32),
                                     SETUP, pulses=1e30))
  assert np.all(np.isfinite(counts)) and counts.min() > 0


# --------------------------------------------------------------------- keys
def test_keys_control_the_draw():
  x = np.full((T, H, W), 0.5, np.float32)
  a = np.asarray(add_spad_noise(jax.random.key(10), x, SETUP, pulses=10.0))
  b = np.asarray(add_spad_noise(jax.random.key(10), x, SETUP, pulses=10.0))
  c = np.asarray(add_spad_noise(jax.random.key(11), x, SETUP, pulses=10.0))
  d = np.asarray(add_spad_noise(jax.random.PRNGKey(10), x, SETUP, pulses=10.0))
  np.testing.assert_array_equal(a, b)
  assert not np.array_equal(a, c)
  assert d.shape == a.shape and np.all(d >= 0)


# --------------------------------------------------------------- transforms
def test_works_under_jit_and_vmap_with_traced_options():
  rng = np.random.default_rng(4)
  x = rng.random((T, H, W)).astype(np.float32)
  key = jax.random.key(12)

  @jax.jit
  def f(key, x, ambient):
    return add_spad_noise(key, x, SETUP, pulses=20.0, ambient=ambient, jitter=70e-12)

  eager = np.asarray(add_spad_noise(key, x, SETUP, pulses=20.0, ambient=0.5, jitter=70e-12))
  np.testing.assert_array_equal(np.asarray(f(key, x, 0.5)), eager)

  xs = np.stack([x, 3 * x])
  rate = jax.vmap(lambda xi: expected_counts(xi, SETUP, photons_per_point=10.0))(jnp.asarray(xs))
  np.testing.assert_allclose(np.asarray(rate), np.asarray(expected_counts(xs, SETUP,
                                                                          photons_per_point=10.0)),
                             rtol=1e-6)
  # Traced inputs are not validated, but a NaN rate is still guarded to 0.
  bad = np.full((T, H, W), np.nan, np.float32)
  assert np.all(np.asarray(f(key, bad, 0.0)) == 0)
  assert np.all(np.asarray(f(key, x, jnp.nan)) == 0)


# --------------------------------------------------------------- validation
def test_invalid_inputs_raise_value_errors_naming_the_argument():
  x = np.ones((T, H, W), np.float32)
  key = jax.random.key(0)
  nan = x.copy()
  nan[3, 1, 1] = np.nan
  neg = x.copy()
  neg[3, 1, 1] = -1e-3
  inf = x.copy()
  inf[0, 0, 0] = np.inf
  cases = [
      (dict(transient=nan), "transient.*NaN"),
      (dict(transient=jnp.asarray(nan)), "transient.*NaN"),
      (dict(transient=inf), "transient"),
      (dict(transient=neg), "transient.*negative"),
      (dict(transient=np.ones((T, H, W + 1), np.float32)), "transient"),
      (dict(transient=np.ones((T - 1, H, W), np.float32)), "transient"),
      (dict(transient=np.ones((T, H), np.float32)), "transient"),
      (dict(pulses=1.0, photons_per_point=1.0), "photons_per_point"),
      (dict(pulses=None), "photons_per_point"),
      (dict(efficiency=0.0), "efficiency"),
      (dict(efficiency=1.5), "efficiency"),
      (dict(efficiency=float("nan")), "efficiency"),
      (dict(ambient=-0.1), "ambient"),
      (dict(dark_counts=-1.0), "dark_counts"),
      (dict(pulses=0.0), "pulses"),
      (dict(pulses=None, photons_per_point=-5.0), "photons_per_point"),
      (dict(jitter="gaussian"), "jitter"),
      (dict(jitter=-1e-12), "jitter"),
      (dict(dtype=jnp.int32), "dtype"),
      (dict(setup=(4, 4)), "setup"),
  ]
  for overrides, match in cases:
    kwargs = dict(transient=x, setup=SETUP, pulses=1.0)
    kwargs.update(overrides)
    transient, setup = kwargs.pop("transient"), kwargs.pop("setup")
    with pytest.raises(ValueError, match=match):
      add_spad_noise(key, transient, setup, **kwargs)
    with pytest.raises(ValueError, match=match):
      expected_counts(transient, setup, **kwargs)

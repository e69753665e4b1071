"""Stability of the physics at the extremes: finite outputs *and* a bounded deviation.

The extremes, and the reference each is held to:

* detection efficiency 0.1 % and 100 %: the SPAD rate against its closed form
  ``eta (s (tau (*) g) + ambient) + dark`` (NumPy), Poisson draws against that
  rate (mean per bin, and the fraction of all-zero histograms against
  ``exp(-sum_t lam)``), traced against concrete efficiency, bfloat16 draws
  against float32 ones;
* zero-photon and saturated (1e9 counts, 65535 in every bin) frames: every
  classic method is positively homogeneous of degree 1 (``fk`` too: it squares
  a square root), so ``recon(c x) = c recon(x)`` and zero in gives exactly zero out;
* scan grids: 2 x 2 and 12 x 12 (every method, against float64) and the paper's
  128 x 128 x 512 (LCT: a point found where it is);
* depth ranges: one bin (gated volume against the ungated one's slice) and the
  full range (equal to ungated), for every method;
* bad values (NaN, +inf, a negative count) under ``physics.checks.checked``:
  every classic method, through ``reconstruct`` and its own function, raises
  ``ValueError`` naming the problem;
* operators first built inside a user's ``jit`` work eagerly after.

Covered elsewhere: every method on zero / one-photon / 1e9 inputs and a 1-bin
range is finite and LCT ``snr`` extremes (``test_physics``); zero-photon and
1e9-rate SPAD draws (``test_noise``). The network and losses:
``test_stability_network``; the metrics: ``test_stability_metrics``.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nlosjax import physics
from nlosjax.physics import Setup, checks, reconstruct, render_points
from tests.stability import (
  BAD_VALUES,
  assert_finite_nonnegative,
  fast_compiles,  # noqa: F401 (the module's fixture, by name below)
  peak,
  rel_dev,
)
from tests.xla_options import xla_optimizations

pytestmark = pytest.mark.usefixtures("fast_compiles")


# ==================================================================== SPAD noise
# tests/test_noise.py's SETUP and M: run in one process, the Poisson sampler compiles once.
NOISE = Setup(1.0, (4, 4), 32e-12, 64)
M = 1000


@pytest.fixture
def _optimized():
  """XLA's optimisations back on: the Poisson sampler's rejection loop runs 3x slower without."""
  with xla_optimizations(True):
    yield


@pytest.mark.parametrize("efficiency", [1e-3, 1.0])
@pytest.mark.usefixtures("_optimized")
def test_efficiency_extremes_match_the_closed_form_rate_and_poisson_draws(efficiency):
  clean = render_points(np.array([[0.1, -0.1, 0.2]]), 1.0, NOISE)            # [T, H, W]
  opts = dict(photons_per_point=2000.0, ambient=0.5, dark_counts=0.05, jitter=70e-12)
  lam = np.asarray(physics.expected_counts(clean.astype(np.float32), NOISE,
                                           efficiency=efficiency, **opts), np.float64)
  # Closed form in float64: s = S / mean_points sum_t tau; jitter as a centred 'same' convolution.
  s = 2000.0 / clean.sum(0).mean()
  g = physics.jitter_kernel(NOISE, 70e-12).astype(np.float64)
  c = g.size // 2
  conv = np.apply_along_axis(lambda v: np.convolve(v, g)[c:c + NOISE.num_bins], 0, clean)
  ref = efficiency * (s * conv + 0.5) + 0.05
  np.testing.assert_allclose(lam, ref, rtol=1e-5, atol=1e-6 * ref.max())
  # A traced efficiency is never skipped (1.0 is, when concrete): both give the same rate.
  traced = jax.jit(lambda e: physics.expected_counts(clean.astype(np.float32), NOISE,
                                                     efficiency=e, **opts))(efficiency)
  np.testing.assert_allclose(traced, lam, rtol=1e-6, atol=1e-7 * lam.max())

  batch = np.broadcast_to(clean.astype(np.float32), (M,) + clean.shape)
  key = jax.random.key(11)
  counts = np.asarray(physics.add_spad_noise(key, batch, NOISE, efficiency=efficiency, **opts),
                      np.float64)
  assert np.all(np.isfinite(counts)) and counts.min() >= 0 and np.all(counts == np.round(counts))
  z = (counts.mean(0) - lam) / np.sqrt(lam / M)
  assert np.abs(z).max() < 5.5, np.abs(z).max()
  assert abs(z.mean()) < 5 / math.sqrt(z.size), z.mean()
  # Empty histograms: P(all T bins of a scan point are 0) = exp(-sum_t lam). At 0.1 % about 1
  # histogram in 190 is empty (zero-photon frames happen); at 100 % none.
  expected_empty = M * float(np.sum(np.exp(-lam.sum(0))))
  empty = int(np.sum(np.all(counts == 0, axis=1)))
  assert abs(empty - expected_empty) <= 5 * math.sqrt(expected_empty) + 1, (empty, expected_empty)
  # bfloat16 counts: the same draw, rounded once (integers up to 256 are exact in bfloat16).
  bf16 = physics.add_spad_noise(key, batch, NOISE, efficiency=efficiency, dtype=jnp.bfloat16,
                                **opts)
  assert bf16.dtype == jnp.bfloat16
  np.testing.assert_array_equal(np.asarray(bf16, np.float32),
                                np.asarray(jnp.asarray(counts, jnp.float32).astype(jnp.bfloat16),
                                           np.float32))
  # The sparse 0.1 % histograms reconstruct to a finite, non-negative volume.
  assert_finite_nonnegative(reconstruct(counts[0].astype(np.float32), NOISE, "lct"), "lct")


# ============================================ classic methods: medium and 2 x 2 grids
MID = Setup(1.0, (12, 12), 32e-12, 256)
MID_POINTS = np.array([[0.1, -0.2, 0.8], [-0.2, 0.15, 0.6]])


@functools.lru_cache(maxsize=None)
def _mid_transient() -> np.ndarray:
  """``[T, H, W]`` float32 counts of two points (peak ~1e3)."""
  x = render_points(MID_POINTS, 1.0, MID)
  return (x / x.max() * 1e3).astype(np.float32)


def _stack(x: np.ndarray) -> np.ndarray:
  """``[4, T, H, W]``: the frame, the frame saturated to 1e9 counts, a zero-photon frame, and
  the frame rounded to bfloat16 (as float32)."""
  bf = np.asarray(jnp.asarray(x).astype(jnp.bfloat16), np.float32)
  return np.stack([x, x * np.float32(1e9 / x.max()), np.zeros_like(x), bf])


@functools.lru_cache(maxsize=None)
def _mid_volumes(method: str) -> np.ndarray:
  """Ungated ``[4, Z, H, W]`` volumes of :func:`_stack` (one compile per method)."""
  return np.asarray(reconstruct(_stack(_mid_transient()), MID, method))


def _check_stack(out: np.ndarray, x: np.ndarray, method: str, setup: Setup, **opts) -> None:
  """The four rows of a reconstructed :func:`_stack`: finite, homogeneous, zero, bfloat16-exact."""
  assert_finite_nonnegative(out, method)
  scale = 1e9 / float(x.max())
  assert rel_dev(out[1] / scale, out[0]) < 1e-5, (method, rel_dev(out[1] / scale, out[0]))
  assert np.all(out[2] == 0), method
  # bfloat16 input: converted to float32 exactly, so the same volume as its float32 values (row 3).
  bf = np.asarray(reconstruct(jnp.asarray(_stack(x)).astype(jnp.bfloat16), setup, method, **opts))
  np.testing.assert_array_equal(bf[0], out[3])


@pytest.mark.parametrize("method", physics.METHODS)
def test_medium_grid_matches_float64_and_is_homogeneous_from_zero_to_saturated(method):
  x = _mid_transient()
  out = _mid_volumes(method)
  _check_stack(out, x, method, MID)
  with jax.enable_x64(True):
    ref = np.asarray(reconstruct(x.astype(np.float64), MID, method))
  assert ref.dtype == np.float64
  # Measured float32 vs float64: 0.9e-7 (lct) .. 4.5e-7 (fk) of the peak.
  assert rel_dev(out[0], ref) < 1e-5, (method, rel_dev(out[0], ref))
  # Images: a saturated frame gives the same intensity and depth maps.
  i0, d0 = physics.intensity_depth(out[0], MID)
  i1, d1 = physics.intensity_depth(out[1], MID)
  np.testing.assert_allclose(i1, i0, atol=1e-5)
  assert np.mean(np.asarray(d1) == np.asarray(d0)) > 0.99


GRID2 = Setup(0.2, (2, 2), 32e-12, 128)       # 2 x 2 scan points, 20 cm apart


@pytest.mark.parametrize("method", physics.METHODS)
def test_two_by_two_scan_grid(method):
  """A point straight in front of scan point (1, 1), 0.4 m deep (bin 83.4)."""
  x = render_points(np.array([[0.1, 0.1, 0.4]]), 1.0, GRID2)
  x = (x / x.max() * 1e3).astype(np.float32)
  # The refined operators (true spacing, footprint-averaged cone): the public PSF's
  # implied wall / N spacing and half-pixel apex put this point at bin 91 on 2 x 2.
  opts = {"variant": "refined"} if method in ("fbp", "lct", "fk", "phasor") else {}
  out = np.asarray(reconstruct(_stack(x), GRID2, method, **opts))
  assert out.shape == (4, 128, 2, 2)
  _check_stack(out, x, method, GRID2, **opts)
  with jax.enable_x64(True):
    ref = np.asarray(reconstruct(x.astype(np.float64), GRID2, method, **opts))
  assert rel_dev(out[0], ref) < 1e-5, (method, rel_dev(out[0], ref))    # measured <= 3.5e-7
  k, i, j = peak(out[0])
  assert (i, j) == (1, 1), (method, k, i, j)
  if method != "rsd":
    # RSD's virtual wavelength here is 0.8 m (4 x the 20 cm spacing, 83 bins): its peak sits
    # 14 bins early; the others are within 2.4 bins (measured: 81, 81, 83, 85 for 83.4).
    assert abs(k - 0.4 / GRID2.depth_bin_length) <= 3, (method, k)


@pytest.mark.parametrize("method", ["fbp", "lct", "phasor", "render"])
def test_a_grid_whose_light_cone_misses_every_bin_raises(method):
  """Regression: 2 x 2 points 2 m apart seen over 0.32 m of depth. Every footprint sample of the
  light cone lies beyond the last bin, so the PSF was empty and every volume NaN."""
  coarse = Setup(2.0, (2, 2), 264e-12, 8)
  with pytest.raises(ValueError, match="light cone"):
    if method == "render":
      physics.render(np.ones((8, 2, 2), np.float32), coarse)
    else:
      reconstruct(np.ones((8, 2, 2), np.float32), coarse, method)


@pytest.mark.full
def test_paper_grid_lct_finds_a_point():
  """128 x 128 scan points, 512 bins of 33 ps (the paper's synthetic capture); ~6 s."""
  setup = Setup(2.0, (128, 128), 33e-12, 512)
  x = render_points(np.array([[0.3, -0.2, 1.0]]), 1.0, setup)
  out = np.asarray(reconstruct((x / x.max() * 1e9).astype(np.float32), setup, "lct"))
  assert out.shape == (512, 128, 128)
  assert_finite_nonnegative(out)
  k, i, j = peak(out)
  assert abs(i - np.argmin(np.abs(setup.scan_y + 0.2))) <= 1
  assert abs(j - np.argmin(np.abs(setup.scan_x - 0.3))) <= 1
  assert abs(k - 1.0 / setup.depth_bin_length) <= 3


# ---------------------------------------------------------------- depth ranges
# One depth bin around the 0.8 m point (bin 166): the gated volume against the ungated volume's
# slice, relative to the ungated peak. Measured: fbp 1.0e-4, rsd 2.4e-7, phasor 2.1e-3,
# lct 3.2e-2, fk 6.5e-2. fbp and rsd were 9.6e-3 and 6.0e-2 before their gating fixes (the
# -LoG margin bins lacked their time bins; RSD ignored the wavelet's half-length before the
# range). LCT's Wiener filter is not local; f-k zeroes every bin before the range, and its
# migration filter rings from that edge (measured: 32 kept bins would bring it to 5e-4).
ONE_BIN_TOL = {"fbp": 5e-4, "rsd": 1e-5, "phasor": 1e-2, "lct": 5e-2, "fk": 1e-1}


@pytest.mark.parametrize("method", physics.METHODS)
def test_one_bin_and_full_depth_ranges(method):
  x = _mid_transient()
  full = _mid_volumes(method)
  dz = MID.depth_bin_length
  one = MID.with_depth_range(166.0 * dz - 0.2 * dz, 166.0 * dz + 0.2 * dz)
  assert one.depth_bins == (166, 167) and one.time_bins[0] == 166
  out = np.asarray(reconstruct(_stack(x), one, method))
  assert out.shape == (4, 1, 12, 12)
  _check_stack(out, x, method, one)
  dev = np.max(np.abs(out[0] - full[0, 166:167])) / full[0].max()
  assert dev <= ONE_BIN_TOL[method], (method, dev)
  # The full range, and one reaching beyond the last bin, are the ungated capture.
  for z_range in ((0.0, MID.max_depth), (0.0, 100.0)):
    whole = MID.with_depth_range(*z_range)
    assert whole.depth_bins == whole.time_bins == (0, MID.num_bins)
    got = np.asarray(reconstruct(_stack(x), whole, method))
    np.testing.assert_allclose(got, full, rtol=0, atol=1e-6 * full[0].max())


def test_operators_built_first_inside_a_user_jit_do_not_leak_tracers():
  """Each method's cached operators, first built under a user's jit, still work eagerly after."""
  from nlosjax import physics
  setup = physics.Setup(wall_size=1.0, grid=(6, 6), bin_width=96e-12, num_bins=40)
  x = np.random.default_rng(7).poisson(0.5, (40, 6, 6)).astype(np.float32)
  for method in ("fbp", "lct", "fk", "phasor", "rsd"):
    inside = jax.jit(lambda v, m=method: physics.reconstruct(v, setup, m))(x)
    outside = physics.reconstruct(x, setup, method)        # raised UnexpectedTracerError before
    np.testing.assert_allclose(np.asarray(outside), np.asarray(inside), rtol=1e-5,
                               atol=1e-6 * float(np.max(np.abs(inside))), err_msg=method)
  albedo = np.zeros((40, 6, 6), np.float32)
  albedo[20, 3, 3] = 1.0
  inside = jax.jit(lambda a: physics.render(a, setup))(albedo)
  np.testing.assert_allclose(np.asarray(physics.render(albedo, setup)), np.asarray(inside), rtol=1e-5,
                             atol=1e-6 * float(np.max(inside)))


# ============================================== bad values under jit, checks on
# What NaN, +inf and a negative value do to every public metric and every classic method under a
# compiled call with the library's input checks on (``physics.checks.checked``). The methods check
# their counts: each bad value raises ValueError naming the problem. The metrics have no compiled
# check (their NaN check is eager only), and their documented behaviour under jit is propagation:
# an image holding a NaN scores NaN, an inf gives a non-finite score wherever it enters an error,
# and a negative value (a real number like any other to a metric) gives the definition's value.
# Regression: rmse, and the five object scores, turned a NaN into a finite number (0, or the
# score of the image with that pixel counted as background).
BAD_SETUP = Setup(1.0, (4, 4), 96e-12, 32)
BAD_COUNTS_MESSAGE = {"NaN": "^transient holds NaN or infinite values$",
                      "+inf": "^transient holds NaN or infinite values$",
                      "negative": "^transient holds negative values; photon counts must be >= 0$"}


@pytest.mark.parametrize("method", physics.METHODS)
def test_bad_counts_raise_naming_the_problem_in_every_method_under_checked_jit(method):
  """Through ``reconstruct`` and the method's own function; one bad bin in the second frame of a
  batch of two is enough. Good counts give the plain ``jit`` volume."""
  x = np.random.default_rng(36).poisson(0.5, (2, BAD_SETUP.num_bins, *BAD_SETUP.grid)).astype(np.float32)
  plain = np.asarray(jax.jit(lambda v: reconstruct(v, BAD_SETUP, method))(x))
  for fn in (lambda v: reconstruct(v, BAD_SETUP, method),
             lambda v: getattr(physics, method)(v, BAD_SETUP)):
    safe = checks.checked(fn)
    np.testing.assert_allclose(np.asarray(safe(x)), plain, rtol=1e-6, atol=1e-7 * plain.max())
    for kind, value in BAD_VALUES.items():
      bad = x.copy()
      bad[1, 7, 2, 3] = value
      with pytest.raises(ValueError, match=BAD_COUNTS_MESSAGE[kind]):
        safe(bad)
      with pytest.raises(ValueError, match=BAD_COUNTS_MESSAGE[kind]):      # eagerly: the same
        fn(bad)

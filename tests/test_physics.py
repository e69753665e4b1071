"""Physics: Setup, operators, render vs brute force, point scatterers, gating, stability, errors.

Independent references: the brute-force ``render_points`` loop, numerical
quadrature (scipy), NumPy convolution, closed forms of the wavelet spectrum,
and physical properties (a point reconstructs at its position).
"""

import importlib
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.ndimage

from nlosjax import physics
from nlosjax.physics import Setup, reconstruct, render, render_points
from nlosjax.physics.operators import linear_axis_matrix, public_time_power, squared_axis_matrix
from tests.xla_options import xla_optimizations


@pytest.fixture(scope="module", autouse=True)
def _optimised_xla():
  # Programs here run long (full captures, samplers, renderers): XLA's optimisations pay for
  # their compile time. The suite turns them off by default (conftest.py).
  with xla_optimizations(True):
    yield


C = physics.SPEED_OF_LIGHT
# the module (``physics.reconstruct`` is the function of the same name)
RECON = importlib.import_module("nlosjax.physics.reconstruct")
# 16 x 16 scan of a 1 m wall, 32 ps bins, 512 bins: depths up to 2.46 m.
SETUP = Setup(wall_size=1.0, grid=(16, 16), bin_width=32e-12, num_bins=512)


def peak(vol):
  return np.unravel_index(int(np.argmax(np.asarray(vol))), np.shape(vol))


def corr(a, b):
  a = np.ravel(a) - np.mean(a)
  b = np.ravel(b) - np.mean(b)
  return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


# ------------------------------------------------------------------- Setup
def test_setup_derived_quantities_match_closed_forms():
  s = Setup(2.0, (64, 32), 32e-12, 512)
  assert s.bin_length == pytest.approx(C * 32e-12)
  assert s.depth_bin_length == pytest.approx(C * 16e-12)
  assert s.max_depth == pytest.approx(512 * C * 16e-12)
  assert s.spacing == pytest.approx((2.0 / 63, 2.0 / 31))
  np.testing.assert_allclose(s.scan_x, np.linspace(-1, 1, 32))
  np.testing.assert_allclose(s.scan_y, np.linspace(-1, 1, 64))
  np.testing.assert_allclose(s.depths, np.arange(512) * C * 16e-12)
  assert s.scan_points.shape == (64, 32, 3)
  g = s.with_depth_range(0.5, 1.0)
  k0, k1 = g.depth_bins
  assert g.depths[0] >= 0.5 and g.depths[-1] <= 1.0
  assert (k0 - 1) * s.depth_bin_length < 0.5 and k1 * s.depth_bin_length > 1.0
  t0, t1 = g.time_bins
  assert t0 == k0
  # The latest return from the range: a voxel at z_max one wall diagonal away.
  assert t1 >= min(512, np.hypot(1.0, 2.0 * np.sqrt(2)) / s.depth_bin_length)


@pytest.mark.parametrize("kwargs, match", [
    (dict(wall_size=-1.0), "wall_size"),
    (dict(wall_size=float("nan")), "wall_size"),
    (dict(bin_width=32.0), "picoseconds"),
    (dict(grid=(1, 16)), "grid"),
    (dict(grid=(16.5, 16)), "grid"),
    (dict(num_bins=1), "num_bins"),
    (dict(depth_range=(1.0, 0.5)), "depth_range"),
    (dict(depth_range=(5.0, 6.0)), "depth_range"),
    (dict(depth_range=(0.501, 0.502)), "no depth bin"),
])
def test_setup_rejects_bad_arguments(kwargs, match):
  args = dict(wall_size=1.0, grid=(16, 16), bin_width=32e-12, num_bins=512)
  args.update(kwargs)
  with pytest.raises(ValueError, match=match):
    Setup(**args)


# --------------------------------------------------------------- operators
@pytest.mark.parametrize("bin_index", [3, 40, 200])
def test_time_to_v_resampling_is_the_bin_average(bin_index):
  """Row i of the t->v matrix applied to f(t) equals the mean of (t/T)^p f(t(v)) over v-bin i."""
  T, p = 256, 3.0
  f = lambda t: np.cos(t / 17.0) + 2.0  # noqa: E731
  # Histogram of the piecewise-constant function f(floor(t) + 0.5).
  hist = f(np.arange(T) + 0.5)
  m = squared_axis_matrix(T, (0, T), (0, T), power=p, samples=4096)
  got = m[bin_index] @ hist

  def integrand(v):
    t = np.sqrt(v * T)
    return (t / T) ** p * f(np.floor(t) + 0.5)

  want, _ = scipy.integrate.quad(integrand, bin_index, bin_index + 1, limit=200)
  assert got == pytest.approx(want, rel=2e-3)


def test_v_to_time_averaging_preserves_constants():
  T = 128
  m = linear_axis_matrix(T, (1, T), (0, T), power=0.0)
  np.testing.assert_allclose(m.sum(axis=1), 1.0, rtol=1e-12)


# ------------------------------------------------------------------ render
@pytest.mark.parametrize("falloff", ["diffuse", "retroreflective"])
def test_render_matches_brute_force(falloff):
  setup = Setup(1.0, (12, 12), 32e-12, 256)
  albedo = np.zeros((256, 12, 12))
  albedo[150, 4, 7] = 1.0
  albedo[110, 9, 2] = 0.5
  albedo[180, 6, 6] = 0.8
  # A voxel covers its pixel's footprint: brute-force it as 4 x 4 points across it.
  k, i, j = np.nonzero(albedo)
  dy, dx = setup.spacing
  sub = (np.arange(4) + 0.5) / 4 - 0.5
  points, weights = [], []
  for sy in sub:
    for sx in sub:
      points.append(np.stack([setup.scan_x[j] + sx * dx, setup.scan_y[i] + sy * dy,
                              setup.depths[k]], -1))
      weights.append(albedo[k, i, j] / 16)
  brute = render_points(np.concatenate(points), np.concatenate(weights), setup, falloff=falloff)
  fast = np.asarray(render(albedo, setup, falloff=falloff))
  # Same energy at every scan point (units of albedo / r^4), within 3 %.
  np.testing.assert_allclose(fast.sum(0), brute.sum(0), rtol=0.03)
  # Same arrival times: identical onsets and high correlation after a 2-bin blur
  # (the LCT form spreads a point over neighbouring bins).
  blur = lambda x: scipy.ndimage.gaussian_filter1d(x, 2.0, axis=0)  # noqa: E731
  assert corr(blur(fast), blur(brute)) > 0.95
  onset_fast = np.argmax(fast > 1e-3 * fast.max(axis=0), axis=0)
  onset_brute = np.argmax(brute > 0, axis=0)
  assert np.max(np.abs(onset_fast - onset_brute)) <= 2
  assert np.all(fast >= 0) and np.all(fast[:108] == 0)  # causal


def test_render_is_linear_and_batched():
  setup = Setup(1.0, (8, 8), 32e-12, 128)
  rng = np.random.default_rng(0)
  a = rng.random((128, 8, 8)) * (rng.random((128, 8, 8)) > 0.99)
  b = rng.random((128, 8, 8)) * (rng.random((128, 8, 8)) > 0.99)
  a[:20] = b[:20] = 0
  ra, rb = render(a, setup), render(b, setup)
  rab = render(np.stack([a, b, a + b]), setup)
  np.testing.assert_allclose(rab[0], ra, rtol=1e-5, atol=1e-5 * float(ra.max()))
  np.testing.assert_allclose(rab[2], ra + rb, rtol=1e-4, atol=1e-4 * float(rab[2].max()))


# -------------------------------------------------------- point scatterers
_rng = np.random.default_rng(1234)
POINTS = [(x, y, z) for x, y, z in zip(_rng.uniform(-0.35, 0.35, 4), _rng.uniform(-0.35, 0.35, 4),
                                        np.linspace(0.5, 1.5, 4))]


@pytest.fixture(scope="module")
def point_transients():
  return [render_points(np.array([p]), 1.0, SETUP) for p in POINTS]


#: Methods with an operator ``variant`` (``"public"`` default, ``"refined"`` ours).
VARIANT_METHODS = ("fbp", "lct", "fk", "phasor")


def refined(method):
  """Options selecting our refined operators where a method has variants."""
  return {"variant": "refined"} if method in VARIANT_METHODS else {}


@pytest.mark.parametrize("method, variant", [(m, "refined") for m in physics.METHODS]
                         + [(m, "public") for m in VARIANT_METHODS])
def test_point_scatterer_reconstructs_at_its_position(method, variant, point_transients):
  opts = {"variant": variant} if method in VARIANT_METHODS else {}
  # The public phasor's 1/t-weighted resampling tilts its long wavelet envelope and pulls
  # peaks toward the wall (measured: 4.2 bins at 0.5 m); the refined one stays within 3.
  tol = 6 if (method, variant) == ("phasor", "public") else 3
  for (x, y, z), transient in zip(POINTS, point_transients):
    vol = reconstruct(transient, SETUP, method, **opts)
    assert vol.shape == (512, 16, 16) and vol.dtype == jnp.float32
    k, i, j = peak(vol)
    true_i = np.argmin(np.abs(SETUP.scan_y - y))
    true_j = np.argmin(np.abs(SETUP.scan_x - x))
    true_k = z / SETUP.depth_bin_length
    assert abs(i - true_i) <= 1 and abs(j - true_j) <= 1, (method, (x, y, z), (k, i, j))
    assert abs(k - true_k) <= tol, (method, (x, y, z), (k, i, j), true_k)


@pytest.mark.parametrize("method", ["fbp", "lct", "phasor"])
def test_oversampled_lct_grid_also_reconstructs_points(method, point_transients):
  for (x, y, z), transient in zip(POINTS, point_transients):
    k, i, j = peak(reconstruct(transient, SETUP, method, oversample=2, variant="refined"))
    assert abs(i - np.argmin(np.abs(SETUP.scan_y - y))) <= 1
    assert abs(j - np.argmin(np.abs(SETUP.scan_x - x))) <= 1
    assert abs(k - z / SETUP.depth_bin_length) <= 3, (method, z, k)


def test_lct_apply_equals_the_full_padded_fft_convolution():
  """The pruned one-axis-at-a-time FFTs give NumPy's full ``irfftn(rfftn(x) * filt)``."""
  from nlosjax.physics.operators import lct_apply, lct_filter, lct_operators
  setup = Setup(0.8, (6, 5), 32e-12, 64)
  ops = lct_operators(setup, 3.0, oversample=1)
  x = np.random.default_rng(0).uniform(size=(64, 6, 5))
  filt = lct_filter(ops, 0.5)
  got = np.asarray(lct_apply(jnp.asarray(x, jnp.float32), ops, filt))
  data_v = np.asarray(ops.to_v, np.float64) @ x.reshape(64, -1)
  data_v = data_v.reshape(-1, 6, 5)
  filt = np.moveaxis(np.asarray(filt), -1, 0)        # [2H, W + 1, Lv] -> NumPy's [Lv, 2H, W + 1]
  ref = np.fft.irfftn(np.fft.rfftn(data_v, s=ops.domain.fft_shape, axes=(0, 1, 2)) * filt,
                      s=ops.domain.fft_shape, axes=(0, 1, 2))[:ops.domain.num_u, :6, :5]
  np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max())


@pytest.mark.parametrize("depth_range", [None, (0.3, 0.6)])
def test_lct_fft_length_stops_at_the_cone_and_changes_nothing(depth_range):
  """On a wall small beside the depth range the cone spans few v-bins, so ``lct_domain(...,
  fft_length="cone")`` shortens the FFT along time; backprojection (``filt=None``) and the forward model still
  equal the linear correlation / convolution done with NumPy on twice the full length."""
  import dataclasses

  from nlosjax.physics.forward import render_operators
  from nlosjax.physics.operators import cone_psf, cone_reach, lct_apply, lct_operators
  setup = Setup(0.2, (8, 7), 32e-12, 256, depth_range=depth_range)
  ops = lct_operators(setup, 0.0, oversample=1, fft_length="cone")
  dom = ops.domain
  lv = dom.fft_shape[0]
  assert lct_operators(setup, 0.0, oversample=1).domain.fft_shape[0] >= dom.num_v + dom.num_u - 1
  assert cone_reach(setup) < 40 and lv < dom.num_v + dom.num_u - 1
  long = dataclasses.replace(dom, fft_shape=(2 * (dom.num_v + dom.num_u),) + dom.fft_shape[1:])
  psf = cone_psf(setup, long)                                 # no wrap at this length
  rng = np.random.default_rng(0)
  x = rng.uniform(size=(dom.t[1] - dom.t[0], 8, 7))
  data_v = (np.asarray(ops.to_v, np.float64) @ x.reshape(x.shape[0], -1)).reshape(-1, 8, 7)
  spec = np.fft.rfftn(psf, axes=(0, 1, 2))
  ref = np.fft.irfftn(np.fft.rfftn(data_v, s=long.fft_shape, axes=(0, 1, 2)) * np.conj(spec),
                      s=long.fft_shape, axes=(0, 1, 2))[:dom.num_u, :8, :7]
  got = np.asarray(lct_apply(jnp.asarray(x, jnp.float32), ops, None))
  np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max())
  # The forward model: volume on the u-grid -> v-grid by the same kernel (a convolution).
  fwd = render_operators(setup)
  fdom = fwd.domain
  rho_u = rng.uniform(size=(fdom.num_u, 8, 7)) * (rng.uniform(size=(fdom.num_u, 8, 7)) > 0.9)
  flong = dataclasses.replace(fdom, fft_shape=(2 * (fdom.num_v + fdom.num_u),) + fdom.fft_shape[1:])
  scale = np.asarray(fwd.psf_fft).ravel()[0] / cone_psf(setup, fdom).sum()   # the calibration
  fspec = np.fft.rfftn(cone_psf(setup, flong), axes=(0, 1, 2)) * scale
  fref = np.fft.irfftn(np.fft.rfftn(rho_u, s=flong.fft_shape, axes=(0, 1, 2)) * fspec,
                       s=flong.fft_shape, axes=(0, 1, 2))[:fdom.num_v, :8, :7]
  fgot = np.fft.irfftn(np.fft.rfftn(rho_u, s=fdom.fft_shape, axes=(0, 1, 2)) * np.asarray(fwd.psf_fft),
                       s=fdom.fft_shape, axes=(0, 1, 2))[:fdom.num_v, :8, :7]
  np.testing.assert_allclose(fgot, fref, rtol=1e-4, atol=1e-5 * np.abs(fref).max())


def test_neg_log_filter_equals_the_dense_3d_kernel():
  from nlosjax.physics.reconstruct import _neg_log_kernel, neg_log_filter
  vol = np.random.default_rng(1).normal(size=(11, 7, 9))
  ref = scipy.ndimage.correlate(vol, _neg_log_kernel(), mode="nearest")
  got = np.asarray(neg_log_filter(jnp.asarray(vol, jnp.float32)))
  np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max())


def test_retroreflective_lct_and_fbp_find_a_retroreflective_point():
  p = np.array([[0.1, -0.2, 0.9]])
  transient = render_points(p, 1.0, SETUP, falloff="retroreflective")
  for method in ("lct", "fbp"):
    k, i, j = peak(reconstruct(transient, SETUP, method, falloff="retroreflective"))
    assert abs(k - 0.9 / SETUP.depth_bin_length) <= 3
    assert abs(i - np.argmin(np.abs(SETUP.scan_y + 0.2))) <= 1
    assert abs(j - np.argmin(np.abs(SETUP.scan_x - 0.1))) <= 1


def test_batched_reconstruction_equals_one_by_one(point_transients):
  batch = np.stack(point_transients[:2])[None]          # [1, 2, T, H, W]
  for method in physics.METHODS:
    out = reconstruct(batch, SETUP, method)
    assert out.shape == (1, 2, 512, 16, 16)
    for n in range(2):
      one = reconstruct(point_transients[n], SETUP, method)
      np.testing.assert_allclose(out[0, n], one, rtol=1e-4, atol=1e-5 * float(one.max()))


# ------------------------------------------------------------------ gating
SMALL = Setup(1.0, (12, 12), 32e-12, 384)


@pytest.fixture(scope="module")
def two_points():
  pts = np.array([[0.1, -0.15, 0.6], [-0.2, 0.2, 0.75]])
  return render_points(pts, 1.0, SMALL)


# Backprojections and migrations are exact inside the range; the Wiener filter
# (LCT) is not local, so its gated solution differs slightly.
# f-k resamples its spectrum on a grid set by the (shorter) time window.
# Phasor: the wavelet's tails at the window edges and the coarse u-grid near
# them (measured 0.65% of the peak at oversample 1, under 0.5% at 2).
@pytest.mark.parametrize("method, tol", [("fbp", 1e-4), ("rsd", 1e-4), ("phasor", 1e-2),
                                         ("fk", 5e-2), ("lct", 5e-2)])
def test_gated_matches_ungated_inside_the_range_and_costs_less(method, tol, two_points):
  gated = SMALL.with_depth_range(0.5, 0.9)
  k0, k1 = gated.depth_bins
  full = np.asarray(reconstruct(two_points, SMALL, method))[k0:k1]
  part = np.asarray(reconstruct(two_points, gated, method))
  assert part.shape == (k1 - k0, 12, 12)
  assert np.max(np.abs(full - part)) <= tol * full.max()

  def flops(setup):
    x = jnp.zeros((384, 12, 12), jnp.float32)
    compiled = jax.jit(lambda t: reconstruct(t, setup, method)).lower(x).compile()
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return cost["flops"]

  assert flops(gated) < flops(SMALL)


def test_aperture_window_is_the_closed_form_and_shrinks_with_the_range():
  wide = Setup(2.0, (16, 16), 32e-12, 512)
  dz = wide.depth_bin_length
  for z0, z1 in [(0.5, 1.5), (0.75, 1.25)]:
    for rho in (0.3, 1.0):
      s = wide.with_depth_range(z0, z1).with_aperture(rho)
      k0, k1 = s.depth_bins
      t0, t1 = s.time_bins
      # Rendered (brute force, ungated): a point at the window's edge, the last depth bin at the
      # aperture's lateral reach from a scan point, returns there just inside the window (its
      # last two bins); one 2 bins later (beyond the aperture) just outside; a point straight
      # ahead at the first depth bin returns at the window's start.
      corner = wide.scan_points[0, 0]
      z_last = (k1 - 1) * dz
      beyond = np.sqrt(((np.hypot(z_last, rho) // dz + 2.5) * dz) ** 2 - z_last ** 2)
      for lateral, inside in ((rho, True), (beyond, False)):
        hist = render_points([corner + [lateral, 0.0, z_last]], 1.0, wide)[:, 0, 0]
        (b,) = np.flatnonzero(hist)
        assert (t1 - 2 <= b < t1) if inside else (b >= t1), (z0, z1, rho, lateral, b, t1)
      (b,) = np.flatnonzero(render_points([corner + [0.0, 0.0, k0 * dz + 1e-9]], 1.0, wide)[:, 0, 0])
      assert b == t0, (b, t0)
      assert s.time_bins == (k0, min(512, int(np.hypot((k1 - 1) * dz, rho) // dz) + 2))
  # R -> R/2 halves the window only with an aperture (the wall diagonal is 2.83 m)
  full = [wide.with_depth_range(*r).time_bins for r in [(0.5, 1.5), (0.75, 1.25)]]
  ap = [wide.with_depth_range(*r).with_aperture(0.8).time_bins for r in [(0.5, 1.5), (0.75, 1.25)]]
  assert full[0][1] == full[1][1] == 512
  assert (ap[0][1] - ap[0][0]) / (ap[1][1] - ap[1][0]) > 1.5
  # an aperture beyond the wall diagonal is no aperture
  assert wide.with_aperture(10.0).with_depth_range(0.5, 1.5).time_bins == full[0]
  assert repr(wide) == ("Setup(wall_size=2.0, grid=(16, 16), bin_width=3.2e-11, num_bins=512,"
                        " depth_range=None)")
  for bad in (0.0, -1.0, float("nan"), "1"):
    with pytest.raises(ValueError, match="aperture"):
      wide.with_aperture(bad)


def test_aperture_cuts_the_cone_and_never_the_forward_model():
  from nlosjax.physics.operators import cone_psf, lct_domain
  s = Setup(1.0, (12, 12), 32e-12, 384)
  rho = 0.35
  cut = s.with_aperture(rho)
  full_psf = cone_psf(s, lct_domain(s))
  cut_psf = cone_psf(cut, lct_domain(s))
  assert lct_domain(cut, fft_length="cone").fft_shape[0] < lct_domain(s, fft_length="cone").fft_shape[0]
  dy, dx = s.spacing
  p = np.fft.fftfreq(24, 1 / 24)                      # signed lateral offsets of the FFT layout
  lateral = np.hypot(p[:, None] * dy, p[None, :] * dx)
  half_pixel = 0.5 * np.hypot(dy, dx)
  support = np.abs(cut_psf).sum(0) > 0
  assert not np.any(support & (lateral > rho + half_pixel))
  inside = lateral < rho - half_pixel                 # every footprint sample within the aperture
  ratio = cut_psf[:, inside].sum() / full_psf[:, inside].sum()
  np.testing.assert_allclose(cut_psf[:, inside], ratio * full_psf[:, inside], rtol=1e-12, atol=1e-15)
  # render drops the aperture: the very same operators, so the same transient up to the
  # run-to-run round-off of XLA's threaded reductions (measured 7.8e-8 of the peak between
  # two calls with one Setup); the cut cone would change the PSF by O(1).
  from nlosjax.physics.forward import render_operators
  assert render_operators(cut) is render_operators(s)
  rng = np.random.default_rng(0)
  albedo = rng.random((384, 12, 12)).astype(np.float32) * (rng.random((384, 12, 12)) > 0.999)
  ref = np.asarray(render(albedo, s))
  np.testing.assert_allclose(np.asarray(render(albedo, cut)), ref, rtol=0, atol=1e-6 * ref.max())


@pytest.mark.parametrize("method", ["fbp", "lct", "phasor"])
def test_point_scatterer_with_an_aperture_and_a_range(method):
  """A 0.8 m aperture (the wall diagonal is 2.8 m) still puts a point at its position."""
  s = Setup(2.0, (16, 16), 32e-12, 512)
  x, y, z = 0.3, -0.25, 0.9
  transient = render_points(np.array([[x, y, z]]), 1.0, s)
  gated = s.with_depth_range(0.75, 1.25).with_aperture(0.8)
  vol = np.asarray(reconstruct(transient, gated, method, **refined(method)))   # the aperture is ours
  k, i, j = peak(vol)
  assert abs(i - np.argmin(np.abs(s.scan_y - y))) <= 1 and abs(j - np.argmin(np.abs(s.scan_x - x))) <= 1
  assert abs(k + gated.depth_bins[0] - z / s.depth_bin_length) <= 3
  assert gated.time_bins[1] < 512


@pytest.mark.parametrize("depth_range", [None, (0.31, 0.77)])
def test_rsd_nufft_depth_sum_equals_the_brute_force_sum(depth_range):
  """The NUFFT over depth reproduces ``|ifft2(sum_k U_k exp(i z kz_k))|`` summed plane by plane in NumPy."""
  setup = Setup(0.7, (6, 9), 32e-12, 160, depth_range=depth_range)   # odd Z when gated
  rng = np.random.default_rng(3)
  tau = rng.poisson(2.0, (160, 6, 9)).astype(np.float64)
  with jax.enable_x64(True):
    fast = np.asarray(reconstruct(tau, setup, "rsd"))
    direct = np.asarray(reconstruct(tau, setup, "rsd", depth_sum="direct", chunk=5))
    # the wall field and wavenumbers, as the method builds them
    dtft, kz, mask = (np.asarray(a) for a in RECON._rsd_operators(setup, 3.0, 2.0, 0.1, jnp.float64))
  t0, t1 = RECON._rsd_window(setup, physics.illumination_wavelet(setup, cycles=3.0))
  spec = np.fft.fft2(np.einsum("kt,thw->khw", dtft, tau[t0:t1]), s=(12, 18)) * mask
  k0, k1 = setup.depth_bins
  brute = np.stack([np.abs(np.fft.ifft2((spec * np.exp(1j * k * setup.depth_bin_length * kz)).sum(0)))
                    [:6, :9] for k in range(k0, k1)])
  assert fast.shape == brute.shape == (k1 - k0, 6, 9)
  np.testing.assert_allclose(direct, brute, rtol=0, atol=1e-10 * brute.max())
  # NUFFT kernel error: 2.3e-7 of the peak in float64 (8 taps)
  np.testing.assert_allclose(fast, brute, rtol=0, atol=1e-6 * brute.max())
  fast32 = np.asarray(reconstruct(tau.astype(np.float32), setup, "rsd"))
  np.testing.assert_allclose(fast32, brute, rtol=0, atol=1e-5 * brute.max())


def test_rsd_rejects_an_unknown_depth_sum():
  with pytest.raises(ValueError, match="depth_sum"):
    reconstruct(np.zeros((128, 8, 8), np.float32), TINY, "rsd", depth_sum="fast")


# --------------------------------------------------------------- stability
def _assert_clean(vol):
  vol = np.asarray(vol)
  assert np.all(np.isfinite(vol)), "non-finite output"
  assert np.all(vol >= 0), "negative output"


TINY = Setup(0.6, (8, 8), 32e-12, 128)


@pytest.mark.parametrize("method", physics.METHODS)
def test_extreme_inputs_give_finite_nonnegative_volumes(method):
  zero = np.zeros((128, 8, 8), np.float32)
  single = zero.copy()
  single[70, 3, 4] = 1.0
  huge = np.full((128, 8, 8), 1e9, np.float32)
  saturated = np.zeros((128, 8, 8), np.float32)
  saturated[:, 2:5, 2:5] = 1e9
  thin = TINY.with_depth_range(100 * TINY.depth_bin_length, 100.5 * TINY.depth_bin_length)
  assert thin.num_depth_bins == 1
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    for transient in (zero, single, huge, saturated):
      _assert_clean(reconstruct(transient, TINY, method))
      out = reconstruct(transient, thin, method)
      assert out.shape == (1, 8, 8)
      _assert_clean(out)
    assert float(jnp.max(reconstruct(zero, TINY, method))) == 0.0


@pytest.mark.parametrize("snr", [1e-6, 1e-3, 1.0, 1e3, 1e6])
def test_lct_snr_extremes(snr):
  single = np.zeros((128, 8, 8), np.float32)
  single[70, 3, 4] = 1.0
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    _assert_clean(physics.lct(single, TINY, snr=snr))
    _assert_clean(physics.lct(single * 1e9, TINY, snr=snr))


# -------------------------------------------------------------- bad input
@pytest.mark.parametrize("bad, match", [
    (np.zeros((8, 8)), "rank"),
    (np.zeros((64, 8, 8)), "does not match the Setup"),
    (np.full((128, 8, 8), np.nan), "NaN"),
    (-np.ones((128, 8, 8)), "negative"),
])
def test_bad_transients_raise(bad, match):
  for method in physics.METHODS:
    with pytest.raises(ValueError, match=match):
      reconstruct(bad, TINY, method)


def test_bad_method_and_options_raise():
  x = np.zeros((128, 8, 8), np.float32)
  with pytest.raises(ValueError, match="unknown method"):
    reconstruct(x, TINY, "backprojection")
  with pytest.raises(ValueError, match="does not take"):
    reconstruct(x, TINY, "fk", snr=0.1)
  with pytest.raises(ValueError, match="snr"):
    reconstruct(x, TINY, "lct", snr=0.0)
  with pytest.raises(ValueError, match="falloff"):
    reconstruct(x, TINY, "lct", falloff="lambertian")
  with pytest.raises(ValueError, match="setup"):
    reconstruct(x, "not a setup", "lct")
  with pytest.raises(ValueError, match="albedo"):
    render(np.zeros((64, 8, 8)), TINY)


# ----------------------------------------------------- intensity and depth
def test_intensity_depth_of_a_known_volume():
  setup = TINY.with_depth_range(0.3, 1.0)
  vol = np.zeros((setup.num_depth_bins, 8, 8), np.float32)
  vol[10, 2, 3] = 4.0
  vol[30, 5, 5] = 2.0
  vol[5, 0, 0] = 0.2                        # below 10 % of the max: background
  intensity, depth = physics.intensity_depth(vol, setup)
  assert float(intensity[2, 3]) == 1.0 and float(intensity[5, 5]) == 0.5
  assert float(depth[2, 3]) == pytest.approx(setup.depths[10], rel=1e-6)
  assert float(depth[5, 5]) == pytest.approx(setup.depths[30], rel=1e-6)
  assert float(depth[0, 0]) == 0.0 and float(intensity[0, 0]) == pytest.approx(0.05)
  zi, zd = physics.intensity_depth(np.zeros_like(vol), setup)
  assert float(jnp.max(zi)) == 0.0 and float(jnp.max(zd)) == 0.0


def test_point_scatterer_depth_map_is_metric(point_transients):
  (_, _, z), transient = POINTS[1], point_transients[1]
  intensity, depth = physics.intensity_depth(reconstruct(transient, SETUP, "fk"), SETUP)
  i, j = np.unravel_index(int(np.argmax(intensity)), intensity.shape)
  assert float(depth[i, j]) == pytest.approx(z, abs=3 * SETUP.depth_bin_length)


# ----------------------------------------------------------------- wavelet
def test_wavelet_parameters_and_spectrum():
  setup = Setup(2.0, (64, 64), 32e-12, 512)
  wl = physics.illumination_wavelet(setup)
  delta = 2.0 / 63
  assert wl.wavelength == pytest.approx(4 * delta)
  assert wl.num_samples % 2 == 1
  assert abs(wl.num_samples - 5 * 4 * delta / setup.bin_length) <= 1
  assert wl.omega == pytest.approx(2 * np.pi * C / wl.wavelength)
  # Closed-form Gaussian spectrum vs the DFT of the (long-padded) samples.
  n = 1 << 14
  spec = np.abs(np.fft.fft(wl.samples, n))
  w = 2 * np.pi * np.fft.fftfreq(n, d=setup.bin_width)
  keep = spec > 0.2 * spec.max()
  np.testing.assert_allclose(spec[keep] / spec.max(), wl.spectrum(w[keep]), atol=0.02)


def test_convolve_time_matches_numpy():
  setup = Setup(0.6, (8, 8), 32e-12, 512)
  wl = physics.illumination_wavelet(setup)
  x = np.random.default_rng(0).random((512, 3, 2))
  got = np.asarray(physics.convolve_time(jnp.asarray(x, jnp.float32), wl, axis=0))
  want = np.stack([np.convolve(x[:, a, b], wl.samples, mode="same")
                   for a in range(3) for b in range(2)], -1).reshape(512, 3, 2)
  np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("public", [False, True])
def test_phasor_wavelet_matrix_is_matlabs_same_convolution(public):
  """The phasor folds its wavelet convolution into the resampling matrix: that matrix applied to
  a histogram equals MATLAB ``conv(x, w, 'same')`` (numpy's full convolution from ``L // 2``),
  for the public even-length wavelet too; and convolve_time agrees."""
  setup = Setup(1.0, (12, 12), 32e-12, 96)
  wl = (physics.wavelet.public_wavelet if public else physics.illumination_wavelet)(setup)
  assert (wl.num_samples % 2 == 0) == public                 # 5 cycles of 4 spacings: 190 samples
  x = np.random.default_rng(0).uniform(size=96)
  full = np.convolve(x, wl.samples)                           # [T + L - 1]
  same = full[wl.num_samples // 2:wl.num_samples // 2 + 96]
  m = RECON.wavelet_matrix(wl, (0, 96), (0, 96))
  np.testing.assert_allclose(m @ x, same, rtol=1e-12, atol=1e-12)
  np.testing.assert_allclose(np.asarray(physics.convolve_time(jnp.asarray(x, jnp.float32), wl, axis=0)),
                             same, rtol=1e-4, atol=1e-5 * np.abs(same).max())
  # a window: rows 20..60 of the field from samples 10..70 (zero outside)
  part = x.copy()
  part[:10] = part[70:] = 0
  ref = np.convolve(part, wl.samples)[wl.num_samples // 2:][20:60]
  np.testing.assert_allclose(RECON.wavelet_matrix(wl, (20, 60), (10, 70)) @ x[10:70], ref,
                             rtol=1e-12, atol=1e-12)


def test_sparse_resampling_equals_the_dense_product():
  """The public ``mtx`` is applied as a gather + sorted segment sum: the same sums as NumPy's dense product."""
  from nlosjax.physics.operators import apply_axis_matrix, public_resampling_matrix, sparse_rows
  rng = np.random.default_rng(0)
  for T in (64, 100, 256):
    m = public_resampling_matrix(T).astype(np.float32)
    assert np.count_nonzero(m) <= 2 * T                  # each x in 1..T^2 adds to one (row, col), both monotone
    sparse = sparse_rows(m)
    assert sparse is not None
    x = rng.random((T, 5, 3)).astype(np.float32)
    want = (m.astype(np.float64) @ x.reshape(T, -1)).reshape(T, 5, 3)
    got = np.asarray(apply_axis_matrix(jnp.asarray(m), sparse, jnp.asarray(x)))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)
  assert sparse_rows(np.ones((8, 8))) is None              # dense stays dense


def test_public_time_power_is_the_public_codes_falloff():
  """The public LCT scales by ``grid_z.^4`` (diffuse) and ``grid_z.^2`` (retroreflective)
  (O'Toole's ``cnlos_reconstruction.m``), and phasor's plain backprojection by nothing;
  the public grid has one v-bin per time bin."""
  from nlosjax.physics.operators import check_falloff
  assert public_time_power(float(check_falloff("diffuse"))) == 4
  assert public_time_power(float(check_falloff("retroreflective"))) == 2
  assert public_time_power(0.0) == 0
  with pytest.raises(ValueError, match="oversample=2 needs variant='refined'"):
    public_time_power(3.0, oversample=2)
  with pytest.raises(ValueError, match="whole number"):
    public_time_power(1.5)


def test_public_lct_domain_is_the_box_of_the_public_psf_and_crops_only_depths():
  """The public code convolves on the box of its cone PSF (``psf = zeros(2M, 2N, 2N)``) and
  reads every bin; a depth range (widened by ``z_margin``, clipped) crops the output only."""
  from nlosjax.physics.operators import public_cone_psf, public_lct_domain, public_lct_operators
  setup = Setup(0.6, (8, 8), 64e-12, 64).with_depth_range(0.2, 0.5)
  dom = public_lct_domain(setup)
  assert dom.fft_shape == public_cone_psf(setup).shape == (128, 16, 16)
  assert dom.t == dom.v == dom.u == (0, 64) and dom.oversample == 1
  assert dom.z == setup.depth_bins
  k0, k1 = setup.depth_bins
  assert public_lct_domain(setup, z_margin=3).z == (max(0, k0 - 3), min(64, k1 + 3))
  assert public_lct_domain(setup, z_margin=100).z == (0, 64)
  assert public_lct_operators(setup, 0, z_margin=3).domain == public_lct_domain(setup, z_margin=3)
  for bad in (-1, 1.5, True):
    with pytest.raises(ValueError, match="z_margin"):
      public_lct_domain(setup, z_margin=bad)

"""CSA (nlosjax.physics.methods.csa): against the tested LCT backprojection, a dense NumPy twin,
the l1 problem's optimality conditions and brute-force point scatterers."""

import numpy as np
import pytest

from nlosjax.physics import Setup
from nlosjax.physics.forward import render_points
from nlosjax.physics.methods import csa as C
from nlosjax.physics.operators import lct_apply

TINY = Setup(0.4, (4, 4), 64e-12, 32)          # 0.31 m of depth


def _dense(fn, n_in, shape_in):
  """The matrix of a linear map, one unit vector at a time (``[n_out, n_in]``, float64)."""
  cols = []
  for k in range(n_in):
    e = np.zeros(n_in, np.float32)
    e[k] = 1.0
    cols.append(np.asarray(fn(e.reshape(shape_in)), np.float64).ravel())
  return np.stack(cols, axis=1)


def test_adjoint_is_the_lct_backprojection_and_forward_its_exact_transpose():
  ops = C.csa_operators(TINY)
  dom = ops.domain
  rng = np.random.default_rng(0)
  x = rng.random((dom.t[1] - dom.t[0], 4, 4)).astype(np.float32)
  # A^T after the t -> v resampling is lct_apply's backprojection (tested against the public code).
  mine = C.adjoint_v(np.einsum("vt,thw->vhw", np.asarray(ops.to_v), x), ops)
  np.testing.assert_allclose(np.asarray(mine), np.asarray(lct_apply(x, ops, None)), rtol=1e-5, atol=1e-6)
  nu, nv = dom.num_u, dom.num_v
  a = _dense(lambda u: C.forward_v(u, ops), nu * 16, (nu, 4, 4))
  at = _dense(lambda r: C.adjoint_v(r, ops), nv * 16, (nv, 4, 4))
  np.testing.assert_allclose(a, at.T, atol=1e-6 * np.abs(a).max())
  assert np.abs(a).max() > 0


def _numpy_fista(a, b, tau, lip, iterations):
  """FISTA for min_{u >= 0} 1/2 ||A u - b||^2 + tau sum(u), float64, from the textbook (Beck and Teboulle)."""
  u = y = np.zeros(a.shape[1])
  t = 1.0
  for _ in range(iterations):
    u_new = np.maximum(y - (a.T @ (a @ y - b) + tau) / lip, 0.0)
    t_new = (1 + np.sqrt(1 + 4 * t * t)) / 2
    y = u_new + (t - 1) / t_new * (u_new - u)
    u, t = u_new, t_new
  return u


def _problem(stride=2, seed=1):
  """A tiny masked capture and the dense pieces of its CSA problem (A with the mask, b, to_z)."""
  ops = C.csa_operators(TINY)
  dom = ops.domain
  y = render_points([[0.05, -0.1, 0.15]], 1.0, TINY, falloff="retroreflective").astype(np.float32)
  y = 50 * y / y.max() + np.random.default_rng(seed).random(y.shape).astype(np.float32)
  mask = C.interval_mask(4, 4, stride)
  nu = dom.num_u
  a = _dense(lambda u: mask * C.forward_v(u, ops), nu * 16, (nu, 4, 4))
  t0, t1 = dom.t
  b = (mask * np.einsum("vt,thw->vhw", np.asarray(ops.to_v, np.float64), y[t0:t1])).ravel()
  scale = np.abs(b).max()                  # csa solves at max |b| = 1 and scales the volume back
  return ops, y, mask, a, b / scale, scale


def test_csa_equals_a_dense_numpy_fista_with_the_same_step_and_weight():
  ops, y, mask, a, b, scale = _problem()
  iters, tau_rel = 60, 0.05
  out = C.csa_solve(y, TINY, mask=mask, tau_rel=tau_rel, iterations=iters, tol=0.0)
  assert int(out["iterations"]) == iters
  tau = tau_rel * np.max(a.T @ b)
  # The step: the power iteration's estimate times the margin, within that margin of the exact norm.
  lip_exact = np.linalg.norm(a, 2) ** 2
  u = _numpy_fista(a, b, tau, C.LIPSCHITZ_MARGIN * lip_exact, iters)
  vol = np.asarray(ops.to_z, np.float64) @ u.reshape(ops.domain.num_u, -1)
  want = scale * np.maximum(vol.reshape(-1, 4, 4), 0)
  np.testing.assert_allclose(np.asarray(out["volume"]), want, rtol=2e-3, atol=2e-3 * want.max())
  objective = 0.5 * np.sum((a @ u - b) ** 2) + tau * u.sum()
  assert float(out["objective"]) == pytest.approx(objective, rel=1e-3)


def test_at_convergence_the_l1_optimality_conditions_hold():
  """u >= 0 solves the problem iff grad_i = -tau where u_i > 0 and grad_i >= -tau where u_i = 0."""
  ops, y, mask, a, b, _ = _problem(stride=1)
  tau = 0.1 * np.max(a.T @ b)
  u = _numpy_fista(a, b, tau, np.linalg.norm(a, 2) ** 2, 3000)
  grad = a.T @ (a @ u - b)
  on = u > 1e-6 * u.max()
  assert on.any() and (~on).any()
  scale = np.abs(a.T @ b).max()
  np.testing.assert_allclose(grad[on], -tau, atol=1e-3 * scale)
  assert np.all(grad[~on] >= -tau - 1e-3 * scale)
  # and the fast solver reaches the same minimum
  out = C.csa_solve(y, TINY, mask=mask, tau_rel=0.1, iterations=3000, tol=1e-7)
  objective = 0.5 * np.sum((a @ u - b) ** 2) + tau * u.sum()
  assert float(out["objective"]) == pytest.approx(objective, rel=1e-3)


def test_two_points_found_from_a_quarter_of_the_scan_points():
  s = Setup(1.0, (16, 16), 32e-12, 256)
  pts = np.array([[0.1, -0.1, 0.5], [-0.2, 0.15, 0.8]])
  y = render_points(pts, [1.0, 1.0], s, falloff="retroreflective").astype(np.float32)
  mask = C.interval_mask(16, 16, 4)                          # 4 x 4 of 16 x 16 points
  v = np.asarray(C.csa(100 * y / y.max() * mask, s, mask=mask, tau_rel=0.3))
  for p in pts:                                              # the voxel nearest each point holds a peak
    k = int(round(p[2] / s.depth_bin_length))
    j, i = (int(round((c + 0.5) * 15)) for c in p[:2])
    near = v[k - 2:k + 3, i - 1:i + 2, j - 1:j + 2].max()
    assert near >= 0.3 * v.max(), (p, near, v.max())


def test_scale_free_and_blind_to_unscanned_points():
  ops, y, mask, *_ = _problem()
  base = np.asarray(C.csa(y, TINY, mask=mask, iterations=50, tol=0.0))
  np.testing.assert_allclose(np.asarray(C.csa(7.0 * y, TINY, mask=mask, iterations=50, tol=0.0)),
                             7.0 * base, rtol=1e-4, atol=1e-4 * 7 * base.max())
  junk = y + 1e3 * (1 - mask) * np.random.default_rng(2).random(y.shape).astype(np.float32)
  np.testing.assert_allclose(np.asarray(C.csa(junk, TINY, mask=mask, iterations=50, tol=0.0)), base,
                             rtol=1e-5, atol=1e-6 * base.max())


@pytest.mark.parametrize("case", ["zero", "one_photon", "saturated"])
def test_extreme_inputs_give_finite_volumes(case):
  y = np.zeros((32, 4, 4), np.float32)
  if case == "one_photon":
    y[20, 1, 2] = 1.0
  elif case == "saturated":
    y[:] = 3e38 / 1e6
  out = C.csa_solve(y, TINY, mask=C.interval_mask(4, 4, 2), iterations=20)
  v = np.asarray(out["volume"])
  assert np.all(np.isfinite(v)) and np.all(v >= 0) and np.isfinite(float(out["objective"]))
  if case == "zero":
    assert not v.any() and int(out["iterations"]) == 1       # the first step changes nothing: stop


def test_batches_and_bad_options():
  y = np.random.default_rng(0).random((2, 32, 4, 4)).astype(np.float32)
  out = C.csa_solve(y, TINY, iterations=5)
  assert out["volume"].shape == (2, TINY.num_depth_bins, 4, 4) and out["iterations"].shape == (2,)
  np.testing.assert_allclose(np.asarray(out["volume"][1]), np.asarray(C.csa(y[1], TINY, iterations=5)),
                             rtol=1e-5, atol=1e-6)
  for kwargs, msg in [({"mask": np.ones((3, 4))}, "mask must be"), ({"mask": np.full((4, 4), 0.5)}, "only 0"),
                      ({"mask": np.zeros((4, 4))}, "no point"), ({"tau_rel": 0.0}, "tau_rel"),
                      ({"iterations": 0}, "iterations"), ({"tol": -1.0}, "tol"),
                      ({"falloff": "lambertian"}, "falloff")]:
    with pytest.raises(ValueError, match=msg):
      C.csa(y[0], TINY, **kwargs)
  with pytest.raises(ValueError, match="stride"):
    C.interval_mask(4, 4, 0)
  np.testing.assert_array_equal(np.nonzero(C.interval_mask(8, 8, 4)[:, 2])[0], [2, 6])


def test_sparse_on_grid_puts_each_sample_on_its_scan_point():
  """Against a plain loop over the samples: sample (i, j) at (s//2 + s i, s//2 + s j), zeros elsewhere."""
  rng = np.random.default_rng(0)
  for (H, W), s in [((8, 8), 4), ((9, 7), 3), ((5, 5), 1)]:
    h, w = len(range(s // 2, H, s)), len(range(s // 2, W, s))
    x = rng.random((2, 3, h, w)).astype(np.float32)
    want = np.zeros((2, 3, H, W), np.float32)
    for i in range(h):
      for j in range(w):
        want[..., s // 2 + s * i, s // 2 + s * j] = x[..., i, j]
    got = np.asarray(C.sparse_on_grid(x, (H, W), s))
    np.testing.assert_array_equal(got, want)
    assert np.all(got[..., C.interval_mask(H, W, s) == 0] == 0)
  with pytest.raises(ValueError, match="does not match grid"):
    C.sparse_on_grid(np.zeros((3, 2, 2)), (8, 8), 2)

"""Losses: each term against a NumPy/SciPy reference, batch-size independence, zero-error gradients."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage

from nlosjax import losses
from nlosjax.physics import Setup, illumination_wavelet

SETUP = Setup(0.8, (6, 6), 32e-12, 48)
RNG = np.random.default_rng(0)


def _total_loss(out, tgt, weights, wavelet):
  """``losses.total_loss`` under one ``jit``: run eagerly, each of its operations compiles on its own."""
  return jax.jit(lambda o, t: losses.total_loss(o, t, weights, wavelet))(out, tgt)


def _batch(b=2):
  return {
      "transient": RNG.uniform(size=(b, 48, 6, 6)).astype(np.float32),
      "volume": RNG.uniform(size=(b, 48, 6, 6)).astype(np.float32),
      "intensity": RNG.uniform(size=(b, 6, 6)).astype(np.float32),
      "depth": RNG.uniform(0.3, 1.0, size=(b, 6, 6)).astype(np.float32),
  }


def test_rmse_is_the_batch_mean_of_per_sample_rmse():
  a, b = RNG.normal(size=(3, 4, 5)), RNG.normal(size=(3, 4, 5))
  ref = np.mean(np.sqrt(np.mean((a - b) ** 2, axis=(1, 2))))
  assert float(losses.rmse_loss(jnp.asarray(a), jnp.asarray(b))) == pytest.approx(ref, rel=1e-5)


def test_phasor_field_loss_matches_numpy_convolution():
  wl = illumination_wavelet(SETUP)
  p, t = _batch()["transient"], _batch()["transient"]
  d = (p - t).astype(np.float64)
  n, length = d.shape[1], wl.num_samples
  full = np.apply_along_axis(lambda s: np.convolve(s, np.asarray(wl.samples)), 1, d)
  same = full[:, length // 2:length // 2 + n]
  ref = np.mean(np.sqrt(np.mean(np.abs(same) ** 2, axis=(1, 2, 3))))
  got = float(losses.phasor_field_loss(jnp.asarray(p), jnp.asarray(t), wl))
  assert got == pytest.approx(ref, rel=1e-4)


def test_local_similarity_matches_scipy_blur():
  v = _batch()["volume"].astype(np.float64)
  g = np.exp(-np.arange(-1, 2) ** 2 / (2 * 1.5 ** 2))
  g /= g.sum()
  k = np.outer(g, g)[None, None]
  blurred = scipy.ndimage.correlate(v, k, mode="nearest")
  ref = np.mean(np.sqrt(np.mean((v - blurred) ** 2, axis=(1, 2, 3))))
  got = float(losses.local_similarity_loss(jnp.asarray(v, jnp.float32)))
  assert got == pytest.approx(ref, rel=1e-4)


def test_tv_is_the_per_sample_sum_of_absolute_differences():
  v = _batch()["volume"].astype(np.float64)
  ref = np.mean(sum(np.abs(np.diff(v, axis=a)).sum(axis=(1, 2, 3)) for a in (1, 2, 3)))
  got = float(losses.tv_loss(jnp.asarray(v, jnp.float32)))
  assert got == pytest.approx(ref, rel=1e-4)


def test_object_intensity_is_the_rmse_over_true_surface_pixels_by_a_loop():
  pred, tgt = RNG.uniform(size=(3, 5, 4)), RNG.uniform(size=(3, 5, 4))
  depth = np.where(RNG.uniform(size=(3, 5, 4)) < 0.4, 0.0, 0.8)
  depth[2] = 0.0                                   # a sample with no object contributes 0
  per_sample = []
  for b in range(3):
    errs = [(pred[b, i, j] - tgt[b, i, j]) ** 2 for i in range(5) for j in range(4)
            if depth[b, i, j] != 0.0]
    per_sample.append(np.sqrt(np.mean(errs)) if errs else 0.0)
  got = losses.object_intensity_loss(jnp.asarray(pred), jnp.asarray(tgt), jnp.asarray(depth))
  assert float(got) == pytest.approx(np.mean(per_sample), rel=1e-5, abs=1e-5)
  # Background errors do not count; inside total_loss the term enters L_v with its weight.
  far = pred.copy()
  far[depth == 0.0] += 5.0
  assert float(losses.object_intensity_loss(jnp.asarray(far), jnp.asarray(tgt),
                                            jnp.asarray(depth))) == pytest.approx(float(got), rel=1e-5)
  out, t = _batch(), _batch()
  w = losses.LossWeights(phasor_field=0.0, alpha1=0.0, gamma=0.0, object_intensity=2.0)
  loss, terms = _total_loss(out, t, w, None)
  assert float(loss) == pytest.approx(float(terms["int"] + terms["dep"] + 2.0 * terms["obj"]), rel=1e-6)
  g = jax.grad(lambda i: losses.object_intensity_loss(i, i, jnp.zeros((2, 3))))(jnp.ones((2, 3)))
  assert np.all(np.isfinite(np.asarray(g)))


def test_balanced_rmse_weighs_object_and_background_pixels_half_each_by_a_loop():
  pred, tgt = RNG.uniform(size=(4, 5, 6)), RNG.uniform(size=(4, 5, 6))
  depth = np.where(RNG.uniform(size=(4, 5, 6)) < 0.8, 0.0, 0.9)      # few object pixels, as in the data
  depth[2] = 0.0                                                       # background only
  depth[3] = 1.1                                                       # objects only
  for balance in (0.0, 0.3, 1.0):
    per_sample = []
    for b in range(4):
      obj = [(pred[b, i, j] - tgt[b, i, j]) ** 2 for i in range(5) for j in range(6) if depth[b, i, j] != 0.0]
      bg = [(pred[b, i, j] - tgt[b, i, j]) ** 2 for i in range(5) for j in range(6) if depth[b, i, j] == 0.0]
      every = np.mean(obj + bg)
      halves = 0.5 * (np.mean(obj) + np.mean(bg)) if obj and bg else np.mean(obj or bg)
      per_sample.append(np.sqrt((1 - balance) * every + balance * halves))
    got = losses.balanced_rmse_loss(jnp.asarray(pred), jnp.asarray(tgt), jnp.asarray(depth), balance)
    assert float(got) == pytest.approx(np.mean(per_sample), rel=1e-5), balance
  assert float(losses.balanced_rmse_loss(jnp.asarray(pred), jnp.asarray(tgt), jnp.asarray(depth), 0.0)) == \
      pytest.approx(float(losses.rmse_loss(jnp.asarray(pred), jnp.asarray(tgt))), rel=1e-6)
  # Inside total_loss, balance makes L_int and L_dep balanced (depth: its own map marks the objects).
  out, t = _batch(), _batch()
  w = losses.LossWeights(phasor_field=0.0, alpha1=0.0, gamma=0.0, balance=1.0)
  _, terms = _total_loss(out, t, w, None)
  dep = np.asarray(t["depth"])
  assert float(terms["int"]) == pytest.approx(float(losses.balanced_rmse_loss(
      out["intensity"], t["intensity"], dep, 1.0)), rel=1e-6)
  assert float(terms["dep"]) == pytest.approx(float(losses.balanced_rmse_loss(out["depth"], dep, dep, 1.0)),
                                              rel=1e-6)
  with pytest.raises(ValueError, match="balance"):
    losses.LossWeights(balance=1.5)
  assert "balance" not in losses.LossWeights().to_dict()        # older runs' recorded weights still match
  g = jax.grad(lambda i: losses.balanced_rmse_loss(i, i, jnp.zeros((2, 3)), 1.0))(jnp.ones((2, 3)))
  assert np.all(np.isfinite(np.asarray(g))) and not np.any(np.asarray(g))


def test_total_loss_does_not_depend_on_batch_size_and_composes_as_the_paper():
  wl = illumination_wavelet(SETUP)
  out, tgt = _batch(1), _batch(1)
  w = losses.LossWeights()
  one, terms = _total_loss(out, tgt, w, wl)
  two = {k: np.concatenate([v, v]) for k, v in out.items()}
  two_t = {k: np.concatenate([v, v]) for k, v in tgt.items()}
  both, _ = _total_loss(two, two_t, w, wl)
  assert float(both) == pytest.approx(float(one), rel=1e-5)
  expect = (terms["pf"] + 0.5 * terms["t"] + 1.0 * (terms["int"] + terms["dep"])
            + 1e-5 * (terms["ls"] + 0.1 * terms["tv"]))
  assert float(one) == pytest.approx(float(expect), rel=1e-6)


def test_zero_weights_switch_terms_off():
  out, tgt = _batch(), _batch()
  w = losses.LossWeights(phasor_field=0.0, gamma=0.0, alpha2=0.0)
  loss, terms = _total_loss(out, tgt, w, None)
  assert set(terms) == {"t", "int", "m", "v", "r"}
  assert float(loss) == pytest.approx(float(0.5 * terms["t"] + terms["int"]), rel=1e-6)
  with pytest.raises(ValueError, match="wavelet"):
    losses.total_loss(out, tgt, losses.LossWeights(), None)
  with pytest.raises(ValueError, match="gamma"):
    losses.LossWeights(gamma=-1.0)
  with pytest.raises(ValueError, match="shape"):
    losses.rmse_loss(jnp.zeros((2, 3)), jnp.zeros((2, 4)))


def test_gradients_are_finite_and_zero_at_zero_error():
  wl = illumination_wavelet(SETUP)
  tgt = _batch()
  flat = {**tgt, "volume": np.zeros_like(tgt["volume"])}   # constant volume: ls = tv = 0

  def f(out):
    return losses.total_loss(out, tgt, losses.LossWeights(), wl)[0]

  grads = jax.jit(jax.grad(f))(jax.tree.map(jnp.asarray, flat))
  for name, g in grads.items():
    g = np.asarray(g)
    assert np.all(np.isfinite(g)), name
    assert np.max(np.abs(g)) < 1e-3, name      # sqrt(mean + eps): no 1/sqrt(0) blow-up


def _mmd2_loop(x, y, bandwidths):
  """The U-statistic written out with explicit loops over pairs."""
  d = x.shape[1]

  def k(a, b):
    return sum(math.exp(-float(np.sum((a - b) ** 2)) / (2 * s * s * d)) for s in bandwidths)

  n, m = len(x), len(y)
  xx = sum(k(x[i], x[j]) for i in range(n) for j in range(n) if i != j) / (n * (n - 1))
  yy = sum(k(y[i], y[j]) for i in range(m) for j in range(m) if i != j) / (m * (m - 1))
  xy = sum(k(x[i], y[j]) for i in range(n) for j in range(m)) / (n * m)
  return xx + yy - 2 * xy


def test_mmd2_matches_the_pairwise_loop_and_tells_distributions_apart():
  mmd2 = jax.jit(losses.mmd2, static_argnums=2)      # one compile per shape, not one per operation
  rng = np.random.default_rng(0)
  x, y = rng.normal(size=(12, 3)), rng.normal(size=(9, 3)) + 0.7
  assert float(mmd2(x, y, (0.5, 2.0))) == pytest.approx(_mmd2_loop(x, y, (0.5, 2.0)), rel=1e-4, abs=1e-6)
  same = [float(mmd2(rng.normal(size=(64, 4)), rng.normal(size=(64, 4)))) for _ in range(5)]
  apart = float(mmd2(rng.normal(size=(64, 4)), rng.normal(size=(64, 4)) + 1.0))
  assert max(abs(v) for v in same) < 0.15 < 0.4 < apart
  with pytest.raises(ValueError, match="n, m >= 2"):
    losses.mmd2(x[:1], y)

"""Tests for nlosjax.metrics against scikit-image and NumPy closed forms."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from nlosjax import metrics

SSIM_ATOL = 1e-5  # observed float32 error vs skimage's float64: ~3e-7
SSIM_ATOL_TIGHT = 1e-6
PSNR_ATOL = 1e-4  # dB


# --------------------------------------------------------------------------
# Helpers: test images and per-image references.


def _noisy(rng, image, noise, lo=0.0, hi=1.0):
  return np.clip(image + noise * rng.standard_normal(image.shape), lo, hi)


def _structured(h, w):
  """A stack [5, h, w] of deterministic, structured images in [0, 1]."""
  yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
  ramp = (xx + yy) / (h + w - 2)
  checker = ((yy // 3 + xx // 3) % 2).astype(np.float64)
  disk = ((yy - h / 2) ** 2 + (xx - w / 3) ** 2 < (min(h, w) / 3) ** 2).astype(np.float64)
  waves = 0.5 + 0.5 * np.sin(xx / 1.7) * np.cos(yy / 2.3)
  edge = (xx > w / 2).astype(np.float64) * 0.8 + 0.1
  return np.stack([ramp, checker, disk, waves, edge])


def _sk_ssim(a, b, *, data_range=1.0, win_size=None, sigma=1.5, k1=0.01, k2=0.03,
             full=False):
  return structural_similarity(
      a, b, gaussian_weights=True, sigma=sigma, use_sample_covariance=False,
      data_range=data_range, win_size=win_size, K1=k1, K2=k2, full=full)


def _per_image(fn, a, b, **kw):
  """Apply a 2D reference to every [H, W] slice of [..., H, W] inputs."""
  lead = a.shape[:-2]
  a2 = a.reshape((-1,) + a.shape[-2:])
  b2 = b.reshape((-1,) + b.shape[-2:])
  return np.array([fn(x, y, **kw) for x, y in zip(a2, b2)]).reshape(lead)


# --------------------------------------------------------------------------
# SSIM against skimage.


@pytest.mark.parametrize("shape", [(11, 11), (16, 16), (13, 24), (30, 12), (2, 3, 14, 17)])
def test_ssim_matches_skimage_random(shape):
  rng = np.random.default_rng(sum(shape))
  target = rng.random(shape)
  # A range of similarities, from near 0 (independent noise) to near 1.
  noise = np.array([0.02, 0.1, 0.3, 1.0])[:, None, None]
  pred = np.stack([_noisy(rng, target, n) for n in noise[:, 0, 0]])
  target = np.broadcast_to(target, pred.shape)
  expected = _per_image(_sk_ssim, pred, target)
  got = np.asarray(metrics.ssim(pred, target))
  assert got.shape == pred.shape[:-2]
  assert got.dtype == np.float32
  np.testing.assert_allclose(got, expected, rtol=0, atol=SSIM_ATOL)
  assert np.ptp(expected) > 0.3  # the cases really differ


@pytest.mark.parametrize("shape", [(12, 12), (15, 26)])
def test_ssim_matches_skimage_structured(shape):
  rng = np.random.default_rng(1)
  target = _structured(*shape)
  pred = _noisy(rng, np.roll(target, 1, axis=-1), 0.05)
  expected = _per_image(_sk_ssim, pred, target)
  np.testing.assert_allclose(metrics.ssim(pred, target), expected, rtol=0, atol=SSIM_ATOL)
  # Symmetric in its two arguments, as SSIM is.
  np.testing.assert_allclose(metrics.ssim(target, pred), expected, rtol=0, atol=SSIM_ATOL)


@pytest.mark.parametrize("h, w, win_size", [(9, 12, 7), (3, 4, 3), (5, 9, 5)])
def test_ssim_small_win_size_matches_skimage(h, w, win_size):
  # win_size < 11 only changes the crop; the 11-tap Gaussian then reaches past
  # the image, so these exercise the (repeated) symmetric border padding.
  rng = np.random.default_rng(h * w)
  target = rng.random((2, h, w))
  pred = _noisy(rng, target, 0.2)
  expected = _per_image(_sk_ssim, pred, target, win_size=win_size)
  got = metrics.ssim(pred, target, win_size=win_size)
  np.testing.assert_allclose(got, expected, rtol=0, atol=SSIM_ATOL)


@pytest.mark.parametrize("sigma", [1.0, 2.0, 3.0])
def test_ssim_other_parameters_match_skimage(sigma):
  # Dark, dimmed prediction on a [0, 2] range: C1 (k1) and C2 (k2) both
  # matter, and a wrong Gaussian truncation (radius int(3.5 sigma + 0.5))
  # shows at the 1e-6 level.
  rng = np.random.default_rng(7)
  target = 2.0 * (0.2 * rng.random((2, 18, 20)) + 0.05 * (np.arange(20) > 10))
  pred = _noisy(rng, 0.6 * target, 0.05, 0.0, 2.0)
  kw = dict(data_range=2.0, sigma=sigma, k1=0.05, k2=0.1, win_size=9)
  expected = _per_image(_sk_ssim, pred, target, **kw)
  np.testing.assert_allclose(metrics.ssim(pred, target, **kw), expected,
                             rtol=0, atol=SSIM_ATOL_TIGHT)
  default_k = _per_image(_sk_ssim, pred, target, **{**kw, "k1": 0.01, "k2": 0.03})
  assert np.all(np.abs(default_k - expected) > 1e-2)  # k1, k2 are not ignorable here


def test_ssim_float32_bright_low_contrast_image():
  # Bright, low-contrast images: E[x^2] - E[x]^2 cancels in float32; the
  # naive formula is off by ~1e-5 here, the mean-shifted one by ~2e-7.
  rng = np.random.default_rng(3)
  means = np.array([0.95, 0.99, 0.999])[:, None, None]
  target = means + 0.005 * (1 - means) / 0.05 * rng.random((3, 24, 24))
  pred = target + 0.2 * (target - means) * rng.standard_normal(target.shape)
  expected = _per_image(_sk_ssim, pred, target)
  got = metrics.ssim(pred.astype(np.float32), target.astype(np.float32))
  np.testing.assert_allclose(got, expected, rtol=0, atol=SSIM_ATOL_TIGHT)


# --------------------------------------------------------------------------
# PSNR against skimage; RMSE / MAD against NumPy.


@pytest.mark.parametrize("shape", [(8, 8), (5, 13), (3, 2, 7, 6)])
def test_psnr_matches_skimage(shape):
  rng = np.random.default_rng(sum(shape))
  target = rng.random(shape)
  pred = _noisy(rng, target, 0.05)
  expected = _per_image(peak_signal_noise_ratio, target, pred, data_range=1.0)
  got = np.asarray(metrics.psnr(pred, target))
  assert got.shape == shape[:-2]
  np.testing.assert_allclose(got, expected, rtol=0, atol=PSNR_ATOL)


def test_psnr_structured_and_data_range():
  rng = np.random.default_rng(5)
  target = _structured(10, 14) * 255.0
  pred = _noisy(rng, target, 4.0, 0.0, 255.0)
  expected = _per_image(peak_signal_noise_ratio, target, pred, data_range=255.0)
  np.testing.assert_allclose(metrics.psnr(pred, target, data_range=255.0), expected,
                             rtol=0, atol=PSNR_ATOL)
  # A per-image data_range broadcasts over the leading dims.
  ranges = np.array([1.0, 2.0, 4.0, 8.0, 255.0])
  expected = [peak_signal_noise_ratio(t, p, data_range=r)
              for t, p, r in zip(target, pred, ranges)]
  np.testing.assert_allclose(metrics.psnr(pred, target, data_range=ranges), expected,
                             rtol=0, atol=PSNR_ATOL)


def test_rmse_mad_closed_form_depth_maps():
  rng = np.random.default_rng(11)
  target = 1.0 + 2.0 * rng.random((2, 3, 9, 7))  # metres
  pred = target + 0.1 * rng.standard_normal(target.shape)
  diff = pred - target
  np.testing.assert_allclose(metrics.rmse(pred, target),
                             np.sqrt(np.mean(diff ** 2, axis=(-2, -1))), rtol=1e-5)
  np.testing.assert_allclose(metrics.mad(pred, target),
                             np.mean(np.abs(diff), axis=(-2, -1)), rtol=1e-5)
  assert metrics.rmse(pred[0, 0], target[0, 0]).shape == ()


# --------------------------------------------------------------------------
# Masks.


def _random_mask(rng, shape, p=0.6):
  mask = rng.random(shape) < p
  mask[..., 0, 0] = True  # never empty
  return mask


def test_masked_rmse_mad_psnr_equal_metric_over_selected_pixels():
  rng = np.random.default_rng(13)
  target = rng.random((3, 8, 10))
  pred = _noisy(rng, target, 0.1)
  pred[..., :2, :] = 5.0  # large errors outside the mask must not count
  mask = _random_mask(rng, target.shape)
  mask[..., :2, :] = False
  for i in range(3):
    sel = mask[i]
    d = pred[i][sel] - target[i][sel]
    assert metrics.rmse(pred, target, mask=mask)[i] == pytest.approx(
        np.sqrt(np.mean(d ** 2)), rel=1e-5)
    assert metrics.mad(pred, target, mask=mask)[i] == pytest.approx(
        np.mean(np.abs(d)), rel=1e-5)
    assert metrics.psnr(pred, target, mask=mask)[i] == pytest.approx(
        peak_signal_noise_ratio(target[i][sel], pred[i][sel], data_range=1.0),
        abs=PSNR_ATOL)
  # A 0/1 float mask means the same as the boolean one.
  for fn in (metrics.rmse, metrics.mad, metrics.psnr):
    np.testing.assert_allclose(fn(pred, target, mask=mask.astype(np.float32)),
                               fn(pred, target, mask=mask), rtol=1e-6)


def test_masked_ssim_averages_cropped_skimage_map():
  rng = np.random.default_rng(17)
  target = rng.random((2, 16, 19))
  pred = _noisy(rng, target, 0.2)
  pred[:, :, 12:] = 1.0 - pred[:, :, 12:]  # a badly wrong region
  mask = _random_mask(rng, target.shape)
  mask[..., 5, 5] = True  # at least one pixel inside the crop
  got = metrics.ssim(pred, target, mask=mask)
  for i in range(2):
    _, smap = _sk_ssim(pred[i], target[i], full=True)
    inner = (slice(5, -5), slice(5, -5))
    expected = smap[inner][mask[i][inner]].mean()
    assert got[i] == pytest.approx(expected, abs=SSIM_ATOL)
  # The mask matters here: unmasked SSIM is different.
  assert np.all(np.abs(np.asarray(got) - np.asarray(metrics.ssim(pred, target))) > 1e-3)


def test_empty_mask_concrete_raises_and_jit_scores_zero_error():
  rng = np.random.default_rng(19)
  target = rng.random((2, 12, 12))
  pred = _noisy(rng, target, 0.2)
  mask = np.ones(target.shape, bool)
  mask[1] = False
  for fn in (metrics.psnr, metrics.ssim, metrics.rmse, metrics.mad):
    with pytest.raises(ValueError, match="mask selects no pixel"):
      fn(pred, target, mask=mask)
  # Only border pixels: nothing survives SSIM's 5-pixel crop.
  border = np.zeros(target.shape, bool)
  border[..., :5, :] = True
  with pytest.raises(ValueError, match="border crop"):
    metrics.ssim(pred, target, mask=border)
  # Under jit the values cannot be checked: empty means zero error.
  args = (jnp.asarray(pred), jnp.asarray(target), jnp.asarray(mask))
  p = jax.jit(lambda a, b, m: metrics.psnr(a, b, mask=m))(*args)
  s = jax.jit(lambda a, b, m: metrics.ssim(a, b, mask=m))(*args)
  r = jax.jit(lambda a, b, m: metrics.rmse(a, b, mask=m))(*args)
  d = jax.jit(lambda a, b, m: metrics.mad(a, b, mask=m))(*args)
  assert p[1] == pytest.approx(metrics.PSNR_CAP_DB, abs=1e-3)
  assert s[1] == 1.0 and r[1] == 0.0 and d[1] == 0.0
  assert p[0] < 30 and s[0] < 0.9 and r[0] > 0.05 and d[0] > 0.05


def test_non_binary_mask_raises():
  x = np.zeros((8, 8))
  with pytest.raises(ValueError, match="only 0 and 1"):
    metrics.rmse(x, x, mask=np.full((8, 8), 0.5))


# --------------------------------------------------------------------------
# jit, gradients, identical images.


def test_jit_matches_eager():
  rng = np.random.default_rng(23)
  target = jnp.asarray(rng.random((2, 13, 15)), jnp.float32)
  pred = jnp.asarray(_noisy(rng, np.asarray(target), 0.1), jnp.float32)
  mask = jnp.asarray(_random_mask(rng, target.shape) | (np.arange(15) == 7))
  fns = (metrics.psnr, metrics.ssim, metrics.rmse, metrics.mad)
  all_metrics = jax.jit(lambda a, b, m: [fn(a, b, mask=m) for fn in fns])
  for m in (None, mask):
    for fn, jitted in zip(fns, all_metrics(pred, target, m)):
      np.testing.assert_allclose(jitted, fn(pred, target, mask=m), rtol=1e-6, atol=1e-6)
  # vmap over the batch gives the batched result as well.
  np.testing.assert_allclose(jax.vmap(metrics.ssim)(pred, target),
                             metrics.ssim(pred, target), rtol=1e-6, atol=1e-6)


def test_identical_images_cap_and_one():
  img = _structured(14, 12)
  p = np.asarray(metrics.psnr(img, img))
  assert np.all(np.isfinite(p))
  np.testing.assert_allclose(p, metrics.PSNR_CAP_DB, atol=1e-3)
  np.testing.assert_allclose(metrics.psnr(img * 7, img * 7, data_range=7.0),
                             metrics.PSNR_CAP_DB, atol=1e-3)
  np.testing.assert_allclose(metrics.ssim(img, img), 1.0, atol=1e-6)
  np.testing.assert_array_equal(metrics.rmse(img, img), 0.0)
  np.testing.assert_array_equal(metrics.mad(img, img), 0.0)
  # Any error at all drops below the cap.
  assert np.all(np.asarray(metrics.psnr(img, img + 1e-3)) < 61.0)


def test_gradients_finite_at_zero_error():
  x = jnp.asarray(_structured(12, 13)[1], jnp.float32)
  for fn in (metrics.rmse, metrics.mad, metrics.psnr, metrics.ssim):
    g = jax.grad(lambda p: fn(p, x))(x)
    assert np.all(np.isfinite(np.asarray(g))), fn.__name__
  np.testing.assert_array_equal(jax.grad(lambda p: metrics.rmse(p, x))(x), 0.0)


def test_rmse_gradient_away_from_zero():
  rng = np.random.default_rng(29)
  t = rng.random((6, 5))
  p = t + 0.1 * rng.standard_normal(t.shape)
  g = jax.grad(lambda a: metrics.rmse(a, jnp.asarray(t, jnp.float32)))(
      jnp.asarray(p, jnp.float32))
  r = np.sqrt(np.mean((p - t) ** 2))
  np.testing.assert_allclose(g, (p - t) / (p.size * r), rtol=1e-4, atol=1e-7)


def test_rmse_propagates_nan_under_jit_and_stays_zero_with_finite_gradient_at_zero_error():
  """NaN must propagate: a sqrt guard that falls back to 0 where the mean square is not > 0 would hide it."""
  target = jnp.asarray(_structured(6, 7)[0], jnp.float32)
  pred = target.at[2, 3].set(jnp.nan)
  jitted = jax.jit(metrics.rmse)
  assert np.isnan(float(jitted(pred, target))) and np.isnan(float(jitted(target, pred)))
  # Eagerly the NaN is refused before anything runs (documented); the computation itself, run op
  # by op, propagates it as the compiled one does.
  with pytest.raises(ValueError, match="pred contains NaN"):
    metrics.rmse(pred, target)
  with jax.disable_jit():
    assert np.isnan(float(metrics._rmse(pred, target, None)))
  # Only the image holding the NaN: its neighbours in the batch keep their values.
  batch = jnp.stack([pred, target + 0.5, target])
  got = np.asarray(jitted(batch, jnp.broadcast_to(target, batch.shape)))
  assert np.isnan(got[0]) and got[1] == pytest.approx(0.5) and got[2] == 0.0
  assert float(jitted(target.at[0, 0].set(jnp.inf), target)) == np.inf
  # A NaN outside the mask is not part of the metric.
  mask = jnp.ones(target.shape, bool).at[2, 3].set(False)
  assert float(jax.jit(lambda a, b, m: metrics.rmse(a, b, mask=m))(pred, target, mask)) == 0.0
  # Zero error: exactly 0 and a zero (finite) gradient, eagerly and under jit.
  for fn in (metrics.rmse, jitted):
    value, grad = jax.value_and_grad(lambda p, fn=fn: fn(p, target))(target)
    assert float(value) == 0.0
    np.testing.assert_array_equal(grad, 0.0)
  # The guard itself: sqrt everywhere but at 0, where value and gradient are 0.
  ms = jnp.array([0.0, 4.0, jnp.nan, jnp.inf], jnp.float32)
  np.testing.assert_array_equal(metrics._sqrt_guarded(ms), [0.0, 2.0, np.nan, np.inf])
  np.testing.assert_array_equal(jax.vmap(jax.grad(metrics._sqrt_guarded))(ms[:2]), [0.0, 0.25])


# --------------------------------------------------------------------------
# Validation.


@pytest.mark.parametrize("fn", [metrics.psnr, metrics.ssim, metrics.rmse, metrics.mad])
def test_validation_errors(fn):
  a = np.zeros((12, 12))
  shapes = r"target has shape \(12, 13\) but pred has shape \(12, 12\)"
  with pytest.raises(ValueError, match=shapes):
    fn(a, np.zeros((12, 13)))
  with pytest.raises(ValueError, match=r"mask has shape \(1, 12, 12\) but pred"):
    fn(a, a, mask=np.ones((1, 12, 12), bool))
  with pytest.raises(ValueError, match="rank >= 2"):
    fn(np.zeros(12), np.zeros(12))
  bad = a.copy()
  bad[3, 4] = np.nan
  with pytest.raises(ValueError, match="pred contains NaN"):
    fn(bad, a)
  with pytest.raises(ValueError, match="target contains NaN"):
    fn(a, jnp.asarray(bad))
  # Shapes are static, so they are checked under jit too.
  with pytest.raises(ValueError, match="target has shape"):
    jax.jit(fn)(jnp.zeros((12, 12)), jnp.zeros((12, 13)))


def test_ssim_size_and_parameter_errors():
  with pytest.raises(ValueError, match="smaller than win_size=11"):
    metrics.ssim(np.zeros((10, 20)), np.zeros((10, 20)))
  with pytest.raises(ValueError, match="smaller than win_size=11"):
    metrics.ssim(np.zeros((3, 20, 10)), np.zeros((3, 20, 10)))
  metrics.ssim(np.zeros((2, 11, 11)), np.zeros((2, 11, 11)))  # the smallest accepted
  with pytest.raises(ValueError, match="odd"):
    metrics.ssim(np.zeros((12, 12)), np.zeros((12, 12)), win_size=8)
  with pytest.raises(ValueError, match="sigma"):
    metrics.ssim(np.zeros((12, 12)), np.zeros((12, 12)), sigma=0.0)
  with pytest.raises(ValueError, match="data_range"):
    metrics.psnr(np.zeros((4, 4)), np.zeros((4, 4)), data_range=0.0)


# --------------------------------------------------------------------------
# Object-aware depth scores, against hand-computed cases and a per-pixel loop.

# True depth (0 = background): 3 surface pixels.
GT_DEPTH = np.array([[0.0, 1.0, 1.0, 0.0],
                     [0.0, 2.0, 0.0, 0.0],
                     [0.0, 0.0, 0.0, 0.0]])
# Reconstructed: 0.05 m is below SURFACE_MIN_DEPTH (background); 4 pixels are surface.
PRED_DEPTH = np.array([[0.05, 1.5, 0.0, 0.5],
                       [0.0, 2.0, 0.0, 0.0],
                       [0.0, 0.0, 0.0, 0.2]])


def test_surface_scores_by_hand():
  # TP = (0,1), (1,1); FN = (0,2); FP = (0,3), (2,3).
  s = {k: float(v) for k, v in metrics.surface_scores(PRED_DEPTH, GT_DEPTH).items()}
  assert s["recall"] == pytest.approx(2 / 3)
  assert s["precision"] == pytest.approx(2 / 4)
  assert s["f1"] == pytest.approx(4 / 7)                     # 2TP / (2TP + FP + FN)
  # Depth errors over the true surface: 0.5, -1.0 (missed, 0 m), 0.0.
  assert s["rmse_object"] == pytest.approx(np.sqrt(1.25 / 3))
  assert s["mad_object"] == pytest.approx(0.5)
  assert tuple(metrics.surface_scores(PRED_DEPTH, GT_DEPTH)) == metrics.OBJECT_METRICS
  # The single-score functions are the same numbers.
  assert float(metrics.recall(PRED_DEPTH, GT_DEPTH)) == pytest.approx(2 / 3)
  assert float(metrics.precision(PRED_DEPTH, GT_DEPTH)) == pytest.approx(0.5)
  assert float(metrics.f1(PRED_DEPTH, GT_DEPTH)) == pytest.approx(4 / 7)
  assert float(metrics.rmse_object(PRED_DEPTH, GT_DEPTH)) == pytest.approx(np.sqrt(1.25 / 3))
  assert float(metrics.mad_object(PRED_DEPTH, GT_DEPTH)) == pytest.approx(0.5)
  # A higher threshold makes the 0.2 m false positive background.
  assert float(metrics.precision(PRED_DEPTH, GT_DEPTH, min_depth=0.3)) == pytest.approx(2 / 3)


def test_surface_scores_empty_denominators_are_nan_not_invented():
  empty = np.zeros_like(GT_DEPTH)
  # No true surface, something reconstructed: recall and object depth undefined, all FP.
  s = metrics.surface_scores(PRED_DEPTH, empty)
  assert np.isnan(s["recall"]) and np.isnan(s["rmse_object"]) and np.isnan(s["mad_object"])
  assert float(s["precision"]) == 0.0 and float(s["f1"]) == 0.0
  # Nothing reconstructed, a true surface: recall 0, precision undefined, the depth error is
  # the true depth itself.
  s = metrics.surface_scores(empty, GT_DEPTH)
  assert float(s["recall"]) == 0.0 and np.isnan(s["precision"]) and float(s["f1"]) == 0.0
  assert float(s["mad_object"]) == pytest.approx(4 / 3)
  # Neither has a surface: every score is undefined.
  assert all(np.isnan(v) for v in metrics.surface_scores(empty, empty).values())
  # Perfect reconstruction: errors exactly 0 (guarded sqrt), rates 1.
  s = metrics.surface_scores(GT_DEPTH, GT_DEPTH)
  assert float(s["rmse_object"]) == 0.0 and float(s["f1"]) == 1.0


def test_surface_scores_match_a_pixel_loop_batched_and_jitted():
  rng = np.random.default_rng(7)
  gt = np.where(rng.random((2, 3, 9, 11)) < 0.3, rng.uniform(0.3, 2.5, (2, 3, 9, 11)), 0.0)
  gt[0, 1] = 0.0                                               # one frame without an object
  pred = np.where(rng.random(gt.shape) < 0.6, gt + rng.normal(0, 0.2, gt.shape), 0.0)
  pred = np.clip(pred + np.where(rng.random(gt.shape) < 0.1, 0.8, 0.0), 0, None)
  got = jax.jit(metrics.surface_scores)(pred.astype(np.float32), gt.astype(np.float32))
  for i, j in np.ndindex(2, 3):
    tp = fp = fn = 0
    sq = ab = 0.0
    for y, x in np.ndindex(9, 11):
      t, p = gt[i, j, y, x], pred[i, j, y, x]
      is_true, is_found = t > 0, p >= metrics.SURFACE_MIN_DEPTH
      tp += is_true and is_found
      fn += is_true and not is_found
      fp += is_found and not is_true
      if is_true:
        sq += (p - t) ** 2
        ab += abs(p - t)
    n = tp + fn
    want = {"recall": tp / n if n else np.nan, "precision": tp / (tp + fp) if tp + fp else np.nan,
            "f1": 2 * tp / (2 * tp + fp + fn) if 2 * tp + fp + fn else np.nan,
            "rmse_object": np.sqrt(sq / n) if n else np.nan, "mad_object": ab / n if n else np.nan}
    for k, v in want.items():
      np.testing.assert_allclose(got[k][i, j], v, rtol=1e-5, err_msg=f"{k} [{i}, {j}]")


def test_surface_scores_of_an_image_holding_nan_are_nan_under_jit():
  """NaN >= min_depth and NaN > 0 are false: without the guard a NaN pixel counted as background
  and every score stayed finite (recall 8/9 where it should be NaN)."""
  scores = jax.jit(metrics.surface_scores)
  good = np.stack([PRED_DEPTH, GT_DEPTH]).astype(np.float32)      # [pred, target] of one image
  for which, (y, x) in ((0, (2, 0)), (0, (0, 1)), (1, (2, 0)), (1, (0, 1))):   # background, surface
    bad = good.copy()
    bad[which, y, x] = np.nan
    # A batch of two: the NaN image, and the clean one whose scores are unchanged.
    got = scores(np.stack([bad[0], good[0]]), np.stack([bad[1], good[1]]))
    assert set(got) == set(metrics.OBJECT_METRICS)
    for name in metrics.OBJECT_METRICS:
      assert np.isnan(got[name][0]), (name, which, y, x)
      assert float(got[name][1]) == pytest.approx(float(metrics.surface_scores(*good)[name]))
      single = jax.jit(getattr(metrics, name))(bad[0], bad[1])
      assert np.isnan(single), name


def test_surface_scores_reject_bad_input():
  with pytest.raises(ValueError, match="shape"):
    metrics.surface_scores(PRED_DEPTH, GT_DEPTH[:2])
  with pytest.raises(ValueError, match="NaN"):
    metrics.surface_scores(np.full_like(GT_DEPTH, np.nan), GT_DEPTH)
  with pytest.raises(ValueError, match="min_depth"):
    metrics.surface_scores(PRED_DEPTH, GT_DEPTH, min_depth=0.0)


# --------------------------------------------------------------------------
# Temporal consistency: the change between consecutive frames against the true change.

# A 3-frame sequence of 2 x 2 intensity images (frames first).
SEQ_TRUTH = np.array([[[0.0, 0.0], [0.0, 0.0]],
                      [[1.0, 0.0], [0.0, 0.0]],
                      [[1.0, 1.0], [0.0, 0.0]]])
SEQ_PRED = np.array([[[0.5, 0.0], [0.0, 0.0]],
                     [[0.5, 0.0], [0.0, 0.5]],
                     [[1.0, 0.5], [0.0, 0.5]]])
# True depth (0 = background) of 4 frames, and a reconstruction of it.
SEQ_DEPTH = np.array([[[1.0, 0.0], [0.0, 2.0]],
                      [[1.5, 1.0], [0.0, 0.0]],
                      [[0.0, 1.0], [0.0, 0.0]],
                      [[0.0, 0.0], [0.0, 0.0]]])
SEQ_PRED_DEPTH = np.array([[[1.2, 0.0], [0.3, 2.0]],
                           [[1.2, 0.9], [0.0, 0.0]],
                           [[0.0, 1.3], [0.0, 0.0]],
                           [[0.5, 0.5], [0.5, 0.5]]])


def test_temporal_scores_by_hand():
  # Pair (0, 1): true change [[1, 0], [0, 0]], reconstructed change [[0, 0], [0, 0.5]];
  #   error [[-1, 0], [0, 0.5]], mean square (1 + 0.25) / 4 = 0.3125.
  # Pair (1, 2): true change [[0, 1], [0, 0]], reconstructed [[0.5, 0.5], [0, 0]];
  #   error [[0.5, -0.5], [0, 0]], mean square 0.5 / 4 = 0.125.
  # Pooled: (0.3125 + 0.125) / 2 = 0.21875. PSNR peak 1: 10 log10(1 / MSE).
  np.testing.assert_allclose(metrics.temporal_rmse(SEQ_PRED, SEQ_TRUTH),
                             [np.sqrt(0.3125), np.sqrt(0.125)], rtol=1e-6)
  np.testing.assert_allclose(metrics.temporal_psnr(SEQ_PRED, SEQ_TRUTH),
                             [10 * np.log10(1 / 0.3125), 10 * np.log10(8.0)], rtol=1e-6)
  assert float(metrics.temporal_rmse(SEQ_PRED, SEQ_TRUTH, pooled=True)) == pytest.approx(
      np.sqrt(0.21875), rel=1e-6)
  assert float(metrics.temporal_psnr(SEQ_PRED, SEQ_TRUTH, pooled=True)) == pytest.approx(
      10 * np.log10(1 / 0.21875), rel=1e-6)
  # The peak is the images' data range, as in psnr: the PSNR of the two changes.
  np.testing.assert_allclose(metrics.temporal_psnr(SEQ_PRED, SEQ_TRUTH, data_range=2.0),
                             metrics.psnr(np.diff(SEQ_PRED, axis=0), np.diff(SEQ_TRUTH, axis=0),
                                          data_range=2.0), rtol=1e-6)
  # Depth over the pixels that are surface in both frames:
  # pair (0, 1): only (0, 0); reconstructed change 0, true change 0.5: error -0.5.
  # pair (1, 2): only (0, 1); reconstructed change 0.4, true change 0: error 0.4 (the reconstructed
  #   background at (0, 0) and the surface that left at (1, 1) do not count).
  # pair (2, 3): no pixel is surface in frame 3: NaN, not a number made up for it.
  got = np.asarray(metrics.temporal_rmse_object(SEQ_PRED_DEPTH, SEQ_DEPTH))
  np.testing.assert_allclose(got[:2], [0.5, 0.4], rtol=1e-5)
  assert np.isnan(got[2])
  # Pooled: (0.25 + 0.16) / 2 object pixels; a sequence with no pair scored is NaN.
  assert float(metrics.temporal_rmse_object(SEQ_PRED_DEPTH, SEQ_DEPTH, pooled=True)) == pytest.approx(
      np.sqrt(0.41 / 2), rel=1e-5)
  assert np.isnan(metrics.temporal_rmse_object(SEQ_PRED_DEPTH[2:], SEQ_DEPTH[2:], pooled=True))


def _temporal_loop(pred, target):
  """The definitions by a pixel loop in float64: per pair, then pooled, for each sequence."""
  lead, (f, h, w) = pred.shape[:-3], pred.shape[-3:]
  out = {k: np.zeros(lead + (f - 1,)) for k in ("rmse", "psnr", "object")}
  pooled = {k: np.zeros(lead) for k in ("rmse", "psnr", "object")}
  for idx in np.ndindex(*lead):
    p, y = pred[idx], target[idx]
    all_sq = obj_sq = 0.0
    obj_n = 0
    for t in range(1, f):
      sq, o_sq, o_n = 0.0, 0.0, 0
      for i, j in np.ndindex(h, w):
        e = (p[t, i, j] - p[t - 1, i, j]) - (y[t, i, j] - y[t - 1, i, j])
        sq += e * e
        if y[t, i, j] > 0 and y[t - 1, i, j] > 0:
          o_sq, o_n = o_sq + e * e, o_n + 1
      out["rmse"][idx + (t - 1,)] = np.sqrt(sq / (h * w))
      out["psnr"][idx + (t - 1,)] = 10 * np.log10(1 / max(sq / (h * w), 1e-10))
      out["object"][idx + (t - 1,)] = np.sqrt(o_sq / o_n) if o_n else np.nan
      all_sq, obj_sq, obj_n = all_sq + sq, obj_sq + o_sq, obj_n + o_n
    pooled["rmse"][idx] = np.sqrt(all_sq / ((f - 1) * h * w))
    pooled["psnr"][idx] = 10 * np.log10((f - 1) * h * w / all_sq)
    pooled["object"][idx] = np.sqrt(obj_sq / obj_n) if obj_n else np.nan
  return out, pooled


def test_temporal_scores_match_a_pixel_loop_batched_and_jitted():
  rng = np.random.default_rng(37)
  shape = (2, 3, 4, 5, 6)                                  # 2 x 3 sequences of 4 frames of 5 x 6
  target = np.where(rng.random(shape) < 0.5, rng.uniform(0.3, 2.0, shape), 0.0)
  target[1, 2] = 0.0                                       # a sequence without an object
  target[0, 1, 2] = 0.0                                    # a frame without one
  pred = np.clip(target + rng.normal(0, 0.2, shape), 0, None)
  p32, y32 = pred.astype(np.float32), target.astype(np.float32)

  def every(p, y):
    return {"rmse": metrics.temporal_rmse(p, y), "psnr": metrics.temporal_psnr(p, y),
            "object": metrics.temporal_rmse_object(p, y),
            "pooled_rmse": metrics.temporal_rmse(p, y, pooled=True),
            "pooled_psnr": metrics.temporal_psnr(p, y, pooled=True),
            "pooled_object": metrics.temporal_rmse_object(p, y, pooled=True)}

  jitted = jax.jit(every)(p32, y32)
  eager = every(p32, y32)
  want, want_pooled = _temporal_loop(pred, target)
  assert np.isnan(want["object"][1, 2]).all() and np.isnan(want["object"][0, 1, 1:3]).all()
  for k in want:
    assert jitted[k].shape == shape[:2] + (3,) and jitted[k].dtype == np.float32
    np.testing.assert_allclose(jitted[k], want[k], rtol=1e-5, atol=1e-6, err_msg=k)
    np.testing.assert_allclose(jitted[f"pooled_{k}"], want_pooled[k], rtol=1e-5, atol=1e-6, err_msg=k)
    for name in (k, f"pooled_{k}"):
      np.testing.assert_allclose(eager[name], jitted[name], rtol=1e-6, atol=1e-7, err_msg=name)


def test_temporal_error_is_zero_for_a_constant_offset_and_the_flicker_rms_for_a_static_truth():
  rng = np.random.default_rng(5)
  truth = rng.uniform(0, 1, (3, 5, 4, 4)).astype(np.float32)     # 3 sequences of 5 frames
  depth = np.where(truth > 0.3, 1.0 + truth, 0.0).astype(np.float32)
  # The truth plus a constant per sequence (here even per pixel): every change is the true one.
  offset = rng.uniform(-0.2, 0.2, (3, 1, 4, 4)).astype(np.float32)
  np.testing.assert_allclose(metrics.temporal_rmse(truth + offset, truth), 0.0, atol=1e-6)
  np.testing.assert_allclose(metrics.temporal_psnr(truth + offset, truth), metrics.PSNR_CAP_DB,
                             atol=1e-3)
  np.testing.assert_allclose(metrics.temporal_rmse_object(depth + offset, depth), 0.0, atol=1e-6)
  # Identical sequences: exactly 0 and the cap.
  assert float(jnp.max(metrics.temporal_rmse(truth, truth))) == 0.0
  assert float(jnp.min(metrics.temporal_psnr(truth, truth))) == pytest.approx(metrics.PSNR_CAP_DB)
  # A static truth and a reconstruction that flickers around it: the error is the RMS of the
  # flicker, the reconstruction's frame-to-frame change. Alternating +-a (a pattern m): each
  # change is +-2 a m, whose RMS is 2 a RMS(m), for every pair and pooled.
  static = np.broadcast_to(truth[:, :1], truth.shape)
  m = rng.uniform(0.5, 1.0, (4, 4)).astype(np.float32)
  a = 0.05
  sign = np.array([1.0, -1.0, 1.0, -1.0, 1.0], np.float32)[:, None, None]
  flicker = static + a * sign * m
  rms = 2 * a * np.sqrt(np.mean(m.astype(np.float64) ** 2))
  np.testing.assert_allclose(metrics.temporal_rmse(flicker, static), rms, rtol=1e-5)
  np.testing.assert_allclose(metrics.temporal_rmse(flicker, static, pooled=True), rms, rtol=1e-5)
  # A random flicker: per pair, the RMS of that pair's change.
  noisy = static + rng.normal(0, 0.1, truth.shape).astype(np.float32)
  change_rms = np.sqrt(np.mean(np.diff(noisy.astype(np.float64), axis=1) ** 2, axis=(-2, -1)))
  np.testing.assert_allclose(metrics.temporal_rmse(noisy, static), change_rms, rtol=1e-5)


def test_temporal_scores_propagate_nan_under_jit_to_the_pairs_holding_it():
  rng = np.random.default_rng(8)
  truth = rng.uniform(0.2, 1.0, (2, 4, 5, 5)).astype(np.float32)   # surface everywhere
  pred = truth + rng.normal(0, 0.1, truth.shape).astype(np.float32)
  fns = {n: jax.jit(getattr(metrics, n)) for n in metrics.TEMPORAL_METRICS}
  clean = {n: np.asarray(fn(pred, truth)) for n, fn in fns.items()}
  for which in (0, 1):                                    # NaN in pred, then in the target
    p, y = pred.copy(), truth.copy()
    (p, y)[which][0, 1, 2, 3] = np.nan                    # sequence 0, frame 1
    for name, fn in fns.items():
      got = np.asarray(fn(p, y))
      assert np.isnan(got[0, :2]).all(), (name, which)     # pairs (0, 1) and (1, 2)
      np.testing.assert_array_equal(got[0, 2], clean[name][0, 2])   # pair (2, 3) keeps its value
      np.testing.assert_array_equal(got[1], clean[name][1])         # so does the other sequence
      pooled = np.asarray(jax.jit(functools.partial(getattr(metrics, name), pooled=True))(p, y))
      assert np.isnan(pooled[0]) and np.isfinite(pooled[1]), (name, which)
    # Eagerly the NaN is refused before anything runs.
    for name in metrics.TEMPORAL_METRICS:
      with pytest.raises(ValueError, match=f"{('pred', 'target')[which]} contains NaN"):
        getattr(metrics, name)(p, y)
  # A NaN at a pixel that is background in the truth still makes the depth pair NaN
  # (NaN > 0 is false: without the guard it would drop out of the object silently).
  y = truth.copy()
  y[0, 1, 0, 0] = 0.0
  p = pred.copy()
  p[0, 1, 0, 0] = np.nan
  got = np.asarray(fns["temporal_rmse_object"](p, y))
  assert np.isnan(got[0, :2]).all() and np.isfinite(got[0, 2])


def test_temporal_scores_reject_bad_input():
  for name in metrics.TEMPORAL_METRICS:
    fn = getattr(metrics, name)
    with pytest.raises(ValueError, match="at least 2 frames"):
      fn(np.zeros((1, 4, 4)), np.zeros((1, 4, 4)))
    with pytest.raises(ValueError, match="at least 2 frames"):           # shapes are static
      jax.jit(fn)(jnp.zeros((3, 1, 4, 4)), jnp.zeros((3, 1, 4, 4)))
    with pytest.raises(ValueError, match="rank >= 3"):
      fn(np.zeros((4, 4)), np.zeros((4, 4)))
    with pytest.raises(ValueError, match="target has shape"):
      fn(np.zeros((2, 4, 4)), np.zeros((3, 4, 4)))
    with pytest.raises(ValueError, match="pooled"):
      fn(np.zeros((2, 4, 4)), np.zeros((2, 4, 4)), pooled="yes")
  with pytest.raises(ValueError, match="data_range"):
    metrics.temporal_psnr(np.zeros((2, 4, 4)), np.zeros((2, 4, 4)), data_range=0.0)


def test_object_intensity_error_is_the_mean_absolute_error_over_true_object_pixels_by_loop():
  rng = np.random.default_rng(7)
  pred = rng.uniform(0, 1, (3, 9, 7)).astype(np.float32)
  gt = rng.uniform(0, 1, (3, 9, 7)).astype(np.float32)
  depth = np.where(rng.uniform(size=(3, 9, 7)) < 0.3, rng.uniform(0.5, 2.0, (3, 9, 7)), 0.0).astype(np.float32)
  depth[2] = 0.0                                              # a frame without an object
  got = np.asarray(metrics.intensity_mae_object(pred, gt, depth))
  for i in range(2):
    errs = [abs(float(pred[i, y, x]) - float(gt[i, y, x])) for y in range(9) for x in range(7)
            if depth[i, y, x] > 0]
    assert got[i] == pytest.approx(sum(errs) / len(errs), rel=1e-6)
  assert np.isnan(got[2])
  # A dark image scores the objects' mean true intensity, whatever the background.
  dark = np.asarray(metrics.intensity_mae_object(np.zeros_like(gt), gt, depth))
  assert dark[0] == pytest.approx(float(gt[0][depth[0] > 0].mean()), rel=1e-6)
  with pytest.raises(ValueError, match="intensity_mae_object"):
    metrics.intensity_mae_object(pred, gt, depth[:, :8])


def test_the_all_zero_floor_is_skimages_psnr_of_a_black_image():
  from skimage.metrics import peak_signal_noise_ratio
  rng = np.random.default_rng(8)
  gt = (rng.uniform(size=(2, 16, 16)) * (rng.uniform(size=(2, 16, 16)) < 0.2)).astype(np.float32)
  got = np.asarray(metrics.psnr_zero(gt))
  for i in range(2):
    assert got[i] == pytest.approx(peak_signal_noise_ratio(gt[i], np.zeros_like(gt[i]), data_range=1.0),
                                   abs=1e-4)
  assert float(metrics.psnr_zero(np.zeros((4, 4), np.float32))) == metrics.PSNR_CAP_DB

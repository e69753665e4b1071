"""Every public metric under ``jit`` with bad values: NaN propagates, inf and negatives score by definition.

The metrics have no compiled check (their NaN check is eager only), and their
documented behaviour under jit is propagation: an image (a temporal score: a
pair of frames) holding a NaN scores NaN, an inf gives a non-finite score
wherever it enters an error, and a negative value (a real number like any other
to a metric) gives the definition's value, each against the definitions in
float64 NumPy. The classic methods' checks on bad counts: ``test_stability_physics``.
"""


import jax
import numpy as np
import pytest
from skimage.metrics import structural_similarity

from nlosjax import metrics
from nlosjax.physics import checks
from tests.stability import (
  BAD_VALUES,
  fast_compiles,  # noqa: F401 (the module's fixture, by name below)
)

pytestmark = pytest.mark.usefixtures("fast_compiles")


METRICS = ("psnr", "ssim", "rmse", "mad", "rmse_object", "mad_object", "recall", "precision", "f1")
#: The metrics of other signatures, as functions of the (pred, target) pair: the object intensity
#: error with the target as the depth map too (its object pixels are target > 0), and the
#: all-zero floor, a function of the target alone (so a NaN in pred does not reach it).
OTHER = {"intensity_mae_object": lambda pred, target: metrics.intensity_mae_object(pred, target, target),
         "psnr_zero": lambda pred, target: metrics.psnr_zero(target),
         "psnr_balanced": lambda pred, target: metrics.psnr_balanced(pred, target, target),
         "psnr_balanced_zero": lambda pred, target: metrics.psnr_balanced_zero(target, target)}
#: The floors: functions of the target alone.
FLOORS = ("psnr_zero", "psnr_balanced_zero")


def _all_metrics(pred, target) -> dict:
  """Every public metric of ``nlosjax.metrics`` (``surface_scores`` as ``surface.<name>``)."""
  out = {name: getattr(metrics, name)(pred, target) for name in METRICS}
  out.update({name: f(pred, target) for name, f in OTHER.items()})
  out.update({f"surface.{k}": v for k, v in metrics.surface_scores(pred, target).items()})
  return out


def _reference_metrics(pred: np.ndarray, target: np.ndarray) -> dict:
  """The definitions in float64 NumPy, one image (inf in, inf or NaN out by IEEE rules)."""
  with np.errstate(all="ignore"):
    mse = np.mean((pred - target) ** 2)
    truth, found = target > 0, pred >= metrics.SURFACE_MIN_DEPTH
    tp, fn, fp = np.sum(truth & found), np.sum(truth & ~found), np.sum(~truth & found)
    err = np.where(truth, pred - target, 0.0)
    ref = {"psnr": 10 * np.log10(1.0 / max(mse, 1e-10)), "rmse": np.sqrt(mse),
           "mad": np.mean(np.abs(pred - target)),
           "ssim": (structural_similarity(pred, target, gaussian_weights=True, sigma=1.5,
                                          use_sample_covariance=False, data_range=1.0)
                    if np.all(np.isfinite(pred) & np.isfinite(target)) else np.nan),
           "rmse_object": np.sqrt(np.sum(err ** 2) / (tp + fn)),
           "mad_object": np.sum(np.abs(err)) / (tp + fn), "recall": tp / (tp + fn),
           "precision": tp / (tp + fp), "f1": 2 * tp / (2 * tp + fp + fn),
           "intensity_mae_object": (np.sum(np.where(truth, np.abs(pred - target), 0.0)) / np.sum(truth)
                                    if not np.isnan(pred).any() | np.isnan(target).any() else np.nan),
           "psnr_zero": 10 * np.log10(1.0 / max(np.mean(target ** 2), 1e-10))}
    for name, p in (("psnr_balanced", pred), ("psnr_balanced_zero", np.zeros_like(pred))):
      sq = (p - target) ** 2
      balanced = 0.5 * (np.mean(sq[truth]) + np.mean(sq[~truth]))
      ref[name] = np.nan if np.isnan(balanced) else 10 * np.log10(1.0 / max(balanced, 1e-10))
  ref.update({f"surface.{k}": ref[k] for k in metrics.OBJECT_METRICS})
  return ref


def test_every_metric_propagates_nan_and_scores_inf_and_negative_values_under_checked_jit():
  """One compile of every metric for seven 12 x 12 depth maps: a clean pair, then NaN, +inf and
  -1 m at a true-surface pixel of the prediction, then of the target."""
  # Every public function of nlosjax.metrics is here but ``surface`` (a boolean mask, not a score)
  # and the temporal scores of sequences (the next test).
  public = {n for n in metrics.__all__ if callable(getattr(metrics, n))}
  assert public == (set(METRICS) | set(OTHER) | {"surface_scores", "surface"}
                    | set(metrics.TEMPORAL_METRICS)), public
  rng = np.random.default_rng(36)
  target = np.zeros((12, 12))
  target[3:9, 2:8] = rng.uniform(0.8, 1.5, (6, 6))
  pred = np.where(rng.random(target.shape) < 0.8, target + rng.normal(0, 0.05, target.shape), 0.0)
  pred[0, 0] = 0.4                                          # one false positive
  rows = [("clean", None, None)] + [(kind, arg, v) for arg in (0, 1)
                                    for kind, v in BAD_VALUES.items()]
  pairs = np.stack([np.stack([pred, target])] * len(rows)).astype(np.float32)   # [7, 2, H, W]
  for i, (_, arg, value) in enumerate(rows[1:], 1):
    pairs[i, arg, 5, 4] = value
  got = checks.checked(_all_metrics)(pairs[:, 0], pairs[:, 1])
  plain = jax.jit(_all_metrics)(pairs[:, 0], pairs[:, 1])
  assert set(got) == set(METRICS) | set(OTHER) | {f"surface.{k}" for k in metrics.OBJECT_METRICS}
  for i, (kind, arg, _) in enumerate(rows):
    ref = _reference_metrics(pairs[i, 0].astype(np.float64), pairs[i, 1].astype(np.float64))
    for name, value in got.items():
      v, what = float(value[i]), (name, kind, "-" if arg is None else ("pred", "target")[arg])
      assert v == float(plain[name][i]) or (np.isnan(v) and np.isnan(plain[name][i])), what
      if kind == "NaN" and not (name in FLOORS and arg == 0):
        assert np.isnan(v), what                    # never a finite number made up for it
      else:
        np.testing.assert_allclose(v, ref[name], rtol=1e-5, atol=1e-6, err_msg=str(what))
      if kind == "+inf" and name in ("psnr", "ssim", "rmse", "mad", "rmse_object", "mad_object"):
        assert not np.isfinite(v), what             # the inf enters each of these errors
  # Eagerly, NaN is refused before anything compiles; inf and negative values score as under jit.
  calls = {**{name: getattr(metrics, name) for name in METRICS + ("surface_scores",)}, **OTHER}
  for name, call in calls.items():
    for i in (i for i, (kind, _, _) in enumerate(rows) if kind == "NaN"):
      if name in FLOORS and rows[i][1] == 0:
        continue                                    # pred is not its argument
      with pytest.raises(ValueError, match=f"{('pred', 'target')[rows[i][1]]} contains NaN"):
        call(pairs[i, 0], pairs[i, 1])
  eager_rows = [i for i, (kind, _, _) in enumerate(rows) if kind != "NaN"]
  eager = _all_metrics(pairs[eager_rows, 0], pairs[eager_rows, 1])
  for name, value in eager.items():
    np.testing.assert_allclose(value, np.asarray(got[name])[eager_rows], rtol=1e-6, err_msg=name)


def _reference_temporal(pred: np.ndarray, target: np.ndarray) -> dict:
  """The temporal scores' definitions in float64 NumPy, one sequence ``[F, H, W]`` -> ``[F - 1]``."""
  with np.errstate(all="ignore"):
    err = np.diff(pred, axis=0) - np.diff(target, axis=0)
    both = (target[1:] > 0) & (target[:-1] > 0)
    mse = np.mean(err ** 2, axis=(1, 2))
    return {"temporal_rmse": np.sqrt(mse), "temporal_psnr": 10 * np.log10(1.0 / np.maximum(mse, 1e-10)),
            "temporal_rmse_object": np.sqrt(np.sum(np.where(both, err ** 2, 0.0), axis=(1, 2))
                                            / np.sum(both, axis=(1, 2)))}


def test_temporal_metrics_propagate_nan_and_score_inf_and_negative_values_under_checked_jit():
  """The temporal scores of seven 3-frame sequences of 8 x 8 depth maps: a clean one, then NaN, +inf
  and -1 m at a true-surface pixel of frame 1 of the prediction, then of the target. The bad value
  enters both pairs; NaN makes them NaN, the others score by the definition."""
  rng = np.random.default_rng(37)
  target = np.zeros((3, 8, 8))
  target[:, 2:6, 2:6] = rng.uniform(0.8, 1.5, (3, 4, 4))
  pred = target + rng.normal(0, 0.05, target.shape)
  rows = [("clean", None, None)] + [(kind, arg, v) for arg in (0, 1)
                                    for kind, v in BAD_VALUES.items()]
  seqs = np.stack([np.stack([pred, target])] * len(rows)).astype(np.float32)   # [7, 2, F, H, W]
  for i, (_, arg, value) in enumerate(rows[1:], 1):
    seqs[i, arg, 1, 3, 4] = value

  def every(p, y):
    return {n: getattr(metrics, n)(p, y) for n in metrics.TEMPORAL_METRICS}

  got = checks.checked(every)(seqs[:, 0], seqs[:, 1])
  plain = jax.jit(every)(seqs[:, 0], seqs[:, 1])
  for i, (kind, arg, _) in enumerate(rows):
    ref = _reference_temporal(seqs[i, 0].astype(np.float64), seqs[i, 1].astype(np.float64))
    for name, value in got.items():
      v, what = np.asarray(value[i]), (name, kind, "-" if arg is None else ("pred", "target")[arg])
      np.testing.assert_array_equal(v, np.asarray(plain[name][i]), err_msg=str(what))
      if kind == "NaN":
        assert np.isnan(v).all(), what
      else:
        np.testing.assert_allclose(v, ref[name], rtol=1e-5, atol=1e-5, err_msg=str(what))
      if kind == "+inf":
        assert not np.isfinite(v).any(), what
  for name in metrics.TEMPORAL_METRICS:
    for i in (i for i, (kind, _, _) in enumerate(rows) if kind == "NaN"):
      with pytest.raises(ValueError, match=f"{('pred', 'target')[rows[i][1]]} contains NaN"):
        getattr(metrics, name)(seqs[i, 0], seqs[i, 1])

"""experiments.studies.realism: the input features and the held-out classifier.

Independent references: inputs built by hand with a known background, return
width, signal-to-background ratio and falloff exponent; classes drawn from
one distribution (chance) or two far apart (separable).
"""

import numpy as np
import pytest

from experiments.studies import realism

BIN_LENGTH = 0.02   # m of round-trip path per bin: a return at bin k is 0.01 k m away


def synthetic_input(power=3.0, background=2.0, width_bins=3, T=128, n=6):
  """Boxes of ``width_bins`` bins at a per-point distance, counts ∝ r^-power, on a flat floor."""
  x = np.full((T, n, n), background)
  peaks = 40 + 6 * np.arange(n * n).reshape(n, n) % 60
  amp = np.zeros((n, n))
  for i in range(n):
    for j in range(n):
      r = (peaks[i, j] + 0.5) * BIN_LENGTH / 2
      amp[i, j] = 50.0 * r ** -power
      x[peaks[i, j]:peaks[i, j] + width_bins, i, j] += amp[i, j]
  return x, amp, peaks


def test_features_recover_the_counts_width_ratio_and_falloff_of_a_known_input():
  x, amp, _ = synthetic_input()
  f = dict(zip(realism.FEATURES, realism.features(x, BIN_LENGTH)))
  assert f["log10_counts"] == pytest.approx(np.log10(x.sum(0).mean()))
  assert f["return_width"] == 3
  sbr = (3 * amp).sum() / (2.0 * 128 * amp.size)
  assert f["log10_sbr"] == pytest.approx(np.log10(sbr), abs=1e-9)
  # The smoothed peak sits in the box's middle bin: distances are (peak + 1 + 1/2) bins, not
  # the box's start, so the fitted slope is close to, not exactly, -3.
  assert f["falloff_slope"] == pytest.approx(-3.0, abs=0.3)
  early, late = x[:32].mean(), x[-32:].mean()
  assert f["signal_share"] == 1.0
  assert f["background_ratio"] == pytest.approx(np.log10((early + 1e-3) / (late + 1e-3)))
  assert f["shape_+0"] == pytest.approx(1.0) and f["shape_-3"] == 0.0


def test_a_gated_start_shows_in_the_background_ratio():
  x, _, _ = synthetic_input()
  x[:32] = 0.0                                   # the first quarter zeroed, as published preparations do
  f = dict(zip(realism.FEATURES, realism.features(x, BIN_LENGTH)))
  assert f["background_ratio"] == pytest.approx(np.log10(1e-3 / (2.0 + 1e-3)), abs=0.05)


def test_the_classifier_is_at_chance_on_one_distribution_and_right_on_two():
  rng = np.random.default_rng(0)
  meas = {s: rng.normal(size=(16, 5)) for s in "abcd"}
  sim = rng.normal(size=(64, 5))
  seq = np.repeat(np.arange(16), 4)
  assert realism.classify(meas, sim, seq)["accuracy"] == pytest.approx(0.5, abs=0.2)
  far = {s: v + 4.0 for s, v in meas.items()}
  result = realism.classify(far, sim, seq)
  assert result["accuracy"] > 0.95 and len(result["folds"]) == 4

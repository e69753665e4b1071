"""Bootstrap intervals over sequences and seeds: against a loop, the normal approximation,
and the invariants that would fail if frames were resampled one by one."""

import numpy as np
import pytest

from nlosjax import stats


def _loop_bootstrap(x, n_boot, rng):
  """Percentile interval of the pooled mean, resampling rows (sequences) of ``x [S, F]``."""
  s = x.shape[0]
  reps = []
  for _ in range(n_boot):
    rows = x[rng.integers(0, s, s)]
    rows = rows[~np.isnan(rows)]
    if rows.size:
      reps.append(rows.mean())
  return np.quantile(reps, [0.025, 0.975])


def test_interval_matches_a_plain_resampling_loop():
  rng = np.random.default_rng(1)
  x = rng.normal(0.0, 1.0, (12, 1)) + rng.normal(0.0, 0.3, (12, 6))   # 12 sequences x 6 frames
  x[3, 2] = np.nan
  got = stats.summarize(x, n_boot=4000, seed=3)
  want = _loop_bootstrap(x, 4000, np.random.default_rng(99))          # another random stream
  width = want[1] - want[0]
  np.testing.assert_allclose(got["ci95"], want, atol=0.08 * width)    # Monte-Carlo error only
  assert got["mean"] == pytest.approx(np.nanmean(x))
  assert got["n_frames"] == 71 and got["n_sequences"] == 12 and got["n_seeds"] == 1


def test_frames_of_a_sequence_are_resampled_together():
  # 400 sequences, each 16 identical frames: the information is 400 values, not 6400.
  rng = np.random.default_rng(0)
  per_sequence = rng.normal(0.0, 1.0, (400, 1))
  x = np.repeat(per_sequence, 16, axis=1)
  lo, hi = stats.summarize(x, n_boot=2000)["ci95"]
  sd = per_sequence.std()
  # Normal approximation over sequences: half-width 1.96 sd / sqrt(400).
  assert (hi - lo) / 2 == pytest.approx(1.96 * sd / np.sqrt(400), rel=0.15)
  # Had frames been resampled one by one, the interval would be sqrt(16) = 4x narrower.
  assert (hi - lo) / 2 > 3 * 1.96 * x.std() / np.sqrt(x.size)


def test_paired_difference_sees_what_overlapping_intervals_hide():
  rng = np.random.default_rng(2)
  base = rng.normal(20.0, 3.0, (8, 6))          # scenes differ a lot: wide single intervals
  better = base + 0.1                           # one method is 0.1 dB better on every frame
  a, b = stats.summarize(better), stats.summarize(base)
  assert a["ci95"][0] < b["ci95"][1]            # the intervals overlap...
  d = stats.paired_difference(better, base)
  assert d["ci95"] == pytest.approx([0.1, 0.1]) and d["mean"] == pytest.approx(0.1)
  assert stats.excludes_zero(d)                 # ...the paired difference does not
  assert not stats.excludes_zero(stats.paired_difference(base, base + rng.normal(0, 1, (8, 6))))


def test_seeds_widen_the_interval_and_broadcast_against_a_classic_method():
  rng = np.random.default_rng(4)
  scenes = rng.normal(0.0, 1.0, (10, 5))
  same = stats.summarize(np.stack([scenes] * 3))
  one = stats.summarize(scenes)
  assert same["ci95"] == pytest.approx(one["ci95"], abs=0.05) and same["n_seeds"] == 3
  spread = stats.summarize(np.stack([scenes - 2.0, scenes, scenes + 2.0]))   # seeds disagree
  assert spread["ci95"][1] - spread["ci95"][0] > 2 * (one["ci95"][1] - one["ci95"][0])
  d = stats.paired_difference(np.stack([scenes + 1.0] * 3), scenes)           # [3,S,F] - [S,F]
  assert d["ci95"] == pytest.approx([1.0, 1.0]) and d["n_seeds"] == 3


def test_undefined_frames_are_left_out_and_counted():
  x = np.array([[1.0, np.nan], [np.nan, np.nan], [3.0, 5.0]])
  s = stats.summarize(x)
  assert s["mean"] == pytest.approx(3.0) and s["n_frames"] == 3 and s["n_sequences"] == 2
  assert 1.0 <= s["ci95"][0] <= s["ci95"][1] <= 5.0
  empty = stats.summarize(np.full((2, 3), np.nan))
  assert np.isnan(empty["mean"]) and np.isnan(empty["ci95"]).all() and empty["n_frames"] == 0
  # The same seed gives the same interval: tables are reproducible.
  assert stats.summarize(x, seed=5) == stats.summarize(x, seed=5)


def test_bad_input_is_named():
  with pytest.raises(ValueError, match=r"\[S, F\] or \[K, S, F\]"):
    stats.summarize(np.zeros(5))
  with pytest.raises(ValueError, match="inf"):
    stats.summarize(np.array([[1.0, np.inf]]))
  with pytest.raises(ValueError, match="n_boot"):
    stats.summarize(np.zeros((2, 2)), n_boot=10)
  with pytest.raises(ValueError, match="same sequences"):
    stats.paired_difference(np.zeros((3, 2)), np.zeros((2, 2)))
  with pytest.raises(ValueError, match="same sequences"):
    stats.paired_difference(np.zeros((2, 3, 2)), np.zeros((3, 3, 2)))

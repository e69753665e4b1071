"""Per-bin Poisson moment checks against a rate written out here (not the library's rate function).

``stated_rate`` is ``eta * (clean (*) g + ambient) + dark`` with ``g`` convolved by
``np.convolve`` (zero padding, index ``K // 2`` zero delay, as documented for
``nlosjax.physics.expected_counts``). ``poisson_z`` returns z-scores of, per time bin
(summed over every other axis; bins grouped where the rate is low) and pooled, the mean ``sum (c - lam)`` (variance
``sum lam``) and the second factorial moment ``sum ((c - lam)^2 - c)`` (mean 0,
variance ``sum 2 lam^2`` for Poisson counts): a shifted or rescaled rate moves the
first, counts that are not Poisson (no noise, or too much) the second.
"""

import numpy as np


def stated_rate(clean, kernel, *, efficiency, ambient, dark_counts, axis=-3):
  """``[..., T, H, W]`` float64 ``efficiency * (clean (*) kernel + ambient) + dark_counts``."""
  clean = np.asarray(clean, np.float64)
  kernel = np.asarray(kernel, np.float64)
  mid, T = len(kernel) // 2, clean.shape[axis]
  blurred = np.apply_along_axis(lambda h: np.convolve(h, kernel)[mid:mid + T], axis, clean)
  return efficiency * (blurred + ambient) + dark_counts


def _groups(weight, least):
  """Consecutive runs of bins, each with ``weight`` summing to >= ``least`` (the last merged back)."""
  groups, start, acc = [], 0, 0.0
  for t, w in enumerate(weight):
    acc += w
    if acc >= least:
      groups.append((start, t + 1))
      start, acc = t + 1, 0.0
  if start < len(weight):
    groups[-1:] = [(groups[-1][0] if groups else 0, len(weight))]
  return groups


def poisson_z(counts, rate, axis=-3, *, least_mean=25.0, least_pairs=50.0) -> dict:
  """z-scores ``{"mean_bins", "var_bins"}`` (per group of bins) and ``{"mean", "var"}`` (pooled).

  Bins are grouped (consecutive) so that each group expects >= ``least_mean`` counts, and
  for the variance >= ``least_pairs`` pairs (``sum lam^2 / 2``; at low rates the second
  moment is a rare-pair count, far from normal): each bin alone where the rate is high.
  """
  c = np.moveaxis(np.asarray(counts, np.float64), axis, 0).reshape(np.shape(counts)[axis], -1)
  lam = np.moveaxis(np.asarray(rate, np.float64), axis, 0).reshape(c.shape)
  d = c - lam
  second = d * d - c
  first, first_var = d.sum(1), lam.sum(1)
  pair, pair_var = second.sum(1), 2 * (lam * lam).sum(1)

  def grouped(x, v, least):
    return np.array([x[a:b].sum() / np.sqrt(v[a:b].sum()) for a, b in _groups(v, least)])

  return {"mean_bins": grouped(first, first_var, least_mean),
          "var_bins": grouped(pair, pair_var, 4 * least_pairs),
          "mean": first.sum() / np.sqrt(first_var.sum()),
          "var": pair.sum() / np.sqrt(pair_var.sum())}


def assert_poisson(counts, rate, *, limit=5.0, axis=-3, label=""):
  """Every per-bin and pooled z-score of :func:`poisson_z` within ``limit``."""
  z = poisson_z(counts, rate, axis)
  worst = {k: float(np.max(np.abs(v))) for k, v in z.items()}
  assert max(worst.values()) < limit, (label, worst)
  return worst

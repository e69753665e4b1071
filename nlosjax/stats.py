"""Uncertainty of a table's means: bootstrap over sequences (and seeds), paired differences.

Frames of one sequence are strongly correlated (the same objects a few
milliseconds apart), so treating 48 frames of 8 sequences as 48 independent
samples gives intervals far too narrow. Here a bootstrap replicate resamples
whole *sequences* with replacement (a sequence's frames travel together) and,
when several training seeds are given, resamples the *seeds* too (crossed: a
replicate draws seeds and sequences independently), so the interval covers
both the test scenes and the training run.

Layout: scores are ``[K, S, F]``, K seeds (1 for a classic method), S
sequences, F frames per sequence. NaN marks a frame a score is undefined on
(e.g. ``recall`` of a frame with no object, :mod:`nlosjax.metrics`): it is left
out of every mean, and ``n_frames`` counts the frames that were not. A
statistic is the pooled mean over the frames a replicate holds,
``sum of scores / number of scores``, so sequences weigh by their frames.

The interval is the percentile bootstrap: the 2.5 and 97.5 % quantiles of
``n_boot`` replicate means. A paired difference (:func:`paired_difference`)
is the same bootstrap on per-frame differences ``a - b``: both methods see the
same resampled sequences (and seeds), which removes what the sequences share
(a hard scene is hard for both). Call a difference only when its interval
excludes 0 (:func:`excludes_zero`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["N_BOOT", "summarize", "paired_difference", "excludes_zero"]

N_BOOT = 2000
"""Bootstrap replicates by default (the 2.5 % quantile then rests on 50 replicates)."""


def _as_kfs(scores, name: str) -> np.ndarray:
  """``[S, F]`` or ``[K, S, F]`` array-like -> float64 ``[K, S, F]``."""
  x = np.asarray(scores, dtype=np.float64)
  if x.ndim == 2:
    x = x[None]
  if x.ndim != 3 or 0 in x.shape:
    raise ValueError(f"{name} must be [S, F] or [K, S, F] (seeds, sequences, frames) with no "
                     f"empty axis, got shape {np.shape(scores)}")
  if np.isinf(x).any():
    raise ValueError(f"{name} contains inf; mark undefined scores with NaN")
  return x


def _replicate_weights(rng, n: int, n_boot: int) -> np.ndarray:
  """``[n_boot, n]``: how many times each of n units is drawn in each replicate."""
  draws = rng.integers(0, n, size=(n_boot, n))
  weights = np.zeros((n_boot, n))
  np.add.at(weights, (np.arange(n_boot)[:, None], draws), 1.0)
  return weights


def summarize(scores, *, n_boot: int = N_BOOT, seed: int = 0, level: float = 0.95) -> dict:
  """Mean and bootstrap interval of per-frame scores, resampling sequences (and seeds).

  Args:
    scores: ``[S, F]`` (one seed) or ``[K, S, F]`` per-frame scores; NaN =
      undefined on that frame, left out.
    n_boot: bootstrap replicates, >= 100.
    seed: seed of the resampling (fixed: a table is reproducible).
    level: coverage of the interval, in (0, 1).

  Returns:
    ``{"mean", "ci95": [lo, hi], "std", "n_sequences", "n_frames", "n_seeds"}``:
    the pooled mean over defined frames, its percentile interval (named
    ``ci95`` whatever ``level`` is, for a fixed table layout: pass the default),
    the standard deviation over frames (spread, not uncertainty), the
    sequences with at least one defined frame, the defined frames, the seeds.
    With no defined frame every number is NaN and the counts are 0.

  Raises:
    ValueError: bad shape, inf, ``n_boot < 100``, ``level`` outside (0, 1).
  """
  x = _as_kfs(scores, "scores")
  if int(n_boot) < 100:
    raise ValueError(f"n_boot must be >= 100, got {n_boot}")
  if not 0.0 < level < 1.0:
    raise ValueError(f"level must be in (0, 1), got {level}")
  defined = ~np.isnan(x)
  counts = defined.sum(axis=2).astype(np.float64)          # [K, S]
  sums = np.where(defined, x, 0.0).sum(axis=2)             # [K, S]
  n_frames = int(counts.sum())
  out = {"n_sequences": int((counts.sum(axis=0) > 0).sum()), "n_frames": n_frames,
         "n_seeds": int(x.shape[0])}
  if n_frames == 0:
    nan = float("nan")
    return {"mean": nan, "ci95": [nan, nan], "std": nan, **out}
  rng = np.random.default_rng(seed)
  k, s = counts.shape
  w_seed = _replicate_weights(rng, k, n_boot) if k > 1 else np.ones((n_boot, 1))
  w_seq = _replicate_weights(rng, s, n_boot)
  num = np.einsum("bk,ks,bs->b", w_seed, sums, w_seq)
  den = np.einsum("bk,ks,bs->b", w_seed, counts, w_seq)
  # A replicate that drew only undefined sequences has no mean; it is left out.
  reps = num[den > 0] / den[den > 0]
  tail = (1.0 - level) / 2.0
  lo, hi = np.quantile(reps, [tail, 1.0 - tail])
  values = x[defined]
  return {"mean": float(values.mean()), "ci95": [float(lo), float(hi)],
          "std": float(values.std()), **out}


def paired_difference(a, b, **kwargs) -> dict:
  """:func:`summarize` of the per-frame difference ``a - b`` on the same frames.

  Args:
    a, b: per-frame scores, ``[S, F]`` or ``[K, S, F]``. A method without seeds
      (a classic one, ``[S, F]``) is broadcast against the other's seeds.
      A frame is left out where either is NaN.
    **kwargs: as :func:`summarize`.
  Returns:
    :func:`summarize`'s dict for ``a - b`` (positive mean: ``a`` scores higher).
  """
  xa, xb = _as_kfs(a, "a"), _as_kfs(b, "b")
  if xa.shape[1:] != xb.shape[1:] or (xa.shape[0] != xb.shape[0] and 1 not in (xa.shape[0],
                                                                              xb.shape[0])):
    raise ValueError(f"a {xa.shape} and b {xb.shape} must hold the same sequences and frames "
                     f"([K, S, F]; K equal, or 1 for a method without seeds)")
  return summarize(xa - xb, **kwargs)


def excludes_zero(summary: dict) -> bool:
  """Whether a summary's interval lies wholly above or wholly below 0 (a difference to call)."""
  lo, hi = summary["ci95"]
  return bool(lo > 0 or hi < 0)


def format_interval(summary: dict | None, digits: int = 2, signed: bool = False, missing: str = "—") -> str:
  """``"mean [lo, hi]"`` of a :func:`summarize` result, ``digits`` decimals (``signed``: with "+").

  ``missing`` when there is no summary (``None``, or a mean that is ``None`` or not finite).
  """
  mean = None if summary is None else summary.get("mean")
  if mean is None or not np.isfinite(mean):
    return missing
  f = f"{{:{'+' if signed else ''}.{digits}f}}"
  lo, hi = summary["ci95"]
  return f"{f.format(mean)} [{f.format(lo)}, {f.format(hi)}]"

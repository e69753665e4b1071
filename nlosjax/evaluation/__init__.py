"""Evaluation: classic baselines, per-frame scores, intervals, tables and figures.

One concern per module:

* :mod:`~nlosjax.evaluation.baselines` -- classic methods on under-scanned
  input, their settings tuned on the validation split;
* :mod:`~nlosjax.evaluation.scores` -- every metric per frame, grouped by
  sequence, summarised with bootstrap intervals (:mod:`nlosjax.stats`);
* :mod:`~nlosjax.evaluation.protocol` -- every method on one split, the
  table and the paired comparisons, the results folder;
* :mod:`~nlosjax.evaluation.report` -- the Markdown;
* :mod:`~nlosjax.evaluation.figures` -- the PNGs.
"""

"""experiments.studies.surface_cut: the per-threshold scores against a count by hand, and the verdicts."""

import numpy as np
import pytest

from experiments.studies import surface_cut as S


def test_frame_scores_count_surface_pixels_by_hand():
  """One 1 x 4 frame: truth surface at pixels 0-1; the reconstruction's intensities 1, 0.3, 0.3, 0.1
  at depth 1 m. At 0.2 it claims pixels 0-2: recall 2/2, precision 2/3; at 0.5 pixel 0 only."""
  gt = np.array([[[1.0, 1.0, 0.0, 0.0]]], np.float32)
  intensity = np.array([[[1.0, 0.3, 0.3, 0.1]]], np.float32)
  depth = np.ones_like(intensity)
  s = S.frame_scores(intensity, depth, gt, thresholds=(0.2, 0.5))
  assert s[0.2]["recall"][0] == pytest.approx(1.0) and s[0.2]["precision"][0] == pytest.approx(2 / 3)
  assert s[0.2]["f1"][0] == pytest.approx(0.8)
  assert s[0.5]["recall"][0] == pytest.approx(0.5) and s[0.5]["precision"][0] == pytest.approx(1.0)


def test_operating_point_takes_the_best_f1_among_thresholds_reaching_the_recall():
  curve = {0.1: {"recall": 0.95, "f1": 0.5}, 0.2: {"recall": 0.85, "f1": 0.6}, 0.3: {"recall": 0.7, "f1": 0.7}}
  assert S.operating_point(curve, 0.8) == 0.2
  assert S.operating_point(curve, 0.9) == 0.1
  assert S.operating_point(curve, 0.99) is None


def _per_frame(recall, precision):
  f1 = 2 * recall * precision / (recall + precision)
  return {"recall": np.asarray(recall, float), "precision": np.asarray(precision, float), "f1": f1}


def test_compare_finds_the_high_recall_and_best_f1_classic_and_pairs_the_network_with_them():
  """Two sequences of two frames. Classic "lct" has the highest recall at its chosen 0.3, "rsd" the
  highest F1; the network reaches lct's recall at 0.1 only, where its F1 is below rsd's."""
  seq = np.array([0, 0, 1, 1])
  ones = np.ones(4)
  per_frame = {
      "lct": {0.1: _per_frame(ones * 0.99, ones * 0.2), 0.3: _per_frame(ones * 0.9, ones * 0.5)},
      "rsd": {0.1: _per_frame(ones * 0.98, ones * 0.25), 0.3: _per_frame(ones * 0.8, ones * 0.7)},
      "ours": {0.1: _per_frame(ones * 0.92, ones * 0.45), 0.3: _per_frame(ones * 0.7, ones * 0.8)}}
  v = S.compare(per_frame, {"lct": 0.3, "rsd": 0.3}, seq, ("ours",))
  assert v["high_recall"] == "lct" and v["target_recall"] == pytest.approx(0.9)
  assert v["best_f1"] == "rsd"
  r = v["networks"]["ours"]
  assert r["threshold"] == 0.1 and r["recall"] == pytest.approx(0.92)
  f1_ours, f1_rsd = 2 * 0.92 * 0.45 / 1.37, 2 * 0.8 * 0.7 / 1.5
  assert r["f1_minus_best"]["mean"] == pytest.approx(f1_ours - f1_rsd)
  assert r["f1_minus_best"]["ci95"][1] < 0                  # the same on every frame: no spread
  assert r["precision_minus_high_recall"]["mean"] == pytest.approx(0.45 - 0.5)
  text = S.report(per_frame | {}, {"lct": 0.3, "rsd": 0.3}, v, {"lct": {}, "rsd": {}}, "cmd", "d.h5")
  assert "**The cut is not a lever for recall:**" in text
  # A network as precise as rsd at lct's recall is a lever.
  per_frame["ours"][0.1] = _per_frame(ones * 0.95, ones * 0.9)
  v = S.compare(per_frame, {"lct": 0.3, "rsd": 0.3}, seq, ("ours",))
  assert "**The cut is a lever:** Ours" in S.report(per_frame, {"lct": 0.3, "rsd": 0.3}, v,
                                                     {"lct": {}, "rsd": {}}, "cmd", "d.h5")

"""experiments.studies.generalisation: the brightness and extent ratios, against frames worked by hand."""

import numpy as np

from experiments.studies import generalisation as G


def test_ratios_of_a_hand_worked_frame():
  # Truth: a 2 x 2 object (4 pixels) of intensity 0.5 at 1 m in a 4 x 4 frame; total 2.0.
  gt_i = np.zeros((1, 4, 4))
  gt_d = np.zeros((1, 4, 4))
  gt_i[0, :2, :2] = 0.5
  gt_d[0, :2, :2] = 1.0
  # Reconstruction: intensity 0.25 on the object (sum 1.0) plus light outside it, which
  # brightness ignores; a surface on 6 pixels (3 on the object, 3 beside it).
  inten = np.full((1, 4, 4), 0.9)
  inten[0, :2, :2] = 0.25
  depth = np.zeros((1, 4, 4))
  depth[0, 0, :3] = 1.0
  depth[0, 1, 0] = 1.0
  depth[0, 3, 2:] = 1.0
  r = G.object_ratios(inten, depth, gt_i, gt_d)
  np.testing.assert_allclose(r["brightness"], [1.0 / 2.0])
  np.testing.assert_allclose(r["extent"], [6 / 4])


def test_ratios_are_nan_without_an_object_and_one_for_the_truth():
  rng = np.random.default_rng(0)
  gt_i = rng.uniform(0.1, 1.0, (3, 8, 8))
  gt_d = np.where(rng.uniform(size=(3, 8, 8)) < 0.3, 1.5, 0.0)
  gt_d[2] = 0.0                                   # frame 2: no object
  r = G.object_ratios(gt_i, gt_d, gt_i, gt_d)
  np.testing.assert_allclose(r["brightness"][:2], 1.0)
  np.testing.assert_allclose(r["extent"][:2], 1.0)
  assert np.isnan(r["brightness"][2]) and np.isnan(r["extent"][2])

"""nlosjax.evaluation: sequence grouping, classic tuning on validation, paired comparisons, reports."""

import numpy as np
import pytest

from nlosjax.evaluation import baselines, protocol, report, scores
from tests.small_capture import three_patch_capture


def test_by_sequence_groups_frames_and_pads_short_sequences():
  values = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
  seq = np.array([7, 3, 7, 3, 3])                 # any order, any ids
  out = scores.by_sequence(values, seq)
  np.testing.assert_array_equal(out[0], [[2.0, 4.0, 5.0], [1.0, 3.0, np.nan]])
  two = scores.by_sequence(np.stack([values, 10 * values]), seq)
  assert two.shape == (2, 2, 3) and two[1, 0, 2] == 50.0
  with pytest.raises(ValueError, match="one sequence index per frame"):
    scores.by_sequence(values, seq[:4])


def test_frame_scores_match_the_metrics_by_hand():
  gt_i = np.zeros((1, 12, 12), np.float32)
  gt_i[0, 4:6, 4:6] = 1.0                         # a 2 x 2 object
  gt_d = np.where(gt_i > 0, 1.0, 0.0).astype(np.float32)
  depth = gt_d.copy()
  depth[0, 4, 4] = 0.0                            # one object pixel missed
  depth[0, 0, 0] = 2.0                            # one background pixel called surface
  s = scores.frame_scores(gt_i, depth, gt_i, gt_d)
  assert set(s) == set(scores.METRICS)
  assert s["psnr"][0] == pytest.approx(100.0)     # identical intensity: the PSNR cap
  assert s["recall"][0] == pytest.approx(3 / 4) and s["precision"][0] == pytest.approx(3 / 4)
  assert s["f1"][0] == pytest.approx(3 / 4)
  assert s["rmse_object"][0] == pytest.approx(np.sqrt(1 / 4))
  assert s["mad_object"][0] == pytest.approx(1 / 4)
  assert s["rmse"][0] == pytest.approx(np.sqrt(5 / 144))


@pytest.fixture(scope="module")
def small_capture():
  setup, full, albedo = three_patch_capture()
  gt_i = albedo.max(axis=1)
  gt_d = np.where(gt_i > 0, np.asarray(setup.depths)[albedo.argmax(axis=1)], 0.0).astype(np.float32)
  return setup, full[..., 1::3, 1::3], gt_i, gt_d


def test_tune_picks_the_best_option_then_the_best_threshold(small_capture):
  """The choice equals a brute-force search over the same grid with classic_images."""
  from nlosjax import metrics
  setup, x, gt_i, gt_d = small_capture
  got = baselines.tune(x, gt_i, gt_d, setup, 3, methods=("lct", "fbp"), log=lambda s: None)
  for method in ("lct", "fbp"):
    grid = baselines.option_grid(method, setup)
    psnr = [float(np.mean(metrics.psnr(baselines.classic_images(x, setup, 3, method, o)[0], gt_i)))
            for o in grid]
    best = grid[int(np.argmax(psnr))]
    assert got[method]["options"] == best
    assert got[method]["psnr"] == pytest.approx(max(psnr), abs=1e-4)
    f1 = {t: float(np.nanmean(metrics.surface_scores(
        baselines.classic_images(x, setup, 3, method, best, threshold=t)[1], gt_d)["f1"]))
          for t in baselines.THRESHOLDS}
    assert f1[got[method]["threshold"]] == pytest.approx(max(f1.values()), abs=1e-6)
    assert len(got[method]["grid"]) == len(grid)
  with pytest.raises(ValueError, match="classic method"):
    baselines.option_grid("lct2", setup)


def _summary(mean, lo, hi):
  return {"mean": mean, "ci95": [lo, hi], "std": 1.0, "n_sequences": 8, "n_frames": 48, "n_seeds": 3}


def test_report_calls_a_difference_only_when_its_interval_excludes_zero():
  metrics_ = ("psnr", "ssim", "rmse_object", "recall", "f1")
  better = {k: _summary(0.5, 0.1, 0.9) for k in metrics_}
  unclear = {k: _summary(0.5, -0.1, 1.1) for k in metrics_}
  worse = {**better, "rmse_object": _summary(0.2, 0.05, 0.4)}     # larger depth error is worse
  text = report.format_comparisons([
      {"a": "ours", "b": "ours_s", "label": "Ours - Ours-S", "diff": unclear},
      {"a": "ours", "b": "fbp", "label": "Ours - FBP", "diff": worse}])
  assert "Ours - Ours-S, intensity PSNR: +0.50 dB [-0.10, +1.10]; the interval includes 0" in text
  assert "Ours - FBP, intensity PSNR: +0.50 dB [+0.10, +0.90]; Ours is better than FBP." in text
  assert "Ours - FBP, object depth RMSE: +0.200 m [+0.050, +0.400]; Ours is worse than FBP." in text
  table = report.format_tables({"fbp": {k: _summary(1.0, 0.5, 1.5) for k in scores.METRICS}})
  assert "| FBP | 1.00 [0.50, 1.50] |" in table and "8 / 48 / 3" in table


def test_tabulate_pairs_ours_with_ours_s_and_the_best_classic():
  rng = np.random.default_rng(1)
  seq = np.repeat(np.arange(6), 4)
  base = {k: rng.normal(size=24) for k in scores.METRICS}
  ev = {"scores": {"fbp": base, "lct": {k: v - 1 for k, v in base.items()},
                   "ours_s": {k: np.stack([v + 0.5, v + 0.6]) for k, v in base.items()},
                   "ours": {k: np.stack([v + 1.0, v + 1.1]) for k, v in base.items()}},
        "sequence": seq}
  assert protocol.best_classic(ev) == "fbp"
  assert protocol.best_classic(ev, "rmse") == "lct"            # lower is better
  table, comparisons = protocol.tabulate(ev, best_classic_method="fbp", n_boot=200)
  assert [c["label"] for c in comparisons] == ["Ours - Ours-S", "Ours - FBP", "Ours-S - FBP"]
  assert comparisons[1]["diff"]["psnr"]["mean"] == pytest.approx(1.05)
  assert comparisons[0]["diff"]["psnr"]["ci95"] == pytest.approx([0.5, 0.5])  # a constant shift
  assert table["ours"]["psnr"]["n_seeds"] == 2 and table["fbp"]["psnr"]["n_sequences"] == 6


def test_surface_cut_matches_a_loop_and_zero_keeps_the_model_depth():
  rng = np.random.default_rng(4)
  inten = rng.uniform(0, 1, (2, 5, 6)).astype(np.float32)
  depth = rng.uniform(0.5, 1.5, (2, 5, 6)).astype(np.float32)
  want = depth.copy()
  for idx in np.ndindex(*depth.shape):
    if inten[idx] < 0.3:
      want[idx] = 0.0
  np.testing.assert_array_equal(protocol.surface_cut(inten, depth, 0.3), want)
  np.testing.assert_array_equal(protocol.surface_cut(inten, depth, 0.0), depth)


def test_learned_surface_threshold_is_chosen_by_validation_f1():
  """One object of 4 pixels at intensity 0.8 and a halo of 12 false-surface pixels at 0.25:
  cutting at 0.3 or 0.5 removes the halo and gives F1 = 1, the lower cuts keep it (F1 = 0.4);
  0.3 comes first among the ties. Two seeds are averaged."""
  gt = np.zeros((1, 8, 8), np.float32)
  gt[0, 2:4, 2:4] = 1.0
  inten = np.zeros((1, 8, 8), np.float32)
  inten[0, 1:5, 1:5] = 0.25
  inten[0, 2:4, 2:4] = 0.8
  depth = np.where(inten > 0, 1.0, 0.0).astype(np.float32)
  ims = [{"intensity": inten, "depth": depth}] * 2
  got = protocol.choose_surface_threshold(ims, gt)
  assert got["threshold"] == 0.3 and got["f1"] == pytest.approx(1.0)
  assert got["f1_by_threshold"]["0.0"] == pytest.approx(2 * 4 / (2 * 4 + 12))
  assert got["f1_by_threshold"]["0.5"] == pytest.approx(1.0)

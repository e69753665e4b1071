"""nlosjax.evaluation: sequence grouping, classic tuning on validation, paired comparisons, reports."""

import numpy as np
import pytest

from nlosjax.evaluation import baselines, protocol, report, scores
from nlosjax.train import RunConfig
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


@pytest.mark.full
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
  # The object table first, the object intensity error first in it, each PSNR beside its floor.
  objects = ("| method | object intensity error ↓ | object-balanced PSNR (dB) ↑ | all-zero image's balanced "
             "PSNR (dB) ↑ | object depth RMSE (m) ↓ |")
  paper = "| method | intensity PSNR (dB) ↑ | all-zero image's PSNR (dB) ↑ | intensity SSIM ↑ |"
  assert objects in table and paper in table and table.index(objects) < table.index(paper)
  # A table written before those metrics existed renders them as n/a.
  old = report.format_tables({"fbp": {k: _summary(1.0, 0.5, 1.5) for k in scores.METRICS
                                      if k not in ("psnr_zero", "intensity_mae_object")}})
  assert "| FBP | 1.00 [0.50, 1.50] | n/a | 1.000 [0.500, 1.500] |" in old


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


def test_consecutive_pairs_stay_within_a_sequence():
  seq = np.array([4, 4, 4, 9, 9, 4])
  frame = np.array([2, 1, 3, 1, 2, 5])                # any order; frame 4 of sequence 4 is missing
  prev, cur = scores.consecutive_pairs(seq, frame)
  assert list(zip(prev, cur)) == [(1, 0), (0, 2), (3, 4)]     # (1, 2), (2, 3) of 4; (1, 2) of 9
  # Without frame indices: consecutive in the order they appear, sequence by sequence.
  prev, cur = scores.consecutive_pairs(np.array([4, 4, 9, 4, 9]))
  assert list(zip(prev, cur)) == [(0, 1), (1, 3), (2, 4)]
  with pytest.raises(ValueError, match="appears twice"):
    scores.consecutive_pairs(seq, np.array([1, 1, 2, 1, 2, 3]))
  with pytest.raises(ValueError, match="one frame index per frame"):
    scores.consecutive_pairs(seq, frame[:5])


def _direct_temporal_rmse(inten, gt, seq, frame) -> list[float]:
  """Per pair, by sequence: RMSE of the change against the true change, straight from the arrays."""
  out = []
  for s in np.unique(seq):
    rows = {int(f): n for n, f in enumerate(frame) if seq[n] == s}
    for f in sorted(rows):
      if f - 1 in rows:
        a, b = rows[f - 1], rows[f]
        out.append(np.sqrt(np.mean(((inten[b] - inten[a]) - (gt[b] - gt[a])) ** 2)))
  return out


def test_tabulated_temporal_score_equals_a_direct_computation_and_never_crosses_sequences():
  """Two sequences in file order (3 and 2 middle frames), the second's first frame right after the
  first's last: a pair across them would see a jump of 1 in the truth that no method follows."""
  rng = np.random.default_rng(37)
  seq = np.array([0, 0, 0, 1, 1])
  frame = np.array([1, 2, 3, 1, 2])
  gt_i = np.zeros((5, 12, 12), np.float32)               # 12 x 12: SSIM's smallest is 11 x 11
  gt_i[3:] = 1.0                                          # the jump between the two sequences
  gt_i[:, 3:9, 3:9] += rng.uniform(0, 0.5, (5, 6, 6)).astype(np.float32)
  gt_i = np.clip(gt_i, 0, 1)
  gt_d = np.where(gt_i > 0.1, 1.0 + gt_i, 0.0).astype(np.float32)
  ev_scores, images = {}, {}
  for method, noise in (("fbp", 0.2), ("ours_s", 0.1), ("ours", 0.05)):
    seeds = 1 if method == "fbp" else 2
    images[method] = [(np.clip(gt_i + rng.normal(0, noise, gt_i.shape), 0, 1).astype(np.float32),
                       gt_d + rng.normal(0, noise, gt_d.shape).astype(np.float32))
                      for _ in range(seeds)]
    per_seed = [scores.frame_scores(i, d, gt_i, gt_d, sequence=seq, frame=frame)
                for i, d in images[method]]
    assert set(per_seed[0]) == set(scores.TABLE_METRICS)
    ev_scores[method] = (per_seed[0] if method == "fbp" else
                         {k: np.stack([s[k] for s in per_seed]) for k in scores.TABLE_METRICS})
  # A sequence's first evaluated frame has no pair: NaN there, the pair's score at its later frame.
  t = ev_scores["fbp"]["temporal_rmse"]
  assert np.isnan(t[[0, 3]]).all() and np.isfinite(t[[1, 2, 4]]).all()
  table, comparisons = protocol.tabulate({"scores": ev_scores, "sequence": seq}, n_boot=200)
  for method, ims in images.items():
    direct = [v for i, _ in ims for v in _direct_temporal_rmse(i, gt_i, seq, frame)]
    cell = table[method]["temporal_rmse"]
    assert len(direct) == 3 * len(ims)                 # 2 + 1 pairs per seed, none across sequences
    assert cell["mean"] == pytest.approx(np.mean(direct), rel=1e-5)
    assert (cell["n_frames"], cell["n_sequences"], cell["n_seeds"]) == (3 * len(ims), 2, len(ims))
    assert all(v < 0.5 for v in direct)                # a pair across the jump would score ~1
    psnr = table[method]["temporal_psnr"]["mean"]
    assert psnr == pytest.approx(np.mean([10 * np.log10(1 / v ** 2) for v in direct]), rel=1e-5)
  # The paired difference Ours - Ours-S, seed by seed on the same pairs.
  ours_vs_s = next(c for c in comparisons if (c["a"], c["b"]) == ("ours", "ours_s"))
  want = np.mean([a - b for (ia, _), (ib, _) in zip(images["ours"], images["ours_s"])
                  for a, b in zip(_direct_temporal_rmse(ia, gt_i, seq, frame),
                                  _direct_temporal_rmse(ib, gt_i, seq, frame))])
  assert ours_vs_s["diff"]["temporal_rmse"]["mean"] == pytest.approx(want, rel=1e-5)
  assert ours_vs_s["diff"]["temporal_rmse"]["n_frames"] == 6
  # The Markdown: a temporal table with its own counts, and the temporal column and sentence in the
  # paired differences; a table without the temporal scores renders as before.
  text = report.format_tables(table) + report.format_comparisons(comparisons)
  assert "| temporal intensity error ↓ | temporal intensity PSNR (dB) ↑ |" in text
  assert "temporal depth error (objects) (m) ↓ | sequences / frame pairs / seeds |" in text
  assert "| Ours | " in text and "| 2 / 6 / 2 |" in text and "| 2 / 3 / 1 |" in text
  assert "Ours - Ours-S, temporal intensity error: " in text
  old = {m: {k: r[k] for k in scores.METRICS} for m, r in table.items()}
  assert "Over time" not in report.format_tables(old)
  old_c = [{**c, "diff": {k: c["diff"][k] for k in scores.METRICS}} for c in comparisons]
  assert "temporal" not in report.format_comparisons(old_c)


@pytest.mark.full
def test_evaluate_pairs_the_consecutive_middle_frames_of_each_test_sequence(tmp_path):
  """The protocol end to end on a tiny file of 2 test sequences of 4 frames (one classic method): the
  middle frames 1 and 2 of each sequence come in file order with their frame index, and each
  temporal score is that of the previous middle frame of its own sequence."""
  from nlosjax import metrics, train
  from tests.tiny_run import tiny_config
  path = tmp_path / "tiny.h5"
  cfg = tiny_config(path, eval_batch_size=4)
  cfg["data"]["num_sequences"] = {"train": 1, "val": 1, "test": 2}
  train.ensure_dataset(RunConfig.from_dict(cfg), path, log=lambda s: None)
  ev = protocol.evaluate(RunConfig.from_dict(cfg), path, {}, split="test", methods=("lct",), log=lambda s: None)
  np.testing.assert_array_equal(ev["sequence"], [0, 0, 1, 1])
  np.testing.assert_array_equal(ev["frame"], [1, 2, 1, 2])       # loader ends="valid": 1 .. F - 2
  got, im, gt = ev["scores"]["lct"], ev["images"]["lct"], ev["images"]["gt"]
  assert set(got) == set(scores.TABLE_METRICS)
  for k in scores.TEMPORAL_METRICS:
    assert np.isnan(got[k][[0, 2]]).all(), k                     # a sequence's first middle frame
  for cur in (1, 3):
    pair = slice(cur - 1, cur + 1)
    want = {"temporal_rmse": metrics.temporal_rmse(im["intensity"][pair], gt["intensity"][pair]),
            "temporal_psnr": metrics.temporal_psnr(im["intensity"][pair], gt["intensity"][pair]),
            "temporal_rmse_object": metrics.temporal_rmse_object(im["depth"][pair], gt["depth"][pair])}
    for k, v in want.items():
      assert got[k][cur] == pytest.approx(float(v[0]), rel=1e-6, nan_ok=True), (k, cur)
  assert np.isfinite(got["temporal_rmse"][[1, 3]]).all()


def test_spread_frames_spans_the_split():
  from nlosjax.evaluation.baselines import spread_frames
  np.testing.assert_array_equal(spread_frames(5, 16), np.arange(5))
  np.testing.assert_array_equal(spread_frames(9, 3), [0, 4, 8])
  with pytest.raises(ValueError, match="n >= 1"):
    spread_frames(0, 3)


@pytest.mark.full
def test_tune_csa_keeps_the_option_whose_masked_csa_scores_best():
  """Its choice against CSA run by hand on the masked full grid and scored with the metrics."""
  from nlosjax import metrics
  from nlosjax.evaluation.baselines import tune_csa
  from nlosjax.physics import intensity_depth
  from nlosjax.physics.methods import csa
  from tests.small_capture import three_patch_capture
  setup, full, albedo = three_patch_capture()
  mask = csa.interval_mask(*setup.grid, 3)
  grid = ({"tau_rel": 0.05, "falloff": "diffuse"}, {"tau_rel": 0.9, "falloff": "diffuse"})
  gt_i, gt_d = (np.asarray(a) for a in intensity_depth(albedo, setup))
  out = tune_csa(full[..., 1::3, 1::3], gt_i, gt_d, setup, 3, grid=grid, thresholds=(0.1, 0.3), log=lambda _: None)
  psnr = [float(np.mean(np.asarray(metrics.psnr(np.asarray(intensity_depth(
      csa.csa(full * mask, setup, mask=mask, **g), setup)[0]), gt_i)))) for g in grid]
  assert out["options"] == grid[int(np.argmax(psnr))]
  np.testing.assert_allclose([r["psnr"] for r in out["grid"]], psnr, rtol=1e-4)
  assert out["threshold"] in (0.1, 0.3)

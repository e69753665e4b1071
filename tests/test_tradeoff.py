"""Tests of the speed-accuracy benchmark's own logic (``experiments/studies/tradeoff/``).

The Pareto front against a brute-force O(n^2) dominance check, the
recommendations, the frame windows, the re-noising at another exposure
against the dataset's own rate, the accuracy-inside-a-range arithmetic, the
LCT stage split against ``nlosjax.physics.lct``, and an end-to-end smoke of
one classic configuration (timed, scored, written as Markdown and a plot).
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from experiments.studies import tradeoff
from nlosjax.physics import Setup, jitter_kernel
from tests.poisson_checks import assert_poisson, stated_rate


def brute_force_front(t, s):
  """``[n]`` bool: no other point is <= in time, >= in score and strictly better in one."""
  n = len(t)
  out = np.zeros(n, bool)
  for i in range(n):
    if not (np.isfinite(t[i]) and np.isfinite(s[i])):
      continue
    out[i] = not any(
        np.isfinite(t[j]) and np.isfinite(s[j]) and t[j] <= t[i] and s[j] >= s[i]
        and (t[j] < t[i] or s[j] > s[i]) for j in range(n) if j != i)
  return out


@pytest.mark.parametrize("seed", range(6))
def test_pareto_front_matches_brute_force(seed):
  rng = np.random.default_rng(seed)
  n = 40
  t = rng.integers(1, 8, n).astype(float)          # few values: many ties in time and score
  s = rng.integers(0, 6, n).astype(float)
  t[:3] = t[3]                                     # exact duplicates
  s[:3] = s[3]
  t[5] = np.nan
  s[6] = np.inf
  np.testing.assert_array_equal(tradeoff.pareto_front(t, s), brute_force_front(t, s))


def test_pareto_front_continuous_and_errors():
  rng = np.random.default_rng(7)
  t, s = rng.lognormal(size=200), rng.normal(size=200)
  front = tradeoff.pareto_front(t, s)
  np.testing.assert_array_equal(front, brute_force_front(t, s))
  # On the front, score strictly increases with time.
  order = np.argsort(t[front])
  assert np.all(np.diff(s[front][order]) > 0)
  with pytest.raises(ValueError, match="1-D of one length"):
    tradeoff.pareto_front([1.0, 2.0], [1.0])


def test_recommend_and_learned_beats_classic():
  pts = [
      {"name": "fbp", "time": 0.010, "psnr": 17.0, "kind": "classic"},
      {"name": "lct", "time": 0.012, "psnr": 16.5, "kind": "classic"},      # dominated
      {"name": "rsd", "time": 0.300, "psnr": 19.0, "kind": "classic"},
      {"name": "small", "time": 0.050, "psnr": 20.0, "kind": "learned"},
      {"name": "big", "time": 0.200, "psnr": 20.6, "kind": "learned"},
      {"name": "slow", "time": 0.400, "psnr": 20.5, "kind": "learned"},     # dominated
  ]
  assert tradeoff.recommend(pts) == {"fastest": "fbp", "balanced": "small", "best": "big"}
  assert tradeoff.recommend(pts, tolerance_db=0.1)["balanced"] == "big"
  # "small": faster than rsd (the only classic point nearly as accurate) and more accurate
  # than every faster classic point; "big" likewise.
  assert tradeoff.learned_beats_classic(pts) == ["small", "big"]
  # A classic point faster and better than "small" takes it off the front and the list.
  pts.append({"name": "magic", "time": 0.040, "psnr": 20.1, "kind": "classic"})
  assert tradeoff.learned_beats_classic(pts) == ["big"]


def _tiny_split(F=4, T=32, H=8, seed=0):
  rng = np.random.default_rng(seed)
  setup = Setup(wall_size=1.0, grid=(H, H), bin_width=64e-12, num_bins=T)
  clean = [rng.gamma(2.0, 3.0, (F, T, H, H)).astype(np.float32) for _ in range(2)]
  meas = [np.arange(F * T * H * H, dtype=np.float32).reshape(F, T, H, H) + 1000 * i
          for i in range(2)]
  attrs = [{"efficiency": 0.2, "ambient": 0.5, "dark_counts": 0.01},
           {"efficiency": 0.05, "ambient": 2.0, "dark_counts": 0.02}]
  maps = [np.zeros((F, H, H), np.float32) for _ in range(2)]
  ex = np.asarray([(s, m) for s in range(2) for m in range(1, F - 1)])
  return tradeoff.TestSplit(setup, meas, clean, maps, maps, attrs, ex)


def test_windows_slice_the_model_scan_points():
  split = _tiny_split()
  x = split.windows(4, 3)
  assert x.shape == (4, 3, 32, 2, 2)
  s, m = split.examples[1]
  np.testing.assert_array_equal(x[1], split.measurement[s][m - 1:m + 2][..., 2::4, 2::4])
  x5 = split.windows(2, 5)
  np.testing.assert_array_equal(x5[0, :2], split.measurement[0][[0, 0]][..., 1::2, 1::2])


def test_renoised_counts_follow_the_scaled_rate():
  from nlosjax.data.dataset import measurement_rate
  split = _tiny_split(F=4, T=32, H=4)
  for e in (0.3, 3.0):
    counts = split.renoised(e, seed=3)
    for s in range(2):
      a = split.attrs[s]
      lam = measurement_rate(split.clean[s] * e, split.setup, efficiency=a["efficiency"],
                             ambient=a["ambient"] * e, dark_counts=a["dark_counts"] * e,
                             jitter="measured")
      c = counts[s]
      assert c.shape == lam.shape and np.all(c >= 0) and np.all(c == np.round(c))
      # Poisson: the total is within 5 standard deviations of the total rate.
      assert abs(c.sum() - lam.sum()) < 5 * np.sqrt(lam.sum())
      # Per bin, against the rate written out in tests/poisson_checks.py (mean and variance).
      rate = stated_rate(split.clean[s] * e, jitter_kernel(split.setup, "measured"),
                         efficiency=a["efficiency"], ambient=a["ambient"] * e,
                         dark_counts=a["dark_counts"] * e)
      assert_poisson(c, rate, label=(e, s))
  np.testing.assert_array_equal(split.renoised(0.3, seed=3)[0], split.renoised(0.3, seed=3)[0])
  assert not np.array_equal(split.renoised(0.3, seed=3)[0], split.renoised(0.3, seed=4)[0])


def test_in_range_accuracy_arithmetic():
  setup = Setup(wall_size=1.0, grid=(4, 4), bin_width=132e-12, num_bins=128)   # 2.53 m
  gated_setup = setup.with_depth_range(0.5, 1.5)
  gt_d = np.zeros((2, 4, 4), np.float32)
  gt_d[:, :2] = 1.0                           # 16 pixels in range
  gt_d[:, 2, :] = 2.0                         # out of range; the rest background
  ungated = {"depth": gt_d + 0.1}
  gated = {"depth": gt_d - 0.3}
  gated["depth"][:, 3] = 7.0                  # background pixels: ignored
  gated["depth"][1, 2, :] = 0.05              # out of range, near 0: ignored too
  acc = tradeoff.in_range_accuracy(gated, ungated, gt_d, gated_setup)
  assert acc["pixels"] == 16
  assert acc["rmse_ungated"] == pytest.approx(0.1, rel=1e-5)
  assert acc["rmse_gated"] == pytest.approx(0.3, rel=1e-5)
  assert acc["mad_gated"] == pytest.approx(0.3, rel=1e-5)
  assert acc["agreement"] == pytest.approx(0.4, rel=1e-5)
  assert acc["missed_gated"] == 0.0 and acc["missed_ungated"] == 0.0
  ungated["depth"][0, 0, :2] = 0.0            # 4 of the 16 in-range pixels called background
  ungated["depth"][0, 0, 2:] = 0.05           # (depth below near = 0.1 m)
  acc = tradeoff.in_range_accuracy(gated, ungated, gt_d, gated_setup)
  assert acc["missed_ungated"] == pytest.approx(0.25)
  assert acc["rmse_ungated"] == pytest.approx(
      np.sqrt((12 * 0.01 + 2 * 1.0 + 2 * 0.95 ** 2) / 16), rel=1e-5)
  assert acc["agreement"] == pytest.approx((12 * 0.4 + 2 * 0.7 + 2 * 0.65) / 16, rel=1e-5)
  assert tradeoff.in_range_accuracy(ungated, ungated, gt_d, setup)["pixels"] == 24
  empty = tradeoff.in_range_accuracy(gated, ungated, gt_d, setup.with_depth_range(2.2, 2.4))
  assert empty["pixels"] == 0 and np.isnan(empty["rmse_gated"])


def test_depth_ranges_halve():
  r = {label: (rng, ap) for label, rng, ap in tradeoff.depth_ranges((0.5, 1.5), 2.5, 0.7)}
  assert r["full"] == (None, None) and r["full/2"] == ((0.0, 1.25), None)
  assert r["R"] == ((0.5, 1.5), None) and r["R|a"] == ((0.5, 1.5), 0.7)
  assert r["R/2"][0] == pytest.approx((0.75, 1.25)) and r["R/4"][0] == pytest.approx((0.875, 1.125))
  assert r["R/2|a"][0] == pytest.approx((0.75, 1.25)) and r["R/2|a"][1] == 0.7
  assert "R|a" not in {label for label, _, _ in tradeoff.depth_ranges((0.5, 1.5), 2.5)}
  s = tradeoff.gated_setup(Setup(2.0, (8, 8), 64e-12, 64), (0.5, 1.0), 0.7)
  assert s.depth_range == (0.5, 1.0) and s.aperture == 0.7


def test_lct_stages_compose_to_lct():
  import jax

  from nlosjax import physics
  setup = Setup(wall_size=1.0, grid=(8, 8), bin_width=64e-12, num_bins=48).with_depth_range(0.3, 0.7)
  albedo = np.zeros((48, 8, 8), np.float32)
  albedo[26, 3:5, 4] = 1.0
  x = np.asarray(physics.render(albedo, setup.ungated()))[None] * 100 + 0.1   # [1, T, H, W]
  stages, dom = tradeoff.lct_stages(setup)
  out = stages["output"](stages["v-axis"](stages["input"](jax.numpy.asarray(x))))
  ref = physics.lct(x, setup, snr=0.1, variant="refined")
  assert out.shape == ref.shape == (1, setup.num_depth_bins, 8, 8)
  np.testing.assert_allclose(np.asarray(out), np.asarray(ref), rtol=1e-4,
                             atol=1e-5 * float(np.max(ref)))


@pytest.mark.full
def test_end_to_end_classic_configuration(tmp_path):
  """One classic configuration through evaluate -> timing -> scores -> Markdown and plot."""
  from nlosjax.evaluation.baselines import classic_images
  from tests.small_capture import three_patch_capture
  setup, full, albedo = three_patch_capture()
  x = full[..., 1::3, 1::3]                                          # stride 3: 4 x 4 input
  cache = {}
  m = tradeoff.evaluate(tradeoff.classic_pipeline("lct", setup, 3), x, batch=2, cache=cache,
                        key="lct")
  inten, depth = classic_images(x, setup, 3, "lct")                 # the library's path, eager
  np.testing.assert_allclose(m["outputs"]["intensity"], inten, atol=1e-5)
  np.testing.assert_allclose(m["outputs"]["depth"], depth, atol=1e-6)
  assert m["outputs"]["intensity"].shape == (3, 12, 12)               # padded batch trimmed
  assert m["compile_s"] > 0 and m["mem_mib"] > 0 and list(cache) == ["lct"]
  # The same key reuses the executable (another exposure): same compile time, new outputs.
  m2 = tradeoff.evaluate(None, 2 * x, batch=2, cache=cache, key="lct")
  assert m2["compile_s"] == m["compile_s"]
  # LCT is linear and the projection scale-free: twice the counts, the same images.
  np.testing.assert_allclose(m2["outputs"]["intensity"], m["outputs"]["intensity"], atol=1e-5)
  np.testing.assert_array_equal(m2["outputs"]["depth"], m["outputs"]["depth"])
  e = cache["lct"]
  rounds = tradeoff.interleaved_times({"lct": e["executable"]}, {"lct": e["args"]}, rounds=3)
  assert len(rounds["lct"]) == 3 and min(rounds["lct"]) > 0

  gt_i = np.where(albedo.max(1) > 0, 1.0, 0.0).astype(np.float32)
  gt_d = (np.argmax(albedo, 1) * setup.depth_bin_length * (gt_i > 0)).astype(np.float32)
  sc = tradeoff.scores(m["outputs"]["intensity"], m["outputs"]["depth"], gt_i, gt_d)
  assert set(sc) == {"psnr", "ssim", "rmse", "mad"}
  assert sc["rmse"][0] < 0.1                      # LCT finds the planes (0.12-0.17 m)

  row = {"knob": "method", "name": "lct", "label": "LCT", "kind": "classic", "capture": "default",
         "setting": "", "time": np.median(rounds["lct"]) / 2, "compile_s": m["compile_s"],
         "mem_mib": m["mem_mib"], **sc}
  fast = dict(row, name="fbp", label="FBP", time=row["time"] / 2, psnr=[sc["psnr"][0] - 1, 0.0])
  net = dict(row, name="ours", label="Ours", kind="learned", time=row["time"] * 3,
             psnr=[sc["psnr"][0] + 2, 0.0])
  res = {"configs": [row, fast, net], "steps": 1, "batch": 2, "rounds": 3, "frames": 3,
         "data": "tiny", "wall_s": 1.0, "executables": 1, "timing_s": 0.1, "grid": [8, 8], "stride": 4, "num_bins": 48,
         "bin_width": 64e-12, "wall_size": 1.0, "depth_range": [0.3, 0.7]}
  md = tradeoff.to_markdown(res, "cmd", "machine", ("0", "0"), gating=False)
  assert "| fastest | FBP |" in md and "| best | Ours |" in md
  assert "more accurate than every faster classic one: Ours." in md
  tradeoff.plot(res, tmp_path / "p.png")
  assert (tmp_path / "p.png").stat().st_size > 1000


@pytest.mark.full
def test_csa_pipeline_reads_only_the_sparse_scan_points():
  """The timed CSA pipeline on the ``[h, w]`` input equals the library's CSA on the full grid
  masked to those points (where the full grid holds anything else, it is never read)."""
  from nlosjax.physics import intensity_depth
  from nlosjax.physics.methods import csa
  from tests.small_capture import three_patch_capture
  setup, full, _ = three_patch_capture()
  mask = csa.interval_mask(*setup.grid, 3)
  m = tradeoff.evaluate(tradeoff.csa_pipeline(setup, 3, tau_rel=0.1, falloff="diffuse"),
                        full[..., 1::3, 1::3], batch=3, cache={}, key="csa")
  garbage = full + 7.0 * (1.0 - mask)                # unscanned points: anything
  inten, depth = intensity_depth(csa.csa(garbage, setup, mask=mask, tau_rel=0.1,
                                         falloff="diffuse"), setup)
  np.testing.assert_allclose(m["outputs"]["intensity"], np.asarray(inten), atol=1e-5)
  np.testing.assert_allclose(m["outputs"]["depth"], np.asarray(depth), atol=1e-5)


def test_csa_choice_table_bolds_the_chosen_setting():
  choice = {"frames": 4, "chosen": ["retroreflective", 0.3],
            "psnr": [["diffuse", 0.1, 15.0], ["diffuse", 0.3, 16.0],
                     ["retroreflective", 0.1, 17.0], ["retroreflective", 0.3, 18.25]]}
  md = "\n".join(tradeoff.csa_choice_markdown(choice))
  assert "| retroreflective | 17.00 | **18.25** |" in md and "| diffuse | 15.00 | 16.00 |" in md


@pytest.mark.full
def test_learned_configurations_train_through_train_model_and_a_rerun_restores(tmp_path_factory, tmp_path):
  from nlosjax import train as T
  from tests.tiny_run import make_tiny_dataset, tiny_config
  path = make_tiny_dataset(tmp_path_factory)
  config = T.RunConfig.from_dict(tiny_config(path, steps=2))
  setup = config.data.setup()
  spec = tradeoff.Learned("wide", "wide", 3, (("width", 6),))
  made = []

  def get_loader():
    made.append(T.make_loader(config, path, "train", batch_size=config.train.batch_size, shuffle=True,
                              seed=config.train.seed, window=5))
    return made[-1]

  mcfg, params = tradeoff.train_learned(spec, config, setup, tmp_path, get_loader, log=lambda s: None)
  assert (mcfg.width, mcfg.frames) == (6, 3)
  assert mcfg == tradeoff.learned_config(config, setup, spec)
  assert [r["step"] for r in T.read_metrics(tmp_path / "wide" / "metrics.jsonl")][-1] == 2
  # The loader reads 5-frame windows; the network takes the middle 3.
  assert made[0].batch(0)["measurement"].shape[1] == 5
  messages = []
  again, restored = tradeoff.train_learned(spec, config, setup, tmp_path, get_loader, log=messages.append)
  assert again == mcfg and any("resumed from step 2" in m for m in messages)
  assert [r["step"] for r in T.read_metrics(tmp_path / "wide" / "metrics.jsonl")] == [1, 2]   # no step more
  jax.tree.map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)), params, restored)

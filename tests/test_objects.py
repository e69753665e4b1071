"""The objects study's choice and verdicts, on per-frame scores made by hand."""

import numpy as np
import pytest

from experiments.studies.objects import __main__ as study
from nlosjax.evaluation import scores

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


def _frames(shift: float, n_seq: int = 6, per: int = 4, noise: float = 0.01, seed: int = 0) -> dict:
  """Per-frame scores of one method: every metric a base value plus ``shift``, a little noise."""
  rng = np.random.default_rng(seed)
  n = n_seq * per
  return {k: 0.5 + shift + noise * rng.standard_normal(n) for k in scores.METRICS}


def test_choose_takes_the_row_whose_ours_has_the_best_validation_balanced_psnr():
  val = {"paper": {"ours": {"psnr_balanced": np.array([[10.0, 11.0], [10.5, 10.5]])}},
         "balanced": {"ours": {"psnr_balanced": np.array([[12.0, np.nan], [11.0, 12.0]])}},
         "ours_s_only": {"ours_s": {"psnr_balanced": np.array([30.0])}},
         "long": {"ours": {"psnr_balanced": np.array([[40.0]])}}}               # past the main job's budget
  assert study.choose(val) == "balanced"          # 11.67 over its frames and seeds, NaN left out
  assert study.choose({}) is None


def test_verdicts_follow_the_paired_intervals_and_the_direction_of_each_score():
  seq = np.repeat(np.arange(6), 4)
  fbp = _frames(0.0, seed=1)
  lct = _frames(0.0, seed=2)
  lct["intensity_mae_object"] = fbp["intensity_mae_object"] - 0.2                  # LCT's objects: better still
  ours = {k: np.stack([fbp[k] + 0.1, fbp[k] + 0.12]) for k in scores.METRICS}     # 2 seeds, above FBP
  ours["intensity_mae_object"] = np.stack([fbp["intensity_mae_object"] - 0.1] * 2)  # an error: lower is better
  swing = 0.3 * (-1.0) ** np.arange(24)                                           # mean 0 in every sequence
  ours_s = {k: np.stack([fbp[k] + swing, fbp[k] - swing]) for k in scores.METRICS}
  per_frame = {"fbp": fbp, "lct": lct, "ours": ours, "ours_s": ours_s}
  lines, verdicts = study.versus_classic(per_frame, seq)
  assert verdicts[("ours", "fbp", "psnr_balanced")] == "better"
  assert verdicts[("ours", "fbp", "intensity_mae_object")] == "better"    # lower error
  assert verdicts[("ours", "fbp", "rmse_object")] == "worse"              # higher error
  assert verdicts[("ours_s", "fbp", "psnr_balanced")] == "tie"            # noise around the same mean
  assert any(line.startswith("| Ours - Ours-S |") for line in lines)
  goals = study.goals(per_frame, verdicts)
  assert goals[0].startswith("- object intensity error below every classic method's: not met against lct")
  assert goals[2] == "- surface F1 above every classic method's: met"


def test_the_report_reads_the_score_files_the_main_job_writes(tmp_path):
  seq, frame = np.repeat(np.arange(6), 4), np.tile(np.arange(4), 6)
  for row, shift in (("paper", 0.0), ("balanced", 0.2)):
    res = tmp_path / row / "results"
    res.mkdir(parents=True)
    methods = {"fbp": _frames(0.0, seed=1), "ours": {k: v[None] for k, v in _frames(shift, seed=4).items()}}
    for name in ("val_scores.npz", "scores.npz"):
      np.savez(res / name, sequence=seq, frame=frame,
               **{f"{m}/{k}": v for m, s in methods.items() for k, v in s.items()})
  text = study.write_report(tmp_path, ["paper", "balanced"], tmp_path / "objects.md",
                            "python -m experiments.studies.objects --report-only")
  assert "Chosen: **balanced**." in text
  assert "## paper: test set" in text and "## balanced: test set" in text
  assert text.index("object intensity error") < text.index("intensity PSNR (dB)")   # objects first


def test_the_shipped_section_says_whether_seed_0_beats_the_shipped_weights():
  row = {"ours": {"psnr_balanced": np.array([[14.0, 14.2], [15.0, 15.4], [13.0, 13.0]]),
                  "intensity_mae_object": np.array([[0.2, 0.2], [0.1, 0.1], [0.3, 0.3]])},
         "ours_s": {"psnr_balanced": np.array([[12.0, 12.0], [12.5, 12.5], [11.0, 11.0]]),
                    "intensity_mae_object": np.full((3, 2), 0.25)}}
  shipped = {"ours": {"psnr_balanced": np.array([[14.5, 14.5]]), "intensity_mae_object": np.array([[0.2, 0.2]])},
             "ours_s": {"psnr_balanced": np.array([13.0, 13.0]), "intensity_mae_object": np.array([0.2, 0.2])}}
  assert study.per_seed(row, "ours") == pytest.approx([14.1, 15.2, 13.0])
  lines = study.shipped_section(shipped, row, "wide")
  ours = next(line for line in lines if line.startswith("| Ours |"))
  ours_s = next(line for line in lines if line.startswith("| Ours-S |"))
  assert ours.endswith("| 14.500 / 0.200 | 14.100, 15.200, 13.000 | 0.200, 0.100, 0.300 | no |")  # seed 1 would
  assert ours_s.endswith("| 12.000, 12.500, 11.000 | 0.250, 0.250, 0.250 | no |")
  row["ours"]["psnr_balanced"][0] += 1.0                                   # seed 0: 15.1 dB
  lines = study.shipped_section(shipped, row, "wide")
  assert any(line.startswith("| Ours |") and line.endswith("| yes |") for line in lines)

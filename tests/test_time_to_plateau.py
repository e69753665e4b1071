import numpy as np
import pytest

from experiments import configs
from experiments.studies import mechanisms as M
from experiments.studies import time_to_plateau as P
from tests.test_mechanisms import fake_record


def test_the_short_schedule_differs_from_the_study_in_two_numbers_only():
  base = M.study_recipe(configs.get_config("cpu"))
  base["train"]["optim"] = M.study_optim(base)          # as the CLIs build the study's base
  assert base["train"]["optim"]["learning_rate"] == 1e-3
  for row in ("full", "ours_s"):
    study = M.run_config(base, "full", row, 1, M.STUDY_STOP)
    short = P.short_config(base, row, 1)
    assert short["train"]["optim"]["learning_rate"] == P.SHORT["learning_rate"]
    assert short["train"]["stop"]["max_steps"] == short["train"]["steps"] == P.SHORT["max_steps"]
    study["train"]["optim"]["learning_rate"] = P.SHORT["learning_rate"]
    study["train"]["stop"]["max_steps"] = study["train"]["steps"] = P.SHORT["max_steps"]
    assert short == study


def _write(tmp_path, row, seed, psnr, steps, seq, frames, short):
  r = fake_record("full", row, seed, psnr, seq, frames)
  r["steps_taken"] = steps
  M.write_json(P.record_path(tmp_path, row, seed) if short else M.run_json(tmp_path, "full", row, seed), r)


def test_the_report_pairs_each_seed_and_sums_the_steps(tmp_path):
  """Against the plain per-frame mean of the paired differences and a hand-summed step ratio."""
  rng = np.random.default_rng(0)
  seq, frames = np.repeat(np.arange(6), 4), np.tile(np.arange(1, 5), 6)
  study = {s: 20 + rng.normal(0, 1, 24) for s in (0, 1)}
  for s, steps in ((0, 800), (1, 1200)):
    _write(tmp_path, "ours_s", s, study[s], steps, seq, frames, short=False)
    _write(tmp_path, "ours_s", s, study[s] - 2.0, 400, seq, frames, short=True)   # 2 dB lower everywhere
  assert P.main(["--report-only", "--results", str(tmp_path), "--study-results", str(tmp_path)]) == 0
  text = (tmp_path / f"{P.NAME}.md").read_text()
  assert f"| ours_s | 0, 1 | {800 / 2000:.2f} | -2.00 [-2.00, -2.00] |" in text
  assert "- ours_s: 0.40x the steps" in text and "lower (called)." in text
  assert "| ours_s | 0 | 800 → 400 (0.50) |" in text
  # A short run scored on other frames is refused.
  _write(tmp_path, "ours_s", 1, study[1], 400, seq, frames[::-1], short=True)
  with pytest.raises(ValueError, match="different test frames"):
    P.main(["--report-only", "--results", str(tmp_path), "--study-results", str(tmp_path)])

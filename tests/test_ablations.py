"""experiments.studies.ablations: rows over several training seeds, paired with the full model seed by seed."""

import numpy as np
import pytest

from experiments.studies import ablations as A


def fake_run(row, seed, psnr, seq):
  metrics = ("psnr", "ssim", "rmse", "mad", "rmse_object", "mad_object", "recall", "precision", "f1")
  scores = {m: list(psnr) if m == "psnr" else [0.5] * len(psnr) for m in metrics}
  split = {"sequence": list(seq), "scores": scores}
  return {"row": row, "seed": seed, "steps": 1, "train_s": 10.0, "val": split, "test": split}


def test_summary_covers_seeds_and_pairs_them():
  rng = np.random.default_rng(0)
  seq = np.repeat(np.arange(6), 4)
  full = [fake_run("full", k, 20 + rng.normal(0, 1, 24), seq) for k in range(3)]
  # no_pf: the same frames 1 dB lower, seed by seed, plus small noise.
  no_pf = [fake_run("no_pf", k, np.asarray(full[k]["test"]["scores"]["psnr"]) - 1
                    + rng.normal(0, 0.01, 24), seq) for k in range(3)]
  s = A.summarise({"full": full, "no_pf": no_pf})
  assert s["test"]["full"]["psnr"]["n_seeds"] == 3
  d = s["vs_full"]["no_pf"]["psnr"]
  assert d["mean"] == pytest.approx(-1.0, abs=0.01)
  lo, hi = d["ci95"]
  assert hi < 0 and hi - lo < 0.05          # pairing removes the scene-to-scene spread
  with pytest.raises(ValueError, match="different frames"):
    A.summarise({"full": [full[0], fake_run("full", 1, np.zeros(24), seq[::-1])]})

"""``experiments.studies.preset_choice``'s tables against means computed by hand from fixed per-frame scores."""

from __future__ import annotations

import json

import numpy as np

from experiments.studies import preset_choice

SEQUENCE = np.array([0, 0, 1, 1, 2, 2])
#: per-frame PSNR of each (model label, data label); classic scores per data label.
PSNR = {("a", "a"): [10, 12, 14, 16, 18, 20], ("b", "a"): [11, 13, 15, 17, 19, 21],
        ("a", "b"): [5, 5, 5, 5, 5, 5], ("b", "b"): [6, 6, 6, 6, 6, 6]}
CLASSIC = {"a": 9.0, "b": 4.0}


def _frame_scores(psnr, data):
  psnr = np.asarray(psnr, float)
  return {"psnr": psnr, "psnr_zero": np.full(6, 3.0 if data == "a" else 2.0),
          "intensity_mae_object": psnr / 100}


def test_tables_are_the_hand_means_of_the_per_frame_scores(tmp_path, monkeypatch):
  monkeypatch.setattr(preset_choice, "load_candidate",
                      lambda source, variant: ("mcfg", source, {"data": {"path": source}}))
  monkeypatch.setattr(preset_choice, "validation_file", lambda cfg: (cfg["data"]["path"], cfg))

  def evaluate(cfg, path, trained, *, split, methods):
    assert split == "val"
    out = {method: _frame_scores(np.full(6, CLASSIC[path]), path) for method in methods}
    for variant, [(_, source)] in trained.items():
      out[variant] = {k: v[None] for k, v in _frame_scores(PSNR[(source, path)], path).items()}
    return {"scores": out, "sequence": SEQUENCE}

  from nlosjax.evaluation import protocol
  monkeypatch.setattr(protocol, "evaluate", evaluate)
  out = tmp_path / "choice.md"
  assert preset_choice.main(["--model", "A=a", "--model", "B=b", "--variants", "ours",
                             "--methods", "lct", "--out", str(out)]) == 0
  record = json.loads(out.with_suffix(".json").read_text())
  # means over sequences of the per-sequence means (equal frame counts: the plain mean)
  assert np.isclose(record["ours/A"]["means"]["A"]["mean"], 15.0)
  assert np.isclose(record["ours/A"]["means"]["B"]["mean"], 16.0)
  assert np.isclose(record["ours/A"]["differences"]["B"]["mean"], 1.0)
  assert np.isclose(record["ours/B"]["differences"]["B"]["mean"], 1.0)
  ctx = record["context"]
  assert set(ctx) == {"A/lct", "B/lct", "A/A ours", "A/B ours", "B/A ours", "B/B ours"}
  assert np.isclose(ctx["A/lct"]["psnr"]["mean"], 9.0) and np.isclose(ctx["B/lct"]["psnr"]["mean"], 4.0)
  assert np.isclose(ctx["B/A ours"]["psnr_zero"]["mean"], 2.0)
  assert np.isclose(ctx["A/B ours"]["intensity_mae_object"]["mean"], 0.16)
  text = out.read_text()
  assert "| A | lct | 9.00" in text and "all-zero PSNR" in text


def test_a_workdir_candidate_is_its_runs_model_config_and_parameters(monkeypatch):
  """``load_candidate`` on a workdir: :func:`nlosjax.inference.load_run` (no seeds) gives
  ``variant -> (model_config, params)``; a variant it lacks is refused by name."""
  import pytest

  from nlosjax import inference
  monkeypatch.setattr(inference, "load_run", lambda source: ({"c": 1}, {"ours": ("mcfg", "params")}))
  assert preset_choice.load_candidate("runs/x", "ours") == ("mcfg", "params", {"c": 1})
  with pytest.raises(SystemExit, match="no trained ours_s"):
    preset_choice.load_candidate("runs/x", "ours_s")

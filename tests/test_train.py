"""Training: the end-to-end main job and evaluate CLI, bad configs, scan interpolation.

Resume, checkpoint errors, the 4-device step and the 200-step run are in
``test_train_resume.py`` (the two slow halves run on different xdist workers).
"""

import json

import numpy as np
import pytest

from nlosjax import train as T
from tests.nested import assert_nested_close
from tests.tiny_run import make_tiny_dataset, tiny_config

@pytest.fixture(scope="module")
def data_path(tmp_path_factory):
  return make_tiny_dataset(tmp_path_factory)


def test_main_job_writes_table_and_figures(data_path, tmp_path):
  cfg = tiny_config(data_path, steps=2)
  table = T.train_and_evaluate(cfg, tmp_path)
  saved = json.loads((tmp_path / "results" / "table.json").read_text())
  assert set(saved) == set(T.TABLE_METHODS)
  for method, row in saved.items():
    assert set(row) == {"psnr", "ssim", "rmse", "mad"}
    assert all(np.isfinite(v).all() and len(v) == 2 for v in row.values()), method
    assert_nested_close(row, table[method], path=method)
  for name in ("table.md", "comparison.png", "training_curves.png"):
    assert (tmp_path / "results" / name).stat().st_size > 0
  rows = [json.loads(l) for l in (tmp_path / "ours" / "metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in rows] == [1, 2]
  assert all(np.isfinite(r["loss"]) for r in rows)
  # The evaluate CLI restores the same checkpoints from disk and reproduces the table.
  from experiments import evaluate
  evaluated = evaluate.main(["--checkpoint", str(tmp_path), "--data", str(data_path),
                             "--out", str(tmp_path / "eval")])
  again = json.loads((tmp_path / "eval" / "table.json").read_text())
  assert set(again) == set(T.TABLE_METHODS)
  assert_nested_close(again, saved, rtol=1e-5, atol=1e-6)
  assert_nested_close(evaluated["ours"], again["ours"], path="ours")
  # One variant's folder selects that variant only.
  from nlosjax import checkpoints_io
  _, only = checkpoints_io.load_run(tmp_path / "ours_s" / "checkpoints", log=lambda s: None)
  assert set(only) == {"ours_s"}


def test_evaluate_cli_errors_name_the_problem(data_path, tmp_path):
  from experiments import evaluate
  with pytest.raises(SystemExit, match="not a training run"):
    evaluate.main(["--checkpoint", str(tmp_path), "--data", str(data_path)])
  with pytest.raises(SystemExit, match="no such file"):
    evaluate.main(["--checkpoint", str(tmp_path), "--data", str(tmp_path / "absent.h5")])
  (tmp_path / "config.json").write_text("{}")
  (tmp_path / "ours" / "checkpoints" / "7").mkdir(parents=True)
  with pytest.raises(SystemExit, match="config.json"):
    evaluate.main(["--checkpoint", str(tmp_path), "--data", str(data_path)])


def test_bad_configs_raise(data_path, tmp_path):
  cfg = tiny_config(data_path)
  with pytest.raises(ValueError, match="unknown key"):
    T.with_defaults({**cfg, "train": {**cfg["train"], "stepz": 3}})
  with pytest.raises(ValueError, match="variant"):
    T.model_config_for(cfg, None, "ours_xl")
  empty = tmp_path / "empty.h5"
  empty.write_bytes(b"")
  with pytest.raises(ValueError, match="empty.h5"):
    T.train_model(tiny_config(empty), empty, tmp_path, "ours_s", log=lambda s: None)


def test_upsample_scan_interpolates_linearly_between_samples():
  m = T.interpolation_matrix(16, 4)              # samples at 2, 6, 10, 14
  x = np.array([1.0, 3.0, 5.0, 7.0])
  y = m @ x
  np.testing.assert_allclose(y[[2, 6, 10, 14]], x)
  np.testing.assert_allclose(y[4], 2.0)
  np.testing.assert_allclose(y[:2], 1.0)        # before the first sample: nearest
  np.testing.assert_allclose(y[15], 7.0)

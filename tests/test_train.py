"""Training: the end-to-end main job, bitwise resume, checkpoint errors, data-parallel equivalence."""

import json
import os
import pathlib
import shutil
import subprocess
import sys

import jax
import numpy as np
import pytest

from experiments import configs
from nlosjax import train as T

# 16 x 16 capture, every 4th point in (4 x 4), 64 bins of 264 ps; a model a few thousand parameters big.
TINY_DATA = dict(grid=16, num_bins=64, bin_width=264e-12, frames=4, input_stride=4, input_offset=2,
                 num_sequences={"train": 2, "test": 1}, render_batch=4)
TINY_MODEL = dict(width=4, d_state=2, extract_time_stride=2, extract_blocks=1, st_depth=1,
                  cross_depth=1, spread_min_width=1, volume_features=1, refine_width=2)


def tiny_config(data_path, **train):
  cfg = configs.get_config("cpu")
  cfg["data"].update(TINY_DATA, path=str(data_path))
  cfg["model"] = dict(TINY_MODEL)
  cfg["train"] = {"steps": 4, "batch_size": 2, "log_every": 1, "checkpoint_every": 2,
                  "eval_batch_size": 2, **train}
  return T.with_defaults(cfg)


@pytest.fixture(scope="module")
def data_path(tmp_path_factory):
  path = tmp_path_factory.mktemp("data") / "tiny.h5"
  T.ensure_dataset(tiny_config(path), path, log=lambda s: None)
  return path


def test_main_job_writes_table_and_figures(data_path, tmp_path):
  cfg = tiny_config(data_path, steps=2)
  table = T.train_and_evaluate(cfg, tmp_path)
  saved = json.loads((tmp_path / "results" / "table.json").read_text())
  assert set(saved) == set(T.TABLE_METHODS)
  for method, row in saved.items():
    assert set(row) == {"psnr", "ssim", "rmse", "mad"}
    assert all(np.isfinite(v).all() and len(v) == 2 for v in row.values()), method
    assert row == pytest.approx(table[method])
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
  for method in T.TABLE_METHODS:
    for metric in ("psnr", "ssim", "rmse", "mad"):
      assert again[method][metric] == pytest.approx(saved[method][metric], rel=1e-5, abs=1e-6), \
          (method, metric)
  assert evaluated["ours"] == pytest.approx(again["ours"])
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


def test_two_hundred_steps_stay_finite_at_the_lowest_efficiency_and_exposure(tmp_path):
  # The CPU preset's lowest efficiency (1 %) and photon budget (1e3 per point), nothing higher.
  path = tmp_path / "dim.h5"
  cfg = tiny_config(path, steps=200, log_every=1, checkpoint_every=200)
  low = configs.get_config("cpu")["data"]
  cfg["data"].update(efficiency=(low["efficiency"][0],) * 2, photons=(low["photons"][0],) * 2)
  T.ensure_dataset(cfg, path, log=lambda s: None)
  T.train_model(cfg, path, tmp_path, "ours_s", log=lambda s: None)  # raises on a non-finite metric
  rows = [json.loads(l) for l in (tmp_path / "ours_s" / "metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in rows] == list(range(1, 201))
  for key in ("loss", "l2_grads", "l2_updates"):
    values = np.array([r[key] for r in rows])
    assert np.isfinite(values).all(), key
  assert rows[-1]["l2_grads"] > 0                   # still learning, not silently zeroed


def test_resume_after_a_kill_matches_an_uninterrupted_run(data_path, tmp_path):
  cfg = tiny_config(data_path)
  _, straight = T.train_model(cfg, data_path, tmp_path / "a", "ours_s", log=lambda s: None)
  # "Killed" after step 2: a run with steps=2 leaves the checkpoint at 2; the rerun resumes.
  T.train_model({**cfg, "train": {**cfg["train"], "steps": 2}}, data_path, tmp_path / "b",
                "ours_s", log=lambda s: None)
  messages = []
  _, resumed = T.train_model(cfg, data_path, tmp_path / "b", "ours_s", log=messages.append)
  assert any("resumed from step 2" in m for m in messages)
  assert int(resumed.step) == int(straight.step) == 4
  jax.tree.map(lambda a, b: np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0,
                                                       atol=1e-6), straight.params, resumed.params)
  la = [json.loads(l) for l in (tmp_path / "a/ours_s/metrics.jsonl").read_text().splitlines()]
  lb = [json.loads(l) for l in (tmp_path / "b/ours_s/metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in lb] == [1, 2, 3, 4]
  assert lb[-1]["loss"] == pytest.approx(la[-1]["loss"], abs=1e-6)


def test_checkpoint_of_another_config_or_corrupt_raises_and_is_kept(data_path, tmp_path):
  cfg = tiny_config(data_path, steps=2)
  T.train_model(cfg, data_path, tmp_path, "ours_s", log=lambda s: None)
  ckpt = tmp_path / "ours_s" / "checkpoints"
  before = sorted(p.name for p in ckpt.iterdir())
  other = {**cfg, "model": {**cfg["model"], "width": 6}}
  with pytest.raises(ValueError, match="another model config"):
    T.train_model(other, data_path, tmp_path, "ours_s", log=lambda s: None)
  assert sorted(p.name for p in ckpt.iterdir()) == before
  # Corrupt every array file of the latest checkpoint.
  for f in (ckpt / "2").rglob("*"):
    if f.is_file() and "state" in str(f) and f.stat().st_size > 64:
      f.write_bytes(b"\0" * 16)
  with pytest.raises(ValueError, match="checkpoint .*2"):
    T.train_model(cfg, data_path, tmp_path, "ours_s", log=lambda s: None)
  assert (ckpt / "2").exists()


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


_MULTI = r"""
import os, sys, json
import jax, numpy as np
sys.path.insert(0, os.getcwd())
from tests.test_train import tiny_config
from nlosjax import train as T, losses
from nlosjax.data.dataset import TripletLoader
cfg = tiny_config(sys.argv[1])
loader = TripletLoader(sys.argv[1], batch_size=4, stride=4, offset=2)
b = loader.batch(0)
batch = {k: b[k] for k in T.BATCH_KEYS}
mcfg = T.model_config_for(cfg, loader.setup, "ours")
from nlosjax.models.network import STMambaNet
out = {}
for n in (1, 4):
  mesh = T.make_mesh(jax.devices()[:n])
  state = T.create_train_state(STMambaNet(mcfg), batch["measurement"].shape,
                               T.make_optimizer(T.OptimConfig(), 10), jax.random.key(0), mesh)
  step = T.make_train_step(mcfg, losses.LossWeights(), mesh)
  state, m = step(state, T.shard_batch(batch, mesh), jax.random.key(1))
  out[n] = (jax.device_get(state.params), float(m["loss"]))
diff = max(float(np.max(np.abs(a - b))) for a, b in zip(jax.tree.leaves(out[1][0]), jax.tree.leaves(out[4][0])))
print(json.dumps({"devices": jax.device_count(), "diff": diff, "loss1": out[1][1], "loss4": out[4][1]}))
"""


def test_four_device_step_matches_one_device(data_path):
  env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4",
         "JAX_PLATFORMS": "cpu"}
  root = pathlib.Path(__file__).resolve().parents[1]
  res = subprocess.run([sys.executable, "-c", _MULTI, str(data_path)], cwd=root, env=env,
                       capture_output=True, text=True, timeout=600)
  assert res.returncode == 0, res.stderr[-3000:]
  out = json.loads(res.stdout.strip().splitlines()[-1])
  assert out["devices"] == 4
  assert out["loss4"] == pytest.approx(out["loss1"], rel=1e-5)
  assert out["diff"] < 1e-6

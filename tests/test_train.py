"""Training: the end-to-end main job and evaluate CLI, bad configs, scan interpolation.

Resume, checkpoint errors, the 4-device step and the 200-step run are in
``test_train_resume.py`` (the two slow halves run on different xdist workers).
"""

import json

import numpy as np
import pytest

from nlosjax import train as T
from nlosjax.train import RunConfig
from tests.nested import assert_nested_close
from tests.tiny_run import make_tiny_dataset, tiny_config
from tests.xla_options import xla_optimizations


@pytest.fixture(scope="module", autouse=True)
def _compile_fast():
  # Tiny shapes and 2-step runs: compiling dominates. The main-job test ran 103 s with XLA's
  # optimisations, 71 s without (the same validation scores), measured alone on 2 cores.
  with xla_optimizations(False):
    yield


@pytest.fixture(scope="module")
def data_path(tmp_path_factory):
  return make_tiny_dataset(tmp_path_factory)


def test_phases_add_a_name_met_again_and_count_the_rest_as_other():
  """``main_job.Phases`` on a fake clock: the sums are the clock's, by hand."""
  from experiments.main_job import Phases
  ticks = iter([0.0, 1.0, 4.0, 4.5, 6.0, 7.0, 9.5, 10.0])
  phases = Phases(clock=lambda: next(ticks))          # starts at 0
  with phases("dataset"):                             # 1 -> 4
    pass
  with phases("train ours"):                          # 4.5 -> 6
    pass
  with pytest.raises(RuntimeError), phases("train ours"):   # 7 -> 9.5, timed though it raised
    raise RuntimeError("stop")
  record = phases.record()                            # at 10
  assert record == {"phases_s": {"dataset": 3.0, "train ours": 4.0}, "total_s": 10.0, "other_s": 3.0}
  assert Phases(clock=iter([0.0, 2.0, 2.0]).__next__).line() == "phases: other 2 s (2 s in all)"


@pytest.mark.full
def test_main_job_writes_table_and_figures(data_path, tmp_path, monkeypatch):
  from experiments.main_job import train_and_evaluate
  from nlosjax.evaluation import baselines, protocol, report, scores
  # Two settings per classic method instead of up to eight: the choice among several is
  # what this job needs; tests/test_evaluation.py checks tune() over the whole grid.
  grid = baselines.option_grid
  monkeypatch.setattr(baselines, "option_grid", lambda method, setup: grid(method, setup)[:2])
  cfg = tiny_config(data_path, steps=2, seeds=2, select_checkpoint="val", keep_checkpoints=2,
                    checkpoint_every=1, variants=("ours_s", "ours", "usm"))
  table = train_and_evaluate(T.RunConfig.from_dict(cfg), tmp_path, extra_test_sets={"again": data_path},
                             log=lambda s: None)
  saved = json.loads((tmp_path / "results" / "table.json").read_text())
  # Every classic method and the variants trained (LFE is a variant this run does not train).
  methods = {m for m in report.TABLE_METHODS if m not in T.VARIANT_FRAMES} | {"ours_s", "ours", "usm"}
  assert set(saved) == methods
  for method, row in saved.items():
    assert set(row) == set(scores.TABLE_METRICS), method
    for metric, cell in row.items():
      assert set(cell) == {"mean", "ci95", "std", "n_sequences", "n_frames", "n_seeds"}
      lo, hi = cell["ci95"]
      if metric in ("psnr", "ssim", "rmse", "mad", "temporal_rmse", "temporal_psnr"):  # every frame
        assert np.isfinite([cell["mean"], lo, hi]).all() and lo <= cell["mean"] <= hi, (method, metric)
      # 2 consecutive middle frames of 1 sequence: 2 frames, 1 frame pair for the temporal scores.
      per_seed = 1 if metric in scores.TEMPORAL_METRICS else 2
      assert cell["n_sequences"] == 1 and cell["n_frames"] == per_seed * cell["n_seeds"], (method, metric)
      assert cell["n_seeds"] == (2 if method in T.VARIANT_FRAMES else 1)
    assert_nested_close(row, table[method], path=method)
  comparisons = json.loads((tmp_path / "results" / "comparisons.json").read_text())
  validation = json.loads((tmp_path / "results" / "validation.json").read_text())
  best = validation["best_classic"]
  assert [(c["a"], c["b"]) for c in comparisons] == [
      ("ours", "ours_s"), ("ours", "usm"), ("ours_s", "usm"), ("ours", best), ("ours_s", best),
      ("usm", best)]
  # Ours - Ours-S on the temporal scores: 1 frame pair per seed, both seeds.
  assert set(comparisons[0]["diff"]) == set(scores.TABLE_METRICS)
  assert comparisons[0]["diff"]["temporal_rmse"]["n_frames"] == 2
  assert set(validation["classic"]) == {"fbp", "lct", "fk", "phasor", "rsd"}
  assert set(validation["checkpoints"]) == {"ours_s", "ours_s-seed1", "ours", "ours-seed1", "usm",
                                            "usm-seed1"}
  for c in validation["learned"].values():          # surface threshold chosen by validation F1
    assert c["threshold"] in protocol.MODEL_THRESHOLDS
    assert c["f1"] == max(c["f1_by_threshold"].values())
  assert set(validation["learned"]) == {"ours_s", "ours", "usm"}
  for c in validation["checkpoints"].values():      # both kept steps scored on validation
    assert sorted(int(k) for k in c["val_psnr"]) == [1, 2] and c["step"] in (1, 2)
  text = (tmp_path / "results" / "table.md").read_text()
  for needle in ("object recall", "Ours - Ours-S", "Ours - USM", f"Ours - {report.label(best)}",
                 "validation split", "temporal intensity error", "temporal depth error (objects)",
                 "Ours - Ours-S, temporal intensity error:"):
    assert needle in text, needle
  for name in ("comparison.png", "training_curves.png", "table1_again_comparison.png"):
    assert (tmp_path / "results" / name).stat().st_size > 0
  # An extra test set is scored with the same models and settings: the same file, the same table.
  again_table = json.loads((tmp_path / "results" / "table1_again.json").read_text())
  assert_nested_close(again_table, saved, rtol=1e-5, atol=1e-6)
  assert "Nothing is chosen" in (tmp_path / "results" / "table1_again.md").read_text()
  # Each step's wall seconds: a phase per variant (its two seeds in one), in the order they ran.
  phases = json.loads((tmp_path / "results" / "phases.json").read_text())
  assert list(phases["phases_s"]) == ["dataset", "train ours_s", "train ours", "train usm",
                                      "tune classic", "tune thresholds", "test split",
                                      "write results", "test set again"]
  assert all(v >= 0 for v in phases["phases_s"].values()) and phases["other_s"] >= -0.01
  assert sum(phases["phases_s"].values()) + phases["other_s"] == pytest.approx(phases["total_s"], abs=0.05)
  rows = [json.loads(l) for l in (tmp_path / "ours" / "metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in rows] == [1, 2]
  assert all(np.isfinite(r["loss"]) for r in rows)
  # The evaluate CLI restores the chosen checkpoints (seed 0) from disk with the run's
  # validation choices and reproduces the classic rows and the seed-0 model scores.
  from experiments import evaluate
  evaluate.main(["--checkpoint", str(tmp_path), "--data", str(data_path),
                 "--out", str(tmp_path / "eval")])
  again = json.loads((tmp_path / "eval" / "table.json").read_text())
  assert set(again) == methods
  for method in ("fbp", "lct", "fk", "phasor", "rsd"):
    assert_nested_close(again[method], saved[method], rtol=1e-5, atol=1e-6, path=method)
  assert again["ours"]["psnr"]["n_seeds"] == again["usm"]["psnr"]["n_seeds"] == 1
  # USM's training followed Ours' recipe (config usm.recipe "ours"): the same loss terms.
  usm_rows = [json.loads(l) for l in (tmp_path / "usm" / "metrics.jsonl").read_text().splitlines()]
  assert set(usm_rows[-1]) == set(rows[-1]) and {"pf", "ls", "tv"} <= set(usm_rows[-1])
  assert np.isfinite(usm_rows[-1]["loss"])
  # One variant's folder selects that variant only.
  from nlosjax import inference
  _, only = inference.load_run(tmp_path / "ours_s" / "checkpoints", log=lambda s: None)
  assert set(only) == {"ours_s"}
  # Every training seed's folder with seeds=True (a copy stands in for a second seed).
  import shutil
  before = inference.seed_folders(tmp_path, "ours_s")
  assert before[0] == "ours_s" and all(f.startswith("ours_s-seed") for f in before[1:])
  shutil.copytree(tmp_path / "ours_s", tmp_path / "ours_s-seed30")
  (tmp_path / "ours_s-seedx").mkdir()                            # not a seed folder
  assert inference.seed_folders(tmp_path, "ours_s") == before + ["ours_s-seed30"]
  _, by_seed = inference.load_run(tmp_path, seeds=True, log=lambda s: None)
  assert len(by_seed["ours_s"]) == len(before) + 1
  assert len(by_seed["ours"]) == len(inference.seed_folders(tmp_path, "ours"))
  assert_nested_close(by_seed["ours_s"][-1][1], by_seed["ours_s"][0][1], rtol=0, atol=0)


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
  with pytest.raises(TypeError, match="stepz"):
    T.RunConfig.from_dict({**cfg, "train": {**cfg["train"], "stepz": 3}})
  with pytest.raises(ValueError, match="variant"):
    T.model_config_for(cfg, None, "ours_xl")
  empty = tmp_path / "empty.h5"
  empty.write_bytes(b"")
  with pytest.raises(ValueError, match="empty.h5"):
    T.train_model(RunConfig.from_dict(tiny_config(empty)), empty, tmp_path, "ours_s", log=lambda s: None)


def test_prefetching_batches_changes_no_trained_parameter(data_path, tmp_path):
  # data.loader.prefetch reads the next batches in a thread while the step runs: the same
  # batches in the same order, so the same parameters bit for bit as reading them in turn.
  from nlosjax.data.dataset import loader as loader_module
  asked = []
  real_prefetch = loader_module.prefetch

  def recording(iterator, size):
    asked.append(size)
    return real_prefetch(iterator, size)

  params = {}
  for ahead in (0, 3):
    cfg = tiny_config(data_path, steps=3, checkpoint_every=3)
    cfg["data"]["loader"] = {**cfg["data"]["loader"], "prefetch": ahead}
    with pytest.MonkeyPatch.context() as mp:
      mp.setattr(loader_module, "prefetch", recording)
      _, state = T.train_model(RunConfig.from_dict(cfg), data_path, tmp_path / f"prefetch{ahead}", "ours_s",
                               log=lambda s: None)
    params[ahead] = T.to_host(state.params)
  assert asked == [3]                      # the training loop read ahead only when asked to
  assert_nested_close(params[3], params[0], rtol=0, atol=0)


def test_upsample_scan_interpolates_linearly_between_samples():
  from nlosjax.evaluation.baselines import interpolation_matrix
  m = interpolation_matrix(16, 4)              # samples at 2, 6, 10, 14
  x = np.array([1.0, 3.0, 5.0, 7.0])
  y = m @ x
  np.testing.assert_allclose(y[[2, 6, 10, 14]], x)
  np.testing.assert_allclose(y[4], 2.0)
  np.testing.assert_allclose(y[:2], 1.0)        # before the first sample: nearest
  np.testing.assert_allclose(y[15], 7.0)


def test_train_cli_seeds_flag_sets_the_config(monkeypatch, tmp_path):
  from experiments import independent_set, main_job
  from experiments import train as cli
  seen = {}
  monkeypatch.setattr(main_job, "train_and_evaluate",
                      lambda config, workdir, **kw: seen.update(config=config, workdir=workdir, **kw))
  monkeypatch.setattr(independent_set, "ensure_independent_set", lambda path, *a: path)
  monkeypatch.chdir(tmp_path)             # the command records its invocation under the workdir
  cli.main(["--seeds", "3", "--workdir", "runs/x", "--config.train.steps=5"])
  assert seen["config"].train.seeds == 3 and seen["config"].train.steps == 5
  assert seen["workdir"] == "runs/x"
  # The CPU preset scores its models on the independent set too.
  assert seen["extra_test_sets"] == {"independent": "runs/data/independent-cpu-v3-gen3.h5"}
  with pytest.raises(SystemExit):
    cli.main(["--seeds", "0"])

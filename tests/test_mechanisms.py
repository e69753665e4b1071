"""experiments.studies.mechanisms: photon budgets, rows, resumable JSON records, the honest report, the SSM probe."""

import copy
import json
import math
import time

import numpy as np
import pytest

from experiments import configs
from experiments.studies import mechanisms as M
from tests.xla_options import xla_optimizations


def strict_json(path):
  """The file's JSON; fails on NaN/Infinity (the records are strict JSON)."""
  def refuse(name):
    raise AssertionError(f"{path}: non-standard JSON constant {name}")
  return json.loads(path.read_text(), parse_constant=refuse)


def fake_record(budget, row, seed, psnr, seq, frames):
  n = len(psnr)
  scores = {"psnr": list(psnr), "ssim": [0.5] * n, "rmse_object": [0.3] * n,
            "recall": [None] + [0.8] * (n - 1), "temporal_psnr": [None] + [float(v) + 5 for v in psnr[1:]]}
  curve = [{"step": 50 * (i + 1), "val_psnr": 15.0 + i, "time_s": 10.0 * i, "val_s": 1.0, "lr": 1e-3}
           for i in range(5)]
  return {"budget": budget, "row": row, "seed": seed, "variant": M.ROWS[row][1], "label": M.ROWS[row][2],
          "config": {"data": {"photons": [50.0, 2000.0], "ambient": [50.0, 500.0], "path": "x.h5"},
                     "model": {}, "train": {"stop": dict(M.STUDY_STOP)}},
          "machine": {"cpu": "Test CPU", "cores": 2, "commit": "abc", "code_digest": "0" * 12},
          "steps_taken": 250, "stop_reason": "plateau", "best_step": 250, "best_val_psnr": 19.0,
          "train_wall_s": 40.0, "validation_curve": curve, "loss_curve": [],
          "test": {"split": "test", "sequence": list(seq), "frame": list(frames), "scores": scores}}


def test_the_tenth_budget_is_derived_from_the_preset():
  base = configs.get_config("cpu")
  # Fixed counts in place of the preset's, so a change of the preset's own range needs no edit here.
  base["data"].update(photons=(50.0, 2000.0), ambient=(50.0, 500.0), path="runs/data/cpu-vN.h5")
  before = copy.deepcopy(base)
  tenth = M.budget_config(base, "tenth")["data"]
  # The low-photon tables' overrides, derived rather than typed.
  assert tenth["photons"] == (5.0, 200.0) and tenth["ambient"] == (5.0, 50.0)
  assert tenth["path"] == "runs/data/cpu-vN-exposure-0.1.h5"
  assert M.budget_config(base, "full")["data"] == base["data"]
  assert base == before                                              # the preset is left as it was


@pytest.mark.full
def test_the_report_refuses_records_of_other_data_or_another_recipe(tmp_path):
  seq, frames = [0, 0, 1, 1], [1, 2, 1, 2]
  for seed in (0, 1):
    M.write_json(M.run_json(tmp_path, "full", "full", seed), fake_record("full", "full", seed, [20.0] * 4, seq, frames))
  other = fake_record("full", "no_ssm", 0, [20.0] * 4, seq, frames)
  other["config"]["data"]["photons"] = [5.0, 200.0]              # copied from another study
  M.write_json(M.run_json(tmp_path, "full", "no_ssm", 0), other)
  with pytest.raises(ValueError, match="differ in data: photons"):
    M.main(["--report-only", "--results", str(tmp_path)])
  other = fake_record("full", "no_ssm", 0, [20.0] * 4, seq, frames)
  M.write_json(M.run_json(tmp_path, "full", "no_ssm", 0), other)
  assert M.main(["--report-only", "--results", str(tmp_path)]) == 0   # rows may differ in their recipe
  late = fake_record("full", "full", 2, [20.0] * 4, seq, frames)
  late["config"]["train"]["stop"] = {**M.STUDY_STOP, "patience": 8}   # the same row, another rule
  M.write_json(M.run_json(tmp_path, "full", "full", 2), late)
  with pytest.raises(ValueError, match="share a row but differ in train: stop"):
    M.main(["--report-only", "--results", str(tmp_path)])


def test_a_loss_weight_set_by_the_user_wins_over_the_budget_recipe():
  base = configs.get_config("cpu")
  assert M.budget_config(base, "tenth")["train"]["loss"]["object_intensity"] == 1.0    # BUDGET_LOSS
  base["train"]["loss"]["object_intensity"] = 2.5                 # as --config.train.loss... sets it
  kept = M.run_config(base, "tenth", "full", 0, M.STUDY_STOP, keep_loss=("object_intensity",))
  assert kept["train"]["loss"]["object_intensity"] == 2.5
  assert M.run_config(base, "tenth", "full", 0, M.STUDY_STOP)["train"]["loss"]["object_intensity"] == 1.0


def test_each_row_trains_its_variant_with_the_plateau_rule():
  base = configs.get_config("cpu")
  full = M.run_config(base, "full", "full", 1, M.STUDY_STOP)
  assert full["train"]["variants"] == ("ours",) and full["train"]["seed"] == 1
  assert full["train"]["stop"] == M.STUDY_STOP
  assert M.run_config(base, "full", "ours_s", 0, M.STUDY_STOP)["train"]["variants"] == ("ours_s",)
  no_ssm = M.run_config(base, "tenth", "no_ssm", 2, M.STUDY_STOP)
  tenth = tuple(p / 10 for p in base["data"]["photons"])           # BUDGETS["tenth"], whatever the preset's
  assert no_ssm["model"]["variant"] == "none" and no_ssm["data"]["photons"] == tenth
  assert M.run_config(base, "full", "no_pf", 0, M.STUDY_STOP)["train"]["loss"]["phasor_field"] == 0.0
  # USM, for Table 1 at the plateau: Ours' data, stopping rule and recipe; its widths recorded.
  usm = M.run_config(base, "full", "usm", 0, M.STUDY_STOP)
  assert usm["train"]["variants"] == ("usm",) and usm["usm"]["recipe"] == "ours"
  assert usm["data"] == full["data"] and usm["train"]["stop"] == M.STUDY_STOP
  assert M.essentials(usm)["usm"] == usm["usm"] and "usm" not in M.essentials(full)
  assert ("full", "usm") in M.PAIRS and ("ours_s", "usm") in M.PAIRS
  # LFE likewise: Ours' data and stopping rule, its section recorded, paired with Ours and Ours-S.
  lfe = M.run_config({**base, "lfe": {"model": {"extract_width": 3}}}, "full", "lfe", 0, M.STUDY_STOP)
  assert lfe["train"]["variants"] == ("lfe",) and lfe["data"] == full["data"]
  assert M.essentials(lfe)["lfe"] == {"model": {"extract_width": 3}} and "lfe" not in M.essentials(usm)
  assert ("full", "lfe") in M.PAIRS and ("ours_s", "lfe") in M.PAIRS and "lfe" in M.TABLE1_ROWS
  with pytest.raises(SystemExit, match="plateau"):
    M.study_stop({"train": {"stop": {"rule": "steps"}}})


def test_the_report_names_missing_runs_and_pairs_only_common_seeds(tmp_path):
  rng = np.random.default_rng(0)
  seq, frames = np.repeat(np.arange(6), 4), np.tile(np.arange(1, 5), 6)
  full = {s: 20 + rng.normal(0, 1, 24) for s in M.SEEDS}
  for s in M.SEEDS:
    M.write_json(M.run_json(tmp_path, "full", "full", s), fake_record("full", "full", s, full[s], seq, frames))
  for s in (0, 1):           # no_ssm: the same frames 1 dB lower, seeds 0 and 1 only
    M.write_json(M.run_json(tmp_path, "full", "no_ssm", s),
                 fake_record("full", "no_ssm", s, full[s] - 1 + rng.normal(0, 0.01, 24), seq, frames))
  assert M.main(["--report-only", "--results", str(tmp_path)]) == 0
  text = (tmp_path / M.REPORT).read_text()
  assert text.startswith("# Mechanisms")
  assert "Produced by `python -m experiments.studies.mechanisms --report-only" in text
  assert "**Missing runs (13 of 18)**" in text
  assert "full/ours_s-seed0" in text and "full/no_ssm-seed2" in text and "tenth/full-seed0" in text
  assert "No run of this budget has finished yet." in text
  line = next(x for x in text.splitlines() if x.startswith("- **full - no_ssm**"))
  assert "seeds 0, 1" in line and "+1.00 dB" in line and "Called" in line and "Only 2 of 3 seeds" in line
  assert "intensity PSNR" in line
  assert "- **full - ours_s** (`full`, intensity PSNR): not computed yet" in text
  assert "temporal PSNR (dB) ↑" in text                      # the temporal column, every table
  assert "Barely trained" not in text                          # every fake run peaks at its last validation
  summary = M.summarise(M.load_runs(tmp_path), ["full"], list(M.MAIN_ROWS))["full"]
  assert summary["rows"]["full"]["psnr"]["n_seeds"] == 3
  assert summary["rows"]["full"]["recall"]["n_frames"] == 3 * 23          # the None frame left out
  assert (tmp_path / M.FIGURE).read_bytes()[:4] == b"\x89PNG"


def test_a_run_that_peaked_at_its_first_validation_is_named_barely_trained(tmp_path):
  seq, frames = np.repeat(np.arange(3), 2), np.tile([1, 2], 3)
  for row in ("full", "ours_s"):
    record = fake_record("tenth", row, 0, [16.0] * 6, seq, frames)
    if row == "ours_s":
      record["best_step"], record["best_val_psnr"] = 50, 15.0         # its first validation
    M.write_json(M.run_json(tmp_path, "tenth", row, 0), record)
  assert [r["row"] for r in M.barely_trained(list(M.load_runs(tmp_path).values()))] == ["ours_s"]
  assert M.main(["--report-only", "--results", str(tmp_path)]) == 0
  text = (tmp_path / M.REPORT).read_text()
  assert "**Barely trained**: ours_s-seed0 validated best at their first validation (step 50)" in text


def test_a_run_with_no_object_pixel_is_flagged_and_compared_without_it(tmp_path):
  seq, frames = np.repeat(np.arange(3), 2), np.tile([1, 2], 3)
  for seed in (0, 1):
    M.write_json(M.run_json(tmp_path, "tenth", "full", seed),
                 fake_record("tenth", "full", seed, [18.0 + seed] * 6, seq, frames))
    record = fake_record("tenth", "ours_s", seed, [16.0 + 2 * seed] * 6, seq, frames)
    if seed == 0:                                         # collapsed: recall 0 on every frame
      record["test"]["scores"]["recall"] = [None] + [0.0] * 5
    M.write_json(M.run_json(tmp_path, "tenth", "ours_s", seed), record)
  runs = M.load_runs(tmp_path)
  assert [(r["row"], r["seed"]) for r in M.empty_output(list(runs.values()))] == [("ours_s", 0)]
  assert M.main(["--report-only", "--results", str(tmp_path)]) == 0
  text = (tmp_path / M.REPORT).read_text()
  assert "**Empty output**: ours_s-seed0 reconstruct no object pixel" in text
  # Over both seeds: (2 + 0) / 2 = +1 dB; over seed 1 alone (ours_s learned): 19 - 18 = +1 dB.
  sub = text.split("neither run collapsed")[1]
  row = next(x for x in sub.splitlines() if x.startswith("| full - ours_s"))
  assert row.startswith("| full - ours_s | 1 | +1.00")


@pytest.mark.full
def test_subsets_skip_finished_runs_and_stop_at_the_limits(tmp_path, monkeypatch):
  seq, frames = [0, 0, 1, 1], [1, 2, 1, 2]
  calls = []

  def fake_run_one(base, budget, row, seed, stop, workdir, results, log=print, keep_loss=(), state=None,
                   deadline=None):
    calls.append((budget, row, seed))
    assert keep_loss == () and state is None and deadline is None
    assert stop == M.STUDY_STOP and base["train"]["stop"] == M.STUDY_STOP
    record = fake_record(budget, row, seed, [20.0, 21.0, 22.0, 23.0], seq, frames)
    record["config"] = M.essentials(M.run_config(base, budget, row, seed, stop))   # as run_one records
    M.write_json(M.run_json(results, budget, row, seed), record)
    return record

  monkeypatch.setattr(M.cli, "run_one", fake_run_one)   # where main looks it up
  args = ["--results", str(tmp_path), "--workdir", str(tmp_path / "runs"), "--budgets", "tenth"]
  M.main(args + ["--max-runs", "2"])
  assert calls == [("tenth", "full", 0), ("tenth", "ours_s", 0)]          # seed by seed, every row first
  M.main(args + ["--max-runs", "2", "--rows", "full", "no_ssm"])
  assert calls[2:] == [("tenth", "no_ssm", 0), ("tenth", "full", 1)]     # finished runs are skipped
  M.main(args + ["--time-limit-s", "0"])
  assert len(calls) == 4                                                 # no run starts after the limit
  M.main(args + ["--seeds", "0", "--extra-rows"])
  assert calls[4:] == [("tenth", "bidirectional", 0), ("tenth", "no_pf", 0)]


def test_state_exports_each_run_and_a_pause_stops_the_study(tmp_path, monkeypatch, capsys):
  """``--state DIR --hours H``: each run gets its state folder and deadline; a paused run ends the invocation."""
  from nlosjax.train import TrainingPaused
  calls = []

  def pausing_run_one(base, budget, row, seed, stop, workdir, results, log=print, keep_loss=(), state=None,
                      deadline=None):
    calls.append((row, seed, state, deadline))
    raise TrainingPaused("ours", 50, M.state_dir(state, budget, row, seed) / "model")

  monkeypatch.setattr(M.cli, "run_one", pausing_run_one)
  args = ["--results", str(tmp_path), "--workdir", str(tmp_path / "runs"), "--budgets", "full",
          "--rows", "lfe", "--seeds", "0", "1"]
  M.main(args + ["--state", str(tmp_path / "state"), "--hours", "0.5"])
  assert len(calls) == 1 and calls[0][:3] == ("lfe", 0, tmp_path / "state")   # seed 1 does not start
  assert 0 < calls[0][3] - time.time() <= 1800
  assert "full/lfe-seed0 [ours] paused at step 50" in capsys.readouterr().out
  assert M.state_dir(tmp_path / "state", "full", "lfe", 0) == tmp_path / "state" / "full" / "lfe-seed0"
  with pytest.raises(SystemExit):
    M.main(args + ["--hours", "1"])                      # --hours needs --state


@pytest.mark.full
def test_tiny_study_end_to_end_resumes_and_probes(tmp_path, monkeypatch, capsys):
  results = tmp_path / "results"
  args = ["--tiny", "--workdir", str(tmp_path / "runs"), "--results", str(results)]
  with xla_optimizations(False):          # tiny shapes compile faster without them
    assert M.main(args) == 0
  from nlosjax.evaluation import scores
  records = {}
  for row in M.TINY_DESIGN["rows"]:
    path = M.run_json(results, "full", row, 0)
    r = records[row] = strict_json(path)
    assert (r["budget"], r["row"], r["seed"]) == ("full", row, 0)
    assert r["config"]["train"]["stop"] == M.TINY_STOP
    assert r["stop_reason"] in ("plateau", "max_steps") and 2 <= r["steps_taken"] <= M.TINY_STOP["max_steps"]
    assert [p["step"] for p in r["validation_curve"]] == list(range(2, r["steps_taken"] + 1, 2))
    assert r["best_val_psnr"] == max(p["val_psnr"] for p in r["validation_curve"])
    assert r["loss_curve"][-1]["step"] == r["steps_taken"]
    n = len(r["test"]["sequence"])
    assert n == len(r["test"]["frame"]) > 0
    assert set(scores.METRICS) <= set(r["test"]["scores"])               # every per-frame key kept
    assert all(len(v) == n for v in r["test"]["scores"].values())
    assert r["machine"]["commit"]
  assert "probe" not in records["no_ssm"]

  # The probe: bypassing nothing is the model as validated (exactly), bypassing an SSM changes it.
  p = records["full"]["probe"]
  assert p["intact_psnr"] == records["full"]["best_val_psnr"]          # the validation program itself
  assert p["probe_intact_psnr"] == pytest.approx(p["intact_psnr"], abs=1e-3)  # the probe's, to rounding
  assert len(p["modules"]) == 10 and p["modules"][0]["module"] == "st_mamba0/ssm/temporal0"
  assert any(m["psnr"] != p["intact_psnr"] for m in p["modules"])
  assert all(m["drop_db"] == pytest.approx(p["probe_intact_psnr"] - m["psnr"]) for m in p["modules"])
  assert set(p["gates"]) == {"st_mamba0", "cross_prev1_0", "cross_next1_0"}
  assert all(-0.28 < g < 10 and math.isfinite(g) for g in p["gates"].values())  # SiLU >= -0.2785
  text = (results / M.REPORT).read_text()
  assert "All 2 runs of the design are present." in text and "| `st_mamba0/ssm/spatial1` |" in text
  assert "- **full - no_ssm** (`full`, seeds 0, intensity PSNR)" in text
  assert "- **full - no_ssm** (`full`, seeds 0, temporal PSNR" in text
  assert "1 test sequence(s) give no interval" in text
  assert (results / M.FIGURE).read_bytes()[:4] == b"\x89PNG"

  # Resume: a second invocation trains nothing; --report-only rewrites the same report.
  def no_run(*a, **k):
    raise AssertionError("a run with a JSON file was trained again")

  monkeypatch.setattr(M.cli, "run_one", no_run)
  capsys.readouterr()
  assert M.main(args) == 0
  assert "2 of 2 runs already have their JSON" in capsys.readouterr().out
  assert M.main(args + ["--report-only"]) == 0

  def body(t):
    return [x for x in t.splitlines() if not x.startswith(("Produced by", "- Date", "- Load", "- Code"))]

  assert body((results / M.REPORT).read_text()) == body(text)

  # --probe RUN_DIR reloads the finished run without training it and finds the same numbers.
  from nlosjax.train import loop
  monkeypatch.setattr(loop, "make_train_step", lambda *a, **k: no_run)
  with xla_optimizations(False):
    assert M.main(args + ["--probe", str(M.run_dir(tmp_path / "runs", "full", "full", 0))]) == 0
  again = strict_json(M.run_json(results, "full", "full", 0))["probe"]
  assert [m["psnr"] for m in again["modules"]] == [m["psnr"] for m in p["modules"]]
  assert again["intact_psnr"] == p["intact_psnr"] and again["gates"] == p["gates"]


def test_a_run_on_other_data_than_its_budgets_finished_runs_is_refused(tmp_path):
  """The study pairs runs sequence by sequence: a preset whose data changed must not join it."""
  record = {"budget": "full", "row": "full", "seed": 0,
            "config": {"data": {"path": "runs/data/cpu-v3.h5", "photons": [50.0, 2000.0]}}}
  M.write_json(M.run_json(tmp_path, "full", "full", 0), record)
  cfg = {"data": {"path": "runs/data/cpu-v3.h5", "photons": (50.0, 2000.0), "grid": 32}, "train": {}}
  M.check_same_data(tmp_path, "full", cfg)                      # same data (grid: not recorded there)
  M.check_same_data(tmp_path, "tenth", {**cfg, "data": {**cfg["data"], "path": "other.h5"}})
  with pytest.raises(SystemExit, match="path: 'runs/data/cpu-v3.h5' there, 'runs/data/cpu-v4.h5' now"):
    M.check_same_data(tmp_path, "full", {**cfg, "data": {**cfg["data"], "path": "runs/data/cpu-v4.h5"}})


def test_the_real_preset_trains_to_the_plateau_rule_of_the_study():
  """experiments may not import benchmarks, so the real preset repeats the study's rule: kept equal."""
  assert configs.get_config("real")["train"]["stop"] == M.STUDY_STOP


def test_a_run_with_another_recipe_than_its_rows_finished_runs_is_refused(tmp_path):
  data = {"path": "runs/data/cpu-v3-exposure-0.1.h5"}
  train = {"seed": 0, "batch_size": 4, "loss": {"object_intensity": 3.0}}
  M.write_json(M.run_json(tmp_path, "tenth", "full", 0),
               {"budget": "tenth", "row": "full", "seed": 0, "config": {"data": data, "train": train}})
  cfg = M.budget_config({"data": {"path": "runs/data/cpu-v3.h5", "photons": (50.0, 2000.0),
                                  "ambient": (50.0, 500.0)},
                         "train": {"seed": 1, "batch_size": 4, "loss": {"object_intensity": 3.0}}}, "tenth")
  assert cfg["train"]["loss"] == {"object_intensity": 1.0}          # BUDGET_LOSS over the preset's
  M.check_same_data(tmp_path, "tenth", {**cfg, "_study_row": "no_pf"})   # another row: data only
  with pytest.raises(SystemExit, match="train.loss"):
    M.check_same_data(tmp_path, "tenth", {**cfg, "_study_row": "full"})


def test_methods_without_training_are_paired_with_each_seed_of_the_learned_rows(tmp_path):
  """Each learned seed minus the one deterministic score of the method, frame by frame: the
  mean difference is the plain mean of those differences (equal frames per sequence)."""
  from experiments.studies.mechanisms.untrained import untrained_json
  rng = np.random.default_rng(1)
  seq, frames = np.repeat(np.arange(6), 4), np.tile(np.arange(1, 5), 6)
  full = {s: 20 + rng.normal(0, 1, 24) for s in M.SEEDS}
  for s in M.SEEDS:
    M.write_json(M.run_json(tmp_path, "full", "full", s), fake_record("full", "full", s, full[s], seq, frames))
  lct = 18 + rng.normal(0, 1, 24)
  csa = full[0] + 3.0                                           # 3 dB above seed 0 on every frame
  test = lambda psnr: {"sequence": list(seq), "frame": list(frames),   # noqa: E731
                       "scores": fake_record("full", "full", 0, psnr, seq, frames)["test"]["scores"]}
  M.write_json(untrained_json(tmp_path, "full"), {"budget": "full", "methods": {
      "lct": {"settings": {"options": {"snr": 0.1}, "threshold": 0.3}, "test": test(lct)},
      "csa": {"settings": {"options": {"tau_rel": 0.3, "falloff": "diffuse"}, "threshold": 0.5}, "test": test(csa)}}})
  assert M.main(["--report-only", "--results", str(tmp_path)]) == 0
  text = (tmp_path / M.REPORT).read_text()
  assert "### Methods without training, `full` budget" in text
  assert "| LCT | snr 0.1; threshold 0.3 |" in text and "| CSA | tau_rel 0.3, falloff diffuse; threshold 0.5 |" in text
  want = np.mean([full[s] - lct for s in M.SEEDS])
  line = next(x for x in text.splitlines() if x.startswith("- **full - lct**"))
  assert f"{want:+.2f} dB" in line and "called: Ours is better" in line
  row = next(x for x in text.splitlines() if x.startswith("| full - csa | 0, 1, 2 |"))
  assert f"{np.mean([full[s] - csa for s in M.SEEDS]):+.2f}" in row
  assert not any(x.startswith("| ours_s - ") for x in text.splitlines())    # no Ours-S run: no pair
  # Scored on other frames than the learned runs: refused, not paired.
  bad = {"budget": "full", "methods": {"lct": {"settings": {}, "test": {**test(lct), "frame": list(frames[::-1])}}}}
  M.write_json(untrained_json(tmp_path, "full"), bad)
  with pytest.raises(ValueError, match="other test frames"):
    M.main(["--report-only", "--results", str(tmp_path)])


@pytest.mark.full
def test_csa_volume_places_the_sparse_scan_on_its_points_of_the_full_grid():
  from nlosjax.evaluation.baselines import csa_volume
  from nlosjax.physics.methods import csa
  from tests.small_capture import three_patch_capture
  setup, full, _ = three_patch_capture()
  mask = csa.interval_mask(*setup.grid, 3)
  got = np.asarray(csa_volume(full[..., 1::3, 1::3], setup, 3, {"tau_rel": 0.1, "falloff": "diffuse"}))
  want = np.asarray(csa.csa(full * mask, setup, mask=mask, tau_rel=0.1, falloff="diffuse"))
  np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6 * float(np.max(want)))


def test_the_study_keeps_training_the_recipe_its_committed_runs_were_trained_with():
  import json

  from experiments.studies.mechanisms.records import RESULTS
  record = json.loads((RESULTS / "mechanisms" / "full" / "full-seed0.json").read_text())["config"]
  base = M.study_recipe(configs.get_config("cpu"))          # the cpu preset trains the objects' recipe now
  cfg = M.essentials(M.run_config(base, "full", "full", 0, M.study_stop(base)))
  assert cfg["model"]["width"] == record["model"]["width"] == 8
  assert cfg["train"]["loss"] == record["train"]["loss"] == {"object_intensity": 3.0}
  assert cfg["train"]["stop"] == record["train"]["stop"] == M.STUDY_STOP
  kept = M.study_recipe(configs.get_config("cpu"), ["--config.model.width=16"])   # set on the command line
  assert kept["model"]["width"] == 16 and kept["train"]["loss"] == {"object_intensity": 3.0}
  for preset in ("real", "paper"):                            # presets with their own recipe: unchanged
    assert M.study_recipe(configs.get_config(preset)) == configs.get_config(preset)

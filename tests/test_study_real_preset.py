"""The real-preset study runs a working stretch at a time: pause at the deadline, status, resume to the end."""

import pathlib

import pytest

from experiments import store
from experiments.studies.real_preset import study
from nlosjax import train as T
from nlosjax.train import RunConfig
from tests.tiny_run import tiny_config

TINY = study.Run("tiny-ours_s", "cpu", "ours_s")


@pytest.fixture
def tiny_study(tmp_path, monkeypatch):
  monkeypatch.setenv(store.ENV, str(tmp_path / "home"))
  monkeypatch.setattr(study, "STATE_DIR", tmp_path / "repo" / "experiments" / "studies" / "x" / "state")
  monkeypatch.setattr(study, "RUNS", (TINY,))

  def config(run):
    path = store.data_path("tiny.h5")
    cfg = tiny_config(path, checkpoint_every=2,
                      stop={"rule": "plateau", "every": 2, "patience": 1, "min_delta_db": 100.0,
                            "max_steps": 8})
    return cfg
  monkeypatch.setattr(study, "run_config", config)
  return tmp_path


@pytest.mark.full
def test_a_run_that_stops_on_the_balanced_psnr_trains_to_its_plateau(tiny_study, monkeypatch):
  config = study.run_config
  monkeypatch.setattr(study, "run_config", lambda run: {
      **config(run), "train": {**config(run)["train"],
                               "stop": {**config(run)["train"]["stop"], "metric": "psnr_balanced"}}})
  rows = study.run_study(log=lambda s: None)
  assert rows[0]["done"] and rows[0]["step"] == 4


@pytest.mark.full
def test_a_study_pauses_reports_hours_left_and_resumes_to_the_plateau(tiny_study, capsys):
  assert study.status(TINY)["step"] == 0
  # A stretch that ends at once: data made in the store, one step, paused and exported.
  rows = study.run_study(hours=1e-9, log=lambda s: None)
  assert store.data_path("tiny.h5").exists()
  assert rows[0]["step"] == 1 and not rows[0]["done"]
  assert (study.STATE_DIR / TINY.name / "ours_s" / "state.npz").exists()
  # The export records the data's fingerprint, so another CPU model's regenerated data can resume it.
  from nlosjax.data.dataset import dataset_fingerprint
  from nlosjax.train import run_state
  assert run_state.read_fingerprint(study.STATE_DIR / TINY.name / "ours_s") == \
      dataset_fingerprint(store.data_path("tiny.h5"))
  # The next stretch, as on a fresh machine: the store is gone, the committed state kept.
  import shutil
  shutil.rmtree(store.home())
  rows = study.run_study(log=lambda s: None)
  row = rows[0]
  # min_delta 100 dB: the second validation (step 4) cannot beat the first by that, so patience 1 stops.
  assert row["done"] and row["step"] == 4 and row["best_step"] in (2, 4)
  assert row["steps_left"] == (0, 0) and row["hours_left"] == (0.0, 0.0)
  assert row["s_per_step"] > 0
  # Each stretch says where its steps came from: commit, machine, data digest.
  lines = (study.STATE_DIR / TINY.name / "invocations.jsonl").read_text().splitlines()
  assert len(lines) == 2 and all("data_digest" in line and "commit" in line for line in lines)
  text = study.format_status(rows)
  assert "| tiny-ours_s | ours_s | 4 |" in text and "| done |" in text


def test_status_counts_the_fewest_and_most_steps_the_plateau_rule_leaves(tiny_study):
  import json
  folder = study.STATE_DIR / TINY.name / "ours_s"
  folder.mkdir(parents=True)
  # Validations at 2, 4, 6; best at 4; patience 4 (the preset's), every 2, max 3000: with no gain
  # from now, the rule stops after 4 validations past step 4, i.e. at step 12: 6 steps left.
  points = [{"step": s, "val_psnr": v, "time_s": 1.5 * s} for s, v in ((2, 10.0), (4, 12.0), (6, 11.0))]
  (folder / "validation_curve.json").write_text(json.dumps(
      {"curve": points, "best_step": 4, "best_val_psnr": 12.0, "stop_reason": None}))
  (folder / "run_state.json").write_text(json.dumps({"step": 6, "best_step": 4, "signature": "tiny"}))
  study.run_config = lambda run: tiny_config(pathlib.Path("x.h5"), stop={
      "rule": "plateau", "every": 2, "patience": 4, "min_delta_db": 0.05, "max_steps": 3000})
  row = study.status(TINY)
  assert row["steps_left"] == (6, 2994)
  assert row["s_per_step"] == pytest.approx(1.5)
  assert row["hours_left"] == (round(6 * 1.5 / 3600, 2), round(2994 * 1.5 / 3600, 2))


def test_store_paths_refuse_folders_and_follow_the_environment(monkeypatch, tmp_path):
  monkeypatch.setenv(store.ENV, str(tmp_path))
  assert store.data_path("a.h5") == tmp_path / "data" / "a.h5"
  assert store.run_path("s", "r") == tmp_path / "runs" / "s" / "r"
  for bad in ("", "../a.h5", "x/a.h5"):
    with pytest.raises(ValueError, match="file name alone"):
      store.data_path(bad)
  monkeypatch.delenv(store.ENV)
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
  assert store.home() == tmp_path / "cache" / "nlosjax"


def test_data_of_an_edited_candidate_config_are_refused_not_used(tiny_study):
  cfg = study.run_config(TINY)
  path = store.data_path("tiny.h5")
  path.parent.mkdir(parents=True)
  T.ensure_dataset(RunConfig.from_dict(cfg), path, log=lambda s: None)
  edited = {**cfg, "data": {**cfg["data"], "photons": (10.0, 20.0)}}
  with pytest.raises(ValueError, match="another data configuration"):
    T.ensure_dataset(RunConfig.from_dict(edited), path, log=lambda s: None)


def test_a_candidates_workdir_links_its_runs_and_names_both_variants(monkeypatch, tmp_path):
  import json
  monkeypatch.setenv(store.ENV, str(tmp_path))
  runs = (study.Run("c-ours_s", "experiments/configs/cand.py", "ours_s"),
          study.Run("c-ours", "experiments/configs/cand.py", "ours"))
  monkeypatch.setattr(study, "RUNS", runs + (study.Run("c-ours_s-seed1", "experiments/configs/cand.py",
                                                       "ours_s", seed=1),))     # not linked: seed 0 only
  with pytest.raises(FileNotFoundError, match="train c-ours_s first"):
    study.candidate_workdir("experiments/configs/cand.py")
  for r in runs:
    (study.workdir(r) / r.variant / "checkpoints").mkdir(parents=True)
    (study.workdir(r) / "config.json").write_text(json.dumps({"train": {"variants": [r.variant]}, "x": 1}))
  out = study.candidate_workdir("experiments/configs/cand.py")
  assert out == store.run_path(study.STUDY, "cand")
  assert json.loads((out / "config.json").read_text()) == {"train": {"variants": ["ours_s", "ours"]}, "x": 1}
  for r in runs:
    assert (out / r.variant).resolve() == (study.workdir(r) / r.variant).resolve()
  assert study.candidate_workdir("experiments/configs/cand.py") == out           # again: links replaced
  with pytest.raises(ValueError, match="no run of"):
    study.candidate_workdir("experiments/configs/other.py")


def test_alignment_folds_accumulate_across_stretches_and_machines(tmp_path, monkeypatch):
  """One fold a stretch past the deadline; a fresh store gets the committed folds back and
  only the missing ones run; the status counts folds from the committed state alone.

  The stage itself is replaced by a recorder (tests/test_align_cli.py tests the CLI's folds,
  tests/test_align.py the stage).
  """
  import json
  import shutil

  import numpy as np

  from experiments.studies import align as cli
  from experiments.studies import alignment as stage
  from nlosjax.evaluation import protocol
  monkeypatch.setenv(store.ENV, str(tmp_path / "home"))
  monkeypatch.setattr(study, "STATE_DIR", tmp_path / "repo" / "state")
  a = study.Alignment("align-x", "pretrained:real", "ours_s")
  monkeypatch.setattr(study, "ALIGNMENTS", (a,))
  monkeypatch.setattr(T, "ensure_dataset", lambda config, path, log: None)
  monkeypatch.setattr(protocol, "validation_psnr", lambda config, path: None)
  monkeypatch.setattr(cli, "load_source", lambda source, variants: (
      tiny_config("unused.h5"), {"ours_s": ("mcfg", {"w": np.zeros(2)})}))
  files = [tmp_path / f"data_{s}.mat" for s in ("p", "q", "r")]
  monkeypatch.setattr(cli, "measured_inputs", lambda fs, mcfg: {
      f.stem[len("data_"):]: np.full((1, 1), i, np.float32) for i, f in enumerate(fs)})
  calls = []

  def fake_align(config, data_path, mcfg, params, measured, folder, **kw):
    calls.append((folder.name, sorted(np.unique(measured).tolist())))
    folder.mkdir(parents=True)
    np.savez(folder / "params.npz", w=params["w"] + 1)
    (folder / "align.json").write_text(json.dumps({"seconds": 600.0}))
    return params, {}
  monkeypatch.setattr(stage, "align", fake_align)

  rows = study.run_alignments(files, hours=1e-9, log=lambda s: None)        # deadline past: one fold
  assert calls == [("ours_s-without-p", [1.0, 2.0])]                        # never its own scan (0)
  assert rows[0]["done"] == ["p"] and rows[0]["left"] == 2 and rows[0]["hours_left"] == pytest.approx(0.33)
  assert (study.STATE_DIR / "align" / "ours_s-without-p" / "params.npz").exists()
  shutil.rmtree(store.home())                                               # a new machine
  rows = study.run_alignments(files, log=lambda s: None)
  assert [c[0] for c in calls] == ["ours_s-without-p", "ours_s-without-q", "ours_s-without-r"]
  assert rows[0]["done"] == ["p", "q", "r"] and rows[0]["left"] == 0
  assert (study.alignment_workdir(a) / "ours_s-without-p" / "params.npz").exists()   # restored
  assert "| align-x | `pretrained:real` | ours_s | 1.0 | 3 | 0 | 600 | 0 |" in study.format_alignment_status(rows)
  b = study.Alignment("align-y", "pretrained:real", "ours_s", "balanced", "align-y")   # not started: a's rate
  monkeypatch.setattr(study, "ALIGNMENTS", (a, b))
  row = study.alignment_status(b, ["p", "q", "r"])
  assert row["done"] == [] and row["estimated"] and row["hours_left"] == pytest.approx(0.5)
  assert "| align-y | `pretrained:real` | ours_s | balanced | 0 | 3 | 600 (est.) | 0.5 (est.) |" in \
      study.format_alignment_status([row])
  assert study.alignment_workdir(b) != study.alignment_workdir(a)
  with pytest.raises(ValueError, match="unknown alignment"):
    study.run_alignments(files, ["nope"])


def test_the_objects_recipe_takes_the_cpu_presets_four_keys_and_leaves_the_rest():
  from experiments import configs
  base = next(r for r in study.RUNS if r.name == "v5-ours_s")
  probe = next(r for r in study.RUNS if r.name == "v5-ours_s-objects")
  a, b = study.run_config(base), study.run_config(probe)
  cpu = configs.get_config("cpu")
  assert b["model"]["width"] == cpu["model"]["width"] == 16
  assert b["train"]["loss"]["balance"] == 1.0 and b["train"]["loss"]["object_intensity"] == 0.0
  assert b["train"]["stop"] == {**a["train"]["stop"], "metric": "psnr_balanced"}      # the plateau rule kept
  assert a["model"]["width"] == 8 and a["train"]["loss"]["object_intensity"] == 3.0
  for d in (a, b):                                  # everything else equal
    del d["model"]["width"], d["train"]["loss"], d["train"]["stop"]
  assert a == b
  assert probe.probe and not base.probe
  with pytest.raises(ValueError, match="unknown recipe"):
    study.apply_recipe(a, "bright")

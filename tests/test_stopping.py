"""Training until learning stops: the plateau rule, its resumable curve, and the unchanged default.

The rule is tested as a pure function of a hand-made validation sequence, then
inside :func:`nlosjax.train.train_model` on the tiny config (``ours_s``, a few
steps; every plateau run here has ``max_steps = 8``, so the runs share one
optimiser and one compiled train step).
"""

import json
import math

import jax
import numpy as np
import pytest

from nlosjax import train as T
from nlosjax.train import RunConfig, loop, stopping
from tests.tiny_run import make_tiny_dataset, tiny_config

MAX_STEPS = 8
#: A warm-up + cosine schedule, so that the schedule's horizon shows in the losses.
OPTIM = {"learning_rate": 1e-3, "warmup_steps": 2, "cosine": True}


@pytest.fixture(scope="module")
def data_path(tmp_path_factory):
  return make_tiny_dataset(tmp_path_factory)


def plateau(**kw):
  return {"rule": "plateau", "every": 2, "patience": 1, "min_delta_db": 0.05, "max_steps": MAX_STEPS, **kw}


def quiet(s):
  return None


def assert_same_tree(a, b):
  jax.tree.map(lambda x, y: np.testing.assert_array_equal(np.asarray(x), np.asarray(y)), a, b)


# ------------------------------------------------------------------ the rule, pure
def test_the_rule_stops_where_a_hand_made_sequence_says():
  # patience 2, margin 0.1 dB: 10 -> 11 improves; 11.05 and 11.08 are within 0.1 of 11.
  s = [10.0, 11.0, 11.05, 11.08]
  assert [stopping.plateau_reached(s[:n], 2, 0.1) for n in range(1, 5)] == [False, False, False, True]
  # An improvement by more than the margin inside the window keeps it going.
  assert not stopping.plateau_reached([10.0, 11.0, 11.05, 11.2], 2, 0.1)
  # Exactly the margin does not count as an improvement ("by more than").
  assert stopping.plateau_reached([10.0, 10.5], 1, 0.5)
  assert not stopping.plateau_reached([10.0, 10.5 + 1e-9], 1, 0.5)
  # A late drop does not reset anything: the best before the window is what must be beaten.
  assert stopping.plateau_reached([12.0, 9.0, 11.9], 2, 0.0)
  # NaN never counts as a best.
  assert stopping.plateau_reached([10.0, math.nan], 1, 0.0)
  assert stopping.best_index([10.0, math.nan, 11.0, 11.0]) == 2          # earliest of equal bests


def test_simulated_runs_stop_at_the_plateau_or_at_max_steps():
  rule = T.StopRule(rule="plateau", every=50, patience=4, min_delta_db=0.05, max_steps=3000)
  # Rises by 1 dB per validation until step 500, then flat: the 4 validations after 500 fail.
  steps, reason, validated = stopping.simulate(rule, lambda s: min(s, 500) / 50.0)
  assert (steps, reason) == (700, "plateau") and validated[-1] == 700 and validated[:2] == [50, 100]
  # Always improving by more than the margin: max_steps, which is validated even off the grid.
  rule = T.StopRule(rule="plateau", every=40, patience=2, min_delta_db=0.05, max_steps=100)
  assert stopping.simulate(rule, float) == (100, "max_steps", [40, 80, 100])
  assert stopping.stop_reason(rule, [1.0, 1.0, 1.0], 100) == "plateau"    # plateau wins a tie
  assert stopping.stop_reason(T.StopRule(), [1.0] * 9, 10**6) is None     # "steps": the loop's range ends it


def test_stop_rules_are_checked_and_reach_the_cli():
  assert T.StopRule.from_config(None) == T.StopRule.from_config({}) == T.StopRule()
  assert T.StopRule().horizon(350) == 350 and T.StopRule(rule="plateau").horizon(350) == 3000
  with pytest.raises(ValueError, match="unknown key"):
    T.StopRule.from_config({"rule": "plateau", "patiense": 3})
  for bad in ({"rule": "loss"}, {"every": 0}, {"patience": 1.5}, {"min_delta_db": -1}):
    with pytest.raises(ValueError, match="train.stop"):
      T.StopRule.from_config(bad)
  from experiments.cli import load_config
  cfg = load_config("cpu", ["--config.train.stop.rule=plateau", "--config.train.stop.patience=6"])
  assert T.StopRule.from_config(cfg["train"]["stop"]) == T.StopRule(rule="plateau", patience=6, metric="psnr_balanced")
  with pytest.raises(SystemExit, match="config.train.stop has no key 'patients' .did you mean 'patience'"):
    load_config("cpu", ["--config.train.stop.patients=6"])


def test_the_learning_rate_spans_max_steps_under_the_plateau_rule():
  optim = T.OptimConfig(learning_rate=1e-3, warmup_steps=20, cosine=True, end_fraction=0.1)
  assert T.learning_rate_at(optim, 3000, 20) == pytest.approx(1e-3)
  assert T.learning_rate_at(optim, 3000, 2999) == pytest.approx(1e-4, rel=1e-3)
  assert T.learning_rate_at(optim, 3000, 1510) == pytest.approx(5.5e-4, rel=1e-2)   # cosine midpoint
  assert T.learning_rate_at(T.OptimConfig(), 10, 5) == pytest.approx(1e-4)           # constant default


# ------------------------------------------------------------------ inside train_model
@pytest.mark.full
def test_a_plateau_run_stops_where_its_validations_say_and_keeps_the_best(data_path, tmp_path):
  scores = iter([5.0, 6.5, 6.0])               # steps 2, 4, 6: 6.0 does not beat 6.5 + 0.05
  calls = []

  def validate(mcfg, params):
    calls.append(1)
    return next(scores)

  cfg = tiny_config(data_path, stop=plateau(), optim=OPTIM)
  _, state = T.train_model(RunConfig.from_dict(cfg), data_path, tmp_path, "ours_s", validate=validate, log=quiet)
  folder = tmp_path / "ours_s"
  curve = T.read_curve(folder)
  assert [p["step"] for p in curve["curve"]] == [2, 4, 6] and len(calls) == 3
  assert [p["val_psnr"] for p in curve["curve"]] == [5.0, 6.5, 6.0]
  assert curve["stop_reason"] == "plateau" and curve["steps_taken"] == 6 and curve["best_step"] == 4
  assert all(p["time_s"] >= 0 and p["lr"] > 0 for p in curve["curve"])
  sel = T.read_selection(folder)
  assert (sel["select"], sel["step"], sel["steps_taken"], sel["stop_reason"]) == ("plateau", 4, 6, "plateau")
  assert sel["val_psnr"] == {2: 5.0, 4: 6.5, 6: 6.0}
  assert [r["step"] for r in T.read_metrics(folder / "metrics.jsonl")] == list(range(1, 7))
  # The model returned is the best on validation: step 4's checkpoint, not the last one.
  assert int(state.step) == 4
  ckpt = T.Checkpointer(folder / "checkpoints", "unused", every=2)
  assert 4 in ckpt.all_steps()
  item = ckpt.manager.restore(4, args=ckpt._ocp.args.Composite(state=ckpt._ocp.args.StandardRestore()))
  assert_same_tree(jax.tree.map(np.asarray, item["state"]["params"]), T.to_host(state.params))
  ckpt.close()

  # The schedule spans max_steps, so a plateau run is the start of the fixed-length run of
  # max_steps steps: the same losses step by step.
  fixed = tiny_config(data_path, steps=MAX_STEPS, optim=OPTIM)
  T.train_model(RunConfig.from_dict(fixed), data_path, tmp_path / "fixed", "ours_s", log=quiet)
  a = T.read_metrics(folder / "metrics.jsonl")
  b = T.read_metrics(tmp_path / "fixed" / "ours_s" / "metrics.jsonl")[:6]
  assert [r["loss"] for r in a] == [r["loss"] for r in b]


def test_a_plateau_run_on_the_balanced_psnr_decides_on_it_and_keeps_every_score(data_path, tmp_path):
  """The callback returns every score; the rule stops and chooses on ``metric`` alone: the hand-made
  whole-image PSNRs would stop at step 6 and keep step 4, the balanced ones keep rising to step 8."""
  psnr = iter([5.0, 6.5, 6.0, 6.2])
  balanced = iter([3.0, 3.5, 4.0, 4.5])
  validate = lambda mcfg, params: {"psnr": next(psnr), "psnr_balanced": next(balanced), "f1": 0.5}  # noqa: E731
  cfg = tiny_config(data_path, stop=plateau(metric="psnr_balanced"), optim=OPTIM)
  _, state = T.train_model(RunConfig.from_dict(cfg), data_path, tmp_path, "ours_s", validate=validate, log=quiet)
  curve = T.read_curve(tmp_path / "ours_s")
  assert [(p["step"], p["val_psnr"], p["score"]) for p in curve["curve"]] == \
      [(2, 5.0, 3.0), (4, 6.5, 3.5), (6, 6.0, 4.0), (8, 6.2, 4.5)]
  assert curve["curve"][0]["val"] == {"psnr": 5.0, "psnr_balanced": 3.0, "f1": 0.5}
  assert (curve["stop_reason"], curve["best_step"], curve["best_score"]) == ("max_steps", 8, 4.5)
  assert curve["rule"]["metric"] == "psnr_balanced" and int(state.step) == 8
  sel = T.read_selection(tmp_path / "ours_s")
  assert (sel["metric"], sel["step"], sel["val_score"]) == ("psnr_balanced", 8, {2: 3.0, 4: 3.5, 6: 4.0, 8: 4.5})
  # The default rule records as before; a number cannot feed a rule on another metric.
  assert "metric" not in T.StopRule(rule="plateau").to_dict()
  with pytest.raises(ValueError, match="dict of scores"):
    T.StopRule(rule="plateau", metric="psnr_balanced").score(5.0)
  with pytest.raises(ValueError, match="metric must be one of"):
    T.StopRule(metric="ssim")


@pytest.mark.full
def test_a_killed_plateau_run_resumes_to_the_same_curve_and_parameters(data_path, tmp_path, monkeypatch):
  from nlosjax.evaluation import protocol
  cfg = tiny_config(data_path, stop=plateau(patience=2, min_delta_db=0.0), optim=OPTIM)
  config = RunConfig.from_dict(cfg)
  real = protocol.validation_psnr(config, data_path)
  _, straight = T.train_model(config, data_path, tmp_path / "a", "ours_s", validate=real, log=quiet)

  class Kill(Exception):
    pass

  # Kill 1: inside step 5 (steps 1-4 done, the checkpoint and curve of step 4 written).
  make_step = loop.make_train_step

  def killing_step(*args, **kwargs):
    fn = make_step(*args, **kwargs)

    def step(state, batch, key):
      if int(state.step) == 4:
        raise Kill
      return fn(state, batch, key)
    return step

  monkeypatch.setattr(loop, "make_train_step", killing_step)
  with pytest.raises(Kill):
    T.train_model(config, data_path, tmp_path / "b", "ours_s", validate=real, log=quiet)
  monkeypatch.setattr(loop, "make_train_step", make_step)
  assert [p["step"] for p in T.read_curve(tmp_path / "b" / "ours_s")["curve"]] == [2, 4]

  # Kill 2: during the validation of step 6 (its checkpoint saved, its curve point not).
  def killing_validate(mcfg, params):
    raise Kill

  messages = []
  with pytest.raises(Kill):
    T.train_model(config, data_path, tmp_path / "b", "ours_s", validate=killing_validate,
                  log=messages.append)
  assert any("resumed from step 4" in m for m in messages)
  assert [p["step"] for p in T.read_curve(tmp_path / "b" / "ours_s")["curve"]] == [2, 4]

  messages = []
  _, resumed = T.train_model(config, data_path, tmp_path / "b", "ours_s", validate=real,
                             log=messages.append)
  assert any("resumed from step 6" in m for m in messages)
  ca, cb = (T.read_curve(tmp_path / x / "ours_s") for x in ("a", "b"))
  assert [(p["step"], p["val_psnr"]) for p in ca["curve"]] == [(p["step"], p["val_psnr"]) for p in cb["curve"]]
  for key in ("steps_taken", "stop_reason", "best_step", "best_val_psnr"):
    assert ca[key] == cb[key], key
  assert T.read_selection(tmp_path / "a" / "ours_s") == T.read_selection(tmp_path / "b" / "ours_s")
  assert int(resumed.step) == int(straight.step)
  assert_same_tree(T.to_host(straight.params), T.to_host(resumed.params))
  la, lb = (T.read_metrics(tmp_path / x / "ours_s" / "metrics.jsonl") for x in ("a", "b"))
  assert [(r["step"], r["loss"]) for r in la] == [(r["step"], r["loss"]) for r in lb]

  # A finished run is not retrained: no step, no validation, the same best model.
  def no_step(*args, **kwargs):
    raise AssertionError("a finished run took a training step")

  monkeypatch.setattr(loop, "make_train_step", lambda *a, **k: no_step)
  before = (tmp_path / "b" / "ours_s" / "metrics.jsonl").read_text()
  _, again = T.train_model(config, data_path, tmp_path / "b", "ours_s", validate=killing_validate,
                           log=quiet)
  assert (tmp_path / "b" / "ours_s" / "metrics.jsonl").read_text() == before
  assert_same_tree(T.to_host(straight.params), T.to_host(again.params))


@pytest.mark.full
def test_the_default_rule_is_unchanged(data_path, tmp_path):
  cfg = tiny_config(data_path, steps=MAX_STEPS, optim=OPTIM)
  assert "stop" not in cfg["train"] and T.StopRule().rule == "steps"
  assert RunConfig.from_dict(cfg).train.stop == T.StopRule()             # a config silent on the rule
  default_cfg = cfg
  explicit = tiny_config(data_path, steps=MAX_STEPS, optim=OPTIM, stop={"rule": "steps"})
  _, a = T.train_model(RunConfig.from_dict(default_cfg), data_path, tmp_path / "a", "ours_s", log=quiet)
  _, b = T.train_model(RunConfig.from_dict(explicit), data_path, tmp_path / "b", "ours_s", validate=lambda m,
                       p: 1 / 0, log=quiet)
  assert int(a.step) == int(b.step) == MAX_STEPS
  assert_same_tree(T.to_host(a.params), T.to_host(b.params))
  for run in ("a", "b"):
    folder = tmp_path / run / "ours_s"
    assert sorted(p.name for p in folder.iterdir()) == ["checkpoints", "metrics.jsonl", "selection.json"]
    assert json.loads((folder / "selection.json").read_text()) == {"select": "last", "step": MAX_STEPS,
                                                                  "val_psnr": {}}
  with pytest.raises(ValueError, match="needs the validate callback"):
    T.train_model(RunConfig.from_dict(tiny_config(data_path, stop=plateau(), optim=OPTIM)), data_path,
                  tmp_path / "c", "ours_s", log=quiet)


def test_the_main_job_caption_names_how_long_its_models_trained():
  from experiments.main_job import _training_length
  assert _training_length(T.TrainConfig.from_dict({"steps": 350})) == "350 steps"
  text = _training_length(T.TrainConfig.from_dict(
      {"steps": 350, "stop": {"rule": "plateau", "every": 25, "max_steps": 900}}))
  assert "plateau" in text and "900" in text and "25 steps apart" in text and "350" not in text

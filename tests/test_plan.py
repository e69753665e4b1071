"""The dry run (``nlosjax.plan``, ``experiments.train --dry-run``) and the paper recipe."""

import dataclasses

import jax
import numpy as np
import pytest

from experiments import configs
from experiments import train as train_cli
from nlosjax import plan
from nlosjax import train as T
from nlosjax.models.network import ModelConfig
from nlosjax.train import RunConfig
from tests.tiny_run import tiny_config
from tests.xla_options import xla_optimizations


@pytest.fixture(autouse=True, scope="module")
def _fast_compiles():
  """Tiny shapes compile faster without XLA's optimisations; the checks are invariants of any plan."""
  with xla_optimizations(False):
    yield


def test_paper_recipe_is_explicit_and_matches_model_config_paper(tmp_path):
  cfg = configs.get_config("paper")
  tr = cfg["train"]
  assert (tr["batch_size"], tr["optim"]["learning_rate"], tr["optim"]["weight_decay"]) == (4, 1e-4, 0.95)
  # 150 training sequences x 30 triplets / batch 4 per epoch, 40 epochs.
  assert tr["steps"] == 40 * 150 * 30 // 4 and tr["checkpoint_every"] == 150 * 30 // 4
  assert tr["check_memory"] and tr["select_checkpoint"] == "val"
  paper = ModelConfig.paper()
  for key, value in cfg["model"].items():
    if key != "volume_activation":                     # softplus: the cpu preset's choice (config)
      assert getattr(paper, key) == value, key
  # The model section builds exactly ModelConfig.paper() on the preset's data.
  setup = T.RunConfig.from_dict(cfg).data.spec().setup
  mcfg = T.model_config_for(RunConfig.from_dict(cfg), setup, "ours")
  assert dataclasses.replace(mcfg, volume_activation="relu") == paper


def test_estimate_step_time_from_measured_points():
  pts = [{"factor": 4, "flops": 1e9, "step_s": 0.3}, {"factor": 2, "flops": 5e9, "step_s": 1.1}]
  # Through the two points: 0.1 s + 0.2 s per GFLOP.
  assert plan.estimate_step_s(pts, 20e9) == pytest.approx(0.1 + 0.2 * 20)
  assert plan.estimate_step_s(pts[:1], 20e9) == pytest.approx(0.3 * 20)
  assert plan.estimate_step_s(pts + [{"factor": 1, "flops": 20e9, "step_s": 7.0}], 20e9) == 7.0


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
  path = tmp_path_factory.mktemp("plan") / "never-made.h5"
  return tiny_config(path, batch_size=2, steps=10, variants=("ours_s",))


def _hoisted_constant_bytes(config, mcfg, variant, state, batch) -> int:
  """Bytes of the train step's captured constants that JAX itself passes as arguments (0 up to JAX 0.10).

  From JAX 0.12 (``jax_use_simplified_jaxpr_constants`` on by default; a transitional flag, so absent
  means on) a jitted function's captured arrays over ``jax_embedded_constants_max_bytes`` become
  arguments of the program, counted in XLA's ``argument_size_in_bytes`` (at the tiny run, a 64 x 32
  float32 matrix of the depth resampling). Counted here from the traced jaxpr's constants, not from XLA.
  """
  if not getattr(jax.config, "jax_use_simplified_jaxpr_constants", True):
    return 0
  _, weights = T.training_recipe(config, variant)
  step = T.make_train_step(mcfg, weights, T.make_mesh())
  key = jax.eval_shape(lambda: jax.random.key(0))
  consts = step.jitted.trace(state, batch, key, step.table).jaxpr.consts
  limit = jax.config.jax_embedded_constants_max_bytes
  hoisted = {id(c): c for c in consts if np.ndim(c) > 0 and getattr(c, "nbytes", 0) > limit}
  return sum(int(c.nbytes) for c in hoisted.values())


@pytest.mark.full
def test_dry_run_plans_from_shapes_and_measures_without_data(tiny):
  config = T.RunConfig.from_dict(tiny)
  result = plan.dry_run(config, log=lambda s: None)
  assert not __import__("pathlib").Path(tiny["data"]["path"]).exists()      # no data generated
  for variant, v in result["variants"].items():
    p = v["train"]
    mcfg = v["model_config"]
    # Arguments of the train step: the state (params + AdamW's two moments + counts), the
    # batch and the physics operators (an argument, not constants), counted here from shapes
    # independently of XLA.
    state = T.abstract_train_state(T.network(mcfg), mcfg.input_shape(2), T.make_optimizer(T.OptimConfig(), 10),
                                   T.make_mesh())
    batch = plan._abstract_batch(mcfg, 2, T.make_mesh())
    ops = mcfg.physics_operators()
    nbytes = sum(np.prod(x.shape) * x.dtype.itemsize
                 for x in jax.tree.leaves((state, batch, ops)) if hasattr(x, "shape"))
    nbytes += _hoisted_constant_bytes(config, mcfg, variant, state, batch)
    assert abs(p.argument_bytes - nbytes) <= 64, (p.argument_bytes, nbytes)
    assert p.alias_bytes > 0                              # the donated state is reused
    assert p.peak_bytes >= p.argument_bytes and p.temp_bytes > 0 and p.flops > 0
    assert v["fits"] and v["step_s"] > 0 and v["run_s"] == pytest.approx(10 * v["step_s"])
    assert v["inference"].batch == 2 and v["inference"].peak_bytes > 0
  report = plan.format_plan(result)
  assert "ours_s" in report and "fits." in report


def test_a_plan_over_the_device_memory_is_refused_with_the_fix(tiny, monkeypatch):
  monkeypatch.setattr(plan, "device_memory", lambda device=None: (2 ** 20, "test"))
  with pytest.raises(plan.DoesNotFit, match="train.batch_size|remat") as e:
    plan.check_fits(T.RunConfig.from_dict(tiny), log=lambda s: None)
  assert "more devices" in str(e.value) and "check_memory=False" in str(e.value)
  # The main job refuses before making any data.
  from experiments.main_job import train_and_evaluate
  cfg = {**tiny, "train": {**tiny["train"], "check_memory": True}}
  with pytest.raises(plan.DoesNotFit):
    train_and_evaluate(T.RunConfig.from_dict(cfg), tiny["data"]["path"] + ".work", log=lambda s: None)
  assert not __import__("pathlib").Path(tiny["data"]["path"]).exists()


def test_train_cli_dry_run_exits_cleanly_without_data(tiny, tmp_path, capsys, monkeypatch):
  cfg_file = tmp_path / "tiny_cfg.py"
  cfg_file.write_text(f"def get_config():\n  return {tiny!r}\n")
  train_cli.main(["--config", str(cfg_file), "--dry-run", "--no-measure"])
  out = capsys.readouterr().out
  assert "planned peak" in out and "ours_s" in out and "fits." in out
  assert not __import__("pathlib").Path(tiny["data"]["path"]).exists()

"""The typed run config (nlosjax.train.config): one schema per section, one reader of a preset's dict."""

import dataclasses
import pathlib
import re

import pytest

from experiments import cli, configs
from nlosjax import losses
from nlosjax import train as T
from nlosjax.train import config as C

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("preset", configs.PRESETS)
def test_every_preset_reads_into_typed_sections_with_its_own_values(preset):
  d = T.with_defaults(configs.get_config(preset))
  cfg = T.RunConfig.from_dict(d)
  for key, value in d["train"].items():          # the dict, read by hand, is the reference
    got = getattr(cfg.train, key)
    if key == "optim":
      assert got == T.OptimConfig(**value)
    elif key == "loss":
      assert got == losses.LossWeights(**value)
    elif key == "stop":
      assert got == T.StopRule(**value)
    elif key == "variants":
      assert got == tuple(value)
    else:
      assert got == value, key
  assert cfg.data.stride() == d["data"]["input_stride"]
  assert cfg.data.input_offset == d["data"]["input_stride"] // 2
  assert cfg.data.path == d["data"]["path"]
  assert dict(cfg.model) == d["model"]
  assert cfg.data.spec().setup.num_bins == d["data"]["num_bins"]
  assert T.RunConfig.from_dict(cfg) is cfg                  # a RunConfig passes through unchanged
  assert T.require_run_config(cfg) is cfg
  assert sorted(cfg.extra) == sorted(set(d) - {"data", "model", "train", "usm", "lfe", "ik"})


@pytest.mark.parametrize("path", [("train",), ("train", "optim"), ("train", "loss"), ("train", "stop"),
                                  ("model",), ("data",), ("data", "scene"), ("data", "loader"),
                                  ("data", "physics"), ("usm",), ("usm", "model"), ("lfe", "optim"),
                                  ("ik", "model")])
def test_a_key_no_section_reads_is_refused_with_the_known_ones(path):
  d = T.with_defaults(configs.get_config("cpu"))
  node = d
  for p in path:
    node[p] = dict(node.get(p) or {})
    node = node[p]
  node["not_a_key"] = 1
  with pytest.raises(ValueError, match=re.escape(".".join(path)) + r".*'not_a_key'.*known"):
    T.RunConfig.from_dict(d)


def test_the_command_line_overrides_use_the_readers_schema():
  # every key the reader knows is an override the command line takes, and nothing else
  for path in [("train",), ("usm",), ("usm", "model"), ("data", "loader"), ("model",)]:
    assert cli._schema(path) == C.section_schema(path)
  assert cli._schema(())[1] == C.section_schema(())[1]
  config = cli.apply_overrides(cli.load_config("cpu"), ["--config.train.eval_batch_size=2",
                                                       "--config.lfe.optim.learning_rate=1e-3"])
  cfg = T.RunConfig.from_dict(T.with_defaults(config))
  assert cfg.train.eval_batch == 2
  assert T.training_recipe(cfg, "lfe")[0].learning_rate == 1e-3


def test_training_recipe_merges_a_baselines_optimiser_over_ours_as_the_dicts_did():
  d = T.with_defaults(configs.get_config("cpu"))
  d["usm"] = {**d["usm"], "optim": {"learning_rate": 3e-4}}
  d["ik"] = {"optim": {"warmup_steps": 7}}
  for variant, section in (("usm", d["usm"]), ("ik", d["ik"]), ("lfe", {})):
    twin = T.OptimConfig(**{**d["train"]["optim"], **section.get("optim", {})})   # the former dict merge
    assert T.training_recipe(T.RunConfig.from_dict(d), variant) == (twin, losses.LossWeights(**d["train"]["loss"]))
  assert T.training_recipe(T.RunConfig.from_dict(d), "ours")[0] == T.OptimConfig(**d["train"]["optim"])
  d["usm"]["recipe"] = "published"
  from nlosjax.models.usm import PUBLISHED_OPTIM
  assert T.training_recipe(T.RunConfig.from_dict(d), "usm")[0] == T.OptimConfig(**PUBLISHED_OPTIM)
  d["usm"]["recipe"] = "own"
  with pytest.raises(ValueError, match="usm.recipe"):
    T.RunConfig.from_dict(d)


def test_eval_batch_falls_back_to_the_training_batch_where_the_section_is_silent():
  assert T.RunConfig.from_dict({"train": {"batch_size": 3}}).train.eval_batch == 3
  assert T.RunConfig.from_dict(T.with_defaults({"train": {"batch_size": 3}})).train.eval_batch == 8


def test_sections_are_checked_where_they_are_read_and_not_before():
  # a config with only what a caller reads is enough: the Setup keys are read by setup() alone
  cfg = T.RunConfig.from_dict({"data": {"input_stride": 4}})
  assert cfg.data.stride() == 4 and cfg.data.input_offset == 2
  with pytest.raises(KeyError):
    cfg.data.setup()
  with pytest.raises(ValueError, match="input_stride"):
    T.RunConfig.from_dict({}).data.stride()
  with pytest.raises(ValueError, match="offset 2 for stride 4"):
    T.RunConfig.from_dict({"data": {"input_stride": 4, "input_offset": 0}})
  with pytest.raises(ValueError, match="select_checkpoint"):
    T.RunConfig.from_dict({"train": {"select_checkpoint": "best"}})
  with pytest.raises(ValueError, match="unknown variant"):
    T.RunConfig.from_dict({"train": {"variants": ("ours", "nlost")}})


def test_the_typed_sections_are_frozen():
  cfg = T.RunConfig.from_dict(T.with_defaults(configs.get_config("cpu")))
  with pytest.raises(dataclasses.FrozenInstanceError):
    cfg.train.steps = 1
  with pytest.raises(TypeError):
    cfg.model["width"] = 3


def test_the_library_indexes_no_config_dict():
  """nlosjax reads a config through its typed sections only (issue 63): no ``config["..."]``."""
  hits = [f"{p.relative_to(ROOT)}:{i}" for p in sorted((ROOT / "nlosjax").rglob("*.py"))
          for i, line in enumerate(p.read_text().splitlines(), 1)
          if re.search(r"\bconfig\[", line) or re.search(r"\bconfig\.get\(", line)]
  allowed = {"nlosjax/train/config.py"}                 # the one reader
  assert [h for h in hits if h.split(":")[0] not in allowed] == []


@pytest.mark.parametrize("preset", configs.PRESETS)
def test_to_dict_reads_back_to_the_same_config_also_through_json(preset):
  import json

  cfg = T.RunConfig.from_dict(T.with_defaults(configs.get_config(preset)))
  d = cfg.to_dict()
  assert T.RunConfig.from_dict(d) == cfg
  d["data"]["grid"] = -1                        # a plain copy: editing it leaves the config alone
  assert cfg.data.section["grid"] != -1
  back = T.RunConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))    # a run's config.json
  assert back.train == cfg.train                 # (lists where tuples were: the models they build agree)
  setup = cfg.data.spec().setup
  for variant in ("ours", "usm"):
    assert T.model_config_for(back, setup, variant) == T.model_config_for(cfg, setup, variant)


def test_the_paper_preset_model_is_model_config_paper_itself():
  from experiments.configs import paper
  from nlosjax.models.network import ModelConfig
  cfg = T.RunConfig.from_dict(T.with_defaults(configs.get_config("paper")))
  built = T.model_config_for(cfg, cfg.data.spec().setup, "ours")
  assert built == ModelConfig.paper(volume_activation="softplus")
  want = ModelConfig.paper()
  rebuilt = ModelConfig(setup=want.setup, stride=want.stride, frames=want.frames, **paper.model_section(want))
  assert rebuilt == want
  assert paper.model_section(ModelConfig(setup=want.setup, stride=8)) == {}    # the defaults: nothing to say


def test_the_library_takes_a_run_config_and_refuses_a_dict_naming_the_fix(tmp_path):
  """Every function of the library that reads a run's config takes the typed config only: a preset's
  dict raises ``TypeError`` naming the function and the one reader, before any work is done."""
  from nlosjax import inference, plan
  from nlosjax.evaluation import protocol
  from nlosjax.train import sharding
  d = T.with_defaults(configs.get_config("cpu"))
  typed = T.read_preset(configs.get_config("cpu"))
  assert typed == T.RunConfig.from_dict(d)                  # read_preset: the defaults filled, then read
  setup = typed.data.setup()
  calls = {
      "model_config_for": lambda c: T.model_config_for(c, setup, "ours"),
      "make_loader": lambda c: T.make_loader(c, tmp_path / "absent.h5", "train", batch_size=1, shuffle=False,
                                             seed=0),
      "ensure_dataset": lambda c: T.ensure_dataset(c, tmp_path / "absent.h5"),
      "train_model": lambda c: T.train_model(c, tmp_path / "absent.h5", tmp_path, "ours"),
      "training_recipe": lambda c: T.training_recipe(c, "ours"),
      "mesh_for": lambda c: sharding.mesh_for(c),
      "training_setup": lambda c: inference.training_setup(c),
      "load_split": lambda c: protocol.load_split(c, tmp_path / "absent.h5", "val", batch_size=1),
      "validation_psnr": lambda c: protocol.validation_psnr(c, tmp_path / "absent.h5"),
      "tune_model_thresholds": lambda c: protocol.tune_model_thresholds(c, tmp_path / "absent.h5", {}),
      "evaluate": lambda c: protocol.evaluate(c, tmp_path / "absent.h5", {}),
      "check_fits": lambda c: plan.check_fits(c),
      "dry_run": lambda c: plan.dry_run(c),
      "plan_variant": lambda c: plan.plan_variant(c, setup, "ours", None),
      "measure_reduced": lambda c: plan.measure_reduced(c, setup, "ours", None),
      "compile_train_step": lambda c: plan.compile_train_step(c, None, "ours", None),
  }
  for name, call in calls.items():
    with pytest.raises(TypeError, match=f"{name} takes a nlosjax.train.RunConfig, got dict.*read_preset"):
      call(d)
  assert not list(tmp_path.iterdir())                       # nothing written, no dataset made
  assert T.training_recipe(typed, "ours")[0] == T.OptimConfig(**d["train"]["optim"])
  assert T.model_config_for(typed, setup, "ours").setup == setup

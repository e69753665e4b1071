"""The typed run config (nlosjax.train.config): frozen sections built once from a preset's dict or a config.json."""

import dataclasses
import pathlib
import re

import pytest

from experiments import configs
from nlosjax import losses
from nlosjax import train as T

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("preset", configs.PRESETS)
def test_every_preset_reads_into_typed_sections_with_its_own_values(preset):
  d = configs.get_config(preset)
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
  assert sorted(cfg.extra) == sorted(set(d) - {"data", "model", "train", "usm", "lfe", "ik"})


def test_training_recipe_merges_a_baselines_optimiser_over_ours_as_the_dicts_did():
  d = configs.get_config("cpu")
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


def test_eval_batch_is_8_where_the_section_is_silent_and_the_training_batch_where_it_is_none():
  assert T.RunConfig.from_dict({"train": {"batch_size": 3}}).train.eval_batch == 8
  assert T.RunConfig.from_dict({"train": {"batch_size": 3, "eval_batch_size": None}}).train.eval_batch == 3


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
  cfg = T.RunConfig.from_dict(configs.get_config("cpu"))
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

  cfg = T.RunConfig.from_dict(configs.get_config(preset))
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
  cfg = T.RunConfig.from_dict(configs.get_config("paper"))
  built = T.model_config_for(cfg, cfg.data.spec().setup, "ours")
  assert built == ModelConfig.paper(volume_activation="softplus")
  want = ModelConfig.paper()
  rebuilt = ModelConfig(setup=want.setup, stride=want.stride, frames=want.frames, **paper.model_section(want))
  assert rebuilt == want
  assert paper.model_section(ModelConfig(setup=want.setup, stride=8)) == {}    # the defaults: nothing to say

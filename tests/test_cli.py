"""One command-line habit: ``experiments.train`` and ``experiments.make_dataset`` read ``--config`` alike.

``--config`` is a preset file read by ``ml_collections.config_flags`` (:mod:`experiments.cli`), locked.
Parse-only: generation and training are replaced by recorders, so nothing is simulated or compiled.
"""

import pathlib
import types

import pytest

from experiments import cli, configs, independent_set, main_job, make_dataset
from experiments import train as train_cli
from nlosjax import train as T
from nlosjax.data import dataset as D
from nlosjax.data.dataset import PhysicsMix
from nlosjax.train import RunConfig


@pytest.fixture
def record(monkeypatch):
  """Run either command with its work replaced: ``{"train": config, "write": (path, spec, workers)}``."""
  seen = {}

  def write(path, spec, *, workers=1, **kw):
    seen["write"] = (pathlib.Path(path), spec, workers)
    pathlib.Path(path).write_bytes(b"")
    return types.SimpleNamespace(generated=spec.num_sequences, resumed=0)

  monkeypatch.setattr(D, "write_dataset", write)
  monkeypatch.setattr(main_job, "train_and_evaluate", lambda config, workdir, **kw: seen.update(train=config))
  monkeypatch.setattr(independent_set, "ensure_independent_set", lambda path, *a: path)
  return seen


def train_dataset(config, record):
  """``(path, spec, workers)`` of the dataset ``experiments.train``'s main job makes for ``config`` (a RunConfig)."""
  path = pathlib.Path(config.data.path)
  path.unlink(missing_ok=True)
  T.ensure_dataset(config, path, log=lambda s: None)
  return record.pop("write")


@pytest.mark.parametrize("preset, overrides", [
    ("cpu", ["--config.data.renderer=lct", "--config.data.retroreflective=0.0", "--config.data.frames=4"]),
    ("paper", ["--config.data.photons=(5.0, 200.0)", "--config.data.scene.max_tilt_deg=20.0",
               "--config.data.num_sequences.val=2", "--config.train.data_workers=3"]),
])
def test_make_dataset_takes_trains_overrides_and_makes_trains_file(record, tmp_path, preset, overrides):
  overrides = overrides + [f"--config.data.path={tmp_path / 'data.h5'}"]
  train_cli.main(["--config", preset, "--workdir", str(tmp_path / "run"), *overrides])
  config = record["train"]                           # the typed config the main job is handed
  assert isinstance(config, T.RunConfig) and config.data.path == str(tmp_path / "data.h5")
  assert make_dataset.main(["--config", preset, "--quiet", *overrides]) == 0
  made = record.pop("write")
  assert made == train_dataset(config, record)
  path, spec, workers = made
  assert path == tmp_path / "data.h5"
  assert spec == D.DatasetSpec.from_config(config.data.section)
  if preset == "cpu":
    assert (spec.renderer, spec.retroreflective, spec.frames) == ("lct", 0.0, 4)
  else:
    assert (spec.photons, spec.num_val, workers) == ((5.0, 200.0), 2, 3)


def test_make_dataset_flags_are_shorthands_of_config_keys(record, tmp_path, capsys):
  out = tmp_path / "a.h5"
  flags = ["--out", str(out), "--frames", "3", "--seed", "5", "--train", "2", "--val", "1", "--test", "1",
           "--no-clean", "--albedo", "--workers", "2", "--quiet"]
  assert make_dataset.main(flags) == 0
  by_flags = record["write"]
  out.unlink()
  keys = [f"--config.data.path={out}", "--config.data.frames=3", "--config.data.seed=5",
          "--config.data.num_sequences.train=2", "--config.data.num_sequences.val=1",
          "--config.data.num_sequences.test=1", "--config.data.store_clean=False",
          "--config.data.store_albedo=True", "--config.train.data_workers=2"]
  assert make_dataset.main([*keys, "--quiet"]) == 0
  assert record["write"] == by_flags
  assert (by_flags[1].frames, by_flags[1].num_sequences, by_flags[1].store_clean) == (3, 4, False)
  # --sequences splits in the (overridden) config's proportion.
  out.unlink()
  assert make_dataset.main(["--out", str(out), "--sequences", "4", "--config.data.num_sequences.val=0",
                            "--quiet"]) == 0
  assert (record["write"][1].num_train, record["write"][1].num_val, record["write"][1].num_test) == (3, 0, 1)
  # A flag and an override of the same key: say so, do nothing.
  del record["write"]
  for argv, match in ((["--frames", "3", "--config.data.frames=4"], "--frames and --config.data.frames"),
                      (["--train", "3", "--config.data.num_sequences.train=1"], "data.num_sequences.train"),
                      (["--no-clean", "--config.data.store_clean=True"], "--no-clean and")):
    with pytest.raises(SystemExit) as e:
      make_dataset.main(["--out", str(out), *argv])
    assert e.value.code == 2 and match in capsys.readouterr().err
  assert "write" not in record


@pytest.mark.parametrize("command", [train_cli.main, make_dataset.main], ids=["train", "make_dataset"])
@pytest.mark.parametrize("argv, match", [
    (["--config.data.renderr=lct"],
     r"^--config\.data\.renderr: config\.data has no key 'renderr' \(did you mean 'renderer'\?\); "
     r"it has: ambient, .*grid, .*renderer, retroreflective, scene"),
    (["--config.nosuch.x=1"], r"^--config\.nosuch\.x: config has no key 'nosuch'; it has: data, ik, independent, lfe, "
                              r"model, train, usm$"),
    (["--config.train.stpes=5"], r"config\.train has no key .stpes. \(did you mean .steps.\?\); it has: .*seeds"),
    (["--config.model.widht=5"], r"config\.model has no key 'widht' \(did you mean 'width'\?\)"),
    (["--config.data.scene.colour=1"], r"config\.data\.scene has no key 'colour'; it has: .*max_tilt_deg"),
    (["--config.usm.modle.x=1"], r"config\.usm has no key 'modle' \(did you mean 'model'\?\)"),
    (["--config.data.grid.x=1"], r"config\.data\.grid is a value \(32\), not a section"),
    (["--config.train.steps=many"], r"^--config cpu: flag --config\.train\.steps=many: invalid literal for int"),
    (["--config.train.steps=1.5"], r"--config\.train\.steps=1\.5: invalid literal for int"),
    (["--config.data.store_clean=maybe"], r"--config\.data\.store_clean=maybe"),
    (["--config", "gpu"], r"^--config gpu: neither a preset \(cpu, paper, real\) nor a \.py file$"),
    (["--config", "nowhere/absent.py"], r"^--config nowhere/absent\.py: no such file$"),
    (["--config.data.frames=4", "4"], r"^unrecognised argument\(s\) 4"),
])
def test_both_commands_exit_with_one_line_naming_a_bad_key_or_value_before_any_work(record, tmp_path, command,
                                                                                     argv, match):
  with pytest.raises(SystemExit, match=match) as e:
    command(["--workdir" if command is train_cli.main else "--out", str(tmp_path / "x"), *argv])
  assert isinstance(e.value.code, str) and "\n" not in e.value.code          # one line, no traceback
  assert not record and not list(tmp_path.iterdir())


def test_a_nested_override_changes_that_key_and_nothing_else():
  # The reference: the preset's dict edited by hand (no config_flags on that side).
  want = configs.get_config("paper")
  want["data"]["scene"]["max_tilt_deg"] = 20.0
  want["data"]["photons"] = (5.0, 200.0)
  want["train"]["variants"] = ("ours",)
  want["train"]["optim"]["learning_rate"] = 3e-4
  got = cli.load_config("paper", ["--config.data.scene.max_tilt_deg=20", "--config.data.photons=(5.0, 200.0)",
                                  '--config.train.variants=("ours",)', "--config.train.optim.learning_rate=3e-4"])
  assert got == want
  assert isinstance(got["data"]["scene"]["max_tilt_deg"], float)           # an int typed for a float key: a float


def test_keys_the_preset_leaves_unset_can_be_set_and_reach_the_typed_config():
  config = cli.load_config("cpu", [
      "--config.data.falloff=retroreflective", "--config.data.noise_sampler=jax",
      "--config.usm.optim.learning_rate=3e-4", "--config.train.devices=2", "--config.model.remat=True",
      "--config.data.renderer=lct", "--config.data.retroreflective=0.0", "--config.train.stop.rule=plateau",
      "--config.lfe.model.extract_width=2"])
  assert config["usm"]["optim"] == {"learning_rate": 3e-4}
  typed = RunConfig.from_dict(config)
  assert typed.train.devices == 2 and typed.model["remat"] is True
  # the rule set, the preset's metric kept, the rest at the defaults
  assert typed.train.stop == T.StopRule(rule="plateau", metric="psnr_balanced")
  assert D.DatasetSpec.from_config(config["data"]).falloff == "retroreflective"
  assert T.training_recipe(typed, "usm")[0] == T.OptimConfig(**{**config["train"]["optim"], "learning_rate": 3e-4})
  assert T.model_config_for(typed, typed.data.setup(), "lfe").extract_width == 2
  # Unset keys are absent from the dict a run records: the library's defaults apply.
  assert "lfe" not in cli.load_config("cpu") and cli.load_config("cpu")["train"]["stop"] == {"metric": "psnr_balanced"}


def test_none_is_a_value_where_the_library_reads_it_as_one():
  # No clipping, the training batch for evaluation, no jitter, no compression: each field's None.
  config = cli.load_config("cpu", ["--config.train.optim.clip_norm=None", "--config.train.eval_batch_size=None",
                                   "--config.data.jitter=None", "--config.data.compression=None"])
  typed = RunConfig.from_dict(config)
  cpu = configs.get_config("cpu")
  assert typed.train.optim == T.OptimConfig(**{**cpu["train"]["optim"], "clip_norm": None})
  assert typed.train.eval_batch == cpu["train"]["batch_size"]
  spec = typed.data.spec()
  assert spec.jitter is None and spec.compression is None
  # ... and where a preset leaves them alone they are the preset's (or the dataclass's) values.
  assert cli.load_config("cpu")["train"]["optim"]["clip_norm"] == 1.0
  assert "clip_norm" not in cli.load_config("cpu", ["--config.usm.optim.learning_rate=1e-3"])["usm"]["optim"]


def test_a_section_set_empty_on_purpose_is_kept_with_its_defaults(record, tmp_path):
  # docs/dataset.md: the forward model drawn per sequence, every PhysicsMix range at its default.
  out = tmp_path / "mix.h5"
  assert make_dataset.main(["--config.data.renderer=mix", "--config.data.retroreflective=0.0",
                            "--config.data.physics={}", "--out", str(out), "--quiet"]) == 0
  assert record["write"][1].physics == PhysicsMix()
  assert "physics" not in cli.load_config("cpu")["data"]             # unset: no section at all


def test_a_preset_without_an_independent_set_refuses_half_of_one(record, tmp_path):
  with pytest.raises(SystemExit, match=r"independent\.path is needed"):
    train_cli.main(["--config", "paper", "--workdir", str(tmp_path / "x"), "--config.independent.seed=3"])
  assert not record


def test_a_config_file_is_a_flax_style_variant_of_a_preset(record, tmp_path):
  variant = tmp_path / "short.py"
  variant.write_text("from experiments.configs import cpu\n\n\n"
                     "def get_config(arg=None):\n"
                     "  config = cpu.get_config()\n"
                     "  config.train.steps = 7 if arg is None else int(arg)\n"
                     "  return config\n")
  want = configs.get_config("cpu")
  want["train"]["steps"] = 7
  assert cli.load_config(str(variant)) == want
  assert cli.load_config(f"{variant}:9")["train"]["steps"] == 9           # FILE:ARG -> get_config("9")
  want["train"]["batch_size"] = 2
  assert cli.load_config(str(variant), ["--config.train.batch_size=2"]) == want
  with pytest.raises(SystemExit, match="config.train has no key 'batchsize'"):    # the file's config is locked too
    cli.load_config(str(variant), ["--config.train.batchsize=2"])
  # A preset's name and its file are the same config.
  assert cli.load_config("real") == cli.load_config(str(configs.FOLDER / "real.py")) == configs.get_config("real")


def test_help_of_both_commands_documents_the_overrides(capsys):
  for command in (train_cli.main, make_dataset.main):
    with pytest.raises(SystemExit) as e:
      command(["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert "--config.SECTION.KEY=VALUE" in text and "preset name (cpu, paper, real)" in text

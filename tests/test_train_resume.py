"""Training, continued: bitwise resume, checkpoint errors, 200 finite steps.

Data-parallel equivalence (4, 2 and 1 devices, restores across device counts, two
processes) is tested in ``tests/test_distributed.py``.

Split from ``test_train.py`` so the two slow halves run on different xdist workers.
"""

import json

import jax
import numpy as np
import pytest

from experiments import configs
from nlosjax import train as T
from nlosjax.train import RunConfig
from tests.tiny_run import make_tiny_dataset, tiny_config


@pytest.fixture(scope="module")
def data_path(tmp_path_factory):
  return make_tiny_dataset(tmp_path_factory)


@pytest.mark.full
def test_resume_after_a_kill_matches_an_uninterrupted_run(data_path, tmp_path):
  cfg = tiny_config(data_path)
  config = RunConfig.from_dict(cfg)
  _, straight = T.train_model(config, data_path, tmp_path / "a", "ours_s", log=lambda s: None)
  # "Killed" after step 2: a run with steps=2 leaves the checkpoint at 2; the rerun resumes.
  T.train_model(RunConfig.from_dict({**cfg, "train": {**cfg["train"], "steps": 2}}), data_path, tmp_path / "b",
                "ours_s", log=lambda s: None)
  messages = []
  _, resumed = T.train_model(config, data_path, tmp_path / "b", "ours_s", log=messages.append)
  assert any("resumed from step 2" in m for m in messages)
  assert int(resumed.step) == int(straight.step) == 4
  jax.tree.map(lambda a, b: np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0,
                                                       atol=1e-6), straight.params, resumed.params)
  la = [json.loads(l) for l in (tmp_path / "a/ours_s/metrics.jsonl").read_text().splitlines()]
  lb = [json.loads(l) for l in (tmp_path / "b/ours_s/metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in lb] == [1, 2, 3, 4]
  assert lb[-1]["loss"] == pytest.approx(la[-1]["loss"], abs=1e-6)


@pytest.mark.full
def test_checkpoint_of_another_config_or_corrupt_raises_and_is_kept(data_path, tmp_path):
  cfg = tiny_config(data_path, steps=2)
  config = RunConfig.from_dict(cfg)
  T.train_model(config, data_path, tmp_path, "ours_s", log=lambda s: None)
  ckpt = tmp_path / "ours_s" / "checkpoints"
  before = sorted(p.name for p in ckpt.iterdir())
  other = {**cfg, "model": {**cfg["model"], "width": 6}}
  with pytest.raises(ValueError, match="another model config"):
    T.train_model(RunConfig.from_dict(other), data_path, tmp_path, "ours_s", log=lambda s: None)
  assert sorted(p.name for p in ckpt.iterdir()) == before
  # Corrupt every array file of the latest checkpoint.
  for f in (ckpt / "2").rglob("*"):
    if f.is_file() and "state" in str(f) and f.stat().st_size > 64:
      f.write_bytes(b"\0" * 16)
  with pytest.raises(ValueError, match="checkpoint .*2"):
    T.train_model(config, data_path, tmp_path, "ours_s", log=lambda s: None)
  assert (ckpt / "2").exists()


@pytest.mark.full
def test_two_hundred_steps_stay_finite_at_the_lowest_efficiency_and_exposure(tmp_path):
  # The CPU preset's lowest efficiency (1 %) and photon budget (1e3 per point), nothing higher.
  path = tmp_path / "dim.h5"
  cfg = tiny_config(path, steps=200, log_every=1, checkpoint_every=200)
  low = configs.get_config("cpu")["data"]
  cfg["data"].update(efficiency=(low["efficiency"][0],) * 2, photons=(low["photons"][0],) * 2)
  config = RunConfig.from_dict(cfg)
  T.ensure_dataset(config, path, log=lambda s: None)
  T.train_model(config, path, tmp_path, "ours_s", log=lambda s: None)  # raises on a non-finite metric
  rows = [json.loads(l) for l in (tmp_path / "ours_s" / "metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in rows] == list(range(1, 201))
  for key in ("loss", "l2_grads", "l2_updates"):
    values = np.array([r[key] for r in rows])
    assert np.isfinite(values).all(), key
  assert rows[-1]["l2_grads"] > 0                   # still learning, not silently zeroed


@pytest.mark.full
def test_a_passed_loader_and_model_config_are_what_trains(data_path, tmp_path):
  # The trade-off study's path: train_model with its own loader and network.
  cfg = tiny_config(data_path)
  run = RunConfig.from_dict(cfg)
  _, default = T.train_model(run, data_path, tmp_path / "a", "ours_s", log=lambda s: None)
  loader = T.make_loader(run, data_path, "train", batch_size=run.train.batch_size, shuffle=True,
                         seed=run.train.seed)
  mcfg = T.model_config_for(run, loader.setup, "ours_s")
  _, passed = T.train_model(run, None, tmp_path / "b", "ours_s", log=lambda s: None,
                            loader=loader, model_config=mcfg)
  jax.tree.map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)),
               default.params, passed.params)

  read = []

  class Recording(type(loader)):
    def batch(self, step):
      read.append(int(step))
      return super().batch(step)

  recording = Recording(data_path, split="train", batch_size=run.train.batch_size, stride=run.data.stride(),
                        offset=run.data.input_offset, seed=run.train.seed, shuffle=True, drop_remainder=True)
  wider = T.model_config_for(RunConfig.from_dict({**cfg, "model": {**cfg["model"], "width": 6}}), loader.setup,
                             "ours_s")
  got, state = T.train_model(run, None, tmp_path / "c", "ours_s", folder="wide",
                             log=lambda s: None,
                             loader=recording, model_config=wider)
  assert read == list(range(run.train.steps))
  assert got == wider and (tmp_path / "c" / "wide" / "checkpoints").exists()
  assert T.param_fingerprint(state.params) != T.param_fingerprint(default.params)

  # A passed loader is closed however training ends: here a batch that cannot be read.
  closed = []

  class Failing(type(loader)):
    def batch(self, step):
      raise OSError("the disk went away")

    def close(self):
      closed.append(True)
      super().close()

  failing = Failing(data_path, split="train", batch_size=run.train.batch_size, stride=run.data.stride(),
                    offset=run.data.input_offset, seed=run.train.seed, shuffle=True, drop_remainder=True)
  with pytest.raises(OSError, match="the disk went away"):
    T.train_model(run, None, tmp_path / "d", "ours_s", log=lambda s: None, loader=failing)
  assert closed and not failing.dataset._file   # h5py: a closed file is falsy

"""Runs that outlast one working stretch: the exported state resumes on a fresh workdir, bit for bit.

A "fresh clone" here is an empty workdir and the export folder copied to another
path: nothing of the first run's orbax checkpoints, logs or absolute paths is left.
"""

import json
import shutil

import jax
import numpy as np
import pytest

from nlosjax import inference
from nlosjax import train as T
from nlosjax.data.dataset import dataset_digest
from nlosjax.train import RunConfig, run_state
from tests.tiny_run import make_tiny_dataset, tiny_config


@pytest.fixture(scope="module")
def data_path(tmp_path_factory):
  return make_tiny_dataset(tmp_path_factory)


def _score(mcfg, params):
  """A deterministic stand-in for the validation PSNR: any function of the parameters will do."""
  leaves = jax.tree.leaves(params)
  return float(sum(np.sum(np.asarray(x, np.float64) ** 2) for x in leaves) % 7.0)


def _plateau_config(data_path):
  # Validates every 2 steps for 8 steps; patience high enough that max_steps ends it.
  return tiny_config(data_path, checkpoint_every=3,
                     stop={"rule": "plateau", "every": 2, "patience": 10, "min_delta_db": 0.0,
                           "max_steps": 8})


def _assert_same_tree(a, b):
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


class _Killed(Exception):
  pass


def _fail(mcfg, params):
  raise AssertionError("a finished run validates nothing")


@pytest.mark.full
def test_a_killed_plateau_run_resumes_from_its_export_on_a_fresh_workdir_bit_for_bit(data_path, tmp_path):
  cfg = _plateau_config(data_path)
  config = RunConfig.from_dict(cfg)
  quiet = lambda s: None
  _, straight = T.train_model(config, data_path, tmp_path / "a", "ours_s", validate=_score, log=quiet)
  # The interrupted run: killed inside the validation of step 6, after that step's checkpoint
  # and before its export (the export still holds step 4, the last finished validation).
  calls = []

  def dying(mcfg, params):
    calls.append(1)
    if len(calls) == 3:
      raise _Killed
    return _score(mcfg, params)

  export = T.StateExport(tmp_path / "state", data_digest=dataset_digest(data_path))
  with pytest.raises(_Killed):
    T.train_model(config, data_path, tmp_path / "b", "ours_s", validate=dying, log=quiet,
                  export=export)
  meta = run_state.read_meta(tmp_path / "state" / "ours_s")
  assert meta["step"] == 4 and meta["best_step"] in (2, 4)
  # A fresh clone: the export moved, the workdir gone.
  shutil.copytree(tmp_path / "state", tmp_path / "clone" / "state")
  shutil.rmtree(tmp_path / "b")
  shutil.rmtree(tmp_path / "state")
  messages = []
  moved = T.StateExport(tmp_path / "clone" / "state", data_digest=dataset_digest(data_path))
  _, resumed = T.train_model(config, data_path, tmp_path / "c", "ours_s", validate=_score,
                             log=messages.append, export=moved)
  assert any("resumed from step 4 of the exported state" in m for m in messages)
  _assert_same_tree(straight.params, resumed.params)          # the best state, chosen alike
  assert int(straight.step) == int(resumed.step)
  curve_a = json.loads((tmp_path / "a/ours_s/validation_curve.json").read_text())
  curve_c = json.loads((tmp_path / "c/ours_s/validation_curve.json").read_text())
  assert [(p["step"], p["val_psnr"]) for p in curve_a["curve"]] == \
         [(p["step"], p["val_psnr"]) for p in curve_c["curve"]]
  # The export now holds the finished run: the chosen parameters alone, at the best step.
  final = run_state.read_meta(tmp_path / "clone/state/ours_s")
  assert final["step"] == 8 and (tmp_path / "clone/state/ours_s/selection.json").exists()
  assert final["finished"] and final["chosen_step"] == final["best_step"] == int(straight.step)
  assert sorted(p.name for p in (tmp_path / "clone/state/ours_s").glob("*.npz")) == ["params.npz"]
  with np.load(tmp_path / "clone/state/ours_s/params.npz") as f:
    assert not any("opt_state" in k for k in f.files)
    _assert_same_tree(straight.params, run_state.arrays_tree(
        {k: f[k] for k in f.files if k.startswith("['params']")}, {"params": straight.params})["params"])
  # A fresh clone of the finished export: the chosen parameters, no step trained, the selection kept;
  # the workdir it leaves reads back as the run would (load_trained: the selected step).
  _, again = T.train_model(config, data_path, tmp_path / "d", "ours_s", validate=_fail, log=quiet, export=moved)
  _assert_same_tree(straight.params, again.params)
  assert (tmp_path / "d/ours_s/metrics.jsonl").read_text() == (tmp_path / "c/ours_s/metrics.jsonl").read_text()
  (tmp_path / "d/config.json").write_text(json.dumps(config.to_dict()))      # as experiments.train writes it
  _, loaded, info = inference.load_trained(tmp_path / "d", "ours_s")
  assert info["step"] == int(straight.step) and info["selected_on_validation"]
  _assert_same_tree(straight.params, loaded)
  assert run_state.read_meta(tmp_path / "clone/state/ours_s") == final
  rows_a = [json.loads(l) for l in (tmp_path / "a/ours_s/metrics.jsonl").read_text().splitlines()]
  rows_c = [json.loads(l) for l in (tmp_path / "c/ours_s/metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in rows_c] == [r["step"] for r in rows_a]
  assert [r["loss"] for r in rows_c] == [r["loss"] for r in rows_a]
  # Under 1 MB for this model, as the docs promise for ~20k parameters (this one is far smaller).
  size = sum(f.stat().st_size for f in (tmp_path / "clone/state").rglob("*") if f.is_file())
  assert size < 1 << 20


@pytest.mark.full
def test_a_run_past_its_deadline_pauses_exported_and_continues_to_the_same_parameters(data_path, tmp_path):
  cfg = tiny_config(data_path, steps=5, checkpoint_every=4)
  config = RunConfig.from_dict(cfg)
  quiet = lambda s: None
  _, straight = T.train_model(config, data_path, tmp_path / "a", "ours_s", log=quiet)
  paused = T.StateExport(tmp_path / "state", deadline=0.0)       # already past: pause after step 1
  with pytest.raises(T.TrainingPaused) as info:
    T.train_model(config, data_path, tmp_path / "b", "ours_s", log=quiet, export=paused)
  assert info.value.step == 1
  assert run_state.read_meta(tmp_path / "state/ours_s")["step"] == 1
  shutil.rmtree(tmp_path / "b")
  _, resumed = T.train_model(config, data_path, tmp_path / "c", "ours_s", log=quiet,
                             export=T.StateExport(tmp_path / "state"))
  _assert_same_tree(straight.params, resumed.params)
  _assert_same_tree(straight.opt_state, resumed.opt_state)


@pytest.mark.full
def test_an_export_of_another_run_or_other_data_is_refused_and_kept(data_path, tmp_path):
  cfg = tiny_config(data_path, steps=2)
  quiet = lambda s: None
  T.train_model(RunConfig.from_dict(cfg), data_path, tmp_path / "a", "ours_s", log=quiet,
                export=T.StateExport(tmp_path / "state", data_digest="0123456789abcdef"))
  before = (tmp_path / "state/ours_s/params.npz").read_bytes()      # finished: the chosen parameters
  other = {**cfg, "model": {**cfg["model"], "width": 6}}
  with pytest.raises(ValueError, match="another run signature"):
    T.train_model(RunConfig.from_dict(other), data_path, tmp_path / "b", "ours_s", log=quiet,
                  export=T.StateExport(tmp_path / "state"))
  longer = {**cfg, "train": {**cfg["train"], "steps": 4}}
  with pytest.raises(ValueError, match="content digest 0123456789abcdef.*--allow-data-change"):
    T.train_model(RunConfig.from_dict(longer), data_path, tmp_path / "c", "ours_s", log=quiet,
                  export=T.StateExport(tmp_path / "state", data_digest=dataset_digest(data_path)))
  # The same data and run, told to train further: the finished export has no optimiser state to go on.
  with pytest.raises(ValueError, match="finished run's chosen parameters only"):
    T.train_model(RunConfig.from_dict(longer), data_path, tmp_path / "d", "ours_s", log=quiet,
                  export=T.StateExport(tmp_path / "state"))
  assert (tmp_path / "state/ours_s/params.npz").read_bytes() == before


def test_arrays_tree_names_the_leaf_that_does_not_fit():
  template = {"a": np.zeros((2, 3), np.float32), "b": {"c": np.zeros((), np.int32)}}
  arrays = run_state.tree_arrays(template)
  assert set(arrays) == {"['a']", "['b']['c']"}
  with pytest.raises(ValueError, match=r"\['a'\].*float32\[3, 2\]"):
    run_state.arrays_tree({**arrays, "['a']": np.zeros((3, 2), np.float32)}, template)
  with pytest.raises(ValueError, match="lacks the leaf"):
    run_state.arrays_tree({"['a']": arrays["['a']"]}, template)
  with pytest.raises(ValueError, match="leaves this model lacks"):
    run_state.arrays_tree({**arrays, "['z']": np.zeros(1)}, template)


def test_dataset_digest_sees_one_changed_count_and_not_the_file_layout(data_path, tmp_path):
  import h5py
  copy = tmp_path / "copy.h5"
  with h5py.File(data_path, "r") as src, h5py.File(copy, "w") as dst:
    for k, v in src.attrs.items():
      dst.attrs[k] = v

    def copy_one(name, obj):                       # returns None: visititems goes on
      if isinstance(obj, h5py.Dataset):
        dst.create_dataset(name, data=obj[()], compression="gzip", chunks=True)
    src.visititems(copy_one)
  assert dataset_digest(copy) == dataset_digest(data_path)
  assert dataset_digest(copy, chunk_bytes=64) == dataset_digest(data_path)
  with h5py.File(copy, "r+") as f:
    names = []
    f.visititems(lambda n, obj: names.append(n) if n.endswith("/measurement") else None)
    ds = f[sorted(names)[0]]
    first = ds[0]
    first.flat[0] += 1
    ds[0] = first
  assert dataset_digest(copy) != dataset_digest(data_path)


def test_finishing_an_older_export_keeps_the_best_parameters_and_drops_the_optimiser(tmp_path):
  """An export written before runs finished their exports (``state.npz`` and ``best.npz``): against
  hand-made arrays, :func:`finish_export` keeps the best state's parameters and step, byte for byte."""
  folder = tmp_path / "model"
  folder.mkdir()
  rng = np.random.default_rng(0)
  best = {"['params']['w']": rng.normal(size=(3, 2)).astype(np.float32), "['step']": np.int32(4),
          "['opt_state'][0].mu['w']": rng.normal(size=(3, 2)).astype(np.float32)}
  last = {**best, "['params']['w']": rng.normal(size=(3, 2)).astype(np.float32), "['step']": np.int32(8)}
  np.savez(folder / "best.npz", **best)
  np.savez(folder / "state.npz", **last)
  (folder / "run_state.json").write_text(json.dumps({"step": 8, "best_step": 4, "signature": {}}))
  with pytest.raises(ValueError, match="has not finished"):
    run_state.finish_export(folder)
  (folder / "selection.json").write_text(json.dumps({"select": "plateau", "step": 4, "stop_reason": "plateau"}))
  meta = run_state.finish_export(folder)
  assert meta["finished"] and meta["chosen_step"] == 4 and meta["step"] == 8
  assert sorted(p.name for p in folder.iterdir()) == ["params.npz", "run_state.json", "selection.json"]
  with np.load(folder / "params.npz") as f:
    assert sorted(f.files) == ["['params']['w']", "['step']"]
    np.testing.assert_array_equal(f["['params']['w']"], best["['params']['w']"])
    assert int(f["['step']"]) == 4
  assert run_state.finish_export(folder) == meta                    # finished already: left as it is

"""Weights shipped inside the package (``nlosjax/weights/``): loading, provenance and recorded scores.

The shipped models must reproduce the validation score recorded at export on
data regenerated from their recorded data specification (one val sequence,
Ours only, to stay fast); damaged or edited files must fail by name; the
commands that reconstruct captures must use them when no checkpoint is given.
Only the comparison with the original training run needs ``runs/`` (absent in
a fresh clone) and skips without it.
"""

from __future__ import annotations

import copy
import json
import pathlib
import shutil
import tomllib

import jax
import numpy as np
import pytest

from nlosjax import inference, metrics, pretrained
from nlosjax.data import dataset as D
from nlosjax.data import scenes
from nlosjax.evaluation import protocol
from nlosjax.train import RunConfig
from tests.xla_options import xla_optimizations

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHIPPED = (("cpu", "ours"), ("cpu", "ours_s"), ("cpu", "lfe"), ("cpu", "ik"), ("real", "ours"),
           ("real", "ours_s"))
#: Tolerance of the reproduced per-sequence validation PSNR (dB). On the machine that
#: exported the weights the regenerated sequence is bit-identical to the stored one and
#: the PSNR equal to the last digit. What another CPU may change is float32 rounding in
#: the renderer and in the network. Measured here: multiplying every rendered value by
#: 1 + 1e-5 N(0, 1) (about 80 float32 ulps; the stored transient is rounded to 12
#: mantissa bits anyway) changes 2 of 1 048 576 counts and the PSNR by < 1e-6 dB;
#: moving 1 % of all counts by +-1 moves it by 0.005 dB. 0.02 dB is thus far above
#: rounding and far below what other data give (the eight val sequences score 15.8 to
#: 20.8 dB).
TOL_DB = 0.02


def test_the_models_are_shipped_small_and_packaged():
  assert set(SHIPPED) <= set(inference.pretrained_names())
  with open(ROOT / "pyproject.toml", "rb") as f:
    globs = tomllib.load(f)["tool"]["setuptools"]["package-data"]["nlosjax"]
  for name, variant in SHIPPED:
    folder = pretrained.weights_folder(name, variant)
    for file in (pretrained.PARAMS_FILE, pretrained.PROVENANCE_FILE):
      rel = pathlib.PurePosixPath("weights", folder.name, file)
      assert any(rel.match(g) for g in globs), f"{rel} is not package data in pyproject.toml"
    assert (folder / pretrained.PARAMS_FILE).stat().st_size < 4 * 2**20     # a few MB at most


@pytest.mark.parametrize("name, variant", SHIPPED)
def test_provenance_records_what_the_weights_came_from(name, variant):
  prov = pretrained.read_provenance(pretrained.weights_folder(name, variant))
  for key in ("command", "commit", "date", "machine", "config", "data_spec", "training_seed",
              "steps_taken", "stop_reason", "best_step", "model_config", "param_fingerprint",
              "params_sha256"):
    assert key in prov, key
  assert prov["config"]["train"]["seed"] == prov["training_seed"]
  assert prov["data_spec"]["seed"] == prov["config"]["data"]["seed"] == prov["data_seed"]
  val = prov["validation"]
  assert val["split"] == "val" and abs(val["psnr_db"] - val["recorded_psnr_db"]) <= 1e-3
  # The per-sequence means, weighted by their frames, give the split's mean.
  frames = val["frames_per_sequence"]
  mean = sum(val["per_sequence_psnr_db"][s] * n for s, n in frames.items()) / sum(frames.values())
  assert sum(frames.values()) == val["n_frames"] and mean == pytest.approx(val["psnr_db"], abs=1e-4)


def _regenerate(name, variant, folder):
  """Val sequence 0 of the data specification recorded with the shipped ``name-variant``, simulated into ``folder``.

  Returns ``(model_config, params, provenance, config pointing at the file, path)``.
  """
  mcfg, params, prov = inference.load_pretrained(name, variant)
  if prov["dataset"]["generator_version"] != scenes.GENERATOR_VERSION:
    pytest.fail(f"the scene generator is version {scenes.GENERATOR_VERSION}, the weights were validated"
                f" on version {prov['dataset']['generator_version']}: their data cannot be regenerated;"
                " re-export them (python -m experiments.export_weights) on data of this version")
  config = copy.deepcopy(prov["config"])
  # Sequence seeds depend only on the base seed, the split and the index (D.sequence_seed),
  # so a file of one val sequence holds the val-00000 the weights were scored on.
  spec = D.DatasetSpec.from_config(config["data"], num_train=0, num_val=1, num_test=0)
  assert spec.generation_key() == D.DatasetSpec.from_config(prov["data_spec"]).generation_key()
  path = folder / "val.h5"
  # Rendering runs long: 185 s without XLA's optimisations, 73 s with (2 cores, a training run beside).
  with xla_optimizations(True):
    D.write_dataset(path, spec, progress=False)
  config["data"]["path"] = str(path)
  return mcfg, params, prov, config, path


def _val_sequence_psnr(mcfg, params, config, path) -> np.ndarray:
  """``[F]`` intensity PSNR (dB) of the model on each frame of the one val sequence in ``path``."""
  data = protocol.load_split(RunConfig.from_dict(config), path, "val",
                             batch_size=int(config["train"]["eval_batch_size"]))
  try:
    images = protocol.model_images(mcfg, params, data["loader"])
    assert data["loader"].names == ["val-00000"]
  finally:
    data["loader"].close()
  return np.asarray(metrics.psnr(images["intensity"], data["intensity"]))


@pytest.fixture(scope="module")
def regenerated(tmp_path_factory):
  """The shipped ``cpu`` Ours and its regenerated val sequence (:func:`_regenerate`)."""
  return _regenerate("cpu", "ours", tmp_path_factory.mktemp("val"))


def _check_reproduced(mcfg, params, prov, config, path):
  psnr = _val_sequence_psnr(mcfg, params, config, path)
  assert psnr.size == prov["validation"]["frames_per_sequence"]["val-00000"]
  recorded = prov["validation"]["per_sequence_psnr_db"]["val-00000"]
  assert abs(float(np.mean(psnr)) - recorded) <= TOL_DB, (float(np.mean(psnr)), recorded)


@pytest.mark.full
def test_shipped_weights_reproduce_their_recorded_validation_score(regenerated):
  _check_reproduced(*regenerated)


@pytest.mark.full
def test_shipped_real_weights_reproduce_their_recorded_validation_scores(tmp_path):
  """Every shipped ``real`` variant, on its regenerated transport-rendered val sequence (about a minute each).

  The variants may have been trained on different data (``real-ours_s`` on the v5 candidate's):
  variants validated on the same data specification share one regenerated file.
  """
  variants = [v for n, v in inference.pretrained_names() if n == "real"]
  assert {"ours", "ours_s"} <= set(variants)
  files = {}
  for k, variant in enumerate(variants):
    mcfg, params, prov = inference.load_pretrained("real", variant)
    key = json.dumps(prov["data_spec"], sort_keys=True)
    if key not in files:
      (tmp_path / f"spec{k}").mkdir()
      files[key] = _regenerate("real", variant, tmp_path / f"spec{k}")[3:]
    _check_reproduced(mcfg, params, prov, *files[key])


# ------------------------------------------------------------ damaged or edited files
def _tamper_shape(folder):
  with np.load(folder / "params.npz") as z:
    flat = {k: z[k] for k in z.files}
  key = next(k for k, a in flat.items() if a.ndim == 2)
  flat[key] = np.zeros((flat[key].shape[0] + 1,) + flat[key].shape[1:], np.float32)
  (folder / "params.npz").write_bytes(pretrained._npz_bytes(flat))
  prov = json.loads((folder / "provenance.json").read_text())
  prov["params_sha256"] = pretrained.sha256_file(folder / "params.npz")      # only the shape is wrong
  (folder / "provenance.json").write_text(json.dumps(prov))
  return ["params.npz", "shape mismatches", key.split("/")[-1]]


def _tamper_values(folder):
  with np.load(folder / "params.npz") as z:
    flat = {k: z[k] for k in z.files}
  key = sorted(flat)[0]
  flat[key] = flat[key] + np.float32(1e-3)
  (folder / "params.npz").write_bytes(pretrained._npz_bytes(flat))
  return ["params.npz", "sha256", "changed or damaged"]


def _tamper_config(folder):
  prov = json.loads((folder / "provenance.json").read_text())
  prov["config"]["model"]["width"] = 2 * prov["config"]["model"]["width"]
  (folder / "provenance.json").write_text(json.dumps(prov))
  return ["provenance.json", "differs from the one", "width: 16 recorded, 32 now"]


def _tamper_recorded_config(folder):
  prov = json.loads((folder / "provenance.json").read_text())
  if isinstance(prov["model_config"], dict):         # the structured record exports write now
    prov["model_config"]["d_state"] = 8
  else:                                               # a repr, as older exports recorded
    prov["model_config"] = prov["model_config"].replace("d_state=4", "d_state=8")
  (folder / "provenance.json").write_text(json.dumps(prov))
  return ["provenance.json", "recorded", "d_state: 8 recorded, 4 now"]


@pytest.mark.parametrize("tamper", [_tamper_shape, _tamper_values, _tamper_config, _tamper_recorded_config])
def test_tampered_weights_fail_by_name(tamper, tmp_path):
  src = pretrained.weights_folder("cpu", "ours")
  shutil.copytree(src, tmp_path / src.name)
  expected = tamper(tmp_path / src.name)
  with pytest.raises(ValueError) as e:
    inference.load_pretrained("cpu", "ours", root=tmp_path)
  for text in expected:
    assert text in str(e.value), (text, str(e.value))


def test_unknown_weights_list_the_shipped_ones():
  for name, variant in (("nope", "ours"), ("cpu", "usm")):
    with pytest.raises(ValueError, match="shipped: ") as e:
      inference.load_pretrained(name, variant)
    assert "cpu (ours)" in str(e.value) and "cpu (ours_s)" in str(e.value) and "real (ours)" in str(e.value)


def test_load_pretrained_moves_to_another_setup():
  from nlosjax.physics.setup import Setup
  other = Setup(wall_size=1.0, grid=(16, 16), bin_width=132e-12, num_bins=128)
  mcfg, _, prov = inference.load_pretrained("cpu", "ours_s", setup=other)
  assert mcfg.setup == other and mcfg.frames == 1 and prov["variant"] == "ours_s"
  # Other bins would be read as the trained ones: refused, pointing at for_capture.
  with pytest.raises(ValueError, match="for_capture"):
    inference.load_pretrained("cpu", "ours_s", setup=Setup(wall_size=1.0, grid=16, bin_width=33e-12,
                                                           num_bins=512))


# ------------------------------------------------------------ the commands
@pytest.mark.full
def test_reconstruct_uses_the_shipped_weights(tmp_path, capsys):
  from experiments import reconstruct
  from nlosjax.data import io
  from nlosjax.physics.setup import Setup
  capture = Setup(wall_size=1.0, grid=(16, 16), bin_width=33e-12, num_bins=512)
  counts = np.random.default_rng(0).poisson(0.5, (512, 16, 16)).astype(np.float32)
  counts[200:210, 4:12, 6:10] += 20.0
  path = io.save_capture(tmp_path / "capture.h5", counts, capture)
  res = reconstruct.main([str(path), "--method", "ours", "--pretrained", "cpu", "--no-cache", "--quiet",
                          "--out", str(tmp_path / "out")])
  # Moved to the capture: its wall and grid, 4 x 33 ps = 132 ps bins (the trained width).
  assert res["setup"].grid == (16, 16) and res["setup"].wall_size == 1.0
  assert res["setup"].num_bins == 128 and res["setup"].bin_width == pytest.approx(132e-12)
  assert res["volume"].shape == (1, 128, 16, 16) and np.isfinite(res["volume"]).all()
  assert 0.0 <= res["intensity"].min() and res["intensity"].max() <= 1.0
  import h5py
  with h5py.File(tmp_path / "out" / "volume.h5", "r") as f:
    info = json.loads(f.attrs["model"])
  assert info["pretrained"] == "cpu" and info["variant"] == "ours"
  # The CLI's volume is the shipped network's, applied by hand to the same input: bins summed
  # 4 by 4, the scan points stride // 2 + stride * i kept, the one frame repeated as its own
  # neighbours, the model moved to the capture's 132 ps Setup with the wavelet the CLI recorded.
  import dataclasses

  from nlosjax.models.network import STMambaNet
  model_setup = Setup(wall_size=1.0, grid=(16, 16), bin_width=132e-12, num_bins=128)
  mcfg, params, _ = inference.load_pretrained("cpu", "ours", setup=model_setup)
  mcfg = dataclasses.replace(mcfg, wavelet_sampling=float(info["wavelet_sampling"]))
  binned = counts.reshape(128, 4, 16, 16).sum(axis=1)
  s = mcfg.stride
  x = np.stack([binned[:, s // 2::s, s // 2::s]] * 3)[None]               # [1, 3, T, h, w]
  out = STMambaNet(mcfg).apply({"params": params}, x)
  np.testing.assert_allclose(res["volume"][0], np.asarray(out["volume"][0]), rtol=1e-5,
                             atol=1e-5 * float(np.abs(out["volume"]).max()))
  np.testing.assert_allclose(res["intensity"][0], np.clip(np.asarray(out["intensity"][0]), 0, 1), atol=1e-5)
  # Weights that are not shipped: the error lists what is.
  with pytest.raises(SystemExit):
    reconstruct.main([str(path), "--method", "ours", "--pretrained", "nope", "--no-cache", "--quiet",
                      "--out", str(tmp_path / "x")])
  err = capsys.readouterr().err
  assert "'nope'" in err and "cpu (ours)" in err and "real (ours)" in err and "--checkpoint" in err


@pytest.mark.full
def test_real_undersampling_loads_every_shipped_variant_of_a_name():
  from experiments.studies import real_undersampling as R
  with pytest.raises(ValueError, match=r"cpu \(ours\)"):
    R.load_models(pretrained="nope", log=lambda s: None)
  trained = R.load_models(pretrained="cpu", log=lambda s: None)
  assert set(trained) == {"ours", "ours_s"}     # the measured protocol's networks (its VARIANTS)
  assert trained["ours"][0].frames == 3 and trained["ours_s"][0].frames == 1
  # Without a name, the default: every variant shipped under "real".
  trained = R.load_models(log=lambda s: None)
  assert {"ours", "ours_s"} <= set(trained)
  assert {m.setup.bin_width for m, _ in trained.values()} == {64e-12}


@pytest.mark.full
def test_export_weights_from_a_main_job_workdir(regenerated, tmp_path):
  """The exporter on a main-job layout (config.json, ours/checkpoints, ours/selection.json).

  The shipped Ours saved as step 7 of a workdir whose config reads the regenerated val
  sequence: the export recomputes its score, refuses a recorded score 0.01 dB off, and
  writes weights that load back to the same parameters.
  """
  import optax

  from experiments import export_weights
  from nlosjax import train
  mcfg, params, prov, config, path = regenerated
  workdir = tmp_path / "run"
  (workdir / "ours").mkdir(parents=True)
  (workdir / "config.json").write_text(json.dumps(config))
  state = train.TrainState.create(apply_fn=None, params=params, tx=optax.sgd(0.1))
  ckpt = train.Checkpointer(workdir / "ours" / "checkpoints", json.dumps({"model": repr(mcfg)}), every=1)
  ckpt.save(state.replace(step=7), 0, force=True)
  ckpt.close()
  score = prov["validation"]["per_sequence_psnr_db"]["val-00000"]
  for recorded, ok in ((score + 0.01, False), (score, True)):
    (workdir / "ours" / "selection.json").write_text(json.dumps({"select": "val", "step": 7,
                                                                 "val_psnr": {"7": recorded}}))
    if not ok:
      with pytest.raises(ValueError, match="recomputed"):
        export_weights.export(workdir, "test", "ours", root=tmp_path / "w", commit="abc", log=lambda s: None)
      assert not (tmp_path / "w" / "test-ours").exists()
      continue
    export_weights.export(workdir, "test", "ours", root=tmp_path / "w", commit="abc", log=lambda s: None)
  got_cfg, got, written = inference.load_pretrained("test", "ours", root=tmp_path / "w")
  assert got_cfg == mcfg and written["commit"] == "abc" and written["best_step"] == 7
  # The checkpoint recorded the repr; the export records the config field by field.
  assert written["model_config"] == json.loads(json.dumps(train.model_record(mcfg)))
  assert written["validation"]["per_sequence_psnr_db"] == {"val-00000": score}
  assert written["param_fingerprint"] == prov["param_fingerprint"]
  jax.tree.map(np.testing.assert_array_equal, got, params)


def test_main_job_workdir_records_where_it_trained(tmp_path, monkeypatch):
  """experiments.train appends one record per invocation; the exporter names the first and every resume."""
  from experiments import export_weights, provenance, train
  first = train.record_invocation(tmp_path, ["--config", "real", "--workdir", str(tmp_path)])
  assert first["command"] == f"python -m experiments.train --config real --workdir {tmp_path}"
  assert first["commit"] == provenance.git_commit() and first["cores"] == provenance.usable_cores()
  got = export_weights._invocations(tmp_path)
  assert got["commit"] == first["commit"] and got["command"] == first["command"]
  assert got["machine"]["cpu"] == provenance.cpu_model() and "command" not in got["machine"]
  # A resume at another commit is named; the first record still gives command and machine.
  monkeypatch.setattr(provenance, "git_commit", lambda repo=None: "0123abcd")
  train.record_invocation(tmp_path, ["--workdir", str(tmp_path)])
  got = export_weights._invocations(tmp_path)
  assert got["commit"] == f"{first['commit']} (resumed at 0123abcd)" and got["command"] == first["command"]
  # Without the file: unknown, as before it existed.
  assert export_weights._invocations(tmp_path / "none")["commit"] == "unknown"
  (tmp_path / train.INVOCATIONS).write_text("{not json\n")
  with pytest.raises(ValueError, match="invocations.jsonl"):
    export_weights._invocations(tmp_path)


def _state_copy(tmp_path, row="lfe"):
  """A copy of the committed ``full/<row>-seed0`` run state and its record, as ``(state, results)``."""
  state = tmp_path / "state" / "full" / f"{row}-seed0"
  results = tmp_path / "results"
  shutil.copytree(ROOT / "experiments" / "studies" / "mechanisms" / "state" / "full" / f"{row}-seed0", state)
  (results / "mechanisms" / "full").mkdir(parents=True)
  shutil.copy(ROOT / "experiments" / "studies" / "mechanisms" / "results" / "mechanisms" / "full" / f"{row}-seed0.json",
              results / "mechanisms" / "full")
  return state, results


def test_export_reads_a_committed_run_state(tmp_path):
  """A study's committed state: the selected step's parameters from best.npz, the record's config.

  Checked against what training recorded independently of the exporter: the parameter-tree
  fingerprint in the state's signature, the record's best step and stop reason; a state whose
  selection or record disagrees with it is refused by name.
  """
  from experiments import export_weights
  from nlosjax import train
  state, results = _state_copy(tmp_path)
  record = json.loads((results / "mechanisms" / "full" / "lfe-seed0.json").read_text())
  run = export_weights.find_run(state, "lfe", results)
  assert run["kind"] == "committed run state" and run["variant"] == "lfe"
  assert run["step"] == record["best_step"] and run["stop_reason"] == record["stop_reason"]
  assert run["recorded_val_psnr"] == pytest.approx(record["best_val_psnr"], abs=1e-9)
  assert run["command"].startswith("python -m experiments.studies.mechanisms --budgets full --rows lfe --seeds 0")
  config = RunConfig.from_dict(run["config"])
  mcfg = train.model_config_for(config, inference.training_setup(config), "lfe")
  params, restored = export_weights.state_params(run, mcfg)
  assert restored["step"] == run["step"]
  assert train.param_fingerprint(params) == run["signature"]["params"]
  shapes = jax.eval_shape(mcfg.module().init, jax.random.key(0),
                          jax.ShapeDtypeStruct(mcfg.input_shape(), np.float32))["params"]
  jax.tree.map(lambda a, s: np.testing.assert_equal(a.shape, s.shape), params, shapes)
  with pytest.raises(ValueError, match="not --variant 'ik'"):
    export_weights.find_run(state, "ik", results)
  # A selection naming another step than the best state's is refused.
  sel = json.loads((state / "model" / "selection.json").read_text())
  (state / "model" / "selection.json").write_text(json.dumps({**sel, "step": sel["step"] - 50}))
  with pytest.raises(ValueError, match="best state"):
    export_weights.find_run(state, "lfe", results)
  (state / "model" / "selection.json").write_text(json.dumps(sel))
  # A record whose config builds another model than the one trained is refused.
  record["config"].setdefault("lfe", {}).setdefault("model", {})["extract_width"] = 5
  (results / "mechanisms" / "full" / "lfe-seed0.json").write_text(json.dumps(record))
  run = export_weights.find_run(state, "lfe", results)
  config = RunConfig.from_dict(run["config"])
  mcfg = train.model_config_for(config, inference.training_setup(config), "lfe")
  with pytest.raises(ValueError, match="rebuilt"):
    export_weights.state_params(run, mcfg)


def test_params_checked_on_the_config_a_capture_moves_them_to():
  """``load_pretrained(check_tree=False)`` then ``check_params`` on the moved config (what the
  reconstruct CLI does): the same parameters as the checked load, and a tree that lost a leaf or
  changed a shape is refused there, naming it."""
  from nlosjax.physics.setup import Setup
  capture = Setup(wall_size=0.8, grid=(64, 64), bin_width=64e-12, num_bins=256)
  checked = inference.load_pretrained("cpu", "ours_s")
  mcfg, params, _ = inference.load_pretrained("cpu", "ours_s", check_tree=False)
  assert jax.tree.all(jax.tree.map(lambda a, b: bool((a == b).all()), params, checked[1]))
  moved = inference.for_capture(mcfg, capture).model_config
  inference.check_params(moved, params, "shipped")
  lost = copy.deepcopy(jax.tree.map(np.asarray, params))
  top = sorted(lost)[0]
  lost[top].pop(sorted(lost[top])[0])
  with pytest.raises(ValueError, match="shipped: parameters do not fit the model .missing"):
    inference.check_params(moved, lost, "shipped")
  bent = jax.tree.map(np.asarray, params)
  leaf = jax.tree_util.tree_leaves_with_path(bent)[0]
  bent = jax.tree_util.tree_map_with_path(lambda k, v: v[..., :1] if k == leaf[0] else v, bent)
  with pytest.raises(ValueError, match="shape mismatches"):
    inference.check_params(moved, bent, "shipped")


def test_only_i_k_is_tied_to_its_training_setup():
  """Every shipped network moves to another Setup but I-K, whose kernel volume is its grid's.

  Independent of the check's own tracing: the I-K module's documented kernel shape
  (``IKConfig.kernel_shape``) at the training Setup and at the capture's.
  """
  from nlosjax.physics.setup import Setup
  capture = Setup(wall_size=0.6, grid=(64, 64), bin_width=64e-12, num_bins=256)
  for name, variant in inference.pretrained_names():
    mcfg, _, _ = inference.load_pretrained(name, variant)
    tied = inference.setup_dependent_params(mcfg)
    # The family's declaration (what moving a model reads, untraced) is the traced answer.
    assert tied == inference.traced_setup_dependent_params(mcfg), (name, variant)
    assert type(mcfg).params_depend_on_setup == bool(tied), (name, variant)
    if variant != "ik":
      assert tied == [], (name, variant, tied)
      continue
    assert tied and all("transform" in t and "kernel_" in t for t in tied), tied
    assert str(tuple(mcfg.kernel_shape())) in tied[0]
    with pytest.raises(ValueError, match="runs on that Setup only"):
      inference.for_capture(mcfg, capture)
    tied.clear()                       # the answer kept per model config is not the caller's list
    assert inference.setup_dependent_params(mcfg)

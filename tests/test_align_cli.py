"""python -m experiments.studies.align end to end, the training stage replaced by a recorder.

Independent references: the shipped weights as nlosjax.inference.load_pretrained reads them
(the CLI must hand each fold exactly those parameters), and the leave-one-scan-out count
(each fold gets every other scan's stride^2 offsets, never its own scan).
"""

import jax
import numpy as np
import pytest

from experiments.studies import align as cli
from experiments.studies import alignment as stage
from nlosjax import inference
from nlosjax import train as T
from nlosjax.evaluation import protocol


@pytest.fixture()
def recorded(monkeypatch, tmp_path):
  """Two measured scans (scan a all 0s, b all 1s), the stage, the validator and the data replaced.

  Returns ``(calls, argv)``: the recorded stage calls, the CLI arguments naming the scans.
  """
  scans = tmp_path / "scans"
  scans.mkdir()
  for name in ("data_a.mat", "data_b.mat"):     # read by measured_inputs, replaced below
    (scans / name).write_bytes(b"")
  calls = []

  def fake_align(config, data_path, mcfg, params, measured, folder, **kw):
    calls.append({"folder": folder, "mcfg": mcfg, "params": params, "measured": measured, **kw})
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "params.npz").write_bytes(b"")
    (folder / "align.json").write_text("{}")     # a fold is finished once its record is written
    return params, {}

  monkeypatch.setattr(stage, "align", fake_align)
  monkeypatch.setattr(protocol, "validation_psnr", lambda config, path: "validator")
  monkeypatch.setattr(cli, "measured_inputs", lambda files, mcfg: {
      f.stem[len("data_"):]: np.full((mcfg.stride ** 2, mcfg.frames, 1, 1, 1), i, np.float32)
      for i, f in enumerate(files)})
  data = tmp_path / "synthetic.h5"
  monkeypatch.setattr(T, "ensure_dataset", lambda config, path: None)
  return calls, ["--data-dir", str(scans), "--data", str(data), "--workdir", str(tmp_path / "w")]


def test_each_fold_gets_the_shipped_parameters_and_only_the_other_scans(recorded, tmp_path):
  calls, argv = recorded
  assert cli.main(["--checkpoint", "pretrained:real", "--variants", "ours_s", "--steps", "3", *argv]) == 0
  want_cfg, want, _ = inference.load_pretrained("real", "ours_s")
  assert [c["folder"].name for c in calls] == ["ours_s-without-a", "ours_s-without-b"]
  s2 = want_cfg.stride ** 2
  for c, other in zip(calls, (1.0, 0.0)):    # scan a is 0s, scan b is 1s: each fold sees the other
    assert c["mcfg"] == want_cfg and c["steps"] == 3 and c["validate"] == "validator"
    assert c["measured"].shape[0] == s2 and np.all(c["measured"] == other)
    jax.tree_util.tree_map(np.testing.assert_array_equal, c["params"], want)
  calls.clear()                              # a second call resumes: every folder is done
  assert cli.main(["--checkpoint", "pretrained:real", "--variants", "ours_s", *argv]) == 0
  assert calls == []


def test_an_unknown_source_or_variant_is_refused_before_anything_runs(recorded):
  calls, argv = recorded
  with pytest.raises(SystemExit, match="pretrained:nowhere"):
    cli.main(["--checkpoint", "pretrained:nowhere", *argv])
  with pytest.raises(SystemExit, match="pretrained:real"):
    cli.main(["--checkpoint", "pretrained:real", "--variants", "ours_x", *argv])
  assert calls == []


def test_lam_balanced_sets_each_folds_lam_from_its_own_training_inputs_and_records_it(recorded, monkeypatch):
  calls, argv = recorded
  seen = []

  def fake_norms(config, data_path, mcfg, params, measured, **kw):
    seen.append(float(np.unique(measured)[0]))                     # the fold's inputs: the other scan
    return {"synthetic": [2.0, 4.0, 6.0], "mmd": [0.01, 0.02, 0.03], "mmd_value": [0.0] * 3}
  monkeypatch.setattr(stage, "term_gradient_norms", fake_norms)
  assert cli.main(["--checkpoint", "pretrained:real", "--variants", "ours_s", "--lam", "balanced", *argv]) == 0
  assert seen == [1.0, 0.0]
  for c in calls:
    assert c["lam"] == pytest.approx(4.0 / 0.02)
    assert c["extra"]["lam_rule"]["rule"] == "balanced" and c["extra"]["lam_rule"]["norms"]["mmd"][1] == 0.02
  for bad in ("-1", "lots"):
    with pytest.raises(SystemExit):
      cli.main(["--checkpoint", "pretrained:real", "--lam", bad, *argv])


def test_layer_auto_chooses_each_folds_layer_on_its_own_training_inputs_and_records_it(recorded, monkeypatch):
  calls, argv = recorded
  seen = []

  class Loader:                        # the synthetic training batches: 7s, [B, 3 frames, ...]
    def batch(self, k):
      return {"measurement": np.full((2, 3, 1, 1, 1), 7.0, np.float32)}

    def close(self):
      pass

  def fake_separation(mcfg, params, synthetic, measured, **kw):
    seen.append((float(np.unique(synthetic)[0]), synthetic.shape[1], float(np.unique(measured)[0])))
    # The fold without scan a (it trains on scan b's 1s) finds its inputs furthest off at st_mamba0.
    far = "st_mamba0" if np.all(measured == 1.0) else "cross_prev1_0"
    return {name: {"z": 9.0 if name == far else 1.0} for name in ("extract", "st_mamba0", "cross_prev1_0")}

  monkeypatch.setattr(T, "make_loader", lambda *a, **kw: Loader())
  monkeypatch.setattr(stage, "layer_separation", fake_separation)
  assert cli.main(["--checkpoint", "pretrained:real", "--variants", "ours_s", "--layer", "auto", *argv]) == 0
  frames = inference.load_pretrained("real", "ours_s")[0].frames
  assert seen == [(7.0, frames, 1.0), (7.0, frames, 0.0)]   # synthetic cut to the model's frames; the other scan
  assert [c["layer"] for c in calls] == ["st_mamba0", "cross_prev1_0"]
  assert [c["extra"]["layer_rule"]["separation"]["st_mamba0"]["z"] for c in calls] == [9.0, 1.0]
  calls.clear()
  assert cli.main(["--checkpoint", "pretrained:real", "--variants", "ours_s", "--layer", "extract", *argv[:2],
                   *argv[2:4], "--workdir", str(argv[-1]) + "-fixed"]) == 0
  assert [c["layer"] for c in calls] == ["extract", "extract"] and all(c["extra"] is None for c in calls)


def test_a_fold_without_its_record_is_not_finished(recorded, tmp_path):
  calls, argv = recorded
  half = cli.fold_folder(tmp_path / "w", "ours_s", "a")
  half.mkdir(parents=True)
  (half / "params.npz").write_bytes(b"")                             # killed before align.json was written
  assert cli.main(["--checkpoint", "pretrained:real", "--variants", "ours_s", *argv]) == 0
  assert [c["folder"].name for c in calls] == ["ours_s-without-a", "ours_s-without-b"]

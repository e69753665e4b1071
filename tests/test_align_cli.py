"""python -m experiments.align end to end, the training stage replaced by a recorder.

Independent references: the shipped weights as nlosjax.inference.load_pretrained reads them
(the CLI must hand each fold exactly those parameters), and the leave-one-scan-out count
(each fold gets every other scan's stride^2 offsets, never its own scan).
"""

import jax
import numpy as np
import pytest

from experiments import align as cli
from nlosjax import inference
from nlosjax import train as T
from nlosjax.evaluation import protocol
from nlosjax.train import align as stage


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

"""experiments.studies.mitransient without mitsuba: the set's assembly, its file, its scoring.

A stand-in renderer (exact-distance points of each tile,
:func:`experiments.independent_set.point_transient`) takes mitransient's
place; the references are the preset's own sequence
(:func:`nlosjax.data.dataset.simulate_sequence`: the same ground truth and
detector draws) and the protocol reading the written file.
"""

import json

import h5py
import numpy as np
import pytest

from experiments import configs
from experiments.independent_set import point_transient
from experiments.studies import mitransient as M
from nlosjax.train import RunConfig


def tiny_config() -> RunConfig:
  cfg = configs.get_config("cpu")
  data = {**cfg["data"], "grid": 12, "num_bins": 48, "bin_width": 264e-12, "frames": 3,
          "num_sequences": {"train": 0, "test": 2, "val": 0}}
  return RunConfig.from_dict({**cfg, "data": data})


def stand_in(calls: list):
  """A ``render_frame`` from the tiles' centres (no mitsuba); records each call's tile count and seed."""
  def render_frame(patches, setup, seed):
    calls.append((len(patches), seed))
    c = np.asarray([p.centre for p in patches])
    w = np.asarray([p.albedo * 4 * p.half_size[0] * p.half_size[1] for p in patches])
    return point_transient(c[:, 0], c[:, 1], c[:, 2], w, setup).astype(np.float32)
  return render_frame


def test_only_the_renderer_changes_from_the_presets_sequence():
  from nlosjax.data.dataset import simulate_sequence
  spec = tiny_config().data.spec()
  calls = []
  seq = M.make_sequence(spec, 1, stand_in(calls))
  ours = simulate_sequence(spec, "test", 1)
  assert seq["name"] == ours["name"] == "test-00001"
  for key in ("intensity", "depth", "trajectory"):           # the preset's ground truth
    np.testing.assert_array_equal(seq["arrays"][key], ours["arrays"][key])
  for key in ("seed", "efficiency", "photons", "ambient", "dark_counts", "jitter"):   # its detector draws
    assert seq["attrs"][key] == ours["attrs"][key], key
  # One render per frame, each with its own seed, of the frame's tiles.
  assert [n for n, _ in calls] == json.loads(seq["attrs"]["tiles"]) and len(calls) == spec.frames
  assert all(n > 0 for n, _ in calls) and len({s for _, s in calls}) == spec.frames
  clean, counts = seq["arrays"]["clean"], seq["arrays"]["measurement"]
  assert clean.shape == counts.shape == (3, 48, 12, 12) and counts.dtype == np.uint16
  assert clean.sum(axis=1).mean() == pytest.approx(seq["attrs"]["photons"], rel=1e-5)   # the photon budget
  # Counts: efficiency x (signal + ambient) + dark counts, Poisson: the totals agree within a few sigma.
  expected = seq["attrs"]["efficiency"] * (clean.sum() + seq["attrs"]["ambient"] * clean.size) \
      + seq["attrs"]["dark_counts"] * clean.size
  assert abs(counts.sum() - expected) < 6 * np.sqrt(expected) + 0.01 * expected


def test_the_set_is_written_reused_refused_and_scored_beside_the_presets_split(tmp_path):
  from nlosjax import train as T
  from nlosjax.evaluation import protocol, report
  cfg = tiny_config()
  spec = cfg.data.spec()
  attr = M.set_attr(spec, 2, 64, 6)
  path = M.ensure_set(tmp_path / "set.h5", spec, 2, stand_in([]), attr, log=lambda s: None)
  with h5py.File(path) as f:
    assert f.attrs["complete"] and f.attrs["generator_version"] == M.GENERATOR_VERSION
    assert sorted(f["sequences"]) == ["test-00000", "test-00001"] and f.attrs["num_test"] == 2
  assert not (tmp_path / "set.h5.partial").exists()

  def no_render(*_):
    raise AssertionError("a cached set is not rendered again")
  assert M.ensure_set(path, spec, 2, no_render, attr, log=lambda s: None) == path
  with pytest.raises(ValueError, match="another mitransient set"):
    M.ensure_set(path, spec, 2, no_render, M.set_attr(spec, 2, 128, 6), log=lambda s: None)

  # Both files through the protocol (one classic method, no networks: fast), paired frame by frame.
  reference = tmp_path / "preset.h5"
  T.ensure_dataset(cfg, reference, log=lambda s: None)
  results = []
  for p in (path, reference):
    ev = protocol.evaluate(cfg, p, {}, methods=("fbp",), log=lambda s: None)
    table, comparisons = protocol.tabulate(ev, n_boot=200)
    results.append({"evaluation": ev, "table": table, "comparisons": comparisons})
  on_set, ref = results
  assert on_set["evaluation"]["n_frames"] == 2                # one middle frame per 3-frame sequence
  np.testing.assert_array_equal(on_set["evaluation"]["images"]["gt"]["depth"],
                                ref["evaluation"]["images"]["gt"]["depth"])
  change = M.changes(on_set, ref)
  assert set(change) == {"fbp"} and set(change["fbp"]) == set(M.CHANGE_METRICS)
  want = np.nanmean(on_set["evaluation"]["scores"]["fbp"]["psnr"] - ref["evaluation"]["scores"]["fbp"]["psnr"])
  assert change["fbp"]["psnr"]["mean"] == pytest.approx(want)
  assert M.changes(ref, ref)["fbp"]["psnr"]["mean"] == 0.0
  shifted = {**ref, "evaluation": {**ref["evaluation"], "frame": ref["evaluation"]["frame"] + 1}}
  with pytest.raises(ValueError, match="other frames"):
    M.changes(on_set, shifted)
  text = M.report_text("cmd", header=["Produced by `cmd`."], set_file=path, reference_file=reference,
                       on_set=on_set, reference=ref, change=change, best="fbp", variants=(),
                       weights="cpu", sequences=2, samples=64, max_depth=6, val_path=reference, wall=1.0)
  # The object table first, each section present, what the path tracer adds and leaves out named.
  assert text.index("object intensity error") < text.index("intensity PSNR (dB)")
  for heading in ("## Headline", "## What the path tracer adds", "## The mitransient set",
                  "## Change from our renderer", "## The same scenes from our renderer"):
    assert heading in text, heading
  assert all(f"- {a}." in text for a in M.ADDS + M.LEAVES_OUT)
  assert f"| {report.label('fbp')} |" in text

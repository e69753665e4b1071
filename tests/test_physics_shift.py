"""experiments.studies.physics_shift: the held-out renderer, the study's configs and its report.

Independent references: a triple loop over points, scan points and the
radiometric formula for the held-out renderer; a hand-made pair of records
whose differences are known for the report.
"""

import json
import math

import h5py
import numpy as np
import pytest

from experiments import configs
from experiments.studies.physics_shift import heldout, report, study
from nlosjax.train import RunConfig


def loop_returns(x, y, z, w, scan_x, scan_y, bin_length, T, power, cosines):
  out = np.zeros((T, len(scan_y), len(scan_x)))
  for p in range(len(x)):
    for i, sy in enumerate(scan_y):
      for j, sx in enumerate(scan_x):
        r = math.sqrt((x[p] - sx) ** 2 + (y[p] - sy) ** 2 + z[p] ** 2)
        k = int(math.floor(2 * r / bin_length))
        if k < T:
          out[k, i, j] += w[p] * (z[p] / r) ** (cosines * power) / r ** power
  return out


@pytest.mark.parametrize("power,cosines", [(4, 0), (4, 1), (2, 0), (2, 1)])
def test_point_returns_match_a_loop(power, cosines):
  rng = np.random.default_rng(power + 10 * cosines)
  x, y = rng.uniform(-0.5, 0.5, (2, 30))
  z, w = rng.uniform(0.4, 1.6, 30), rng.uniform(0.1, 1.0, 30)
  sx, sy = np.linspace(-0.9, 0.9, 5), np.linspace(-0.8, 0.8, 4)
  got = heldout.point_returns(x, y, z, w, sx, sy, 0.04, 90, power=power, cosines=cosines)
  want = loop_returns(x, y, z, w, sx, sy, 0.04, 90, power, cosines)
  assert want.sum() > 0
  np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)


def test_a_written_condition_is_read_by_the_evaluation_protocol(tmp_path):
  from nlosjax.evaluation import protocol
  cfg = configs.get_config("cpu")
  data = {**cfg["data"], "grid": 16, "num_bins": 64, "bin_width": 264e-12, "input_stride": 4, "input_offset": 2}
  path = heldout.write_condition(tmp_path / "far.h5", data, "far", sequences=2, frames=3, seed=1,
                                 progress=False)
  with h5py.File(path) as f:
    assert f.attrs["complete"] and f.attrs["generator_version"] == heldout.GENERATOR_VERSION
    cond = json.loads(f.attrs["condition"])
    assert cond["name"] == "far" and cond["depth"] == [0.9, 1.8]
    assert cond["photons"] == [float(p) for p in data["photons"]]
    g = f["sequences/test-00001"]
    assert g["measurement"].shape == (3, 64, 16, 16) and g["measurement"].dtype == np.uint32
    depth = g["depth"][...]
    assert depth[depth > 0].min() >= 0.9 - 1e-6 and depth.max() <= 1.8 + 1e-6
    # The clean transient meets its photon budget on average over the sequence.
    assert g["clean"][...].sum(axis=1).mean() == pytest.approx(g.attrs["photons"], rel=1e-4)
  assert heldout.ensure_condition(path, data, "far", 2, 3, 1) == path        # the same set: reused
  with pytest.raises(ValueError, match="another held-out set"):
    heldout.ensure_condition(path, {**data, "photons": (1.0, 2.0)}, "far", 2, 3, 1)
  split = protocol.load_split(RunConfig.from_dict({**cfg, "data": data}), path, "test", batch_size=4)
  split["loader"].close()
  assert split["measurement"].shape == (2, 64, 4, 4) and split["intensity"].shape == (2, 16, 16)


def test_design_configs_name_their_families_and_files():
  base = configs.get_config("cpu")
  mix = study.design_config(base, "mix")
  assert mix["data"]["renderer"] == "mix" and mix["data"]["physics"]["families"] == list(study.FAMILIES)
  no_lct = study.design_config(base, "no_lct")
  assert no_lct["data"]["physics"]["families"] == ["transport", "points"]
  stem = f"runs/data/cpu-v3-mix-{study.physics_digest(None)}"
  assert no_lct["data"]["path"] == f"{stem}-no-lct.h5" and mix["data"]["path"] == f"{stem}.h5"
  assert study.data_stem(mix) == stem.split("/")[-1]
  other = study.design_config(base, "mix", {"time_shift": 0})
  assert other["data"]["path"] != mix["data"]["path"] and other["data"]["physics"]["time_shift"] == 0
  assert study.physics_digest({"families": ["lct"]}) == study.physics_digest({})
  wide = study.design_config(base, "wide")
  assert wide["data"]["path"] == f"{stem}-wide.h5"
  scene = wide["data"]["scene"]
  assert scene["size_range"] == (0.15, 1.0) and scene["lateral_extent"] == 0.7
  assert scene["depth_range"] == (0.4, 2.0) and mix["data"]["scene"] == base["data"]["scene"]
  fam = study.family_set_config(base, "points")
  assert fam["data"]["physics"]["families"] == ["points"] and fam["data"]["num_sequences"] == {"train": 0, "test": 8}
  assert study.design_config(base, "base")["data"]["path"] == base["data"]["path"]
  # A preset that adopted a mix: base is its scenes by the transport renderer alone, in a file of its own.
  adopted = study.design_config(base, "mix")
  transport = study.design_config(adopted, "base")["data"]
  assert transport["renderer"] == "transport" and "physics" not in transport
  assert transport["retroreflective"] == 0.2 and transport["path"] == "runs/data/cpu-v3-transport.h5"
  assert study.classic_design("family:lct") == "no_lct" and study.classic_design("heldout:far") == "mix"
  assert study.sets_of("no_points", {"family:points": 0, "heldout:far": 0}) == ["family:points"]
  # wide_base: base's renderer and file stem, wide's scenes; scored on every set.
  wide_base = study.design_config(base, "wide_base")["data"]
  assert wide_base["renderer"] == "transport" and "physics" not in wide_base
  assert wide_base["path"] == "runs/data/cpu-v3-wide.h5" and wide_base["scene"] == scene
  assert study.sets_of("wide_base", {"val:base": 0, "heldout:far": 0}) == ["val:base", "heldout:far"]


def _frames(offset):
  seq = np.repeat(np.arange(4), 3)
  return {"sequence": seq.tolist(), "frame": np.tile([1, 2, 3], 4).tolist(),
          "scores": {"psnr": (20.0 + offset + 0.1 * seq).tolist(), "recall": [0.8] * 12}}


def test_report_differences_and_goal_from_records():
  name = "family:lct"
  runs = {("no_lct", "ours"): {"sets": {name: _frames(2.0)}},
          ("no_lct", "ours_s"): {"sets": {name: _frames(1.5)}}}
  classic = {("no_lct", name): {"best": "rsd", "sequence": np.repeat(np.arange(4), 3).tolist(),
                                "methods": {m: {"psnr": _frames(0.5 if m == "rsd" else -1)["scores"]["psnr"],
                                                "recall": [0.7] * 12}
                                            for m in ("fbp", "lct", "fk", "phasor", "rsd")}}}
  c = report.compare(runs, classic, name, "no_lct")
  assert c["diff"]["ours"]["psnr"]["mean"] == pytest.approx(1.5)
  assert c["diff"]["ours"]["recall"]["mean"] == pytest.approx(0.1)
  assert c["ours_vs_ours_s"]["mean"] == pytest.approx(0.5)
  assert report._goal(c) == "met"
  runs[("no_lct", "ours")]["sets"][name] = _frames(1.0)        # +0.5 dB only: misses the 1 dB margin
  assert report._goal(report.compare(runs, classic, name, "no_lct")) == "missed"
  text = report.to_markdown(runs, classic, ["header"], ["base"])
  assert "| lct |" in text and "Runs still missing" in text


def test_wider_scenes_table_reports_object_error_against_the_best_classic_method():
  name, seq = "heldout:large", np.repeat(np.arange(4), 3).tolist()

  def frames(psnr, error):
    return {"sequence": seq, "frame": np.tile([1, 2, 3], 4).tolist(),
            "scores": {"psnr": [psnr] * 12, "recall": [0.8] * 12, "intensity_mae_object": [error] * 12}}

  runs = {("wide_base", "ours"): {"sets": {name: frames(18.0, 0.20)}},
          ("wide_base", "ours_s"): {"sets": {name: frames(17.5, 0.22)}}}
  classic = {("mix", name): {"best": "phasor", "sequence": seq,
                             "methods": {m: frames(16.0 if m == "phasor" else 12.0, 0.25)["scores"]
                                         for m in ("fbp", "lct", "fk", "phasor", "rsd")}}}
  lines = report._wider_scenes(runs, classic, ["large"])
  row = next(x for x in lines if x.startswith("| large | wide_base |"))
  # Ours 18 dB, +2 over phasor; object error 0.20 against 0.25 (-0.05); Ours - Ours-S +0.5 dB.
  assert "18.00" in row and "+2.00" in row and "0.200" in row and "phasor 0.250" in row
  assert "-0.050" in row and "+0.50" in row
  assert any(x.startswith("| large | base | (not run)") for x in lines)
  # Records written before the object error was scored: the row says so instead of failing.
  del runs[("wide_base", "ours")]["sets"][name]["scores"]["intensity_mae_object"]
  row = next(x for x in report._wider_scenes(runs, classic, ["large"]) if x.startswith("| large | wide_base |"))
  assert "18.00" in row and row.count("not scored") == 3


def test_the_stored_trajectory_is_where_the_dynamic_object_was_drawn(tmp_path):
  """As for the independent set (tests/test_independent_set.py): the held-out renderer's trajectory
  against its rendered depth maps, with this renderer's scan-pixel centres."""
  from tests.test_independent_set import dynamic_object_checks
  cfg = configs.get_config("cpu")
  data = {**cfg["data"], "grid": 16, "num_bins": 64, "bin_width": 264e-12}
  path = heldout.write_condition(tmp_path / "base.h5", data, "base", sequences=3, frames=4, seed=2,
                                 progress=False)
  centres = -1.0 + (np.arange(16) + 0.5) * 2.0 / 16          # wall 2 m, 16 pixels
  checked = 0
  with h5py.File(path) as f:
    for g in f["sequences"].values():
      traj = g["trajectory"][...]
      assert traj.shape == (4, 3)
      size = json.loads(g.attrs["objects"])[-1]["size"]
      checked += dynamic_object_checks(g["depth"][...], traj, size, centres, centres)
  assert checked >= 10

"""experiments.studies.headroom: the truth through the scan grid, the breakdown's bins, the report.

Independent references: an 8 x 8 case worked out by hand (two objects at two scan points)
and the classic methods' own reading of a sparse scan
(:func:`nlosjax.evaluation.baselines.upsample_scan`); loops over frames for the attributes,
the terciles and the per-bin means; hand-made records whose differences are known for the report.
"""

import json

import h5py
import numpy as np
import pytest

from experiments.studies.headroom import bounds, breakdown, report, study
from nlosjax.evaluation import baselines


# ---------------------------------------------------------------------------- bounds
def hand_case():
  """8 x 8 grid, stride 4: scan points at rows/columns 2 and 6. An object of depth 1 m and intensity
  0.8 covers the scan point (2, 2), one of 2 m and intensity 0.4 the point (2, 6); the rest is
  background, also where no scan point falls (pixel (7, 7) is object in the truth, never sampled)."""
  inten = np.zeros((8, 8), np.float32)
  depth = np.zeros((8, 8), np.float32)
  inten[1:4, 1:4], depth[1:4, 1:4] = 0.8, 1.0
  inten[1:4, 5:8], depth[1:4, 5:8] = 0.4, 2.0
  inten[7, 7], depth[7, 7] = 1.0, 1.5
  return inten, depth


def test_the_scan_points_are_the_models():
  inten, depth = hand_case()
  s = bounds.sample(depth, 4)
  np.testing.assert_array_equal(s, [[1.0, 2.0], [0.0, 0.0]])


def test_nearest_reading_by_hand():
  # rows 0-3 read the scan point at 2, rows 4-7 the one at 6 (row 4 is as far from both: the later).
  want = np.zeros((8, 2))
  want[:4, 0] = 1
  want[4:, 1] = 1
  np.testing.assert_array_equal(bounds.nearest_matrix(8, 4), want)
  inten, depth = hand_case()
  i, d = bounds.bound_images(inten, depth, 4, "nearest")
  want_d = np.zeros((8, 8))
  want_d[:4, :4], want_d[:4, 4:] = 1.0, 2.0
  np.testing.assert_array_equal(d, want_d)
  want_i = np.zeros((8, 8))
  want_i[:4, :4], want_i[:4, 4:] = 0.8, 0.4
  np.testing.assert_allclose(i, want_i, rtol=1e-6)


def test_bilinear_reading_by_hand():
  """Along an axis the scan point at 2 weighs 1, 1, 1, 0.75, 0.5, 0.25, 0, 0 on pixels 0-7 (constant
  before it, linear to the point at 6): worked out from the model's convention, not the code."""
  w0 = np.array([1, 1, 1, 0.75, 0.5, 0.25, 0, 0])
  w1 = 1 - w0
  inten, depth = hand_case()
  i, d = bounds.bound_images(inten, depth, 4, "bilinear", cut=0.5)
  # Only the top row of scan points holds objects: the row weight is w0.
  np.testing.assert_allclose(i, np.outer(w0, 0.8 * w0 + 0.4 * w1), rtol=1e-6)
  # Pixel (2, 4) lies half-way between the two objects' points: surface (indicator 1), depth their mean.
  assert d[2, 4] == pytest.approx(1.5)
  # Pixel (3, 3): indicator 0.75 >= 0.5, both neighbours' depths weighted 0.75 * (0.75, 0.25).
  assert d[3, 3] == pytest.approx((0.75 * 1.0 + 0.25 * 2.0) / 1.0)
  # Pixel (4, 0): indicator 0.5 (the cut): surface at 1 m; pixel (5, 0): 0.25, background.
  assert d[4, 0] == pytest.approx(1.0) and d[5, 0] == 0
  # The never-sampled object at (7, 7) is lost; rows 5-7 read background only.
  assert np.all(d[5:] == 0) and np.all(i[6:] == 0)
  # Every surface pixel's depth lies between the two objects' depths: background never pulls it to 0.
  assert np.all((d == 0) | ((d >= 1.0 - 1e-6) & (d <= 2.0 + 1e-6)))
  # A higher cut keeps fewer pixels, each at the same depth.
  _, d9 = bounds.bound_images(inten, depth, 4, "bilinear", cut=0.9)
  assert (d9 > 0).sum() < (d > 0).sum() and np.all((d9 == 0) | (d9 == d))


def test_bilinear_intensity_is_the_classic_methods_reading_of_the_sparse_scan():
  rng = np.random.default_rng(0)
  inten = rng.uniform(size=(3, 32, 32)).astype(np.float32)
  depth = np.where(inten > 0.5, 1.0, 0.0).astype(np.float32)
  got, _ = bounds.bound_images(inten, depth, 4, "bilinear")
  want = np.asarray(baselines.upsample_scan(inten[:, None, 2::4, 2::4], (32, 32), 4))[:, 0]
  np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_bound_refuses_a_cut_outside_0_1():
  inten, depth = hand_case()
  with pytest.raises(ValueError, match="cut"):
    bounds.bound_images(inten, depth, 4, "bilinear", cut=0.0)
  with pytest.raises(ValueError, match="reading"):
    bounds.bound_images(inten, depth, 4, "cubic")


# ---------------------------------------------------------------------------- breakdown
def loop_quantile(values, q):
  v = sorted(x for x in values if np.isfinite(x))
  pos = (len(v) - 1) * q
  lo = int(np.floor(pos))
  hi = min(lo + 1, len(v) - 1)
  return v[lo] + (pos - lo) * (v[hi] - v[lo])


def test_terciles_and_bins_match_a_loop():
  rng = np.random.default_rng(1)
  values = np.round(rng.uniform(0, 1, 61), 1)          # many ties, some at the edges
  values[[3, 17]] = np.nan
  edges = breakdown.tercile_edges(values)
  np.testing.assert_allclose(edges, [loop_quantile(values, 1 / 3), loop_quantile(values, 2 / 3)])
  got = breakdown.bins(values, edges)
  for v, b in zip(values, got):
    if not np.isfinite(v):
      assert b == -1
    elif v <= edges[0]:
      assert b == 0
    elif v <= edges[1]:
      assert b == 1
    else:
      assert b == 2
  assert set(got.tolist()) == {-1, 0, 1, 2}


def test_bin_means_and_counts_match_a_loop():
  rng = np.random.default_rng(2)
  seq = np.repeat(np.arange(6), 5)
  which = rng.integers(-1, 3, seq.size)
  scores = {"f1": rng.uniform(size=seq.size), "precision": rng.uniform(size=seq.size)}
  scores["precision"][::7] = np.nan
  got = breakdown.bin_summaries(scores, seq, which, n_boot=200)
  for b in range(3):
    for k, v in scores.items():
      vals = [v[n] for n in range(seq.size) if which[n] == b and np.isfinite(v[n])]
      seqs = {seq[n] for n in range(seq.size) if which[n] == b and np.isfinite(v[n])}
      assert got[b][k]["mean"] == pytest.approx(sum(vals) / len(vals))
      assert got[b][k]["n_frames"] == len(vals) and got[b][k]["n_sequences"] == len(seqs)
  diff = breakdown.bin_differences(scores, {k: v * 0 + 0.25 for k, v in scores.items()}, seq, which, n_boot=200)
  for b in range(3):
    assert diff[b]["f1"]["mean"] == pytest.approx(got[b]["f1"]["mean"] - 0.25)


def test_frame_attributes_match_a_loop(tmp_path):
  """A file by hand: two sequences, their photons, kinds or objects, trajectories; attributes by loops."""
  path = tmp_path / "set.h5"
  rng = np.random.default_rng(3)
  traj = {0: rng.uniform(-1, 1, (5, 3)), 1: rng.uniform(-1, 1, (5, 3))}
  depth = {s: np.where(rng.uniform(size=(5, 6, 6)) > 0.6, rng.uniform(0.5, 1.5, (5, 6, 6)), 0.0) for s in (0, 1)}
  with h5py.File(path, "w") as f:
    f.attrs.update({"format": "nlosjax-dynamic-nlos", "format_version": 1, "wall_size": 2.0, "grid": [6, 6],
                    "bin_width": 1e-10, "num_bins": 4, "complete": True})
    for s in (0, 1):
      g = f.create_group(f"sequences/test-{s:05d}")
      g.attrs.update({"split": "test", "photons": 100.0 * (s + 1), "efficiency": 0.1 * (s + 1)})
      g.attrs["kinds" if s == 0 else "objects"] = json.dumps(["a", "b"] if s == 0 else [{}, {}, {}])
      g["measurement"] = np.zeros((5, 4, 6, 6), np.uint16)
      g["intensity"] = (depth[s] > 0).astype(np.float32)
      g["depth"] = depth[s].astype(np.float32)
      g["trajectory"] = traj[s]
  sequence, frame = np.array([0, 0, 1, 1, 1]), np.array([1, 3, 1, 2, 3])
  gt = np.stack([depth[s][m] for s, m in zip(sequence, frame)]).astype(np.float32)
  got = breakdown.frame_attributes(path, "test", sequence, frame, gt)
  for n, (s, m) in enumerate(zip(sequence, frame)):
    d = depth[s][m]
    obj = [d[i, j] for i in range(6) for j in range(6) if d[i, j] > 0]
    assert got["size"][n] == pytest.approx(len(obj) / 36)
    assert got["depth"][n] == pytest.approx(sum(obj) / len(obj), rel=1e-6)
    assert got["photons"][n] == 100.0 * (s + 1) and got["efficiency"][n] == pytest.approx(0.1 * (s + 1))
    assert got["objects"][n] == (2 if s == 0 else 3)
    step = lambda a, b: float(np.sqrt(sum((traj[s][b][k] - traj[s][a][k]) ** 2 for k in range(3))))
    assert got["motion"][n] == pytest.approx((step(m - 1, m) + step(m, m + 1)) / 2)
    assert got["name"][n] == f"test-{s:05d}"


# ---------------------------------------------------------------------------- report
METHODS = (study.ZERO, *study.CLASSIC, *(study.oracle(m, src) for m in ("fbp", "lct") for src in study.INPUTS),
           "ours_s", "ours", *study.TRUTH)


def fake_records(n_seq=6, frames=4):
  """Three groups of sets. Each method's score on a frame is a fixed offset from the frame's size;
  Ours is 0.1 worse than FBP in object intensity error on the smallest third of the frames
  (size < 0.1) and 0.05 better elsewhere; the bilinear truth is 0.02 better than Ours everywhere.
  FBP is the reference of every score but the recall's, LCT's."""
  rng = np.random.default_rng(4)
  offset = {m: i * 0.01 for i, m in enumerate(METHODS)}
  sets = {}
  for name in ("test", "independent", "heldout-base", "heldout-far"):
    seq = np.repeat(np.arange(n_seq), frames)
    size = rng.permutation(np.linspace(0.0, 0.3, seq.size))      # its lower tercile: size < 0.1
    attrs = {"size": size, "objects": np.full(seq.size, 2.0), "depth": rng.uniform(0.5, 1.5, seq.size),
             "photons": np.repeat(rng.uniform(50, 2000, n_seq), frames), "efficiency": np.full(seq.size, 0.1),
             "motion": rng.uniform(0, 0.1, seq.size)}
    methods = {}
    for m in METHODS:
      s = {k: size + offset[m] for k in study.REFERENCE_SCORES + ("psnr_zero", "psnr_balanced_zero")}
      methods[m] = {"method": m, "scores": s}
    ours = methods["ours"]["scores"]["intensity_mae_object"]
    ours[:] = methods["fbp"]["scores"]["intensity_mae_object"] + np.where(size < 0.1, 0.1, -0.05)
    for k in study.OBJECT_SCORES:
      sign = -1 if k in ("intensity_mae_object", "rmse_object") else 1
      methods["truth_bilinear"]["scores"][k] = methods["ours"]["scores"][k] + sign * 0.02
    sets[name] = {"path": name, "split": "test", "sequence": seq, "frame": np.tile(np.arange(frames), n_seq),
                  "name": [f"s{s}" for s in seq], "attributes": attrs, "methods": methods}
  choices = {"reference": {**{k: "fbp" for k in study.REFERENCE_SCORES}, "recall": "lct"}}
  return {"choices": choices, "sets": sets, "invocations": []}


def test_summary_pools_the_heldout_conditions_and_keeps_their_sequences_apart():
  records = fake_records()
  s = report.summarise(records, n_boot=200)
  assert list(s["groups"]) == ["test", "independent", "heldout"]
  held = s["groups"]["heldout"]
  assert held["n_sequences"] == 12 and held["n_frames"] == 48 and list(held["conditions"]) == ["base", "far"]
  both = np.concatenate([records["sets"][n]["methods"]["ours"]["scores"]["f1"]
                         for n in ("heldout-base", "heldout-far")])
  assert held["table"]["ours"]["f1"]["mean"] == pytest.approx(both.mean())
  assert held["table"]["ours"]["f1"]["n_sequences"] == 12


def test_report_gaps_are_the_known_differences():
  records = fake_records()
  s = report.summarise(records, n_boot=200)
  for e in s["groups"].values():
    gap = e["gaps"]["truth_bilinear - ours"]
    assert gap["intensity_mae_object"]["mean"] == pytest.approx(-0.02)
    assert gap["f1"]["mean"] == pytest.approx(0.02)
    # Per size tercile, Ours - FBP on the object intensity error, against a loop over the frames.
    split = e["breakdown"]["size"]
    for b, rng_ in enumerate(split["bins"]):
      lo, hi = rng_["lo"], rng_["hi"]
      size = np.concatenate([records["sets"][n]["attributes"]["size"] for n in e["sets"]])
      sel = (size >= lo) & (size <= hi)
      want = np.where(size[sel] < 0.1, 0.1, -0.05).mean()
      assert split["gaps"]["ours - reference"][b]["intensity_mae_object"]["mean"] == pytest.approx(want)
  text = report.to_markdown(s, ["Produced by `x`."], records["choices"], stride=4, grid=(32, 32))
  assert "8 × 8 scan points" in text
  assert text.index("## Objects on the `cpu` preset's test split") < text.index("### Broken down on the `cpu`")
  # Ours is worse (higher object error) than FBP in the smallest size tercile, better in the others.
  line = next(l for l in text.splitlines()
              if l.startswith("- Ours − reference classic method, object intensity error"))
  better, worse = (part.split(" in ", 1)[1].rstrip(".").split(", ") for part in line.split("; "))
  assert "size 1" in worse and "size 2" in better and "size 3" in better, line
  assert "| all-zero image |" in text and "| truth at the scan points, bilinear |" in text


def test_reference_rows_take_each_score_from_its_reference():
  """The composite rows: recall from LCT, every other score from FBP, on each input (a loop over the
  records), and the difference of a better input's row to the input's row."""
  records = fake_records()
  s = report.summarise(records, n_boot=200)
  e = records["sets"]["test"]["methods"]
  for row, suffix in (("reference", ""), *((f"reference@{src}", f"@{src}") for src in study.INPUTS)):
    got = s["groups"]["test"]["table"][row]
    for k in study.REFERENCE_SCORES:
      source = ("lct" if k == "recall" else "fbp") + suffix
      assert got[k]["mean"] == pytest.approx(np.nanmean(e[source]["scores"][k])), (row, k)
  d = s["groups"]["test"]["gaps"]["reference@full - reference"]
  want = np.mean(e["lct@full"]["scores"]["recall"] - e["lct"]["scores"]["recall"])
  assert d["recall"]["mean"] == pytest.approx(want)


def test_reference_classic_is_the_best_validation_mean_with_direction_and_ties():
  means = {m: {k: 0.5 for k in study.REFERENCE_SCORES} for m in study.CLASSIC}
  means["lct"]["recall"] = 0.9               # higher is better
  means["fk"]["intensity_mae_object"] = 0.1  # lower is better
  ref = study.reference_classic(means)
  assert ref["recall"] == "lct" and ref["intensity_mae_object"] == "fk"
  assert ref["f1"] == "fbp"                  # a tie keeps the first


# ---------------------------------------------------------------------------- the command, end to end
@pytest.mark.full
def test_tiny_study_resumes_from_its_records_and_rebuilds_its_report(tmp_path):
  """--tiny twice: the second invocation writes no record again; --report-only rebuilds the same tables
  from the records alone (only the header and the list of invocations differ)."""
  from experiments.studies.headroom.__main__ import main
  args = ["--tiny", "--results", str(tmp_path), "--conditions", "base", "--methods", "fbp", "phasor"]
  assert main(args) == 0
  records = sorted((tmp_path / "headroom").glob("*/*.json"))
  names = {p.parent.name for p in records}
  assert names == {"val", "test", "independent", "heldout-base"}
  for folder in names - {"val"}:
    got = {p.stem for p in (tmp_path / "headroom" / folder).glob("*.json")}
    want = {"attributes", "zero", "fbp", "phasor", "truth_bilinear", "truth_nearest"}
    refs = set(json.loads((tmp_path / "headroom" / "choices.json").read_text())["reference"].values())
    want |= {study.oracle(m, src) for m in refs for src in study.INPUTS}
    assert got == want, got
  stamps = {p: p.stat().st_mtime_ns for p in records}
  first = (tmp_path / "headroom.md").read_text()
  assert main(args) == 0
  assert {p: p.stat().st_mtime_ns for p in records} == stamps
  assert main(["--tiny", "--results", str(tmp_path), "--report-only"]) == 0
  again = (tmp_path / "headroom.md").read_text()

  def body(text):
    return text.split("\nEvery method on the objects", 1)[1].split("The records were written by", 1)[0]
  assert body(again) == body(first)
  summary = json.loads((tmp_path / "headroom.json").read_text())
  assert set(summary["groups"]) == {"test", "independent", "heldout"}
  assert (tmp_path / "headroom.png").stat().st_size > 0
  # The better inputs: the network's input is the full capture at the model's scan points, and the
  # noise-free input is the stored clean transient there (read here with h5py, not the loader).
  cfg = study.preset(tmp_path / "data")
  run = study.Study(cfg, tmp_path, {}, ("fbp",))
  path = cfg["data"]["path"]
  data = run._truth(path, "test")
  inputs = run._better_inputs(path, "test", data)
  np.testing.assert_array_equal(inputs["full"][0][..., 2::4, 2::4], data["measurement"])
  assert inputs["full"][1] == 1 and inputs["clean"][1] == 4
  with h5py.File(path) as f:
    names = sorted(n for n in f["sequences"] if f["sequences"][n].attrs["split"] == "test")
    clean = np.stack([f["sequences"][names[s]]["clean"][m] for s, m in zip(data["sequence"], data["frame"])])
  np.testing.assert_allclose(inputs["clean_full"][0], clean)
  np.testing.assert_allclose(inputs["clean"][0], clean[..., 2::4, 2::4])


def test_records_of_shipped_weights_name_the_weights_so_replaced_ones_are_scored_again(tmp_path, monkeypatch):
  from experiments.studies.headroom import study
  from nlosjax import pretrained
  folder = tmp_path / "cpu-ours"
  folder.mkdir()
  monkeypatch.setattr(pretrained, "weights_folder", lambda name, variant, root=None: tmp_path / f"{name}-{variant}")
  (folder / "params.npz").write_bytes(b"old weights")
  old = study.weights_identity("pretrained:cpu/ours")
  assert old.startswith("pretrained:cpu/ours@sha256:") and old.endswith(study.weights_identity("pretrained:cpu")[-12:])
  (folder / "params.npz").write_bytes(b"new weights")
  assert study.weights_identity("pretrained:cpu/ours") != old
  assert study.weights_identity("runs/mechanisms/full/full-seed0") == "runs/mechanisms/full/full-seed0"

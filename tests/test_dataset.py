"""Dynamic NLOS datasets (nlosjax.data.dataset): physics of the stored data, layout, loader, errors.

Independent references: the brute-force renderer ``render_points`` applied to
the stored intensity and depth maps, the SPAD rate written out with a NumPy
convolution, the helix equation, and plain array slicing of the stored data.
"""

import dataclasses
import json
import math
import shutil

import h5py
import numpy as np
import pytest

from experiments import configs, make_dataset
from nlosjax.data import dataset as D
from nlosjax.data import scenes
from nlosjax.physics import Setup, render_points
from nlosjax.physics.noise import jitter_kernel
from nlosjax.train import RunConfig
from tests.poisson_checks import assert_poisson, stated_rate
from tests.tiny_run import LCT_DATA, LCT_SCENE
from tests.xla_options import xla_optimizations


@pytest.fixture(scope="module", autouse=True)
def _optimised_xla():
  # Programs here run long (full captures, samplers, renderers): XLA's optimisations pay for
  # their compile time. The suite turns them off by default (conftest.py).
  with xla_optimizations(True):
    yield


# Tiny capture: 16 x 16 on a 2 m wall, 64 bins of 264 ps (2.53 m of depth, as the presets).
# The light-cone renderer and helix scenes: these tests check the fast path against
# brute-force loops of its own model and the stored helix trajectory
# (tests/test_transport.py covers the transport renderer the cpu preset uses).
TINY = dict(grid=16, num_bins=64, bin_width=264e-12, frames=4, num_train=3, num_test=1, num_val=0,
            store_albedo=True, render_batch=4, **LCT_DATA)
SCENE = {**configs.get_config("cpu")["data"]["scene"], **LCT_SCENE}


def tiny_spec(**overrides):
  return D.DatasetSpec.from_config({**configs.get_config("cpu")["data"], "scene": SCENE},
                                   **{**TINY, **overrides})


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
  """(path, spec) of a small dataset written once for the module."""
  path = tmp_path_factory.mktemp("data") / "tiny.h5"
  spec = tiny_spec()
  result = D.write_dataset(path, spec, progress=False)
  assert result.generated == 4 and result.resumed == 0 and path.exists()
  assert not D._partial_path(path).exists()
  return path, spec


def first_return(x, frac=0.1):
  """[H, W] first bin where the histogram exceeds frac of its own maximum."""
  return np.argmax(x > np.maximum(frac * x.max(axis=0, keepdims=True), 1e-30), axis=0)


# --------------------------------------------------------------- physics
def test_clean_agrees_with_brute_force_render_of_the_stored_maps(tiny):
  path, spec = tiny
  s = spec.setup
  with D.open_dataset(path) as ds:
    for name in ds.names():
      for f in (0, 3):
        clean = ds.read(name, "clean", f).astype(np.float64)
        inten, depth = ds.read(name, "intensity", f), ds.read(name, "depth", f)
        fg = inten > 0
        ys, xs = np.nonzero(fg)
        pts = np.stack([s.scan_x[xs], s.scan_y[ys], depth[fg]], -1)
        ref = render_points(pts, inten[fg], s)               # [T, H, W], 1 / r^4 units
        e_clean, e_ref = clean.sum(0), ref.sum(0)
        assert np.corrcoef(e_clean.ravel(), e_ref.ravel())[0, 1] > 0.99
        strong = e_clean > 0.1 * e_clean.max()
        assert strong.sum() > 50
        diff = (first_return(clean) - first_return(ref))[strong]
        # Bins of 264 ps (4 cm of depth). Outliers: pixels straddling two surfaces,
        # whose stored depth is the mean of their rays' depths.
        assert np.mean(np.abs(diff) <= 2) >= 0.9 and np.abs(diff).max() <= 6, diff
        assert abs(np.median(diff)) <= 1.5
        # Photon units: the sequence's mean signal per point per frame is its budget.
  with D.open_dataset(path) as ds:
    for name in ds.names():
      clean = ds.read(name, "clean").astype(np.float64)
      photons = ds.sequence_attrs(name)["photons"]
      assert clean.sum(1).mean() == pytest.approx(photons, rel=1e-3)


def test_retroreflective_falloff_renders_r2_returns_of_the_same_scene():
  """``falloff="retroreflective"``: the same scene as the diffuse spec, with 1/r^2 returns."""
  spec = tiny_spec(frames=1, num_train=1, num_test=0, falloff="retroreflective")
  seq = D.simulate_sequence(spec, "train", 0)
  diffuse = D.simulate_sequence(tiny_spec(frames=1, num_train=1, num_test=0), "train", 0)
  for key in ("intensity", "depth"):        # the scene does not depend on the falloff
    np.testing.assert_array_equal(seq["arrays"][key], diffuse["arrays"][key])
  s = spec.setup
  clean = seq["arrays"]["clean"][0].astype(np.float64)
  inten, depth = seq["arrays"]["intensity"][0], seq["arrays"]["depth"][0]
  fg = inten > 0
  ys, xs = np.nonzero(fg)
  pts = np.stack([s.scan_x[xs], s.scan_y[ys], depth[fg]], -1)

  def shape_error(falloff):
    """L1 distance of the per-bin return totals (where r^-2 vs r^-4 shows), each normalised."""
    a = clean.sum((1, 2))
    b = render_points(pts, inten[fg], s, falloff=falloff).sum((1, 2))
    return np.abs(a / a.sum() - b / b.sum()).sum()

  retro, diffuse_err = shape_error("retroreflective"), shape_error("diffuse")
  assert retro < 0.5 * diffuse_err, (retro, diffuse_err)
  assert retro < 0.15, retro
  spec_dict = spec.to_dict()
  assert spec_dict["falloff"] == "retroreflective" and "falloff" not in tiny_spec().to_dict()
  assert D.DatasetSpec.from_config(spec_dict) == spec
  with pytest.raises(ValueError, match="falloff"):
    tiny_spec(falloff="lambertian")


def test_transport_renderer_same_scene_photon_budget_and_round_trip():
  """``renderer="transport"``: the same scene and maps as the LCT renderer, another transient
  (cosines, visibility), the photon budget kept; the spec round-trips and refuses mixed options."""
  kw = dict(frames=2, num_train=1, num_test=0, store_albedo=False)
  spec = tiny_spec(renderer="transport", retroreflective=0.5, **kw)
  seq = D.simulate_sequence(spec, "train", 0)
  lct = D.simulate_sequence(tiny_spec(**kw), "train", 0)
  for key in ("intensity", "depth", "trajectory"):
    np.testing.assert_array_equal(seq["arrays"][key], lct["arrays"][key])
  a, b = seq["arrays"]["clean"].astype(np.float64), lct["arrays"]["clean"].astype(np.float64)
  assert a.sum(1).mean() == pytest.approx(seq["attrs"]["photons"], rel=1e-3)
  assert not np.allclose(a, b, rtol=0.05)
  # Returns from the same surfaces: per-scan-point energy maps agree in shape.
  assert np.corrcoef(a.sum(1).ravel(), b.sum(1).ravel())[0, 1] > 0.8
  d = spec.to_dict()
  assert d["renderer"] == "transport" and "renderer" not in tiny_spec().to_dict()
  assert D.DatasetSpec.from_config(d) == spec
  with pytest.raises(ValueError, match="renderer must be"):
    tiny_spec(renderer="raytrace")
  with pytest.raises(ValueError, match="falloff='retroreflective'"):
    tiny_spec(retroreflective=0.5)
  with pytest.raises(ValueError, match="retroreflective=1.0"):
    tiny_spec(renderer="transport", falloff="retroreflective")
  with pytest.raises(ValueError, match="probability"):
    tiny_spec(renderer="transport", retroreflective=2.0)


def test_albedo_volume_is_the_depth_binned_intensity(tiny):
  path, spec = tiny
  dz = spec.setup.depth_bin_length
  singles = 0
  with D.open_dataset(path) as ds:
    for name in ds.names():
      vol = ds.read(name, "albedo")
      inten, depth = ds.read(name, "intensity"), ds.read(name, "depth")
      col = vol.sum(1)
      np.testing.assert_allclose(col / col.max(axis=(1, 2), keepdims=True), inten, atol=1e-5)
      # Columns whose rays all fall in one bin sit at floor(depth / dz).
      single = (vol > 0).sum(1) == 1
      singles += single.sum()
      k = np.argmax(vol, axis=1)
      np.testing.assert_array_equal(k[single], np.floor(depth[single] / dz).astype(int))
      # Empty columns are background.
      assert np.all(depth[col == 0] == scenes.BACKGROUND_DEPTH)
  assert singles > 50


def test_noise_mean_of_many_draws_is_efficiency_budget_clean_plus_background():
  """A motionless scene gives F independent draws of the same rate."""
  fwhm = 600e-12   # ~2.3 bins: visibly widens the pulse
  spec = tiny_spec(frames=48, num_train=1, num_test=0, efficiency=(0.2, 0.2),
                   photons=(3000.0, 3000.0), ambient=(64.0, 64.0), dark_counts=3.2, jitter=fwhm,
                   store_albedo=False, render_batch=16,
                   scene={**SCENE, "helix_speed": (0.0, 0.0)})
  seq = D.simulate_sequence(spec, "train", 0)
  a, attrs = seq["arrays"], seq["attrs"]
  clean = a["clean"].astype(np.float64)
  np.testing.assert_array_equal(clean, clean[:1].repeat(len(clean), 0))     # nothing moves
  assert attrs["efficiency"] == 0.2 and attrs["ambient"] == 1.0 and attrs["dark_counts"] == 0.05
  assert clean[0].sum(0).mean() == pytest.approx(3000.0, rel=1e-3)
  # Independent rate: eta * (clean (*) g + ambient) + dark, with a NumPy convolution.
  g = jitter_kernel(spec.setup, fwhm).astype(np.float64)
  c = len(g) // 2
  T = spec.setup.num_bins
  conv = np.apply_along_axis(lambda v: np.convolve(v, g)[c:c + T], 0, clean[0])
  lam = 0.2 * (conv + 1.0) + 0.05
  mean = a["measurement"].astype(np.float64).mean(0)
  F = len(a["measurement"])
  # Per scan point totals: z-scores of the mean of F draws.
  z = (mean.sum(0) - lam.sum(0)) / np.sqrt(lam.sum(0) / F)
  assert np.abs(z).max() < 5.0
  assert abs(z.mean()) < 5.0 / math.sqrt(z.size)
  # Per bin where the rate is sizeable.
  big = lam * F > 100
  zb = (mean[big] - lam[big]) / np.sqrt(lam[big] / F)
  assert big.sum() > 100 and np.abs(zb).max() < 5.5 and abs(zb.mean()) < 0.2
  # Jitter widens the pulse: temporal spread of the mean exceeds the clean one's.
  strong = clean[0].sum(0) > 0.3 * clean[0].sum(0).max()
  t = np.arange(T)[:, None]

  def spread(x):
    x = x[:, strong]
    w = x / x.sum(0)
    mu = (w * t).sum(0)
    return np.sqrt((w * (t - mu) ** 2).sum(0))

  var_g = (g * (np.arange(len(g)) - c) ** 2).sum()
  widened = np.median(spread(mean - 0.25) ** 2 - spread(clean[0]) ** 2)
  assert widened == pytest.approx(var_g, abs=0.35 * var_g), (widened, var_g)


def test_stored_measurement_is_poisson_around_the_rate_of_its_attributes(tiny):
  path, spec = tiny
  with D.open_dataset(path) as ds:
    for name in ds.names():
      at = ds.sequence_attrs(name)
      clean = ds.read(name, "clean").astype(np.float64)
      meas = ds.read(name, "measurement").astype(np.float64)
      lam = D.measurement_rate(clean, spec.setup, efficiency=at["efficiency"],
                               ambient=at["ambient"], dark_counts=at["dark_counts"],
                               jitter=spec.jitter).astype(np.float64)
      assert 0.01 <= at["efficiency"] <= 0.30
      # Rate without jitter differs by what jitter pushes out of the window only.
      plain = at["efficiency"] * (clean + at["ambient"]) + at["dark_counts"]
      assert lam.sum() == pytest.approx(plain.sum(), rel=1e-3)
      total, expected = meas.sum((1, 2, 3)), lam.sum((1, 2, 3))
      assert np.all(np.abs(total - expected) < 5 * np.sqrt(expected))
      assert np.all(meas == np.round(meas)) and meas.min() >= 0


def test_the_jax_sampler_draws_the_same_distribution():
  spec = tiny_spec(frames=3, num_train=1, num_test=0, noise_sampler="jax", store_albedo=False)
  seq = D.simulate_sequence(spec, "train", 0)
  at, a = seq["attrs"], seq["arrays"]
  lam = D.measurement_rate(a["clean"], spec.setup, efficiency=at["efficiency"],
                           ambient=at["ambient"], dark_counts=at["dark_counts"], jitter=spec.jitter)
  total, expected = a["measurement"].sum((1, 2, 3), dtype=np.float64), lam.sum((1, 2, 3), dtype=np.float64)
  assert np.all(np.abs(total - expected) < 5 * np.sqrt(expected))
  # Per bin, against the rate written out in tests/poisson_checks.py: mean and second factorial
  # moment within 5 sigma (measured: at most 2.5 sigma; noiseless counts: 23 sigma).
  rate = stated_rate(a["clean"], jitter_kernel(spec.setup, spec.jitter), efficiency=at["efficiency"],
                     ambient=at["ambient"], dark_counts=at["dark_counts"])
  np.testing.assert_allclose(lam, rate, rtol=1e-5, atol=1e-6 * rate.max())
  assert_poisson(a["measurement"], rate, label="jax sampler")
  numpy_seq = D.simulate_sequence(tiny_spec(frames=3, num_train=1, num_test=0, store_albedo=False),
                                  "train", 0)
  np.testing.assert_array_equal(numpy_seq["arrays"]["clean"], a["clean"])


def test_stored_trajectory_is_a_helix_and_the_data_follow_it(tiny):
  path, spec = tiny
  with D.open_dataset(path) as ds:
    for name in ds.names():
      at = ds.sequence_attrs(name)
      traj = ds.read(name, "trajectory")
      t = np.arange(len(traj)) / at["frame_rate"]
      th = at["helix_phase"] + at["helix_angular_speed"] * t
      u = at["helix_ref"]
      v = np.cross(at["helix_axis"], u)
      ref = (at["helix_center"] + at["helix_radius"] * (np.cos(th)[:, None] * u + np.sin(th)[:, None] * v)
             + (at["helix_pitch"] * (th - at["helix_phase"]) / (2 * math.pi))[:, None] * at["helix_axis"])
      np.testing.assert_allclose(traj, ref, atol=1e-12)
      # The stored maps are the scene regenerated from the stored seed ...
      scene = scenes.make_scene(int(at["seed"]), spec.scene, spec.frames, setup=spec.setup)
      np.testing.assert_allclose(scene.trajectory, traj, atol=1e-12)
      full = scenes.rasterize(scene, spec.setup, supersample=spec.scene.supersample)
      np.testing.assert_array_equal(full.depth, ds.read(name, "depth"))
      np.testing.assert_array_equal(full.intensity, ds.read(name, "intensity"))
      # ... where only the dynamic object's footprint changes between frames.
      depth = ds.read(name, "depth")
      moving = scenes.rasterize(scene, spec.setup, objects=[int(at["dynamic_index"])],
                                supersample=spec.scene.supersample)
      footprint = np.isfinite(moving.ray_depth).any(1)       # [F, H, W]
      for f in range(1, len(depth)):
        changed = depth[f] != depth[0]
        assert not np.any(changed & ~(footprint[f] | footprint[0]))


# ---------------------------------------------------------------- layout
def test_file_layout_attributes_and_chunks(tiny):
  path, spec = tiny
  with h5py.File(path, "r") as f:
    a = f.attrs
    assert a["format"] == D.FORMAT_NAME and a["format_version"] == D.FORMAT_VERSION
    assert a["generator_version"] == scenes.GENERATOR_VERSION and bool(a["complete"])
    assert a["wall_size"] == 2.0 and list(a["grid"]) == [16, 16]
    assert a["bin_width"] == 264e-12 and a["num_bins"] == 64
    assert json.loads(a["spec"]) == spec.to_dict()
    assert sorted(f["sequences"]) == ["test-00000", "train-00000", "train-00001", "train-00002"]
    g = f["sequences/train-00001"]
    assert g.attrs["split"] == "train" and g.attrs["index"] == 1 and bool(g.attrs["complete"])
    assert g.attrs["seed"] == D.sequence_seed(spec.seed, "train", 1)
    assert g["measurement"].shape == (4, 64, 16, 16) and g["measurement"].dtype == np.uint16
    assert g["measurement"].chunks == (1, 64, 1, 16) and g["measurement"].compression == "gzip"
    assert g["clean"].dtype == np.float32 and g["albedo"].shape == (4, 64, 16, 16)
    assert g["intensity"].chunks == (1, 16, 16) and g["trajectory"].shape == (4, 3)
    assert f["sequences/test-00000"].attrs["split"] == "test"
  with D.open_dataset(path, spec.setup) as ds:
    assert ds.setup == spec.setup
    assert ds.names("test") == ["test-00000"] and len(ds.names("train")) == 3


def test_sequences_are_reproducible_and_independent_of_the_split_counts(tiny):
  path, spec = tiny
  again = D.simulate_sequence(tiny_spec(num_train=7, num_test=5), "train", 2)
  with D.open_dataset(path) as ds:
    for key, arr in again["arrays"].items():
      np.testing.assert_array_equal(ds.read("train-00002", key), arr)
  seeds = {D.sequence_seed(0, s, i) for s in D.SPLITS for i in range(50)}
  assert len(seeds) == 50 * len(D.SPLITS)
  assert D.SPLITS[:2] == ("train", "test")     # new splits go last: old files keep their seeds


def test_extend_dataset_adds_the_validation_split_and_keeps_every_stored_sequence(tiny, tmp_path):
  path, spec = tiny
  out = tmp_path / "extended.h5"
  shutil.copy(path, out)
  with D.open_dataset(out) as ds:
    before = {n: ds.read(n, "measurement") for n in ds.names()}
  wider = dataclasses.replace(spec, num_val=2)
  result = D.extend_dataset(out, wider, progress=False)
  assert (result.generated, result.resumed) == (2, 4)
  with D.open_dataset(out) as ds:
    assert ds.names("val") == ["val-00000", "val-00001"]
    for name, arr in before.items():
      np.testing.assert_array_equal(ds.read(name, "measurement"), arr)
    fresh = D.simulate_sequence(wider, "val", 1)
    np.testing.assert_array_equal(ds.read("val-00001", "measurement"), fresh["arrays"]["measurement"])
    assert json.loads(ds.attrs["spec"])["num_sequences"]["val"] == 2
  assert D.extend_dataset(out, wider, progress=False).generated == 0        # nothing missing
  with pytest.raises(ValueError, match="more sequences"):
    D.extend_dataset(out, dataclasses.replace(spec, num_train=1), progress=False)
  with pytest.raises(ValueError, match=r"another data configuration.*seed: file 0, config 9"):
    D.extend_dataset(out, dataclasses.replace(wider, seed=9), progress=False)


def test_the_main_jobs_dataset_step_refuses_a_file_of_other_data(tiny, tmp_path):
  """A config changed under an existing file (a photon range, say) is an error, not a silent
  run on the old data; the message names what differs."""
  from nlosjax import train as T
  path, spec = tiny
  out = tmp_path / "data.h5"
  shutil.copy(path, out)
  config = {"data": {**spec.to_dict(), "path": str(out)}}
  T.ensure_dataset(RunConfig.from_dict(config), out, log=lambda s: None)                  # the same data: used
  before = out.read_bytes()
  other = {**config, "data": {**config["data"], "photons": (10.0, 20.0)}}
  with pytest.raises(ValueError, match=r"photons: file \[.*\], config \[10\.0, 20\.0\]"):
    T.ensure_dataset(RunConfig.from_dict(other), out, log=lambda s: None)
  fewer = {**config, "data": {**config["data"], "num_sequences": {"train": 1, "val": 1, "test": 1}}}
  with pytest.raises(ValueError, match="more sequences"):
    T.ensure_dataset(RunConfig.from_dict(fewer), out, log=lambda s: None)
  assert out.read_bytes() == before                                  # nothing written


# ------------------------------------------------------- under-scanning
def test_under_scanning_is_array_slicing_of_the_stored_data(tiny):
  path, _ = tiny
  with D.open_dataset(path) as ds:
    name = ds.names()[1]
    full = ds.read(name, "measurement")
    for stride, offset in ((2, 0), (4, 0), (4, 3), (3, 1), (5, 2)):
      sub = ds.read(name, "measurement", stride=stride, offset=offset)
      np.testing.assert_array_equal(sub, full[..., offset::stride, offset::stride])
      np.testing.assert_array_equal(D.undersample(full, stride, offset), sub)
      np.testing.assert_array_equal(ds.read(name, "measurement", [2, 0, 2], stride, offset),
                                    full[[2, 0, 2]][..., offset::stride, offset::stride])
      np.testing.assert_array_equal(ds.read(name, "intensity", 1, stride, offset),
                                    ds.read(name, "intensity", 1)[offset::stride, offset::stride])
  setup = Setup(2.0, (128, 128), 33e-12, 512)
  sub = D.undersampled_setup(setup, 8)
  ys, xs = D.undersampled_positions(setup, 8)
  assert sub.grid == (16, 16) and len(ys) == 16
  assert sub.spacing[0] == pytest.approx(8 * setup.spacing[0])
  np.testing.assert_allclose(np.diff(xs), sub.spacing[1])
  with pytest.raises(ValueError, match="offset"):
    D.undersample(full, 4, 4)
  with pytest.raises(ValueError, match="stride"):
    D.undersample(full, 0)


# ----------------------------------------------------------------- loader
@pytest.mark.parametrize("in_memory", [False, True])
@pytest.mark.parametrize("ends", ["valid", "replicate"])
def test_loader_triplets_are_the_right_frames(tiny, ends, in_memory):
  path, _ = tiny
  with D.TripletLoader(path, batch_size=3, stride=4, offset=1, ends=ends, in_memory=in_memory,
                       seed=5) as loader, D.open_dataset(path) as ds:
    F = 4
    per_seq = F - 2 if ends == "valid" else F
    assert len(loader.examples) == 3 * per_seq
    assert len(loader) == (3 * per_seq) // 3
    seen = []
    for batch in loader.epoch(0):
      assert batch["measurement"].shape == (3, 3, 64, 4, 4) and batch["measurement"].dtype == np.float32
      assert batch["transient"].shape == (3, 64, 16, 16)
      assert batch["intensity"].shape == (3, 16, 16) and batch["depth"].shape == (3, 16, 16)
      for b in range(3):
        name, m = loader.names[batch["sequence"][b]], int(batch["frame"][b])
        seen.append((name, m))
        frames = np.clip([m - 1, m, m + 1], 0, F - 1)
        full = ds.read(name, "measurement")
        np.testing.assert_array_equal(batch["measurement"][b], full[frames][..., 1::4, 1::4])
        np.testing.assert_array_equal(batch["transient"][b], ds.read(name, "clean", m))
        np.testing.assert_array_equal(batch["intensity"][b], ds.read(name, "intensity", m))
        np.testing.assert_array_equal(batch["depth"][b], ds.read(name, "depth", m))
        assert batch["efficiency"][b] == np.float32(ds.sequence_attrs(name)["efficiency"])
    # Each example exactly once per epoch; only train sequences.
    assert sorted(seen) == sorted(set(seen)) and len(seen) == 3 * per_seq
    assert all(n.startswith("train-") for n, _ in seen)
    middles = {m for _, m in seen}
    assert middles == ({1, 2} if ends == "valid" else {0, 1, 2, 3})


@pytest.mark.parametrize("in_memory", [False, True])
def test_a_wider_window_reads_the_clipped_neighbours_and_keeps_the_triplets_batches(tiny, in_memory):
  """A 5-frame window: each example's frames m-2..m+2 clipped to the sequence (a loop over the
  stored frames), the same examples in the same order as the triplet loader, whose frames are
  the window's middle three."""
  path, _ = tiny
  kw = dict(batch_size=2, stride=4, offset=1, ends="replicate", in_memory=in_memory, seed=3)
  with D.TripletLoader(path, window=5, **kw) as wide, D.TripletLoader(path, **kw) as triplet, \
       D.open_dataset(path) as ds:
    for step in range(len(wide) + 1):
      w, t = wide.batch(step), triplet.batch(step)
      assert w["measurement"].shape == (2, 5, 64, 4, 4)
      for k in ("transient", "intensity", "depth", "sequence", "frame", "efficiency"):
        np.testing.assert_array_equal(w[k], t[k])
      np.testing.assert_array_equal(w["measurement"][:, 1:4], t["measurement"])
      for b in range(2):
        name, m = wide.names[w["sequence"][b]], int(w["frame"][b])
        full = ds.read(name, "measurement")
        for i, d in enumerate(range(-2, 3)):
          f = min(max(m + d, 0), full.shape[0] - 1)
          np.testing.assert_array_equal(w["measurement"][b, i], full[f, :, 1::4, 1::4])
  for bad in (0, 4, -1, 2.0, True):
    with pytest.raises(ValueError, match="window must be a positive odd integer"):
      D.TripletLoader(path, window=bad, **kw)


def test_loader_shuffles_by_seed_and_resumes_from_a_step(tiny):
  path, _ = tiny
  with D.TripletLoader(path, batch_size=2, seed=1) as a, D.TripletLoader(path, batch_size=2, seed=1) as b, \
       D.TripletLoader(path, batch_size=2, seed=2) as c:
    steps = 3 * len(a)
    run = list(a.iterate(0, steps))
    keys = [(tuple(x["sequence"]), tuple(x["frame"])) for x in run]
    assert keys == [(tuple(x["sequence"]), tuple(x["frame"])) for x in b.iterate(0, steps)]
    assert keys != [(tuple(x["sequence"]), tuple(x["frame"])) for x in c.iterate(0, steps)]
    assert keys[:len(a)] != keys[len(a):2 * len(a)]   # a new order each epoch
    # Resume at step k: the same batches as the uninterrupted run.
    k = len(a) + 1
    for x, y in zip(run[k:], b.iterate(k, steps - k, prefetch_size=2)):
      for key in x:
        np.testing.assert_array_equal(x[key], y[key])
  with D.TripletLoader(path, split="test", batch_size=1, shuffle=False, target="measurement") as t:
    batch = t.batch(0)
    with D.open_dataset(path) as ds:
      np.testing.assert_array_equal(batch["transient"][0], ds.read("test-00000", "measurement", 1))
    assert [int(t.batch(i)["frame"][0]) for i in range(len(t))] == [1, 2]


def test_loader_options_one_schema_with_clear_errors():
  assert D.LoaderOptions.from_dict(None) == D.LoaderOptions("valid", "clean", True, 0)
  assert D.LoaderOptions.from_dict({"prefetch": 3, "in_memory": False}).prefetch == 3
  with pytest.raises(ValueError, match=r"unknown data.loader key\(s\) \['shuffle'\]; known"):
    D.LoaderOptions.from_dict({"shuffle": True})
  for bad, match in [({"ends": "wrap"}, "ends"), ({"target": "noisy"}, "target"),
                     ({"in_memory": 1}, "in_memory"), ({"prefetch": -1}, "prefetch"),
                     ({"prefetch": True}, "prefetch")]:
    with pytest.raises(ValueError, match=f"data.loader.{match}"):
      D.LoaderOptions.from_dict(bad)
  # The presets' sections are read by it.
  for preset in ("cpu", "paper"):
    D.LoaderOptions.from_dict(configs.get_config(preset)["data"]["loader"])


def test_prefetch_passes_items_and_errors_through():
  assert list(D.prefetch(iter(range(10)), 3)) == list(range(10))

  def broken():
    yield 1
    raise RuntimeError("boom")

  it = D.prefetch(broken(), 2)
  assert next(it) == 1
  with pytest.raises(RuntimeError, match="boom"):
    next(it)

  # Closed early (a paused run): the producer has stopped when close() returns, so the
  # loader's file can be closed right after.
  import itertools
  import threading
  def running():
    return [t for t in threading.enumerate() if t.name == "nlosjax-prefetch" and t.is_alive()]

  it = D.prefetch(itertools.count(), 2)
  assert [next(it), next(it)] == [0, 1]
  it.close()
  assert not running()
  # Closed before its first item (a finished run rerun: the loop stops before reading): no thread.
  D.prefetch(itertools.count(), 2).close()
  assert not running()


# ---------------------------------------------------------------- errors
def test_bad_files_raise_naming_the_file(tiny, tmp_path):
  path, spec = tiny
  truncated = tmp_path / "truncated.h5"
  data = path.read_bytes()
  truncated.write_bytes(data[:len(data) // 2])
  with pytest.raises(ValueError, match="truncated.h5.*(truncated|corrupt)"):
    D.open_dataset(truncated)
  text = tmp_path / "notes.h5"
  text.write_text("not hdf5")
  with pytest.raises(ValueError, match="notes.h5"):
    D.TripletLoader(text)
  foreign = tmp_path / "foreign.h5"
  with h5py.File(foreign, "w") as f:
    f["data"] = np.zeros(3)
  with pytest.raises(ValueError, match="foreign.h5.*not an nlosjax dynamic NLOS dataset"):
    D.open_dataset(foreign)
  with pytest.raises(FileNotFoundError, match="missing.h5"):
    D.open_dataset(tmp_path / "missing.h5")
  # A missing dataset.
  holed = tmp_path / "holed.h5"
  shutil.copy(path, holed)
  with h5py.File(holed, "a") as f:
    del f["sequences/train-00001/depth"]
  with D.open_dataset(holed) as ds:
    with pytest.raises(ValueError, match="holed.h5.*train-00001.*'depth'"):
      ds.read("train-00001", "depth")
  with pytest.raises(ValueError, match="holed.h5.*'depth'"):
    D.TripletLoader(holed, in_memory=True)
  # A Setup that does not match.
  with pytest.raises(ValueError, match="tiny.h5.*grid"):
    D.open_dataset(path, Setup(2.0, (32, 32), 264e-12, 64))
  with pytest.raises(ValueError, match="tiny.h5.*bin_width"):
    D.TripletLoader(path, setup=Setup(2.0, (16, 16), 132e-12, 64))
  # No clean transients stored, or a batch larger than the split.
  with h5py.File(holed, "a") as f:
    for name in f["sequences"]:
      del f["sequences"][name]["clean"]
  with pytest.raises(ValueError, match="holed.h5.*no 'clean'.*target='measurement'"):
    D.TripletLoader(holed, target="clean")
  with pytest.raises(ValueError, match="batch_size 100 exceeds"):
    D.TripletLoader(path, batch_size=100)
  # An unfinished file and a newer format.
  for attr, value, match in (("complete", False, "not finished"), ("format_version", 99, "format_version")):
    odd = tmp_path / f"odd_{attr}.h5"
    shutil.copy(path, odd)
    with h5py.File(odd, "a") as f:
      f.attrs[attr] = value
    with pytest.raises(ValueError, match=f"odd_{attr}.h5.*{match}"):
      D.open_dataset(odd)


def test_existing_files_are_never_overwritten_without_permission(tiny, tmp_path, monkeypatch):
  path, spec = tiny
  out = tmp_path / "keep.h5"
  shutil.copy(path, out)
  before = out.read_bytes()
  with pytest.raises(FileExistsError, match="keep.h5"):
    D.write_dataset(out, spec, progress=False)
  assert make_dataset.main(["--out", str(out), "--quiet", "--sequences", "2"]) == 2
  assert out.read_bytes() == before
  # With overwrite, a crash mid-way leaves the old file intact ...
  calls = []
  real = D.simulate_sequence

  def crash_on_third(spec_, split, index):
    calls.append((split, index))
    if len(calls) == 3:
      raise RuntimeError("killed")
    return real(spec_, split, index)

  monkeypatch.setattr(D.file, "simulate_sequence", crash_on_third)
  with pytest.raises(RuntimeError, match="killed"):
    D.write_dataset(out, spec, overwrite=True, progress=False)
  assert out.read_bytes() == before
  partial = D._partial_path(out)
  with h5py.File(partial, "a") as f:
    assert sorted(f["sequences"]) == ["train-00000", "train-00001"]
    f["sequences/train-00001"].attrs["complete"] = False     # as if killed while writing it
  # ... and the rerun resumes: keeps the finished sequence, redoes the half-written one.
  monkeypatch.setattr(D.file, "simulate_sequence", real)
  result = D.write_dataset(out, spec, overwrite=True, progress=False)
  assert (result.resumed, result.generated) == (1, 3)
  assert not partial.exists()
  with D.open_dataset(out) as new, D.open_dataset(path) as old:
    for name in old.names():
      for key in ("measurement", "clean", "depth"):
        np.testing.assert_array_equal(new.read(name, key), old.read(name, key))


def test_spec_and_config_errors_name_the_key():
  data = configs.get_config("cpu")["data"]
  with pytest.raises(ValueError, match="unknown data config key.*'colour'"):
    D.DatasetSpec.from_config({**data, "colour": 1})
  with pytest.raises(ValueError, match="efficiency"):
    tiny_spec(efficiency=(0.0, 0.3))
  with pytest.raises(ValueError, match="maximum depth"):
    tiny_spec(num_bins=32)
  with pytest.raises(ValueError, match="lacks 'grid'"):
    D.DatasetSpec.from_config({k: v for k, v in data.items() if k != "grid"})
  with pytest.raises(ValueError, match="config must be one of"):
    configs.get_config("gpu")
  assert D.DatasetSpec.from_config(tiny_spec().to_dict()) == tiny_spec()


def test_presets_keep_the_paper_ratios():
  for name in configs.PRESETS:
    cfg = configs.get_config(name)
    assert {"data", "model", "train"} <= set(cfg) <= {"data", "model", "train", "independent", "usm"}
    spec = D.DatasetSpec.from_config(cfg["data"])
    d = cfg["data"]
    h = len(range(d["input_offset"], spec.setup.height, d["input_stride"]))
    assert h >= 8 and d["input_stride"] >= 4 and spec.setup.height // h >= 4
    assert spec.scene.depth_range[1] < spec.setup.max_depth
  paper = D.DatasetSpec.from_config(configs.get_config("paper")["data"])
  assert paper.setup == Setup(2.0, (128, 128), 33e-12, 512)
  assert (paper.frames, paper.num_train, paper.num_test) == (32, 150, 17)   # Sec. 5.1
  assert configs.get_config("paper")["data"]["input_stride"] == 8


@pytest.mark.full
def test_cli_writes_the_preset_split_and_the_loader_reads_it_by_config(tmp_path):
  out = tmp_path / "cli.h5"
  assert make_dataset.main(["--out", str(out), "--sequences", "3", "--frames", "3", "--quiet"]) == 0
  data = configs.get_config("cpu")["data"]
  with D.open_dataset(out) as ds:
    assert len(ds.names("train")) == 2 and len(ds.names("test")) == 1
    assert ds.num_frames("train-00000") == 3
    assert json.loads(ds.attrs["spec"])["grid"] == [data["grid"]] * 2
  from nlosjax import train as T
  config = configs.get_config("cpu")
  with T.make_loader(RunConfig.from_dict(config), out, "test", batch_size=1, shuffle=False, seed=0) as loader:
    assert not loader.shuffle and loader.stride == data["input_stride"]
    assert loader._cache is not None and loader.prefetch_size == data["loader"]["prefetch"]
    batch = next(loader.iterate())
    assert batch["measurement"].shape == (1, 3, data["num_bins"], 8, 8)
  with pytest.raises(ValueError, match="unknown data.loader"):
    T.make_loader(RunConfig.from_dict({**config, "data": {**data, "loader": {"shuffle": True}}}), out, "test",
                  batch_size=1,
                  shuffle=False, seed=0)


@pytest.mark.parametrize("in_memory", [False, True])
def test_sharded_loaders_read_their_rows_of_the_global_batch(tiny, in_memory):
  # Multi-process training: process i of n gets rows i*B/n .. (i+1)*B/n.
  path, _ = tiny
  kw = dict(batch_size=4, stride=4, offset=1, seed=3, in_memory=in_memory)
  with D.TripletLoader(path, **kw) as whole, D.TripletLoader(path, shard=(0, 2), **kw) as a, \
       D.TripletLoader(path, shard=(1, 2), **kw) as b:
    if in_memory:
      assert a._cache == [None] * len(a.names)          # nothing read before it is needed
    for step in (0, 1, 5):
      full, parts = whole.batch(step), (a.batch(step), b.batch(step))
      for k in full:
        np.testing.assert_array_equal(np.concatenate([p[k] for p in parts]), full[k])
      assert parts[0]["measurement"].shape[0] == 2
  with pytest.raises(ValueError, match="shard"):
    D.TripletLoader(path, batch_size=4, shard=(2, 2))
  with pytest.raises(ValueError, match="split into 3 shards"):
    D.TripletLoader(path, batch_size=4, shard=(0, 3))

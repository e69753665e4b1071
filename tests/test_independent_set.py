"""experiments.independent_set: the test set made without the training generator's code.

Independent references: ``render_points`` times the cosine factors written
out per scan point, the photon budget and Poisson rate of the stored
attributes, and nlosjax's own reader (the file must be in the documented layout).
"""

import h5py
import numpy as np
import pytest

from experiments import configs
from experiments import independent_set as I
from nlosjax.data.dataset import DatasetSpec, open_dataset
from nlosjax.physics import Setup, jitter_kernel, render_points

DATA = {**configs.get_config("cpu")["data"], "grid": 16, "num_bins": 64, "bin_width": 264e-12}


def test_point_transient_is_the_brute_force_loop_with_cosines():
  setup = Setup(wall_size=1.0, grid=(5, 6), bin_width=64e-12, num_bins=64)
  rng = np.random.default_rng(0)
  x, y, z = rng.uniform(-0.4, 0.4, 7), rng.uniform(-0.4, 0.4, 7), rng.uniform(0.3, 0.9, 7)
  a = rng.uniform(0.1, 1.0, 7)
  want = np.zeros((64, 5, 6))
  for k in range(7):
    r = np.linalg.norm(setup.scan_points - [x[k], y[k], z[k]], axis=-1)      # [H, W]
    want += render_points([[x[k], y[k], z[k]]], a[k], setup) * (z[k] / r) ** 4
  np.testing.assert_allclose(I.point_transient(x, y, z, a, setup), want, rtol=1e-12, atol=0)


def test_jitter_taps_agree_with_the_library_kernel_at_the_peak():
  """Sampled independently of nlosjax.physics.noise, the measured kernel's taps agree."""
  setup = DatasetSpec.from_config(DATA).setup
  taps, centre = I._jitter_taps(setup, "measured")
  lib = jitter_kernel(setup, "measured")
  mid = len(lib) // 2
  np.testing.assert_allclose(taps, lib[mid - centre:mid - centre + len(taps)], atol=3e-3)


def test_written_set_is_in_the_documented_layout_with_its_photon_budget(tmp_path):
  path = I.write_independent_set(tmp_path / "ind.h5", DATA, sequences=2, frames=3, seed=1,
                                 progress=False)
  with open_dataset(path) as ds:
    names = ds.names("test")
    assert len(names) == 2
    for name in names:
      attrs = ds.sequence_attrs(name)
      clean = ds.read(name, "clean").astype(np.float64)
      assert clean.shape == (3, 64, 16, 16)
      assert clean.sum(1).mean() == pytest.approx(attrs["photons"], rel=1e-4)
      counts = ds.read(name, "measurement").astype(np.float64)
      # Poisson counts around eta * (signal + ambient) + dark: the total matches within noise.
      lo = attrs["efficiency"] * clean.sum()
      assert counts.sum() >= 0.9 * lo
      # Both sides, by z-score: the ambient level is drawn in DATA's range (not stored).
      pixels = clean.shape[0] * clean.shape[2] * clean.shape[3]
      dark = DATA["dark_counts"] * pixels
      low = lo + attrs["efficiency"] * DATA["ambient"][0] * pixels + dark
      high = lo + attrs["efficiency"] * DATA["ambient"][1] * pixels + dark
      assert (counts.sum() - low) / np.sqrt(low) > -5 and (counts.sum() - high) / np.sqrt(high) < 5
      inten, depth = ds.read(name, "intensity"), ds.read(name, "depth")
      assert inten.max() == pytest.approx(1.0) and np.all((depth == 0) == (inten == 0))
  # The same call again returns the file; another version is refused, not reused.
  assert I.ensure_independent_set(path, DATA) == path
  # Other detector ranges (a preset's photon budget changed) are refused too.
  with pytest.raises(ValueError, match="other detector ranges"):
    I.ensure_independent_set(path, {**DATA, "photons": (1.0, 2.0)})
  with h5py.File(path, "a") as f:
    f.attrs["generator_version"] = "experiments.studies.independent_test"
  with pytest.raises(ValueError, match="delete the file"):
    I.ensure_independent_set(path, DATA)


def test_written_counts_are_poisson_around_the_stated_rate_per_bin(tmp_path):
  """Detector fixed (efficiency 0.3, 2000 photons a pixel, ambient 80 a pixel, DATA's dark
  counts): the rate is ``eta (clean * jitter + ambient / T) + dark / T`` with the library's
  measured jitter kernel (not the writer's taps). The total and every bin's sum over frames and
  pixels must be within 5 sigma (Poisson: variance = mean): 0.14 % of the total, so a 1 % gain
  or a photon budget off by 1 % fails, and a one-bin shift fails on the bins of the scene."""
  eff, photons, ambient = 0.3, 2000.0, 80.0
  data = {**DATA, "efficiency": (eff, eff), "photons": (photons, photons), "ambient": (ambient, ambient)}
  path = I.write_independent_set(tmp_path / "fixed.h5", data, sequences=2, frames=3, seed=1,
                                 progress=False)
  setup = DatasetSpec.from_config(data).setup
  kernel = np.asarray(jitter_kernel(setup, "measured"), np.float64)
  mid, T = len(kernel) // 2, setup.num_bins
  with open_dataset(path) as ds:
    for name in ds.names("test"):
      attrs = ds.sequence_attrs(name)
      assert attrs["efficiency"] == pytest.approx(eff) and attrs["photons"] == pytest.approx(photons)
      clean = ds.read(name, "clean").astype(np.float64)
      assert clean.sum(1).mean() == pytest.approx(photons, rel=1e-4)
      blurred = np.apply_along_axis(lambda h: np.convolve(h, kernel)[mid:mid + T], 1, clean)
      rate = eff * (blurred + ambient / T) + DATA["dark_counts"] / T
      counts = ds.read(name, "measurement").astype(np.float64)
      z_total = (counts.sum() - rate.sum()) / np.sqrt(rate.sum())
      per_bin, rate_bin = counts.sum((0, 2, 3)), rate.sum((0, 2, 3))
      z_bins = (per_bin - rate_bin) / np.sqrt(rate_bin)
      assert abs(z_total) < 5 and np.abs(z_bins).max() < 5, (name, z_total, np.abs(z_bins).max())


def dynamic_object_checks(depth, trajectory, size, ys, xs):
  """Each frame where the dynamic object shows: some pixel lies at the trajectory's depth, and every
  such pixel within the object's reach of the trajectory's (x, y). Returns the frames checked."""
  checked = 0
  for f in range(len(depth)):
    x, y, z = trajectory[f]
    at = np.isclose(depth[f], z, rtol=0, atol=1e-5)
    if not at.any():                 # hidden behind a static object in this frame
      continue
    rows, cols = np.nonzero(at)
    reach = 0.75 * size + np.hypot(xs[1] - xs[0], ys[1] - ys[0])
    assert np.hypot(xs[cols] - x, ys[rows] - y).max() <= reach, (f, trajectory[f])
    checked += 1
  return checked


def test_the_stored_trajectory_is_where_the_dynamic_object_was_drawn(tmp_path):
  """The trajectory against the rendered depth maps: the dynamic object's depth is its z, and its
  pixels lie around its (x, y) (a file whose trajectory swapped x and y, or left out the depth
  oscillation, fails)."""
  import json
  path = I.write_independent_set(tmp_path / "ind.h5", DATA, sequences=3, frames=4, seed=3,
                                 progress=False)
  setup = DatasetSpec.from_config(DATA).setup
  checked = 0
  with open_dataset(path) as ds:
    for name in ds.names("test"):
      traj = ds.read(name, "trajectory")
      assert traj.shape == (4, 3)
      size = json.loads(ds.sequence_attrs(name)["objects"])[-1]["size"]
      checked += dynamic_object_checks(ds.read(name, "depth"), traj, size, setup.scan_y, setup.scan_x)
  assert checked >= 10

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
      inten, depth = ds.read(name, "intensity"), ds.read(name, "depth")
      assert inten.max() == pytest.approx(1.0) and np.all((depth == 0) == (inten == 0))
  # The same call again returns the file; another version is refused, not reused.
  assert I.ensure_independent_set(path, DATA) == path
  # Other detector ranges (a preset's photon budget changed) are refused too.
  with pytest.raises(ValueError, match="other detector ranges"):
    I.ensure_independent_set(path, {**DATA, "photons": (1.0, 2.0)})
  with h5py.File(path, "a") as f:
    f.attrs["generator_version"] = "benchmarks.independent_test"
  with pytest.raises(ValueError, match="delete the file"):
    I.ensure_independent_set(path, DATA)

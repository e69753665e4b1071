"""``depth_range="auto"``: the range estimated from a capture holds its scene and gates the rest.

Reference: point scatterers at known depths, rendered by the brute-force
``render_points`` (not the LCT operator the estimate's f-k does not use either).
"""

import jax
import numpy as np
import pytest

from nlosjax import physics
from nlosjax.physics import Setup, estimate_depth_range

SETUP = Setup(2.0, (16, 16), 32e-12, 512)                   # 0-2.46 m


@pytest.fixture(scope="module")
def two_points():
  pts = np.array([[0.2, -0.3, 0.7], [-0.4, 0.1, 1.1]])
  x = np.asarray(physics.render_points(pts, np.array([1.0, 0.8]), SETUP))
  rng = np.random.default_rng(0)
  return rng.poisson(x / x.max() * 50 + 0.01).astype(np.float32)


def test_estimated_range_holds_the_scene_and_gates_the_rest(two_points):
  z0, z1 = estimate_depth_range(two_points, SETUP)
  assert z0 <= 0.7 - 0.1 and z1 >= 1.1 + 0.1                 # both points, with the margin
  assert z1 - z0 < 0.6 * SETUP.max_depth                     # and much less than the window
  # the estimate reads frames as one capture
  assert estimate_depth_range(np.stack([two_points] * 3), SETUP) == pytest.approx((z0, z1))


def test_reconstruct_auto_equals_the_auto_gated_setup(two_points):
  gated = physics.auto_depth_range(two_points, SETUP)
  auto = np.asarray(physics.reconstruct(two_points, SETUP, "fk", depth_range="auto"))
  np.testing.assert_allclose(auto, np.asarray(physics.reconstruct(two_points, gated, "fk")),
                             rtol=1e-6)
  assert auto.shape[0] == gated.num_depth_bins < SETUP.num_bins
  k = int(np.argmax(auto.max(axis=(1, 2)))) + gated.depth_bins[0]
  assert abs(k * SETUP.depth_bin_length - 0.7) < 0.05          # the brighter point survives gating


def test_bad_requests_say_why(two_points):
  with pytest.raises(ValueError, match="no photon"):
    estimate_depth_range(np.zeros_like(two_points), SETUP)
  with pytest.raises(ValueError, match="'auto'"):
    physics.reconstruct(two_points, SETUP, "fk", depth_range="automatic")
  with pytest.raises(ValueError, match="outside jit"):
    jax.jit(lambda x: physics.reconstruct(x, SETUP, "fk", depth_range="auto"))(two_points)
  with pytest.raises(ValueError, match="threshold"):
    estimate_depth_range(two_points, SETUP, threshold=1.5)


def test_cli_depth_range_auto(tmp_path, two_points):
  import h5py

  from experiments import reconstruct as cli
  from nlosjax.data import io
  path = io.save_capture(tmp_path / "cap.h5", two_points, SETUP)
  res = cli.main([str(path), "--method", "fk", "--depth-range", "auto", "--out", str(tmp_path / "o"),
                  "--no-cache", "--quiet"])
  assert res["intensity"].shape == (1, 16, 16)
  with h5py.File(tmp_path / "o" / "volume.h5", "r") as f:
    assert f["volume"].shape[-3] == physics.auto_depth_range(two_points, SETUP).num_depth_bins
  with pytest.raises(SystemExit):
    cli.main([str(path), "--method", "fk", "--depth-range", "near", "--out", str(tmp_path / "p"),
              "--no-cache", "--quiet"])

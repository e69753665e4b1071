"""Checked inputs inside compiled code (``nlosjax.physics.checks.checked``).

The invariant: under a plain ``jit`` bad counts pass silently (NaN volumes, a
plausible network image); under ``checked`` the same call raises ``ValueError``
naming the array, and good input gives exactly the plain result.
"""

import jax
import numpy as np
import pytest

from nlosjax import physics
from nlosjax.models.network import ModelConfig, STMambaNet
from nlosjax.physics import Setup, checks
from tests.xla_options import xla_optimizations

SETUP = Setup(0.8, (8, 8), 32e-12, 64)
GOOD = np.random.default_rng(0).poisson(1.0, (64, 8, 8)).astype(np.float32)


def bad_inputs(x):
  nan = x.copy()
  nan[10, 3, 4] = np.nan
  inf = x.copy()
  inf[0, 0, 0] = np.inf
  neg = x.copy()
  neg[5, 1, 1] = -1.0
  return [(nan, "NaN or infinite"), (inf, "NaN or infinite"), (neg, "negative values")]


# Every method validates through the same prepare_transient; f-k is the one whose plain
# output hides a NaN (sqrt of a clamp), LCT the one that spreads it.
@pytest.mark.parametrize("method", ["lct", "fk"])
def test_reconstruct_raises_on_bad_counts_only_when_checked(method):
  plain = jax.jit(lambda v: physics.reconstruct(v, SETUP, method))
  safe = checks.checked(lambda v: physics.reconstruct(v, SETUP, method))
  np.testing.assert_array_equal(np.asarray(safe(GOOD)), np.asarray(plain(GOOD)))
  for bad, match in bad_inputs(GOOD):
    with pytest.raises(ValueError, match=f"^transient holds {match}"):
      safe(bad)
  if method == "lct":
    assert np.isnan(np.asarray(plain(bad_inputs(GOOD)[0][0]))).any()  # what checked prevents


def test_spad_noise_raises_on_bad_counts_when_checked():
  key = jax.random.key(0)
  draw = lambda v: physics.add_spad_noise(key, v, SETUP, photons_per_point=50.0)
  safe = checks.checked(draw)
  np.testing.assert_array_equal(np.asarray(safe(GOOD)), np.asarray(jax.jit(draw)(GOOD)))
  nan, _ = bad_inputs(GOOD)[0]
  assert float(np.asarray(jax.jit(draw)(nan)).min()) >= 0      # plain: NaN becomes counts
  with pytest.raises(ValueError, match="NaN or infinite"):
    safe(nan)


@pytest.mark.full
def test_network_raises_on_bad_frames_when_checked():
  with xla_optimizations(False):        # tiny shapes: compiling dominates
    _network_case()


def _network_case():
  cfg = ModelConfig.cpu(Setup(wall_size=0.5, grid=(8, 8), bin_width=64e-12, num_bins=32),
                        stride=2, width=4, d_state=2, extract_time_stride=2, extract_blocks=1,
                        st_depth=1, cross_depth=1, volume_features=1, frames=3)
  model = STMambaNet(cfg)
  x = np.asarray(jax.random.poisson(jax.random.key(1), 0.5, cfg.input_shape(1)), np.float32)
  variables = jax.jit(model.init)(jax.random.key(2, impl="rbg"), x)
  apply = lambda v, f: model.apply(v, f)["intensity"]
  safe = checks.checked(apply)
  np.testing.assert_allclose(np.asarray(safe(variables, x)),
                             np.asarray(jax.jit(apply)(variables, x)), rtol=1e-6, atol=1e-7)
  bad = x.copy()
  bad[0, 1, 3, 2, 2] = -3.0
  assert np.isfinite(np.asarray(jax.jit(apply)(variables, bad))).all()   # plausible, wrong
  with pytest.raises(ValueError, match="^frames holds negative values"):
    safe(variables, bad)


def test_checked_leaves_plain_jit_untouched_and_composes_without_jit():
  plain = jax.jit(lambda v: physics.reconstruct(v, SETUP, "fk"))
  assert "check" not in str(jax.make_jaxpr(lambda v: physics.reconstruct(v, SETUP, "fk"))(GOOD))
  inner = checks.checked(lambda v: physics.reconstruct(v, SETUP, "fk"), jit=False)
  np.testing.assert_allclose(np.asarray(inner(GOOD)), np.asarray(plain(GOOD)), rtol=1e-6)
  with pytest.raises(ValueError, match="NaN"):
    inner(bad_inputs(GOOD)[0][0])


def test_checked_of_an_already_jitted_function_checks_and_leaves_it_plain():
  # jit's trace cache does not see whether checks were on: checked(f) of a jitted f that has
  # run once must still check, and f must still run plainly after checked(f) has traced it.
  f = jax.jit(lambda v: physics.reconstruct(v, SETUP, "lct"))
  plain = np.asarray(f(GOOD))
  nan = bad_inputs(GOOD)[0][0]
  with pytest.raises(ValueError, match="^transient holds NaN"):
    checks.checked(f)(nan)
  np.testing.assert_array_equal(np.asarray(f(GOOD)), plain)
  assert np.isnan(np.asarray(f(nan))).any()          # f itself stays unchecked


# ------------------------------------------------------- eager input checks
def test_save_capture_refuses_bad_data_and_keeps_what_was_written(tmp_path):
  from nlosjax.data import io
  setup = Setup(0.8, (4, 5), 32e-12, 16)
  good = np.ones((2, 16, 4, 5), np.float32)
  path = io.save_capture(tmp_path / "cap.h5", good, setup)
  before = path.read_bytes()
  nan = good.copy()
  nan[1, 3, 2, 2] = np.nan
  neg = good.copy()
  neg[0, 0, 0, 0] = -1
  cases = [(nan, {}, "NaN or infinite"), (neg, {}, "negative"),
           (np.zeros((0, 16, 4, 5), np.float32), {}, "no frame"),
           (good, {"volume": np.full((16, 4, 5), np.inf)}, "'volume' holds NaN"),
           (good, {"depth": np.zeros((0, 5))}, "'depth' is empty")]
  for data, extra, match in cases:
    with pytest.raises(ValueError, match=match):
      io.save_capture(path, data, setup, overwrite=True, **extra)
    assert path.read_bytes() == before                       # the old file is intact
    assert not path.with_name(path.name + ".partial").exists()


def test_implausible_units_and_cube_layouts_warn():
  with pytest.warns(physics.setup.UnitWarning, match="bin_width"):
    Setup(2.0, (16, 16), 32e-9, 512)                          # 32 ns: nanoseconds for ps?
  with pytest.warns(physics.setup.UnitWarning, match="wall_size"):
    Setup(60.0, (16, 16), 32e-12, 512)                        # a 60 m wall
  with pytest.warns(physics.setup.UnitWarning, match="wall_size"):
    Setup(0.02, (16, 16), 32e-12, 512)
  cube = Setup(0.6, (16, 16), 32e-12, 16)
  with pytest.warns(physics.setup.LayoutWarning, match=r"read as \[..., T, H, W\]"):
    cube.check_transient(np.zeros((16, 16, 16)))
  import warnings
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    Setup(2.0, (16, 16), 32e-12, 512).check_transient(np.zeros((512, 16, 16)))   # no warning

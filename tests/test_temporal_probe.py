"""experiments.studies.temporal_probe: the stage-1 knock-out removes every SSM's influence, and only that."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.studies import temporal_probe as P
from nlosjax.models.network import ModelConfig, STMambaNet
from nlosjax.physics.setup import Setup
from tests.xla_options import xla_optimizations


@pytest.fixture(scope="module", autouse=True)
def _fast_compiles():
  # A tiny model compiled three ways: compiling is the whole cost.
  with xla_optimizations(False):
    yield


def _perturb(params, prefixes, scale=0.5):
  """``params`` with every leaf under a top-level name starting with one of ``prefixes`` shifted."""
  def shift(path, v):
    top = path[0].key
    return v + scale if any(top.startswith(p) for p in prefixes) else v
  return jax.tree_util.tree_map_with_path(shift, params)


@pytest.mark.full
def test_zeroed_features_make_stage_one_irrelevant():
  setup = Setup(wall_size=1.0, grid=(8, 8), bin_width=264e-12, num_bins=32)
  cfg = ModelConfig(setup=setup, stride=4, frames=3, width=4, d_state=2, extract_time_stride=2,
                    extract_blocks=1, st_depth=1, cross_depth=1, spread_min_width=1,
                    volume_features=1, refine_width=2, skip_frames="weighted")
  model = STMambaNet(cfg)
  x = jax.random.uniform(jax.random.key(0), cfg.input_shape(2), minval=0.0, maxval=5.0)
  params = jax.jit(model.init)(jax.random.key(1), x)["params"]
  trained, zeroed = P._intensity_fns(model)
  stage1 = ("extract", "st_mamba", "cross_")
  other = _perturb(params, stage1)
  assert any(k.startswith("cross_") for k in params)          # the cross blocks are perturbed too
  # As trained, stage 1 changes the output; knocked out, nothing in stage 1 can.
  assert float(jnp.max(jnp.abs(trained(params, x) - trained(other, x)))) > 1e-4
  np.testing.assert_array_equal(np.asarray(zeroed(params, x)), np.asarray(zeroed(other, x)))
  # The knock-out leaves the rest alive: the spreading and volume stages still act.
  later = _perturb(params, ("spread", "volume"))
  assert float(jnp.max(jnp.abs(zeroed(params, x) - zeroed(later, x)))) > 1e-4
  # The measured frames still reach the output through the skip.
  assert float(jnp.max(jnp.abs(zeroed(params, x) - zeroed(params, 2 * x[:, :, ::-1])))) > 1e-4

"""The physics operators as jit arguments (nlosjax.models.operator_args): same numbers, no baked constants."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nlosjax.models import physics_layer
from nlosjax.physics import operator_args
from nlosjax.physics.setup import Setup
from nlosjax.train import step as train_step_module
from tests.tiny_run import TINY_MODEL

SETUP = Setup(wall_size=1.0, grid=(16, 16), bin_width=64e-12, num_bins=64)


@pytest.mark.parametrize("method", ["phasor", "lct"])
def test_a_bound_physics_layer_computes_the_same_volume_without_the_psf_constant(method):
  ft = physics_layer.FeatureTransform(SETUP, method)
  a, b = ft.window()
  x = jax.random.uniform(jax.random.key(0), (1, b - a, 16, 16, 2))
  fn = lambda v: ft.apply({}, v, time_offset=a)                       # noqa: E731
  table = operator_args.operators_of(fn, jax.ShapeDtypeStruct(x.shape, x.dtype))
  (key,) = table.keys
  assert key[0] == "lct_operators" and key[1] == SETUP
  psf = table.values[0].psf_fft
  bound = operator_args.bind(fn, table)
  ref = np.asarray(jax.jit(fn)(x))             # the layer with its operators as constants
  np.testing.assert_allclose(np.asarray(bound(x)), ref, rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(np.asarray(bound.lower(x).compile()(x)), ref, rtol=1e-5, atol=1e-6)
  # The PSF spectrum is an argument: the bound program's text is far smaller than the spectrum's bytes.
  assert len(bound.lower(x).as_text()) < psf.nbytes / 4
  const_text = jax.jit(fn).lower(x).as_text()
  if getattr(jax.config, "jax_use_simplified_jaxpr_constants", True):   # a transitional flag: absent means on
    # JAX 0.12 turned it on by default: jit itself passes a captured constant over
    # jax_embedded_constants_max_bytes as an argument of the program ({jax.const = true}), not as text.
    psf_type = f"tensor<{'x'.join(map(str, psf.shape))}xcomplex<f32>>"
    assert f"{psf_type} {{jax.const = true}}" in const_text
  else:
    # Up to JAX 0.10 the constant program's text holds the spectrum (hex, two characters a byte).
    assert psf.nbytes / 4 < len(const_text) / 8
  # Outside bind, op by op or in a user's own jit, the cached constants are read as before.
  assert operator_args.lookup(key, lambda: "built") == "built"


def test_an_unknown_key_inside_bind_falls_back_to_the_constants():
  table = operator_args.OperatorTable(("other",), (jnp.ones(3),))
  out = operator_args.bind(lambda v: v + operator_args.lookup("mine", lambda: jnp.full(3, 2.0)), table)
  np.testing.assert_array_equal(np.asarray(out(jnp.zeros(3))), [2.0, 2.0, 2.0])
  leaves, treedef = jax.tree.flatten(table)                 # keys static, arrays leaves
  assert len(leaves) == 1 and jax.tree.unflatten(treedef, leaves).keys == ("other",)


def test_the_train_step_reads_the_model_operators_from_its_argument():
  from nlosjax.models.network import ModelConfig
  mcfg = ModelConfig(setup=SETUP, stride=4, **TINY_MODEL)
  table = mcfg.physics_operators()
  assert len(table.keys) == 1 and table.keys[0][1] == physics_layer.coarsen_setup(SETUP, mcfg.volume_time_stride)
  from nlosjax import losses
  from nlosjax.train.sharding import make_mesh
  step = train_step_module.make_train_step(mcfg, losses.LossWeights(), make_mesh())
  assert step.table.keys == table.keys
  for got, want in zip(jax.tree.leaves(step.table), jax.tree.leaves(table)):
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))

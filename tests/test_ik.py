"""nlosjax.models.ik: the I-K approximation's kernel, attention, gradients, errors and training.

Independent references: a per-frequency Python loop for the band weights; LFE
(:mod:`nlosjax.models.lfe`, whose transform is :class:`FeatureTransform`'s LCT and is
itself tested against ``nlosjax.physics.reconstruct``) for I-K at initialisation,
where its kernel is LCT's Wiener filter and every attention gain is 1; and a
second LCT run by hand (``nlosjax.physics.operators`` with a filter built here) for
a kernel moved away from the physics one.
"""

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nlosjax.models import count_params
from nlosjax.models.ik import IKConfig, LearnableInverseKernel, band_weights
from nlosjax.models.lfe import LFEConfig
from nlosjax.physics import Setup
from nlosjax.train import RunConfig
from tests.test_lfe import TINY, scene


def test_band_weights_against_a_loop_over_frequencies():
  shape, bands = (6, 4, 5), 3
  got = band_weights(shape, bands)
  want = np.zeros((bands,) + shape)
  for i, j, k in itertools.product(*map(range, shape)):
    fy = (i if i < 3 else i - 6) / 6              # fftfreq of 6
    fx = j / 6                                    # rfftfreq of 2 * (4 - 1) = 6
    fv = (k if k < 3 else k - 5) / 5              # fftfreq of 5
    r = math.sqrt(fy * fy + fx * fx + fv * fv) / (math.sqrt(3) / 2)
    for b in range(bands):
      want[b, i, j, k] = max(0.0, 1.0 - abs(r - b / (bands - 1)) * (bands - 1))
  np.testing.assert_allclose(got, want, atol=1e-6)
  np.testing.assert_allclose(got.sum(0), 1.0, atol=1e-6)     # radii stay within [0, 1]


def test_at_initialisation_ik_is_lfe():
  """Kernel = LCT's Wiener filter and gains = 1: with LFE's extraction and heads, LFE's outputs."""
  ik, lfe = IKConfig(setup=TINY, extract_width=1), LFEConfig(setup=TINY, extract_width=1)
  x = scene()
  p_ik = ik.module().init(jax.random.PRNGKey(1), jnp.zeros(ik.input_shape()))["params"]
  p_lfe = jax.device_get(lfe.module().init(jax.random.PRNGKey(2), jnp.zeros(lfe.input_shape()))["params"])
  p_ik = {**jax.device_get(p_ik), **{k: v for k, v in p_lfe.items() if k != "transform"}}
  a, b = ik.module().apply({"params": p_ik}, x), lfe.module().apply({"params": p_lfe}, x)
  for key in ("feature_volume", "intensity", "depth", "volume"):
    np.testing.assert_allclose(np.asarray(a[key]), np.asarray(b[key]), atol=2e-5, err_msg=key)


def test_a_moved_kernel_and_gains_match_lct_run_by_hand_with_that_filter():
  from nlosjax.models.usm import half_setup
  from nlosjax.physics.operators import lct_apply, lct_filter, to_depth
  coarse = half_setup(TINY)
  layer = LearnableInverseKernel(coarse, snr=0.1, bands=3, attention_width=2)
  a, b = layer.window()
  rng = np.random.default_rng(0)
  x = rng.uniform(size=(2, b - a, 8, 8, 2)).astype(np.float32)
  params = jax.device_get(layer.init(jax.random.PRNGKey(0), x, time_offset=a)["params"])
  params["kernel_re"] = rng.normal(0, 0.1, params["kernel_re"].shape).astype(np.float32)
  params["kernel_im"] = rng.normal(0, 0.1, params["kernel_im"].shape).astype(np.float32)
  params["attention_gain"]["kernel"] = rng.normal(0, 0.5, params["attention_gain"]["kernel"].shape).astype(np.float32)
  got = np.asarray(layer.apply({"params": params}, x, time_offset=a))
  # By hand: the attention MLP in NumPy, then LCT with the filter K * sum_k gain_k w_k.
  ops = layer.operators()
  phys = np.asarray(lct_filter(ops, 0.1))
  kernel = phys + np.abs(phys).max() * (params["kernel_re"] + 1j * params["kernel_im"])
  pooled = np.concatenate([x.mean(axis=(1, 2, 3)), x.max(axis=(1, 2, 3))], -1)
  h = np.maximum(pooled @ params["attention_hidden"]["kernel"] + params["attention_hidden"]["bias"], 0)
  logits = (h @ params["attention_gain"]["kernel"] + params["attention_gain"]["bias"]).reshape(2, 2, 3)
  gains = 2 / (1 + np.exp(-logits))
  w = band_weights(phys.shape, 3)
  t0, t1 = ops.domain.t
  for i, c in itertools.product(range(2), range(2)):
    filt = jnp.asarray(kernel * np.tensordot(gains[i, c], w, axes=1), jnp.complex64)
    want = np.maximum(np.asarray(to_depth(lct_apply(jnp.asarray(x[i, t0 - a:t1 - a, :, :, c]), ops, filt), ops)), 0)
    np.testing.assert_allclose(got[i, ..., c], want, rtol=1e-4, atol=1e-5 * np.abs(want).max())


def test_size_is_lfes_plus_the_kernel_volume_and_the_attention():
  cfg = IKConfig(setup=TINY, extract_width=3, bands=4, attention_width=8)
  shapes = jax.eval_shape(cfg.module().init, jax.random.PRNGKey(0), jnp.zeros(cfg.input_shape()))
  C = 4
  attention = (2 * C * 8 + 8) + (8 * C * 4 + C * 4)
  assert count_params(shapes["params"]) == 1_095 + 2 * 13_659 + 2 * math.prod(cfg.kernel_shape()) + attention


@pytest.mark.parametrize("case", ["zeros", "one_photon", "saturated", "scene"])
def test_extreme_inputs_give_finite_outputs_and_gradients_that_reach_the_kernel(case):
  cfg = IKConfig(setup=TINY, extract_width=1)
  net = cfg.module()
  params = net.init(jax.random.PRNGKey(0), jnp.zeros(cfg.input_shape()))["params"]
  x = scene() if case == "scene" else np.zeros(cfg.input_shape(), np.float32)
  if case == "one_photon":
    x[0, 0, 20, 1, 2] = 1.0
  elif case == "saturated":
    x[:] = 1e6

  def loss(p):
    out = net.apply({"params": p}, x)
    return jnp.mean(out["intensity"] ** 2) + jnp.mean(out["depth"] ** 2)

  value, grads = jax.value_and_grad(loss)(params)
  assert np.isfinite(float(value))
  assert all(np.all(np.isfinite(g)) for g in jax.tree_util.tree_leaves(grads))
  if case == "scene":
    assert np.any(np.asarray(grads["transform"]["kernel_re"]) != 0)
    # The gain layer starts at 0, so at initialisation only it (not the hidden layer) has a gradient.
    assert np.any(np.asarray(grads["transform"]["attention_gain"]["kernel"]) != 0)


@pytest.mark.parametrize("kwargs, match", [
    (dict(physics="phasor"), "physics must be 'lct'"), (dict(bands=1), "bands"),
    (dict(attention_width=0), "attention_width"), (dict(stride=9), "stride must be"),
])
def test_bad_configs_are_refused(kwargs, match):
  with pytest.raises(ValueError, match=match):
    IKConfig(setup=TINY, **kwargs)


def test_the_training_loop_builds_ik_and_two_steps_move_the_kernel_and_the_attention():
  import optax

  from experiments import configs
  from nlosjax import losses, train
  from nlosjax.train.sharding import make_mesh
  from nlosjax.train.state import create_train_state
  from nlosjax.train.step import make_train_step
  config = {"data": {"input_stride": 4}, "model": {"wavelet_cycles": 4.0},
            "ik": {"model": {"extract_width": 1, "bands": 3}}}
  mcfg = train.model_config_for(RunConfig.from_dict(config), TINY, "ik")
  assert mcfg == IKConfig(setup=TINY, stride=4, extract_width=1, bands=3, wavelet_cycles=4.0)
  assert set(configs.skeleton().ik.model) >= {"extract_width", "bands", "attention_width"}
  state = create_train_state(mcfg.module(), mcfg.input_shape(2), optax.adam(1e-2), jax.random.PRNGKey(0),
                             make_mesh())
  before = jax.device_get(state.params)
  rng = np.random.default_rng(0)
  batch = {"measurement": np.concatenate([scene(0), scene(1)]).astype(np.float32),
           "transient": rng.poisson(1.0, (2, 64, 16, 16)).astype(np.float32),
           "intensity": rng.uniform(size=(2, 16, 16)).astype(np.float32),
           "depth": rng.uniform(0.3, 1.0, (2, 16, 16)).astype(np.float32)}
  step = make_train_step(mcfg, losses.LossWeights(), make_mesh())
  for i in range(2):         # two: the hidden layer's gradient waits for the zero-started gain layer to move
    state, metrics = step(state, batch, jax.random.PRNGKey(1 + i))
    assert np.isfinite(float(metrics["loss"]))
  moved = jax.tree_util.tree_map(lambda a, b: bool(np.any(a != b)), before, jax.device_get(state.params))
  assert all(jax.tree_util.tree_leaves(moved["transform"]))
  assert all(jax.tree_util.tree_leaves(moved["render_intensity"]))


def test_a_setup_it_cannot_run_is_refused():
  with pytest.raises(ValueError, match="square grid"):
    IKConfig(setup=Setup(wall_size=0.6, grid=(16, 12), bin_width=64e-12, num_bins=64))

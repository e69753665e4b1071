"""nlosjax.models.lfe: LFE's size, its input, its physics path, gradients, errors.

Independent references: the parameter count of the public code's parts
(extraction 1,095 and each rendering head 13,659, counted by hand from the
layer list of the authors' release), a hand-built interpolation of the scan
points, a NumPy 2 x 2 x 2 block mean (the pooling kernel at initialisation),
``nlosjax.physics.reconstruct`` (the transform must reproduce LCT on the
pooled transient) and ``jax.image.resize`` for the rendering's x2.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nlosjax import physics
from nlosjax.models import count_params
from nlosjax.models.lfe import LFEConfig, interpolate_scan
from nlosjax.models.usm import half_setup
from nlosjax.physics import Setup
from nlosjax.train import RunConfig

# 16 x 16 scan of a 0.6 m wall, 64 ps bins, 64 bins; stride 4 -> 4 x 4 input.
TINY = Setup(wall_size=0.6, grid=(16, 16), bin_width=64e-12, num_bins=64)


def scene(seed=0):
  """``[1, 1, 64, 4, 4]`` counts of a patch at depth bin 30 plus background, at stride 4's points."""
  albedo = np.zeros((64, 16, 16), np.float32)
  albedo[30, 5:11, 6:10] = 1.0
  clean = np.asarray(physics.render(albedo, TINY))
  counts = np.random.default_rng(seed).poisson(clean / clean.max() * 40 + 0.1).astype(np.float32)
  return counts[None, None, :, 2::4, 2::4]


def hand_interpolation(x):
  """Bilinear between the points 2 + 4 i, held past the ends (written apart from the library)."""
  pos = np.clip((np.arange(16) - 2) / 4.0, 0, 3)
  lo = np.minimum(np.floor(pos).astype(int), 2)
  m = np.zeros((16, 4))
  m[np.arange(16), lo] = 1 - (pos - lo)
  m[np.arange(16), lo + 1] += pos - lo
  return np.einsum("Hh,...hw,Ww->...HW", m, x, m)


def test_published_size_is_the_public_parts_count():
  cfg = LFEConfig(setup=TINY, extract_width=3)
  shapes = jax.eval_shape(cfg.module().init, jax.random.PRNGKey(0), jnp.zeros(cfg.input_shape()))
  assert count_params(shapes["params"]) == 1_095 + 2 * 13_659
  assert cfg.render_widths == (8, 16)


def test_interpolation_is_the_classic_methods_input():
  x = scene()[0, 0]
  np.testing.assert_allclose(np.asarray(interpolate_scan(jnp.asarray(x), TINY.grid, 4)),
                             hand_interpolation(x), rtol=1e-5, atol=1e-5)
  with pytest.raises(ValueError, match="samples must be"):
    interpolate_scan(jnp.zeros((64, 5, 4)), TINY.grid, 4)


def test_with_the_residual_zeroed_the_intensity_is_lct_of_the_pooled_interpolated_scan():
  cfg = LFEConfig(setup=TINY, extract_width=1)
  x = scene()
  net = cfg.module()
  params = jax.device_get(net.init(jax.random.PRNGKey(1), jnp.zeros(cfg.input_shape()))["params"])
  last = params["render_intensity"]["conv2"]
  params["render_intensity"]["conv2"] = {k: np.zeros_like(v) for k, v in last.items()}
  out = net.apply({"params": params}, x)
  # Independent path: scale, interpolate, min-max, 2 x 2 x 2 block mean, LCT, min-max, max, x2.
  dense = hand_interpolation(x[0, 0] / np.sqrt(np.mean(x.astype(np.float64) ** 2)))
  dense = (dense - dense.min()) / (dense.max() - dense.min())
  pooled = dense.reshape(32, 2, 8, 2, 8, 2).mean(axis=(1, 3, 5)).astype(np.float32)
  vol = np.asarray(physics.reconstruct(pooled, half_setup(TINY), "lct", snr=0.1, falloff="diffuse",
                                       variant="refined"))
  vol = (vol - vol.min()) / (vol.max() - vol.min())
  np.testing.assert_allclose(np.asarray(out["feature_volume"][0, ..., 0]), vol, atol=2e-5)
  expected = jax.image.resize(jnp.asarray(vol.max(axis=0)), (16, 16), "linear")
  np.testing.assert_allclose(np.asarray(out["intensity"][0]), np.clip(np.asarray(expected), 0, 1),
                             atol=2e-5)
  assert out["volume"].shape == (1, TINY.num_depth_bins, 16, 16)
  assert out["transient"].shape == (1, 64, 16, 16)


@pytest.fixture(scope="module")
def loss_and_grad():
  """``(params, jitted (params, frames) -> (loss, grads))`` of a tiny LFE: one compile for every case."""
  cfg = LFEConfig(setup=TINY, extract_width=1)
  net = cfg.module()
  params = net.init(jax.random.PRNGKey(0), jnp.zeros(cfg.input_shape()))["params"]

  def loss(p, x):
    out = net.apply({"params": p}, x)
    return jnp.mean(out["intensity"] ** 2) + jnp.mean(out["depth"] ** 2)

  return params, cfg.input_shape(), jax.jit(jax.value_and_grad(loss))


@pytest.mark.parametrize("case", ["zeros", "one_photon", "saturated"])
def test_extreme_inputs_give_finite_outputs_and_gradients(case, loss_and_grad):
  params, shape, fn = loss_and_grad
  x = np.zeros(shape, np.float32)
  if case == "one_photon":
    x[0, 0, 20, 1, 2] = 1.0
  elif case == "saturated":
    x[:] = 1e6
  value, grads = fn(params, x)
  assert np.isfinite(float(value))
  assert all(np.all(np.isfinite(g)) for g in jax.tree_util.tree_leaves(grads))


@pytest.mark.parametrize("kwargs, match", [
    (dict(stride=9), "stride must be"), (dict(frames=3), "frames must be 1"),
    (dict(physics="fk"), "physics must be one of"), (dict(extract_width=0), "extract_width"),
    (dict(lct_snr=0.0), "lct_snr"), (dict(input_norm="l1"), "input_norm"),
])
def test_bad_configs_are_refused(kwargs, match):
  with pytest.raises(ValueError, match=match):
    LFEConfig(setup=TINY, **kwargs)


def test_wrong_frames_and_negative_counts_are_refused():
  cfg = LFEConfig(setup=TINY, extract_width=1)
  net = cfg.module()
  params = net.init(jax.random.PRNGKey(0), jnp.zeros(cfg.input_shape()))["params"]
  with pytest.raises(ValueError, match="scan grid"):
    net.apply({"params": params}, jnp.zeros((1, 1, 64, 5, 5)))
  with pytest.raises(ValueError):
    net.apply({"params": params}, -np.ones(cfg.input_shape(), np.float32))


def test_the_training_loop_builds_lfe_and_one_step_moves_every_learned_part():
  import optax

  from experiments import configs
  from nlosjax import losses, train
  from nlosjax.train.sharding import make_mesh
  from nlosjax.train.state import create_train_state
  from nlosjax.train.step import make_train_step
  config = {"data": {"input_stride": 4}, "model": {"wavelet_cycles": 4.0},
            "train": {"optim": {"learning_rate": 1e-3}},
            "lfe": {"model": {"extract_width": 1}, "optim": {"learning_rate": 3e-4}}}
  mcfg = train.model_config_for(RunConfig.from_dict(config), TINY, "lfe")
  assert mcfg == LFEConfig(setup=TINY, stride=4, extract_width=1, wavelet_cycles=4.0)
  assert train.training_recipe(RunConfig.from_dict(config), "lfe")[0].learning_rate == 3e-4
  assert train.training_recipe(RunConfig.from_dict(config), "ours")[0].learning_rate == 1e-3
  assert set(configs.skeleton().lfe.model) >= {"extract_width", "physics", "lct_snr"}
  weights = losses.LossWeights()
  state = create_train_state(mcfg.module(), mcfg.input_shape(2), optax.adam(1e-2), jax.random.PRNGKey(0),
                             make_mesh())
  before = jax.device_get(state.params)
  rng = np.random.default_rng(0)
  batch = {"measurement": np.concatenate([scene(0), scene(1)]).astype(np.float32),
           "transient": rng.poisson(1.0, (2, 64, 16, 16)).astype(np.float32),
           "intensity": rng.uniform(size=(2, 16, 16)).astype(np.float32),
           "depth": rng.uniform(0.3, 1.0, (2, 16, 16)).astype(np.float32)}
  state, metrics = make_train_step(mcfg, weights, make_mesh())(state, batch, jax.random.PRNGKey(1))
  assert np.isfinite(float(metrics["loss"]))
  moved = jax.tree_util.tree_map(lambda a, b: bool(np.any(a != b)), before, jax.device_get(state.params))
  assert all(jax.tree_util.tree_leaves(moved["render_intensity"]))
  assert all(jax.tree_util.tree_leaves(moved["extract"]))

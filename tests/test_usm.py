"""nlosjax.models.usm: USM's published size, its input convention, its LCT layer, gradients, errors.

Independent references: the parameter count of the public code (115,042,
counted by hand from the layer list of the authors' public release),
the public code's scan mask written out for 128 x 128 at stride 8, brute-force
NumPy loops (replicate-padded convolution, 2 x 2 x 2 average pooling, the mask
times the full transient), ``nlosjax.physics.lct`` (the LCT layer must
reproduce it), and the geometry of the scan points (a coarse point is the
mean of its 2 x 2 block).
"""

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nlosjax import losses, physics, train
from nlosjax.models import conv, count_params, model_summary, physics_layer
from nlosjax.models.usm import (
  PUBLISHED_LOSS,
  PUBLISHED_OPTIM,
  Extraction,
  USMConfig,
  USMNet,
  half_setup,
  scan_mask,
  zero_fill,
)
from nlosjax.physics import Setup
from nlosjax.train import RunConfig
from tests.xla_options import xla_optimizations

# 8 x 8 scan of a 0.5 m wall, 64 ps bins, 32 bins; stride 2 -> 4 x 4 input.
TINY = Setup(wall_size=0.5, grid=(8, 8), bin_width=64e-12, num_bins=32)
TINY_KW = dict(stride=2, trn_width=2, trn_kernels=(3, 5), fusion_widths=(2,), extract_width=1,
               refine=((2, 3), (2, 3)), render_widths=(2, 2))


@pytest.fixture(scope="module", autouse=True)
def _fast_compiles():
  with xla_optimizations(False):
    yield


def tiny(**kw):
  return USMConfig(**{"setup": TINY, **TINY_KW, **kw})


def counts(key, shape, rate=0.5):
  return jax.random.poisson(key, rate, shape).astype(jnp.float32)


# ------------------------------------------------------------------ size
def test_published_parameter_count():
  """USM's widths on its 128 x 128 x 512 capture: the public code's 115,042 parameters."""
  cfg = USMConfig.published()
  x = jax.ShapeDtypeStruct(cfg.input_shape(1), jnp.float32)
  params = jax.eval_shape(USMNet(cfg).init, jax.random.key(0), x)["params"]
  assert count_params(params) == 115_042
  # Per stage (the public code's: recovery 58,953, extraction 1,095, refinement 27,676,
  # each rendering head 13,659).
  stage = {k: count_params(v) for k, v in params.items()}
  assert stage["trn"] == 58_953
  assert stage["extract"] == 1_095
  assert sum(v for k, v in stage.items() if k.startswith("refine")) == 27_676
  assert stage["render_intensity"] == stage["render_depth"] == 13_659


def test_parameter_tree_does_not_depend_on_the_setup():
  cfg = tiny()
  other = cfg.with_setup(Setup(wall_size=1.0, grid=(12, 12), bin_width=32e-12, num_bins=48))
  shapes = []
  for c in (cfg, other):
    x = jax.ShapeDtypeStruct(c.input_shape(1), jnp.float32)
    p = jax.eval_shape(USMNet(c).init, jax.random.key(0), x)["params"]
    shapes.append(jax.tree.map(lambda a: a.shape, p))
  assert shapes[0] == shapes[1]


# ------------------------------------------------------------ input convention
def test_scan_mask_is_the_public_one():
  """128 x 128 at stride 8: rows and columns 4, 12, ..., 124 (USM's ``ds_meas`` mask)."""
  m = scan_mask((128, 128), 8)
  rows = np.flatnonzero(m.any(axis=1))
  cols = np.flatnonzero(m.any(axis=0))
  np.testing.assert_array_equal(rows, np.arange(4, 128, 8))
  np.testing.assert_array_equal(cols, np.arange(4, 128, 8))
  assert m.sum() == 16 * 16


@pytest.mark.parametrize("grid, stride", [((8, 8), 2), ((12, 12), 4), ((9, 9), 3)])
def test_zero_fill_is_mask_times_full_transient(grid, stride):
  rng = np.random.default_rng(0)
  full = rng.poisson(2.0, (5,) + grid).astype(np.float32)
  samples = full[:, stride // 2::stride, stride // 2::stride]
  filled = np.asarray(zero_fill(jnp.asarray(samples), grid, stride))
  expected = np.zeros_like(full)
  for i in range(grid[0]):
    for j in range(grid[1]):
      if i % stride == stride // 2 and j % stride == stride // 2:
        expected[:, i, j] = full[:, i, j]
  np.testing.assert_array_equal(filled, expected)
  np.testing.assert_array_equal(filled, full * scan_mask(grid, stride))


def test_zero_fill_rejects_a_wrong_grid():
  with pytest.raises(ValueError, match="samples must be"):
    zero_fill(jnp.zeros((4, 3, 3)), (8, 8), 2)


def test_half_setup_points_are_block_means():
  setup = Setup(wall_size=0.7, grid=(10, 10), bin_width=50e-12, num_bins=20)
  coarse = half_setup(setup)
  fine = setup.scan_points
  means = fine.reshape(5, 2, 5, 2, 3).mean(axis=(1, 3))
  np.testing.assert_allclose(coarse.scan_points, means, atol=1e-12)
  assert coarse.bin_width == 2 * setup.bin_width and coarse.num_bins == 10


# ----------------------------------------------------------------- layers
def _conv3d_edge_loop(x, k, b):
  """Brute force: replicate padding 1, 3x3x3 cross-correlation. x [T, H, W, C], k [3,3,3,C,F]."""
  T, H, W, C = x.shape
  xp = np.pad(x, ((1, 1), (1, 1), (1, 1), (0, 0)), mode="edge")
  out = np.zeros((T, H, W, k.shape[-1]))
  for t in range(T):
    for i in range(H):
      for j in range(W):
        out[t, i, j] = np.einsum("abcx,abcxf->f", xp[t:t + 3, i:i + 3, j:j + 3], k) + b
  return out


@pytest.mark.parametrize("impl", ["fold", "xla"])
def test_replicate_padded_conv_matches_a_loop(impl):
  rng = np.random.default_rng(1)
  x = rng.normal(size=(1, 5, 4, 6, 2)).astype(np.float32)
  layer = conv.Conv3D(3, padding="edge", impl=impl)
  params = layer.init(jax.random.key(0), x)
  params = jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape), jnp.float32), params)
  y = np.asarray(layer.apply(params, x))[0]
  ref = _conv3d_edge_loop(x[0].astype(np.float64), np.asarray(params["params"]["kernel"], np.float64),
                          np.asarray(params["params"]["bias"], np.float64))
  np.testing.assert_allclose(y, ref, rtol=1e-4, atol=1e-4)


def test_extraction_pool_starts_as_average_pooling():
  rng = np.random.default_rng(2)
  x = rng.uniform(size=(1, 6, 4, 8)).astype(np.float32)
  ext = Extraction(2)
  params = ext.init(jax.random.key(0), x)
  y = np.asarray(ext.apply(params, x))
  assert y.shape == (1, 3, 2, 4, 3)
  pooled = np.zeros((3, 2, 4))
  for t in range(3):
    for i in range(2):
      for j in range(4):
        pooled[t, i, j] = x[0, 2 * t:2 * t + 2, 2 * i:2 * i + 2, 2 * j:2 * j + 2].mean()
  np.testing.assert_allclose(y[0, ..., 0], pooled, rtol=1e-5, atol=1e-6)


def test_lct_layer_is_nlosjax_physics_lct():
  """The features entering USM's LCT layer, channel 0, give exactly ``physics.lct`` on the half Setup."""
  cfg = tiny()
  shape, params, _ = _tiny_usm_compiled()
  x = counts(jax.random.key(3), shape, 2.0)
  model = USMNet(cfg)

  def features_in_and_out(params, x):
    seen = {}

    def record(next_fun, args, kwargs, context):
      out = next_fun(*args, **kwargs)
      if isinstance(context.module, physics_layer.FeatureTransform) and context.method_name == "__call__":
        seen["x"], seen["out"] = args[0], out
      return out

    with nn.intercept_methods(record):
      model.apply(params, x)
    return seen["x"], seen["out"]

  feats, out = map(np.asarray, jax.jit(features_in_and_out)(params, x))
  coarse = half_setup(TINY)
  assert feats.shape[1:4] == (coarse.num_bins,) + coarse.grid
  ref = physics.lct(jnp.asarray(feats[..., 0]), coarse, snr=cfg.lct_snr, falloff=cfg.falloff,
                    variant="refined")
  np.testing.assert_allclose(out[..., 0], np.asarray(ref), rtol=1e-4,
                             atol=1e-5 * float(np.abs(ref).max()))


# ------------------------------------------------------------------ model
def test_shapes_and_finite_outputs():
  cfg = tiny()
  shape, params, apply = _tiny_usm_compiled()
  assert shape == cfg.input_shape(1)
  out = apply(params, counts(jax.random.key(5), shape))
  H, W = TINY.grid
  assert out["transient"].shape == (1, TINY.num_bins, H, W)
  assert out["volume"].shape == (1, TINY.num_depth_bins, H, W)
  assert out["feature_volume"].shape == (1, 16, H // 2, W // 2, cfg.channels)
  assert out["intensity"].shape == out["depth"].shape == (1, H, W)
  assert all(bool(jnp.all(jnp.isfinite(v))) for v in out.values())
  assert float(out["volume"].min()) >= 0.0


@functools.lru_cache(maxsize=1)
def _tiny_usm_compiled():
  """``(input shape, variables, jitted apply)`` of the tiny USM, built once per test process."""
  cfg = tiny()
  shape = cfg.input_shape(1)
  model = USMNet(cfg)
  return shape, jax.jit(model.init)(jax.random.key(7), jnp.ones(shape)), jax.jit(model.apply)


@pytest.mark.parametrize("kind", ["zero", "single", "saturated"])
def test_extreme_inputs_stay_finite(kind):
  shape, params, apply = _tiny_usm_compiled()
  x = np.zeros(shape, np.float32)
  if kind == "single":
    x[0, 0, 5, 1, 2] = 1.0
  elif kind == "saturated":
    x[:] = 1e9
  out = apply(params, jnp.asarray(x))
  for k, v in out.items():
    assert bool(jnp.all(jnp.isfinite(v))), (kind, k)


def test_gradients_reach_every_parameter():
  cfg = tiny()
  x = counts(jax.random.key(8), cfg.input_shape(2), 2.0)
  model = USMNet(cfg)
  params = jax.jit(model.init)(jax.random.key(9), x)["params"]

  def loss(p):
    out = model.apply({"params": p}, x)
    return (jnp.mean(out["intensity"] ** 2) + jnp.mean(out["depth"] ** 2)
            + jnp.mean(out["transient"] ** 2) + jnp.mean(out["feature_volume"] ** 2))

  grads = jax.jit(jax.grad(loss))(params)
  for path, g in jax.tree_util.tree_leaves_with_path(grads):
    assert bool(jnp.all(jnp.isfinite(g))), jax.tree_util.keystr(path)
    assert float(jnp.abs(g).max()) > 0, f"no gradient reaches {jax.tree_util.keystr(path)}"


@pytest.mark.full
def test_jit_matches_eager():
  shape, params, apply = _tiny_usm_compiled()
  x = counts(jax.random.key(10), shape)
  eager = USMNet(tiny()).apply(params, x)          # op by op
  jitted = apply(params, x)
  for k in eager:
    np.testing.assert_allclose(np.asarray(jitted[k]), np.asarray(eager[k]), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("kwargs, match", [
    (dict(frames=3), "frames must be 1"),
    (dict(trn_kernels=(3, 4)), "odd"),
    (dict(refine=((2, 3), (3, 3))), "must end at 2 channels"),
    (dict(setup=Setup(wall_size=0.5, grid=(8, 6), bin_width=64e-12, num_bins=32)), "square grid"),
    (dict(setup=Setup(wall_size=0.5, grid=(8, 8), bin_width=64e-12, num_bins=31)), "T even"),
    (dict(stride=0), "stride"),
    (dict(falloff="specular"), "falloff"),
])
def test_config_errors(kwargs, match):
  with pytest.raises(ValueError, match=match):
    tiny(**kwargs)


def test_wrong_input_is_named():
  cfg = tiny()
  model = USMNet(cfg)
  good = jnp.zeros(cfg.input_shape(1))
  params = _tiny_usm_compiled()[1]
  with pytest.raises(ValueError, match="frames"):
    model.apply(params, jnp.zeros((1, 3) + cfg.input_shape(1)[2:]))
  with pytest.raises(ValueError, match="NaN|negative"):
    model.apply(params, good.at[0, 0, 0, 0, 0].set(jnp.nan))


def test_summary_counts_parameters_and_the_lct_ffts():
  s = model_summary(tiny())
  assert s["params"] > 0 and s["fft_flops"] > 0 and s["scan_flops"] == 0


# ------------------------------------------------------------------ recipe
def test_published_recipe_and_variant_config():
  widths = {k: v for k, v in TINY_KW.items() if k != "stride"}
  config = {"data": {"input_stride": 2}, "train": {"loss": {"object_intensity": 3.0}},
            "usm": {"recipe": "published", "model": widths}}
  optim, weights = train.training_recipe(RunConfig.from_dict(config), "usm")
  assert optim == train.OptimConfig(**PUBLISHED_OPTIM)
  assert (optim.learning_rate, optim.weight_decay, optim.cosine, optim.clip_norm) == (1e-4, 1e-4,
                                                                                      False, None)
  assert weights == losses.LossWeights(**PUBLISHED_LOSS)
  # USM's loss: transient 1, intensity 1, depth 0, LS 1e-5, TV 1e-6, no phasor-field term.
  assert weights.alpha1 == 1 and weights.alpha2 == 0 and weights.phasor_field == 0
  assert weights.gamma * weights.local_similarity == pytest.approx(1e-5)
  assert weights.gamma * weights.alpha3 == pytest.approx(1e-6)
  # Ours' recipe for Ours, and for USM unless asked otherwise.
  assert train.training_recipe(RunConfig.from_dict(config), "ours")[1].object_intensity == 3.0
  config["usm"]["recipe"] = "ours"
  assert train.training_recipe(RunConfig.from_dict(config), "usm")[1].object_intensity == 3.0
  # USM's own optimiser entries (its learning rate chosen on validation) over Ours'.
  config["train"]["optim"] = {"learning_rate": 1e-3, "weight_decay": 0.95}
  config["usm"]["optim"] = {"learning_rate": 3e-4}
  usm_optim = train.training_recipe(RunConfig.from_dict(config), "usm")[0]
  assert (usm_optim.learning_rate, usm_optim.weight_decay) == (3e-4, 0.95)
  assert train.training_recipe(RunConfig.from_dict(config), "ours")[0].learning_rate == 1e-3
  config["usm"]["recipe"] = "nope"
  with pytest.raises(ValueError, match="recipe"):
    train.training_recipe(RunConfig.from_dict(config), "usm")
  with pytest.raises(ValueError, match="recipe"):    # the typed config refuses it wherever it is read
    train.model_config_for(RunConfig.from_dict(config), TINY, "usm")
  config["usm"]["recipe"] = "ours"
  mcfg = train.model_config_for(RunConfig.from_dict(config), TINY, "usm")
  assert isinstance(mcfg, USMConfig) and mcfg.trn_width == 2 and mcfg.stride == 2


def test_regularisers_act_on_every_feature_channel():
  """LS sums its per-channel terms and TV never differences across channels (USM's ``V``)."""
  rng = np.random.default_rng(12)
  vol = jnp.asarray(rng.uniform(size=(2, 4, 5, 6, 3)), jnp.float32)
  local_similarity, tv_loss = jax.jit(losses.local_similarity_loss), jax.jit(losses.tv_loss)
  ls = local_similarity(vol)
  assert float(ls) == pytest.approx(sum(float(local_similarity(vol[..., c])) for c in range(3)), rel=1e-5)
  tv = tv_loss(vol)
  assert float(tv) == pytest.approx(sum(float(tv_loss(vol[..., c])) for c in range(3)), rel=1e-5)

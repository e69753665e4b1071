"""nlosjax.models: shapes, causality, mirror equivariance, gradients, the physics layer, jit, errors.

Independent references: ``nlosjax.physics.phasor`` / ``lct`` (the physics
layer must reproduce them), XLA's own 3-D convolution (for the time-folded
one), the hard argmax projection of ``nlosjax.physics.intensity_depth``, and
properties that hold by construction (causality of the temporal SSM, the
180-degree rotation equivariance of the bidirectional spatial SSM with
mirrored parameters, scale invariance of the input normalisation).
Everything runs at tiny shapes (8 x 8 scan grid, 32 bins).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nlosjax import physics
from nlosjax.models import (
  BLOCK_MIXERS,
  CrossSTMambaBlock,
  FeatureTransform,
  ModelConfig,
  STMambaBlock,
  STMambaNet,
  VolumeReconstruction,
  blocks,
  coarsen_setup,
  conv,
  count_params,
  mirror_spatial_params,
  model_summary,
  soft_projection,
  underscan,
)
from nlosjax.physics import Setup
from tests.conv_reference import same_conv3d
from tests.xla_options import xla_optimizations

# 8 x 8 scan of a 0.5 m wall, 64 ps bins, 32 bins (depths up to 0.31 m); stride 2 -> 4 x 4 input.
TINY = Setup(wall_size=0.5, grid=(8, 8), bin_width=64e-12, num_bins=32)
TINY_KW = dict(stride=2, width=8, d_state=4, extract_time_stride=2, extract_blocks=1,
               st_depth=1, cross_depth=1, volume_time_stride=2, volume_features=2, refine_width=4,
               spread_min_width=2)


@pytest.fixture(scope="module", autouse=True)
def _fast_compiles():
  """Tiny shapes: XLA's optimisations cost more compile time than they save (as flax's examples)."""
  with xla_optimizations(False):
    yield


def tiny_config(**kw):
  return ModelConfig.cpu(TINY, **{**TINY_KW, **kw})


def counts(key, shape, rate=0.5):
  return jax.random.poisson(key, rate, shape).astype(jnp.float32)


def point_scene(setup: Setup) -> np.ndarray:
  """A noise-free transient ``[T, H, W]`` of two small patches, max-normalised."""
  T, (H, W) = setup.num_bins, setup.grid
  albedo = np.zeros((T, H, W), np.float32)
  albedo[T // 3, H // 4:H // 2, W // 3] = 1.0
  albedo[T // 2, 2 * H // 3, W // 2:3 * W // 4] = 0.7
  x = np.asarray(physics.render(albedo, setup.ungated()))
  return x / x.max()


# ------------------------------------------------------------------ config
@pytest.mark.parametrize("kwargs, match", [
    (dict(frames=2), "frames"),
    (dict(stride=0), "stride"),
    (dict(stride=16), "stride"),
    (dict(variant="xy"), "variant"),
    (dict(extract_time_stride=3), "extract_time_stride"),
    (dict(physics="fk"), "physics"),
    (dict(dtype="float16"), "dtype"),
    (dict(input_norm="median"), "input_norm"),
])
def test_config_rejects_bad_fields(kwargs, match):
  with pytest.raises(ValueError, match=match):
    tiny_config(**kwargs)


def test_config_derives_shapes_from_the_setup():
  cfg = ModelConfig.paper()
  assert cfg.input_shape(4) == (4, 3, 512, 16, 16)
  cfg = tiny_config()
  assert cfg.input_grid == (4, 4) and cfg.scan_offset == 1
  gated = cfg.with_setup(TINY.with_depth_range(0.1, 0.2))
  a, b = gated.time_window
  assert a % gated.volume_time_stride == 0 and 0 <= a < b <= TINY.num_bins
  x = np.arange(32 * 8 * 8, dtype=np.float32).reshape(32, 8, 8)
  np.testing.assert_array_equal(underscan(x, 2), x[:, 1::2, 1::2])
  assert underscan(np.zeros((5, 128, 128)), 8).shape == (5, 16, 16)


# ------------------------------------------------------------------- shapes
@pytest.mark.parametrize("kw, setup", [
    (dict(frames=3), TINY),
    (dict(frames=1), TINY),
    (dict(frames=3, variant="s", remat=True, physics_chunk=1), TINY),
    (dict(frames=1, variant="tt", temporal_causal=False), TINY),
    (dict(frames=3, variant="ss", physics="lct", dtype="bfloat16"), TINY),
    (dict(frames=1, stride=4, volume_time_stride=1, extract_time_stride=4), TINY),
    (dict(frames=1, variant="t"), Setup(0.6, (12, 10), 48e-12, 40, depth_range=(0.1, 0.25))),
])
def test_network_output_shapes(kw, setup):
  cfg = tiny_config(**kw).with_setup(setup)
  model = STMambaNet(cfg)
  x = jax.ShapeDtypeStruct(cfg.input_shape(2), jnp.float32)
  variables = jax.eval_shape(model.init, jax.random.key(0), x)
  out = jax.eval_shape(model.apply, variables, x)
  T, (H, W), Z = setup.num_bins, setup.grid, setup.num_depth_bins
  assert out["transient"].shape == (2, T, H, W)
  assert out["volume"].shape == (2, Z, H, W)
  assert out["intensity"].shape == out["depth"].shape == (2, H, W)
  assert out["scale"].shape == (2,)
  assert all(v.dtype == jnp.float32 for v in out.values())
  # Frames = 1 has no cross ST-Mamba parameters; frames = 3 has one block per neighbour.
  names = set(variables["params"])
  assert any(n.startswith("cross_prev1") for n in names) == (cfg.frames == 3)
  assert any(n.startswith("cross_next1") for n in names) == (cfg.frames == 3)


def test_same_weights_run_on_another_setup():
  """Parameters do not depend on the Setup: weights built for one capture run on another."""
  cfg = tiny_config()
  other = cfg.with_setup(Setup(1.2, (10, 12), 40e-12, 48, depth_range=(0.1, 0.3)))
  x = jax.ShapeDtypeStruct(cfg.input_shape(1), jnp.float32)
  x_other = jax.ShapeDtypeStruct(other.input_shape(1), jnp.float32)
  params = jax.eval_shape(STMambaNet(cfg).init, jax.random.key(0), x)
  params_other = jax.eval_shape(STMambaNet(other).init, jax.random.key(0), x_other)
  assert jax.tree.structure(params) == jax.tree.structure(params_other)
  assert jax.tree.leaves(jax.tree.map(lambda a, b: a.shape == b.shape, params, params_other))
  out = jax.eval_shape(STMambaNet(other).apply, params, x_other)
  assert out["volume"].shape == (1, other.setup.num_depth_bins, 10, 12)


# ---------------------------------------------------------------- ST blocks
def _block_input(key, shape=(1, 12, 3, 4, 8)):
  return jax.random.normal(key, shape)


def _perturb(x, t0, seed):
  return x.at[:, t0].add(jax.random.normal(jax.random.key(seed), x[:, t0].shape))


@pytest.mark.parametrize("variant", ["st", "tt"])
def test_st_block_temporal_path_is_causal(variant):
  block = STMambaBlock(8, d_state=4, mixers=BLOCK_MIXERS[variant])
  x = _block_input(jax.random.key(1))
  params = jax.jit(block.init)(jax.random.key(2), x)
  t0 = 6
  x2 = _perturb(x, t0, 3)
  apply = jax.jit(block.apply)
  y, y2 = apply(params, x), apply(params, x2)
  np.testing.assert_allclose(y2[:, :t0], y[:, :t0], atol=1e-6, rtol=0)
  assert float(jnp.max(jnp.abs(y2[:, t0:] - y[:, t0:]))) > 1e-3
  if variant == "st":
    # The non-causal ablation does see the future (so the check above can fail).
    nc = STMambaBlock(8, d_state=4, mixers=BLOCK_MIXERS[variant], temporal_direction="bidirectional")
    apply_nc = jax.jit(nc.apply)
    p_nc = jax.jit(nc.init)(jax.random.key(2), x)
    assert float(jnp.max(jnp.abs(apply_nc(p_nc, x2)[:, :t0] - apply_nc(p_nc, x)[:, :t0]))) > 1e-4


def test_no_ssm_control_is_the_gated_mlp_written_out():
  """variant "none": every SSM is the identity, so the block is ``x + W_out((W_x LN(x)) * SiLU(W_z
  LN(x)))``, written here with plain jnp from the parameters; and no SSM parameter exists."""
  block = STMambaBlock(8, d_state=4, mixers=BLOCK_MIXERS["none"])
  x = _block_input(jax.random.key(11))
  params = jax.jit(block.init)(jax.random.key(12), x)["params"]
  assert set(params) == {"norm", "in_proj", "out_proj"}
  mu = x.mean(-1, keepdims=True)
  ln = (x - mu) / jnp.sqrt(((x - mu) ** 2).mean(-1, keepdims=True) + 1e-6)
  ln = ln * params["norm"]["scale"] + params["norm"]["bias"]
  xs, z = jnp.split(ln @ params["in_proj"]["kernel"], 2, axis=-1)
  expected = x + (xs * z * jax.nn.sigmoid(z)) @ params["out_proj"]["kernel"]
  np.testing.assert_allclose(block.apply({"params": params}, x), expected, atol=2e-5, rtol=1e-5)
  cross = CrossSTMambaBlock(8, d_state=4, mixers=BLOCK_MIXERS["none"])
  nb = _block_input(jax.random.key(13))
  cp = jax.jit(cross.init)(jax.random.key(14), x, nb)["params"]
  assert not any(k.startswith("ssm") for k in cp)


def test_cross_block_is_causal_in_both_inputs():
  block = CrossSTMambaBlock(8, d_state=4)
  ref, nb = _block_input(jax.random.key(4)), _block_input(jax.random.key(5))
  params = jax.jit(block.init)(jax.random.key(6), ref, nb)
  apply = jax.jit(block.apply)
  t0 = 5
  y = apply(params, ref, nb)
  for r2, n2 in ((_perturb(ref, t0, 1), nb), (ref, _perturb(nb, t0, 2))):
    y2 = apply(params, r2, n2)
    np.testing.assert_allclose(y2[:, :t0], y[:, :t0], atol=1e-6, rtol=0)
    assert float(jnp.max(jnp.abs(y2[:, t0:] - y[:, t0:]))) > 1e-3


@pytest.mark.parametrize("variant", ["st", "s", "ss"])
def test_spatial_ssm_mirror_equivariance(variant):
  """Rotating the scan grid by 180 degrees reverses the row-major sequence: with the forward
  and reverse spatial branches' parameters swapped, the block's output rotates with it."""
  block = STMambaBlock(8, d_state=4, mixers=BLOCK_MIXERS[variant])
  x = _block_input(jax.random.key(7))
  params = jax.jit(block.init)(jax.random.key(8), x)
  rot = lambda a: a[:, :, ::-1, ::-1]  # noqa: E731
  apply = jax.jit(block.apply)
  y = apply(params, x)
  y_m = apply(mirror_spatial_params(params), rot(x))
  np.testing.assert_allclose(y_m, rot(y), atol=2e-5, rtol=1e-4)
  # Without the swap the two branches play different roles: not equivariant.
  assert float(jnp.max(jnp.abs(apply(params, rot(x)) - rot(y)))) > 1e-3


def test_cross_block_mirror_equivariance():
  block = CrossSTMambaBlock(8, d_state=4)
  ref, nb = _block_input(jax.random.key(9)), _block_input(jax.random.key(10))
  params = jax.jit(block.init)(jax.random.key(11), ref, nb)
  rot = lambda a: a[:, :, ::-1, ::-1]  # noqa: E731
  apply = jax.jit(block.apply)
  np.testing.assert_allclose(apply(mirror_spatial_params(params), rot(ref), rot(nb)),
                             rot(apply(params, ref, nb)), atol=2e-5, rtol=1e-4)


# ----------------------------------------------------------- conv blocks
@pytest.mark.parametrize("kernel, stride, dilation", [
    ((3, 3, 3), 1, 1), ((3, 3, 3), 2, 1), ((3, 3, 3), 1, 4), ((1, 1, 1), 2, 1), ((3, 1, 1), 1, 2)])
def test_time_folded_conv_equals_xla_3d_conv(kernel, stride, dilation):
  x = jax.random.normal(jax.random.key(12), (2, 11, 5, 6, 3))
  fold = conv.Conv3D(4, kernel, stride, dilation)
  params = jax.jit(fold.init)(jax.random.key(13), x)
  ref = conv.Conv3D(4, kernel, stride, dilation, impl="xla").apply(params, x)
  out = fold.apply(params, x)
  assert out.shape == (2, -(-11 // stride), 5, 6, 4)
  np.testing.assert_allclose(out, ref, atol=1e-5, rtol=1e-5)
  # XLA's "SAME" convolution, not given the module's padding amounts.
  p = params["params"]
  np.testing.assert_allclose(out, same_conv3d(x, p["kernel"], p["bias"], stride, dilation),
                             atol=1e-5, rtol=1e-5)


def test_spreading_interpolates_the_measured_points():
  """With the learned branch zeroed, the recovered transient equals the measurement at the
  scanned points (the skip is an interpolation through them)."""
  spread = blocks.TransientSpreading((8, 8), 2, 2, min_width=2)
  skip = jax.random.uniform(jax.random.key(14), (1, 10, 4, 4))
  feats = jnp.zeros((1, 5, 4, 4, 4))
  params = jax.jit(spread.init)(jax.random.key(15), feats, skip)
  params = jax.tree.map(jnp.zeros_like, params)
  params["params"]["skip_gain"] = jnp.ones(())
  out = spread.apply(params, feats, skip)
  assert out.shape == (1, 10, 8, 8)
  np.testing.assert_allclose(underscan(out, 2), skip, atol=1e-6)


# --------------------------------------------------------------- physics
@pytest.mark.parametrize("method", ["phasor", "lct"])
@pytest.mark.parametrize("depth_range", [None, (0.09, 0.2)])
def test_feature_transform_is_the_physics(method, depth_range):
  """Identity features through the physics layer give nlosjax.physics' volume, also when the
  input is only the time window the layer reads (gating)."""
  setup = Setup(0.5, (8, 8), 64e-12, 48, depth_range=depth_range)
  x = point_scene(setup)
  ref = np.asarray(physics.reconstruct(x, setup, method, variant="refined", oversample=1))
  layer = FeatureTransform(setup, method)
  a, b = layer.window()
  apply = jax.jit(layer.apply, static_argnames="time_offset")   # eagerly, each operation compiles alone
  full = apply({}, jnp.asarray(x)[None, ..., None])[0, ..., 0]
  win = apply({}, jnp.asarray(x)[None, a:b, ..., None], time_offset=a)[0, ..., 0]
  assert full.shape == ref.shape == (setup.num_depth_bins, 8, 8)
  np.testing.assert_allclose(full, ref, atol=1e-5 * ref.max(), rtol=1e-4)
  np.testing.assert_allclose(win, ref, atol=1e-5 * ref.max(), rtol=1e-4)
  with pytest.raises(ValueError, match="reads"):
    layer.apply({}, jnp.asarray(x)[None, a + 1:b, ..., None], time_offset=a + 1)


@pytest.mark.parametrize("method", ["phasor", "lct"])
def test_feature_transform_with_public_operators_is_the_public_physics(method):
  """``variant="public"``: the layer gives ``nlosjax.physics``' public volume (its resampling
  matrix and wavelet, every bin read), and reads every bin; another image than the refined one."""
  setup = Setup(0.5, (8, 8), 64e-12, 48, depth_range=(0.09, 0.2))
  x = point_scene(setup)
  ref = np.asarray(physics.reconstruct(x, setup, method, variant="public"))
  layer = FeatureTransform(setup, method, variant="public")
  assert layer.window() == (0, setup.num_bins)
  out = jax.jit(layer.apply)({}, jnp.asarray(x)[None, ..., None])[0, ..., 0]
  assert out.shape == ref.shape == (setup.num_depth_bins, 8, 8)
  np.testing.assert_allclose(out, ref, atol=1e-5 * ref.max(), rtol=1e-4)
  refined = np.asarray(physics.reconstruct(x, setup, method, variant="refined", oversample=1))
  assert np.abs(refined / refined.max() - ref / ref.max()).max() > 1e-2
  with pytest.raises(ValueError, match="oversample"):
    FeatureTransform(setup, method, variant="public", oversample=2).apply({}, jnp.asarray(x)[None, ..., None])


def _physics_variants():
  gated = ModelConfig.cpu(TINY.with_depth_range(0.08, 0.25), **TINY_KW)
  return gated, dataclasses.replace(gated, physics_variant="public")


def test_model_config_physics_variant_is_checked_and_recorded():
  """``ModelConfig.physics_variant``: the refined layer by default, the public one reading every
  bin with its own operators; bad values fail when the config is made; a checkpoint written
  before the field existed (its ``repr`` lacks it) matches a refined run and not a public one."""
  from nlosjax.train import compare_model
  gated, public = _physics_variants()
  assert gated.physics_variant == "refined"
  assert public.volume_kwargs()["variant"] == "public"
  assert public.time_window == (0, TINY.num_bins)
  lct = {v: dataclasses.replace(gated, physics="lct", physics_variant=v) for v in ("refined", "public")}
  assert lct["public"].time_window == (0, TINY.num_bins) != lct["refined"].time_window   # gated
  assert [k[0] for k in public.physics_operators().keys] == ["public_lct_operators"]
  assert [k[0] for k in gated.physics_operators().keys] == ["lct_operators"]
  with pytest.raises(ValueError, match="not resolved"):   # checked for the public wavelet too
    dataclasses.replace(public, setup=Setup(0.6, (8, 8), 256e-12, 32), wavelet_sampling=1.0)
  with pytest.raises(ValueError, match="physics_variant"):
    dataclasses.replace(gated, physics_variant="published")
  with pytest.raises(ValueError, match="physics_oversample"):
    dataclasses.replace(gated, physics_variant="public", physics_oversample=2)
  before = repr(gated).replace(", physics_variant='refined'", "")
  assert "physics_variant" not in before
  assert compare_model(before, gated) == ([], ["setup.aperture", "physics_variant"])
  differ, _ = compare_model(before, public)
  assert len(differ) == 1 and differ[0].startswith("physics_variant: not recorded, 'public' now")


@pytest.mark.full
def test_model_config_physics_variant_reaches_the_layer():
  """The public layer takes the refined network's parameters and gives another output (three
  whole-network compiles: in the full tier)."""
  gated, public = _physics_variants()
  x = jnp.zeros(public.input_shape(1), jnp.float32).at[..., 20, :, :].set(1.0)
  params = jax.jit(gated.module().init)(jax.random.key(0), x)["params"]      # jit: eager takes a minute
  assert jax.tree.map(jnp.shape, jax.eval_shape(public.module().init, jax.random.key(0), x)["params"]) == \
      jax.tree.map(jnp.shape, params)                               # the same parameters
  a = jax.jit(gated.module().apply)({"params": params}, x)["volume"]
  b = jax.jit(public.module().apply)({"params": params}, x)["volume"]
  assert np.isfinite(np.asarray(b)).all() and not np.allclose(a, b, atol=1e-3)


def test_volume_stage_physics_channel_is_the_physics_of_the_pooled_transient():
  """Inside VolumeReconstruction (time stride 2, gated Setup) the physics channel is
  physics.phasor of the 2-bin-averaged transient on the coarse Setup."""
  setup = TINY.with_depth_range(0.08, 0.25)
  stage = VolumeReconstruction(setup, time_stride=2, features=1, refine_width=2)
  a, b = stage.window()
  x = point_scene(setup)
  xw = jnp.asarray(x[None, a:b])
  params = jax.jit(stage.init)(jax.random.key(16, impl="rbg"), xw)
  _, state = jax.jit(lambda p, v: stage.apply(p, v, capture_intermediates=True))(params, xw)
  got = state["intermediates"]["transform"]["__call__"][0][0, ..., 0]
  coarse = coarsen_setup(setup, 2)
  pooled = x.reshape(setup.num_bins // 2, 2, 8, 8).mean(axis=1)
  ref = np.asarray(physics.phasor(pooled, coarse, variant="refined", oversample=1))
  np.testing.assert_allclose(got, ref, atol=1e-5 * ref.max(), rtol=1e-4)


def test_softplus_volume_activation_keeps_gradients_where_relu_is_dead():
  """Lower the output conv's bias until most columns are negative: under the ReLU clamp the
  pixels they project to are 0 and pass the image loss no gradient (the dead columns seen in
  training); under softplus the same pixels still do."""
  setup = TINY.with_depth_range(0.08, 0.25)
  x, dead, grads = None, None, {}
  for act in ("relu", "softplus"):
    stage = VolumeReconstruction(setup, time_stride=2, features=1, refine_width=2, activation=act)
    a, b = stage.window()
    if x is None:
      x = jnp.asarray(point_scene(setup)[None, a:b])
    params = jax.jit(stage.init)(jax.random.key(3), x)
    params["params"]["refine"]["to_volume"]["bias"] = jnp.full((1,), -0.9)
    if dead is None:
      dead = jax.jit(stage.apply)(params, x)["intensity"] == 0
      assert 0.3 < float(dead.mean()) < 1.0

    def loss(p, dead=dead):
      return jnp.sum(jnp.where(dead, stage.apply(p, x)["intensity"], 0.0))

    g = jax.jit(jax.grad(loss))(params)
    grads[act] = max(float(jnp.max(jnp.abs(v))) for v in jax.tree_util.tree_leaves(g))
  assert grads["relu"] == 0.0 and grads["softplus"] > 1e-6, grads
  with pytest.raises(ValueError, match="volume_activation"):
    tiny_config(volume_activation="gelu")


def test_soft_projection_matches_the_hard_projection_when_peaked():
  setup = Setup(0.5, (8, 8), 64e-12, 32)
  rng = np.random.default_rng(0)
  vol = rng.uniform(0, 0.05, (32, 8, 8)).astype(np.float32)
  k = rng.integers(3, 29, (8, 8))
  vol[k, np.arange(8)[:, None], np.arange(8)[None, :]] = rng.uniform(0.5, 1.0, (8, 8))
  project = jax.jit(lambda v: soft_projection(v, setup.depths, temperature=0.01, softness=1e-3))
  inten, depth = project(jnp.asarray(vol))
  ref_i, ref_d = physics.intensity_depth(vol, setup)
  np.testing.assert_allclose(inten, ref_i, atol=1e-6)
  np.testing.assert_allclose(depth, ref_d, atol=0.05 * setup.depth_bin_length)
  # All-zero volume: finite values and finite gradients.
  g = jax.jit(jax.grad(lambda v: jnp.sum(sum(soft_projection(v, setup.depths)))))(
      jnp.zeros((32, 8, 8)))
  assert bool(jnp.all(jnp.isfinite(g)))


# --------------------------------------------------- whole network, numbers
@pytest.fixture(scope="module")
def tiny_net():
  cfg = tiny_config(frames=3)
  model = STMambaNet(cfg)
  x = counts(jax.random.key(20), cfg.input_shape(2))
  # rbg keys: the init compiles 2x faster than with threefry (any key works).
  variables = jax.jit(model.init)(jax.random.key(21, impl="rbg"), x)
  traces = []

  @jax.jit
  def forward(v, frames):
    traces.append(frames.shape)
    return model.apply(v, frames)

  return cfg, model, variables, x, forward, traces


def test_jit_compiles_once_per_shape_and_handles_any_photon_budget(tiny_net):
  cfg, _, variables, x, forward, traces = tiny_net
  out = forward(variables, x)
  n = len(traces)
  out_hi = forward(variables, 30.0 * x)           # 30x the photons: same shape, no retrace
  out_zero = forward(variables, jnp.zeros_like(x))
  assert len(traces) == n
  # Normalisation by the per-sample scale: 30x the counts gives the same reconstruction.
  for k in ("transient", "volume", "intensity", "depth"):
    np.testing.assert_allclose(out_hi[k], out[k], atol=1e-4, rtol=1e-4)
  np.testing.assert_allclose(out_hi["scale"], 30.0 * out["scale"], rtol=1e-5)
  for k, v in out_zero.items():
    assert bool(jnp.all(jnp.isfinite(v))), k
  assert float(jnp.max(jnp.abs(out_zero["transient"]))) < 1e-3 + float(
      jnp.max(jnp.abs(out["transient"])))
  assert 0.0 <= float(out["intensity"].min()) and float(out["intensity"].max()) <= 1.0
  assert float(out["volume"].min()) >= 0.0
  depths = cfg.setup.depths
  assert float(out["depth"].min()) >= 0.0 and float(out["depth"].max()) <= depths[-1] + 1e-6
  forward(variables, x[:1])                      # a new shape compiles once more
  assert len(traces) == n + 1


def test_gradients_finite_and_nonzero_for_every_parameter(tiny_net):
  cfg, model, variables, x, _, _ = tiny_net
  keys = ("transient", "volume", "intensity", "depth")
  weights = {k: jax.random.normal(jax.random.fold_in(jax.random.key(22), i),
                                  jax.eval_shape(model.apply, variables, x)[k].shape)
             for i, k in enumerate(keys)}

  @jax.jit
  def grads(params):
    def loss(p):
      out = model.apply({"params": p}, x)
      return sum(jnp.mean(weights[k] * out[k]) + jnp.mean(out[k] ** 2) for k in keys)
    return jax.grad(loss)(params)

  g = grads(variables["params"])
  flat = jax.tree_util.tree_flatten_with_path(g)[0]
  assert len(flat) == len(jax.tree.leaves(variables["params"]))
  for path, leaf in flat:
    name = jax.tree_util.keystr(path)
    leaf = np.asarray(leaf)
    assert np.all(np.isfinite(leaf)), name
    assert np.max(np.abs(leaf)) > 0.0, name


# ------------------------------------------------------------- bad input
@pytest.mark.parametrize("shape, match", [
    ((1, 1, 32, 4, 4), "1 frames"),
    ((1, 3, 16, 4, 4), "16 time bins"),
    ((1, 3, 32, 8, 8), r"scan grid \(8, 8\)"),
    ((3, 32, 4, 4), "rank 4"),
])
def test_bad_frames_raise_value_error_naming_the_mismatch(shape, match):
  model = STMambaNet(tiny_config(frames=3))
  with pytest.raises(ValueError, match=match):
    jax.eval_shape(model.init, jax.random.key(0), jax.ShapeDtypeStruct(shape, jnp.float32))


def test_negative_or_nan_counts_raise_before_compiling():
  cfg = tiny_config(frames=1)
  model = STMambaNet(cfg)
  bad = np.zeros(cfg.input_shape(1), np.float32)
  bad[0, 0, 3, 1, 1] = -1.0
  with pytest.raises(ValueError, match="negative"):
    model.init(jax.random.key(0), bad)
  bad[0, 0, 3, 1, 1] = np.nan
  with pytest.raises(ValueError, match="NaN"):
    model.init(jax.random.key(0), bad)


# --------------------------------------------------------------- summary
def test_model_summary_counts_params_without_allocating():
  cfg = tiny_config()
  s = model_summary(cfg)
  x = jax.ShapeDtypeStruct(cfg.input_shape(1), jnp.float32)
  params = jax.eval_shape(STMambaNet(cfg).init, jax.random.key(0), x)["params"]
  assert s["params"] == count_params(params) > 1000
  assert s["flops"] > s["xla_flops"] > 0 and s["fft_flops"] > 0
  assert s["output_shapes"]["transient"] == (1, 32, 8, 8)
  s1 = model_summary(cfg.replace(frames=1))
  assert s1["params"] < s["params"] and s1["flops"] < s["flops"]


def test_weighted_skip_is_the_softmax_mix_of_the_frames():
  """With the learned path of the spreading stage switched off, the recovered transient (in
  counts) is ``gain * interp(skip)``; so a "weighted" model fed frames ``x_f`` must give what
  a "middle" model with the same weights gives when fed three copies of ``sum_f w_f x_f``,
  ``w = softmax(logits)``. A wrong axis, a missing softmax or a skip that ignores the
  neighbours breaks the equality; the gradient must reach the logits."""
  cfg = tiny_config(skip_frames="weighted")
  x = counts(jax.random.key(0), cfg.input_shape(2), rate=2.0)
  model = STMambaNet(cfg)
  params = jax.jit(model.init)(jax.random.key(1), x)["params"]
  assert params["skip_frame_logits"].shape == (3,)
  params["skip_frame_logits"] = jnp.log(jnp.array([1.0, 2.0, 1.0]))   # w = (1/4, 1/2, 1/4)
  params["spread"]["to_transient"] = jax.tree_util.tree_map(jnp.zeros_like,
                                                            params["spread"]["to_transient"])

  def loss(logits):                     # the outputs and the logits' gradient from one compile
    o = model.apply({"params": {**params, "skip_frame_logits": logits}}, x)
    return jnp.sum(o["transient"] ** 2), o

  (_, out), grad = jax.jit(jax.value_and_grad(loss, has_aux=True))(params["skip_frame_logits"])
  mixed = 0.25 * x[:, 0] + 0.5 * x[:, 1] + 0.25 * x[:, 2]
  middle = STMambaNet(cfg.replace(skip_frames="middle"))
  p_mid = {k: v for k, v in params.items() if k != "skip_frame_logits"}
  ref = jax.jit(middle.apply)({"params": p_mid}, jnp.stack([mixed] * 3, axis=1))
  got = out["transient"] * out["scale"][:, None, None, None]
  want = ref["transient"] * ref["scale"][:, None, None, None]
  np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * float(jnp.max(want)))
  assert float(jnp.max(jnp.abs(grad))) > 0.0


def test_weighted_skip_of_one_frame_is_the_middle_frame():
  single = tiny_config(frames=1, skip_frames="weighted")
  x = counts(jax.random.key(2), single.input_shape(1))
  p_w = jax.eval_shape(STMambaNet(single).init, jax.random.key(3), x)["params"]
  p_m = jax.eval_shape(STMambaNet(single.replace(skip_frames="middle")).init, jax.random.key(3), x)["params"]
  assert jax.tree_util.tree_structure(p_w) == jax.tree_util.tree_structure(p_m)
  with pytest.raises(ValueError, match="skip_frames"):
    tiny_config(skip_frames="mean")

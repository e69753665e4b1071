"""The fast "direct" 3-D convolution (``Conv3D(impl="direct")``, ``ModelConfig.conv_impl="auto"``)
against its references: XLA's own 3-D convolution (values and both gradients) and, for the
whole network at the cpu preset's architecture, the all-"fold" path (loss and every gradient
on a fixed batch, equal to float32 rounding)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import configs
from nlosjax.models import ModelConfig, blocks, conv
from nlosjax.physics import Setup
from tests.conv_reference import loop_conv3d, same_conv3d
from tests.xla_options import xla_optimizations


@pytest.fixture(scope="module", autouse=True)
def _fast_compiles():
  with xla_optimizations(False):
    yield


def _grads(conv, params, x):
  def loss(p, xx):
    return jnp.sum(jnp.sin(conv.apply(p, xx)))
  return jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))(params, x)


@pytest.mark.parametrize("kernel, dilation, cin, feats, padding", [
    ((3, 3, 3), 1, 2, 2, "zero"), ((3, 3, 3), 2, 1, 2, "zero"), ((3, 3, 3), 4, 2, 1, "zero"),
    ((3, 1, 1), 2, 2, 2, "zero"), ((1, 3, 5), 1, 1, 1, "zero"), ((3, 3, 3), 1, 2, 2, "edge")])
def test_direct_conv_equals_xla_3d_conv_with_gradients(kernel, dilation, cin, feats, padding):
  x = jax.random.normal(jax.random.key(0), (2, 9, 5, 6, cin))
  direct = conv.Conv3D(feats, kernel, 1, dilation, impl="direct", padding=padding)
  params = direct.init(jax.random.key(1), x)
  params = jax.tree.map(lambda p: p + 0.1, params)                 # a nonzero bias too
  ref = conv.Conv3D(feats, kernel, 1, dilation, impl="xla", padding=padding)
  np.testing.assert_allclose(direct.apply(params, x), ref.apply(params, x), rtol=1e-5, atol=1e-5)
  if padding == "zero":   # and XLA's "SAME" (not the module's padding amounts)
    p = params["params"]
    np.testing.assert_allclose(direct.apply(params, x), same_conv3d(x, p["kernel"], p["bias"], 1, dilation),
                               rtol=1e-5, atol=1e-5)
  (v, (gp, gx)), (v_ref, (gp_ref, gx_ref)) = _grads(direct, params, x), _grads(ref, params, x)
  np.testing.assert_allclose(v, v_ref, rtol=1e-5)
  np.testing.assert_allclose(gx, gx_ref, rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(gx_ref))))
  for a, b in zip(jax.tree.leaves(gp), jax.tree.leaves(gp_ref)):
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(b))))


@pytest.mark.parametrize("shape, kernel, stride, dilation", [
    ((7, 3, 5), (3, 3, 3), 2, 1), ((8, 4, 3), (2, 1, 3), 3, 2), ((6, 5, 4), (3, 3, 1), 1, 2),
    ((5, 3, 3), (4, 3, 3), 1, 1)])
def test_every_impl_is_the_brute_force_same_convolution(shape, kernel, stride, dilation):
  """Every impl (and "auto") against the NumPy loop over output voxels and taps, at odd and even
  lengths, strides 1-3 and even time kernels (padding split unevenly)."""
  x = jax.random.normal(jax.random.key(6), (1,) + shape + (2,))
  impls = ("fold", "xla", "auto") + (("direct",) if stride == 1 else ())
  params = conv.Conv3D(3, kernel, stride, dilation).init(jax.random.key(7), x)
  params = jax.tree.map(lambda p: p + 0.1, params)
  p = params["params"]
  want = loop_conv3d(x, p["kernel"], p["bias"], stride, dilation)
  assert want.shape == (1, -(-shape[0] // stride)) + shape[1:] + (3,)
  np.testing.assert_allclose(same_conv3d(x, p["kernel"], p["bias"], stride, dilation), want,
                             rtol=1e-5, atol=1e-5)
  for impl in impls:
    got = conv.Conv3D(3, kernel, stride, dilation, impl=impl).apply(params, x)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5, err_msg=impl)


def test_auto_picks_direct_for_few_channels_only():
  assert conv.resolve_conv_impl("auto", (3, 3, 3), 2, 2, 1) == "direct"
  assert conv.resolve_conv_impl("auto", (3, 3, 3), 1, 2, 1) == "direct"
  assert conv.resolve_conv_impl("auto", (3, 3, 3), 4, 8, 1) == "fold"
  assert conv.resolve_conv_impl("auto", (3, 3, 3), 2, 2, 2) == "fold"      # strided
  assert conv.resolve_conv_impl("auto", (1, 1, 1), 1, 1, 1) == "fold"      # a matmul
  assert conv.resolve_conv_impl("xla", (3, 3, 3), 1, 1, 1) == "xla"
  with pytest.raises(ValueError, match="impl"):
    conv.resolve_conv_impl("im2col", (3, 3, 3), 1, 1, 1)
  with pytest.raises(ValueError, match="conv_impl"):
    ModelConfig.cpu(conv_impl="im2col")
  with pytest.raises(ValueError, match="unstrided"):
    conv.Conv3D(2, time_stride=2, impl="direct").init(jax.random.key(0), jnp.zeros((1, 4, 3, 3, 1)))


@pytest.mark.full
def test_fast_path_equals_the_fold_reference_at_the_cpu_preset():
  """The cpu preset's Ours (its widths, a small Setup): its volume stage, which holds every conv
  that "auto" runs "direct" at these widths, gives the same loss and gradients (parameters and
  input) as the all-"fold" reference on a fixed batch. (The whole network at the preset's own
  shapes: ``python -m benchmarks.model --configs cpu --batch 4 --reference``.)"""
  setup = Setup(wall_size=2.0, grid=(8, 8), bin_width=132e-12, num_bins=64)
  cfg = ModelConfig(setup=setup, stride=4, frames=3, **configs.get_config("cpu")["model"])
  assert cfg.conv_impl == "auto"
  assert conv.resolve_conv_impl("auto", (3, 3, 3), cfg.refine_width, cfg.refine_width, 1) == "direct"
  fast = blocks.VolumeReconstruction(**cfg.volume_kwargs())
  ref = blocks.VolumeReconstruction(**cfg.replace(conv_impl="fold").volume_kwargs())
  a, b = cfg.time_window
  x = jax.random.normal(jax.random.key(3), (2, b - a) + setup.grid)
  params = jax.jit(ref.init)(jax.random.key(4), x)["params"]

  def step(stage):
    def loss(p, xx):
      o = stage.apply({"params": p}, xx)
      return sum(jnp.mean(jnp.square(o[k])) for k in ("volume", "intensity", "depth"))
    return jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))(params, x)

  (v_ref, g_ref), (v, g) = step(ref), step(fast)
  np.testing.assert_allclose(v, v_ref, rtol=1e-5)
  assert jax.tree.structure(g) == jax.tree.structure(g_ref)
  for u, w in zip(jax.tree.leaves(g), jax.tree.leaves(g_ref)):
    np.testing.assert_allclose(u, w, rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(w))))
  assert float(jnp.max(jnp.abs(g[0]["refine"]["conv1"]["kernel"]))) > 0    # direct convs got gradients


@pytest.mark.parametrize("cin, feats, kh, kw", [(3, 1, 3, 3), (2, 2, 1, 3), (1, 3, 3, 3), (3, 1, 3, 4)])
def test_conv2d_kernel_grad_equals_a_loop_over_shifts(cin, feats, kh, kw):
  """Both orientations of ``conv2d_kernel_grad`` (the first two cases run the swapped one)
  against the defining sum, one shift at a time."""
  rng = np.random.default_rng(cin * 10 + feats)
  lhs = rng.normal(size=(5, 4 + kh, 4 + kw, cin)).astype(np.float32)     # a 5 x 5 output
  g = rng.normal(size=(5, 5, 5, feats)).astype(np.float32)
  want = np.zeros((kh, kw, cin, feats))
  for b in range(kh):
    for c in range(kw):
      want[b, c] = np.einsum("pyxi,pyxf->if", lhs[:, b:b + 5, c:c + 5].astype(np.float64), g)
  np.testing.assert_allclose(conv.conv2d_kernel_grad(jnp.asarray(lhs), jnp.asarray(g)), want,
                             rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("kernel, stride, dilation, cin, feats", [
    ((3, 3, 3), 1, 1, 3, 4), ((3, 3, 3), 2, 1, 4, 2), ((3, 1, 5), 1, 2, 2, 2), ((2, 3, 3), 1, 1, 1, 3)])
def test_time_folded_conv_gradients_equal_xla_3d_conv(kernel, stride, dilation, cin, feats):
  """"fold" (the 2-D convolution with its own kernel gradient) against XLA's 3-D convolution."""
  x = jax.random.normal(jax.random.key(2), (2, 9, 5, 6, cin))
  fold = conv.Conv3D(feats, kernel, stride, dilation, impl="fold")
  params = jax.tree.map(lambda p: p + 0.1, fold.init(jax.random.key(3), x))
  ref = conv.Conv3D(feats, kernel, stride, dilation, impl="xla")
  p = params["params"]
  np.testing.assert_allclose(fold.apply(params, x), same_conv3d(x, p["kernel"], p["bias"], stride, dilation),
                             rtol=1e-5, atol=1e-5)
  (v, (gp, gx)), (v_ref, (gp_ref, gx_ref)) = _grads(fold, params, x), _grads(ref, params, x)
  np.testing.assert_allclose(v, v_ref, rtol=1e-5)
  np.testing.assert_allclose(gx, gx_ref, rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(gx_ref))))
  for a, b in zip(jax.tree.leaves(gp), jax.tree.leaves(gp_ref)):
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(b))))


@pytest.mark.parametrize("shape, kernel, stride, cin, feats", [
    ((10, 8, 6), (3, 3, 3), 2, 1, 3), ((9, 7, 11), (3, 3, 3), 2, 2, 1), ((11, 9, 10), (3, 2, 4), 3, 1, 2)])
def test_strided_conv3d_equals_xla_strided_conv_with_gradients(shape, kernel, stride, cin, feats):
  """The polyphase form (USM's extraction) against ``lax.conv_general_dilated`` with a stride."""
  x = jax.random.normal(jax.random.key(4), (2,) + shape + (cin,))
  k = jax.random.normal(jax.random.key(5), kernel + (cin, feats))

  def xla(x, k):
    return jax.lax.conv_general_dilated(x, k, (stride,) * 3, "VALID",
                                        dimension_numbers=("NDHWC", "DHWIO", "NDHWC"))

  def loss(fn):
    return jax.jit(jax.value_and_grad(lambda x, k: jnp.sum(jnp.sin(fn(x, k))), argnums=(0, 1)))

  y, y_ref = conv.strided_conv3d(x, k, stride), xla(x, k)
  assert y.shape == y_ref.shape
  np.testing.assert_allclose(y, y_ref, rtol=1e-5, atol=1e-5)
  (v, (gx, gk)), (v_ref, (gx_ref, gk_ref)) = loss(lambda a, b: conv.strided_conv3d(a, b, stride))(x, k), \
      loss(xla)(x, k)
  np.testing.assert_allclose(v, v_ref, rtol=1e-5)
  np.testing.assert_allclose(gx, gx_ref, rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(gx_ref))))
  np.testing.assert_allclose(gk, gk_ref, rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(gk_ref))))
  with pytest.raises(ValueError, match="smaller than the kernel"):
    conv.strided_conv3d(x[:, :2], k, stride)

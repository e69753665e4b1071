"""The accelerator paths (:mod:`nlosjax.platforms`): each equal to its CPU path, and chosen by the lowering platform.

On this CPU machine every branch is called directly and compared with the CPU branch and a
slow reference; programs are lowered (not compiled) for CUDA to read which branch they hold.
The train step's own check, lowered for CUDA, is ``test_train_step_lowered_for_cuda``.
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.fft

from benchmarks import hlo_gpu as H
from nlosjax import platforms
from nlosjax.models import conv as C
from nlosjax.models import physics_layer as PL
from nlosjax.physics import Setup
from nlosjax.physics import wavelet as W

#: Largest prime factor an FFT length may have on the accelerator path.
LARGEST_RADIX = 7


def _lowered(fn, *args, platform: str) -> H.HloModule:
  return H.parse_hlo(jax.jit(fn).trace(*args).lower(lowering_platforms=(platform,)).as_text(dialect="hlo"))


def _ops(module: H.HloModule, opcode: str) -> list:
  return [i for c in module.computations.values() for i in c if i.opcode == opcode]


# --------------------------------------------------------------------- the switch
def test_switch_follows_the_lowering_platform_not_the_process():
  fn = lambda x: platforms.by_platform(x, cpu=jnp.sin, other=jnp.cos)          # noqa: E731
  x = jax.ShapeDtypeStruct((3,), jnp.float32)
  for platform, kept, dropped in (("cpu", "sine", "cosine"), ("cuda", "cosine", "sine")):
    m = _lowered(fn, x, platform=platform)
    assert _ops(m, kept) and not _ops(m, dropped), platform
    assert not _ops(m, "conditional")                    # one platform: its branch alone, no switch left
  assert jax.default_backend() == "cpu"
  np.testing.assert_array_equal(jax.jit(fn)(jnp.ones(3)), jnp.sin(jnp.ones(3)))



def test_override_forces_a_path_whatever_the_lowering_platform():
  """Inside ``cpu_paths()`` a program lowered for CUDA holds the CPU branch; inside ``accelerator_paths()``
  one lowered for the CPU holds the other; outside, the platform chooses again (the same ``jit`` object)."""
  jitted = jax.jit(lambda x: platforms.by_platform(x, cpu=jnp.sin, other=jnp.cos))
  x = jax.ShapeDtypeStruct((3,), jnp.float32)

  def holds(platform):
    m = H.parse_hlo(jitted.trace(x).lower(lowering_platforms=(platform,)).as_text(dialect="hlo"))
    return {op for op in ("sine", "cosine", "conditional") if _ops(m, op)}
  assert platforms.forced() is None
  assert holds("cuda") == {"cosine"} and holds("cpu") == {"sine"}
  with platforms.cpu_paths():
    assert platforms.forced() == platforms.CPU
    assert holds("cuda") == {"sine"} and holds("cpu") == {"sine"}
    with platforms.accelerator_paths():                  # nested: the innermost wins
      assert holds("cpu") == {"cosine"}
    assert holds("cuda") == {"sine"}
    np.testing.assert_array_equal(jitted(jnp.ones(3)), jnp.sin(jnp.ones(3)))
  assert platforms.forced() is None
  assert holds("cuda") == {"cosine"}                    # traced again: no override left in the cache
  with platforms.accelerator_paths():
    np.testing.assert_array_equal(jitted(jnp.ones(3)), jnp.cos(jnp.ones(3)))   # run here, on the CPU
  np.testing.assert_array_equal(jitted(jnp.ones(3)), jnp.sin(jnp.ones(3)))


def test_override_reaches_nested_jit_traced_before_it():
  """An inner ``jit`` function already traced without the override is traced again inside it."""
  inner = jax.jit(lambda x: platforms.by_platform(x, cpu=jnp.sin, other=jnp.cos))
  outer = lambda x: inner(x) * 2                                                  # noqa: E731
  x = jax.ShapeDtypeStruct((3,), jnp.float32)
  assert _ops(_lowered(outer, x, platform="cuda"), "cosine")
  with platforms.cpu_paths():
    m = _lowered(outer, x, platform="cuda")
  assert _ops(m, "sine") and not _ops(m, "cosine")


def test_override_holds_for_its_own_thread_only():
  """A thread inside ``cpu_paths()`` does not change what another thread traces meanwhile."""
  import threading
  fn = lambda x: platforms.by_platform(x, cpu=jnp.sin, other=jnp.cos)           # noqa: E731
  x = jax.ShapeDtypeStruct((3,), jnp.float32)
  entered, done, seen = threading.Event(), threading.Event(), {}

  def worker():
    with platforms.cpu_paths():
      entered.set()
      done.wait(60)
      seen["worker"] = bool(_ops(_lowered(fn, x, platform="cuda"), "sine"))
  t = threading.Thread(target=worker)
  t.start()
  assert entered.wait(60)
  seen["main"] = bool(_ops(_lowered(fn, x, platform="cuda"), "sine"))          # the worker is inside it now
  done.set()
  t.join(60)
  assert seen == {"worker": True, "main": False}


def test_override_holds_the_cpu_constructs_lowered_for_cuda():
  """The real switches under ``cpu_paths()``, lowered for CUDA: the swapped weight-gradient layout,
  the depth resampling's gather and scatter; without it, the accelerator constructs."""
  lhs, g = jax.ShapeDtypeStruct((2, 10, 10, 4), jnp.float32), jax.ShapeDtypeStruct((2, 8, 8, 3), jnp.float32)
  source, target = _depth_pair()
  vol = jax.ShapeDtypeStruct((2, source.depths.size, 4, 4), jnp.float32)

  def resample_grad(v):
    return jax.grad(lambda u: (PL.resample_depth(u, source, target) ** 2).sum())(v)

  def constructs():
    m = _lowered(C.conv2d_kernel_grad, lhs, g, platform="cuda")
    (conv,) = _ops(m, "convolution")
    r = _lowered(resample_grad, vol, platform="cuda")
    return H.swapped_weight_grad(m, conv), bool(_ops(r, "gather") and _ops(r, "scatter"))
  assert constructs() == (False, False)
  with platforms.cpu_paths():
    assert constructs() == (True, True)
  assert constructs() == (False, False)


# -------------------------------------------------------------- weight gradients
def _kernel_grad_brute(lhs: np.ndarray, g: np.ndarray) -> np.ndarray:
  """``dk[b, c, i, f] = sum_{p, y, x} lhs[p, y + b, x + c, i] g[p, y, x, f]`` in float64 loops over taps."""
  _, h, w, _ = g.shape
  kh, kw = lhs.shape[1] - h + 1, lhs.shape[2] - w + 1
  out = np.zeros((kh, kw, lhs.shape[-1], g.shape[-1]))
  for b, c in itertools.product(range(kh), range(kw)):
    out[b, c] = np.einsum("pyxi,pyxf->if", lhs[:, b:b + h, c:c + w].astype(np.float64), g.astype(np.float64))
  return out


def _kernel_grad_vjp(lhs, g):
  """The plain ``jax.vjp`` of ``lax.conv_general_dilated`` (VALID, NHWC / HWIO) with respect to its kernel."""
  kh, kw = lhs.shape[1] - g.shape[1] + 1, lhs.shape[2] - g.shape[2] + 1
  conv = lambda k: jax.lax.conv_general_dilated(lhs, k, (1, 1), "VALID",                 # noqa: E731
                                                dimension_numbers=("NHWC", "HWIO", "NHWC"))
  return jax.vjp(conv, jnp.zeros((kh, kw, lhs.shape[-1], g.shape[-1]), lhs.dtype))[1](g)[0]


# (P, H, W, kernel, C, F): the swapped layout's cases (3 x 3 and 1 x 3, F <= C) and the others (F > C, 5 x 5)
KERNEL_CASES = [(3, 6, 5, (3, 3), 6, 2), (2, 4, 7, (1, 3), 4, 4), (2, 5, 5, (3, 3), 2, 6), (2, 6, 6, (5, 5), 3, 2)]


@pytest.mark.parametrize("case", KERNEL_CASES, ids=lambda c: f"{c[3][0]}x{c[3][1]}-C{c[4]}-F{c[5]}")
def test_kernel_gradient_branches_agree(case):
  p, h, w, (kh, kw), cin, feats = case
  rng = np.random.default_rng(0)
  lhs = rng.standard_normal((p, h + kh - 1, w + kw - 1, cin)).astype(np.float32)
  g = rng.standard_normal((p, h, w, feats)).astype(np.float32)
  brute = _kernel_grad_brute(lhs, g)
  scale = np.abs(brute).max()
  cpu = np.asarray(jax.jit(C.conv2d_kernel_grad_cpu)(lhs, g))
  xla = np.asarray(jax.jit(C.conv2d_kernel_grad_xla)(lhs, g))
  vjp = np.asarray(jax.jit(_kernel_grad_vjp)(lhs, g))
  for name, got in (("cpu", cpu), ("xla", xla), ("vjp", vjp)):
    assert got.shape == brute.shape, name
    np.testing.assert_allclose(got, brute, atol=2e-6 * scale, rtol=0, err_msg=name)
  np.testing.assert_allclose(xla, cpu, atol=2e-6 * scale, rtol=0)
  # The switch itself, run here: the CPU branch, bit for bit.
  np.testing.assert_array_equal(np.asarray(jax.jit(C.conv2d_kernel_grad)(lhs, g)), cpu)


def test_kernel_gradient_layout_by_lowering_platform():
  lhs, g = jax.ShapeDtypeStruct((2, 10, 10, 4), jnp.float32), jax.ShapeDtypeStruct((2, 8, 8, 3), jnp.float32)
  for platform, swapped in (("cpu", True), ("cuda", False)):
    m = _lowered(C.conv2d_kernel_grad, lhs, g, platform=platform)
    (conv,) = _ops(m, "convolution")
    assert H.conv_facts(m, conv)["weight_grad"]
    assert H.swapped_weight_grad(m, conv) == swapped, platform


# ------------------------------------------------------------ depth resampling
def _depth_pair() -> tuple[Setup, Setup]:
  fine = Setup(wall_size=1.0, grid=(4, 4), bin_width=32e-12, num_bins=40)
  return PL.coarsen_setup(fine, 3), fine


def test_resample_depth_branches_agree():
  source, target = _depth_pair()
  assert source.depths.size != target.depths.size
  rng = np.random.default_rng(1)
  vol = rng.standard_normal((2, source.depths.size, 4, 4)).astype(np.float32)
  # Slow reference: numpy's interpolation per column (the nearest end value outside the grid).
  ref = np.zeros((2, target.depths.size, 4, 4))
  for b, y, x in itertools.product(range(2), range(4), range(4)):
    ref[b, :, y, x] = np.interp(target.depths, source.depths, vol[b, :, y, x].astype(np.float64))
  gather = jax.jit(lambda v: PL.resample_depth_gather(v, source, target))
  dense = jax.jit(lambda v: PL.resample_depth_dense(v, source, target))
  np.testing.assert_allclose(gather(vol), ref, atol=1e-5, rtol=0)
  np.testing.assert_allclose(dense(vol), ref, atol=1e-5, rtol=0)
  np.testing.assert_allclose(dense(vol), gather(vol), atol=1e-6, rtol=0)
  np.testing.assert_array_equal(jax.jit(lambda v: PL.resample_depth(v, source, target))(vol), gather(vol))
  cot = rng.standard_normal((2, target.depths.size, 4, 4)).astype(np.float32)
  grads = [jax.jit(jax.vjp(f, vol)[1])(cot)[0] for f in (gather, dense)]
  np.testing.assert_allclose(grads[1], grads[0], atol=1e-5, rtol=0)
  m = PL.interpolation_matrix(source, target)
  np.testing.assert_allclose(m.sum(axis=1), 1.0)
  assert ((m != 0).sum(axis=1) <= 2).all()


def test_resample_depth_off_cpu_has_no_gather_or_scatter():
  source, target = _depth_pair()
  vol = jax.ShapeDtypeStruct((2, source.depths.size, 4, 4), jnp.float32)

  def loss_grad(v):
    return jax.grad(lambda u: (PL.resample_depth(u, source, target) ** 2).sum())(v)
  cpu, cuda = (_lowered(loss_grad, vol, platform=p) for p in ("cpu", "cuda"))
  assert _ops(cpu, "gather") and _ops(cpu, "scatter")
  assert not _ops(cuda, "gather") and not _ops(cuda, "scatter")
  assert _ops(cuda, "dot")


# -------------------------------------------------------------------------- FFTs
def _prime_factors(n: int) -> set[int]:
  out, p = set(), 2
  while n > 1:
    while n % p == 0:
      out.add(p)
      n //= p
    p += 1
  return out


def test_next_smooth_length():
  for n in range(1, 600):
    m = W.next_smooth_length(n)
    assert m >= n and max(_prime_factors(m) | {1}) <= LARGEST_RADIX
    assert all(max(_prime_factors(k) | {1}) > LARGEST_RADIX for k in range(n, m))
  assert W.next_smooth_length(271) == 280 and scipy.fft.next_fast_len(271) == 275


def _wavelet(num_samples: int) -> W.Wavelet:
  return W.Wavelet(wavelength=0.05, omega=2 * np.pi * 3e8 / 0.05, sigma=2e-11, bin_width=1e-11,
                   num_samples=num_samples)


@pytest.mark.parametrize("n,taps", [(256, 16), (128, 37)])
def test_convolve_time_lengths_agree(n, taps):
  wav = _wavelet(taps)
  cpu, other = W.convolution_fft_lengths(n, taps)
  assert cpu != other and 11 in _prime_factors(cpu) and max(_prime_factors(other)) <= LARGEST_RADIX
  assert other >= n + taps - 1                         # a linear convolution: no wrap-around
  x = np.random.default_rng(2).standard_normal((3, n, 2)).astype(np.float32)
  # Slow reference: the direct sum y[t] = sum_k P_k x[t - k + L // 2], in complex128.
  full = np.apply_along_axis(lambda col: np.convolve(col, wav.samples), 1, x.astype(np.float64))
  ref = full[:, taps // 2:taps // 2 + n]
  scale = np.abs(ref).max()
  got_cpu = np.asarray(jax.jit(lambda v: W.convolve_time_at(v, wav, cpu, axis=1))(x))
  got_other = np.asarray(jax.jit(lambda v: W.convolve_time_at(v, wav, other, axis=1))(x))
  np.testing.assert_allclose(got_cpu, ref, atol=2e-6 * scale, rtol=0)
  np.testing.assert_allclose(got_other, ref, atol=2e-6 * scale, rtol=0)
  np.testing.assert_allclose(got_other, got_cpu, atol=2e-6 * scale, rtol=0)
  np.testing.assert_array_equal(jax.jit(lambda v: W.convolve_time(v, wav, axis=1))(x), got_cpu)
  with pytest.raises(ValueError, match="wrap around"):
    W.convolve_time_at(x, wav, n + taps - 2, axis=1)


def _physics_case():
  """A FeatureTransform (phasor, one channel at a time) whose wavelet convolution CPU runs at length 11 x 5^2."""
  setup = Setup(wall_size=1.0, grid=(4, 4), bin_width=32e-12, num_bins=256)
  layer = PL.FeatureTransform(setup, "phasor", chunk=1, cycles=4.0)
  a, b = layer.window()
  wav = W.illumination_wavelet(setup, cycles=4.0)
  cpu, other = W.convolution_fft_lengths(b - a, wav.num_samples)
  return layer, (b - a), cpu, other


def _accelerator_paths(monkeypatch) -> list[str]:
  """Make every switch of :mod:`nlosjax.platforms` take its accelerator branch, run here on the CPU.

  Returns the list the switches taken append their CPU branch's ``__qualname__`` to.
  """
  taken = []

  def other_branch(*args, cpu, other):
    taken.append(cpu.__qualname__)
    return other(*args)
  monkeypatch.setattr(platforms, "by_platform", other_branch)
  return taken


def _physics_value_and_grad(layer, x, a):
  def loss(v):
    return (layer.apply({}, v, a) ** 2).sum()
  return jax.jit(jax.value_and_grad(loss))(x), np.asarray(jax.jit(lambda v: layer.apply({}, v, a))(x))


@pytest.mark.parametrize("chunk", [1, None])
def test_physics_layer_accelerator_path_equals_cpu_path(chunk, monkeypatch):
  layer, nt, _, _ = _physics_case()
  layer = layer.clone(chunk=chunk)
  a = layer.window()[0]
  x = np.random.default_rng(3).standard_normal((2, nt, 4, 4, 3)).astype(np.float32)
  (loss_cpu, grad_cpu), out_cpu = _physics_value_and_grad(layer, x, a)
  _accelerator_paths(monkeypatch)
  (loss_acc, grad_acc), out_acc = _physics_value_and_grad(layer, x, a)
  np.testing.assert_allclose(out_acc, out_cpu, atol=1e-5 * np.abs(out_cpu).max(), rtol=0)
  np.testing.assert_allclose(loss_acc, loss_cpu, rtol=1e-5)
  np.testing.assert_allclose(grad_acc, grad_cpu, atol=1e-5 * np.abs(grad_cpu).max(), rtol=0)


def test_physics_layer_lowered_for_cuda_is_batched_at_smooth_lengths():
  layer, nt, _, _ = _physics_case()
  a = layer.window()[0]
  x = jax.ShapeDtypeStruct((2, nt, 4, 4, 3), jnp.float32)

  def loss_grad(v):
    return jax.grad(lambda u: layer.apply({}, u, a).sum())(v)
  for platform in ("cpu", "cuda"):
    text = jax.jit(loss_grad).trace(x).lower(lowering_platforms=(platform,)).as_text(dialect="hlo", debug_info=True)
    ffts = H.census(text, model="none")["ffts"]
    lengths = {int(v) for f in ffts for v in f["length"].split(",")}
    in_loop = [f for f in ffts if f["in_loop"]]
    if platform == "cpu":                    # the CPU program: one slice a trip, a length with factor 11
      assert in_loop and any(11 in _prime_factors(n) for n in lengths)
    else:
      assert ffts and not in_loop, ffts
      assert max(max(_prime_factors(n)) for n in lengths) <= LARGEST_RADIX, lengths


# ------------------------------------------------------------ the train step itself
def _step_lowered_for_cuda(preset: str) -> tuple[H.HloModule, dict]:
  """The preset's train step (Ours, its batch) as ``benchmarks.hlo_gpu`` lowers it for CUDA: parsed HLO, census."""
  from experiments.cli import load_config
  from nlosjax.ssm import resolve_method
  from nlosjax.variants import OURS
  config = load_config(preset)
  info = H.lower_step(config, OURS, int(config["train"]["batch_size"]),
                      scan_method=resolve_method("auto", backend="gpu"))
  assert info["lowered_for"] == "cuda", info["note"]
  return H.parse_hlo(info["hlo"]), H.census(info["hlo"], model=info["model"])


@pytest.mark.full
@pytest.mark.parametrize("preset", ["cpu", "paper"])
def test_train_step_lowered_for_cuda(preset):
  """What the accelerator paths promise, read from the step lowered for CUDA (no CUDA plugin needed).

  No weight gradient in the swapped layout (each one XLA's own, which XLA:GPU runs as a cuDNN
  backward-filter convolution), no gather or scatter from the depth resampling, every FFT at a
  length whose prime factors are at most 7 and none inside a loop. The ``paper`` step is the one
  whose FFTs the CPU path runs one channel at a time at lengths with a factor 11.
  """
  m, c = _step_lowered_for_cuda(preset)
  g = H.call_graph(m)
  convs = [i for comp, instrs in m.computations.items() if g.runs.get(comp, 0) or comp == m.entry
           for i in instrs if i.opcode == "convolution"]
  weight_grads = [i for i in convs if H.conv_facts(m, i)["weight_grad"]]
  assert weight_grads                                   # the check below has something to read
  swapped = [H.conv_facts(m, i) for i in weight_grads if H.swapped_weight_grad(m, i)]
  assert not swapped, [(f["lhs"], f["rhs"], f["out"], f["dim_labels"]) for f in swapped]
  resampling = [r for r in c["gather_scatter"] if "physics_layer.py:resample_depth" in r["source"]]
  assert not resampling, resampling
  assert c["ffts"]
  lengths = {int(v) for f in c["ffts"] for v in f["length"].split(",")}
  assert max(max(_prime_factors(n)) for n in lengths) <= LARGEST_RADIX, sorted(lengths)
  looped = [(f["type"], f["length"], f["source"]) for f in c["ffts"] if f["in_loop"]]
  assert not looped, looped


def test_tiny_network_gradients_equal_on_both_paths(monkeypatch):
  """A tiny STMambaNet (the physics layer one channel at a time, its volume resampled in depth):
  loss and parameter gradients with every switch on its accelerator branch equal the CPU path's."""
  from nlosjax.models import ModelConfig, STMambaNet
  setup = Setup(wall_size=0.5, grid=(8, 8), bin_width=64e-12, num_bins=32)
  cfg = ModelConfig.cpu(setup, stride=2, width=8, d_state=4, extract_time_stride=2, extract_blocks=1,
                        st_depth=1, cross_depth=1, volume_time_stride=2, volume_features=2, refine_width=4,
                        spread_min_width=2, frames=1, physics_chunk=1)
  model = STMambaNet(cfg)
  x = jax.random.poisson(jax.random.key(0), 0.5, cfg.input_shape(2)).astype(jnp.float32)
  variables = jax.jit(model.init)(jax.random.key(1, impl="rbg"), x)

  def loss(params):
    out = model.apply({**variables, "params": params}, x)
    return sum(jnp.mean(jnp.square(leaf)) for leaf in jax.tree.leaves(out))

  def run():
    return jax.jit(jax.value_and_grad(loss))(variables["params"])
  loss_cpu, grad_cpu = run()
  taken = _accelerator_paths(monkeypatch)
  loss_acc, grad_acc = run()
  switches = {name.split(".")[0] for name in taken}
  assert {"conv2d_kernel_grad_cpu", "resample_depth", "FeatureTransform"} <= switches, switches
  np.testing.assert_allclose(loss_acc, loss_cpu, rtol=1e-5)
  for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(grad_acc), jax.tree.leaves(grad_cpu)):
    scale = max(float(np.abs(b).max()), 1e-12)
    np.testing.assert_allclose(a, b, atol=2e-5 * scale, rtol=0, err_msg=jax.tree_util.keystr(path))

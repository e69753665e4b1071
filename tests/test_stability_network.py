"""Stability of the network, its losses and its training step at the extremes.

* zero-photon and saturated frames: the network normalises its input, so a 1e9x
  frame reconstructs as the frame itself and a 1e9x training batch has the same loss;
* scan grids: a 16 x 16 grid (4 x 4 input) and the smallest input, one scan
  point (4 x 4 output, stride 4, the same weights); the paper-shaped network
  (16 x 16 x 512 in, 128 x 128 out) is too slow for CI and is measured by
  ``python -m benchmarks.model --configs paper``;
* depth ranges: one bin and the full range;
* sequences: a 64-frame video reconstructed frame by frame through the
  ``TripletLoader`` sliding window (``ends="replicate"``: 64 triplets, the
  first ``(0, 0, 1)``), each frame's output independent of what it is batched
  with; a 1-frame video: the triplet loader refuses it with ``ends="valid"``,
  replicates it into ``(0, 0, 0)`` otherwise, and both Ours (F = 3) and
  Ours-S (F = 1) reconstruct it;
* bfloat16: the network end to end against float32 with the same parameters;
* ``dt`` and ``A`` at 1e-8..1e4 and -1e-6..-1e4 in every Mamba mixer of the
  initialised network: finite outputs, float32 within 1e-4 of a float64 run,
  a finite training step (of Ours-S);
* every loss at zero error: the guard value, exactly zero and finite gradients
  (each term alone, float32 and bfloat16), finite second derivatives; through
  the network, a training step (of Ours-S) on an empty scene (every term at zero
  error but depth) has exactly zero gradients.

Covered elsewhere: the selective scan alone at extreme ``dt``/``A`` against
float64 and at 16384 steps, and the mixer in bfloat16 (``test_ssm``); 30x photon
budgets through the network (``test_models``).
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import configs
from nlosjax import losses, physics, train
from nlosjax.data import dataset as D
from nlosjax.models import ModelConfig, STMambaNet
from nlosjax.physics import Setup, render_points
from tests.stability import (
  fast_compiles,  # noqa: F401 (the module's fixture, by name below)
  rel_dev,
)

pytestmark = pytest.mark.usefixtures("fast_compiles")


# ======================================================================= losses
LOSS_SETUP = Setup(0.8, (6, 6), 32e-12, 48)


def _zero_error_terms(wavelet: physics.Wavelet):
  """``f(tr, img, const, directions) -> {term: (value, grad, hvp)}`` at zero error, jitted."""
  def terms(tr, img, const):
    return {
        "transient": (lambda p: losses.transient_loss(p, tr), tr),
        "phasor_field": (lambda p: losses.phasor_field_loss(p, tr, wavelet), tr),
        "intensity": (lambda p: losses.intensity_loss(p, img), img),
        "depth": (lambda p: losses.depth_loss(p, img), img),
        "local_similarity": (losses.local_similarity_loss, const),
        "tv": (losses.tv_loss, const),
    }

  @jax.jit
  def run(tr, img, const, directions):
    out = {}
    for name, (fn, at) in terms(tr, img, const).items():
      value, grad = jax.value_and_grad(fn)(at)
      hvp = jax.jvp(jax.grad(fn), (at,), (directions[name],))[1]
      out[name] = (value, grad, hvp)
    model_out = {"transient": tr, "volume": const, "intensity": img, "depth": img}
    target = {"transient": tr, "intensity": img, "depth": img}
    out["total"] = jax.value_and_grad(
        lambda o: losses.total_loss(o, target, losses.LossWeights(), wavelet)[0])(model_out)
    return out

  return run


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.bfloat16])
def test_every_loss_term_at_zero_error_has_finite_zero_gradients(dtype):
  """Each term alone, and their total, where prediction == target: the value is the
  ``sqrt(eps) = 1e-6`` guard (TV exactly 0), gradients are exactly zero (constant volumes for the
  regularisers), and second derivatives (a Hessian-vector product) are finite."""
  rng = np.random.default_rng(3)
  tr = jnp.asarray(rng.uniform(size=(2, 48, 6, 6)), dtype)
  img = jnp.asarray(rng.uniform(size=(2, 6, 6)), dtype)
  const = jnp.full((2, 48, 6, 6), 0.7, dtype)
  shapes = {"transient": tr, "phasor_field": tr, "intensity": img, "depth": img,
            "local_similarity": const, "tv": const}
  directions = {k: jnp.asarray(rng.normal(size=v.shape), dtype) for k, v in shapes.items()}
  results = _zero_error_terms(physics.illumination_wavelet(LOSS_SETUP))(tr, img, const, directions)
  for name in shapes:
    value, grad, hvp = results[name]
    assert grad.dtype == dtype, name
    g = np.asarray(grad, np.float32)
    assert np.all(np.isfinite(g)), name
    if name == "tv":
      assert float(value) == 0.0 and np.all(g == 0), name
    elif name == "local_similarity":
      # The blur of a constant is that constant up to the taps' float32 rounding.
      assert float(value) == pytest.approx(1e-6, rel=0.05) and np.max(np.abs(g)) < 1e-6, name
    else:
      assert float(value) == pytest.approx(1e-6, rel=1e-3) and np.all(g == 0), name
    assert np.all(np.isfinite(np.asarray(hvp, np.float32))), name
  # The total with the paper's weights, every output at zero error.
  _, grads = results["total"]
  for name, g in grads.items():
    g = np.asarray(g, np.float32)
    assert np.all(np.isfinite(g)) and np.max(np.abs(g)) < 1e-6, name


# ====================================================================== network
# 16 x 16 scan of a 2 m wall, 64 bins of 264 ps (2.53 m of depth), stride 4 -> 4 x 4 input:
# the dataset generator's geometry (objects at 0.5-1.5 m), so the video test reads real frames.
NET = Setup(2.0, (16, 16), 264e-12, 64)
NET_KW = dict(stride=4, width=8, d_state=4, extract_time_stride=2, extract_blocks=1, st_depth=1,
              cross_depth=1, volume_time_stride=2, volume_features=2, refine_width=4,
              spread_min_width=2, dilations=(1,))


def _scene(setup: Setup, frames: int, shift: float = 0.05) -> tuple[np.ndarray, float]:
  """Noise-free full-grid transients ``[F, T, H, W]`` of a point moving along x, and its depth."""
  z = 1.0
  xs = [(np.array([[-0.2 + shift * f, 0.1, z]])) for f in range(frames)]
  clean = np.stack([render_points(p, 1.0, setup) for p in xs]).astype(np.float32)
  return clean / clean.max(), z


def _frames(setup: Setup, stride: int) -> np.ndarray:
  """``[4, 3, T, h, w]`` rows: Poisson counts of the scene, the same x 1e9 (saturated), zeros
  (zero-photon), and 65535 in every bin (a saturated detector)."""
  clean, _ = _scene(setup, 3)
  o = stride // 2
  lam = 0.2 + 30.0 * clean[:, :, o::stride, o::stride]
  counts = np.random.default_rng(5).poisson(lam).astype(np.float32)
  return np.stack([counts, counts * np.float32(1e9), np.zeros_like(counts),
                   np.full_like(counts, 65535.0)])


@pytest.fixture(scope="module")
def net():
  """``(config, params, apply)``: the initialised Ours (F = 3) and its jitted float32 apply."""
  cfg = ModelConfig.cpu(NET, **NET_KW)
  model = STMambaNet(cfg)
  # unsafe_rbg keys: the init compiles in 6 s instead of 9 s (rbg) or more (threefry).
  params = jax.jit(model.init)(jax.random.key(0, impl="unsafe_rbg"),
                               jnp.zeros(cfg.input_shape(1)))
  return cfg, params["params"], jax.jit(lambda p, x: model.apply({"params": p}, x))


@pytest.fixture(scope="module")
def net_out(net):
  cfg, params, apply = net
  x = _frames(NET, cfg.stride)
  return x, apply(params, x)


def _ours_s(cfg: ModelConfig, params: dict) -> tuple[ModelConfig, dict]:
  """Ours-S (F = 1): the same weights without the cross ST-Mamba blocks."""
  params_s = {k: v for k, v in params.items() if not k.startswith("cross_")}
  assert len(params_s) < len(params)
  return cfg.replace(frames=1), params_s


def _check_outputs(out: dict, cfg: ModelConfig, rows=range(4)) -> None:
  """Float32, finite (in ``rows``), intensity in [0, 1], depth in the depth grid, volume >= 0."""
  setup = cfg.setup
  for k in ("transient", "volume", "intensity", "depth", "scale"):
    assert out[k].dtype == jnp.float32, k
    assert np.all(np.isfinite(np.asarray(out[k])[list(rows)])), k
  inten, depth = np.asarray(out["intensity"]), np.asarray(out["depth"])
  assert inten.min() >= 0 and inten.max() <= 1
  assert depth.min() >= 0 and depth.max() <= setup.depths[-1] + 1e-5
  assert np.asarray(out["volume"]).min() >= 0


def _same_reconstruction(out: dict, a: int, b: int, tol: float) -> None:
  """Rows ``a`` and ``b`` of every image-like output agree within ``tol`` of ``b``'s peak."""
  for k in ("transient", "volume", "intensity", "depth"):
    assert rel_dev(out[k][a], out[k][b]) < tol, (k, rel_dev(out[k][a], out[k][b]))


@pytest.mark.full
def test_network_zero_photon_and_saturated_frames(net, net_out):
  cfg, _, _ = net
  x, out = net_out
  _check_outputs(out, cfg)
  # The input is divided by its RMS: 1e9x the counts is the same reconstruction, in 1e9x the units.
  _same_reconstruction(out, 1, 0, 1e-5)
  np.testing.assert_allclose(out["scale"][1], 1e9 * out["scale"][0], rtol=1e-6)
  # Zero photons: the scale guard is 1 and nothing is NaN.
  assert float(out["scale"][2]) == 1.0
  # A detector saturated in every bin: a constant input, a constant 65535 scale.
  assert float(out["scale"][3]) == 65535.0


@pytest.mark.full
def test_network_bfloat16_end_to_end_stays_close_to_float32(net, net_out):
  cfg, params, _ = net
  x, out = net_out
  model = STMambaNet(cfg.replace(dtype="bfloat16"))
  bf = jax.jit(lambda p, v: model.apply({"params": p}, v))(params, x)
  _check_outputs(bf, cfg)
  # Same parameters, activations in bfloat16 (8-bit mantissa, eps 7.8e-3): each output within a
  # few eps of float32 (measured: at most 0.58 % RMS and 1.05 % of the peak; zeros stay zeros).
  for k in ("transient", "volume", "intensity", "depth"):
    for row in range(4):
      a, b = np.asarray(bf[k][row], np.float64), np.asarray(out[k][row], np.float64)
      rms = np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-30)
      assert rms < 2e-2 and rel_dev(a, b) < 4e-2, (k, row, rms, rel_dev(a, b))
  # The normalisation runs in float32 before the cast, so 1e9x the counts stays in range. The
  # two rows' normalised inputs differ in float32's last bit, and a bfloat16 rounding can turn
  # that into one bfloat16 ulp (7.8e-3 of a value): they agree to about one bfloat16 eps of the
  # peak (measured 4.0e-3 on an AMD EPYC, 0 elsewhere), not to float32's.
  _same_reconstruction(bf, 1, 0, 1e-2)


def _extreme_ssm(params: dict) -> dict:
  """Every Mamba mixer's ``A = -exp(A_log)`` alternating -1e4 / -1e-6 over the states and its
  ``dt = softplus(. + bias)`` ~1e4 / ~1e-8 over the channels."""
  big, small = 1e4, math.log(math.expm1(1e-8))

  def set_leaf(path, leaf):
    name = path[-1].key           # A_log, A_log_b; dt_proj_bias, dt_proj_b_bias (reverse branch)
    if name.startswith("A_log"):
      d, n = leaf.shape
      a = np.where(np.arange(n) % 2 == 0, math.log(1e4), math.log(1e-6))
      return jnp.asarray(np.broadcast_to(a, (d, n)), leaf.dtype)
    if name.startswith("dt_proj") and name.endswith("bias"):
      return jnp.asarray(np.where(np.arange(leaf.shape[0]) % 2 == 0, big, small), leaf.dtype)
    return leaf

  return jax.tree_util.tree_map_with_path(set_leaf, params)


def _count(params: dict, test) -> int:
  """Number of parameter leaves whose name passes ``test``."""
  leaves = jax.tree_util.tree_flatten_with_path(params)[0]
  return sum(bool(test(path[-1].key)) for path, _ in leaves)


@pytest.mark.full
def test_ssm_dt_and_A_extremes_inside_the_network(net, net_out):
  cfg, params, apply = net
  x, _ = net_out
  extreme = _extreme_ssm(params)
  # Every scan direction of every mixer: the ST-Mamba block (temporal 1, spatial 2) and the
  # reference and neighbour branches of the two cross blocks.
  a_logs = _count(extreme, lambda n: n.startswith("A_log"))
  dt_biases = _count(extreme, lambda n: n.startswith("dt_proj") and n.endswith("bias"))
  changed = sum(jax.tree.leaves(jax.tree.map(lambda u, v: bool(jnp.any(u != v)), extreme, params)))
  assert a_logs == dt_biases == 15 and changed == 30
  out = apply(extreme, x)
  _check_outputs(out, cfg)
  _same_reconstruction(out, 1, 0, 1e-4)
  # The same network with float64 parameters and input: the SSMs (and whatever is not pinned to
  # float32) run in float64. Measured: at most 5.1e-6 of each output's peak (the transient's
  # peak is 4e11 here: dt = 1e4 amplifies the state 1e4-fold per step).
  model = STMambaNet(cfg)
  with jax.enable_x64(True):
    p64 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), extreme)
    ref = jax.jit(lambda p, v: model.apply({"params": p}, v))(p64, jnp.asarray(x, jnp.float64))
    ref = {k: np.asarray(v, np.float64) for k, v in ref.items()}
  assert ref["transient"].dtype == np.float64
  for k in ("transient", "volume", "intensity", "depth"):
    for row in (0, 3):
      assert rel_dev(out[k][row], ref[k][row]) < 1e-4, (k, row, rel_dev(out[k][row], ref[k][row]))


def _batch(frames: np.ndarray, setup: Setup) -> dict:  # frames [2, F, T, h, w]
  """A training batch of 2: the middle frame's clean transient, intensity and depth."""
  clean, z = _scene(setup, 3)
  inten = clean[1].sum(0) / clean[1].sum(0).max()
  return {"measurement": frames, "transient": np.stack([clean[1]] * 2),
          "intensity": np.stack([inten] * 2),
          "depth": np.stack([np.where(inten > 0.1, z, 0.0).astype(np.float32)] * 2)}


@pytest.mark.full
def test_train_step_on_normal_saturated_empty_and_extreme_ssm_batches(net, net_out):
  """On Ours-S: its training step compiles in half the time of Ours' (10 s against 20 s)."""
  cfg, params, _ = net
  x, _ = net_out
  cfg, params = _ours_s(cfg, params)
  weights = losses.LossWeights()
  wavelet = physics.illumination_wavelet(NET, cycles=cfg.wavelet_cycles,
                                         sampling_coeff=cfg.wavelet_sampling)
  state = train.TrainState.create(apply_fn=STMambaNet(cfg).apply, params=params,
                                  tx=train.make_optimizer(train.OptimConfig(), 10))
  step = jax.jit(functools.partial(train.train_step, weights=weights, wavelet=wavelet,
                                   time_window=cfg.time_window))
  key = jax.random.key(0)

  def run(st, batch):
    new, metrics = step(st, {k: jnp.asarray(v) for k, v in batch.items()}, key)
    metrics = {k: float(v) for k, v in metrics.items()}
    assert all(math.isfinite(v) for v in metrics.values()), metrics
    assert all(bool(jnp.all(jnp.isfinite(p))) for p in jax.tree.leaves(new.params))
    return metrics

  normal = _batch(x[0:1, 1:2].repeat(2, 0), NET)
  m = run(state, normal)
  assert m["l2_grads"] > 0
  # Saturated: 1e9x counts and 1e9x clean target. Input and target are both normalised, so the
  # loss and its gradients are those of the normal batch.
  sat = {**normal, "measurement": normal["measurement"] * np.float32(1e9),
         "transient": normal["transient"] * np.float32(1e9)}
  m_sat = run(state, sat)
  for k in ("loss", "pf", "t", "int", "dep", "l2_grads"):
    assert m_sat[k] == pytest.approx(m[k], rel=1e-5), k    # measured: equal
  # An empty scene (zero photons, zero targets) through the initialised network: the volume is
  # all zero, so the transient, intensity and regulariser terms sit at zero error (their guard
  # values) and only depth differs (the soft mask's background blend). Regression: the soft
  # projection divided by max(peak, 1e-12) and these gradients had a norm of 4.4e11 (Adam's
  # second moment then freezes the refinement for ~1/(1 - b2) steps); now exactly 0.
  empty = {k: np.zeros_like(v) for k, v in normal.items()}
  m_empty = run(state, empty)
  for k in ("pf", "t", "int", "ls"):
    assert m_empty[k] == pytest.approx(1e-6, rel=1e-3), (k, m_empty[k])
  assert m_empty["tv"] == 0.0 and m_empty["dep"] > 0
  assert m_empty["l2_grads"] == 0.0, m_empty["l2_grads"]
  # dt / A extremes in every mixer: a finite step.
  run(state.replace(params=_extreme_ssm(params)), normal)


# ------------------------------------------------------------------ sequences
def _video(path, frames: int) -> None:
  """Write one training sequence of ``frames`` frames on the ``NET`` geometry (CPU scenes)."""
  spec = D.DatasetSpec.from_config(configs.get_config("cpu")["data"], grid=NET.grid[0],
                                   num_bins=NET.num_bins, bin_width=NET.bin_width, frames=frames,
                                   num_train=1, num_test=0, num_val=0, render_batch=64)
  assert spec.setup == NET
  D.write_dataset(path, spec, progress=False)


def _loader(path, ends: str) -> D.TripletLoader:
  return D.TripletLoader(path, split="train", batch_size=4, stride=4, offset=2, shuffle=False,
                         drop_remainder=False, ends=ends, in_memory=True, setup=NET)


@pytest.mark.full
def test_videos_of_64_frames_and_of_one_frame(net, tmp_path):
  """A video is reconstructed frame by frame through the sliding triplet window
  (``ends="replicate"``: every frame is a middle frame, its missing neighbours repeated).
  64 frames: 16 batches of 4 triplets, each frame's reconstruction independent of what it is
  batched with. One frame: the triplet ``(0, 0, 0)`` for Ours (F = 3), the frame itself for
  Ours-S (F = 1)."""
  cfg, params, apply = net
  _video(tmp_path / "v64.h5", 64)
  with _loader(tmp_path / "v64.h5", "replicate") as loader:
    assert len(loader) == 16
    batches = [loader.batch(i) for i in range(16)]
    raw = loader.dataset.read(loader.names[0], "measurement", stride=4, offset=2)
  meas = np.concatenate([b["measurement"] for b in batches])               # [64, 3, T, h, w]
  np.testing.assert_array_equal(np.concatenate([b["frame"] for b in batches]), np.arange(64))
  np.testing.assert_array_equal(meas[0], raw[[0, 0, 1]])
  np.testing.assert_array_equal(meas[40], raw[[39, 40, 41]])
  np.testing.assert_array_equal(meas[63], raw[[62, 63, 63]])
  outs = [apply(params, b["measurement"]) for b in batches]
  video = {k: np.concatenate([np.asarray(o[k]) for o in outs]) for k in outs[0]}
  _check_outputs(video, cfg, rows=range(64))
  assert np.std(video["intensity"], axis=0).max() > 1e-3          # the object moves
  mixed = apply(params, meas[[63, 0, 31, 32]])
  for k in ("transient", "volume", "intensity", "depth"):
    for row, frame in enumerate((63, 0, 31, 32)):
      assert rel_dev(mixed[k][row], video[k][frame]) < 1e-5, (k, frame)

  _video(tmp_path / "v1.h5", 1)
  with pytest.raises(ValueError, match="too short"):
    _loader(tmp_path / "v1.h5", "valid")
  with _loader(tmp_path / "v1.h5", "replicate") as loader:
    one = loader.batch(0)
  assert one["measurement"].shape == (1, 3, 64, 4, 4)
  np.testing.assert_array_equal(one["measurement"][0, 0], one["measurement"][0, 2])
  np.testing.assert_array_equal(one["measurement"][0, 0], one["measurement"][0, 1])
  # Four identical rows agree to float32 reassociation: XLA:CPU may vectorise the last rows of a
  # batch differently (measured up to 1.9e-6 of the peak on an AMD EPYC); mixing rows up would
  # differ by O(1).
  ours = apply(params, one["measurement"].repeat(4, 0))
  _check_outputs(ours, cfg)
  _same_reconstruction(ours, 3, 0, 1e-5)
  cfg_s, params_s = _ours_s(cfg, params)
  model_s = STMambaNet(cfg_s)
  ours_s = jax.jit(lambda p, v: model_s.apply({"params": p}, v))(
      params_s, one["measurement"][:, 1:2].repeat(4, 0))
  _check_outputs(ours_s, cfg_s)
  _same_reconstruction(ours_s, 3, 0, 1e-5)


# ------------------------------------------------------- smallest grid, depth ranges
def test_network_on_one_scan_point_and_one_depth_bin(net):
  """Both extremes in one compile: the smallest input, one scan point (a 4 x 4 output grid,
  stride 4, the same weights), and a one-bin depth range."""
  cfg, params, _ = net
  small = Setup(0.5, (4, 4), 264e-12, 64)
  dz = small.depth_bin_length
  # Full range: the ungated time window and depth grid, so the same computation.
  whole = cfg.with_setup(small.with_depth_range(0.0, small.max_depth))
  assert whole.time_window == (0, small.num_bins)
  assert whole.coarse_setup.depth_bins == cfg.with_setup(small).coarse_setup.depth_bins
  # One depth bin must also be a bin of the physics layer's coarse grid (2 bins merged), else
  # the config says so.
  with pytest.raises(ValueError, match="depth"):
    cfg.with_setup(small.with_depth_range(25 * dz - 0.1 * dz, 25 * dz + 0.1 * dz))
  one = cfg.with_setup(small.with_depth_range(26 * dz - 0.1 * dz, 26 * dz + 0.1 * dz))
  assert one.input_grid == (1, 1) and one.setup.num_depth_bins == 1
  a, b = one.time_window
  assert 0 < b - a < small.num_bins
  model = STMambaNet(one)
  x = _frames(small, one.stride)
  got = jax.jit(lambda p, v: model.apply({"params": p}, v))(params, x)
  assert got["volume"].shape == (4, 1, 4, 4) and got["transient"].shape == (4, 64, 4, 4)
  _check_outputs(got, one)
  _same_reconstruction(got, 1, 0, 1e-5)
  # One bin: the soft depth is that bin's depth wherever the pixel is lit.
  lit = np.asarray(got["intensity"]) > 0.5
  assert lit.any()
  np.testing.assert_allclose(np.asarray(got["depth"])[lit], 26 * dz, rtol=1e-5)
  # The recovered transient is zero outside the gated window.
  tr = np.asarray(got["transient"])
  assert np.all(tr[:, :a] == 0) and np.all(tr[:, b:] == 0)

"""nlosjax.adaptation: fitting a small part of a trained network to one capture.

Independent references: the Poisson negative log-likelihood written out in
NumPy on the forward model's output; the likelihood of counts drawn from a
known volume, which must favour that volume over a displaced one; and
invariants of the fit (frozen leaves bit-identical, no step at ``steps=0``,
the returned step the best held-out one).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nlosjax import adaptation, physics
from nlosjax.models.network import ModelConfig, underscan
from nlosjax.physics import Setup

SETUP = Setup(wall_size=0.5, grid=(8, 8), bin_width=64e-12, num_bins=32)
STRIDE = 2


def volume_at(k):
  v = np.zeros((32, 8, 8), np.float32)
  v[k, 2:6, 3:5] = 1.0
  return v


def test_consistency_nll_is_the_poisson_likelihood_written_out():
  vol = volume_at(12)
  rng = np.random.default_rng(0)
  counts = rng.poisson(3.0, (32, 4, 4)).astype(np.float32)
  points = (rng.uniform(size=(4, 4)) < 0.6).astype(np.float32)
  got = float(adaptation.consistency_nll(vol, counts, SETUP, STRIDE, points))
  pred = np.asarray(underscan(physics.render(vol, SETUP), STRIDE), np.float64)
  b = np.median(counts, axis=0)
  a = (points * np.maximum(counts - b, 0)).sum() / (points * pred).sum()
  lam = a * pred + b + 1e-3
  want = (points * (lam - counts * np.log(lam))).sum() / (32 * points.sum())
  assert got == pytest.approx(want, rel=1e-5)


def test_the_likelihood_prefers_the_volume_the_counts_came_from():
  vol = volume_at(12)
  pred = np.asarray(underscan(physics.render(vol, SETUP), STRIDE), np.float64)
  rng = np.random.default_rng(1)
  counts = rng.poisson(200.0 * pred / pred.max() + 0.5).astype(np.float32)
  ones = np.ones((4, 4), np.float32)
  right = float(adaptation.consistency_nll(vol, counts, SETUP, STRIDE, ones))
  for k in (9, 15):
    assert float(adaptation.consistency_nll(volume_at(k), counts, SETUP, STRIDE, ones)) > right + 0.05


def test_holdout_mask_draws_its_share_reproducibly():
  m = adaptation.holdout_mask((16, 16), 0.25, seed=3)
  assert m.sum() == 64 and np.array_equal(m, adaptation.holdout_mask((16, 16), 0.25, seed=3))
  assert not np.array_equal(m, adaptation.holdout_mask((16, 16), 0.25, seed=4))
  with pytest.raises(ValueError, match="holdout"):
    adaptation.holdout_mask((4, 4), 1.0)


def _tiny_inputs():
  """A tiny Ours and its three-frame counts ``[1, 32, 4, 4]``."""
  cfg = ModelConfig.cpu(SETUP, stride=STRIDE, width=4, d_state=2, extract_time_stride=2, extract_blocks=1,
                        st_depth=1, cross_depth=1, spread_min_width=1, volume_features=1, refine_width=2,
                        frames=3, conv_impl="fold")
  return cfg, np.random.default_rng(2).poisson(2.0, (1, 32, 4, 4)).astype(np.float32)


@pytest.fixture(scope="module")
def tiny():
  cfg, frames = _tiny_inputs()
  frames[0, 10:14] += 20.0
  init = jax.jit(cfg.module().init)                                        # eager init takes minutes
  params = init(jax.random.key(0, impl="rbg"), jnp.asarray(frames[None].repeat(3, 1)))["params"]
  return cfg, jax.tree_util.tree_map(np.asarray, params), frames


def _paths(tree):
  return {"/".join(str(k.key) for k in p): np.asarray(v) for p, v in jax.tree_util.tree_flatten_with_path(tree)[0]}


@pytest.mark.full
def test_adapt_moves_only_the_trainable_leaves_and_returns_the_best_held_out_step(tiny):
  cfg, params, frames = tiny
  r = adaptation.adapt(cfg, params, frames, steps=6, patience=6, learning_rate=1e-2)
  before, after = _paths(params), _paths(r.params)
  moved = {k for k in before if not np.array_equal(before[k], after[k])}
  assert moved and all(k.startswith(adaptation.DEFAULT_TRAINABLE) for k in moved)
  assert r.num_trainable == sum(v.size for k, v in before.items() if k.startswith(adaptation.DEFAULT_TRAINABLE))
  assert len(r.holdout_nll) == r.steps + 1 and r.best_step == int(np.argmin(r.holdout_nll))
  assert r.holdout_nll[r.best_step] <= r.holdout_nll[0]
  assert np.isfinite(r.fit_nll).all() and "adapted" in r.summary()
  again = adaptation.adapt(cfg, params, frames, steps=0)
  assert again.steps == 0 and again.best_step == 0
  assert all(np.array_equal(v, _paths(again.params)[k]) for k, v in before.items())


@pytest.fixture(scope="module")
def tiny_shapes():
  """As ``tiny``, its parameters zeros of the right shapes (refusals need no trained values)."""
  cfg, frames = _tiny_inputs()
  shapes = jax.eval_shape(cfg.module().init, jax.random.key(0, impl="rbg"),
                          jax.ShapeDtypeStruct((1, 3) + frames.shape[1:], jnp.float32))["params"]
  return cfg, jax.tree_util.tree_map(lambda a: np.zeros(a.shape, a.dtype), shapes), frames


def test_adapt_refuses_bad_input(tiny_shapes):
  cfg, params, frames = tiny_shapes
  with pytest.raises(ValueError, match="frames"):
    adaptation.adapt(cfg, params, frames[:, :, :2])
  with pytest.raises(ValueError, match="negative"):
    adaptation.adapt(cfg, params, -frames)
  with pytest.raises(ValueError, match="names no parameter"):
    adaptation.adapt(cfg, params, frames, trainable=("nothing/here",))

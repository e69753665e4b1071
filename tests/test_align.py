"""nlosjax.train.align: the second stage's loss and loop on a tiny run.

Independent references: the synthetic term against the paper's loss computed
directly from the model's outputs; the feature rows against the layer's shape;
the MMD term against nlosjax.losses.mmd2 (tested against a pairwise loop).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nlosjax import losses
from nlosjax import train as T
from nlosjax.train import align as A
from tests.tiny_run import make_tiny_dataset, tiny_config


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
  path = make_tiny_dataset(tmp_path_factory)
  cfg = tiny_config(path)
  loader = T.make_loader(cfg, path, "train", batch_size=2, shuffle=False, seed=0)
  host = loader.batch(0)
  loader.close()
  mcfg = T.model_config_for(cfg, loader.setup, "ours")
  model = mcfg.module()
  batch = {k: jnp.asarray(host[k]) for k in T.BATCH_KEYS}
  params = jax.jit(model.init)(jax.random.key(0, impl="rbg"), batch["measurement"])["params"]
  measured = np.random.default_rng(0).poisson(2.0, (3,) + mcfg.input_shape(1)[1:]).astype(np.float32)
  return cfg, path, mcfg, model, params, batch, measured


@pytest.mark.full
def test_the_loss_is_the_papers_plus_lam_times_the_feature_mmd(tiny):
  cfg, _, mcfg, model, params, batch, measured = tiny
  _, weights = T.training_recipe(cfg, "ours")
  kw = dict(model=model, weights=weights, wavelet=None, time_window=mcfg.time_window, samples=64)
  weights0 = losses.LossWeights(**{**weights.__dict__, "phasor_field": 0.0})
  kw["weights"] = weights0
  key = jax.random.key(3)
  # lam traced, not static: one compile serves both weights.
  loss = jax.jit(lambda p, lam: A.align_loss(p, batch, jnp.asarray(measured), key, lam=lam, **kw))
  total0, _ = loss(params, jnp.float32(0.0))
  # Each reference in one jit: run eagerly, every operation compiles on its own (hundreds).
  want, _ = jax.jit(lambda p: losses.total_loss(model.apply({"params": p}, batch["measurement"]),
                                                T.make_targets(batch, mcfg.time_window), weights0, None))(params)
  assert float(total0) == pytest.approx(float(want), rel=1e-5)
  total2, terms2 = loss(params, jnp.float32(2.0))
  assert float(total2) == pytest.approx(float(want) + 2.0 * float(terms2["mmd"]), rel=1e-5)
  _, f = jax.jit(lambda p: A.layer_features(model, p, batch["measurement"]))(params)
  b, n = batch["measurement"].shape[:2]
  assert f.ndim == 2 and f.shape[1] == mcfg.width and f.shape[0] % (b * n) == 0
  with pytest.raises(ValueError, match="not a module"):           # raised while tracing: nothing compiles
    jax.eval_shape(lambda p: A.layer_features(model, p, batch["measurement"], "nowhere"), params)


@pytest.mark.full
def test_align_trains_writes_its_record_and_refuses_bad_measured_inputs(tiny, tmp_path):
  cfg, path, mcfg, _, params, _, measured = tiny
  got, record = A.align(cfg, path, mcfg, jax.tree_util.tree_map(np.asarray, params), measured, tmp_path,
                        steps=2, every=1, samples=32, measured_batch=2, learning_rate=1e-3,
                        validate=lambda m, p: 1.0, log=lambda s: None)
  assert (tmp_path / "params.npz").exists() and (tmp_path / "align.json").exists()
  assert [r["step"] for r in record["curve"]] == [0, 1, 2] and np.isfinite(record["curve"][-1]["mmd"])
  changed = jax.tree_util.tree_leaves(jax.tree_util.tree_map(lambda a, b: not np.array_equal(a, b), got, params))
  assert any(changed)
  with pytest.raises(ValueError, match="measured must be"):
    A.align(cfg, path, mcfg, params, measured[:, :1], tmp_path, steps=1)

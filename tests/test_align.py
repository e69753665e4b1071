"""experiments.studies.alignment: the second stage's loss and loop on a tiny run.

Independent references: the synthetic term against the paper's loss computed
directly from the model's outputs; the feature rows against the layer's shape;
the MMD term against nlosjax.losses.mmd2 (tested against a pairwise loop).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.studies import alignment as A
from nlosjax import losses
from nlosjax import train as T
from nlosjax.train import RunConfig
from tests.tiny_run import make_tiny_dataset, tiny_config


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
  path = make_tiny_dataset(tmp_path_factory)
  cfg = tiny_config(path)
  loader = T.make_loader(RunConfig.from_dict(cfg), path, "train", batch_size=2, shuffle=False, seed=0)
  host = loader.batch(0)
  loader.close()
  mcfg = T.model_config_for(RunConfig.from_dict(cfg), loader.setup, "ours")
  model = mcfg.module()
  batch = {k: jnp.asarray(host[k]) for k in T.BATCH_KEYS}
  params = jax.jit(model.init)(jax.random.key(0, impl="rbg"), batch["measurement"])["params"]
  measured = np.random.default_rng(0).poisson(2.0, (3,) + mcfg.input_shape(1)[1:]).astype(np.float32)
  return cfg, path, mcfg, model, params, batch, measured


@pytest.mark.full
def test_the_loss_is_the_papers_plus_lam_times_the_feature_mmd(tiny):
  cfg, _, mcfg, model, params, batch, measured = tiny
  _, weights = T.training_recipe(RunConfig.from_dict(cfg), "ours")
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
  got, record = A.align(RunConfig.from_dict(cfg), path, mcfg, jax.tree_util.tree_map(np.asarray, params), measured,
                        tmp_path,
                        steps=2, every=1, samples=32, measured_batch=2, learning_rate=1e-3,
                        validate=lambda m, p: 1.0, log=lambda s: None)
  assert (tmp_path / "params.npz").exists() and (tmp_path / "align.json").exists()
  assert [r["step"] for r in record["curve"]] == [0, 1, 2] and np.isfinite(record["curve"][-1]["mmd"])
  changed = jax.tree_util.tree_leaves(jax.tree_util.tree_map(lambda a, b: not np.array_equal(a, b), got, params))
  assert any(changed)
  with pytest.raises(ValueError, match="measured must be"):
    A.align(RunConfig.from_dict(cfg), path, mcfg, params, measured[:, :1], tmp_path, steps=1)


@pytest.mark.full
def test_term_gradient_norms_are_the_norms_of_the_two_terms_of_the_loss(tiny):
  """Against the loss itself: the synthetic term's gradient is the loss's at lam 0, the MMD
  term's the difference of the loss's gradients at lam 1 and lam 0, on the batch, measured
  draw and sample key that align's first step uses."""
  import optax
  cfg, path, mcfg, model, params, _, measured = tiny
  config = RunConfig.from_dict(cfg)
  norms = A.term_gradient_norms(config, path, mcfg, params, measured[:1], batches=1, measured_batch=2, samples=32)
  assert set(norms) == {"synthetic", "mmd", "mmd_value"} and all(len(v) == 1 for v in norms.values())
  loader = T.make_loader(config, path, "train", batch_size=config.train.batch_size, shuffle=True, seed=0)
  batch = A._device_batch(loader.batch(0), mcfg)
  loader.close()
  meas = jnp.asarray(np.repeat(measured[:1], 2, axis=0))             # one measured input: every draw is it
  key = jax.random.fold_in(jax.random.key(0), 0)
  loss_fn = A._loss_fn(config, mcfg, lam=1.0, samples=32, layer=A.DEFAULT_LAYER)
  ops = mcfg.physics_operators()
  from nlosjax.physics import operator_args

  def grads(p, lam):
    return jax.grad(lambda q: loss_fn(q, batch, meas, key, lam=lam)[0])(p)
  g0, g1 = operator_args.bind(lambda p: (grads(p, 0.0), grads(p, 1.0)), ops)(params)
  want_syn = float(optax.global_norm(g0))
  want_mmd = float(optax.global_norm(jax.tree_util.tree_map(lambda a, b: a - b, g1, g0)))
  assert norms["synthetic"][0] == pytest.approx(want_syn, rel=1e-4)
  assert norms["mmd"][0] == pytest.approx(want_mmd, rel=1e-3, abs=1e-7)
  with pytest.raises(ValueError, match="measured must be"):
    A.term_gradient_norms(RunConfig.from_dict(cfg), path, mcfg, params, measured[:, :1])


def test_balanced_lam_is_the_ratio_of_the_median_norms():
  norms = {"synthetic": [1.0, 2.0, 30.0], "mmd": [0.5, 1e3, 0.25]}
  assert A.balanced_lam(norms) == pytest.approx(2.0 / 0.5)
  assert A.balanced_lam(norms, share=0.5) == pytest.approx(1.0 / 0.5)
  for bad in ({"synthetic": [1.0], "mmd": [0.0]}, {"synthetic": [np.nan], "mmd": [1.0]}):
    with pytest.raises(ValueError, match="no balanced lam"):
      A.balanced_lam(bad)


@pytest.mark.full
def test_layer_separation_is_noise_on_one_distribution_and_large_on_another(tiny):
  cfg, path, mcfg, _, params, _, _ = tiny
  loader = T.make_loader(RunConfig.from_dict(cfg), path, "train", batch_size=2, shuffle=False, seed=0)
  x = np.concatenate([loader.batch(k)["measurement"] for k in range(2)])
  loader.close()
  # The same inputs on both sides: the measured features are a draw of the synthetic ones, so
  # MMD² is within the null's noise at every layer (|z| a few widths at most).
  same = A.layer_separation(mcfg, params, x, x, samples=64, draws=8)
  assert set(same) == {"extract", "st_mamba0", "cross_prev1_0", "cross_next1_0"}
  assert all(abs(r["z"]) < 3 for r in same.values()), same
  assert all(r["channels"] == mcfg.width for r in same.values())
  # A background of 20 counts a bin on the measured side: every layer sees it, far off the noise
  # (z 9-48 at these random weights).
  background = x + np.random.default_rng(0).poisson(20.0, x.shape).astype(np.float32)
  shifted = A.layer_separation(mcfg, params, x, background, samples=64, draws=8)
  assert all(r["z"] > 5 for r in shifted.values()), shifted
  assert A.chosen_layer(shifted) == max(shifted, key=lambda k: shifted[k]["z"])
  with pytest.raises(ValueError, match="no layer"):
    A.chosen_layer({})

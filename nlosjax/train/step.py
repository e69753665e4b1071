"""One pure train step ``(state, batch, key) -> (state, metrics)`` on the paper's loss, and its jitted form.

Batches are dicts of arrays: ``measurement [B, F, T, h, w]`` (under-scanned
noisy counts of ``F`` adjacent frames), ``transient [B, T, H, W]`` (clean
full-grid transient of the middle frame), ``intensity [B, H, W]`` in [0, 1],
``depth [B, H, W]`` metres.
"""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from nlosjax import losses
from nlosjax.physics import illumination_wavelet, operator_args
from nlosjax.train.state import TrainState

BATCH_KEYS = ("measurement", "transient", "intensity", "depth")


def make_targets(batch: dict, time_window: tuple[int, int]) -> dict:
  """Loss targets in the model's units.

  The model predicts the transient's shape, not its photon scale (which
  depends on efficiency and exposure): the clean target is divided by its
  own root-mean-square over the model's time window (guarded against 0).
  """
  a, b = time_window
  clean = batch["transient"].astype(jnp.float32)
  rms = jnp.sqrt(jnp.mean(jnp.square(clean[:, a:b]), axis=(1, 2, 3)))
  clean = clean / jnp.where(rms > 0, rms, 1.0)[:, None, None, None]
  return {"transient": clean, "intensity": batch["intensity"].astype(jnp.float32),
          "depth": batch["depth"].astype(jnp.float32)}


def train_step(state: TrainState, batch: dict, key: jax.Array, *, weights: losses.LossWeights,
               wavelet, time_window: tuple[int, int]) -> tuple[TrainState, dict]:
  """One AdamW step on the paper's loss; pure.

  Args:
    state: the train state.
    batch: see the module docstring.
    key: this step's PRNG key (``fold_in(loop_key, step)``). The model is
      deterministic; the key is part of the signature for stochastic layers
      and augmentation.
    weights, wavelet, time_window: static loss settings.
  Returns:
    ``(new_state, metrics)``; metrics: ``loss``, every loss term, and
    ``l2_grads``, ``l2_params``, ``l2_updates``.
  """
  del key

  def loss_fn(params):
    out = state.apply_fn({"params": params}, batch["measurement"])
    targets = make_targets(batch, time_window)
    return losses.total_loss(out, targets, weights, wavelet)

  (loss, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
  new_state = state.apply_gradients(grads=grads)
  updates = jax.tree.map(lambda a, b: a - b, new_state.params, state.params)
  metrics = {"loss": loss, **terms, "l2_grads": optax.tree.norm(grads),
             "l2_params": optax.tree.norm(new_state.params),
             "l2_updates": optax.tree.norm(updates)}
  return new_state, metrics


@functools.lru_cache(maxsize=8)
def make_train_step(model_config, weights: losses.LossWeights, mesh: Mesh) -> Callable:
  """``train_step`` jitted: state donated and replicated, batch sharded over ``mesh``.

  The physics layer's operators enter the compiled step as an argument
  (replicated over ``mesh``), not as constants
  (:mod:`nlosjax.physics.operator_args`); the returned function is called and
  lowered as ``step(state, batch, key)``.

  Cached per (model config, weights, mesh), so a resumed or repeated run in
  one process reuses the compiled step.
  """
  wavelet = (illumination_wavelet(model_config.setup, cycles=model_config.wavelet_cycles,
                                  sampling_coeff=model_config.wavelet_sampling)
             if weights.phasor_field else None)
  fn = functools.partial(train_step, weights=weights, wavelet=wavelet,
                         time_window=model_config.time_window)
  replicated = NamedSharding(mesh, P())
  table = operator_args.replicate(model_config.physics_operators(), replicated)
  return operator_args.bind(fn, table, donate_argnums=0, out_shardings=(replicated, replicated))

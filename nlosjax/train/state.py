"""The train state: parameters and optimiser state, initialised from shapes and replicated over a mesh."""

from __future__ import annotations

import functools
from typing import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax.training import train_state
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from nlosjax.train.sharding import make_mesh


class TrainState(train_state.TrainState):
  """flax ``TrainState``: ``step`` (int32 ``[]``), ``params``, ``opt_state``; ``apply_fn``, ``tx`` static."""


def create_train_state(model: nn.Module, input_shape: tuple[int, ...], tx, key: jax.Array,
                       mesh: Mesh | None = None) -> TrainState:
  """Initialise parameters and optimiser state, replicated over ``mesh``.

  Shapes are traced with ``jax.eval_shape`` first, so a config error shows
  before anything is allocated.

  Args:
    model: the Flax module (e.g. ``STMambaNet(config)``).
    input_shape: ``[B, F, T, h, w]`` of one batch.
    tx: the optax transformation.
    key: PRNG key for the parameters.
    mesh: devices to replicate over (default: every device).
  """
  mesh = mesh or make_mesh()
  init = _jitted_init(model, tuple(input_shape), tx, mesh)
  return init(key, jnp.zeros(tuple(input_shape), jnp.float32))


@functools.lru_cache(maxsize=8)
def _jitted_init(model: nn.Module, input_shape: tuple[int, ...], tx, mesh: Mesh) -> Callable:
  """``init(key, x) -> TrainState`` jitted, one per (model, shape, optimiser, mesh).

  Compiling it costs about as much as a forward pass (tens of seconds on
  CPU), so the seeds of one run share it: pass the same ``model`` instance
  (:func:`network`) and optimiser (:func:`make_optimizer` is cached).
  """
  abstract = abstract_train_state(model, input_shape, tx, mesh)
  return jax.jit(_init_fn(model, tx), out_shardings=jax.tree.map(lambda a: a.sharding, abstract))


def _init_fn(model: nn.Module, tx) -> Callable:
  """``init(key, x) -> TrainState``: parameters from ``model.init``, optimiser state from ``tx``."""
  def init(k, x):
    params = model.init(k, x)["params"]
    return TrainState.create(apply_fn=model.apply, params=params, tx=tx)
  return init


def abstract_train_state(model: nn.Module, input_shape: tuple[int, ...], tx, mesh: Mesh) -> TrainState:
  """The train state as ``jax.ShapeDtypeStruct`` leaves replicated over ``mesh``; nothing allocated.

  Args:
    model, tx: as :func:`create_train_state`.
    input_shape: ``[B, F, T, h, w]`` of one batch.
    mesh: devices the state is replicated over.
  Returns:
    A :class:`TrainState` whose array leaves are shapes, dtypes and shardings:
    what :func:`create_train_state` would build, e.g. to lower a step ahead
    of time (:mod:`nlosjax.plan`).
  """
  abstract = jax.eval_shape(_init_fn(model, tx), jax.random.key(0),
                            jax.ShapeDtypeStruct(tuple(input_shape), jnp.float32))
  replicated = NamedSharding(mesh, P())
  return jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=replicated), abstract)


@functools.lru_cache(maxsize=8)
def network(model_config) -> nn.Module:
  """The module of ``model_config`` (``STMambaNet`` or ``USMNet``: ``model_config.module()``), one instance per config.

  A ``TrainState`` holds ``model.apply``, a bound method, and bound methods
  compare by the identity of their module: one instance per config lets the
  seeds and resumed runs of one process reuse the compiled init and train
  step instead of compiling them again.
  """
  return model_config.module()

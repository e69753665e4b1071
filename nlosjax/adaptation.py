"""Adapt a trained network to one capture: fit a small part of it so its volume explains the measurement.

The capture is the only truth a user has. :func:`adapt` fine-tunes the
parameters under ``trainable`` (by default the refinement after the physics
layer and the spreading stage's output layer) so that the forward model of
the network's reconstructed volume reproduces the measured counts at the
scan points it read:

    lam = a * underscan(render(volume)) + b,    loss = mean over fit points and bins of lam - y log lam

(:func:`consistency_nll`: the Poisson negative log-likelihood up to a
constant; ``render`` the light-cone forward model,
:func:`nlosjax.physics.render`, on the model's Setup; ``b`` each scan point's
background, the median of its histogram; ``a`` the scale that matches the fit
points' total signal, recomputed every step and not differentiated). A share
``holdout`` of the read scan points is left out of the fit; training stops
when their likelihood has not improved for ``patience`` steps, and the
parameters of the best held-out step are returned. The network's input is the
whole under-scanned capture either way. Shapes: ``frames [F, T, h, w]`` counts
of the model's time bins and under-scanned grid (as
:func:`nlosjax.inference.run_model` takes them).
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

__all__ = ["DEFAULT_TRAINABLE", "AdaptResult", "consistency_nll", "holdout_mask", "adapt"]

#: Parameter paths (``/``-joined prefixes) fitted by default: the refinement after the
#: physics layer and the spreading stage's output layer and skip gain.
DEFAULT_TRAINABLE = ("volume/refine", "spread/to_transient", "spread/skip_gain")


@dataclasses.dataclass(frozen=True)
class AdaptResult:
  """What :func:`adapt` did.

  Attributes:
    params: the adapted parameters (the input tree with the fitted leaves replaced).
    steps: optimiser steps taken; best_step: the step whose parameters are returned (0: the input's).
    fit_nll, holdout_nll: ``[steps + 1]`` mean negative log-likelihood per point and bin on the fit
      and held-out scan points (entry 0 before any step).
    trainable: the fitted parameter paths; num_trainable: their scalars.
    seconds: wall time, compilation included.
  """

  params: dict
  steps: int
  best_step: int
  fit_nll: np.ndarray
  holdout_nll: np.ndarray
  trainable: tuple[str, ...]
  num_trainable: int
  seconds: float

  def summary(self) -> str:
    """One line: steps, the held-out likelihood's change, the time."""
    h = self.holdout_nll
    return (f"adapted {self.num_trainable} parameters ({', '.join(self.trainable)}): {self.steps} steps, "
            f"best {self.best_step}; held-out NLL {h[0]:.4f} -> {h[self.best_step]:.4f} per point and bin; "
            f"{self.seconds:.1f} s")


def holdout_mask(grid, share: float, seed: int = 0) -> np.ndarray:
  """``[h, w]`` bool, True for the scan points held out of the fit: ``round(share h w)`` of them at random."""
  if not 0.0 <= share < 1.0:
    raise ValueError(f"holdout must be in [0, 1), got {share!r}")
  h, w = grid
  n = int(round(share * h * w))
  mask = np.zeros(h * w, bool)
  mask[np.random.default_rng(seed).choice(h * w, n, replace=False)] = True
  return mask.reshape(h, w)


def consistency_nll(volume, counts, setup, stride: int, points, *, falloff: str = "diffuse",
                    background=None):
  """Mean Poisson NLL of ``counts`` under the forward model of ``volume`` (module docstring), one example.

  Args:
    volume: ``[Z, H, W]`` >= 0 on ``setup.depths`` (the network's ``"volume"``).
    counts: ``[T, h, w]`` measured counts at the under-scanned points (``stride``).
    setup: the network's full-grid Setup.
    stride: the under-scanning stride (points ``stride // 2 + stride i``).
    points: ``[h, w]`` weights of the scan points in the mean (1 fit, 0 left out).
    falloff: the forward model's falloff (:func:`nlosjax.physics.render`).
    background: ``[h, w]`` each point's background counts per bin (default: the median of ``counts``
      over time, computed here).
  Returns:
    scalar float32: ``sum points * (lam - y log lam) / (T * sum points)``.
  """
  from nlosjax.models.network import underscan
  from nlosjax.physics.forward import render
  pred = underscan(render(volume, setup, falloff=falloff), stride)         # [T, h, w]
  return _poisson_nll(pred, counts, points, background)


def _poisson_nll(pred, counts, points, background=None):
  """:func:`consistency_nll` from the rendered counts ``pred [T, h, w]`` at the read points."""
  y = jnp.asarray(counts, jnp.float32)
  points = jnp.asarray(points, jnp.float32)
  background = jax.lax.stop_gradient(jnp.median(y, axis=0) if background is None
                                      else jnp.asarray(background, jnp.float32))   # [h, w]
  signal = jnp.sum(points * jnp.maximum(y - background, 0.0))
  total = jnp.sum(points * pred)
  scale = jax.lax.stop_gradient(jnp.where(total > 0, signal / jnp.where(total > 0, total, 1.0), 0.0))
  lam = scale * pred + background + 1e-3
  nll = lam - y * jnp.log(lam)
  return jnp.sum(points * nll) / (y.shape[0] * jnp.maximum(jnp.sum(points), 1.0))


def _paths(params) -> dict:
  return {"/".join(str(k.key) for k in path): leaf
          for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]}


def _split(params, trainable):
  """``(mask tree, number of fitted scalars)``: True at the leaves under a ``trainable`` prefix."""
  flat = _paths(params)
  picked = {p for p in flat if any(p == t or p.startswith(t + "/") for t in trainable)}
  if not picked:
    raise ValueError(f"trainable {trainable} names no parameter; the tree has e.g. {sorted(flat)[:6]}")
  mask = jax.tree_util.tree_map_with_path(
      lambda path, _: "/".join(str(k.key) for k in path) in picked, params)
  return mask, int(sum(np.size(flat[p]) for p in picked))


def adapt(model_config, params, frames, *, trainable=DEFAULT_TRAINABLE, steps: int = 40,
          learning_rate: float = 3e-3, holdout: float = 0.25, patience: int = 8, seed: int = 0,
          falloff: str = "diffuse", log=None) -> AdaptResult:
  """Fine-tune ``trainable`` on one capture (module docstring); the input ``params`` are not changed.

  Args:
    model_config: the network's config, moved to the capture
      (:func:`nlosjax.inference.for_capture` ``.model_config``).
    params: its parameters.
    frames: ``[F, T, h, w]`` under-scanned counts in the model's bins; every frame is fitted.
    trainable: parameter path prefixes to fit (:data:`DEFAULT_TRAINABLE`).
    steps: at most this many Adam steps; learning_rate: Adam's.
    holdout: share of the read scan points left out of the fit, for stopping.
    patience: stop after this many steps without a better held-out NLL.
    seed: the held-out points' draw.
    falloff: the forward model's falloff (``"retroreflective"`` for retroreflective targets).
    log: optional ``print``-like callable for progress.
  Returns:
    an :class:`AdaptResult`.
  Raises:
    ValueError: bad shapes, counts, ``trainable``, ``steps``, ``holdout`` or ``patience``.
  """
  from nlosjax.models.network import triplets, underscan
  from nlosjax.physics import _validate, operator_args
  from nlosjax.physics.forward import render
  t0 = time.perf_counter()
  frames = np.asarray(frames, np.float32)
  if frames.ndim != 4 or tuple(frames.shape[-2:]) != tuple(model_config.input_grid):
    raise ValueError(f"frames must be [F, T, h, w] with (h, w) = {model_config.input_grid}, got {frames.shape}")
  _validate.check_counts(frames, "frames")
  if not (isinstance(steps, int) and steps >= 0 and isinstance(patience, int) and patience >= 1):
    raise ValueError(f"steps must be an integer >= 0 and patience >= 1, got {steps!r}, {patience!r}")
  mask, count = _split(params, tuple(trainable))
  held = holdout_mask(model_config.input_grid, holdout, seed)
  fit_w, held_w = jnp.asarray(~held, jnp.float32), jnp.asarray(held, jnp.float32)
  x = jnp.asarray(triplets(frames, model_config.frames))                  # [F, n, T, h, w]
  data = (x, jnp.asarray(np.median(frames, axis=1)), fit_w, held_w)       # arguments, not constants
  model = model_config.module()
  setup, stride, mid = model_config.setup, model_config.stride, model_config.frames // 2

  def losses(p, data):
    x, background, fit_w, held_w = data
    vol = model.apply({"params": p}, x)["volume"]
    def both(v, c, b):                    # one render, scored at the fit and the held-out points
      pred = underscan(render(v, setup, falloff=falloff), stride)
      return jnp.stack([_poisson_nll(pred, c, fit_w, b), _poisson_nll(pred, c, held_w, b)])
    per = jax.vmap(both)(vol, x[:, mid], background)
    return per.mean(0)

  # Only the trainable leaves are differentiated and optimised; the frozen ones enter as
  # constants, so the backward pass stops where the first trainable parameter enters (the
  # scans and the physics layer before it run forward only).
  leaves, treedef = jax.tree_util.tree_flatten(jax.tree_util.tree_map(jnp.asarray, params))
  picked = jax.tree_util.tree_leaves(mask)
  train0 = [leaf for leaf, m in zip(leaves, picked) if m]
  frozen = [leaf for leaf, m in zip(leaves, picked) if not m]

  def merge(train, frozen):
    it_t, it_f = iter(train), iter(frozen)
    return jax.tree_util.tree_unflatten(treedef, [next(it_t) if m else next(it_f) for m in picked])

  opt = optax.adam(learning_rate)

  def fit_loss(train, frozen, data):
    both = losses(merge(train, frozen), data)
    return both[0], both

  def step(train, frozen, state, data):
    (_, both), grads = jax.value_and_grad(fit_loss, has_aux=True)(train, frozen, data)
    updates, state = opt.update(grads, state, train)
    return optax.apply_updates(train, updates), state, both

  run_step = operator_args.bind(step, model_config.physics_operators())
  train = train0
  state = opt.init(train)
  fit, held_nll = [], []
  best, best_step, best_train = np.inf, 0, train
  for k in range(steps + 1):              # the losses of the parameters after k steps
    # One compiled program: the losses at train, then a step (discarded after the last scoring).
    new_train, state, now = run_step(train, frozen, state, data)
    now = np.asarray(now)
    fit.append(float(now[0]))
    held_nll.append(float(now[1]))
    if not np.all(np.isfinite(now)):
      break
    if held_nll[-1] < best:
      best, best_step, best_train = held_nll[-1], k, train
    if log is not None:
      log(f"[adapt] step {k}: fit NLL {fit[-1]:.4f}, held-out NLL {held_nll[-1]:.4f}")
    if k == steps or k - best_step >= patience:
      break
    train = new_train
  best_params = merge(best_train, frozen)
  taken = len(fit) - 1
  out = jax.tree_util.tree_map(lambda a, b, m: np.asarray(a) if m else np.asarray(b), best_params, params, mask)
  return AdaptResult(out, taken, best_step, np.asarray(fit), np.asarray(held_nll), tuple(trainable), count,
                     time.perf_counter() - t0)

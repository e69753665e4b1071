"""The optimiser: AdamW with optional warm-up + cosine schedule and gradient clipping (paper Sec. 5.1)."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import optax


@dataclasses.dataclass(frozen=True)
class OptimConfig:
  """Optimiser settings (AdamW, paper Sec. 5.1).

  Attributes:
    learning_rate: peak learning rate (paper 1e-4).
    weight_decay: decoupled weight decay. The paper prints 0.95; its
      predecessor USM used 1e-4 (see ``experiments/studies/archive/table2.md`` for the
      measured comparison behind our default).
    warmup_steps: linear warm-up from 0 (0: none).
    cosine: decay to ``end_fraction * learning_rate`` by the last step.
    end_fraction: final learning rate as a fraction of the peak.
    clip_norm: global gradient-norm clipping (None: none).
    b1, b2: Adam moments.
  """

  learning_rate: float = 1e-4
  weight_decay: float = 1e-4
  warmup_steps: int = 0
  cosine: bool = False
  end_fraction: float = 0.1
  clip_norm: float | None = 1.0
  b1: float = 0.9
  b2: float = 0.999


def learning_rate_schedule(cfg: OptimConfig, total_steps: int) -> Any:
  """The learning rate: a float (constant) or an optax schedule ``step -> rate`` over ``total_steps``.

  ``total_steps`` is the horizon of the cosine decay: the run's length, or
  under the plateau stopping rule its ``max_steps`` (:mod:`nlosjax.train.stopping`).
  """
  if not cfg.learning_rate > 0:
    raise ValueError(f"learning_rate must be > 0, got {cfg.learning_rate!r}")
  lr: Any = cfg.learning_rate
  if cfg.cosine:
    lr = optax.warmup_cosine_decay_schedule(
        0.0, cfg.learning_rate, max(cfg.warmup_steps, 1), max(total_steps, cfg.warmup_steps + 1),
        end_value=cfg.learning_rate * cfg.end_fraction)
  elif cfg.warmup_steps:
    lr = optax.join_schedules([optax.linear_schedule(0.0, cfg.learning_rate, cfg.warmup_steps),
                               optax.constant_schedule(cfg.learning_rate)], [cfg.warmup_steps])
  return lr


def learning_rate_at(cfg: OptimConfig, total_steps: int, step: int) -> float:
  """The learning rate of update ``step`` (0-based: the update that makes step ``step + 1``)."""
  lr = learning_rate_schedule(cfg, total_steps)
  return float(lr(step)) if callable(lr) else float(lr)


@functools.lru_cache(maxsize=16)
def make_optimizer(cfg: OptimConfig, total_steps: int) -> optax.GradientTransformation:
  """AdamW with the configured schedule and clipping.

  Cached: the same settings give the same object, so train states built for
  several seeds share one static ``tx`` and one compiled train step.
  """
  lr = learning_rate_schedule(cfg, total_steps)
  if not cfg.weight_decay >= 0:
    raise ValueError(f"weight_decay must be >= 0, got {cfg.weight_decay!r}")
  parts = []
  if cfg.clip_norm:
    parts.append(optax.clip_by_global_norm(cfg.clip_norm))
  parts.append(optax.adamw(lr, b1=cfg.b1, b2=cfg.b2, weight_decay=cfg.weight_decay))
  return optax.chain(*parts)

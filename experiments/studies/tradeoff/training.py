"""Training (or restoring) the learned configurations with one shared budget
(:func:`train_learned`), on windows of adjacent frames (``nlosjax.train.make_loader``'s ``window``).
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, Callable

from experiments.studies.tradeoff.configs import Learned, learned_config


def train_learned(spec: Learned, config, setup, root: pathlib.Path,
                  get_loader: Callable[[], Any], log: Callable[[str], None] = print):
  """Train ``spec`` for ``config.train.steps`` AdamW steps through the main job's
  :func:`nlosjax.train.train_model`, or restore it; returns ``(model_config, params)``.

  The main job's recipe: the preset's optimiser (schedule over the steps), loss, batch
  size and seed, the same batches; the last state is kept (no validation, no plateau
  rule), checkpointed every 50 steps in ``root/<name>/checkpoints`` and resumed after an
  interruption, refused if written by another recipe.

  Args:
    spec: the configuration.
    config: the preset (:class:`~nlosjax.train.RunConfig`), its ``train.steps`` the budget.
    setup: the dataset's full-grid Setup.
    root: checkpoint root.
    get_loader: returns a new training loader (``make_loader`` with a ``window`` wide enough
      for ``spec.frames``); ``train_model`` closes it. A non-finite loss raises
      ``FloatingPointError`` there.
  """
  from nlosjax.train import StopRule, train_model
  config = dataclasses.replace(config, train=dataclasses.replace(
      config.train, checkpoint_every=50, keep_checkpoints=1, select_checkpoint="last", stop=StopRule()))
  mcfg, state = train_model(config, None, root, spec.variant, folder=spec.name, log=log,
                            loader=get_loader(), model_config=learned_config(config, setup, spec))
  return mcfg, state.params

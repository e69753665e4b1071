"""Training (or restoring) the learned configurations with one shared budget
(:func:`train_learned`), on windows of adjacent frames (:func:`window_loader`,
:func:`window_frames`).
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, Callable

import numpy as np

from experiments.studies.tradeoff.configs import Learned, learned_config


def window_loader(config, path, window: int, *, batch_size: int, seed: int):
  """The training loader of :mod:`nlosjax.train` with ``window`` adjacent input frames.

  ``config``: a :class:`~nlosjax.train.RunConfig`. ``window = 3`` gives exactly
  :class:`~nlosjax.data.dataset.TripletLoader`'s batches; wider windows clip frame
  indices at the sequence ends.
  """
  from nlosjax.data.dataset import TripletLoader

  class WindowLoader(TripletLoader):
    def triplet_frames(self, middle: int, num_frames: int) -> np.ndarray:
      return window_frames(middle, num_frames, window)

  data = config.data
  return WindowLoader(path, split="train", batch_size=batch_size, stride=data.stride(),
                      offset=data.input_offset, seed=seed, shuffle=True, drop_remainder=True,
                      ends=data.loader.ends, target=data.loader.target, in_memory=True)


def window_frames(middle: int, num_frames: int, window: int) -> np.ndarray:
  """``[window]`` frame indices centred on ``middle``, clipped to ``[0, num_frames)``."""
  if window < 1 or window % 2 == 0:
    raise ValueError(f"window must be a positive odd integer, got {window!r}")
  half = window // 2
  return np.clip(np.arange(middle - half, middle + half + 1), 0, num_frames - 1)


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
    get_loader: returns a new training loader (:func:`window_loader`, wide enough for
      ``spec.frames``); ``train_model`` closes it. A non-finite loss raises
      ``FloatingPointError`` there.
  """
  from nlosjax.train import StopRule, train_model
  config = dataclasses.replace(config, train=dataclasses.replace(
      config.train, checkpoint_every=50, keep_checkpoints=1, select_checkpoint="last", stop=StopRule()))
  mcfg, state = train_model(config, None, root, spec.variant, folder=spec.name, log=log,
                            loader=get_loader(), model_config=learned_config(config, setup, spec))
  return mcfg, state.params

"""Training (or restoring) the learned configurations with one shared budget
(:func:`train_learned`), on windows of adjacent frames (:func:`window_loader`,
:func:`window_frames`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import time
from typing import Any, Callable

import numpy as np

from benchmarks.tradeoff.configs import Learned, learned_config


def window_loader(config: dict, path, window: int, *, batch_size: int, seed: int):
  """The training loader of :mod:`nlosjax.train` with ``window`` adjacent input frames.

  ``window = 3`` gives exactly :class:`~nlosjax.data.dataset.TripletLoader`'s
  batches; wider windows clip frame indices at the sequence ends.
  """
  from nlosjax.data.dataset import TripletLoader

  class WindowLoader(TripletLoader):
    def triplet_frames(self, middle: int, num_frames: int) -> np.ndarray:
      return window_frames(middle, num_frames, window)

  data = config["data"]
  opts = data.get("loader", {})
  stride = int(data["input_stride"])
  return WindowLoader(path, split="train", batch_size=batch_size, stride=stride,
                      offset=stride // 2, seed=seed, shuffle=True, drop_remainder=True,
                      ends=opts.get("ends", "valid"), target=opts.get("target", "clean"),
                      in_memory=True)


def window_frames(middle: int, num_frames: int, window: int) -> np.ndarray:
  """``[window]`` frame indices centred on ``middle``, clipped to ``[0, num_frames)``."""
  if window < 1 or window % 2 == 0:
    raise ValueError(f"window must be a positive odd integer, got {window!r}")
  half = window // 2
  return np.clip(np.arange(middle - half, middle + half + 1), 0, num_frames - 1)


def train_learned(spec: Learned, config: dict, setup, root: pathlib.Path, steps: int,
                  get_loader: Callable[[], Any], log: Callable[[str], None] = print):
  """Train ``spec`` for ``steps`` AdamW steps, or restore it; returns ``(model_config, params)``.

  The main job's recipe (:func:`nlosjax.train.train_model`): the preset's
  optimiser (schedule over ``steps``), loss, batch size and seed, the same
  batches; checkpoints every 50 steps in ``root/<name>/checkpoints``, resumed
  after an interruption, refused if written by another recipe.

  Args:
    spec: the configuration.
    config: the preset (``data``, ``model``, ``train`` sections).
    setup: the dataset's full-grid Setup.
    root: checkpoint root.
    steps: the training budget.
    get_loader: returns the training loader (:func:`window_loader`, wide
      enough for ``spec.frames``); called only when training is needed.
  """
  import jax
  from jax.sharding import NamedSharding
  from jax.sharding import PartitionSpec as P
  from tqdm import tqdm

  from nlosjax.train import (
    BATCH_KEYS,
    Checkpointer,
    create_train_state,
    make_mesh,
    make_optimizer,
    make_train_step,
    model_record,
    select_frames,
    shard_batch,
    training_recipe,
  )
  tr = config["train"]
  batch_size, seed = int(tr["batch_size"]), int(tr.get("seed", 0))
  mcfg = learned_config(config, setup, spec)
  optim, weights = training_recipe(config, "usm" if spec.variant == "usm" else "ours")
  mesh = make_mesh()
  init_key, loop_key = jax.random.split(jax.random.key(seed))

  def init():
    return create_train_state(mcfg.module(), (batch_size,) + mcfg.input_shape()[1:],
                              make_optimizer(optim, steps), init_key, mesh)

  signature = json.dumps({"benchmark": "tradeoff", "model": model_record(mcfg),
                          "optim": dataclasses.asdict(optim), "loss": dataclasses.asdict(weights),
                          "batch_size": batch_size, "seed": seed, "steps": steps}, sort_keys=True)
  vdir = root / spec.name
  ckpt = Checkpointer(vdir / "checkpoints", signature, every=50, keep=1, model=mcfg)
  latest = ckpt.latest_step()
  if latest is not None and latest >= steps:
    # Finished: restore into shapes only (no compiled initialisation).
    replicated = NamedSharding(mesh, P())
    state = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=replicated),
                         jax.eval_shape(init))
  else:
    state = init()
  start = 0
  restored = ckpt.restore_latest(state)
  if restored is not None:
    state, start = restored
  if start < steps:
    log(f"[{spec.name}] training steps {start}..{steps} into {vdir}")
    loader = get_loader()
    step_fn = make_train_step(mcfg, weights, mesh)
    t0 = time.perf_counter()
    with tqdm(total=steps, initial=start, desc=f"train {spec.name}", unit="step",
              dynamic_ncols=True, mininterval=2.0) as bar:
      for step in range(start, steps):
        host = loader.batch(step)
        batch = {k: host[k] for k in BATCH_KEYS}
        batch["measurement"] = select_frames(batch["measurement"], mcfg.frames)
        state, metrics = step_fn(state, shard_batch(batch, mesh), jax.random.fold_in(loop_key, step))
        ckpt.save(state, step + 1, force=(step + 1 == steps))
        bar.update(1)
    loss = float(metrics["loss"])
    if not math.isfinite(loss):
      raise FloatingPointError(f"[{spec.name}] non-finite loss {loss} after {steps} steps")
    (vdir / "train.json").write_text(json.dumps(
        {"steps": steps, "final_loss": loss, "resumed_from": start,
         "train_s": round(time.perf_counter() - t0, 1)}) + "\n")
  else:
    log(f"[{spec.name}] restored step {int(state.step)} from {vdir / 'checkpoints'}")
  ckpt.close()
  return mcfg, state.params

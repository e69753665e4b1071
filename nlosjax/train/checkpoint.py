"""Checkpoints: orbax saves of a train state that refuse another run's, and the run signature they carry."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib

import jax
import jax.numpy as jnp

from nlosjax import losses
from nlosjax.train.config_record import compare as compare_model
from nlosjax.train.config_record import model_record
from nlosjax.train.optimizer import OptimConfig
from nlosjax.train.state import TrainState


class Checkpointer:
  """orbax ``CheckpointManager`` for a :class:`TrainState` plus JSON metadata.

  Each save writes ``{"params", "opt_state", "step"}`` (``StandardSave``) and
  ``{"data_position", "model_config"}`` (``JsonSave``) to a new step folder;
  orbax finalises a folder atomically, so a kill mid-save leaves the previous
  checkpoints intact. :meth:`restore_latest` refuses a checkpoint whose model
  config differs, and reports a corrupt one by name; it never deletes.

  Args:
    directory: the checkpoint folder (created).
    model_config: the run signature (:func:`run_signature`, JSON) that must
      match on restore.
    every: save interval in steps.
    keep: checkpoints kept.
    model: the run's model config; when given, the signature's ``"model"``
      record is matched by :func:`nlosjax.train.config_record.compare` (a field
      the checkpoint predates passes at its default) and every other entry
      must be equal; without it the whole signature must be equal.
  """

  def __init__(self, directory, model_config: str, *, every: int, keep: int = 2, model=None):
    import orbax.checkpoint as ocp
    self._ocp = ocp
    self.directory = pathlib.Path(directory).absolute()
    self.model_config = model_config
    self.model = model
    self.every = int(every)
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, save_interval_steps=1, create=True)
    self.manager = ocp.CheckpointManager(self.directory, options=options)

  def latest_step(self) -> int | None:
    return self.manager.latest_step()

  def save(self, state: TrainState, data_position: int, *, force: bool = False) -> bool:
    step = int(state.step)
    if not force and (step % self.every):
      return False
    ocp = self._ocp
    item = {"params": state.params, "opt_state": state.opt_state, "step": state.step}
    meta = {"data_position": int(data_position), "model_config": self.model_config}
    self.manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(item),
                                                     meta=ocp.args.JsonSave(meta)), force=force)
    return True

  def all_steps(self) -> list[int]:
    """Steps of the kept checkpoints, ascending."""
    return sorted(self.manager.all_steps())

  def restore_latest(self, state: TrainState) -> tuple[TrainState, int] | None:
    """``(state, data_position)`` from the latest checkpoint, or None when there is none."""
    step = self.latest_step()
    if step is None:
      return None
    return self.restore(state, step)

  def restore(self, state: TrainState, step: int) -> tuple[TrainState, int]:
    """``(state, data_position)`` from the checkpoint of ``step`` (ValueError if absent or refused)."""
    ocp = self._ocp
    if step not in self.manager.all_steps():
      raise ValueError(f"{self.directory}: no checkpoint of step {step} (kept: {self.all_steps()})")
    where = self.directory / str(step)
    try:
      meta = self.manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
    except Exception as e:  # orbax raises many types for a damaged folder
      raise ValueError(f"checkpoint {where} is unreadable ({type(e).__name__}: {e}); "
                       "move it away to resume from an earlier one") from None
    differ = signature_differences(meta.get("model_config"), self.model_config, self.model)
    if differ:
      raise ValueError(f"checkpoint {where} was written by another model config:\n  "
                       + "\n  ".join(differ) + "\nuse another --workdir or the matching config")
    target = {"params": state.params, "opt_state": state.opt_state, "step": state.step}
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, target)
    try:
      item = self.manager.restore(
          step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))["state"]
    except Exception as e:
      raise ValueError(f"checkpoint {where} could not be restored ({type(e).__name__}: {e}); "
                       "it is left untouched") from None
    state = state.replace(step=item["step"], params=item["params"], opt_state=item["opt_state"])
    return state, int(meta["data_position"])

  def wait(self):
    """Block until every save started so far is finalised on disk."""
    self.manager.wait_until_finished()

  def close(self):
    self.manager.wait_until_finished()
    self.manager.close()


def param_fingerprint(params) -> str:
  """A short hash of the parameter tree's paths, shapes and dtypes (not the values).

  Changes when the model code renames or reshapes a layer even though its
  config did not change, so such a checkpoint is refused by name.
  """
  leaves = jax.tree_util.tree_flatten_with_path(params)[0]
  desc = ";".join(f"{jax.tree_util.keystr(path)}:{tuple(x.shape)}:{jnp.dtype(x.dtype).name}"
                  for path, x in leaves)
  return hashlib.sha256(desc.encode()).hexdigest()[:16]


def run_signature(mcfg, params, optim: OptimConfig, weights: losses.LossWeights, batch_size: int,
                  seed: int) -> str:
  """What a checkpoint must have been trained with to be resumed or restored.

  The model config (:func:`~nlosjax.train.config_record.model_record`, field by field), the
  parameter tree (:func:`param_fingerprint`), the
  optimiser, the loss weights (:meth:`~nlosjax.losses.LossWeights.to_dict`:
  a weight added later is absent at its default, so older checkpoints still
  resume), the batch size and the seed, as sorted JSON.
  """
  return json.dumps({"model": model_record(mcfg), "params": param_fingerprint(params),
                     "optim": dataclasses.asdict(optim), "loss": weights.to_dict(),
                     "batch_size": int(batch_size), "seed": int(seed)}, sort_keys=True)


def signature_differences(recorded, signature: str, model=None) -> list[str]:
  """What keeps a checkpoint's recorded signature from matching ``signature`` (empty: it matches).

  ``recorded`` and ``signature``: run signatures (JSON text). With ``model``,
  the ``"model"`` entries are matched by :func:`nlosjax.train.config_record.compare`
  (a record or, from older checkpoints, a ``repr`` string); every other entry
  must be equal. One line per difference.
  """
  if recorded == signature:
    return []
  try:
    rec, mine = json.loads(recorded), json.loads(signature)
  except (TypeError, json.JSONDecodeError):
    rec = mine = None
  if not isinstance(rec, dict) or not isinstance(mine, dict):
    return [f"checkpoint: {recorded}", f"this run:   {signature}"]
  out = []
  for key in sorted(set(rec) | set(mine)):
    if key == "model" and model is not None and key in rec:
      try:
        out += [f"model.{d}" for d in compare_model(rec[key], model)[0]]
      except ValueError as e:
        out.append(f"model: {e}")
    elif rec.get(key) != mine.get(key):
      out.append(f"{key}: {rec.get(key)!r} in the checkpoint, {mine.get(key)!r} in this run")
  return out

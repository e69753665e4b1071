"""Checkpoints: orbax saves of a train state that refuse another run's, and the run signature they carry."""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import hashlib
import json
import logging
import os
import pathlib
import sys
import threading
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from nlosjax import files, losses
from nlosjax.train.config_record import compare as compare_model
from nlosjax.train.config_record import model_record
from nlosjax.train.optimizer import OptimConfig
from nlosjax.train.state import TrainState

#: Set (to anything but ``0``) to let orbax's own logging and tracebacks through (they are kept
#: out of what a user sees when a damaged checkpoint is tried).
DEBUG_ENV = "NLOSJAX_DEBUG"
#: Suffix of a checkpoint folder set aside because it does not restore (``checkpoints/200.damaged``).
DAMAGED_SUFFIX = ".damaged"


class CheckpointDamaged(ValueError):
  """A checkpoint of this run that cannot be restored: unreadable, truncated, or its arrays changed.

  Attributes: ``where`` (the step folder), ``step``, ``reason`` (one line).
  """

  def __init__(self, where, step: int, reason: str):
    self.where, self.step, self.reason = pathlib.Path(where), int(step), reason
    super().__init__(f"checkpoint {where} could not be restored ({reason}); it is left untouched")


def debugging() -> bool:
  """Whether :data:`DEBUG_ENV` asks for the libraries' own tracebacks."""
  return os.environ.get(DEBUG_ENV, "0") not in ("", "0")


@contextlib.contextmanager
def quiet_orbax():
  """Keep orbax's noise about a damaged checkpoint out of what a user sees.

  A failed restore leaves orbax's asyncio loop closed under pending TensorStore reads: their
  callbacks print "Event loop is closed" tracebacks from other threads, un-awaited coroutines
  print "Exception ignored in" blocks when collected, and orbax logs the whole TensorStore spec.
  Inside this context those go nowhere (absl's log below CRITICAL, the unraisable and thread
  exception hooks swapped); the error itself still reaches the caller. With :data:`DEBUG_ENV`
  set nothing is hidden.
  """
  if debugging():
    yield
    return
  absl = logging.getLogger("absl")
  level = absl.level
  hooks = sys.unraisablehook, threading.excepthook
  caught = []
  absl.setLevel(logging.CRITICAL)
  sys.unraisablehook = caught.append
  threading.excepthook = caught.append
  failed = False
  try:
    yield
  except BaseException:
    failed = True
    raise
  finally:
    if failed or caught:               # let the abandoned reads finish while nothing prints
      gc.collect()
      time.sleep(0.2)
      gc.collect()
    sys.unraisablehook, threading.excepthook = hooks
    absl.setLevel(level)


def short_error(error: BaseException, limit: int = 240) -> str:
  """One line of an orbax / TensorStore error: no spec dump, at most ``limit`` characters."""
  text = " ".join(str(error).split())
  for cut in (" [tensorstore_spec", "; tensorstore_spec", " See full TensorStore details"):
    text = text.split(cut)[0]
  text = f"{type(error).__name__}: {text}" if text else type(error).__name__
  if len(text) > limit:              # TensorStore nests "A: B: C: D": keep the kind and the innermost cause
    parts = text.split(": ")
    text = ": ".join(parts[:2] + ["..."] + parts[-1:]) if len(parts) > 3 else text
  return text if len(text) <= limit else text[:limit - 3] + "..."


def tree_digest(tree) -> str | None:
  """SHA-256 (16 hex characters) of a tree's leaves: paths, dtypes, shapes and bytes.

  Recorded with each checkpoint and checked on restore: a flipped bit in orbax's array files
  (which carry no checksum) would otherwise restore silently. None where a leaf is neither
  on this host nor replicated (nothing to compare then).
  """
  h = hashlib.sha256()
  for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
    if isinstance(leaf, jax.Array) and not leaf.is_fully_addressable:
      if not leaf.is_fully_replicated:
        return None
      leaf = leaf.addressable_data(0)
    a = np.ascontiguousarray(np.asarray(leaf))
    h.update(f"{jax.tree_util.keystr(path)}|{a.dtype.str}|{a.shape}\n".encode())
    h.update(a.tobytes())
  return h.hexdigest()[:16]


class Checkpointer:
  """orbax ``CheckpointManager`` for a :class:`TrainState` plus JSON metadata.

  Each save writes ``{"params", "opt_state", "step"}`` (``StandardSave``) and
  ``{"data_position", "model_config", "digest", "params_digest"}`` (``JsonSave``; the
  digests are :func:`tree_digest` of the arrays and of the parameters alone) to a new step
  folder; orbax finalises a folder atomically, so a kill mid-save leaves the previous
  checkpoints intact.
  :meth:`restore` refuses a checkpoint whose model config differs and reports a damaged
  one (unreadable, truncated, or arrays that no longer match their digest) by name as
  :class:`CheckpointDamaged`; :meth:`restore_latest` then goes back to the newest
  checkpoint that restores, setting the newer damaged ones aside (renamed, never deleted).
  Writes that fail (a full disk, a read-only folder) raise :class:`nlosjax.files.FileFault`
  naming the folder.

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
    self._options = ocp.CheckpointManagerOptions(max_to_keep=keep, save_interval_steps=1, create=True)
    with files.writing(self.directory), quiet_orbax():
      self.manager = ocp.CheckpointManager(self.directory, options=self._options)

  def latest_step(self) -> int | None:
    with quiet_orbax():
      return self.manager.latest_step()

  def save(self, state: TrainState, data_position: int, *, force: bool = False) -> bool:
    step = int(state.step)
    if not force and (step % self.every):
      return False
    ocp = self._ocp
    item = {"params": state.params, "opt_state": state.opt_state, "step": state.step}
    meta = {"data_position": int(data_position), "model_config": self.model_config,
            "digest": tree_digest(item), "params_digest": tree_digest(item["params"])}
    nbytes = sum(int(np.size(x)) * np.asarray(x).dtype.itemsize if not hasattr(x, "dtype")
                 else int(np.size(x)) * jnp.dtype(x.dtype).itemsize for x in jax.tree.leaves(item))
    with self._writing(self.directory / str(step)):
      self.manager.wait_until_finished()        # the previous save's errors surface here, named
      # orbax reports a full disk or a read-only folder from its threads, in TensorStore's words,
      # after printing tracebacks: find out first, in one clean OSError.
      files.probe_space(self.directory, int(nbytes * 1.1) + (1 << 20))
      self.manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(item),
                                                       meta=ocp.args.JsonSave(meta)), force=force)
    return True

  @contextlib.contextmanager
  def _writing(self, where):
    """:func:`nlosjax.files.writing`, also for orbax's errors that carry an OS error code."""
    try:
      with files.writing(where):
        yield
    except files.FileFault:
      raise
    except Exception as e:  # noqa: BLE001 - TensorStore raises ValueError with the OS error code in it
      number = files.fault_errno(e)
      if number is None:
        raise
      raise files.FileFault(where, f"{where}: {os.strerror(number)} (writing a checkpoint); "
                                   f"{files.what_to_do(number)}", number) from e

  def all_steps(self) -> list[int]:
    """Steps of the kept checkpoints, ascending."""
    with quiet_orbax():
      return sorted(self.manager.all_steps())

  def restore_latest(self, state: TrainState,
                     log: Callable[[str], None] | None = None) -> tuple[TrainState, int] | None:
    """``(state, data_position)`` from the newest checkpoint that restores, or None when there is none.

    A newer checkpoint that does not restore (:class:`CheckpointDamaged`: a truncated or
    corrupted file, a kill that left it unreadable) is skipped where an older one restores:
    each skipped folder is renamed ``<step>.damaged`` beside the others (kept for a look,
    out of orbax's way, so training writes that step afresh) and ``log`` says which and why.

    Raises:
      ValueError: a checkpoint written by another model config (nothing is skipped for that),
        or none of the checkpoints restores (each named with its reason; all left untouched).
    """
    steps = sorted(self.all_steps(), reverse=True)
    if not steps:
      return None
    skipped = []
    for step in steps:
      try:
        restored = self.restore(state, step)
      except CheckpointDamaged as e:
        skipped.append(e)
        continue
      for bad in skipped:
        aside = self._set_aside(bad.where)
        if log is not None:
          log(f"checkpoint {bad.where} skipped: it does not restore ({bad.reason}); set aside as "
              f"{aside.name}; resuming from step {step}")
      return restored
    reasons = "; ".join(f"step {e.step}: {e.reason}" for e in skipped)
    raise ValueError(f"no checkpoint under {self.directory} restores ({reasons}); they are left "
                     "untouched: move the folder away to train from step 0")

  def _set_aside(self, where: pathlib.Path) -> pathlib.Path:
    """Rename a damaged step folder out of orbax's way (``<step>.damaged``, ``<step>.damaged-2``, ...)."""
    aside = where.with_name(where.name + DAMAGED_SUFFIX)
    n = 1
    while aside.exists():
      n += 1
      aside = where.with_name(f"{where.name}{DAMAGED_SUFFIX}-{n}")
    with files.writing(where):
      os.replace(where, aside)
    with quiet_orbax():
      self.manager.reload()
    return aside

  def restore(self, state: TrainState, step: int) -> tuple[TrainState, int]:
    """``(state, data_position)`` from the checkpoint of ``step``.

    Raises:
      CheckpointDamaged: the checkpoint is unreadable, does not restore, or its arrays differ
        from the digest recorded when it was saved.
      ValueError: no checkpoint of ``step``, or one written by another model config.
    """
    ocp = self._ocp
    if step not in self.all_steps():
      raise ValueError(f"{self.directory}: no checkpoint of step {step} (kept: {self.all_steps()})")
    where = self.directory / str(step)
    try:
      with quiet_orbax():
        meta = self.manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
      if not isinstance(meta, dict) or "data_position" not in meta:
        raise ValueError(f"its metadata is not a checkpoint's: {str(meta)[:80]!r}")
    except Exception as e:  # orbax raises many types for a damaged folder
      raise CheckpointDamaged(where, step, f"metadata unreadable: {short_error(e)}") from None
    differ = signature_differences(meta.get("model_config"), self.model_config, self.model)
    if differ:
      raise ValueError(f"checkpoint {where} was written by another model config:\n  "
                       + "\n  ".join(differ) + "\nuse another --workdir or the matching config")
    target = {"params": state.params, "opt_state": state.opt_state, "step": state.step}
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, target)
    try:
      with quiet_orbax():
        item = self.manager.restore(
            step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))["state"]
    except Exception as e:
      raise CheckpointDamaged(where, step, short_error(e)) from None
    recorded = meta.get("digest")
    if recorded is not None:
      digest = tree_digest(item)
      if digest is not None and digest != recorded:
        raise CheckpointDamaged(where, step, f"its arrays do not match the digest saved with them "
                                             f"({digest}, saved {recorded})")
    state = state.replace(step=item["step"], params=item["params"], opt_state=item["opt_state"])
    return state, int(meta["data_position"])

  def wait(self):
    """Block until every save started so far is finalised on disk."""
    with self._writing(self.directory):
      self.manager.wait_until_finished()

  def close(self):
    with self._writing(self.directory):
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

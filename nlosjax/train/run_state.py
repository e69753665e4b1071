"""A training run's resumable state as a small folder that can be committed, and training that pauses.

A model folder of a run (``workdir/<variant>``) holds orbax checkpoints that are
tied to the machine's paths and too bulky to commit. :class:`StateExport` mirrors
what a resume needs into a folder of its own, rewritten at every checkpoint:

* ``state.npz``: the latest train state, every leaf of ``{"params", "opt_state",
  "step"}`` under its tree path (``jax.tree_util.keystr``), exact float32 values;
* ``best.npz``: under the plateau rule, the best state on validation so far;
* once the run has finished, ``params.npz`` instead of both: the parameters it chose (the
  best on validation, or the selected or last step) and their step, nothing to resume from
  (:func:`finish_export`);
* ``validation_curve.json``, ``metrics.jsonl``, ``selection.json``: copies of the
  model folder's files (the plateau rule's state is its curve);
* ``run_state.json``: the step, the best step, the run signature
  (:func:`~nlosjax.train.checkpoint.run_signature`), the training data's content
  digest (:func:`nlosjax.data.dataset.dataset_digest`) and when it was written;
* ``data_fingerprint.json``: the training data summarised so that float rounding
  leaves it within tolerance (:func:`nlosjax.data.dataset.dataset_fingerprint`).

Data regenerated from their spec on another CPU model round differently (XLA:CPU's
vector width), so their digest differs. A resume is taken when the digest matches, or
when the fingerprint is within :data:`~nlosjax.data.dataset.FINGERPRINT_RTOL` of the
recorded one (the same data, rounded otherwise: the log says by how much); other data
are refused unless ``allow_data_change``.

The loader's position is the step (:meth:`~nlosjax.data.dataset.TripletLoader.batch`
is a function of the step) and the step's PRNG key is folded in from the run's seed,
so these files are the whole state: for a model with about 20k parameters (the ``cpu``
and ``real`` presets) a folder is under 1 MB. :func:`nlosjax.train.train_model` with
``export=StateExport(folder)`` resumes from the folder when it is ahead of the
workdir (a fresh clone, a new machine), refuses it when its signature or data digest
differ, and pauses cleanly at ``deadline`` (:class:`TrainingPaused`) after writing it.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import pathlib
import shutil
import time
from typing import NamedTuple

import jax
import numpy as np

from nlosjax.data.dataset import fingerprint_differences, fingerprint_distance
from nlosjax.train.checkpoint import signature_differences

STATE_FILE = "state.npz"
BEST_FILE = "best.npz"
#: A finished run's export keeps the chosen parameters alone (``{"params", "step"}``).
PARAMS_FILE = "params.npz"
META_FILE = "run_state.json"
FINGERPRINT_FILE = "data_fingerprint.json"
#: The model folder's files mirrored into the export (those present).
COPIED = ("validation_curve.json", "metrics.jsonl", "selection.json")


class TrainingPaused(Exception):
  """Training stopped at its deadline after saving and exporting step ``step`` (resume with the same command)."""

  def __init__(self, variant: str, step: int, directory):
    self.variant, self.step, self.directory = variant, int(step), directory
    super().__init__(f"[{variant}] paused at step {step}; its state is in {directory}")


@dataclasses.dataclass(frozen=True)
class StateExport:
  """Where and how a run's resumable state is mirrored (module docstring).

  Attributes:
    directory: the export root; each model folder of the run gets a sub-folder
      of the same name (``directory/ours``, ``directory/ours_s-seed1``, ...).
    data_digest: the training data's content digest, recorded and, on resume,
      required to match (None: not checked) unless ``data_fingerprint`` is within rounding.
    data_fingerprint: the training data's :func:`~nlosjax.data.dataset.dataset_fingerprint`,
      recorded and, on resume where the digest differs, required within rounding of the
      recorded one (None: not recorded, and a differing digest is refused).
    deadline: ``time.time()`` after which training saves, exports and raises
      :class:`TrainingPaused` at the end of the current step (None: never).
    allow_data_change: resume even when the data digest differs (the run record says so).
  """

  directory: pathlib.Path
  data_digest: str | None = None
  data_fingerprint: dict | None = None
  deadline: float | None = None
  allow_data_change: bool = False

  def __post_init__(self):
    object.__setattr__(self, "directory", pathlib.Path(self.directory))

  def folder(self, name: str) -> pathlib.Path:
    return self.directory / name

  def past_deadline(self) -> bool:
    return self.deadline is not None and time.time() >= self.deadline


def tree_arrays(tree) -> dict[str, np.ndarray]:
  """``{keystr(path): array}`` of every leaf of ``tree`` (host copies, dtypes kept)."""
  leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
  return {jax.tree_util.keystr(path): np.array(leaf, copy=True) for path, leaf in leaves}


def arrays_tree(arrays, template):
  """``template``'s tree with each leaf replaced by ``arrays[keystr(path)]`` (same shape and dtype).

  A leaf that is a ``jax.Array`` in ``template`` comes back on the same sharding.

  Raises ValueError naming the first leaf that is missing, extra or of another shape or dtype.
  """
  leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
  names = [jax.tree_util.keystr(path) for path, _ in leaves]
  extra = sorted(set(arrays) - set(names))
  if extra:
    raise ValueError(f"exported state has leaves this model lacks: {extra[:5]}")
  out = []
  for name, (_, leaf) in zip(names, leaves):
    if name not in arrays:
      raise ValueError(f"exported state lacks the leaf {name}")
    a = np.asarray(arrays[name])
    if a.shape != tuple(np.shape(leaf)) or a.dtype != np.asarray(leaf).dtype:
      raise ValueError(f"exported leaf {name}: {a.dtype}{list(a.shape)}, the model has "
                       f"{np.asarray(leaf).dtype}{list(np.shape(leaf))}")
    # On the template's devices and sharding, so a jitted step that donates its state takes it as it is.
    out.append(jax.device_put(a, leaf.sharding) if isinstance(leaf, jax.Array) else a)
  return jax.tree_util.tree_unflatten(treedef, out)


def _state_tree(state) -> dict:
  return {"params": state.params, "opt_state": state.opt_state, "step": state.step}


def _save_npz(path: pathlib.Path, state) -> None:
  tmp = path.with_name(path.name + ".tmp.npz")
  np.savez(tmp, **tree_arrays(_state_tree(state)))
  os.replace(tmp, path)


def _load_npz(path: pathlib.Path, template):
  with np.load(path, allow_pickle=False) as f:
    item = arrays_tree(dict(f), _state_tree(template))
  return template.replace(step=item["step"], params=item["params"], opt_state=item["opt_state"])


def _save_params(path: pathlib.Path, arrays: dict) -> None:
  """Write the ``['params']...`` and ``['step']`` leaves of ``arrays`` (keystr names) to ``path``, atomically."""
  tmp = path.with_name(path.name + ".tmp.npz")
  np.savez(tmp, **{k: v for k, v in arrays.items() if k.startswith("['params']") or k == "['step']"})
  os.replace(tmp, path)


def _load_params(path: pathlib.Path, template):
  """``template`` with the parameters and step of a :data:`PARAMS_FILE` (its optimiser state kept)."""
  with np.load(path, allow_pickle=False) as f:
    item = arrays_tree(dict(f), {"params": template.params, "step": template.step})
  return template.replace(step=item["step"], params=item["params"])


def _write_json(path: pathlib.Path, obj) -> None:
  tmp = path.with_name(path.name + ".tmp")
  tmp.write_text(json.dumps(obj, indent=1, sort_keys=True) + "\n")
  os.replace(tmp, path)


def read_meta(folder) -> dict | None:
  """An exported model folder's ``run_state.json``, or None when it has none."""
  path = pathlib.Path(folder) / META_FILE
  return json.loads(path.read_text()) if path.exists() else None


def export_state(folder, model_dir, state, *, signature: str, best=None, best_step: int | None = None,
                 data_digest: str | None = None, data_fingerprint: dict | None = None, chosen=None) -> dict:
  """Write ``state`` (and ``best``) with the model folder's logs to ``folder``; returns the metadata.

  Args:
    folder: the export folder of one model (created).
    model_dir: the run's model folder whose :data:`COPIED` files are mirrored.
    state: the train state just checkpointed.
    signature: the run signature the state was trained under.
    best: the best state on validation (plateau rule), written when its step is
      not the one already exported; None keeps an existing ``best.npz`` (whose
      step must then be ``best_step``).
    best_step: the step of the best state (None: no validation yet).
    data_digest: the training data's content digest.
    data_fingerprint: the training data's fingerprint (written as :data:`FINGERPRINT_FILE`
      when given and not already there with the same content).
    chosen: the run has finished and returns this state (the best on validation, or the step
      selected): the folder then keeps its parameters alone (:data:`PARAMS_FILE`), and
      ``state.npz`` and ``best.npz`` go (:func:`finish_export`).
  The metadata file is written last, so a kill leaves the previous export readable
  (its ``state.npz`` may then be newer than its metadata: the metadata's step is read
  back from the arrays on import, and a mismatch is refused).
  """
  folder = pathlib.Path(folder)
  model_dir = pathlib.Path(model_dir)
  folder.mkdir(parents=True, exist_ok=True)
  previous = read_meta(folder) or {}
  if chosen is not None:
    _save_params(folder / PARAMS_FILE, tree_arrays({"params": chosen.params, "step": chosen.step}))
  else:
    _save_npz(folder / STATE_FILE, state)
    if best_step is not None and (best is not None) and previous.get("best_step") != best_step:
      _save_npz(folder / BEST_FILE, best)
    elif best_step is not None and previous.get("best_step") != best_step:
      raise ValueError(f"export_state: best step {best_step} is new but no best state was given")
  for name in COPIED:
    src = model_dir / name
    if src.exists():
      tmp = folder / (name + ".tmp")
      shutil.copyfile(src, tmp)
      os.replace(tmp, folder / name)
  if data_fingerprint is not None and read_fingerprint(folder) != data_fingerprint:
    _write_json(folder / FINGERPRINT_FILE, data_fingerprint)
  meta = {"step": int(state.step), "best_step": None if best_step is None else int(best_step),
          "signature": json.loads(signature), "data_digest": data_digest,
          "written": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
  if chosen is not None:
    meta.update(finished=True, chosen_step=int(chosen.step))
  _write_json(folder / META_FILE, meta)
  if chosen is not None:
    for name in (STATE_FILE, BEST_FILE):
      (folder / name).unlink(missing_ok=True)
  return meta


def finish_export(folder) -> dict:
  """Turn a finished run's export into what it still needs; returns the new metadata.

  Keeps the chosen parameters and their step (:data:`PARAMS_FILE`: the best state's under the
  plateau rule, else the last state's), the logs, the data fingerprint and the metadata
  (``finished``, ``chosen_step``); deletes ``state.npz`` and ``best.npz``, whose optimiser
  state only a resume would read. A folder already finished is left as it is.

  Raises:
    ValueError: the folder is no export, or its run has not finished (no ``selection.json``
      with a stop reason or a selection of the last step).
  """
  folder = pathlib.Path(folder)
  meta = read_meta(folder)
  if meta is None:
    raise ValueError(f"{folder} has no {META_FILE}: not an exported run state")
  if meta.get("finished"):
    return meta
  selection = json.loads((folder / "selection.json").read_text()) if (folder / "selection.json").exists() else {}
  if "stop_reason" in selection:
    source, step = BEST_FILE, meta.get("best_step")
  elif selection.get("select") == "last":
    source, step = STATE_FILE, meta["step"]
  else:
    raise ValueError(f"{folder}: the run has not finished (selection.json names no stop reason or last step)")
  with np.load(folder / source, allow_pickle=False) as f:
    arrays = {k: f[k] for k in f.files}
  held = int(arrays["['step']"])
  if step is None or held != int(step):
    raise ValueError(f"{folder}: {source} holds step {held}, {META_FILE} chose {step}")
  _save_params(folder / PARAMS_FILE, arrays)
  meta = {**meta, "finished": True, "chosen_step": int(step)}
  _write_json(folder / META_FILE, meta)
  for name in (STATE_FILE, BEST_FILE):
    (folder / name).unlink(missing_ok=True)
  return meta


def read_fingerprint(folder) -> dict | None:
  """An exported model folder's recorded data fingerprint, or None when it has none."""
  path = pathlib.Path(folder) / FINGERPRINT_FILE
  return json.loads(path.read_text()) if path.exists() else None


class DataCheck(NamedTuple):
  """How :func:`check_data` accepted a run's data.

  Attributes:
    kind: ``"digest"`` (same content digest, or nothing to compare), ``"rounding"`` (digests
      differ, fingerprints within :data:`~nlosjax.data.dataset.FINGERPRINT_RTOL`) or
      ``"allowed change"`` (other data, taken because ``allow_data_change``).
    distance: with ``"rounding"``, the largest cell difference relative to its array's L1 mass
      (:func:`~nlosjax.data.dataset.fingerprint_distance`); None otherwise.
  """
  kind: str
  distance: float | None = None

  def describe(self) -> str:
    """The clause a resume's log line ends with ("" when the digest matched)."""
    if self.kind == "rounding":
      return f"; data regenerated with another rounding (fingerprint within {self.distance:.2g} of its mass)"
    return "; on other data (--allow-data-change)" if self.kind == "allowed change" else ""


def check_data(folder, meta: dict, data_digest: str | None, data_fingerprint: dict | None,
               allow_data_change: bool = False) -> DataCheck:
  """Whether this run's data are those an export was trained on; returns how that was decided.

  Returns a :class:`DataCheck`. Raises ValueError naming the digests and the fingerprint's
  differences when the data differ beyond rounding and ``allow_data_change`` is false.
  """
  recorded = meta.get("data_digest")
  if not recorded or not data_digest or recorded == data_digest:
    return DataCheck("digest")
  fingerprint = read_fingerprint(folder)
  if fingerprint is not None and data_fingerprint is not None:
    differ = fingerprint_differences(fingerprint, data_fingerprint)
    if not differ:
      return DataCheck("rounding", fingerprint_distance(fingerprint, data_fingerprint))
    why = "their fingerprints differ beyond rounding:\n  " + "\n  ".join(differ)
  elif fingerprint is None:
    why = f"the export records no data fingerprint ({FINGERPRINT_FILE}) to tell rounding from other data"
  else:
    why = "this run computed no data fingerprint to compare"
  if allow_data_change:
    return DataCheck("allowed change")
  raise ValueError(f"exported state {folder} was trained on data with content digest {recorded}, "
                   f"but this run's data have {data_digest}; pass --allow-data-change to resume on "
                   f"these data anyway. Not taken as a rounding difference: {why}")


def import_state(folder, template, *, signature: str, model=None, data_digest: str | None = None,
                 data_fingerprint: dict | None = None, allow_data_change: bool = False):
  """``(state, best or None, meta)`` from an export folder, checked against this run.

  Args:
    folder: an export folder written by :func:`export_state`.
    template: a train state of this run (structure, shapes and dtypes).
    signature: this run's signature; differences are refused as a checkpoint's are
      (:func:`~nlosjax.train.checkpoint.signature_differences`, with ``model``).
    data_digest: this run's data digest; a recorded digest that differs is
      refused unless ``data_fingerprint`` is within rounding of the recorded one
      (:func:`check_data`) or ``allow_data_change``.
    data_fingerprint: this run's data fingerprint.
  Returns the metadata with ``"data_check"`` added: how the data were accepted (a :class:`DataCheck`).
  A finished export (:func:`finish_export`) returns its chosen parameters as both: ``state`` at
  the run's last step and ``best`` at the chosen one, each with the template's optimiser state
  (a finished run is not trained further).
  Raises ValueError naming what differs.
  """
  folder = pathlib.Path(folder)
  meta = read_meta(folder)
  if meta is None:
    raise ValueError(f"{folder} has no {META_FILE}: not an exported run state")
  differ = signature_differences(json.dumps(meta["signature"], sort_keys=True), signature, model)
  if differ:
    raise ValueError(f"exported state {folder} was trained under another run signature:\n  "
                     + "\n  ".join(differ) + "\nuse another export folder or the matching config")
  meta = {**meta, "data_check": check_data(folder, meta, data_digest, data_fingerprint, allow_data_change)}
  if meta.get("finished"):            # the chosen parameters alone; the template's optimiser state
    chosen = _load_params(folder / PARAMS_FILE, template)
    if int(chosen.step) != int(meta["chosen_step"]):
      raise ValueError(f"{folder}: {PARAMS_FILE} holds step {int(chosen.step)}, {META_FILE} says "
                       f"{meta['chosen_step']}")
    return chosen.replace(step=jax.numpy.asarray(meta["step"], chosen.step.dtype)), chosen, meta
  state = _load_npz(folder / STATE_FILE, template)
  if int(state.step) != int(meta["step"]):
    raise ValueError(f"{folder}: {STATE_FILE} holds step {int(state.step)} but {META_FILE} says "
                     f"{meta['step']} (a kill during an export); rerun from the workdir or an earlier commit")
  best = None
  if meta.get("best_step") is not None:
    best = _load_npz(folder / BEST_FILE, template)
    if int(best.step) != int(meta["best_step"]):
      raise ValueError(f"{folder}: {BEST_FILE} holds step {int(best.step)}, {META_FILE} says "
                       f"{meta['best_step']}")
  return state, best, meta


def copy_logs(folder, model_dir) -> None:
  """Copy an export's :data:`COPIED` files into ``model_dir`` (replacing the workdir's older ones)."""
  folder, model_dir = pathlib.Path(folder), pathlib.Path(model_dir)
  model_dir.mkdir(parents=True, exist_ok=True)
  for name in COPIED:
    src = folder / name
    if src.exists():
      shutil.copyfile(src, model_dir / name)

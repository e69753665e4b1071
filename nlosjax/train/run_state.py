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
import hashlib
import json
import os
import pathlib
import shutil
import time
from typing import NamedTuple

import jax
import numpy as np

from nlosjax import files
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
#: What to do about an export file that is damaged (the messages of every reader here).
RESTORE = ("restore the folder from version control (git checkout -- FOLDER) or a copy, or resume "
           "from the run's workdir")


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


def _save_arrays(path: pathlib.Path, arrays: dict) -> None:
  """``np.savez`` to a temporary file renamed over ``path``: whole or not at all (a kill, a full disk)."""
  with files.replaced(path) as tmp:
    with open(tmp, "wb") as f:
      np.savez(f, **arrays)


def _read_arrays(path: pathlib.Path) -> dict:
  """Every array of an ``.npz`` of the export; a missing, truncated or corrupted file raises ValueError naming it.

  (Each member of an ``.npz`` carries a CRC-32 that reading it checks, so a flipped bit does not
  read back silently.)
  """
  try:
    with np.load(path, allow_pickle=False) as f:
      return {k: f[k] for k in f.files}
  except FileNotFoundError:
    raise ValueError(f"{path}: missing from the exported state; {RESTORE}") from None
  except Exception as e:  # noqa: BLE001 - zipfile, numpy and the OS raise many types for a damaged file
    raise ValueError(f"{path}: not a readable .npz (truncated or corrupted: {type(e).__name__}: "
                     f"{' '.join(str(e).split())}); {RESTORE}") from None


def _save_npz(path: pathlib.Path, state) -> None:
  _save_arrays(path, tree_arrays(_state_tree(state)))


def _load_npz(path: pathlib.Path, template):
  arrays = _read_arrays(path)
  try:
    item = arrays_tree(arrays, _state_tree(template))
  except ValueError as e:
    raise ValueError(f"{path}: {e}") from None
  return template.replace(step=item["step"], params=item["params"], opt_state=item["opt_state"])


def _save_params(path: pathlib.Path, arrays: dict) -> None:
  """Write the ``['params']...`` and ``['step']`` leaves of ``arrays`` (keystr names) to ``path``, atomically."""
  _save_arrays(path, {k: v for k, v in arrays.items() if k.startswith("['params']") or k == "['step']"})


def _load_params(path: pathlib.Path, template):
  """``template`` with the parameters and step of a :data:`PARAMS_FILE` (its optimiser state kept)."""
  arrays = _read_arrays(path)
  try:
    item = arrays_tree(arrays, {"params": template.params, "step": template.step})
  except ValueError as e:
    raise ValueError(f"{path}: {e}") from None
  return template.replace(step=item["step"], params=item["params"])


def _write_json(path: pathlib.Path, obj) -> None:
  files.write_text_atomic(path, json.dumps(obj, indent=1, sort_keys=True) + "\n")


def _sha256(path: pathlib.Path) -> str:
  """SHA-256 of a file's bytes, 16 hex characters."""
  h = hashlib.sha256()
  with open(path, "rb") as f:
    for block in iter(lambda: f.read(1 << 20), b""):
      h.update(block)
  return h.hexdigest()[:16]


def _checksum(meta: dict) -> str:
  """The checksum a ``run_state.json`` carries of the rest of its content (16 hex characters)."""
  body = json.dumps({k: v for k, v in meta.items() if k != "checksum"}, sort_keys=True)
  return hashlib.sha256(body.encode()).hexdigest()[:16]


def _read_json(path: pathlib.Path):
  try:
    return json.loads(path.read_text())
  except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
    raise ValueError(f"{path}: not readable JSON (truncated or corrupted: {' '.join(str(e).split())}); "
                     f"{RESTORE}") from None


def read_meta(folder) -> dict | None:
  """An exported model folder's ``run_state.json``, or None when it has none.

  Raises ValueError naming the file where it is not readable JSON or does not match the
  checksum written with it (states exported before checksums existed carry none).
  """
  path = _current(folder) / META_FILE
  if not path.exists():
    return None
  meta = _read_json(path)
  if not isinstance(meta, dict) or "step" not in meta or "signature" not in meta:
    raise ValueError(f"{path}: not an exported run state's metadata; {RESTORE}")
  if "checksum" in meta and meta["checksum"] != _checksum(meta):
    raise ValueError(f"{path}: damaged: its content does not match the checksum written with it; {RESTORE}")
  return meta


def check_files(folder, meta: dict) -> None:
  """Raise ValueError naming an export file that is missing or not the one ``run_state.json`` recorded.

  ``meta["files"]`` (written since checksums existed): file name -> its SHA-256 when exported.
  """
  folder = _current(folder)
  for name, recorded in sorted((meta.get("files") or {}).items()):
    path = folder / name
    if not path.is_file():
      raise ValueError(f"{path}: missing from the exported state ({META_FILE} records it); {RESTORE}")
    if _sha256(path) != recorded:
      raise ValueError(f"{path}: not the file {META_FILE} recorded (changed or damaged since the export, "
                       f"or a kill during one); {RESTORE}")


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
  The new export is put together beside ``folder`` (``.<name>.new``: the files that do not change
  hard-linked, the others written) and swapped in by two renames, the previous folder kept as
  ``.<name>.old`` until the new one is in place. A kill or a full disk at any moment leaves a
  whole export, the previous or the new one (where a kill falls between the renames, the
  readers here take ``.<name>.old`` and the next export puts it back). ``run_state.json``
  records each file's SHA-256 and its own checksum (:func:`check_files`, :func:`read_meta`).
  """
  folder = pathlib.Path(folder)
  model_dir = pathlib.Path(model_dir)
  _recover(folder)
  try:
    previous = read_meta(folder) or {}
  except ValueError:                   # a damaged record: this export replaces it
    previous = {}
  stage = folder.with_name(f".{folder.name}.new")
  with files.writing(stage):
    if stage.exists():                 # left by an export a kill or a full disk stopped
      shutil.rmtree(stage)
    stage.mkdir(parents=True)
  try:
    _fill_stage(stage, folder, model_dir, state, signature=signature, best=best, best_step=best_step,
                data_digest=data_digest, data_fingerprint=data_fingerprint, chosen=chosen,
                previous=previous)
  except BaseException:
    shutil.rmtree(stage, ignore_errors=True)       # the previous export stays as it was
    raise
  meta = json.loads((stage / META_FILE).read_text())
  _swap(stage, folder)
  return meta


def _fill_stage(stage: pathlib.Path, folder: pathlib.Path, model_dir: pathlib.Path, state, *, signature,
                best, best_step, data_digest, data_fingerprint, chosen, previous) -> None:
  """Put the new export together in ``stage`` (:func:`export_state`)."""
  with files.writing(stage):
    if folder.is_dir():
      for p in folder.iterdir():
        if p.is_file():
          _link_or_copy(p, stage / p.name)
  if chosen is not None:
    _save_params(stage / PARAMS_FILE, tree_arrays({"params": chosen.params, "step": chosen.step}))
  else:
    _save_npz(stage / STATE_FILE, state)
    if best_step is not None and (best is not None) and previous.get("best_step") != best_step:
      _save_npz(stage / BEST_FILE, best)
    elif best_step is not None and previous.get("best_step") != best_step and not (stage / BEST_FILE).exists():
      raise ValueError(f"export_state: best step {best_step} is new but no best state was given")
  for name in COPIED:
    src = model_dir / name
    if src.exists():
      with files.replaced(stage / name) as tmp:
        shutil.copyfile(src, tmp)
  if data_fingerprint is not None and _fingerprint_or_none(stage) != data_fingerprint:
    _write_json(stage / FINGERPRINT_FILE, data_fingerprint)
  meta = {"step": int(state.step), "best_step": None if best_step is None else int(best_step),
          "signature": json.loads(signature), "data_digest": data_digest,
          "written": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
  if chosen is not None:
    meta.update(finished=True, chosen_step=int(chosen.step))
    with files.writing(stage):
      for name in (STATE_FILE, BEST_FILE):
        (stage / name).unlink(missing_ok=True)
  _seal_meta(stage, meta, kept=(PARAMS_FILE,) if chosen is not None else (STATE_FILE, BEST_FILE))
  _write_json(stage / META_FILE, meta)


def _previous_export(folder: pathlib.Path) -> pathlib.Path:
  """Where :func:`export_state` keeps the previous export while it swaps the new one in."""
  return folder.with_name(f".{folder.name}.old")


def _current(folder) -> pathlib.Path:
  """``folder``, or the previous export where a kill fell between the two renames of a swap."""
  folder = pathlib.Path(folder)
  old = _previous_export(folder)
  if not folder.exists() and (old / META_FILE).is_file():
    return old
  return folder


def _recover(folder: pathlib.Path) -> None:
  """Put back the previous export that a kill between the renames of a swap left aside."""
  old = _previous_export(folder)
  if not folder.exists() and (old / META_FILE).is_file():
    with files.writing(folder):
      os.replace(old, folder)


def _swap(stage: pathlib.Path, folder: pathlib.Path) -> None:
  """Replace ``folder`` by ``stage`` (two renames; the previous folder removed last)."""
  old = _previous_export(folder)
  with files.writing(folder):
    if folder.exists():
      shutil.rmtree(old, ignore_errors=True)
      os.replace(folder, old)
      os.replace(stage, folder)
      shutil.rmtree(old, ignore_errors=True)
    else:
      folder.parent.mkdir(parents=True, exist_ok=True)
      os.replace(stage, folder)


def _link_or_copy(src: pathlib.Path, dst: pathlib.Path) -> None:
  """A hard link (the same bytes, nothing copied), or a copy where the file system has none."""
  try:
    os.link(src, dst)
  except OSError:
    shutil.copyfile(src, dst)


def _seal_meta(folder: pathlib.Path, meta: dict, kept) -> None:
  """Add to ``meta`` the SHA-256 of each file the export keeps (``files``) and its own ``checksum``."""
  names = [n for n in (*kept, *COPIED, FINGERPRINT_FILE) if (folder / n).is_file()]
  with files.writing(folder):
    meta["files"] = {n: _sha256(folder / n) for n in names}
  meta["checksum"] = _checksum(meta)


def _fingerprint_or_none(folder: pathlib.Path) -> dict | None:
  """The recorded fingerprint, or None where it is absent or unreadable (it is then written again)."""
  try:
    return read_fingerprint(folder)
  except ValueError:
    return None


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
  _recover(folder)
  meta = read_meta(folder)
  if meta is None:
    raise ValueError(f"{folder} has no {META_FILE}: not an exported run state")
  if meta.get("finished"):
    return meta
  selection = _read_json(folder / "selection.json") if (folder / "selection.json").exists() else {}
  if "stop_reason" in selection:
    source, step = BEST_FILE, meta.get("best_step")
  elif selection.get("select") == "last":
    source, step = STATE_FILE, meta["step"]
  else:
    raise ValueError(f"{folder}: the run has not finished (selection.json names no stop reason or last step)")
  arrays = _read_arrays(folder / source)
  held = int(arrays["['step']"])
  if step is None or held != int(step):
    raise ValueError(f"{folder}: {source} holds step {held}, {META_FILE} chose {step}")
  _save_params(folder / PARAMS_FILE, arrays)
  meta = {k: v for k, v in meta.items() if k not in ("files", "checksum")}
  meta = {**meta, "finished": True, "chosen_step": int(step)}
  if "written" in meta:               # sealed as export_state seals (older folders stay as they were)
    _seal_meta(folder, meta, kept=(PARAMS_FILE,))
  _write_json(folder / META_FILE, meta)
  with files.writing(folder):
    for name in (STATE_FILE, BEST_FILE):
      (folder / name).unlink(missing_ok=True)
  return meta


def read_fingerprint(folder) -> dict | None:
  """An exported model folder's recorded data fingerprint, or None when it has none."""
  path = _current(folder) / FINGERPRINT_FILE
  return _read_json(path) if path.exists() else None


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
  folder = _current(folder)
  meta = read_meta(folder)
  if meta is None:
    raise ValueError(f"{folder} has no {META_FILE}: not an exported run state")
  differ = signature_differences(json.dumps(meta["signature"], sort_keys=True), signature, model)
  if differ:
    raise ValueError(f"exported state {folder} was trained under another run signature:\n  "
                     + "\n  ".join(differ) + "\nuse another export folder or the matching config")
  check_files(folder, meta)          # before any file's content is believed
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
  folder, model_dir = _current(folder), pathlib.Path(model_dir)
  with files.writing(model_dir):
    model_dir.mkdir(parents=True, exist_ok=True)
  for name in COPIED:
    src = folder / name
    if src.exists():
      with files.replaced(model_dir / name) as tmp:
        shutil.copyfile(src, tmp)

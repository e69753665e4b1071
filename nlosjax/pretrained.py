"""The on-disk format of trained weights shipped inside the package (``nlosjax/weights/``).

One folder per model, ``<root>/<name>-<variant>/`` (``variant``
a name of :data:`nlosjax.variants.VARIANTS`; the name has no path separator), holding:

* ``params.npz`` -- the model's parameters only (no optimiser state), one
  float32 array per leaf, keyed by the Flax parameter path joined by ``"/"``
  (``"cross_next1_0/in_proj_nb/kernel"``). Written by :func:`write_weights`
  with fixed zip timestamps and entries in sorted order, so the same
  parameters give the same bytes (and the same sha256).
* ``provenance.json`` -- where the parameters came from and how to check them
  (:func:`write_weights` documents the keys it requires): the run's whole
  config, the model config (a field-by-field record), the parameter-tree fingerprint, the
  sha256 of ``params.npz`` and the validation score recomputed at export.

This module reads and writes the two files and checks the file-level facts
(the sha256, float32 arrays, keys); :func:`nlosjax.inference.load_pretrained`
rebuilds the model and checks the parameters against it. Nothing here
imports JAX.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pathlib
import re
import shutil
import tempfile
import zipfile

import numpy as np

from nlosjax.variants import VARIANTS as _VARIANTS

#: The folder of the weights shipped with the package.
WEIGHTS_ROOT = pathlib.Path(__file__).resolve().parent / "weights"
FORMAT = "nlosjax-weights"
FORMAT_VERSION = 1
PARAMS_FILE = "params.npz"
PROVENANCE_FILE = "provenance.json"
#: The trained models a run or weights folder may hold (``nlosjax.inference`` reads them from here).
VARIANTS = tuple(_VARIANTS)
#: Keys every ``provenance.json`` must hold (:func:`write_weights` sets the first five).
REQUIRED_KEYS = ("format", "format_version", "name", "variant", "params_sha256", "config",
                 "model_config", "param_fingerprint", "validation")
#: What to do about a weights file that is missing or damaged (the readers' messages).
RESTORE = ("restore the folder from version control (git checkout -- FOLDER) or export the weights "
           "again (python -m experiments.export_weights)")
_NAME = re.compile(r"^[A-Za-z0-9_.]+(?:-[A-Za-z0-9_.]+)*$")
#: A fixed zip timestamp (the earliest zip allows): byte-identical files for identical parameters.
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def check_name(name: str) -> str:
  """``name`` if it is a valid weights name (letters, digits, ``_``, ``.``, inner ``-``), else ValueError."""
  if not isinstance(name, str) or not _NAME.match(name):
    raise ValueError(f"weights name must be letters, digits, '_', '.' or inner '-', got {name!r}")
  return name


def weights_folder(name: str, variant: str, root=None) -> pathlib.Path:
  """``<root>/<name>-<variant>`` (``root`` default :data:`WEIGHTS_ROOT`); the folder need not exist."""
  if variant not in VARIANTS:
    raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
  return pathlib.Path(WEIGHTS_ROOT if root is None else root) / f"{check_name(name)}-{variant}"


def shipped(root=None) -> list[tuple[str, str]]:
  """``(name, variant)`` of every folder under ``root`` holding both files, sorted."""
  root = pathlib.Path(WEIGHTS_ROOT if root is None else root)
  out = []
  if root.is_dir():
    for p in root.iterdir():
      name, _, variant = p.name.rpartition("-")
      if (p.is_dir() and variant in VARIANTS and name and (p / PARAMS_FILE).is_file()
          and (p / PROVENANCE_FILE).is_file()):
        out.append((name, variant))
  return sorted(out)


def flatten_params(params) -> dict[str, np.ndarray]:
  """A nested dict of arrays -> ``{"a/b/kernel": float32 array}`` (keys sorted).

  Raises:
    ValueError: a key holding ``"/"`` (the path could not be split again), a
      leaf that is not an array, or a non-float32 leaf.
  """
  flat = {}

  def walk(prefix, node):
    if isinstance(node, dict) or hasattr(node, "items") and not hasattr(node, "shape"):
      for k, v in node.items():
        k = str(k)
        if "/" in k or not k:
          raise ValueError(f"parameter key {prefix + k!r}: empty or holds '/', which joins the path")
        walk(prefix + k + "/", v)
      return
    a = np.asarray(node)
    if a.dtype != np.float32:
      raise ValueError(f"parameter {prefix[:-1]!r} is {a.dtype}, expected float32")
    flat[prefix[:-1]] = a

  walk("", params)
  return dict(sorted(flat.items()))


def unflatten_params(flat: dict) -> dict:
  """Inverse of :func:`flatten_params`: ``{"a/b/kernel": x}`` -> ``{"a": {"b": {"kernel": x}}}``."""
  out: dict = {}
  for key, value in flat.items():
    node = out
    *path, leaf = key.split("/")
    for p in path:
      node = node.setdefault(p, {})
    node[leaf] = value
  return out


def sha256_file(path) -> str:
  """Hex sha256 of a file's bytes."""
  h = hashlib.sha256()
  with open(path, "rb") as f:
    for block in iter(lambda: f.read(1 << 20), b""):
      h.update(block)
  return h.hexdigest()


def _npz_bytes(flat: dict[str, np.ndarray]) -> bytes:
  """An ``.npz`` (``np.load`` reads it) with fixed timestamps and sorted entries: deterministic bytes."""
  buf = io.BytesIO()
  with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as z:
    for key in sorted(flat):
      member = io.BytesIO()
      np.lib.format.write_array(member, np.asarray(flat[key]), allow_pickle=False)
      z.writestr(zipfile.ZipInfo(key + ".npy", date_time=_ZIP_DATE), member.getvalue())
  return buf.getvalue()


def write_weights(folder, params, provenance: dict, *, overwrite: bool = False) -> dict:
  """Write ``params.npz`` and ``provenance.json`` into ``folder``, atomically; returns the provenance written.

  Args:
    folder: ``<root>/<name>-<variant>`` (:func:`weights_folder`); its name gives
      ``name`` and ``variant``.
    params: the parameter tree (nested dict of float32 arrays).
    provenance: JSON-able dict; must hold ``config`` (the run config dict),
      ``model_config`` (:func:`nlosjax.train.model_record` of the model config;
      weights exported before records hold its ``repr``), ``param_fingerprint``
      and ``validation`` (``{"psnr_db", "per_sequence_psnr_db", ...}``); the
      ``format``, ``format_version``, ``name``, ``variant``, ``params_sha256``
      and ``num_params`` keys are set here.
    overwrite: replace an existing folder (else FileExistsError).
  Returns:
    The provenance as written.
  Raises:
    ValueError: a bad folder name, missing provenance keys or non-float32 parameters.
    FileExistsError: ``folder`` exists and ``overwrite`` is false.
  """
  folder = pathlib.Path(folder)
  name, _, variant = folder.name.rpartition("-")
  weights_folder(name, variant)                    # checks both
  missing = [k for k in REQUIRED_KEYS[5:] if k not in provenance]
  if missing:
    raise ValueError(f"{folder}: provenance lacks {missing}")
  if folder.exists() and not overwrite:
    raise FileExistsError(f"{folder}: exists; pass overwrite=True (--overwrite) to replace it")
  flat = flatten_params(params)
  data = _npz_bytes(flat)
  prov = {"format": FORMAT, "format_version": FORMAT_VERSION, "name": name, "variant": variant,
          **provenance, "params_sha256": hashlib.sha256(data).hexdigest(),
          "num_params": int(sum(a.size for a in flat.values()))}
  text = json.dumps(prov, indent=1, allow_nan=False) + "\n"
  from nlosjax import files
  with files.writing(folder):
    folder.parent.mkdir(parents=True, exist_ok=True)
    old = _previous(folder)
    if not folder.exists() and old.is_dir():     # a replacement a kill interrupted: the previous weights back
      os.replace(old, folder)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{folder.name}-", dir=folder.parent))
    try:
      (tmp / PARAMS_FILE).write_bytes(data)
      (tmp / PROVENANCE_FILE).write_text(text)
      os.chmod(tmp, 0o755)
      if folder.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(folder, old)      # a kill between these two renames: read_provenance names `old`
        os.replace(tmp, folder)
        shutil.rmtree(old, ignore_errors=True)
      else:
        os.replace(tmp, folder)
    finally:
      shutil.rmtree(tmp, ignore_errors=True)
  return prov


def _previous(folder: pathlib.Path) -> pathlib.Path:
  """Where :func:`write_weights` keeps a folder's previous weights while it replaces them."""
  return folder.with_name(f".{folder.name}.old")


def read_provenance(folder) -> dict:
  """``provenance.json`` of a weights folder, with its required keys checked (ValueError naming the file)."""
  folder = pathlib.Path(folder)
  if not folder.is_dir() and _previous(folder).is_dir():
    raise ValueError(f"{folder}: missing: a replacement of these weights was interrupted and left the "
                     f"previous ones in {_previous(folder)}; rename that folder back to {folder.name} (or "
                     "export the weights again)")
  path = folder / PROVENANCE_FILE
  try:
    prov = json.loads(path.read_text())
  except FileNotFoundError:
    raise ValueError(f"{path}: missing; {RESTORE}") from None
  except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
    raise ValueError(f"{path}: not readable JSON (truncated or damaged: {' '.join(str(e).split())});"
                     f" {RESTORE}") from None
  if not isinstance(prov, dict):
    raise ValueError(f"{path}: expected a JSON object, got {type(prov).__name__} (damaged?); {RESTORE}")
  missing = [k for k in REQUIRED_KEYS if k not in prov]
  if missing:
    raise ValueError(f"{path}: lacks {missing} (damaged or not a weights record); {RESTORE}")
  if prov["format"] != FORMAT or prov["format_version"] != FORMAT_VERSION:
    raise ValueError(f"{path}: format {prov['format']!r} version {prov['format_version']!r}; this"
                     f" nlosjax reads {FORMAT!r} version {FORMAT_VERSION}")
  return prov


def read_weights(folder) -> tuple[dict, dict]:
  """``(params, provenance)`` of a weights folder; params a nested dict of float32 NumPy arrays.

  Checks the file-level facts: ``params.npz``'s sha256 equals the provenance's
  ``params_sha256``, and every array is float32.

  Raises:
    ValueError: naming the file, for a missing or unreadable file, a sha256
      mismatch or a non-float32 array.
  """
  folder = pathlib.Path(folder)
  prov = read_provenance(folder)
  path = folder / PARAMS_FILE
  if not path.is_file():
    raise ValueError(f"{path}: missing; {RESTORE}")
  digest = sha256_file(path)
  if digest != prov["params_sha256"]:
    raise ValueError(f"{path}: sha256 {digest} differs from {prov['params_sha256']} recorded in"
                     f" {folder / PROVENANCE_FILE} (the file was changed or damaged); {RESTORE}")
  try:
    with np.load(path, allow_pickle=False) as z:
      flat = {k: z[k] for k in z.files}
  except (OSError, ValueError, zipfile.BadZipFile) as e:
    raise ValueError(f"{path}: not a readable .npz ({e}); {RESTORE}") from None
  bad = [f"{k}: {a.dtype}" for k, a in flat.items() if a.dtype != np.float32]
  if bad:
    raise ValueError(f"{path}: arrays must be float32, got {bad[:3]}")
  return unflatten_params(flat), prov

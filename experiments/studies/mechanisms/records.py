"""Run records: the code and machine a run came from, and strict-JSON reading and writing."""

from __future__ import annotations

import json
import math
import os
import pathlib

import numpy as np

#: The study's results folder: ``mechanisms.md``, its figure, and the run records under
#: ``RESULTS/mechanisms/<budget>/``.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"

_CODE_AT_START: dict = {}


def code_at_start() -> dict:
  """The commit of this process's code, read once, before its first run.

  A study runs for hours: read at the end of a run, ``git`` and the files on disk may
  already show a later commit or someone's uncommitted edits that this process never
  loaded. :func:`main` calls this first; :func:`machine` reports what it read then.
  """
  if not _CODE_AT_START:
    from experiments import provenance as P
    _CODE_AT_START.update(commit=P.git_commit())
  return dict(_CODE_AT_START)


def machine() -> dict:
  """Where and from which code a run's numbers came (:func:`experiments.provenance.machine_record`;
  the commit as at the start of the process)."""
  from experiments import provenance as P
  return {**P.machine_record(), **code_at_start()}


# --------------------------------------------------------------- JSON I/O
def _plain(x):
  """JSON-ready copy: tuples -> lists, NumPy -> Python, NaN/inf -> None (strict JSON)."""
  if isinstance(x, dict):
    return {str(k): _plain(v) for k, v in x.items()}
  if isinstance(x, (list, tuple)):
    return [_plain(v) for v in x]
  if isinstance(x, np.ndarray):
    return _plain(x.tolist())
  if isinstance(x, (np.floating, float)):
    return float(x) if math.isfinite(float(x)) else None
  if isinstance(x, np.integer):
    return int(x)
  return x


def write_json(path: pathlib.Path, obj) -> None:
  """Write ``obj`` as strict JSON, atomically (a temporary file renamed over ``path``)."""
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = path.with_name(path.name + ".tmp")
  tmp.write_text(json.dumps(_plain(obj), indent=1, allow_nan=False) + "\n")
  os.replace(tmp, path)


def load_runs(results: pathlib.Path) -> dict:
  """``(budget, row, seed) -> run record`` of every JSON file under ``RESULTS/mechanisms/``."""
  runs = {}
  for path in sorted((pathlib.Path(results) / "mechanisms").glob("*/*.json")):
    r = json.loads(path.read_text())
    runs[(r["budget"], r["row"], int(r["seed"]))] = r
  return runs


def _array(values) -> np.ndarray:
  """A JSON list (None = NaN) as float64."""
  return np.asarray([np.nan if v is None else v for v in values], np.float64)

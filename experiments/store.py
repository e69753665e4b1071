"""The store: datasets and full run folders kept outside the work tree, so a machine that keeps its disk resumes.

    $NLOSJAX_HOME            (default: $XDG_CACHE_HOME/nlosjax, else ~/.cache/nlosjax)
      data/<file>.h5         datasets, regenerated from their spec where absent
      runs/<study>/<run>/    full run folders (orbax checkpoints, logs)

Only the long-run studies (``experiments.studies.real_preset``, ``csa``) and commands told so
read it: the
README's two commands and the test suite never do, so a fresh clone still makes and
tests everything from scratch. What must survive a new machine is not here but in
the repository: each long run's small exported state
(:mod:`nlosjax.train.run_state`), committed under ``experiments/studies/<study>/state/``.
"""

from __future__ import annotations

import os
import pathlib

ENV = "NLOSJAX_HOME"


def home() -> pathlib.Path:
  """The store's root (module docstring), not created."""
  if os.environ.get(ENV):
    return pathlib.Path(os.environ[ENV]).expanduser()
  cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
  return pathlib.Path(cache) / "nlosjax"


def data_path(name: str) -> pathlib.Path:
  """``<store>/data/<name>``: where a study keeps the dataset file ``name`` (a file name, no folders)."""
  if not name or pathlib.PurePath(name).name != name:
    raise ValueError(f"a store dataset is named by a file name alone, got {name!r}")
  return home() / "data" / name


def run_path(study: str, run: str) -> pathlib.Path:
  """``<store>/runs/<study>/<run>``: a study's full run folder."""
  for what, v in (("study", study), ("run", run)):
    if not v or pathlib.PurePath(v).name != v:
      raise ValueError(f"a store {what} is named by one folder name, got {v!r}")
  return home() / "runs" / study / run

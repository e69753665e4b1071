"""Experiment presets: plain nested dicts ``{"data": {...}, "model": {...}, "train": {...}}``.

Each preset is a module here exposing ``get_config() -> dict``; :func:`get_config`
returns a fresh copy by name. ``cpu`` is the default: its whole main job
(make data, train a small model, evaluate) fits in about 20 minutes on 2 CPU
cores. ``paper`` reproduces the paper's sizes (128 x 128 full grid, every 8th
point as input, 512 bins of 33 ps, 32 frames, 150 / 16 / 17 sequences for
train / validation / test); ``real`` trains the cpu model on the geometry of the
shipped measured scans.

The ``data`` section is read by :meth:`nlosjax.data.dataset.DatasetSpec.from_config`
(generation) and by the loaders (``input_stride``, ``input_offset``,
``loader``, ``path``); see docs/dataset.md (sections "The command", "Loading" and
"Presets"). Why the presets' less obvious values are what they are: docs/decisions.md.
"""

from __future__ import annotations

import copy
import importlib

#: Preset names (modules of this package).
PRESETS = ("cpu", "paper", "real")
#: The preset used when none is named.
DEFAULT = "cpu"


def get_config(name: str = DEFAULT) -> dict:
  """A fresh (deep-copied) config dict of preset ``name``.

  Raises:
    ValueError: for an unknown preset name.
  """
  if name not in PRESETS:
    raise ValueError(f"config must be one of {PRESETS}, got {name!r}")
  module = importlib.import_module(f"{__name__}.{name}")
  return copy.deepcopy(module.get_config())

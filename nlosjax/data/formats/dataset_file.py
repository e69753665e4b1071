"""Format ``"nlosjax_dataset"``: one sequence of an nlosjax dynamic dataset file.

The HDF5 file written by :mod:`nlosjax.data.dataset` (``docs/dataset.md``;
root attribute ``format = "nlosjax-dynamic-nlos"``); the reader
returns the frames of one sequence.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nlosjax.data.formats._common import _bin_time, _frame_selection, _make_setup, _time_plan
from nlosjax.data.formats.registry import _root_format, register_format

_DATASET_FORMAT = "nlosjax-dynamic-nlos"    # nlosjax.data.dataset.FORMAT_NAME



def _read_dataset(path: Path, *, zero_bins=None, bin_factor=None, num_bins=None, frame=0,
                  split=None, sequence=None, key="measurement"):
  """Read frames of one sequence of an nlosjax dynamic dataset (``docs/dataset.md``).

  Args (beyond the shared ones):
    split: ``"train"`` or ``"test"`` (default: any split).
    sequence: a sequence name (``"test-00003"``) or an index into the
      sequences of ``split`` (sorted by name); default 0, the first.
    frame: frame(s) of the sequence (default 0).
    key: ``"measurement"`` (SPAD counts, default) or ``"clean"``.
  """
  from nlosjax.data import dataset as ds_module
  if key not in ("measurement", "clean"):
    raise ValueError(f"{path}: key must be 'measurement' or 'clean', got {key!r}")
  with ds_module.open_dataset(path) as ds:
    names = ds.names(split)
    if not names:
      raise ValueError(f"{path}: no sequence in split {split!r}")
    if sequence is None:
      name = names[0]
    elif isinstance(sequence, str):
      if sequence not in names:
        raise ValueError(f"{path}: no sequence {sequence!r}"
                         f"{'' if split is None else f' in split {split!r}'}; it has {names[:6]}"
                         f"{' ...' if len(names) > 6 else ''}")
      name = sequence
    elif isinstance(sequence, (int, np.integer)) and not isinstance(sequence, bool):
      if not -len(names) <= sequence < len(names):
        raise ValueError(f"{path}: sequence index {sequence} out of range: {len(names)} sequence(s)"
                         f"{'' if split is None else f' in split {split!r}'}")
      name = names[int(sequence)]
    else:
      raise ValueError(f"{path}: sequence must be a name or an index, got {sequence!r}")
    frames, single = _frame_selection(path, frame, ds.num_frames(name))
    raw = ds.read(name, key, frames=frames, dtype=np.float64)          # [F, T, H, W]
    setup = ds.setup
  raw_bins = setup.num_bins
  zero_bins, bin_factor, num_bins = _time_plan(path, raw_bins, zero_bins, bin_factor, num_bins)
  counts = np.moveaxis(_bin_time(np.moveaxis(raw, 1, -1), zero_bins, bin_factor, num_bins), -1, 1)
  setup = _make_setup(path, wall_size=setup.wall_size, grid=setup.grid,
                      bin_width=setup.bin_width * bin_factor, num_bins=num_bins)
  return (counts[0] if single else counts), setup


register_format(
    "nlosjax_dataset", _read_dataset, container="hdf5",
    accepts=lambda p: _root_format(p) == _DATASET_FORMAT,
    options=("frame", "split", "sequence", "key"),
    summary="HDF5 dynamic NLOS dataset written by nlosjax.data.dataset (format"
            " 'nlosjax-dynamic-nlos'): one sequence's frames")

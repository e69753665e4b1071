"""Format ``"nlost_mat"``: the NLOST captures and the aligned f-k ``final_meas``.

The captures of Li et al., "NLOST: non-line-of-sight imaging with
transformer", CVPR 2023 (public ``Depth2World/NLOST``): ``data`` ``[W, H, T]``,
read by their code with ``scipy.io.loadmat`` and ``transpose([1, 0, 2])``,
already aligned, 32 ps bins, 512 bins, 2 m x 2 m wall. Also the aligned f-k
captures that USM/NLOST distribute (``final_meas`` ``[H, W, T]``, no
transpose).
"""

from __future__ import annotations

from pathlib import Path

from nlosjax.data.formats._common import _bin_time, _check_counts, _make_setup, _MatFile, _positive_float, _time_plan
from nlosjax.data.formats.registry import _root_format, _variables, register_format

# ---------------------------------------------------------------- nlost_mat

#: Bin width of the NLOST captures (Li et al., CVPR 2023), seconds.
NLOST_BIN_WIDTH = 32e-12
#: Side of the scanned square of the NLOST captures, metres.
NLOST_WALL_SIZE = 2.0


def _read_nlost(path: Path, *, zero_bins=None, bin_factor=None, num_bins=None, wall_size=None,
                bin_width=None):
  """Read an NLOST capture (Li et al., "NLOST", CVPR 2023) or an aligned f-k ``final_meas``.

  ``data`` is ``[W, H, T]`` in MATLAB order: the NLOST evaluation code reads it
  with ``scipy.io.loadmat`` and applies ``transpose([1, 0, 2])`` before using
  it as ``[H, W, T]``; so ``transient[t, y, x] = data(x, y, t)``. The
  aligned Stanford f-k captures distributed with USM/NLOST hold
  ``final_meas`` ``[H, W, T]`` used without a transpose:
  ``transient[t, y, x] = final_meas(y, x, t)``. Both are already aligned
  (bin 0 at the wall), 32 ps bins on a 2 m x 2 m wall, usually 512 bins.
  Preparation: zero ``[0, zero_bins)`` (default 0), sum ``bin_factor`` (1),
  keep ``num_bins`` (all).

  Args (beyond the shared ones):
    wall_size: side of the scanned square, metres (default 2; not in the file).
    bin_width: native bin width, seconds (default 32 ps; not in the file).
  """
  wall = _positive_float(path, "wall_size", wall_size, NLOST_WALL_SIZE)
  native = _positive_float(path, "bin_width", bin_width, NLOST_BIN_WIDTH)
  with _MatFile(path, ("data", "final_meas")) as mf:
    name = "data" if mf.has("data") else "final_meas" if mf.has("final_meas") else None
    if name is None:
      raise ValueError(f"{path}: missing variable 'data' (or 'final_meas') of format 'nlost_mat';"
                       f" the file holds {mf.names()}")
    var = mf.get(name)
    if var.ndim != 3:
      raise ValueError(f"{path}: {name} must be rank 3 ([W, H, T] for data, [H, W, T] for"
                       f" final_meas), got rank {var.ndim} shape {var.shape}")
    raw = var[...]
  _check_counts(path, name, raw)
  if name == "data":
    raw = raw.transpose(1, 0, 2)                                 # [H, W, T]
  height, width_px, raw_bins = raw.shape
  if height < 2 or width_px < 2:
    raise ValueError(f"{path}: {name} needs at least 2 x 2 scan points, got shape {var.shape}")
  zero_bins, bin_factor, num_bins = _time_plan(path, raw_bins, zero_bins, bin_factor, num_bins)
  counts = _bin_time(raw, zero_bins, bin_factor, num_bins).transpose(2, 0, 1)
  return counts, _make_setup(path, wall_size=wall, grid=(height, width_px),
                             bin_width=native * bin_factor, num_bins=num_bins)


def _accepts_nlost(path: Path) -> bool:
  if _root_format(path) is not None:
    return False
  _, names = _variables(path)
  return "data" in names or "final_meas" in names


register_format(
    "nlost_mat", _read_nlost, container=("mat5", "hdf5"), accepts=_accepts_nlost,
    options=("wall_size", "bin_width"),
    summary="MATLAB .mat with data [W, H, T] (transposed; NLOST captures, 32 ps, 2 m wall) or"
            " final_meas [H, W, T] (aligned f-k captures)")

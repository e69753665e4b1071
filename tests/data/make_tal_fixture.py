"""Write the TAL fixtures of ``tests/test_tal.py`` with y-tal itself (not part of the suite).

Run once, in an environment of its own (y-tal pins numpy < 2 and needs pyfftw)::

    python3.11 -m venv /tmp/ytal-venv && /tmp/ytal-venv/bin/pip install y-tal==0.20.0 pyfftw
    /tmp/ytal-venv/bin/python tests/data/make_tal_fixture.py

Two tiny confocal captures, each built as a known transient in nlosjax's
convention (``[T, H, W]``, rows along y and columns along x ascending, time
bin ``k`` = round-trip path from the wall in ``[k, k + 1) * delta_t``) and
turned into TAL's layout here, by a loop over the scan points, then written
by ``tal.io.write_capture``:

* ``tal_grid.hdf5``: ``H_format`` ``T_Sx_Sy``, ``X_Y_3`` grids from
  ``tal.render.util.get_grid_xyz`` (4 x-positions, 3 y-positions, cell-centred
  as ``tal render`` lays them), ``t_accounts_first_and_last_bounces`` true
  with a laser and a SPAD off the wall and ``t_start = 1.3`` m, so each
  point's histogram starts at its own path length.
* ``tal_list.hdf5``: ``H_format`` ``T_Si``, ``N_3`` grids listing the same
  points shuffled, times from the wall (``t_accounts_first_and_last_bounces``
  false) starting at ``t_start = 0.05`` m (5 bins).

``tal_expected.npz`` holds, per file, the transient nlosjax must read back
(``<name>_transient``) and its ``wall_size`` (m) and ``bin_width`` (s).
"""

import pathlib

import numpy as np
import tal
import tal.io
from tal.enums import GridFormat, HFormat
from tal.io.capture_data import NLOSCaptureData
from tal.render.util import get_grid_xyz

HERE = pathlib.Path(__file__).resolve().parent
C = 299_792_458.0
DELTA_T = 0.01                           # metres of path per bin
RAW_BINS = 96                            # bins of TAL's H


def transient(num_bins, height, width, seed):
  """A known transient ``[T, H, W]`` in nlosjax's convention: a pulse per point plus a floor, whole counts."""
  rng = np.random.default_rng(seed)
  out = np.zeros((num_bins, height, width), np.float32)
  for r in range(height):
    for c in range(width):
      peak = 8 + 3 * r + 2 * c
      out[peak - 2:peak + 3, r, c] = [2, 6, 10, 6, 2]
      out[:, r, c] += rng.integers(0, 3, num_bins)
  return out


def capture(h, h_format, grid, grid_format, *, accounts, t_start, laser_xyz, sensor_xyz):
  data = NLOSCaptureData()
  data.H = h.astype(np.float32)
  data.H_format = h_format
  normals = np.zeros_like(grid)
  normals[..., 2] = 1.0
  data.sensor_xyz = np.asarray(sensor_xyz, np.float32)
  data.sensor_grid_xyz = grid
  data.sensor_grid_normals = normals
  data.sensor_grid_format = grid_format
  data.laser_xyz = np.asarray(laser_xyz, np.float32)
  data.laser_grid_xyz = grid.copy()
  data.laser_grid_normals = normals.copy()
  data.laser_grid_format = grid_format
  data.delta_t = DELTA_T
  data.t_start = t_start
  data.t_accounts_first_and_last_bounces = accounts
  data.scene_info = {"tal_version": tal.__version__, "note": "nlosjax test fixture"}
  return data


def main():
  expected = {}
  # 1. T_Sx_Sy, X_Y_3, times from the laser's emission.
  grid = get_grid_xyz(4, 3, 0.5, 0.5625)                         # [Sx=4, Sy=3, 3]; both span 0.75 m
  laser_xyz, sensor_xyz, t_start = (-0.4, 0.1, 0.6), (0.3, -0.2, 0.5), 1.3
  xs, ys = np.unique(grid[..., 0]), np.unique(grid[..., 1])
  shifts = {}
  for ix in range(4):
    for iy in range(3):
      p = grid[ix, iy].astype(np.float64)
      legs = (np.linalg.norm(p - np.asarray(laser_xyz, np.float32))          # positions as the file stores them
              + np.linalg.norm(p - np.asarray(sensor_xyz, np.float32)))
      shifts[ix, iy] = int(np.floor((t_start - legs) / DELTA_T + 0.5))   # TAL bin i = our bin i + shift
  num_bins = max(RAW_BINS + s for s in shifts.values())
  ours = transient(num_bins, 3, 4, seed=1)
  h = np.zeros((RAW_BINS, 4, 3), np.float32)
  for (ix, iy), s in shifts.items():
    r, c = int(np.searchsorted(ys, grid[ix, iy, 1])), int(np.searchsorted(xs, grid[ix, iy, 0]))
    for i in range(RAW_BINS):
      if 0 <= i + s < num_bins:
        h[i, ix, iy] = ours[i + s, r, c]
    ours[:max(0, s), r, c] = 0                                    # before this point's first bin: not recorded
    ours[max(0, RAW_BINS + s):, r, c] = 0                             # after its last bin: not recorded
  tal.io.write_capture(str(HERE / "tal_grid.hdf5"),
                       capture(h, HFormat.T_Sx_Sy, grid, GridFormat.X_Y_3, accounts=True, t_start=t_start,
                               laser_xyz=laser_xyz, sensor_xyz=sensor_xyz))
  expected.update(grid_transient=ours, grid_wall_size=np.float64(xs[-1] - xs[0]),
                  grid_bin_width=np.float64(DELTA_T / C))

  # 2. T_Si, N_3 (the points shuffled), times from the wall, recording from 5 bins on.
  t_start, start_bins = 0.05, 5
  points = grid.reshape(-1, 3)[np.random.default_rng(2).permutation(12)]
  ours = transient(RAW_BINS + start_bins, 3, 4, seed=3)
  ours[:start_bins] = 0
  h = np.zeros((RAW_BINS, 12), np.float32)
  for i_s, p in enumerate(points):
    r, c = int(np.searchsorted(ys, p[1])), int(np.searchsorted(xs, p[0]))
    h[:, i_s] = ours[start_bins:, r, c]
  tal.io.write_capture(str(HERE / "tal_list.hdf5"),
                       capture(h, HFormat.T_Si, points, GridFormat.N_3, accounts=False, t_start=t_start,
                               laser_xyz=laser_xyz, sensor_xyz=sensor_xyz))
  expected.update(list_transient=ours, list_wall_size=np.float64(xs[-1] - xs[0]),
                  list_bin_width=np.float64(DELTA_T / C))
  np.savez_compressed(HERE / "tal_expected.npz", **expected)
  for name in ("tal_grid.hdf5", "tal_list.hdf5"):                # y-tal reads back what it wrote
    data = tal.io.read_capture(str(HERE / name))
    assert data.is_confocal(), name
    print(name, data.H_format, data.H.shape, (HERE / name).stat().st_size, "bytes")


if __name__ == "__main__":
  main()

"""TAL (y-tal) HDF5 captures: ``load_measurement`` reads them, ``save_tal`` writes them.

Each check compares against something the reader does not compute itself:
captures hand-built here with h5py in TAL's layout (the fields as
``tal.io.write_capture`` writes them) from a known transient, expected
transients from brute-force loops over scan points and bins, and two files
written by y-tal itself (``tests/data/tal_*.hdf5``, made by
``tests/data/make_tal_fixture.py`` in a y-tal environment, with the
transients they hold in ``tests/data/tal_expected.npz``). The suite needs no
y-tal: the one check that runs y-tal's own reader on our files runs only
where ``NLOSJAX_YTAL_PYTHON`` names a Python with y-tal installed.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import subprocess

import h5py
import numpy as np
import pytest

from nlosjax.data import io
from nlosjax.physics.setup import SPEED_OF_LIGHT, Setup

DATA = pathlib.Path(__file__).resolve().parent / "data"
#: TAL's enum values (tal.enums.HFormat, tal.enums.GridFormat), spelled out here.
H_FORMAT = {"T_Sx_Sy": 1, "T_Lx_Ly_Sx_Sy": 2, "T_Si": 3, "T_Li_Si": 4, "F_Sx_Sy": 10}
GRID_FORMAT = {"N_3": 1, "X_Y_3": 2}
DELTA_T = 0.012                                       # metres of path per bin
#: The fields of y-tal's NLOSCaptureData (tal/io/capture_data.py), the only names read_capture accepts.
NLOS_CAPTURE_DATA_FIELDS = {"H", "H_format", "sensor_xyz", "sensor_grid_xyz", "sensor_grid_normals",
                            "sensor_grid_format", "laser_xyz", "laser_grid_xyz", "laser_grid_normals",
                            "laser_grid_format", "volume_format", "delta_t", "t_start",
                            "t_accounts_first_and_last_bounces", "scene_info"}


def write_tal(path, h, h_format, sensor, *, laser=None, grid_format=None, delta_t=DELTA_T, t_start=0.0,
              accounts=False, laser_xyz=(0.0, 0.0, 0.0), sensor_xyz=(0.0, 0.0, 0.0), enums="enum"):
  """A TAL capture written field by field as ``tal.io.write_capture`` does (``None``: an empty field)."""
  laser = sensor if laser is None else laser
  grid_format = grid_format or ("X_Y_3" if np.ndim(sensor) == 3 else "N_3")
  with h5py.File(path, "w") as f:
    def enum(key, names, name):
      if enums == "int":
        f[key] = np.int64(names[name])
        return
      ds = f.create_dataset(key, (1,), dtype=h5py.enum_dtype(names, basetype="i"))
      ds[0] = names[name]

    def value(key, v):
      f[key] = h5py.Empty("f8") if v is None else v

    value("H", h)
    enum("H_format", H_FORMAT, h_format)
    for role, grid, origin in (("sensor", sensor, sensor_xyz), ("laser", laser, laser_xyz)):
      value(f"{role}_xyz", None if origin is None else np.asarray(origin, np.float32))
      value(f"{role}_grid_xyz", np.asarray(grid, np.float32))
      value(f"{role}_grid_normals", np.broadcast_to(np.float32([0, 0, 1]), np.shape(grid)))
      enum(f"{role}_grid_format", GRID_FORMAT, grid_format)
    value("volume_format", None)
    value("delta_t", delta_t)
    value("t_start", t_start)
    value("t_accounts_first_and_last_bounces", None if accounts is None else bool(accounts))
    f["scene_info"] = "{original_format: HDF5_TAL}"
  return path


def known_transient(num_bins, height, width, seed=0):
  """Counts that differ at every (bin, row, column)."""
  return np.random.default_rng(seed).integers(0, 1000, (num_bins, height, width)).astype(np.float32)


def axes(height, width, wall=0.6):
  """x (columns) and y (rows) positions of a grid spanning ``wall`` m both ways, off the origin."""
  return np.linspace(-wall / 2, wall / 2, width) + 0.2, np.linspace(-wall / 2, wall / 2, height) - 0.1


# ------------------------------------------------------------------ round trip

@pytest.mark.parametrize("grid", [(4, 5), (8, 8)])
@pytest.mark.parametrize("layout", ["T_Sx_Sy", "T_Si"])
def test_round_trip_ours_to_tal_to_ours_is_exact(tmp_path, layout, grid):
  setup = Setup(wall_size=0.8, grid=grid, bin_width=32e-12, num_bins=24)
  transient = known_transient(24, *grid)
  path = io.save_tal(tmp_path / "c.hdf5", transient, setup, layout=layout)
  assert io.detect_format(path) == "tal"
  back, read = io.load_measurement(path)
  np.testing.assert_array_equal(back, transient)
  assert read == setup                     # wall_size and bin_width bit for bit too


def test_writer_writes_tal_fields_in_tal_layout(tmp_path):
  """The file, read with h5py alone: TAL's names, enums, axes, positions and units."""
  setup = Setup(wall_size=0.8, grid=(3, 4), bin_width=16e-12, num_bins=10)
  transient = known_transient(10, 3, 4)
  path = io.save_tal(tmp_path / "c.hdf5", transient, setup, sensor_xyz=(0.1, 0.2, 0.3))
  with h5py.File(path, "r") as f:
    assert set(f) <= NLOS_CAPTURE_DATA_FIELDS                      # read_capture refuses any other name
    h = f["H"][()]
    assert h.shape == (10, 4, 3)                                   # [T, Sx, Sy]: x first
    for t in range(10):
      for r in range(3):
        for c in range(4):
          assert h[t, c, r] == transient[t, r, c]
    grid = f["sensor_grid_xyz"][()]
    xs, ys = np.linspace(-0.4, 0.4, 4), np.linspace(-0.4, 0.4, 3)
    for c in range(4):
      for r in range(3):
        np.testing.assert_allclose(grid[c, r], [xs[c], ys[r], 0.0], atol=1e-15)
    np.testing.assert_array_equal(f["laser_grid_xyz"][()], grid)
    assert int(f["H_format"][0]) == 1 and int(f["sensor_grid_format"][0]) == 2 == int(f["laser_grid_format"][0])
    assert f["H_format"].dtype.kind == "i" and h5py.check_enum_dtype(f["H_format"].dtype)["T_Sx_Sy"] == 1
    assert math.isclose(f["delta_t"][()], 16e-12 * SPEED_OF_LIGHT, rel_tol=1e-15)
    assert f["t_start"][()] == 0.0 and not f["t_accounts_first_and_last_bounces"][()]
    np.testing.assert_array_equal(f["sensor_xyz"][()], [0.1, 0.2, 0.3])
    assert json.loads(f["scene_info"][()])["original_format"] == "nlosjax"
  path = io.save_tal(tmp_path / "l.hdf5", transient, setup, layout="T_Si")
  with h5py.File(path, "r") as f:
    assert f["H"].shape == (10, 12) and int(f["H_format"][0]) == 3 and int(f["sensor_grid_format"][0]) == 1
    np.testing.assert_array_equal(f["H"][()][:, 2 * 3 + 1], transient[:, 1, 2])    # point c * H + r


def test_writer_refusals(tmp_path):
  setup = Setup(wall_size=0.8, grid=(3, 4), bin_width=16e-12, num_bins=10)
  transient = known_transient(10, 3, 4)
  with pytest.raises(ValueError, match="layout"):
    io.save_tal(tmp_path / "a.hdf5", transient, setup, layout="T_Lx_Ly_Sx_Sy")
  with pytest.raises(ValueError, match="one \\[T, H, W\\]"):
    io.save_tal(tmp_path / "a.hdf5", np.stack([transient] * 2), setup)
  bad = transient.copy()
  bad[0, 0, 0] = -1
  with pytest.raises(ValueError, match="negative"):
    io.save_tal(tmp_path / "a.hdf5", bad, setup)
  io.save_tal(tmp_path / "a.hdf5", transient, setup)
  with pytest.raises(FileExistsError):
    io.save_tal(tmp_path / "a.hdf5", transient, setup)


# ---------------------------------------------------- grid layouts by hand

def tal_points(layout, xs, ys, rng):
  """``(grid, [(TAL index, row, column)])`` for one way TAL can lay out the scan points."""
  height, width = len(ys), len(xs)
  if layout in ("X_Y_3", "X_Y_3 reversed", "X_Y_3 y first"):
    cols, rows = np.arange(width), np.arange(height)
    if layout == "X_Y_3 reversed":                     # x and y descending along the grid axes
      cols, rows = cols[::-1], rows[::-1]
    if layout == "X_Y_3 y first":                      # the first grid axis runs along y
      grid = np.zeros((height, width, 3))
      index = [((i, j), rows[i], cols[j]) for i in range(height) for j in range(width)]
    else:
      grid = np.zeros((width, height, 3))
      index = [((i, j), rows[j], cols[i]) for i in range(width) for j in range(height)]
    for idx, r, c in index:
      grid[idx] = [xs[c], ys[r], 0.3]                  # a wall at z = 0.3
    return grid, index
  order = rng.permutation(height * width)              # "N_3": the points in any order
  index = [(i, int(k) // width, int(k) % width) for i, k in enumerate(order)]
  grid = np.array([[xs[c], ys[r], 0.3] for _, r, c in index])
  return grid, index


@pytest.mark.parametrize("layout", ["X_Y_3", "X_Y_3 reversed", "X_Y_3 y first", "N_3"])
@pytest.mark.parametrize("enums", ["enum", "int"])
def test_grid_layouts_against_a_hand_built_capture(tmp_path, layout, enums):
  """Rows come out along y and columns along x, ascending, whatever the TAL grid's order."""
  height, width, bins = 3, 4, 12
  ours = known_transient(bins, height, width)
  xs, ys = axes(height, width)
  grid, index = tal_points(layout, xs, ys, np.random.default_rng(1))
  h = np.zeros((bins,) + grid.shape[:-1], np.float32)
  for idx, r, c in index:
    h[(slice(None),) + (idx if isinstance(idx, tuple) else (idx,))] = ours[:, r, c]
  h_format = "T_Si" if layout == "N_3" else "T_Sx_Sy"
  path = write_tal(tmp_path / "c.hdf5", h, h_format, grid, enums=enums)
  transient, setup = io.load_measurement(path)
  np.testing.assert_array_equal(transient, ours)
  assert setup.grid == (3, 4) and setup.num_bins == bins
  assert math.isclose(setup.wall_size, 0.6, rel_tol=1e-6)
  assert math.isclose(setup.bin_width, DELTA_T / SPEED_OF_LIGHT, rel_tol=1e-12)


def test_t_si_with_a_flattened_x_y_3_grid_reads_too(tmp_path):
  ours = known_transient(8, 2, 3)
  xs, ys = axes(2, 3)
  grid, index = tal_points("X_Y_3", xs, ys, None)      # [3, 2, 3]; H over the 6 points in C order
  h = np.stack([ours[:, r, c] for _, r, c in index], axis=1)
  transient, _ = io.load_measurement(write_tal(tmp_path / "c.hdf5", h, "T_Si", grid))
  np.testing.assert_array_equal(transient, ours)


# ------------------------------------------------------- time conventions

def brute_force(h, points, laser_points, ys, xs, *, t_start, accounts, laser_xyz, sensor_xyz):
  """Our transient from TAL's ``h [T, N]``, bin by bin: the centre of TAL bin ``i`` of point ``p``,
  as path from the wall, falls in our bin ``k = floor(path / delta_t)``."""
  raw_bins, n = h.shape
  entries, last = [], 0
  for p in range(n):
    legs = 0.0
    if accounts:
      legs = (math.dist(laser_points[p], laser_xyz) + math.dist(points[p], sensor_xyz))
    r = int(np.argmin(np.abs(ys - points[p][1])))
    c = int(np.argmin(np.abs(xs - points[p][0])))
    for i in range(raw_bins):
      centre = t_start + (i + 0.5) * DELTA_T - legs
      k = math.floor(centre / DELTA_T)
      assert abs(centre / DELTA_T - k - 0.5) < 0.5 - 1e-6    # no point sits on a bin edge
      if k >= 0:
        entries.append((k, r, c, h[i, p]))
        last = max(last, k)
  out = np.zeros((last + 1, len(ys), len(xs)), np.float32)
  for k, r, c, v in entries:
    out[k, r, c] = v
  return out


@pytest.mark.parametrize("accounts,t_start", [(False, 0.0), (False, 0.05), (False, -0.035),
                                              (True, 1.4), (True, 0.0), (None, 0.05), (True, None)])
def test_time_conventions_against_a_brute_force_loop_over_scan_points(tmp_path, accounts, t_start):
  height, width, raw_bins = 3, 4, 160
  xs, ys = axes(height, width)
  grid, index = tal_points("X_Y_3", xs, ys, None)
  h = known_transient(raw_bins, width, height, seed=5)                 # [T, Sx, Sy]
  laser_xyz, sensor_xyz = (-0.45, 0.3, 0.7), (0.35, -0.25, 0.55)
  path = write_tal(tmp_path / "c.hdf5", h, "T_Sx_Sy", grid, t_start=t_start, accounts=accounts,
                   laser_xyz=laser_xyz, sensor_xyz=sensor_xyz)
  transient, setup = io.load_measurement(path)
  points = grid.reshape(-1, 3).astype(np.float32).astype(np.float64)   # as the file holds them
  expected = brute_force(h.reshape(raw_bins, -1), points, points, ys, xs, t_start=t_start or 0.0,
                         accounts=bool(accounts), laser_xyz=np.float32(laser_xyz).astype(np.float64),
                         sensor_xyz=np.float32(sensor_xyz).astype(np.float64))
  np.testing.assert_array_equal(transient, expected)
  assert setup.num_bins == expected.shape[0]
  if accounts:                          # each point moved by its own legs: shifts differ between points
    first = [np.flatnonzero(transient[:, r, c])[0] for r in range(height) for c in range(width)]
    last = [np.flatnonzero(transient[:, r, c])[-1] for r in range(height) for c in range(width)]
    assert len(set(last)) > 1 and min(first) == 0


def test_laser_legs_use_the_laser_points_and_the_spad_legs_the_sensor_points(tmp_path):
  """With a laser and a SPAD at different places, swapping them changes the per-point shifts."""
  xs, ys = axes(2, 2, wall=1.0)
  grid, _ = tal_points("X_Y_3", xs, ys, None)
  h = known_transient(64, 2, 2, seed=2)
  a, b = (-0.9, 0.0, 0.4), (0.5, 0.5, 0.3)
  one, _ = io.load_measurement(write_tal(tmp_path / "a.hdf5", h, "T_Sx_Sy", grid, accounts=True, t_start=1.5,
                                         laser_xyz=a, sensor_xyz=b))
  two, _ = io.load_measurement(write_tal(tmp_path / "b.hdf5", h, "T_Sx_Sy", grid, accounts=True, t_start=1.5,
                                         laser_xyz=b, sensor_xyz=a))
  np.testing.assert_array_equal(one, two)     # confocal: d1 + d4 is symmetric, as it must be


def test_preparation_applies_after_the_shift(tmp_path):
  xs, ys = axes(2, 3)
  grid, _ = tal_points("X_Y_3", xs, ys, None)
  h = known_transient(40, 3, 2, seed=3)
  path = write_tal(tmp_path / "c.hdf5", h, "T_Sx_Sy", grid, t_start=0.06)    # 5 bins not recorded
  full, setup = io.load_measurement(path)
  binned, bsetup = io.load_measurement(path, bin_factor=2, zero_bins=6, num_bins=20)
  ref = full.copy()
  ref[:6] = 0
  np.testing.assert_array_equal(binned, ref[:40].reshape(20, 2, 2, 3).sum(axis=1))
  assert math.isclose(bsetup.bin_width, 2 * setup.bin_width) and bsetup.num_bins == 20


# ---------------------------------------------------------------- refusals

def refusal_cases():
  xs, ys = axes(3, 3)
  grid, _ = tal_points("X_Y_3", xs, ys, None)
  h = known_transient(8, 3, 3)
  flat = grid.reshape(-1, 3)
  bent = grid.copy()
  bent[1, 1, 2] += 0.05
  moved = grid.copy()
  moved[1, 1, 0] += 0.02
  uneven = grid.copy()
  uneven[2, :, 0] += 0.01                          # the last column of points off the even grid
  wide = grid.copy()
  wide[..., 0] *= 1.5
  return {
      "exhaustive T_Lx_Ly_Sx_Sy": (dict(h=np.zeros((8, 3, 3, 3, 3), np.float32), h_format="T_Lx_Ly_Sx_Sy",
                                        sensor=grid), "exhaustive.*T_Lx_Ly_Sx_Sy"),
      "exhaustive T_Li_Si": (dict(h=np.zeros((8, 9, 9), np.float32), h_format="T_Li_Si", sensor=flat),
                             "exhaustive.*T_Li_Si"),
      "single laser": (dict(h=h, h_format="T_Sx_Sy", sensor=grid, laser=grid[1:2, 1:2]),
                       "single-laser-point"),
      "other laser points": (dict(h=h, h_format="T_Sx_Sy", sensor=grid, laser=grid + [0.01, 0, 0]),
                             "non-confocal"),
      "frequency domain": (dict(h=h, h_format="F_Sx_Sy", sensor=grid), "frequency-domain"),
      "polarized": (dict(h=np.zeros((8, 3, 3, 4), np.float32), h_format="T_Sx_Sy", sensor=grid),
                    "polarized"),
      "not planar": (dict(h=h, h_format="T_Sx_Sy", sensor=bent), "one plane"),
      "irregular": (dict(h=h, h_format="T_Sx_Sy", sensor=moved), "irregular"),
      "uneven": (dict(h=h, h_format="T_Sx_Sy", sensor=uneven), "unevenly spaced.*along x"),
      "unequal extents": (dict(h=h, h_format="T_Sx_Sy", sensor=wide), "one wall_size"),
      "legs without positions": (dict(h=h, h_format="T_Sx_Sy", sensor=grid, accounts=True, laser_xyz=None),
                                 "laser_xyz"),
      "no delta_t": (dict(h=h, h_format="T_Sx_Sy", sensor=grid, delta_t=None), "delta_t"),
      "negative counts": (dict(h=-h, h_format="T_Sx_Sy", sensor=grid), "negative"),
  }


@pytest.mark.parametrize("case", sorted(refusal_cases()))
def test_unsupported_captures_get_one_clear_error(tmp_path, case):
  kwargs, message = refusal_cases()[case]
  path = write_tal(tmp_path / "c.hdf5", kwargs.pop("h"), kwargs.pop("h_format"), kwargs.pop("sensor"), **kwargs)
  assert io.detect_format(path) == "tal"
  with pytest.raises(ValueError, match=message) as err:
    io.load_measurement(path)
  assert str(path) in str(err.value)


# --------------------------------------------------- files written by y-tal

@pytest.mark.parametrize("name", ["grid", "list"])
def test_files_written_by_ytal_read_as_the_transient_they_were_made_from(name):
  expected = np.load(DATA / "tal_expected.npz")
  transient, setup = io.load_measurement(DATA / f"tal_{name}.hdf5")
  np.testing.assert_array_equal(transient, expected[f"{name}_transient"])
  assert math.isclose(setup.wall_size, float(expected[f"{name}_wall_size"]), rel_tol=1e-6)
  assert math.isclose(setup.bin_width, float(expected[f"{name}_bin_width"]), rel_tol=1e-12)
  assert setup.grid == expected[f"{name}_transient"].shape[1:]


YTAL_PYTHON = os.environ.get("NLOSJAX_YTAL_PYTHON")
READ_WITH_YTAL = """
import sys, json, numpy as np, tal.io
c = tal.io.read_capture(sys.argv[1])
print(json.dumps({"confocal": bool(c.is_confocal()), "paired": bool(c.is_laser_paired_to_sensor()),
                  "H_format": c.H_format.name, "grid_format": c.sensor_grid_format.name, "H": c.H.tolist(),
                  "grid": np.asarray(c.sensor_grid_xyz).tolist(), "delta_t": float(c.delta_t),
                  "t_start": float(c.t_start), "legs": bool(c.t_accounts_first_and_last_bounces)}))
"""


@pytest.mark.skipif(not YTAL_PYTHON, reason="NLOSJAX_YTAL_PYTHON (a Python with y-tal) is not set")
@pytest.mark.parametrize("layout", ["T_Sx_Sy", "T_Si"])
def test_ytal_reads_our_files(tmp_path, layout):
  setup = Setup(wall_size=0.8, grid=(3, 4), bin_width=32e-12, num_bins=6)
  transient = known_transient(6, 3, 4)
  path = io.save_tal(tmp_path / "c.hdf5", transient, setup, layout=layout)
  out = subprocess.run([YTAL_PYTHON, "-c", READ_WITH_YTAL, str(path)], capture_output=True, text=True,
                       check=True, timeout=300)
  got = json.loads(out.stdout.strip().splitlines()[-1])
  assert got["confocal"] and got["paired"] and got["H_format"] == layout and not got["legs"]
  assert got["grid_format"] == ("X_Y_3" if layout == "T_Sx_Sy" else "N_3")
  h = np.asarray(got["H"]).reshape(6, 4, 3)
  np.testing.assert_array_equal(h.transpose(0, 2, 1), transient)
  grid = np.asarray(got["grid"]).reshape(4, 3, 3)
  np.testing.assert_allclose(grid[:, 0, 0], setup.scan_x)
  np.testing.assert_allclose(grid[0, :, 1], setup.scan_y)
  assert math.isclose(got["delta_t"] / SPEED_OF_LIGHT, 32e-12, rel_tol=1e-15) and got["t_start"] == 0.0


# ------------------------------------------------------- experiments.reconstruct

@pytest.mark.parametrize("source", ["written by y-tal", "written by save_tal"])
def test_a_tal_capture_reconstructs_bit_for_bit_as_its_twin_in_our_format(tmp_path, source):
  """``experiments.reconstruct`` on a TAL file and on the same capture saved by ``save_capture``."""
  from experiments import reconstruct as cli
  if source == "written by y-tal":
    tal_path = DATA / "tal_grid.hdf5"
    expected = np.load(DATA / "tal_expected.npz")
    transient = expected["grid_transient"]              # the twin from the fixture's own data, not the reader
    setup = Setup(wall_size=float(expected["grid_wall_size"]), grid=transient.shape[1:],
                  bin_width=float(expected["grid_bin_width"]), num_bins=transient.shape[0])
  else:
    setup = Setup(wall_size=0.8, grid=(8, 8), bin_width=32e-12, num_bins=48)
    transient = np.random.default_rng(4).poisson(2.0, (48, 8, 8)).astype(np.float32)
    tal_path = io.save_tal(tmp_path / "c.hdf5", transient, setup)
  ours_path = io.save_capture(tmp_path / "c.h5", transient, setup)
  volumes, setups = [], []
  for path, out in ((tal_path, "tal"), (ours_path, "ours")):
    cli.main([str(path), "--method", "fbp", "--out", str(tmp_path / out), "--no-cache", "--quiet"])
    with h5py.File(tmp_path / out / "volume.h5", "r") as f:
      volumes.append(f["volume"][()])
      setups.append((f.attrs["wall_size"], tuple(f.attrs["grid"]), f.attrs["bin_width"], f.attrs["num_bins"]))
      assert f.attrs["source_format"] == ("tal" if out == "tal" else io.CAPTURE_FORMAT.replace("-", "_"))
  assert volumes[0].shape == (setup.num_bins,) + setup.grid
  np.testing.assert_array_equal(volumes[0], volumes[1])
  assert setups[0] == setups[1]                       # the same Setup, bit for bit

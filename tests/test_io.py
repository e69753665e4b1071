"""Tests for nlosjax.data.io: every format reader, detection, downsampling, overrides, errors."""

from __future__ import annotations

import hashlib
import math
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io

import nlosjax.data
from nlosjax.data import io as dio
from nlosjax.data import load_measurement, shipped_scan_path
from nlosjax.data.formats import registry
from nlosjax.files import seal_attrs
from nlosjax.physics.setup import Setup

REPO = Path(__file__).resolve().parents[1]
EXIT_SIGN_SHA256 = "e577393a3b134f017ee8cabba99cd06a303b9680bb5caa7e2031de298a282920"
S_U_SHA256 = "11a94722540e046ba3d86f7c00108948d1781428939302fd0e829d784a7f8f21"


# ------------------------------------------------------------------ helpers

def poisson_counts(shape, lam=2.0, seed=0):
  return np.random.default_rng(seed).poisson(lam, shape).astype(np.uint16)


def write_lct(path, rect, width=0.3, **kwargs):
  scipy.io.savemat(path, {"rect_data": rect, "width": width}, appendmat=False, **kwargs)
  return path


def reference(rect, zero_bins, bin_factor, num_bins):
  """Independent preparation: per-output-bin loop over raw [x, y, t] counts -> [t, y, x]."""
  raw = np.array(rect, dtype=np.int64)
  raw[:, :, :zero_bins] = 0
  width, height, _ = raw.shape
  out = np.zeros((num_bins, height, width), dtype=np.int64)
  for t in range(num_bins):
    out[t] = raw[:, :, t * bin_factor:(t + 1) * bin_factor].sum(axis=2).T
  return out


def names_file(path):
  return re.escape(str(path))


def sha256(path):
  return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# ------------------------------------------------------ published recipe

def test_default_preparation_matches_numpy(tmp_path):
  rect = poisson_counts((4, 3, 2048))  # [x, y, t] with W != H: checks the axis order
  assert rect[:, :, :600].sum() > 0    # so zeroing is observable
  path = write_lct(tmp_path / "scan.mat", rect, width=0.3)

  transient, setup = load_measurement(path)

  assert transient.dtype == np.float32
  assert transient.shape == (512, 3, 4)
  np.testing.assert_array_equal(transient, reference(rect, 600, 4, 512))
  assert not transient[:150].any()
  assert transient[150:].sum(dtype=np.float64) == rect[:, :, 600:].astype(np.int64).sum()
  # One element by hand: output bin 200 of row y=1, column x=3 = raw bins 800..803.
  assert transient[200, 1, 3] == int(rect[3, 1, 800:804].astype(np.int64).sum())
  assert transient[150, 2, 0] == int(rect[0, 2, 600:604].astype(np.int64).sum())
  assert setup == Setup(wall_size=0.6, grid=(3, 4), bin_width=16e-12, num_bins=512)
  assert math.isclose(setup.wall_size, 0.6, rel_tol=1e-12)
  assert math.isclose(setup.bin_width, 16e-12, rel_tol=1e-12)
  assert setup.depth_range is None


@pytest.mark.parametrize("zero_bins, bin_factor, num_bins, raw_bins", [
    (10, 3, 100, 500),   # zero_bins not a multiple of bin_factor, truncation
    (0, 1, 64, 64),      # no preparation: a pure transposition
    (5, 2, None, 61),    # odd length: trailing partial group dropped
    (600, 2, 512, 2048),  # finer bins, truncated range
])
def test_custom_preparation_matches_numpy(tmp_path, zero_bins, bin_factor, num_bins, raw_bins):
  rect = poisson_counts((5, 4, raw_bins), lam=1.5, seed=1)
  path = write_lct(tmp_path / "scan.mat", rect, width=0.25)

  transient, setup = load_measurement(path, zero_bins=zero_bins, bin_factor=bin_factor, num_bins=num_bins)

  expected_bins = raw_bins // bin_factor if num_bins is None else num_bins
  assert transient.shape == (expected_bins, 4, 5)
  np.testing.assert_array_equal(transient, reference(rect, zero_bins, bin_factor, expected_bins))
  assert setup.num_bins == expected_bins
  assert setup.grid == (4, 5)
  assert math.isclose(setup.bin_width, 4e-12 * bin_factor, rel_tol=1e-12)
  assert math.isclose(setup.wall_size, 0.5, rel_tol=1e-12)


def test_no_preparation_is_the_transpose(tmp_path):
  rect = poisson_counts((3, 5, 16), lam=20, seed=2)
  path = write_lct(tmp_path / "scan.mat", rect)
  transient, _ = load_measurement(path, zero_bins=0, bin_factor=1)
  np.testing.assert_array_equal(transient, np.transpose(rect, (2, 1, 0)).astype(np.float32))


def test_float_counts_and_scalar_width_accepted(tmp_path):
  rect = poisson_counts((4, 4, 32), seed=3).astype(np.float64) + 0.5
  path = write_lct(tmp_path / "scan.mat", rect, width=np.float32(0.125))
  transient, setup = load_measurement(path, zero_bins=4, bin_factor=2)
  np.testing.assert_allclose(transient, reference(rect * 2, 4, 2, 16) / 2, rtol=1e-6)
  assert math.isclose(setup.wall_size, 0.25, rel_tol=1e-6)


def test_input_file_is_never_written(tmp_path):
  path = write_lct(tmp_path / "scan.mat", poisson_counts((4, 4, 2048)))
  path.chmod(0o444)
  before = (sha256(path), path.stat().st_mtime_ns, path.stat().st_size)
  transient, _ = load_measurement(path, spatial_factor=2, setup_overrides={"depth_range": (0.1, 0.5)})
  transient += 1.0  # the returned array is ours to change
  load_measurement(path)
  assert (sha256(path), path.stat().st_mtime_ns, path.stat().st_size) == before


# ----------------------------------------------------------------- detection

def test_detection_reads_content_not_name(tmp_path):
  rect = poisson_counts((4, 4, 2048), seed=4)
  path = write_lct(tmp_path / "measurement.dat", rect)
  assert dio.detect_format(path) == "lct_mat"
  auto, setup_auto = load_measurement(path)
  named, setup_named = load_measurement(path, format="lct_mat")
  np.testing.assert_array_equal(auto, named)
  assert setup_auto == setup_named


def test_compressed_mat_detected_and_read(tmp_path):
  rect = poisson_counts((4, 4, 2048), seed=5)
  path = write_lct(tmp_path / "scan.mat", rect, do_compression=True)
  transient, _ = load_measurement(path)
  np.testing.assert_array_equal(transient, reference(rect, 600, 4, 512))


def test_unknown_format_name_lists_supported(tmp_path):
  path = write_lct(tmp_path / "scan.mat", poisson_counts((4, 4, 2048)))
  with pytest.raises(ValueError, match=names_file(path)) as info:
    load_measurement(path, format="fk_mat")
  assert "lct_mat" in str(info.value)


def test_hdf5_file_is_refused_with_supported_formats(tmp_path):
  path = tmp_path / "scan.mat"
  with h5py.File(path, "w") as f:
    f["rect_data"] = poisson_counts((4, 4, 64))
    f["width"] = 0.3
  for call in (lambda: dio.detect_format(path), lambda: load_measurement(path)):
    with pytest.raises(ValueError, match=names_file(path)) as info:
      call()
    assert "HDF5" in str(info.value) and "lct_mat" in str(info.value)
  # Naming the format skips detection; the reader still refuses, naming the file.
  with pytest.raises(ValueError, match=names_file(path)) as info:
    load_measurement(path, format="lct_mat")
  assert "HDF5" in str(info.value)


def test_matlab_v73_layout_detected_as_hdf5(tmp_path):
  # MATLAB v7.3: a 512-byte text header, then the HDF5 superblock at byte 512.
  path = tmp_path / "v73.mat"
  with h5py.File(path, "w", userblock_size=512) as f:
    f["rect_data"] = poisson_counts((4, 4, 64))
  with open(path, "r+b") as f:
    f.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: today HDF5 schema 1.00 .")
  assert dio._container(path) == "hdf5"
  with pytest.raises(ValueError, match=names_file(path)) as info:
    load_measurement(path)
  assert "HDF5" in str(info.value) and "lct_mat" in str(info.value)


def test_registry_plugs_in_a_new_format(tmp_path, monkeypatch):
  # The registry lives in nlosjax.data.formats.registry (nlosjax.data.io re-exports it).
  monkeypatch.setattr(registry, "FORMATS", dict(registry.FORMATS))
  path = tmp_path / "ours.h5"
  data = poisson_counts((8, 6, 6), seed=6).astype(np.float64)
  with h5py.File(path, "w") as f:
    f["transient"] = data

  def read_h5(p, *, zero_bins, bin_factor, num_bins):
    with h5py.File(p, "r") as f:
      counts = f["transient"][...]
    return counts, Setup(wall_size=1.0, grid=(6, 6), bin_width=32e-12, num_bins=8)

  dio.register_format("test_h5", read_h5, container="hdf5", summary="test HDF5 format")
  assert dio.detect_format(path) == "test_h5"
  transient, setup = load_measurement(path, spatial_factor=3)
  np.testing.assert_array_equal(transient, data.reshape(8, 2, 3, 2, 3).sum(axis=(2, 4)))
  assert setup.grid == (2, 2)
  # A v5 file still goes to lct_mat.
  v5 = write_lct(tmp_path / "scan.mat", poisson_counts((4, 4, 2048)))
  assert dio.detect_format(v5) == "lct_mat"
  with pytest.raises(ValueError, match="container"):
    dio.register_format("bad", read_h5, container="zip", summary="")


# --------------------------------------------------------- spatial downsampling

@pytest.mark.parametrize("k", [2, 4])
def test_spatial_sum_matches_numpy(tmp_path, k):
  rect = poisson_counts((8, 8, 64), lam=3, seed=7)
  path = write_lct(tmp_path / "scan.mat", rect, width=0.35)
  full = reference(rect, 4, 2, 32)

  transient, setup = load_measurement(path, zero_bins=4, bin_factor=2, spatial_factor=k, spatial_mode="sum")

  n = 8 // k
  expected = np.zeros((32, n, n))
  for i in range(n):
    for j in range(n):
      expected[:, i, j] = full[:, i * k:(i + 1) * k, j * k:(j + 1) * k].sum(axis=(1, 2))
  np.testing.assert_array_equal(transient, expected)
  assert setup.grid == (n, n)
  # Block centres span (H - k) old spacings, centred on the wall.
  old = np.linspace(-0.35, 0.35, 8)
  assert math.isclose(setup.wall_size, 0.7 * (8 - k) / 7, rel_tol=1e-12)
  np.testing.assert_allclose(setup.scan_y, [old[i * k:(i + 1) * k].mean() for i in range(n)], atol=1e-12)
  np.testing.assert_allclose(setup.scan_x, setup.scan_y, atol=0)
  assert math.isclose(setup.spacing[0], k * 0.7 / 7, rel_tol=1e-12)


@pytest.mark.parametrize("k, kept, extent", [
    (3, [0, 3, 6, 9], 9),  # last point kept: full wall
    (4, [0, 4, 8], 8),     # last point dropped: the wall shrinks
    (9, [0, 9], 9),
])
def test_spatial_stride_matches_numpy(tmp_path, k, kept, extent):
  rect = poisson_counts((10, 10, 2048), lam=1, seed=8)
  path = write_lct(tmp_path / "scan.mat", rect, width=0.45)
  full = reference(rect, 600, 4, 512)

  transient, setup = load_measurement(path, spatial_factor=k, spatial_mode="stride")

  np.testing.assert_array_equal(transient, full[:, kept][:, :, kept])
  assert setup.grid == (len(kept), len(kept))
  old_spacing = 0.9 / 9
  assert math.isclose(setup.wall_size, extent * old_spacing, rel_tol=1e-12)
  assert math.isclose(setup.spacing[1], k * old_spacing, rel_tol=1e-12)


def test_shipped_scan_understride_64_to_16():
  transient, setup = load_measurement(shipped_scan_path(), spatial_factor=4, spatial_mode="stride")
  full, _ = load_measurement(shipped_scan_path())
  assert transient.shape == (512, 16, 16)
  np.testing.assert_array_equal(transient, full[:, 0:61:4, 0:61:4])
  assert math.isclose(setup.wall_size, 0.8 * 60 / 63, rel_tol=1e-12)


def test_spatial_errors(tmp_path):
  path = write_lct(tmp_path / "scan.mat", poisson_counts((8, 8, 2048)))
  with pytest.raises(ValueError, match=names_file(path)):
    load_measurement(path, spatial_factor=3, spatial_mode="sum")  # 8 not divisible by 3
  with pytest.raises(ValueError, match="2 x 2"):
    load_measurement(path, spatial_factor=8, spatial_mode="stride")  # one point left
  with pytest.raises(ValueError, match="spatial_mode"):
    load_measurement(path, spatial_factor=2, spatial_mode="mean")
  with pytest.raises(ValueError, match="spatial_factor"):
    load_measurement(path, spatial_factor=0)
  transient, setup = load_measurement(path, spatial_factor=1, spatial_mode="stride")
  assert transient.shape == (512, 8, 8) and math.isclose(setup.wall_size, 0.6)
  # Non-square grid: rows span 6/7 of the wall, columns all of it -> no single wall_size.
  odd = write_lct(tmp_path / "odd.mat", poisson_counts((8, 7, 2048)))
  with pytest.raises(ValueError, match="wall_size"):
    load_measurement(odd, spatial_factor=3, spatial_mode="stride")


# ----------------------------------------------------------------- overrides

def test_depth_range_override(tmp_path):
  path = write_lct(tmp_path / "scan.mat", poisson_counts((4, 4, 2048)), width=0.4)
  plain, _ = load_measurement(path)
  transient, setup = load_measurement(path, setup_overrides={"depth_range": (0.2, 1.0)})
  assert setup.depth_range == (0.2, 1.0)
  assert setup.ungated() == Setup(wall_size=0.8, grid=(4, 4), bin_width=16e-12, num_bins=512)
  np.testing.assert_array_equal(transient, plain)
  with pytest.raises(ValueError, match=names_file(path)) as info:
    load_measurement(path, setup_overrides={"depth_range": (5.0, 6.0)})  # beyond 1.23 m
  assert "depth_range" in str(info.value)


def test_overrides_repeating_the_file_are_accepted(tmp_path):
  path = write_lct(tmp_path / "scan.mat", poisson_counts((8, 8, 2048)), width=0.4)
  same = {"wall_size": 0.8, "grid": (8, 8), "bin_width": 16e-12, "num_bins": 512}
  _, setup = load_measurement(path, setup_overrides=same)
  assert setup == Setup(**same)
  # After downsampling the file's grid is the downsampled one.
  _, setup = load_measurement(path, spatial_factor=2, setup_overrides={"grid": (4, 4), "num_bins": 512})
  assert setup.grid == (4, 4)


@pytest.mark.parametrize("field, value, file_value", [
    ("wall_size", 0.5, "0.8"),
    ("grid", (16, 16), "(8, 8)"),
    ("grid", 4, "(8, 8)"),
    ("bin_width", 32e-12, "1.6e-11"),
    ("num_bins", 256, "512"),
])
def test_contradicting_override_raises(tmp_path, field, value, file_value):
  path = write_lct(tmp_path / "scan.mat", poisson_counts((8, 8, 2048)), width=0.4)
  with pytest.raises(ValueError, match=names_file(path)) as info:
    load_measurement(path, setup_overrides={field: value})
  message = str(info.value)
  assert field in message and repr(value) in message and file_value in message


def test_unknown_override_field(tmp_path):
  path = write_lct(tmp_path / "scan.mat", poisson_counts((4, 4, 2048)))
  with pytest.raises(ValueError, match="foo"):
    load_measurement(path, setup_overrides={"foo": 1})
  with pytest.raises(ValueError, match="setup_overrides"):
    load_measurement(path, setup_overrides=[("depth_range", (0.1, 0.2))])


# -------------------------------------------------------------- bad arguments

@pytest.mark.parametrize("kwargs, word", [
    ({"bin_factor": 0}, "bin_factor"),
    ({"bin_factor": 2.0}, "bin_factor"),
    ({"zero_bins": -1}, "zero_bins"),
    ({"zero_bins": 2048}, "zero_bins"),
    ({"num_bins": 513}, "num_bins"),
    ({"num_bins": 1}, "num_bins"),
    ({"bin_factor": 2048}, "bin_factor"),
])
def test_bad_preparation_arguments(tmp_path, kwargs, word):
  path = write_lct(tmp_path / "scan.mat", poisson_counts((4, 4, 2048)))
  with pytest.raises(ValueError, match=names_file(path)) as info:
    load_measurement(path, **kwargs)
  assert word in str(info.value)


# ------------------------------------------------------------ corrupt files

def _valid_bytes(tmp_path, **kwargs):
  path = write_lct(tmp_path / "valid.mat", poisson_counts((8, 8, 256), seed=9), **kwargs)
  return path.read_bytes()


def _truncated(tmp_path):
  data = _valid_bytes(tmp_path)
  return lambda p: p.write_bytes(data[:len(data) // 2])


def _truncated_compressed(tmp_path):
  data = _valid_bytes(tmp_path, do_compression=True)
  return lambda p: p.write_bytes(data[:len(data) // 2])


def _header_only(tmp_path):
  data = _valid_bytes(tmp_path)
  return lambda p: p.write_bytes(data[:140])


def _random_bytes(tmp_path):
  return lambda p: p.write_bytes(np.random.default_rng(0).bytes(5000))


def _empty(tmp_path):
  return lambda p: p.write_bytes(b"")


def _hdf5(tmp_path):
  def write(p):
    with h5py.File(p, "w") as f:
      f["rect_data"] = poisson_counts((4, 4, 64))
      f["width"] = 0.3
  return write


def _v4(tmp_path):
  return lambda p: scipy.io.savemat(p, {"rect_data": np.ones((4, 4))}, format="4", appendmat=False)


def _vars(**variables):
  return lambda tmp_path: (lambda p: scipy.io.savemat(p, variables, appendmat=False))


GOOD = poisson_counts((4, 4, 2048))

CORRUPT = {
    "truncated": (_truncated, None),
    "truncated_compressed": (_truncated_compressed, None),
    "header_only": (_header_only, None),
    "random_bytes": (_random_bytes, "lct_mat"),
    "empty": (_empty, "lct_mat"),
    "hdf5": (_hdf5, "HDF5"),
    "matlab_v4": (_v4, "lct_mat"),
    "no_rect_data": (_vars(data=GOOD, width=0.3), "rect_data"),
    "no_width": (_vars(rect_data=GOOD), "width"),
    "rank_2": (_vars(rect_data=GOOD[:, :, 0], width=0.3), "rank"),
    "rank_4": (_vars(rect_data=GOOD[..., None], width=0.3), "rank"),
    "negative": (_vars(rect_data=GOOD.astype(np.int16) - 1, width=0.3), "negative"),
    "nan": (_vars(rect_data=np.where(GOOD > 3, np.nan, GOOD.astype(float)), width=0.3), "NaN"),
    "inf": (_vars(rect_data=np.where(GOOD > 3, np.inf, GOOD.astype(float)), width=0.3), "infinite"),
    "complex": (_vars(rect_data=GOOD + 1j, width=0.3), "real"),
    "text": (_vars(rect_data="not counts", width=0.3), "rect_data"),
    "one_scan_row": (_vars(rect_data=GOOD[:1], width=0.3), "2 x 2"),
    "width_negative": (_vars(rect_data=GOOD, width=-0.3), "width"),
    "width_zero": (_vars(rect_data=GOOD, width=0.0), "width"),
    "width_nan": (_vars(rect_data=GOOD, width=np.nan), "width"),
    "width_vector": (_vars(rect_data=GOOD, width=np.array([0.3, 0.3])), "width"),
    "width_text": (_vars(rect_data=GOOD, width="0.3"), "width"),
}


@pytest.mark.parametrize("case", sorted(CORRUPT))
def test_corrupt_file_raises_value_error_naming_it(tmp_path, case):
  make, word = CORRUPT[case]
  path = tmp_path / f"bad_{case}.mat"
  make(tmp_path)(path)
  before = sha256(path)
  with pytest.raises(ValueError, match=names_file(path)) as info:
    load_measurement(path)
  if word is not None:
    assert word in str(info.value)
  assert sha256(path) == before


def test_missing_file_and_directory(tmp_path):
  missing = tmp_path / "nowhere" / "scan.mat"
  with pytest.raises(FileNotFoundError, match=names_file(missing)):
    load_measurement(missing)
  with pytest.raises(FileNotFoundError, match=names_file(missing)):
    dio.detect_format(missing)
  with pytest.raises(ValueError, match=names_file(tmp_path)):
    load_measurement(tmp_path)


# ----------------------------------------------------------- shipped scan

def test_package_exports():
  assert nlosjax.data.load_measurement is dio.load_measurement
  assert nlosjax.data.shipped_scan_path is dio.shipped_scan_path


def test_the_shipped_scans_are_package_data():
  """shipped_scan_path works in an installed package, not only in a checkout: pyproject ships them."""
  import tomllib
  with open(REPO / "pyproject.toml", "rb") as f:
    globs = tomllib.load(f)["tool"]["setuptools"]["package-data"]["nlosjax.data"]
  for name in (*dio.SHIPPED_SCAN_NAMES, "README.md"):
    rel = shipped_scan_path().parent.relative_to(REPO / "nlosjax" / "data") / name
    assert any(rel.as_posix() == g or Path(rel).match(g) for g in globs), f"{rel} is not package data"


def test_shipped_scan_is_the_published_file():
  path = shipped_scan_path()
  assert path == REPO / "nlosjax" / "data" / "scans" / "data_exit_sign.mat"
  assert sha256(path) == EXIT_SIGN_SHA256
  assert (REPO / "nlosjax" / "data" / "scans" / "README.md").is_file()
  su = shipped_scan_path("data_s_u.mat")
  assert su == REPO / "nlosjax" / "data" / "scans" / "data_s_u.mat" and sha256(su) == S_U_SHA256
  transient, setup = load_measurement(su)
  assert transient.shape == (512, 64, 64) and setup.wall_size == pytest.approx(0.7)
  with pytest.raises(ValueError, match="shipped scans are"):
    shipped_scan_path("data_bunny.mat")


def test_shipped_exit_sign_loads():
  path = shipped_scan_path()
  raw = scipy.io.loadmat(path)
  rect = raw["rect_data"]
  assert rect.shape == (64, 64, 2048) and rect.dtype == np.uint16
  assert rect[:, :, :600].sum() > 0  # the direct reflection is in the raw file

  transient, setup = load_measurement(path)

  assert transient.shape == (512, 64, 64) and transient.dtype == np.float32
  assert setup.grid == (64, 64) and setup.num_bins == 512 and setup.depth_range is None
  assert math.isclose(setup.wall_size, 0.8, rel_tol=1e-12)
  assert math.isclose(setup.bin_width, 16e-12, rel_tol=1e-12)
  assert transient.min() >= 0 and np.isfinite(transient).all()
  assert not transient[:150].any()
  assert transient[150:].sum(dtype=np.float64) == rect[:, :, 600:].astype(np.int64).sum() > 0
  assert transient[300, 10, 40] == rect[10, 40, 1200:1204].astype(np.int64).sum()


def test_shipped_scan_path_missing(tmp_path, monkeypatch):
  monkeypatch.setattr(dio, "_SHIPPED_DIR", tmp_path)
  with pytest.raises(FileNotFoundError, match="not found"):
    shipped_scan_path()


# ------------------------------------------------- optional shared datasets

def _real_scan_files():
  """The measured scans the repository ships, and those of a shared/data/real folder beside it, if any."""
  files = sorted((REPO / "nlosjax" / "data" / "scans").glob("data_*.mat"))
  for root in (Path("/work/shared/data/real"), REPO.parent / "shared" / "data" / "real"):
    if root.is_dir():
      return files + sorted(root.glob("*.mat"))
  return files


def test_every_shipped_and_shared_real_scan_loads():
  files = _real_scan_files()
  assert len(files) >= 2                      # the shipped exit sign and S U, on every clone
  for path in files:
    raw = scipy.io.loadmat(path)
    height, width, raw_bins = raw["rect_data"].shape
    transient, setup = load_measurement(path)
    assert transient.shape == (raw_bins // 4, height, width), path
    assert setup.grid == (height, width), path
    assert math.isclose(setup.wall_size, 2 * float(raw["width"].squeeze()), rel_tol=1e-12), path
    assert math.isclose(setup.bin_width, 16e-12, rel_tol=1e-12), path
    assert transient.min() >= 0 and np.isfinite(transient).all(), path
    assert not transient[:150].any() and transient[150:].any(), path


# ============================================================ more formats
#
# Small files in every format, written here; each reader is checked against an
# independent NumPy reference (per-pixel loops, explicit transposes).

def write_v73(path, variables):
  """A MATLAB v7.3 file: HDF5 behind a 512-byte text header, arrays stored transposed (as MATLAB does)."""
  with h5py.File(path, "w", userblock_size=512) as f:
    for name, value in variables.items():
      f[name] = np.asarray(value).T
  with open(path, "r+b") as f:
    f.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: test HDF5 schema 1.00 .")
  return path


def fk_reference(meas, tofgrid, keep, zero_bins=0, bin_factor=1):
  """nlos-fk's preparation by loops: circshift each pixel left by floor(tof / 32), crop, zero, bin."""
  height, width, _ = meas.shape
  out = np.zeros((keep // bin_factor, height, width))
  for i in range(height):
    for j in range(width):
      h = np.roll(meas[i, j].astype(np.float64), -int(math.floor(tofgrid[i, j] / 32.0)))[:keep]
      h[:zero_bins] = 0
      out[:, i, j] = h.reshape(-1, bin_factor).sum(axis=1)
  return out


@pytest.fixture
def fk_capture(tmp_path):
  rng = np.random.default_rng(11)
  height, width, raw_bins = 3, 5, 640                          # H != W checks the axis order
  meas = rng.poisson(0.7, (height, width, raw_bins)).astype(np.float64)
  tof = rng.uniform(0.0, 3000.0, (height, width))               # ps: shifts of 0..93 bins
  tof[0, 0] = 31.99                                             # floor, not round
  path = write_v73(tmp_path / "meas_10min.mat", {"meas": meas})
  scipy.io.savemat(tmp_path / "tof_10min.mat", {"tofgrid": tof}, appendmat=False)
  return path, meas, tof


def test_stanford_fk_v73_matches_loop_reference(fk_capture):
  path, meas, tof = fk_capture
  assert dio.detect_format(path) == "stanford_fk"
  transient, setup = load_measurement(path)                    # tof_10min.mat found beside it
  assert transient.shape == (512, 3, 5) and transient.dtype == np.float32
  np.testing.assert_array_equal(transient, fk_reference(meas, tof, 512))
  assert setup == Setup(wall_size=2.0, grid=(3, 5), bin_width=32e-12, num_bins=512)
  # Binning and trimming, and the wall size the files do not record.
  transient, setup = load_measurement(path, zero_bins=6, bin_factor=4, num_bins=100, wall_size=1.0)
  np.testing.assert_array_equal(transient, fk_reference(meas, tof, 400, zero_bins=6, bin_factor=4))
  assert setup == Setup(wall_size=1.0, grid=(3, 5), bin_width=128e-12, num_bins=100)


def test_stanford_fk_alignment_puts_the_wall_at_bin_zero(tmp_path):
  # One photon per pixel at the gated wall return floor(tof / 32) + 7: aligned, all land in bin 7.
  rng = np.random.default_rng(12)
  tof = rng.uniform(0.0, 8000.0, (4, 4))
  meas = np.zeros((4, 4, 600))
  for i in range(4):
    for j in range(4):
      meas[i, j, int(tof[i, j] // 32) + 7] = 1.0
  path = write_v73(tmp_path / "scan.mat", {"meas": meas, "tofgrid": tof})   # tofgrid in the file
  transient, _ = load_measurement(path, num_bins=64)
  assert transient[7].min() == 1.0 and transient.sum() == 16


def test_stanford_fk_tofgrid_sources(fk_capture, tmp_path):
  path, meas, tof = fk_capture
  expected = fk_reference(meas, tof, 512)
  np.testing.assert_array_equal(load_measurement(path, tofgrid=tof)[0], expected)
  other = write_v73(tmp_path / "calibration.mat", {"tofgrid": tof})
  np.testing.assert_array_equal(load_measurement(path, tofgrid=other)[0], expected)
  np.testing.assert_array_equal(load_measurement(path, tofgrid=False)[0],
                                meas[:, :, :512].transpose(2, 0, 1))
  # meas as MATLAB v5 works too.
  v5 = tmp_path / "meas_v5.mat"
  scipy.io.savemat(v5, {"meas": meas, "tofgrid": tof}, appendmat=False)
  assert dio.detect_format(v5) == "stanford_fk"
  np.testing.assert_array_equal(load_measurement(v5)[0], expected)


def test_stanford_fk_tofgrid_errors(fk_capture, tmp_path):
  path, meas, tof = fk_capture
  with pytest.raises(ValueError, match=names_file(path)) as info:
    load_measurement(path, tofgrid=tof[:2])
  assert "tofgrid" in str(info.value) and "(2, 5)" in str(info.value)
  with pytest.raises(ValueError, match="NaN"):
    load_measurement(path, tofgrid=np.where(tof > 1000, np.nan, tof))
  (tmp_path / "alone").mkdir()
  lone = write_v73(tmp_path / "alone" / "meas_1.mat", {"meas": meas})
  with pytest.raises(ValueError, match=names_file(lone)) as info:
    load_measurement(lone)
  assert "tof_1.mat" in str(info.value) and "tofgrid=False" in str(info.value)
  with pytest.raises(FileNotFoundError):
    load_measurement(path, tofgrid=tmp_path / "missing.mat")
  with pytest.raises(ValueError, match="wall_size"):
    load_measurement(path, wall_size=-2.0)


def test_stanford_fk_video_frames(tmp_path):
  rng = np.random.default_rng(13)
  video = rng.poisson(1.0, (3, 4, 4, 80)).astype(np.float64)     # MATLAB [F, H, W, T]
  path = write_v73(tmp_path / "meas_32.mat", {"meas": video})
  tof = np.full((4, 4), 100.0)                                   # shift 3 bins
  write_v73(tmp_path / "tof_32.mat", {"tofgrid": tof})
  one, setup = load_measurement(path, frame=2, num_bins=64)
  np.testing.assert_array_equal(one, fk_reference(video[2], tof, 64))
  frames, _ = load_measurement(path, frame="all", num_bins=64, spatial_factor=2)
  assert frames.shape == (3, 64, 2, 2)
  for f in range(3):
    full = fk_reference(video[f], tof, 64)
    np.testing.assert_array_equal(frames[f], full.reshape(64, 2, 2, 2, 2).sum(axis=(2, 4)))
  picked, _ = load_measurement(path, frame=[2, 0], num_bins=64)
  np.testing.assert_array_equal(picked[0], one)
  with pytest.raises(ValueError, match="out of range"):
    load_measurement(path, frame=3)


def test_nlost_data_is_transposed(tmp_path):
  rng = np.random.default_rng(14)
  data = rng.poisson(1.0, (5, 3, 64)).astype(np.uint16)          # [W, H, T] as NLOST stores it
  path = tmp_path / "nlost.mat"
  scipy.io.savemat(path, {"data": data}, appendmat=False)
  assert dio.detect_format(path) == "nlost_mat"
  transient, setup = load_measurement(path)
  assert transient.shape == (64, 3, 5)
  for t, y, x in [(0, 0, 0), (10, 2, 4), (63, 1, 3)]:
    assert transient[t, y, x] == data[x, y, t]
  assert setup == Setup(wall_size=2.0, grid=(3, 5), bin_width=32e-12, num_bins=64)
  # NLOST's own recipe: transpose([1, 0, 2]) then [H, W, T] -> [T, H, W].
  np.testing.assert_array_equal(transient, data.transpose(1, 0, 2).transpose(2, 0, 1))
  binned, setup = load_measurement(path, bin_factor=2, num_bins=16, bin_width=16e-12)
  np.testing.assert_array_equal(binned, transient[:32].reshape(16, 2, 3, 5).sum(axis=1))
  assert math.isclose(setup.bin_width, 32e-12)
  # Aligned f-k captures as USM/NLOST ship them: final_meas [H, W, T], no transpose, v7.3.
  fm = write_v73(tmp_path / "final.mat", {"final_meas": data.transpose(1, 0, 2)})
  assert dio.detect_format(fm) == "nlost_mat"
  np.testing.assert_array_equal(load_measurement(fm)[0], transient)


def test_capture_roundtrip_and_frames(tmp_path):
  rng = np.random.default_rng(15)
  frames = rng.poisson(2.0, (4, 32, 6, 6)).astype(np.float32)
  setup = Setup(wall_size=1.5, grid=(6, 6), bin_width=50e-12, num_bins=32, depth_range=(0.2, 0.9))
  path = dio.save_capture(tmp_path / "cap.h5", frames, setup, attrs={"scene": "test", "meta": [1, 2]})
  assert not (tmp_path / "cap.h5.partial").exists()
  assert dio.detect_format(path) == "nlosjax_capture"
  one, s1 = load_measurement(path, frame=1)
  np.testing.assert_array_equal(one, frames[1])
  assert s1 == setup
  allf, _ = load_measurement(path, frame="all", bin_factor=2)
  np.testing.assert_array_equal(allf, frames.reshape(4, 16, 2, 6, 6).sum(axis=2))
  single = dio.save_capture(tmp_path / "one.h5", frames[0], setup.ungated())
  np.testing.assert_array_equal(load_measurement(single)[0], frames[0])
  with pytest.raises(FileExistsError):
    dio.save_capture(single, frames[0], setup)
  with pytest.raises(ValueError, match="does not match"):
    dio.save_capture(tmp_path / "bad.h5", frames[0][:, :5], setup)
  # A reconstruction-only file (no transient) is refused by name.
  vol = dio.save_capture(tmp_path / "vol.h5", None, setup, volume=np.zeros((3, 6, 6)))
  with pytest.raises(ValueError, match=names_file(vol)) as info:
    load_measurement(vol)
  assert "transient" in str(info.value)


def test_capture_inconsistent_attributes(tmp_path):
  path = dio.save_capture(tmp_path / "cap.h5", np.ones((8, 4, 4)),
                          Setup(wall_size=1.0, grid=(4, 4), bin_width=1e-11, num_bins=8))
  # save_capture seals the attributes with a digest (nlosjax.files.ATTRS_DIGEST): an attribute
  # changed without resealing reads as a damaged file; resealed, the specific check speaks.
  with h5py.File(path, "r+") as f:
    f.attrs["grid"] = [4, 5]
  with pytest.raises(ValueError, match=names_file(path) + ".*do not match the digest.*damaged"):
    load_measurement(path)
  with h5py.File(path, "r+") as f:
    seal_attrs(f)
  with pytest.raises(ValueError, match=names_file(path)) as info:
    load_measurement(path)
  assert "grid" in str(info.value)
  with h5py.File(path, "r+") as f:
    f.attrs["grid"] = [4, 4]
    f.attrs["format_version"] = 99
    seal_attrs(f)
  with pytest.raises(ValueError, match="format_version"):
    load_measurement(path)


def test_dynamic_dataset_sequence_frames(tmp_path):
  # A minimal file in the documented dataset layout (docs/dataset.md).
  rng = np.random.default_rng(16)
  meas = {name: rng.poisson(3.0, (3, 16, 4, 4)).astype(np.uint16)
          for name in ("test-00000", "test-00001", "train-00000")}
  path = tmp_path / "data.h5"
  with h5py.File(path, "w") as f:
    f.attrs.update(format="nlosjax-dynamic-nlos", format_version=1, complete=True, wall_size=2.0,
                   grid=[4, 4], bin_width=132e-12, num_bins=16)
    for name, m in meas.items():
      g = f.create_group(f"sequences/{name}")
      g.attrs["split"] = name.split("-")[0]
      g["measurement"] = m
  assert dio.detect_format(path) == "nlosjax_dataset"
  frame, setup = load_measurement(path)                          # first sequence, frame 0
  np.testing.assert_array_equal(frame, meas["test-00000"][0])
  assert setup == Setup(wall_size=2.0, grid=(4, 4), bin_width=132e-12, num_bins=16)
  frames, _ = load_measurement(path, split="test", sequence=1, frame="all")
  np.testing.assert_array_equal(frames, meas["test-00001"])
  named, _ = load_measurement(path, sequence="train-00000", frame=-1)
  np.testing.assert_array_equal(named, meas["train-00000"][2])
  with pytest.raises(ValueError, match="no sequence"):
    load_measurement(path, sequence="test-00009")
  with pytest.raises(ValueError, match="out of range"):
    load_measurement(path, split="train", sequence=1)


def test_detection_of_every_format_and_errors(tmp_path):
  scipy.io.savemat(tmp_path / "foo.mat", {"foo": np.ones(3)}, appendmat=False)
  with pytest.raises(ValueError, match=names_file(tmp_path / "foo.mat")) as info:
    load_measurement(tmp_path / "foo.mat")
  assert "'foo'" in str(info.value) and "stanford_fk" in str(info.value)
  # A truncated HDF5 file: named, "corrupt".
  good = write_v73(tmp_path / "meas.mat", {"meas": np.ones((2, 2, 8)), "tofgrid": np.zeros((2, 2))})
  bad = tmp_path / "truncated.mat"
  bad.write_bytes(good.read_bytes()[:700])
  with pytest.raises(ValueError, match=names_file(bad)) as info:
    load_measurement(bad)
  assert "corrupt" in str(info.value)
  # An option the format does not take.
  lct = write_lct(tmp_path / "scan.mat", poisson_counts((4, 4, 2048)))
  with pytest.raises(ValueError, match=names_file(lct)) as info:
    load_measurement(lct, tofgrid=False)
  assert "tofgrid" in str(info.value)
  # A single capture has only frame 0; "all" gives [1, T, H, W].
  assert load_measurement(lct, frame="all")[0].shape == (1, 512, 4, 4)
  with pytest.raises(ValueError, match="out of range"):
    load_measurement(lct, frame=1)


def test_override_of_a_value_the_format_does_not_record(fk_capture):
  path, _, _ = fk_capture
  with pytest.raises(ValueError, match=names_file(path)) as info:
    load_measurement(path, setup_overrides={"wall_size": 1.0})
  assert "wall_size=" in str(info.value) and "does not record" in str(info.value)
  _, setup = load_measurement(path, wall_size=1.0, setup_overrides={"wall_size": 1.0})
  assert setup.wall_size == 1.0

"""Measured scan: our LCT, f-k and phasor reproduce the public reference algorithms.

The reference is ``benchmarks/numpy_twins.py``, a NumPy port of the public
code (MATLAB resampling matrix, one-voxel cone PSF on wall/N spacing, full
complex FFTs). Maximum-intensity projections must correlate >= 0.9.
"""

import numpy as np
import pytest

from benchmarks import numpy_twins as twins
from nlosjax import physics
from nlosjax.data import io


def ncc(a, b):
  a = a.ravel() - a.mean()
  b = b.ravel() - b.mean()
  return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


@pytest.fixture(scope="module")
def scan():
  return io.load_measurement(io.shipped_scan_path())


@pytest.mark.parametrize("method, options", [
    ("lct", dict(snr=0.8, falloff="retroreflective")), ("fk", {}), ("phasor", {})])
def test_measured_scan_matches_public_reference(scan, method, options):
  transient, setup = scan
  ours = np.asarray(physics.reconstruct(transient, setup, method, **options))
  ref = twins.run(transient, method, twins.build(setup, method, **options))
  # Skip the first bins next to the wall (direct-light residue, zeroed in the data).
  assert ncc(ours[10:].max(0), ref[10:].max(0)) >= 0.9


@pytest.mark.parametrize("method", ["lct", "fk", "phasor"])
def test_reconstruct_cli_images_match_public_reference(scan, method, tmp_path):
  """What users see: ``experiments.reconstruct``'s intensity image with default options
  vs the twin's front view as the public code draws it (last 11 bins clipped; f-k's
  albedo^2 square-rooted)."""
  from experiments import reconstruct as cli
  transient, setup = scan
  res = cli.main([str(io.shipped_scan_path()), "--method", method, "--out", str(tmp_path),
                  "--no-cache", "--quiet"])
  ref = twins.run(transient, method, twins.build(setup, method))[:-cli.EDGE_BINS]
  front = np.sqrt(ref.max(0)) if method == "fk" else ref.max(0)
  assert ncc(res["intensity"][0], front) >= 0.9

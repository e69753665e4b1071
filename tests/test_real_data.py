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

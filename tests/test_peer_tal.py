"""``benchmarks.peer_tal`` with y-tal faked: what it compares and what the results file says.

y-tal's worker (a subprocess in y-tal's Python) and our methods are replaced by volumes made
here, so each NCC the benchmark reports is known: f-k compared in one unit (amplitudes on both
sides), y-tal's ``fbp`` against our phasor (the algorithm it computes), not against our FBP.
"""

import json
import re
import subprocess

import numpy as np
import pytest

from benchmarks import peer_tal


def _scene(n: int, z: int, seed: int) -> np.ndarray:
  """A ``[Z, n, n]`` amplitude volume >= 0 whose front view is not flat."""
  return np.random.default_rng(seed).gamma(2.0, size=(z, n, n)).astype(np.float32)


def _ours(n, z, method):
  """Our volumes: phasor the scene, f-k its ``|.|^2``, FBP another scene (a different algorithm)."""
  scene = _scene(n, z, 0)
  return {"phasor": scene, "fk": scene ** 2, "fbp": _scene(n, z, 1)}[method]


def _theirs(n, z, method):
  """y-tal's volumes as its worker saves them: ``pf`` and ``fbp`` the scene ``[Sx, Sy, Z]``,
  ``fk`` its ``|.|^2`` ``[T, Sx, Sy]``."""
  scene = _scene(n, z, 0)
  return {"pf": scene.transpose(2, 1, 0), "fk": (scene ** 2).transpose(0, 2, 1),
          "fbp": scene.transpose(2, 1, 0)}[method]


@pytest.fixture
def fake(monkeypatch):
  real_run = subprocess.run

  def run(cmd, **kwargs):              # subprocess is one module: others' commands (git) run as they are
    if peer_tal.WORKER not in cmd:
      return real_run(cmd, **kwargs)
    tal_file, out, spec = cmd[-3], cmd[-2], json.loads(cmd[-1])
    n, z = int(re.search(r"exit_(\d+)", tal_file).group(1)), len(spec["depths"])
    np.savez(out, **{m: _theirs(n, z, m) for m in spec["methods"]})
    record = {"tal_version": "0.20.0", **{m: {"times_s": [2.0, 1.0]} for m in spec["methods"]}}
    return subprocess.CompletedProcess(cmd, 0, stdout=json.dumps(record) + "\n", stderr="")

  def ours(transient, setup, method, repeats):
    return _ours(transient.shape[-1], len(setup.depths), method), [0.5] * repeats, 1.0

  monkeypatch.setattr(peer_tal.subprocess, "run", run)
  monkeypatch.setattr(peer_tal, "run_ours", ours)


def _table(text: str) -> dict[tuple[str, str], list[str]]:
  rows = [[c.strip() for c in line.strip("|").split("|")] for line in text.splitlines()
          if line.startswith("| ") and "x" in line.split("|")[1]]
  return {(r[0], r[1]): r for r in rows}


def test_fk_is_compared_as_amplitudes_and_ytal_fbp_against_our_phasor(fake, tmp_path):
  out = tmp_path / "peer_tal.md"
  assert peer_tal.main(["--ytal-python", "fake", "--grids", "16", "32", "--ytal-fbp-max-grid", "16",
                        "--out", str(out)]) == 0
  text, record = out.read_text(), json.loads(out.with_suffix(".json").read_text())
  rows = _table(text)
  for n in (16, 32):
    ours = record["grids"][str(n)]["nlosjax"]
    # Both f-k volumes are |.|^2: compared in one unit they agree exactly (ours square-rooted alone: 0.994).
    assert ours["fk"]["ncc_front"] == pytest.approx(1.0, abs=1e-6)
    assert rows[(f"{n} x {n}", "fk")][2:] == ["fk", "0.500", "1.000", "2.0x", "1.000"]
    assert ours["phasor"]["ncc_front"] == pytest.approx(1.0, abs=1e-6)
  # y-tal's fbp ran at 16 x 16: its row times two algorithms, its NCC is against our phasor.
  ours16 = record["grids"]["16"]["nlosjax"]
  assert ours16["phasor"]["ncc_front_ytal_fbp"] == pytest.approx(1.0, abs=1e-6)
  assert "ncc_front" not in ours16["fbp"] and ours16["fbp"]["ncc_front_different_algorithm"] < 0.5
  assert rows[("16 x 16", "fbp")][2:] == ["fbp (a different algorithm: times only)", "0.500", "1.000", "2.0x",
                                          "1.000 against our phasor"]
  # Above --ytal-fbp-max-grid: timed on our side only, no NCC.
  assert rows[("32 x 32", "fbp")][2:] == ["fbp", "0.500", "not run (above --ytal-fbp-max-grid 16)", "—", "—"]
  assert "ncc_front_ytal_fbp" not in record["grids"]["32"]["nlosjax"]["phasor"]


def test_the_results_text_names_ytal_fk_differences_from_the_public_code(fake, tmp_path):
  out = tmp_path / "peer_tal.md"
  peer_tal.main(["--ytal-python", "fake", "--grids", "16", "--out", str(out)])
  text = " ".join(out.read_text().split())
  assert "Produced by `python -m benchmarks.peer_tal --grids 16`." in text
  assert "y-tal 0.20.0's ``fk`` carries a Jacobian bug fixed upstream in commit e720f12 (2025-09-24" in text
  assert "``tau t`` where the public MATLAB code (and ours) uses ``sqrt(tau t^2)``" in text
  assert "the f-k NCC measures those two differences too" in text
  assert "its NCC is y-tal's ``fbp`` against our phasor" in text


def test_amplitude_square_roots_fk_volumes_only():
  v = np.array([4.0, 9.0, -1.0])
  np.testing.assert_array_equal(peer_tal.amplitude(v, "fk"), [2.0, 3.0, 0.0])
  np.testing.assert_array_equal(peer_tal.amplitude(v, "pf"), v)


def _ytal_fk_twin(transient, scan_half_width: float, bin_length: float) -> np.ndarray:
  """y-tal's f-k written from its published algorithm (``tal/reconstruct/fk``, master after commit
  ``e720f12``), with its own conventions: ``[T, N, N]`` counts -> ``[T, N, N]`` ``|.|^2`` volume.

  The input weighted by ``tau * t_n`` (``t_n = linspace(0, 1, T)``), zero-padded to
  ``2T x 2N x 2N``; the centred spectrum resampled linearly at
  ``f = sqrt((N T Delta / (4 T w))^2 (kx^2 + ky^2) + kz^2)`` (normalised frequencies, ``w`` the
  scan grid's last x, ``Delta`` the bin's path length), kept where ``kz > 0`` and weighted by
  ``|kz| / f``; the inverse transform's ``|.|^2``, cropped to the first octant.
  """
  from scipy.interpolate import interpn
  t_bins, n = transient.shape[0], transient.shape[1]
  z, y, x = np.mgrid[-t_bins:t_bins, -n:n, -n:n].astype(np.float64)
  z, y, x = z / t_bins, y / n, x / n
  t_n = np.linspace(0.0, 1.0, t_bins)[:, None, None]
  padded = np.zeros((2 * t_bins, 2 * n, 2 * n))
  padded[:t_bins, :n, :n] = np.abs(transient * t_n)
  spectrum = np.fft.fftshift(np.fft.fftn(padded))
  scale = n * t_bins * bin_length / (t_bins * scan_half_width * 4)
  f = np.sqrt(scale ** 2 * (x ** 2 + y ** 2) + z ** 2)
  axes = (z[:, 0, 0], y[0, :, 0], x[0, 0, :])
  resampled = interpn(axes, spectrum, np.stack([f, y, x], axis=-1), method="linear",
                      bounds_error=False, fill_value=0.0)
  resampled *= (z > 0) * np.abs(z) / np.maximum(f, 1e-8)
  volume = np.abs(np.fft.ifftn(np.fft.ifftshift(resampled))) ** 2
  return volume[:t_bins, :n, :n]


def test_our_fk_is_ytals_fk_algorithm_given_its_input_weight():
  """Where the algorithms match they agree: y-tal's f-k (with the Jacobian fixed upstream after
  0.20.0) weights the input by ``tau * t``, ours by ``sqrt(tau t^2)`` as the public nlos-fk code;
  fed ``tau^2`` ours sees y-tal's weight, and the two front views (amplitudes) then agree at NCC
  1 to four digits on the shipped exit-sign scan at 16 x 16 (the benchmark's capture)."""
  import math

  from nlosjax import physics
  from nlosjax.data import io
  transient, setup = io.load_measurement(io.shipped_scan_path(), spatial_factor=4)
  x = np.asarray(transient, np.float64)
  first = math.ceil(4 * setup.wall_size / (setup.grid[0] - 1) / setup.depth_bin_length)
  theirs = _ytal_fk_twin(x.transpose(0, 2, 1), float(setup.scan_x[-1]),
                         299792458.0 * setup.bin_width).transpose(0, 2, 1)
  ours = np.asarray(physics.reconstruct((x ** 2).astype(np.float32), setup, "fk"), np.float64)

  def front(v):
    a = np.sqrt(np.maximum(v[first:], 0.0)).max(axis=0)
    return a - a.mean()

  a, b = front(ours), front(theirs)
  assert float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum())) > 0.9999

"""The operator-variant study: ``variant="public"`` against ``"refined"`` on point scatterers and the shipped scans."""

from __future__ import annotations

import statistics
import time

import numpy as np

from benchmarks.physics.report import ncc
from nlosjax.physics.forward import render_points
from nlosjax.physics.setup import Setup

#: ``(method, options)`` rows of the variant study.
VARIANT_ROWS = (
    ("fbp", {"variant": "public"}), ("fbp", {"variant": "refined"}),
    ("lct", {"variant": "public"}), ("lct", {"variant": "refined"}),
    ("lct", {"variant": "refined", "oversample": 2}),
    ("fk", {"variant": "public"}), ("fk", {"variant": "refined"}),
    ("phasor", {"variant": "public"}), ("phasor", {"variant": "refined"}),
)
#: The point-scatterer capture of the study: 16 x 16 scan points on a 2 m wall, 512 x 32 ps.
POINT_SETUP = dict(wall_size=2.0, grid=(16, 16), bin_width=32e-12, num_bins=512)


def _peak(vol: np.ndarray) -> tuple[int, int, int]:
  return tuple(int(i) for i in np.unravel_index(int(np.argmax(vol)), vol.shape))


def variant_study(num_points: int = 16, seed: int = 0, repeats: int = 3) -> dict:
  """Point-scatterer errors and measured-scan times of every row of :data:`VARIANT_ROWS`.

  Points: ``num_points`` single scatterers, lateral position uniform in the
  central 70 % of the wall, depth uniform in 0.5-1.5 m, each rendered alone
  (noise-free, :func:`render_points`); the error is the volume's peak against
  the true depth bin (fractional) and the nearest scan point. Measured scans:
  the two shipped ones at full counts, median warm time of ``repeats`` runs and
  the max-projection NCC against the public variant's.
  """
  import jax

  from nlosjax.data import io
  from nlosjax.physics import reconstruct

  setup = Setup(**POINT_SETUP)
  rng = np.random.default_rng(seed)
  half = 0.35 * setup.wall_size
  pts = np.stack([rng.uniform(-half, half, num_points), rng.uniform(-half, half, num_points),
                  rng.uniform(0.5, 1.5, num_points)], axis=1)
  transients = np.stack([render_points(p[None], np.ones(1), setup) for p in pts]).astype(np.float32)
  true_k = pts[:, 2] / setup.depth_bin_length
  true_i = np.array([np.argmin(np.abs(setup.scan_y - p[1])) for p in pts])
  true_j = np.array([np.argmin(np.abs(setup.scan_x - p[0])) for p in pts])
  scans = [io.load_measurement(io.shipped_scan_path(name)) for name in io.SHIPPED_SCAN_NAMES]
  rows, public_mips = [], {}
  for method, opts in VARIANT_ROWS:
    vols = np.asarray(reconstruct(transients, setup, method, **opts))
    peaks = np.array([_peak(v) for v in vols])
    depth_err = peaks[:, 0] - true_k
    lateral = np.abs(peaks[:, 1] - true_i) + np.abs(peaks[:, 2] - true_j)
    row = {"method": method, "options": opts, "depth_bias": float(depth_err.mean()),
           "depth_mae": float(np.abs(depth_err).mean()), "depth_max": float(np.abs(depth_err).max()),
           "lateral_mean": float(lateral.mean()), "scans": []}
    for (transient, capture), name in zip(scans, io.SHIPPED_SCAN_NAMES):
      fn = jax.jit(lambda v, c=capture: reconstruct(v, c, method, **opts))
      x = jax.device_put(transient)
      mip = np.asarray(fn(x)).max(0)
      times = []
      for _ in range(repeats):
        t0 = time.perf_counter()
        fn(x).block_until_ready()
        times.append(time.perf_counter() - t0)
      if opts.get("variant") == "public":
        public_mips[(method, name)] = mip
      ref = public_mips.get((method, name))
      row["scans"].append({"name": name, "run_s": statistics.median(times),
                           "ncc_public": ncc(mip, ref) if ref is not None else None})
    rows.append(row)
  return {"rows": rows, "num_points": num_points, "setup": setup}

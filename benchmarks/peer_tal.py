"""Our phasor, f-k and FBP against y-tal's ``pf``, ``fk`` and ``fbp``: ``benchmarks/results/peer_tal.md``.

    NLOSJAX_YTAL_PYTHON=/tmp/ytal-venv/bin/python python -m benchmarks.peer_tal [--grids 16 32 64]
        [--repeats 1] [--ytal-fbp-max-grid 32]        # or --ytal-python PATH

y-tal (PyPI ``y-tal``) lives in an environment of its own (it pins numpy < 2
and needs ``pyfftw``, which it does not declare)::

    python3.11 -m venv /tmp/ytal-venv && /tmp/ytal-venv/bin/pip install y-tal==0.20.0 pyfftw

The capture is the shipped exit-sign scan (O'Toole et al. 2018), its scan grid
summed to ``n x n`` (``load_measurement(..., spatial_factor=64 // n)``; 512
bins of 16 ps), written as a TAL file by :func:`nlosjax.data.io.save_tal`. Our
methods read it as ``[T, H, W]`` and run through ``nlosjax.physics.reconstruct``
in this process; y-tal's run in its own Python on ``tal.io.read_capture`` of
the same file, under a memory cap (``--ytal-memory-gib``, so a method that
needs more fails alone instead of pushing other work off the machine). Each
method runs once cold, then ``--repeats`` times warm; the best warm time is
reported, for both libraries in the same run. y-tal's ``fbp`` (a
backprojection over every voxel and scan point) runs only up to
``--ytal-fbp-max-grid`` scan points per side.

Conventions matched: the same transient, grid and bins (the TAL file); the
voxels of ``pf`` and ``fbp`` are our volume's (each scan point's ``(x, y)``
at our depth bins' ``z_k = k c bin_width / 2``, ``tal.reconstruct.get_volume_project_rw``);
our phasor's virtual wavelength and cycles (``2 sampling_coeff x spacing``,
5 cycles) passed to ``pf`` and as ``fbp``'s filter. y-tal's ``fk`` chooses its
own output grid (``[T, Sx, Sy]``). Agreement: normalised cross-correlation of
the front maximum projections (over depth, ``[H, W]``; y-tal's ``[Sx, Sy]``
transposed onto ours), of magnitudes (both f-k volumes are ``|.|^2``: the
square root of each, amplitudes, as our f-k's images are made), over the
depths at least one virtual wavelength from the wall (y-tal's ``pf`` divides
by each voxel's distance to the scan points, so its voxels on and near the
wall plane, NaN on it, outshine the scene).

f-k is one algorithm on both sides, but y-tal 0.20.0's ``fk`` carries a
Jacobian bug fixed upstream in commit e720f12 (2025-09-24, unreleased at
0.20.0: it weights the Stolt resampling by ``|k_z|``, not ``k_z / f``) and
weights the input by ``tau t`` where the public MATLAB code (and ours) uses
``sqrt(tau t^2)``; the f-k NCC measures those two differences too. FBP names
different algorithms: y-tal's ``fbp`` filters each histogram in time with the
phasor-field wavelet, backprojects without falloff and takes ``|.|`` (the
algorithm of our phasor), our FBP is the LCT backprojection (``t^4`` weight)
filtered by a 3-D Laplacian of Gaussian. Its row compares times only; its NCC
is y-tal's ``fbp`` against our phasor.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

from experiments import provenance as _machine

ROOT = pathlib.Path(__file__).resolve().parent.parent
DEFAULT_OUT = ROOT / "benchmarks" / "results" / "peer_tal.md"
OURS_TO_TAL = {"phasor": "pf", "fk": "fk", "fbp": "fbp"}
#: Our method that computes each y-tal method's algorithm: the one its NCC is taken against.
SAME_ALGORITHM = {"pf": "phasor", "fk": "fk", "fbp": "phasor"}
CYCLES, SAMPLING_COEFF = 5.0, 2.0

#: Run by y-tal's Python: ``WORKER TAL_FILE OUT.npz SPEC_JSON``; prints one JSON line of times.
WORKER = r"""
import json, sys, time
import numpy as np
import tal, tal.io, tal.reconstruct
from tal.enums import CameraSystem

path, out, spec = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
depths = np.asarray(spec["depths"], np.float64)
record, volumes = {"tal_version": tal.__version__}, {}
for method in spec["methods"]:
  times = []
  try:
    for _ in range(spec["repeats"] + 1):
      data = tal.io.read_capture(path)
      volume_xyz = tal.reconstruct.get_volume_project_rw(data, depths=list(depths))
      t0 = time.perf_counter()
      if method == "pf":
        vol = tal.reconstruct.pf.solve(data, spec["wavelength"], spec["cycles"],
                                       camera_system=CameraSystem.DIRECT_LIGHT, volume=volume_xyz)
      elif method == "fk":
        vol = tal.reconstruct.fk.solve(data)
      else:
        vol = tal.reconstruct.fbp.solve(data, wl_mean=spec["wavelength"], wl_sigma=spec["wavelength"] / np.sqrt(2),
                                        volume_xyz=volume_xyz, camera_system=CameraSystem.DIRECT_LIGHT,
                                        progress=False)
      times.append(time.perf_counter() - t0)
    vol = np.abs(np.asarray(vol))
    record[method] = {"times_s": times, "shape": list(np.shape(vol)), "nan_voxels": int(np.isnan(vol).sum())}
    volumes[method] = np.nan_to_num(vol, nan=0.0).astype(np.float32)
  except MemoryError as e:
    record[method] = {"error": f"MemoryError {e}"}
  except Exception as e:
    record[method] = {"error": f"{type(e).__name__}: {e}"[:300]}
np.savez(out, **volumes)
print(json.dumps(record))
"""


def _method_text() -> str:
  """What the results file says about the setup: the docstring's paragraphs after the commands."""
  return " ".join(p.replace("\n", " ") for p in __doc__.split("\n\n")[4:])


def ncc(a: np.ndarray, b: np.ndarray) -> float:
  """Normalised cross-correlation of two images of one shape."""
  a, b = a - a.mean(), b - b.mean()
  return float((a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum()))


def amplitude(volume: np.ndarray, method: str) -> np.ndarray:
  """``volume`` as amplitudes: f-k's (ours and y-tal's, both ``|.|^2``) square-rooted, others as they are."""
  return np.sqrt(np.maximum(volume, 0)) if method == "fk" else volume


def front(volume: np.ndarray, depth_axis: int, first: int) -> np.ndarray:
  """The maximum projection over depth bins ``first`` onwards."""
  kept = np.take(np.abs(volume), np.arange(first, volume.shape[depth_axis]), axis=depth_axis)
  return kept.max(axis=depth_axis)


def run_ours(transient, setup, method: str, repeats: int) -> tuple[np.ndarray, list[float], float]:
  from nlosjax import physics
  t0 = time.perf_counter()
  vol = np.asarray(physics.reconstruct(transient, setup, method))
  cold = time.perf_counter() - t0
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    vol = np.asarray(physics.reconstruct(transient, setup, method))
    times.append(time.perf_counter() - t0)
  return vol, times, cold


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--ytal-python", default=os.environ.get("NLOSJAX_YTAL_PYTHON"),
                      help="a Python with y-tal installed (default: $NLOSJAX_YTAL_PYTHON)")
  parser.add_argument("--grids", type=int, nargs="+", default=[16, 32, 64],
                      help="scan points per side (default: %(default)s)")
  parser.add_argument("--repeats", type=int, default=1, help="warm runs per method (default: %(default)s)")
  parser.add_argument("--ytal-memory-gib", type=float, default=6.0,
                      help="y-tal's address-space cap (default: %(default)s)")
  parser.add_argument("--ytal-fbp-max-grid", type=int, default=32,
                      help="largest grid y-tal's fbp runs on (default: %(default)s)")
  parser.add_argument("--out", default=str(DEFAULT_OUT), help="Markdown output (a .json beside it)")
  args = parser.parse_args(argv)
  if not args.ytal_python:
    raise SystemExit("peer_tal: name a Python with y-tal installed (--ytal-python or NLOSJAX_YTAL_PYTHON)")
  from nlosjax.data import io
  rows, record = [], {"grids": {}}
  with tempfile.TemporaryDirectory() as tmp:
    for n in args.grids:
      if 64 % n:
        raise SystemExit(f"--grids: {n} does not divide the exit sign's 64 scan points")
      transient, setup = io.load_measurement(io.shipped_scan_path(), spatial_factor=64 // n)
      path = io.save_tal(pathlib.Path(tmp) / f"exit_{n}.hdf5", transient, setup)
      spacing = setup.wall_size / (n - 1)
      methods = [m for m in OURS_TO_TAL.values() if m != "fbp" or n <= args.ytal_fbp_max_grid]
      spec = {"methods": methods, "repeats": args.repeats, "depths": setup.depths.tolist(),
              "wavelength": 2 * SAMPLING_COEFF * spacing, "cycles": CYCLES}
      cap = int(args.ytal_memory_gib * 2**20)
      cmd = ["bash", "-c", f'ulimit -v {cap}; exec "$0" -c "$1" "$2" "$3" "$4"', args.ytal_python, WORKER,
             str(path), str(pathlib.Path(tmp) / f"tal_{n}.npz"), json.dumps(spec)]
      proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
      if proc.returncode != 0:
        raise SystemExit(f"y-tal worker failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
      theirs = json.loads(proc.stdout.strip().splitlines()[-1])
      tal_volumes = dict(np.load(pathlib.Path(tmp) / f"tal_{n}.npz"))
      grid_record = {"shape": list(transient.shape), "wall_size": setup.wall_size, "bin_width": setup.bin_width,
                     "ytal": theirs, "nlosjax": {}}
      ours_fronts = {}
      for ours_name, tal_name in OURS_TO_TAL.items():
        vol, times, cold = run_ours(transient, setup, ours_name, args.repeats)
        grid_record["nlosjax"][ours_name] = {"times_s": times, "cold_s": cold}
        first = math.ceil(spec["wavelength"] / setup.depth_bin_length)       # a wavelength from the wall
        ours_fronts[ours_name] = front(amplitude(vol, ours_name), 0, first)    # [H, W]
        t = theirs.get(tal_name, {"error": f"not run (above --ytal-fbp-max-grid {args.ytal_fbp_max_grid})"})
        if "error" in t:
          rows.append((n, ours_name, tal_name, min(times), None, None, t["error"]))
          continue
        tal_warm = min(t["times_s"][1:]) if len(t["times_s"]) > 1 else t["times_s"][0]
        tal_vol = amplitude(tal_volumes[tal_name], tal_name)
        tal_front = front(tal_vol, 0 if tal_name == "fk" else 2, first).T    # [Sx, Sy] -> [H, W]
        agreement = ncc(ours_fronts[SAME_ALGORITHM[tal_name]], tal_front)
        if SAME_ALGORITHM[tal_name] == ours_name:
          grid_record["nlosjax"][ours_name]["ncc_front"] = agreement
        else:                                    # fbp: the NCC of the pair of names, a different algorithm each
          grid_record["nlosjax"][ours_name]["ncc_front_different_algorithm"] = ncc(ours_fronts[ours_name], tal_front)
          grid_record["nlosjax"][SAME_ALGORITHM[tal_name]][f"ncc_front_ytal_{tal_name}"] = agreement
        rows.append((n, ours_name, tal_name, min(times), tal_warm, agreement, ""))
        print(f"{n}x{n} {ours_name}: ours {min(times):.3f} s, y-tal {tal_name} {tal_warm:.3f} s,"
              f" NCC {agreement:.3f} against our {SAME_ALGORITHM[tal_name]}", flush=True)
      record["grids"][str(n)] = grid_record
  command = "python -m benchmarks.peer_tal" + "".join(
      f" --{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, list) else v}"
      for k in ("grids", "repeats", "ytal_memory_gib", "ytal_fbp_max_grid")
      if (v := getattr(args, k)) != parser.get_default(k))
  lines = ["# Side by side with y-tal: phasor, f-k and FBP on the same TAL capture", ""]
  lines += _machine.provenance(command) + [""]
  lines += [f"y-tal {theirs.get('tal_version', '?')} (its Python named by --ytal-python or NLOSJAX_YTAL_PYTHON)."
            f" {_method_text()}", "",
            "| scan points | ours | y-tal | ours, warm (s) | y-tal, warm (s) | y-tal / ours | NCC, front views |",
            "|---|---|---|---|---|---|---|"]
  for n, ours_name, tal_name, ours_t, tal_t, agreement, error in rows:
    if error:
      lines.append(f"| {n} x {n} | {ours_name} | {tal_name} | {ours_t:.3f} | {error} | — | — |")
    elif SAME_ALGORITHM[tal_name] == ours_name:
      lines.append(f"| {n} x {n} | {ours_name} | {tal_name} | {ours_t:.3f} | {tal_t:.3f} | {tal_t / ours_t:.1f}x |"
                   f" {agreement:.3f} |")
    else:
      lines.append(f"| {n} x {n} | {ours_name} | {tal_name} (a different algorithm: times only) | {ours_t:.3f} |"
                   f" {tal_t:.3f} | {tal_t / ours_t:.1f}x | {agreement:.3f} against our {SAME_ALGORITHM[tal_name]} |")
  lines += ["", "Times are the best of the warm runs, both libraries measured in this one run; a machine with"
            " other jobs (load average above) slows both."]
  text = "\n".join(lines) + "\n"
  print(text)
  pathlib.Path(args.out).write_text(text)
  pathlib.Path(args.out).with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
  print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

"""Reconstruct the shipped measured scan with every classic method: a first look, no training, no weights.

    python -m experiments.demo [--out runs/demo] [--scan FILE]

Loads the O'Toole et al. 2018 exit-sign scan (``nlosjax/data/scans``), runs
FBP, LCT, f-k, phasor and RSD (jitted; compile and run time reported
separately), and writes ``intensity_depth.png`` (one row per method:
intensity and depth) and ``timings.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import numpy as np

from nlosjax import physics
from nlosjax.data import io

# The exit sign is retroreflective (O'Toole et al.: snr 0.8, t^2 falloff).
OPTIONS = {"fbp": dict(falloff="retroreflective"), "lct": dict(snr=0.8, falloff="retroreflective"),
           "fk": {}, "phasor": {}, "rsd": {}}


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--out", default="runs/demo", help="output folder")
  parser.add_argument("--scan", default=None, help="a measured scan (default: the shipped exit sign)")
  parser.add_argument("--depth-range", nargs=2, type=float, default=(0.2, 1.5), metavar=("ZMIN", "ZMAX"),
                      help="reconstruct only these depths, metres")
  from experiments import xla_cache
  xla_cache.add_argument(parser)
  args = parser.parse_args(argv)
  xla_cache.enable_unless(args.no_cache)     # before anything compiles
  out = pathlib.Path(args.out)
  out.mkdir(parents=True, exist_ok=True)

  transient, setup = io.load_measurement(args.scan or io.shipped_scan_path())
  setup = setup.with_depth_range(*args.depth_range)
  print(f"scan {transient.shape} (T, H, W), wall {setup.wall_size} m, bins {setup.bin_width * 1e12:.0f} ps,"
        f" depths {args.depth_range} m -> {setup.num_depth_bins} bins, backend {jax.default_backend()}")
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  fig, axes = plt.subplots(len(OPTIONS), 2, figsize=(5, 2.4 * len(OPTIONS)), squeeze=False)
  timings = {}
  for row, (method, opts) in enumerate(OPTIONS.items()):
    fn = jax.jit(lambda x, m=method, o=opts: physics.reconstruct(x, setup, m, **o))
    t0 = time.perf_counter()
    compiled = fn.lower(transient).compile()
    t1 = time.perf_counter()
    volume = jax.block_until_ready(compiled(transient))
    t2 = time.perf_counter()
    if method == "fk":
      volume = np.sqrt(volume)  # f-k returns albedo squared
    intensity, depth = physics.intensity_depth(volume, setup)
    timings[method] = {"compile_s": t1 - t0, "run_s": t2 - t1}
    print(f"{method:7s} compile {t1 - t0:6.2f} s   run {t2 - t1:6.3f} s")
    extent = [setup.scan_x[0], setup.scan_x[-1], setup.scan_y[0], setup.scan_y[-1]]
    axes[row, 0].imshow(np.asarray(intensity), cmap="gray", origin="upper", extent=extent)
    im = axes[row, 1].imshow(np.asarray(depth), cmap="viridis", origin="upper", extent=extent,
                             vmin=args.depth_range[0], vmax=args.depth_range[1])
    axes[row, 0].set_ylabel(method)
    for ax in axes[row]:
      ax.set_xticks([])
      ax.set_yticks([])
  axes[0, 0].set_title("intensity")
  axes[0, 1].set_title("depth (m)")
  fig.colorbar(im, ax=axes[:, 1], shrink=0.5)
  fig.savefig(out / "intensity_depth.png", dpi=100)
  (out / "timings.json").write_text(json.dumps(timings, indent=2))
  print(f"wrote {out / 'intensity_depth.png'} and {out / 'timings.json'}")


if __name__ == "__main__":
  main()

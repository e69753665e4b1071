"""Simulate a dynamic NLOS dataset into one HDF5 file.

    python -m experiments.make_dataset [--config cpu|paper] [--out FILE] [--overwrite]
        [--sequences N | --train N --val K --test M] [--frames F] [--seed S] [--workers W]
        [--clean | --no-clean] [--albedo] [--quiet]

Reads the ``data`` section of the preset (``experiments/configs``), applies the
flags, and calls :func:`nlosjax.data.dataset.write_dataset` (progress bar,
crash-safe: it writes ``FILE.partial`` and renames it when done; rerunning
after a crash resumes it). An existing ``FILE`` is kept unless ``--overwrite``.
The layout is documented in the README (section "Dynamic NLOS dataset").
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

from experiments import configs
from nlosjax.data import dataset


def _split_counts(total: int, train: int, val: int, test: int) -> tuple[int, int, int]:
  """Split ``total`` sequences in the preset's train:val:test proportion.

  At least 1 test sequence from 2 sequences on, at least 1 validation
  sequence from 4 on (where the preset has the split), at least 1 train.
  """
  if total < 1:
    raise ValueError(f"--sequences must be >= 1, got {total}")
  whole = max(train + val + test, 1)
  n_test = round(total * test / whole)
  n_test = min(max(n_test, 1 if total >= 2 and test > 0 else 0), total - 1 if total >= 2 else 0)
  n_val = round(total * val / whole)
  n_val = min(max(n_val, 1 if total >= 4 and val > 0 else 0), max(total - n_test - 1, 0))
  return total - n_test - n_val, n_val, n_test


def build_spec(args) -> tuple[dataset.DatasetSpec, pathlib.Path]:
  """The DatasetSpec and output path from parsed arguments."""
  data = configs.get_config(args.config)["data"]
  counts = dict(data.get("num_sequences", {}))
  train, val, test = counts.get("train", 0), counts.get("val", 0), counts.get("test", 0)
  if args.sequences is not None:
    train, val, test = _split_counts(args.sequences, train, val, test)
  if args.train is not None:
    train = args.train
  if args.val is not None:
    val = args.val
  if args.test is not None:
    test = args.test
  overrides = {"num_train": train, "num_val": val, "num_test": test}
  if args.frames is not None:
    overrides["frames"] = args.frames
  if args.seed is not None:
    overrides["seed"] = args.seed
  if args.clean is not None:
    overrides["store_clean"] = args.clean
  if args.albedo:
    overrides["store_albedo"] = True
  spec = dataset.DatasetSpec.from_config(data, **overrides)
  out = pathlib.Path(args.out or data.get("path") or f"runs/data/{args.config}.h5")
  return spec, out


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--config", default=configs.DEFAULT, choices=configs.PRESETS,
                      help="preset whose data section to use (default: %(default)s)")
  parser.add_argument("--out", default=None, help="output HDF5 file (default: the preset's data.path)")
  parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
  parser.add_argument("--sequences", "--num-sequences", type=int, default=None,
                      help="total sequences, split train:val:test as in the preset")
  parser.add_argument("--train", type=int, default=None, help="training sequences")
  parser.add_argument("--val", type=int, default=None,
                      help="validation sequences (every choice is made on them)")
  parser.add_argument("--test", type=int, default=None, help="test sequences")
  parser.add_argument("--frames", type=int, default=None, help="frames per sequence")
  parser.add_argument("--seed", type=int, default=None, help="base seed")
  parser.add_argument("--workers", type=int, default=1,
                      help="processes simulating sequences in parallel (default: 1)")
  clean = parser.add_mutually_exclusive_group()
  clean.add_argument("--clean", dest="clean", action="store_true", default=None,
                     help="store the noise-free transients")
  clean.add_argument("--no-clean", dest="clean", action="store_false",
                     help="do not store the noise-free transients")
  parser.add_argument("--albedo", action="store_true", help="also store the albedo volumes")
  parser.add_argument("--quiet", action="store_true", help="no progress bar")
  args = parser.parse_args(argv)

  try:
    spec, out = build_spec(args)
  except ValueError as e:
    parser.error(str(e))
  if out.exists() and not args.overwrite:
    print(f"error: {out} exists; pass --overwrite to replace it", file=sys.stderr)
    return 2
  s = spec.setup
  print(f"{args.config}: {spec.num_train} train + {spec.num_val} val + {spec.num_test} test sequences"
        f" x {spec.frames} frames;"
        f" grid {s.grid[0]}x{s.grid[1]}, {s.num_bins} bins of {s.bin_width * 1e12:.0f} ps,"
        f" wall {s.wall_size} m; clean {'on' if spec.store_clean else 'off'} -> {out}")
  t0 = time.perf_counter()
  result = dataset.write_dataset(out, spec, overwrite=args.overwrite, workers=args.workers,
                                 progress=not args.quiet)
  dt = time.perf_counter() - t0
  resumed = f", {result.resumed} kept from an interrupted run" if result.resumed else ""
  print(f"wrote {out} ({out.stat().st_size / 2**20:.1f} MiB) in {dt:.1f} s: {result.generated}"
        f" sequences simulated ({60 * result.generated / max(dt, 1e-9):.1f}/min){resumed}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

"""Evaluate trained models and the classic methods on a dataset file: Table 1 for any HDF5 file.

Usage::

  python -m experiments.evaluate --checkpoint runs/default --data runs/data/cpu.h5
  python -m experiments.evaluate --checkpoint runs/default/ours --data other.h5 --out runs/eval

``--checkpoint`` is a main-job workdir (every trained variant in it is
evaluated), one variant's folder (``WORKDIR/ours``) or its ``checkpoints``
folder. ``--data`` is any file in the documented dataset layout (README,
"Dynamic NLOS dataset"), not only ones our generator made; the models are
moved to the file's Setup (same parameters, physics layer rebuilt) and the
classic methods get the under-scanned input interpolated to the full grid,
as in the paper. Prints the table and writes ``OUT/table.md``,
``OUT/table.json`` (method -> metric -> [mean, std]) and ``OUT/comparison.png``.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time


def main(argv=None) -> dict:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--checkpoint", required=True,
                      help="training workdir, variant folder, or its checkpoints folder")
  parser.add_argument("--data", required=True, help="HDF5 dataset file in the documented layout")
  parser.add_argument("--split", default="test", help="split of the file to evaluate (default test)")
  parser.add_argument("--out", default=None,
                      help="output folder (default: <workdir>/eval_<data file stem>)")
  parser.add_argument("--classic", default="fbp,lct,fk,phasor,rsd",
                      help="comma-separated classic methods to include ('' for none)")
  args = parser.parse_args(argv)

  from nlosjax import checkpoints_io, train
  from nlosjax.data.dataset import open_dataset
  t0 = time.perf_counter()
  data = pathlib.Path(args.data)
  if not data.is_file():
    raise SystemExit(f"--data {data}: no such file")
  classic = tuple(m for m in args.classic.split(",") if m)
  unknown = set(classic) - set(train.CLASSIC_METHODS)
  if unknown:
    raise SystemExit(f"--classic: unknown method(s) {sorted(unknown)}; known {train.CLASSIC_METHODS}")
  try:
    with open_dataset(data) as ds:
      setup = ds.setup
      if not ds.names(args.split):
        raise ValueError(f"{data}: no sequence in split {args.split!r}")
    config, trained = checkpoints_io.load_run(args.checkpoint, setup=setup)
    config = train.with_defaults(config)
    table, images = train.evaluate(config, data, trained, split=args.split, methods=classic)
  except ValueError as e:
    raise SystemExit(f"error: {e}") from None
  workdir, _, _ = checkpoints_io.find_checkpoints(args.checkpoint)
  out = pathlib.Path(args.out) if args.out else workdir / f"eval_{data.stem}"
  caption = (f"`{args.split}` split of `{data}` ({len(images['gt']['intensity'])} frames); "
             f"models from `{args.checkpoint}`; evaluated in {time.perf_counter() - t0:.0f} s.")
  train.write_results(table, images, out, caption=caption)
  print(f"results written to {out}")
  return table


if __name__ == "__main__":
  sys.exit(main() is None)

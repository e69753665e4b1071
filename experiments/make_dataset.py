"""Simulate a dynamic NLOS dataset into one HDF5 file: the one ``python -m experiments.train`` makes.

    python -m experiments.make_dataset [--config NAME|FILE.py] [--config.section.key=value ...]
        [--out FILE] [--overwrite] [--sequences N | --train N --val K --test M] [--frames F]
        [--seed S] [--workers W] [--clean | --no-clean] [--albedo] [--quiet]

Reads the config as ``python -m experiments.train`` does (:mod:`experiments.cli`:
a preset of ``experiments/configs`` or a ``.py`` file, read by
``ml_collections.config_flags`` with the ``--config.section.key=value`` overrides;
an unknown key or a bad value exits naming it before anything is simulated),
applies the flags below, and
calls :func:`nlosjax.data.dataset.write_dataset` with
``DatasetSpec.from_config(config["data"])`` at ``config["data"]["path"]``
(progress bar, crash-safe: it writes ``FILE.partial`` and renames it when done;
rerunning after a crash resumes it). So with the same ``--config`` and
overrides, e.g. ``--config.data.renderer=lct --config.data.retroreflective=0.0``,
it writes the file that train would make for itself. An existing ``FILE`` is
kept unless ``--overwrite``. The layout is documented in ``docs/dataset.md``.

The flags are shorthands of config keys: ``--out`` of ``data.path``, ``--frames``
of ``data.frames``, ``--seed`` of ``data.seed``, ``--train/--val/--test`` of
``data.num_sequences.{train,val,test}``, ``--clean/--no-clean`` of
``data.store_clean``, ``--albedo`` of ``data.store_albedo`` and ``--workers``
of ``train.data_workers`` (default: the config's, else 1); ``--sequences N``
splits N in the config's ``num_sequences`` proportion (``--train/--val/--test``
then replace single counts). A flag and an override of the same key exit
(give one of them).
"""

from __future__ import annotations

import pathlib
import sys
import time

from experiments import cli, configs
from nlosjax.data import dataset


def _split_counts(total: int, train: int, val: int, test: int) -> tuple[int, int, int]:
  """Split ``total`` sequences in the config's train:val:test proportion.

  At least 1 test sequence from 2 sequences on, at least 1 validation
  sequence from 4 on (where the config has the split), at least 1 train.
  """
  if total < 1:
    raise ValueError(f"--sequences must be >= 1, got {total}")
  whole = max(train + val + test, 1)
  n_test = round(total * test / whole)
  n_test = min(max(n_test, 1 if total >= 2 and test > 0 else 0), total - 1 if total >= 2 else 0)
  n_val = round(total * val / whole)
  n_val = min(max(n_val, 1 if total >= 4 and val > 0 else 0), max(total - n_test - 1, 0))
  return total - n_test - n_val, n_val, n_test


#: Flag (argparse dest) -> the config key it is a shorthand of.
SHORTHANDS = {
    "out": ("data", "path"), "frames": ("data", "frames"), "seed": ("data", "seed"),
    "train": ("data", "num_sequences", "train"), "val": ("data", "num_sequences", "val"),
    "test": ("data", "num_sequences", "test"), "clean": ("data", "store_clean"),
    "albedo": ("data", "store_albedo"), "workers": ("train", "data_workers"),
}


def apply_flags(args, config: dict, overrides=()) -> dict:
  """Write the shorthand flags given in ``args`` into ``config`` (in place; :data:`SHORTHANDS`).

  Raises:
    ValueError: a flag and one of ``overrides`` set the same key, or a bad ``--sequences``.
  """
  touched = [cli.override_key(arg) for arg in overrides]
  data = config.setdefault("data", {})
  counts = dict(data.get("num_sequences", {}))
  if args.sequences is not None:
    train, val, test = _split_counts(args.sequences, counts.get("train", 0), counts.get("val", 0),
                                     counts.get("test", 0))
    counts.update(train=train, val=val, test=test)
  for dest, key in SHORTHANDS.items():
    value = getattr(args, dest)
    if value is None or (dest == "albedo" and not value):
      continue
    for other in touched:
      n = min(len(other), len(key))
      if other[:n] == key[:n]:
        flag = "--" + dest if dest != "clean" else ("--clean" if value else "--no-clean")
        raise ValueError(f"{flag} and --config.{'.'.join(other)} both set {'.'.join(key)}; give one of them")
    if key[1] == "num_sequences":
      counts[key[2]] = value
    else:
      config.setdefault(key[0], {})[key[1]] = value
  if counts:
    data["num_sequences"] = counts
  return config


def build_spec(config: dict, name: str = configs.DEFAULT) -> tuple[dataset.DatasetSpec, pathlib.Path]:
  """The DatasetSpec and output path of ``config`` (after :func:`apply_flags`), as ``experiments.train`` builds them.

  ``name``: the ``--config`` argument, naming the file where the config has no ``data.path``.
  """
  data = config["data"]
  spec = dataset.DatasetSpec.from_config(data)
  out = pathlib.Path(data.get("path") or f"runs/data/{pathlib.Path(name).stem}.h5")
  return spec, out


def main(argv=None) -> int:
  parser = cli.config_parser(__doc__)
  parser.add_argument("--out", default=None, help="output HDF5 file (data.path; default: the config's)")
  parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
  parser.add_argument("--sequences", "--num-sequences", type=int, default=None,
                      help="total sequences, split train:val:test as in the config's data.num_sequences")
  parser.add_argument("--train", type=int, default=None, help="training sequences (data.num_sequences.train)")
  parser.add_argument("--val", type=int, default=None,
                      help="validation sequences, every choice is made on them (data.num_sequences.val)")
  parser.add_argument("--test", type=int, default=None, help="test sequences (data.num_sequences.test)")
  parser.add_argument("--frames", type=int, default=None, help="frames per sequence (data.frames)")
  parser.add_argument("--seed", type=int, default=None, help="base seed (data.seed)")
  parser.add_argument("--workers", type=int, default=None,
                      help="processes simulating sequences in parallel (train.data_workers; default: the"
                           " config's, else 1)")
  clean = parser.add_mutually_exclusive_group()
  clean.add_argument("--clean", dest="clean", action="store_true", default=None,
                     help="store the noise-free transients (data.store_clean=True)")
  clean.add_argument("--no-clean", dest="clean", action="store_false",
                     help="do not store the noise-free transients (data.store_clean=False)")
  parser.add_argument("--albedo", action="store_true", help="also store the albedo volumes (data.store_albedo)")
  parser.add_argument("--quiet", action="store_true", help="no progress bar")
  from experiments import xla_cache
  xla_cache.add_argument(parser)
  args, config, overrides = cli.parse_config(parser, argv)
  xla_cache.enable_unless(args.no_cache)     # before anything compiles (workers inherit the folder)

  try:
    spec, out = build_spec(apply_flags(args, config, overrides), args.config)
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
  workers = int(config.get("train", {}).get("data_workers") or 1)
  with cli.one_line_errors():        # a locked or unwritable file, a full disk: one line, exit status 2
    result = dataset.write_dataset(out, spec, overwrite=args.overwrite, workers=workers,
                                   progress=not args.quiet)
  dt = time.perf_counter() - t0
  resumed = f", {result.resumed} kept from an interrupted run" if result.resumed else ""
  print(f"wrote {out} ({out.stat().st_size / 2**20:.1f} MiB) in {dt:.1f} s: {result.generated}"
        f" sequences simulated ({60 * result.generated / max(dt, 1e-9):.1f}/min){resumed}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

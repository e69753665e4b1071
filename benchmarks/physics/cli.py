"""The command line of :mod:`benchmarks.physics` (``python -m benchmarks.physics``)."""

from __future__ import annotations

import argparse
import pathlib
import sys

from benchmarks import physics
from benchmarks.physics.cases import _jax_worker, _numpy_worker, first_line, run_case
from benchmarks.physics.report import DEFAULT_OUT, cell, fmt, ncc, write_report
from benchmarks.physics.variants import variant_study
from experiments import numpy_twins


def _jax_available() -> tuple[bool, str]:
  try:
    from nlosjax.physics import reconstruct  # noqa: F401
  except Exception as e:  # noqa: BLE001 - any import failure means: skip JAX
    return False, f"skipped: `from nlosjax.physics import reconstruct` failed ({type(e).__name__}: {first_line(e)})"
  import jax

  return True, f"`nlosjax.physics.reconstruct`, backend {jax.default_backend()} ({jax.devices()[0]})"


def parse_args(argv=None):
  p = argparse.ArgumentParser(prog="python -m benchmarks.physics", description=physics.__doc__.split("\n\n")[0])
  p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128], help="scan points per side")
  p.add_argument("--bins", type=int, default=512, help="time bins (32 ps)")
  p.add_argument("--methods", nargs="+", default=list(numpy_twins.METHODS),
                 choices=list(numpy_twins.METHODS))
  p.add_argument("--repeats", type=int, default=3, help="timed warm runs per side (median)")
  p.add_argument("--out", type=pathlib.Path, default=None,
                 help="Markdown output (default benchmarks/results/physics.md; with --quick: print only)")
  p.add_argument("--quick", action="store_true",
                 help="smoke test: 32² scan points, 128 bins, no variant study")
  p.add_argument("--time-limit", type=float, default=120.0,
                 help="seconds one step (build, compile, one run) may take before the case is recorded as a timeout")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--no-jax", action="store_true", help="time the NumPy twins only")
  p.add_argument("--no-variants", action="store_true",
                 help="skip the variant study (public vs refined operators)")
  args = p.parse_args(argv)
  if args.quick:
    args.sizes, args.bins, args.no_variants = [32], 128, True
  if args.out is None and not args.quick:
    args.out = DEFAULT_OUT
  if args.repeats < 1:
    p.error("--repeats must be >= 1")
  return args


def main(argv=None) -> int:
  args = parse_args(argv)
  command = "python -m benchmarks.physics" + (" " + " ".join(sys.argv[1:] if argv is None else argv)).rstrip()
  if args.no_jax:
    with_jax, jax_status = False, "skipped (--no-jax)"
  else:
    with_jax, jax_status = _jax_available()
  print(jax_status, flush=True)

  from tqdm import tqdm

  cases = [(n, m) for n in args.sizes for m in args.methods]
  rows, notes = [], []
  bar = tqdm(cases, desc="cases", unit="case")
  for n, method in bar:
    bar.set_postfix_str(f"{method} {n}² numpy")
    p = run_case(_numpy_worker, method, n, args.bins, args.repeats, args.seed, args.time_limit)
    j = None
    if with_jax:
      bar.set_postfix_str(f"{method} {n}² jax")
      j = run_case(_jax_worker, method, n, args.bins, args.repeats, args.seed, args.time_limit)
    row = {"method": method, "n": n, "bins": args.bins, "numpy": p, "jax": j}
    if j is not None and j.get("status") == "ok" and p.get("status") == "ok":
      row["speedup"] = p["run_s"] / j["run_s"] if j["run_s"] > 0 else None
      row["over_floor"] = j["run_s"] / j["floor_s"] if j.get("floor_s") else None
      row["ncc"] = ncc(p["mip"], j["mip"])
    for side, res in (("NumPy", p), ("JAX", j)):
      if res is None:
        continue
      if res.get("status") != "ok":
        notes.append(f"{method} {n}² {side}: {res['status']}")
        if res.get("traceback"):
          tqdm.write(res["traceback"])
      elif res.get("peak_note"):
        notes.append(f"{method} {n}² {side}: {res['peak_note']}")
    rows.append(row)
    tqdm.write(f"{method:>6} {n:>4}²: numpy {cell(p, 'run_s', '.4f')} s"
               + (f", jax {cell(j, 'run_s', '.4f')} s (compile {cell(j, 'compile_s')} s),"
                  f" speed-up {fmt(row.get('speedup'), '.2f')}, NCC {fmt(row.get('ncc'), '.3f')}"
                  if with_jax else ""))
  bar.close()
  study = None
  if with_jax and not args.no_variants:
    print("variant study ...", flush=True)
    study = variant_study()
  text = write_report(args.out, command, args, rows, with_jax, jax_status, notes, study)
  print()
  print(text)
  if args.out is not None:
    print(f"written to {args.out}")
  return 0

"""Time ``python -m experiments.reconstruct`` from a cold process: ``benchmarks/results/reconstruct_time.md``.

    python -m benchmarks.reconstruct_time [--capture nlosjax/data/scans/data_exit_sign.mat]
        [--pretrained real cpu] [--repeats 2]

What a user waits for when reconstructing a capture with a shipped model:
each method runs as its own fresh Python process with the persistent
compilation cache off (``--no-cache``), so every run pays for the imports,
building the operators, compiling and running, and writing the volume and its
figures. The learned methods use the shipped weights (``--pretrained``, each
name given: ``real`` is trained on the measured scans' geometry, ``cpu`` on a
2 m wall); three
classic methods run in the same measurement so the ratios beside the times hold on
any machine. The goal is under 10 s on 2 cores for the shipped
model on a 64 x 64 x 512 capture, compile included.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import re
import subprocess
import sys
import tempfile
import time

from experiments import provenance as _machine
from nlosjax.variants import OURS, OURS_S

ROOT = pathlib.Path(__file__).resolve().parent.parent
DEFAULT_OUT = ROOT / "benchmarks" / "results" / "reconstruct_time.md"
DEFAULT_CAPTURE = "nlosjax/data/scans/data_exit_sign.mat"
LEARNED = (OURS, OURS_S)
CLASSIC = ("lct", "phasor", "rsd")
GOAL_S = 10.0
_SHAPE = re.compile(r"\(T, H, W\) = \((\d+), (\d+), (\d+)\)")


def time_one(capture: str, method: str, pretrained: str | None, out: pathlib.Path) -> dict:
  """One cold run: ``{"wall_s", "timings": reconstruct's timings.json, "shape": (T, H, W)}``."""
  cmd = [sys.executable, "-m", "experiments.reconstruct", capture, "--method", method,
         "--out", str(out), "--no-cache"]
  if pretrained is not None:
    cmd += ["--pretrained", pretrained]
  t0 = time.perf_counter()
  proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
  wall = time.perf_counter() - t0
  if proc.returncode != 0:
    raise SystemExit(f"reconstruct_time: {' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
  m = _SHAPE.search(proc.stdout)
  return {"wall_s": wall, "timings": json.loads((out / "timings.json").read_text()),
          "shape": tuple(int(v) for v in m.groups()) if m else None}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--capture", default=DEFAULT_CAPTURE, help="capture file (default: %(default)s)")
  parser.add_argument("--pretrained", nargs="+", default=["real", "cpu"],
                      help="shipped weights names (default: %(default)s)")
  parser.add_argument("--repeats", type=int, default=2, help="cold runs per method (default: %(default)s)")
  parser.add_argument("--out", default=str(DEFAULT_OUT), help="Markdown output")
  args = parser.parse_args(argv)
  if args.repeats < 1:
    raise SystemExit("--repeats must be >= 1")
  methods = [(m, name) for name in args.pretrained for m in LEARNED] + [(m, None) for m in CLASSIC]
  runs = {}
  with tempfile.TemporaryDirectory() as tmp:
    for i in range(args.repeats):            # interleaved, so a load change hits every method alike
      for method, weights in methods:
        r = time_one(args.capture, method, weights, pathlib.Path(tmp) / f"{method}-{i}")
        runs.setdefault((method, weights), []).append(r)
        print(f"{method} ({weights or 'classic'}): {r['wall_s']:.2f} s wall", flush=True)
  shape = next((r["shape"] for rs in runs.values() for r in rs if r["shape"]), None)
  best = {m: min(r["wall_s"] for r in rs) for m, rs in runs.items()}
  lct = best[("lct", None)]
  shown = lambda v: " ".join(v) if isinstance(v, list) else v
  command = "python -m benchmarks.reconstruct_time" + "".join(
      f" --{k} {shown(getattr(args, k))}" for k in ("capture", "pretrained", "repeats")
      if getattr(args, k) != parser.get_default(k))
  lines = ["# Reconstructing a capture from a cold process, shipped model beside classic methods", ""]
  lines += _machine.provenance(command) + [""]
  lines += [f"Capture `{args.capture}`" + (f", (T, H, W) = {shape}" if shape else "") + f"; learned"
            " methods with the shipped weights named in the table. Each run is a fresh"
            " `python -m experiments.reconstruct CAPTURE --method M --no-cache` process (imports,"
            " operators, compilation, run, writing the volume and figures); wall time measured around"
            f" the process, {args.repeats} run(s) per method, interleaved. `reconstruct` is the"
            " command's own operators + compile + run time (its `timings.json`).", "",
            f"| method | weights | wall per run (s) | best wall (s) | reconstruct (s) | best wall / LCT's |"
            f" under {GOAL_S:g} s |", "|---|---|---|---|---|---|---|"]
  for key in methods:
    rs = runs[key]
    walls = ", ".join(f"{r['wall_s']:.2f}" for r in rs)
    lines.append(f"| {key[0]} | {key[1] or '—'} | {walls} |"
                 f" {best[key]:.2f} | {min(r['timings']['reconstruct_s'] for r in rs):.2f} |"
                 f" {best[key] / lct:.2f} | {'yes' if best[key] < GOAL_S else 'no'} |")
  lines += ["", f"Goal: the shipped model under {GOAL_S:g} s on 2 cores, compile included, on"
            " a 64 x 64 x 512 capture. A machine with other jobs (load average above) makes every"
            " time an upper bound; the ratio to LCT, measured in the same session, moves less."]
  text = "\n".join(lines) + "\n"
  print(text)
  pathlib.Path(args.out).write_text(text)
  print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

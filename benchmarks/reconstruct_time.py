"""Time ``python -m experiments.reconstruct`` from a cold process: ``benchmarks/results/reconstruct_time.md``.

    python -m benchmarks.reconstruct_time [--capture nlosjax/data/scans/data_exit_sign.mat]
        [--pretrained real cpu] [--repeats 2] [--baseline REV]

What a user waits for when reconstructing a capture with a shipped model:
each method runs as its own fresh Python process, so every run pays for the
imports, building the operators, tracing, and writing the volume and its figures.
Each run is made twice in a row on a persistent compilation cache that starts
empty (its own folder, ``NLOSJAX_CACHE_DIR``): the first ("cold") compiles
everything, the second ("warm": the same command again) is served compiled
programs from the cache. The learned methods use the shipped weights
(``--pretrained``, each name given: ``real`` is trained on the measured
scans' geometry, ``cpu`` on a 2 m wall); three classic methods run in the same
measurement so the ratios beside the times hold on any machine, and
``--help`` is timed beside them. ``--baseline REV`` runs the same commands on a
checkout of commit ``REV`` (a temporary git worktree), interleaved with this
one's, so the change between them is measured side by side.

Goals: the shipped model under 10 s cold and 4 s warm on 2 cores on a
64 x 64 x 512 capture; ``--help`` under 1 s.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import shutil
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
GOAL_COLD_S = 10.0
GOAL_WARM_S = 4.0
GOAL_HELP_S = 1.0
_SHAPE = re.compile(r"\(T, H, W\) = \((\d+), (\d+), (\d+)\)")


def _run(cmd: list[str], cwd: pathlib.Path, env: dict) -> tuple[float, subprocess.CompletedProcess]:
  t0 = time.perf_counter()
  proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env)
  wall = time.perf_counter() - t0
  if proc.returncode != 0:
    raise SystemExit(f"reconstruct_time: {' '.join(cmd)} (in {cwd}) failed ({proc.returncode}):\n"
                     f"{proc.stderr[-2000:]}")
  return wall, proc


def time_pair(capture: str, method: str, pretrained: str | None, out: pathlib.Path,
              code: pathlib.Path) -> dict:
  """A cold run on an empty cache, then the same command warm on what it cached.

  Returns ``{"cold_s", "warm_s", "reconstruct_cold_s", "reconstruct_warm_s", "shape": (T, H, W)}``.
  """
  cache = out / "xla-cache"
  cache.mkdir(parents=True)
  env = {**os.environ, "NLOSJAX_CACHE_DIR": str(cache), "NLOSJAX_CACHE": "1"}
  cmd = [sys.executable, "-m", "experiments.reconstruct", str(pathlib.Path(capture).absolute()),
         "--method", method, "--out", str(out / "volume"), "--quiet"]
  if pretrained is not None:
    cmd += ["--pretrained", pretrained]
  r = {}
  for kind in ("cold", "warm"):
    wall, proc = _run(cmd, code, env)
    r[f"{kind}_s"] = wall
    r[f"reconstruct_{kind}_s"] = json.loads((out / "volume" / "timings.json").read_text())["reconstruct_s"]
    m = _SHAPE.search(proc.stdout)
    r["shape"] = tuple(int(v) for v in m.groups()) if m else r.get("shape")
  shutil.rmtree(cache, ignore_errors=True)
  return r


def _walls(rs: list[dict], key: str) -> str:
  return ", ".join(f"{r[key]:.2f}" for r in rs)


def time_help(code: pathlib.Path) -> float:
  return _run([sys.executable, "-m", "experiments.reconstruct", "--help"], code, dict(os.environ))[0]


def _worktree(rev: str, where: pathlib.Path) -> tuple[pathlib.Path, str]:
  sha = subprocess.run(["git", "rev-parse", "--short=12", rev], cwd=ROOT, capture_output=True,
                       text=True)
  if sha.returncode != 0:
    raise SystemExit(f"reconstruct_time: --baseline {rev}: not a commit ({sha.stderr.strip()})")
  path = where / "baseline"
  subprocess.run(["git", "worktree", "add", "--detach", "--quiet", str(path), rev], cwd=ROOT,
                 check=True)
  return path, sha.stdout.strip()


def _remove_worktree(path: pathlib.Path) -> None:
  subprocess.run(["git", "worktree", "remove", "--force", str(path)], cwd=ROOT)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--capture", default=DEFAULT_CAPTURE, help="capture file (default: %(default)s)")
  parser.add_argument("--pretrained", nargs="+", default=["real", "cpu"],
                      help="shipped weights names (default: %(default)s)")
  parser.add_argument("--repeats", type=int, default=2,
                      help="cold + warm pairs per method (default: %(default)s)")
  parser.add_argument("--baseline", default=None, metavar="REV",
                      help="also time commit REV's code, interleaved (learned methods and --help)")
  parser.add_argument("--out", default=str(DEFAULT_OUT), help="Markdown output")
  args = parser.parse_args(argv)
  if args.repeats < 1:
    raise SystemExit("--repeats must be >= 1")
  methods = [(m, name) for name in args.pretrained for m in LEARNED] + [(m, None) for m in CLASSIC]
  runs, helps = {}, {}
  with tempfile.TemporaryDirectory() as tmp:
    codes = [("this", ROOT)]
    base = None
    if args.baseline is not None:
      path, base = _worktree(args.baseline, pathlib.Path(tmp))
      codes.append((base, path))
    try:
      for i in range(args.repeats):          # interleaved, so a load change hits every row alike
        for label, code in codes:
          helps.setdefault(label, []).append(time_help(code))
          for method, weights in methods:
            if label != "this" and weights is None:
              continue                       # the classic methods are the yardstick, run once
            r = time_pair(args.capture, method, weights,
                          pathlib.Path(tmp) / f"{label}-{method}-{weights}-{i}", code)
            runs.setdefault((method, weights, label), []).append(r)
            print(f"{method} ({weights or 'classic'}, {label}): cold {r['cold_s']:.2f} s, warm"
                  f" {r['warm_s']:.2f} s", flush=True)
    finally:
      if base is not None:
        _remove_worktree(codes[1][1])
  shape = next((r["shape"] for rs in runs.values() for r in rs if r["shape"]), None)
  best = lambda key, kind: min(r[f"{kind}_s"] for r in runs[key])
  lct = best(("lct", None, "this"), "cold")
  shown = lambda v: " ".join(v) if isinstance(v, list) else v
  command = "python -m benchmarks.reconstruct_time" + "".join(
      f" --{k} {shown(getattr(args, k))}" for k in ("capture", "pretrained", "repeats", "baseline")
      if getattr(args, k) != parser.get_default(k))
  lines = ["# Reconstructing a capture from a cold process, shipped model beside classic methods", ""]
  lines += _machine.provenance(command) + [""]
  lines += [f"Capture `{args.capture}`" + (f", (T, H, W) = {shape}" if shape else "") + f"; learned"
            " methods with the shipped weights named in the table. Each run is a fresh"
            " `python -m experiments.reconstruct CAPTURE --method M` process (imports, operators,"
            " tracing, compilation, run, writing the volume and figures), made twice in a row on a"
            " compilation cache that starts empty: *cold* compiles, *warm* (the same command again)"
            " reads the compiled programs the cold run cached. Wall time is measured around the"
            f" process, {args.repeats} pair(s) per row, interleaved"
            + (f" with commit `{base}`'s code (`code` column)" if base else "") + ". `reconstruct`"
            " is the command's own operators + trace + compile + run time (its `timings.json`).", "",
            "| method | weights | code | cold wall per run (s) | warm wall per run (s) | best cold (s)"
            " | best warm (s) | reconstruct cold / warm (s) | best cold / LCT's |"
            f" cold under {GOAL_COLD_S:g} s | warm under {GOAL_WARM_S:g} s |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
  for key in sorted(runs, key=lambda k: (methods.index(k[:2]), k[2] != "this")):
    rs = runs[key]
    cold, warm = best(key, "cold"), best(key, "warm")
    lines.append(
        f"| {key[0]} | {key[1] or '—'} | {'this commit' if key[2] == 'this' else '`' + key[2] + '`'} |"
        f" {_walls(rs, 'cold_s')} | {_walls(rs, 'warm_s')} |"
        f" {cold:.2f} | {warm:.2f} | {min(r['reconstruct_cold_s'] for r in rs):.2f} /"
        f" {min(r['reconstruct_warm_s'] for r in rs):.2f} | {cold / lct:.2f} |"
        f" {'yes' if cold < GOAL_COLD_S else 'no'} | {'yes' if warm < GOAL_WARM_S else 'no'} |")
  lines += ["", f"`python -m experiments.reconstruct --help`, best of {args.repeats}: "
            + "; ".join(f"{'this commit' if k == 'this' else '`' + k + '`'} {min(v):.2f} s"
                        f" ({'under' if min(v) < GOAL_HELP_S else 'over'} {GOAL_HELP_S:g} s)"
                        for k, v in helps.items()) + "."]
  if base:
    for weights in args.pretrained:
      for m in LEARNED:
        new, old = runs.get((m, weights, "this")), runs.get((m, weights, base))
        if new and old:
          lines.append(f"- {m} ({weights}): cold this / `{base}` = "
                       f"{best((m, weights, 'this'), 'cold') / best((m, weights, base), 'cold'):.2f},"
                       f" warm {best((m, weights, 'this'), 'warm') / best((m, weights, base), 'warm'):.2f}")
  lines += ["", f"Goals: the shipped model under {GOAL_COLD_S:g} s cold (empty cache) and"
            f" {GOAL_WARM_S:g} s warm (the second run of the same command) on 2 cores on a"
            f" 64 x 64 x 512 capture; `--help` under {GOAL_HELP_S:g} s. A machine with other jobs"
            " (load average above) makes every time an upper bound; the ratios measured in the same"
            " session move less."]
  text = "\n".join(lines) + "\n"
  print(text)
  pathlib.Path(args.out).write_text(text)
  print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

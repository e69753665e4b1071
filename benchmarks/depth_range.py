"""The automatic depth range (``depth_range="auto"``) against the full range: time saved, accuracy kept.

    python -m benchmarks.depth_range [--config cpu] [--methods lct fk phasor]
                                     [--out benchmarks/results/depth_range.md]

On the **test split** of a preset (the classic protocol: under-scanned middle
frames interpolated to the full grid, each method's table options), every
frame is reconstructed twice per method: over the Setup's full range and over
:func:`nlosjax.physics.estimate_depth_range` of that same input (estimate
included in the gated time). Reported per method, as means with 95 %
bootstrap intervals over sequences (``nlosjax.stats``), paired where two
settings are compared:

* the estimated range's width and its **coverage**: the share of true surface
  pixels whose true depth lies inside it (what a gate can never recover);
* warm run time, full and gated (each Setup compiled before timing: a user
  with many captures pays a compile per distinct range, reported apart);
* object depth error (``mad_object``) and surface recall, full and gated, and
  their paired differences.

On the two **shipped measured scans** (no ground truth): the estimated
range, and the time and the max-projection agreement of the gated
reconstruction with the full one over the gated depths.
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import time

import numpy as np

from benchmarks.physics import ncc
from experiments import provenance as _machine

DEFAULT_OUT = pathlib.Path(__file__).resolve().parent / "results" / "depth_range.md"


def _timed(fn, repeats: int = 2, *, warm: bool = False) -> float:
  """Median warm seconds of ``fn()`` (one call first, to compile, unless ``warm``)."""
  import jax
  if not warm:
    jax.block_until_ready(fn())
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - t0)
  return statistics.median(times)


def split_study(config, methods, *, max_frames: int | None = None, log=print) -> dict:
  """Per-frame scores of full and gated reconstructions on the test split (see module docstring)."""
  from nlosjax import metrics
  from nlosjax.evaluation import baselines as B
  from nlosjax.evaluation.protocol import load_split
  from nlosjax.physics import estimate_depth_range, intensity_depth, reconstruct
  from nlosjax.train import ensure_dataset

  path = pathlib.Path(config.data.path)
  ensure_dataset(config, path, log=log)
  data = load_split(config, path, "test", batch_size=8)
  data["loader"].close()
  setup, stride = data["setup"], data["stride"]
  n = len(data["measurement"]) if max_frames is None else min(max_frames, len(data["measurement"]))
  rows = {m: {k: [] for k in ("t_full", "t_gated", "t_compile", "mad_full", "mad_gated",
                              "recall_full", "recall_gated")} for m in methods}
  ranges, coverage, t_estimate = [], [], []
  for i in range(n):
    x = np.asarray(B.upsample_scan(data["measurement"][i:i + 1], setup.grid, stride))   # [1, T, H, W]
    t0 = time.perf_counter()
    z = estimate_depth_range(x, setup)
    t_estimate.append(time.perf_counter() - t0)
    gated = setup.ungated().with_depth_range(*z)
    gt = data["depth"][i]
    surf = gt > 0
    ranges.append(z)
    coverage.append(float(np.mean((gt[surf] >= z[0]) & (gt[surf] <= z[1]))) if surf.any() else np.nan)
    for m in methods:
      opts = {**B.default_options(m, setup), **({"variant": B.TABLE_VARIANT[m]} if m in B.TABLE_VARIANT else {})}
      r = rows[m]
      for key, s in (("full", setup), ("gated", gated)):
        t0 = time.perf_counter()
        vol = reconstruct(x, s, m, **opts)
        vol.block_until_ready()
        first = time.perf_counter() - t0
        r[f"t_{key}"].append(_timed(lambda s=s: reconstruct(x, s, m, **opts), warm=True))
        if key == "gated":
          r["t_compile"].append(first - r["t_gated"][-1])
        vol = np.sqrt(np.asarray(vol)) if m == "fk" else np.asarray(vol)
        _, depth = intensity_depth(vol, s)
        sc = metrics.surface_scores(np.asarray(depth)[0], gt)
        r[f"mad_{key}"].append(float(sc["mad_object"]))
        r[f"recall_{key}"].append(float(sc["recall"]))
    log(f"frame {i + 1}/{n}: range {z[0]:.2f}-{z[1]:.2f} m, coverage {coverage[-1]:.3f}")
  return {"rows": rows, "ranges": np.asarray(ranges), "coverage": np.asarray(coverage),
          "sequence": data["sequence"][:n], "setup": setup, "t_estimate": t_estimate, "n": n}


def scan_study(methods) -> list[dict]:
  """Estimated range, times and gated-vs-full agreement on the shipped measured scans."""
  from nlosjax.data import io
  from nlosjax.evaluation.baselines import TABLE_VARIANT
  from nlosjax.physics import estimate_depth_range, reconstruct
  out = []
  for name in io.SHIPPED_SCAN_NAMES:
    x, setup = io.load_measurement(io.shipped_scan_path(name))
    z = estimate_depth_range(x, setup)
    gated = setup.with_depth_range(*z)
    k0, k1 = gated.depth_bins
    row = {"name": name, "range": z, "max_depth": setup.max_depth, "methods": {}}
    for m in methods:
      opts = {"variant": TABLE_VARIANT[m]} if m in TABLE_VARIANT else {}
      full = np.asarray(reconstruct(x, setup, m, **opts))
      part = np.asarray(reconstruct(x, gated, m, **opts))
      row["methods"][m] = {"t_full": _timed(lambda: reconstruct(x, setup, m, **opts), warm=True),
                           "t_gated": _timed(lambda: reconstruct(x, gated, m, **opts), warm=True),
                           "ncc": ncc(full[k0:k1].max(0), part.max(0))}
    out.append(row)
  return out


def _by_sequence(values, sequence) -> np.ndarray:
  """``[N]`` per-frame values -> ``[S, F]`` (frames of each sequence; NaN-padded)."""
  seqs = np.unique(sequence)
  width = max(int(np.sum(sequence == s)) for s in seqs)
  out = np.full((len(seqs), width), np.nan)
  for i, s in enumerate(seqs):
    v = np.asarray(values, np.float64)[sequence == s]
    out[i, :len(v)] = v
  return out


def _ci(values, sequence, fmt=".3f") -> str:
  from nlosjax.stats import summarize
  s = summarize(_by_sequence(values, sequence))
  lo, hi = s["ci95"]
  return f"{s['mean']:{fmt}} [{lo:{fmt}}, {hi:{fmt}}]"


def write_report(path, command, study, scans, methods) -> str:
  seq = study["sequence"]
  st = study["setup"]
  width = study["ranges"][:, 1] - study["ranges"][:, 0]
  lines = ["# Automatic depth range: what gating to the estimated range saves and keeps", "",
           *_machine.provenance(command), "",
           f"Test split of the preset: {study['n']} middle frames, {len(np.unique(seq))} sequences;"
           f" Setup {st.grid[0]} × {st.grid[1]}, {st.num_bins} bins of {st.bin_width * 1e12:g} ps"
           f" (maximum depth {st.max_depth:.2f} m). Means with 95 % bootstrap intervals over"
           " sequences; Δ = gated − full on the same frames.", "",
           f"- Estimated range width: {_ci(width, seq, '.2f')} m of {st.max_depth:.2f} m;"
           f" estimate time {statistics.median(study['t_estimate']):.3f} s per frame (median).",
           f"- Coverage (true surface pixels inside the range): {_ci(study['coverage'], seq)}"
           f" (minimum {np.nanmin(study['coverage']):.3f}).", "",
           "| method | full s | gated s | gated / full | compile per new range s | object depth MAD full m |"
           " Δ MAD m | recall full | Δ recall |", "|---|---|---|---|---|---|---|---|---|"]
  for m in methods:
    r = study["rows"][m]
    ratio = np.asarray(r["t_gated"]) / np.asarray(r["t_full"])
    lines.append(
        f"| {m} | {statistics.median(r['t_full']):.3f} | {statistics.median(r['t_gated']):.3f} |"
        f" {_ci(ratio, seq, '.2f')} | {statistics.median(r['t_compile']):.2f} |"
        f" {_ci(r['mad_full'], seq)} | {_ci(np.subtract(r['mad_gated'], r['mad_full']), seq, '+.4f')} |"
        f" {_ci(r['recall_full'], seq)} | {_ci(np.subtract(r['recall_gated'], r['recall_full']), seq, '+.4f')} |")
  lines += ["", "Times are medians over frames of warm runs (the first call per Setup compiles;"
            " its extra time is the compile column).", "",
            "## Shipped measured scans (no ground truth)", "",
            "| scan | estimated range m | " + " | ".join(
                f"{m} full s | {m} gated s | {m} NCC gated vs full" for m in methods) + " |",
            "|" + "---|" * (2 + 3 * len(methods))]
  for row in scans:
    cells = [row["name"], f"{row['range'][0]:.2f}-{row['range'][1]:.2f} (of 0-{row['max_depth']:.2f})"]
    for m in methods:
      v = row["methods"][m]
      cells += [f"{v['t_full']:.3f}", f"{v['t_gated']:.3f}", f"{v['ncc']:.3f}"]
    lines.append("| " + " | ".join(cells) + " |")
  lines += ["", "NCC: the gated volume's max projection against the full volume's over the same"
            " depths (1: gating changed nothing there)."]
  text = "\n".join(lines) + "\n"
  if path is not None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
  return text


def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m benchmarks.depth_range", description=__doc__.split("\n\n")[0])
  p.add_argument("--config", default="cpu")
  p.add_argument("--methods", nargs="+", default=["lct", "fk", "phasor"])
  p.add_argument("--max-frames", type=int, default=None, help="test frames (default all)")
  p.add_argument("--out", type=pathlib.Path, default=DEFAULT_OUT)
  args = p.parse_args(argv)
  command = "python -m benchmarks.depth_range" + (" " + " ".join(sys.argv[1:] if argv is None else argv)).rstrip()
  from experiments.cli import load_config
  from nlosjax import train as T
  config = T.RunConfig.from_dict(load_config(args.config))
  study = split_study(config, args.methods, max_frames=args.max_frames)
  scans = scan_study(args.methods)
  print(write_report(args.out, command, study, scans, args.methods))
  return 0


if __name__ == "__main__":
  sys.exit(main())

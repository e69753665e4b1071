"""Benchmark dataset generation and loading, at the CPU preset and at paper scale.

    python -m benchmarks.data [--sequences 8] [--paper-frames 32] [--repeats 3] [--workers 2]
                              [--out benchmarks/results/data.md] [--quick]

Generation (``nlosjax.data.dataset``): sequences per minute, with the LCT
renderer and (CPU preset, ``min(--sequences, 3)`` sequences) the transport
renderer (``renderer="transport"``, :mod:`nlosjax.data.surfaces`).

* CPU preset (``experiments/configs/cpu.py``): one sequence is simulated
  first (its time includes jit compilation of the renderer and noise model
  for these shapes: "cold"); then ``--sequences`` sequences are written with
  :func:`write_dataset` in this process (simulation + gzip HDF5 writing, "warm").
  The whole preset dataset's time is extrapolated from the warm rate.
* Paper scale (``experiments/configs/paper.py``: 128 x 128 x 512 at 33 ps,
  clean transients not stored): two sequences of ``--paper-frames`` frames
  (default 32, whole paper sequences) are simulated, cold then warm. With
  fewer frames the warm time is extrapolated linearly to 32 frames (the
  per-sequence cost is per frame apart from milliseconds of scene drawing),
  and the table says so.
* Parallel generation: ``--sequences`` cpu-preset sequences written with 1
  and with ``--workers`` processes, wall time from the call to the closed file.

Loading (:class:`TripletLoader`, batch 4): triplets per second (one triplet =
three under-scanned input frames + the middle frame's full-resolution target,
intensity and depth), from disk (chunked gzip reads; the file was just
written, so the OS page cache is warm) and ``in_memory``; median of
``--repeats`` passes over the file's triplets, each pass with a fresh loader
(fresh HDF5 chunk cache). Input frames per second = 3 x triplets per second.

The machine is named in the output; its CPU may be shared with other jobs,
so timings are noisy. ``--quick`` (3 CPU-preset sequences, 2-frame paper
sequences, 1 repeat) only prints unless ``--out`` is given.
"""

from __future__ import annotations

import argparse
import datetime
import pathlib
import statistics
import tempfile
import time

from experiments import configs
from experiments import provenance as _machine_facts
from nlosjax.data import dataset as D

DEFAULT_OUT = pathlib.Path(__file__).resolve().parent / "results" / "data.md"
PAPER_FRAMES = 32
BATCH = 4


def _machine() -> list[str]:
  import h5py
  return [f"- Machine: {_machine_facts.machine_text()}",
          f"- Versions: {_machine_facts.versions_text('numpy', 'h5py')} (HDF5 {h5py.version.hdf5_version})",
          f"- Commit: {_machine_facts.git_commit()}"]


def _load_rate(path, stride, in_memory, repeats, ends="valid", target="clean"):
  """(median triplets/s over passes, triplets per pass, loader open seconds)."""
  rates, opens = [], []
  n = 0
  for _ in range(repeats):
    t0 = time.perf_counter()
    with D.TripletLoader(path, batch_size=BATCH, stride=stride, in_memory=in_memory, ends=ends,
                         target=target, drop_remainder=False) as loader:
      t1 = time.perf_counter()
      n = 0
      for batch in loader.epoch(0):
        n += len(batch["frame"])
      t2 = time.perf_counter()
    rates.append(n / (t2 - t1))
    opens.append(t1 - t0)
  return statistics.median(rates), n, statistics.median(opens)


def bench_cpu(n_seq, repeats, workdir, renderer="lct"):
  data = configs.get_config("cpu")["data"]
  # The preset's scenes and detector with either renderer (materials are drawn per object
  # by the transport renderer only).
  materials = {"retroreflective": data.get("retroreflective", 0.0) if renderer == "transport" else 0.0}
  spec = D.DatasetSpec.from_config(data, num_train=n_seq, num_test=0, num_val=0, renderer=renderer,
                                   **materials)
  t0 = time.perf_counter()
  D.simulate_sequence(spec, "test", 0)
  cold = time.perf_counter() - t0
  path = pathlib.Path(workdir) / f"cpu-{renderer}.h5"
  t0 = time.perf_counter()
  D.write_dataset(path, spec, progress=False)
  warm = (time.perf_counter() - t0) / n_seq
  full = D.DatasetSpec.from_config(data, renderer=renderer, **materials)
  total = full.num_sequences
  preset = data.get("renderer", "lct") == renderer
  rows = {"preset": f"cpu, {renderer} renderer" + (" (the preset's)" if preset else ""),
          "renderer": renderer, "setup": spec.setup, "frames": spec.frames, "clean": spec.store_clean,
          "cold_s": cold, "warm_s": warm, "seq_per_min": 60 / warm,
          "preset_minutes": (cold + warm * (total - 1)) / 60, "preset_sequences": total,
          "measured": f"{n_seq} sequences", "mib_per_seq": path.stat().st_size / 2 ** 20 / n_seq}
  stride = data["input_stride"]
  rows["stride"] = stride
  if renderer == "lct":  # the file layout does not depend on the renderer: load once
    rows["disk"] = _load_rate(path, stride, False, repeats)
    rows["memory"] = _load_rate(path, stride, True, repeats)
  return rows


def bench_paper(frames, repeats, workdir):
  data = configs.get_config("paper")["data"]
  spec = D.DatasetSpec.from_config(data, frames=frames, num_train=1, num_test=0, num_val=0)
  t0 = time.perf_counter()
  D.simulate_sequence(spec, "test", 0)
  cold = time.perf_counter() - t0
  path = pathlib.Path(workdir) / "paper.h5"
  t0 = time.perf_counter()
  D.write_dataset(path, spec, progress=False)
  warm = time.perf_counter() - t0
  per_seq = warm * PAPER_FRAMES / frames
  # Compilation happens once whatever the frame count: only the warm part scales with frames.
  compile_s = max(cold - warm, 0.0)
  measured = (f"1 whole sequence of {frames} frames (cold: a first one in a fresh process)"
              if frames == PAPER_FRAMES else
              f"1 sequence of {frames} frames, warm time x{PAPER_FRAMES / frames:g}"
              f" extrapolated; cold = compilation ({compile_s:.1f} s, once) + warm")
  rows = {"preset": "paper", "setup": spec.setup, "frames": PAPER_FRAMES, "clean": spec.store_clean,
          "cold_s": compile_s + per_seq, "warm_s": per_seq, "seq_per_min": 60 / per_seq,
          "preset_minutes": (compile_s + per_seq * sum(data["num_sequences"].values())) / 60,
          "preset_sequences": sum(data["num_sequences"].values()),
          "measured": measured,
          "mib_per_seq": path.stat().st_size / 2 ** 20 * PAPER_FRAMES / frames}
  stride = data["input_stride"]
  # Few frames: use every frame as a middle frame (ends="replicate") to have triplets to time.
  rows["disk"] = _load_rate(path, stride, False, repeats, ends="replicate", target="measurement")
  rows["memory"] = _load_rate(path, stride, True, repeats, ends="replicate", target="measurement")
  rows["stride"] = stride
  return rows


def bench_workers(n_seq, workers, workdir):
  """Wall time of ``write_dataset`` for ``n_seq`` cpu-preset sequences with each worker count.

  Everything a user waits for is counted: process start, jit compilation in
  each worker, simulation and the single writer.
  """
  data = configs.get_config("cpu")["data"]
  spec = D.DatasetSpec.from_config(data, num_train=n_seq, num_test=0, num_val=0)
  out = {}
  for w in workers:
    path = pathlib.Path(workdir) / f"workers{w}.h5"
    t0 = time.perf_counter()
    D.write_dataset(path, spec, workers=w, progress=False)
    out[w] = time.perf_counter() - t0
  return {"renderer": spec.renderer, "sequences": n_seq, "frames": spec.frames, "seconds": out}


def render(results, args, workers=None) -> str:
  now = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
  cmd = "python -m benchmarks.data" + (" --quick" if args.quick else
                                       f" --sequences {args.sequences} --paper-frames {args.paper_frames}"
                                       f" --repeats {args.repeats} --workers {args.workers}")
  lines = ["# Dynamic NLOS dataset: generation and loading throughput", "",
           f"Produced by `{cmd}`.", "", f"- Date: {now}"] + _machine() + [
      f"- Load average (1, 5, 15 min) when written: {_machine_facts.load_average(', ')}"
      f" (above {_machine_facts.usable_cores()}, the cores were shared and timings are upper"
      " bounds)", "",
      "Generation: cold = first sequence in the process (includes jit compilation); warm ="
      " simulation + compressed HDF5 write per sequence once compiled ('measured' says whether"
      " a paper-scale row is a whole sequence or extrapolated from a short one). Whole preset ="
      " cold + warm x (sequences - 1), one process.", "",
      "| preset | full grid x T, bin | frames | clean stored | measured | cold s/seq | warm s/seq |"
      " sequences/min (warm) | MiB/seq | whole preset |",
      "|---|---|---|---|---|---|---|---|---|---|"]
  for r in results:
    s = r["setup"]
    lines.append(
        f"| {r['preset']} | {s.grid[0]}x{s.grid[1]} x {s.num_bins}, {s.bin_width * 1e12:.0f} ps |"
        f" {r['frames']} | {'yes' if r['clean'] else 'no'} | {r['measured']} | {r['cold_s']:.1f} |"
        f" {r['warm_s']:.2f} | {r['seq_per_min']:.1f} | {r['mib_per_seq']:.1f} |"
        f" {r['preset_sequences']} seq: {r['preset_minutes']:.1f} min |")
  if workers:
    base = workers["seconds"][1]
    lines += ["", f"Parallel generation: `write_dataset(workers=W)` (`python -m experiments.make_dataset"
              f" --workers W`), {workers['sequences']} cpu-preset sequences of {workers['frames']}"
              f" frames ({workers['renderer']} renderer), wall time from the call to the closed file"
              " (process start and each worker's compilation included).", "",
              "| workers | wall s | sequences/min | speed-up over 1 |", "|---|---|---|---|"]
    for w, t in workers["seconds"].items():
      lines.append(f"| {w} | {t:.1f} | {60 * workers['sequences'] / t:.1f} | {base / t:.2f}x |")
  lines += ["", f"Loading: `TripletLoader`, batch {BATCH}, median of {args.repeats if not args.quick else 1}"
            " passes; input frames/s = 3 x triplets/s.", "",
            "| preset | input grid | target | triplets per pass | disk: triplets/s | disk: input frames/s |"
            " in memory: triplets/s | in memory: load time s |", "|---|---|---|---|---|---|---|---|"]
  for r in results:
    if "disk" not in r:
      continue
    s = r["setup"]
    h = len(range(0, s.grid[0], r["stride"]))
    target = "clean" if r["clean"] else "measurement"
    lines.append(f"| {r['preset']} | {h}x{h} (every {r['stride']}) | {target} {s.grid[0]}x{s.grid[1]} |"
                 f" {r['disk'][1]} | {r['disk'][0]:.0f} | {3 * r['disk'][0]:.0f} | {r['memory'][0]:.0f} |"
                 f" {r['memory'][2]:.2f} |")
  lines += ["", "Notes (numbers from the tables above):", ""]
  by = {r["renderer"]: r for r in results if "renderer" in r}
  if "lct" in by and "transport" in by:
    a, b = by["lct"], by["transport"]
    lines.append(
        f"- The transport renderer (`renderer=\"transport\"`: whole surfaces, exact paths, cosines,"
        f" per-scan-point visibility) costs {b['warm_s'] / a['warm_s']:.0f}x the LCT renderer per"
        f" sequence at the CPU preset ({b['warm_s'] / b['frames']:.2f} s against"
        f" {a['warm_s'] / a['frames']:.3f} s per frame, warm, one process): the whole preset in"
        f" {b['preset_minutes']:.1f} min against {a['preset_minutes']:.1f} min; `write_dataset`'s"
        " `workers` run sequences in parallel processes.")
  for r in results:
    if r["preset"] != "paper":
      continue
    s = r["setup"]
    frame_mib = s.grid[0] * s.grid[1] * s.num_bins * 4 / 2 ** 20
    lines += [f"- Paper-scale loading reads a {frame_mib:.0f} MiB full-resolution target frame per"
              f" triplet, gzip-compressed in the file: {1e3 / r['disk'][0]:.0f} ms per triplet from"
              f" disk against {1e3 / r['memory'][0]:.1f} ms in memory, so decompression and HDF5"
              " reads bound it. h5py serialises reads: prefetch threads overlap loading with"
              " training but do not add read throughput.",
              f"- Paper-scale generation: {r['warm_s'] / PAPER_FRAMES:.1f} s per frame once compiled"
              " (128x128x512 render, SPAD model and compressed write, on this CPU); a GPU backend"
              " runs the same JAX code unchanged."]
  lines += ["- The under-scanned input costs little: its rows are whole chunks, so a stride-s read"
            " decompresses 1/s of each input frame."]
  return "\n".join(lines) + "\n"


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--sequences", type=int, default=8, help="CPU-preset sequences to time")
  parser.add_argument("--paper-frames", type=int, default=PAPER_FRAMES,
                      help="frames of the paper-scale sequences (default: a whole one, %(default)s)")
  parser.add_argument("--workers", type=int, default=2,
                      help="time write_dataset with 1 and with this many worker processes (1: skip)")
  parser.add_argument("--repeats", type=int, default=3, help="loading passes (median)")
  parser.add_argument("--skip-paper", action="store_true", help="CPU preset only")
  parser.add_argument("--out", default=None,
                      help=f"Markdown output (default {DEFAULT_OUT}; --quick: print only)")
  parser.add_argument("--quick", action="store_true", help="a smoke run: 3 sequences, 2 paper frames")
  args = parser.parse_args(argv)
  if args.quick:
    args.sequences, args.paper_frames, args.repeats, args.workers = 3, 2, 1, 1
  results = []
  with tempfile.TemporaryDirectory(prefix="nlosjax-bench-data-") as tmp:
    print(f"CPU preset: {args.sequences} sequences ...", flush=True)
    results.append(bench_cpu(args.sequences, args.repeats, tmp))
    n = min(args.sequences, 3)
    print(f"CPU preset, transport renderer: {n} sequences ...", flush=True)
    results.append(bench_cpu(n, args.repeats, tmp, renderer="transport"))
    workers = None
    if args.workers > 1:
      print(f"CPU preset: {args.sequences} sequences with 1 and {args.workers} workers ...", flush=True)
      workers = bench_workers(args.sequences, (1, args.workers), tmp)
    if not args.skip_paper:
      print(f"paper scale: 2 x {args.paper_frames} frames ...", flush=True)
      results.append(bench_paper(args.paper_frames, args.repeats, tmp))
  text = render(results, args, workers)
  print(text)
  out = args.out or (None if args.quick else DEFAULT_OUT)
  if out:
    pathlib.Path(out).parent.mkdir(parents=True, exist_ok=True)
    pathlib.Path(out).write_text(text)
    print(f"wrote {out}")


if __name__ == "__main__":
  main()

"""``python -m experiments.studies.csa``: see the package docstring."""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

from experiments import provenance
from experiments.studies import csa as study

OUT = pathlib.Path(__file__).resolve().parent / "results" / "csa_choice.md"
CLASSIC = ("fbp", "lct", "fk", "phasor", "rsd")


def ensure_data(path: pathlib.Path, sequences: int) -> None:
  """The ``real`` preset's first ``sequences`` validation sequences at ``path`` (made when absent)."""
  from experiments import make_dataset
  from nlosjax.data import dataset
  if path.is_file():
    with dataset.open_dataset(path) as ds:
      if len(ds.names("val")) >= sequences:
        return
  path.parent.mkdir(parents=True, exist_ok=True)
  make_dataset.main(["--config", "real", "--out", str(path), "--overwrite", "--train", "0",
                     "--val", str(sequences), "--test", "0", "--quiet"])


def score(path, sequences: int, frames, strides, taus, log=print) -> dict:
  """``{"csa": {(stride, tau): [S, F] psnr}, <classic>: {stride: [S, F]}, "time_s": ..., "iterations": ...}``."""
  from experiments.reconstruct import edge_masked, project, reconstruct_classic
  from nlosjax import metrics
  from nlosjax.data import dataset, io
  from nlosjax.evaluation import baselines as B
  from nlosjax.physics.methods import csa
  out = {"csa": {(s, t): np.zeros((sequences, len(frames))) for s in strides for t in taus},
         **{m: {s: np.zeros((sequences, len(frames))) for s in strides} for m in CLASSIC},
         "time_s": {(s, t): [] for s in strides for t in taus},
         "iterations": {(s, t): [] for s in strides for t in taus}}
  with dataset.open_dataset(path) as ds:
    names = ds.names("val")[:sequences]
    for i, name in enumerate(names):
      for j, fr in enumerate(frames):
        x, setup = io.load_measurement(path, sequence=name, frame=fr)
        gt = ds.read(name, "intensity", frames=fr)
        for s in strides:
          mask = csa.interval_mask(setup.height, setup.width, s)
          for t in taus:
            t0 = time.perf_counter()
            res = csa.csa_solve(x * mask, setup, mask=mask, tau_rel=t)
            vol = np.asarray(res["volume"])
            out["time_s"][(s, t)].append(time.perf_counter() - t0)
            out["iterations"][(s, t)].append(int(res["iterations"]))
            image, _ = project(edge_masked(vol, setup), setup)
            out["csa"][(s, t)][i, j] = float(metrics.psnr(image, gt))
          for m in CLASSIC:
            _, image, _ = reconstruct_classic(x[None], setup, m, B.default_options(m, setup), s)
            out[m][s][i, j] = float(metrics.psnr(image[0], gt))
        log(f"  {name} frame {fr}: " + ", ".join(
            f"stride {s} csa " + "/".join(f"{out['csa'][(s, t)][i, j]:.2f}" for t in taus) for s in strides))
  return out


def choose(results, strides, taus) -> dict:
  """``stride -> tau_rel`` with the best mean PSNR (ties: the smaller tau)."""
  return {s: max(taus, key=lambda t: (np.mean(results["csa"][(s, t)]), -t)) for s in strides}


def report(results, *, command, path, sequences, frames, strides, taus) -> str:
  from nlosjax.stats import format_interval, paired_difference, summarize
  chosen = choose(results, strides, taus)
  lines = ["# CSA's prior weight, chosen on simulated validation sequences", "",
           *provenance.provenance(command), "",
           f"The `real` preset's validation split (`{path.name}`: its first {sequences} sequences,"
           f" frames {', '.join(map(str, frames))}; 64 x 64 scan of a 0.6 m wall, 128 bins of 64 ps),"
           " under-scanned at the points `stride // 2 + stride i`. CSA reconstructs the masked"
           " scan (`nlosjax.physics.methods.csa.csa`, 200 FISTA steps at most, tol 1e-4); the"
           " classic methods the scan interpolated back to 64 x 64 with their default options, as"
           " `experiments.studies.real_undersampling` runs them. Intensity PSNR (dB) against the simulator's"
           " ground truth; mean [95 % interval over sequences]. No measured scan is read.", "",
           "| method | " + " | ".join(f"{64 // s} × {64 // s}" for s in strides) + " |",
           "|---|" + "---|" * len(strides)]
  for t in taus:
    cells = []
    for s in strides:
      cell = format_interval(summarize(results["csa"][(s, t)]))
      cells.append(f"**{cell}**" if chosen[s] == t else cell)
    lines.append(f"| CSA tau_rel {t:g} | " + " | ".join(cells) + " |")
  for m in CLASSIC:
    lines.append(f"| {m} (interpolated) | " + " | ".join(format_interval(summarize(results[m][s]))
                                                       for s in strides) + " |")
  best = {s: max(CLASSIC, key=lambda m: np.mean(results[m][s])) for s in strides}
  lines += ["", "Chosen (bold): " + "; ".join(f"{64 // s} × {64 // s}: tau_rel {chosen[s]:g}" for s in strides)
            + ". CSA at the chosen weight against the best classic method there (paired over the same"
            " frames, mean [95 % interval]): "
            + "; ".join(f"{64 // s} × {64 // s}: CSA − {best[s]} "
                        + format_interval(paired_difference(results['csa'][(s, chosen[s])], results[best[s]][s]),
                                          signed=True) for s in strides) + ".", "",
            "Cost on this machine, per frame at the chosen weight (median): "
            + "; ".join(f"{64 // s} × {64 // s}: {np.median(results['time_s'][(s, chosen[s])]):.1f} s,"
                        f" {int(np.median(results['iterations'][(s, chosen[s])]))} FISTA steps"
                        for s in strides) + " (compilation included in the first frame).", ""]
  return "\n".join(lines)


def main(argv=None) -> int:
  from experiments import store
  p = argparse.ArgumentParser(description=study.__doc__.splitlines()[0])
  p.add_argument("--data", default=None, help="validation file (default: the store's real-val<N>.h5)")
  p.add_argument("--sequences", type=int, default=4)
  p.add_argument("--frames", type=int, nargs="+", default=[2, 5])
  p.add_argument("--strides", type=int, nargs="+", default=[4, 8])
  p.add_argument("--tau", type=float, nargs="+", default=[0.03, 0.1, 0.3])
  p.add_argument("--out", default=str(OUT))
  args = p.parse_args(argv)
  path = pathlib.Path(args.data) if args.data else store.data_path(f"real-val{args.sequences}.h5")
  ensure_data(path, args.sequences)
  given = sys.argv[1:] if argv is None else list(argv)
  command = " ".join(["python -m experiments.studies.csa", *given])
  results = score(path, args.sequences, args.frames, args.strides, args.tau)
  text = report(results, command=command, path=path, sequences=args.sequences, frames=args.frames,
                strides=args.strides, taus=args.tau)
  pathlib.Path(args.out).write_text(text)
  print(text)
  return 0


if __name__ == "__main__":
  sys.exit(main())

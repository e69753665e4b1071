"""``python -m experiments.studies.real_undersampling``: the command line (the protocol: the package docstring)."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

from experiments.reconstruct import add_weight_arguments
from experiments.studies.real_undersampling import __doc__ as package_doc
from experiments.studies.real_undersampling.ablation import ablated_models, adapted_models, aligned_run
from experiments.studies.real_undersampling.figures import write_figures
from experiments.studies.real_undersampling.protocol import (
  binned_classic,
  default_files,
  load_models,
  run,
  synthetic_check,
)
from experiments.studies.real_undersampling.report import pretrained_data, training_data, write_report
from experiments.studies.real_undersampling.timing import time_cli, time_warm


def main(argv=None):
  parser = argparse.ArgumentParser(prog="python -m experiments.studies.real_undersampling",
                                   description=package_doc.split("\n\n")[0])
  parser.add_argument("--data-dir", default=None,
                      help="folder of real .mat scans (default ../shared/data/real, else the shipped scan)")
  add_weight_arguments(parser, "trained run (workdir of python -m experiments.train); 'none' for"
                               " classic only; default: the shipped weights of --pretrained")
  parser.add_argument("--strides", type=int, nargs="+", default=[4, 8])
  parser.add_argument("--out", default=str(pathlib.Path(__file__).resolve().parent / "results" / "real.md"))
  parser.add_argument("--no-timing", action="store_true", help="skip the CLI vs twin timing")
  parser.add_argument("--timing-repeats", type=int, default=3)
  parser.add_argument("--json", default=None, help="also write the scores as JSON here")
  parser.add_argument("--synthetic", default=None,
                      help="dataset file for the in-domain check (default: the data.path of the"
                           " checkpoint's config.json, or of the shipped weights' without --checkpoint;"
                           " 'none' to skip; skipped if absent)")
  parser.add_argument("--notes", default=None, help="a Markdown file whose text is added after the tables")
  parser.add_argument("--no-ablation", action="store_true",
                      help="skip the networks with their learned residuals zeroed (ablated_models)")
  parser.add_argument("--adapt", action="store_true",
                      help="also fit each network to each scan before reconstructing it (adapted_models)")
  parser.add_argument("--aligned", nargs="+", default=None, metavar="WORKDIR",
                      help="also score each scan with the networks of python -m experiments.studies.align --workdir"
                           " WORKDIR that left it out (aligned_run); several workdirs (e.g. two lam"
                           " settings) get one table each")
  args = parser.parse_args(argv)
  t0 = time.perf_counter()
  command = "python -m experiments.studies.real_undersampling " + " ".join(
      sys.argv[1:] if argv is None else argv)
  from experiments.provenance import provenance
  facts = provenance(command.strip())              # the commit the run starts from
  files = default_files(args.data_dir)
  classic_only = args.checkpoint is not None and args.checkpoint.lower() == "none"
  checkpoint = None if classic_only else args.checkpoint
  try:
    trained = {} if classic_only else load_models(checkpoint, args.pretrained)
  except ValueError as e:
    parser.error(str(e))
  results = run(files, args.strides, checkpoint, trained=trained)
  out = pathlib.Path(args.out)
  out.parent.mkdir(parents=True, exist_ok=True)
  figures = write_figures(results, out.parent, prefix=out.stem)   # beside another report: its own names
  timing = warm = None
  if not args.no_timing:
    timing = {"file": files[0].name, "repeats": args.timing_repeats,
              "methods": time_cli(files[0], repeats=args.timing_repeats)}
    warm = time_warm(files[0])
  synthetic = None
  synthetic_path = args.synthetic or (training_data(checkpoint) if checkpoint or classic_only
                                      else pretrained_data(args.pretrained))
  if synthetic_path.lower() != "none":
    synthetic = synthetic_check(synthetic_path, results["trained"])
  binned = binned_classic(results)
  ablated = {} if args.no_ablation else ablated_models(results["trained"])
  ablation = None
  if ablated:
    ablation = run(files, args.strides, None, trained=ablated, classic=False,
                   references={sc: e["references"] for sc, e in results["scenes"].items()})
  adaptation = None
  if args.adapt and results["trained"]:
    adaptation = run(files, args.strides, None, trained=adapted_models(results["trained"]), classic=False,
                     references={sc: e["references"] for sc, e in results["scenes"].items()})
  aligned = [aligned_run(files, args.strides, results, w) for w in args.aligned or ()]
  notes = pathlib.Path(args.notes).read_text() if args.notes else ""
  write_report(results, out, timing=timing, warm=warm, synthetic=synthetic, binned=binned,
               ablation=ablation, adaptation=adaptation, aligned=aligned, facts=facts,
               elapsed=time.perf_counter() - t0, figures=figures, notes=notes)
  if args.json:
    scores = {sc: {f"{m}@{s}": v for (m, s), v in e["scores"].items()}
              for sc, e in results["scenes"].items()}
    binned_json = None if binned is None else {
        **binned, "scores": {f"{m}@{s}": v for (m, s), v in binned["scores"].items()}}
    if ablation:
      scores["ablation"] = {sc: {f"{m}@{s}": v for (m, s), v in e["scores"].items()}
                            for sc, e in ablation["scenes"].items()}
    pathlib.Path(args.json).write_text(json.dumps({"scores": scores, "timing": timing, "warm": warm,
                                                   "synthetic": synthetic, "binned": binned_json},
                                                  indent=2) + "\n")
  print(out.read_text())


if __name__ == "__main__":
  main()

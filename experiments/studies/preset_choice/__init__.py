"""Which data should a preset train on? Candidate models compared on every candidate's validation split.

    python -m experiments.studies.preset_choice --model LABEL=SOURCE --model LABEL=SOURCE [...]
        [--variants ours ours_s] [--methods lct rsd ...] [--out FILE.md]   # default: results/preset_choice.md

``SOURCE`` is ``pretrained:NAME`` (the weights shipped as ``NAME-<variant>``)
or a main-job workdir (``python -m experiments.train --workdir DIR``). Each
candidate was trained on its own data (its config's ``data`` section); every
candidate's model is scored (mean intensity PSNR, the checkpoint criterion)
on the validation split of every candidate's data, written if absent with no
training or test sequence (``<stem>-val.h5``, the same sequences as the
training file's validation split). The table gives each model's mean with a
95 % bootstrap interval over sequences and each later candidate minus the
first, paired by frame. Nothing here reads a test split or a measured scan.

A second table puts each model beside the all-zero image's PSNR (the floor a dark
background reaches) and the object intensity error (mean absolute error on the true
object pixels), and, with ``--methods``, beside those classic methods on the same
validation frames: so a candidate's lead can be read as objects drawn, not a dark
background, and against what the field's methods give on that data.
"""

from __future__ import annotations

import argparse
import copy
import json
import pathlib
import sys

import numpy as np

from nlosjax.stats import format_interval as cell
from nlosjax.variants import OURS, OURS_S

#: This study's results folder: its reports, figures and JSON records.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def load_candidate(source: str, variant: str):
  """``(model_config, params, training config)`` of one candidate's ``variant``."""
  from nlosjax import inference
  if source.startswith("pretrained:"):
    mcfg, params, provenance = inference.load_pretrained(source[len("pretrained:"):], variant)
    return mcfg, params, provenance["config"]
  config, trained = inference.load_run(source)
  if variant not in trained:
    raise SystemExit(f"{source}: no trained {variant} (it has {sorted(trained)})")
  mcfg, params = trained[variant]                   # load_run without seeds: (model_config, params)
  return mcfg, params, config


def validation_file(config: dict) -> tuple:
  """The config's validation split, in a file of its own when the training file is absent, and the
  :class:`~nlosjax.train.RunConfig` that reads it."""
  from nlosjax import train
  path = pathlib.Path(config["data"]["path"])
  if path.exists():
    return path, train.RunConfig.from_dict(config)
  cfg = copy.deepcopy(config)
  counts = dict(cfg["data"].get("num_sequences", {}))
  cfg["data"]["num_sequences"] = {"train": 0, "test": 0, "val": counts.get("val", 8)}
  cfg["data"]["path"] = str(path.with_name(f"{path.stem}-val.h5"))
  typed = train.RunConfig.from_dict(cfg)
  train.ensure_dataset(typed, pathlib.Path(cfg["data"]["path"]))
  return pathlib.Path(cfg["data"]["path"]), typed


def main(argv=None) -> int:
  from experiments.provenance import provenance
  from nlosjax import stats
  from nlosjax.evaluation import protocol, scores
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--model", action="append", required=True, metavar="LABEL=SOURCE")
  parser.add_argument("--variants", nargs="+", default=[OURS, OURS_S])
  parser.add_argument("--methods", nargs="*", default=[],
                      help="classic methods scored beside the models on each validation split")
  parser.add_argument("--out", default=str(RESULTS / "preset_choice.md"))
  args = parser.parse_args(argv)
  argv = sys.argv[1:] if argv is None else list(argv)
  sources = dict(item.partition("=")[::2] for item in args.model)
  if len(sources) < 2 or not all(sources.values()):
    raise SystemExit("give at least two --model LABEL=SOURCE")
  results, splits, context = {}, {}, {}
  for variant in args.variants:
    models = {label: load_candidate(src, variant) for label, src in sources.items()}
    for label, (_, _, cfg) in models.items():
      splits.setdefault(label, validation_file(cfg))
    for data_label, (path, cfg) in splits.items():
      if args.methods and (data_label, args.methods[0]) not in context:     # once a split
        ev = protocol.evaluate(cfg, path, {}, split="val", methods=tuple(args.methods))
        for method in args.methods:
          context[(data_label, method)] = (ev["scores"][method], np.asarray(ev["sequence"]))
      for label, (mcfg, params, _) in models.items():
        ev = protocol.evaluate(cfg, path, {variant: [(mcfg, params)]}, split="val", methods=())
        results[(variant, data_label, label)] = (np.asarray(ev["scores"][variant]["psnr"]).reshape(-1),
                                                 np.asarray(ev["sequence"]))
        context[(data_label, f"{label} {variant}")] = (ev["scores"][variant], np.asarray(ev["sequence"]))
  labels = list(sources)
  first = labels[0]

  lines = ["# Preset choice: candidate models on every candidate's validation split", ""]
  lines += provenance("python -m experiments.studies.preset_choice " + " ".join(argv)) + [""]
  lines += ["Candidates: " + "; ".join(f"`{k}` = `{v}` (data `{splits[k][0]}`)" for k, v in sources.items())
            + ". Mean intensity PSNR (dB) on each validation split with a 95 % bootstrap interval over "
            f"sequences; differences to `{first}` paired by frame. A candidate is preferred where it is "
            "ahead on the other candidates' data (interval above 0) and not behind on its own.", "",
            "| variant | validation data | " + " | ".join(labels) + " | "
            + " | ".join(f"{k} − {first}" for k in labels[1:]) + " |",
            "|---|---|" + "---|" * (2 * len(labels) - 1)]
  record = {}
  for variant in args.variants:
    for data_label in splits:
      base_v, seq = results[(variant, data_label, first)]
      by = {k: scores.by_sequence(results[(variant, data_label, k)][0], seq) for k in labels}
      means = [stats.summarize(by[k]) for k in labels]
      diffs = [stats.paired_difference(by[k], by[first]) for k in labels[1:]]
      record[f"{variant}/{data_label}"] = {"means": dict(zip(labels, means)),
                                           "differences": dict(zip(labels[1:], diffs))}
      lines.append(f"| {variant} | {data_label} | " + " | ".join(cell(m) for m in means) + " | "
                   + " | ".join(cell(d, signed=True) for d in diffs) + " |")
  lines += ["", "Each method on each validation split: intensity PSNR, the all-zero image's PSNR on the "
            "same frames (a floor), and the object intensity error (lower is better); means with 95 % "
            "bootstrap intervals over sequences.", "",
            "| validation data | method | PSNR (dB) | all-zero PSNR (dB) | object intensity error |",
            "|---|---|---|---|---|"]
  for (data_label, method), (sc, seq) in context.items():
    row = [stats.summarize(scores.by_sequence(np.asarray(sc[k]).reshape(-1), seq))
           for k in ("psnr", "psnr_zero", "intensity_mae_object")]
    record.setdefault("context", {})[f"{data_label}/{method}"] = dict(
        zip(("psnr", "psnr_zero", "intensity_mae_object"), row))
    lines.append(f"| {data_label} | {method} | {cell(row[0])} | {cell(row[1])} | {cell(row[2], digits=3)} |")
  out = pathlib.Path(args.out)
  out.parent.mkdir(parents=True, exist_ok=True)
  out.write_text("\n".join(lines) + "\n")
  out.with_suffix(".json").write_text(json.dumps(record, indent=1, default=float) + "\n")
  print(out.read_text())
  return 0

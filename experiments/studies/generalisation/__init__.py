"""Do learned models keep objects at their true extent and brightness off their own generator?

    python -m experiments.studies.generalisation --model LABEL=RUN [--model LABEL=RUN ...]
        [--sequences 8] [--frames 8] [--seed 2026] [--out experiments/studies/generalisation/results/generalisation.md]

``RUN`` is a finished run of :mod:`experiments.studies.mechanisms` (a folder with
``run.json`` and ``model/``, e.g. ``runs/mechanisms/full/full-seed0``) or
``pretrained:NAME/VARIANT`` (weights shipped in the package,
:func:`nlosjax.inference.load_pretrained`). Every model is scored, beside the
five classic methods, on

* each model's own test split (``config["data"]["path"]``; every model on
  every one of them, so a model trained on other scenes is scored on these);
* the independent set (:mod:`experiments.independent_set`: stroke-font letters
  and digits, bar and dot charts and other shapes, its own motion, renderer
  and noise; written if absent at the first model's Setup and detector).

Beyond the Table 1 metrics, two ratios say whether a method shrinks or dims
the objects, per frame over the true object pixels ``O``
(ground-truth depth > 0):

* brightness ratio ``sum_O intensity / sum_O true intensity`` (1: as bright
  as the truth; intensities as each method outputs them, learned ones clamped
  to [0, 1], classic ones normalised to a peak of 1, the truth to a peak of 1);
* extent ratio ``|predicted surface| / |O|`` (the pixels a method calls
  surface over the object pixels; 1: the true extent).

Choices (classic settings and thresholds, the learned models' surface
thresholds) are made on the first model's validation split; nothing is chosen
on a test split. Means carry 95 % intervals over sequences
(:mod:`nlosjax.stats`); each learned model's paired difference to the best
classic method (by mean intensity PSNR on the validation split, as the main job picks it) is listed.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

from nlosjax.stats import format_interval as cell
from nlosjax.variants import OURS

#: This study's results folder: its reports, figures and JSON records.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"

#: Extra per-frame scores of this report: name -> (header, digits).
RATIOS = {"brightness": ("brightness ratio (1 = true)", 3), "extent": ("extent ratio (1 = true)", 3)}
COLUMNS = {"psnr": ("PSNR (dB) ↑", 2), "ssim": ("SSIM ↑", 3), "recall": ("object recall ↑", 3),
           "precision": ("object precision ↑", 3), **RATIOS}


def object_ratios(intensity, depth, gt_intensity, gt_depth) -> dict:
  """Per-frame brightness and extent ratios over the true object pixels.

  Args:
    intensity, depth: ``[N, H, W]`` a method's intensity and depth (metres; 0 = no surface).
    gt_intensity, gt_depth: ``[N, H, W]`` the truth.
  Returns:
    ``{"brightness": [N], "extent": [N]}`` float64; NaN on a frame without object
    pixels (or, for brightness, whose object pixels are all black in the truth).
  """
  from nlosjax import metrics
  inten = np.asarray(intensity, np.float64)
  gt_i = np.asarray(gt_intensity, np.float64)
  obj = np.asarray(gt_depth) > 0                 # the true object pixels (metrics._true_surface)
  pred = np.asarray(metrics.surface(np.asarray(depth)), bool)
  n_obj = obj.sum(axis=(1, 2)).astype(np.float64)
  true_sum = np.where(obj, gt_i, 0.0).sum(axis=(1, 2))
  with np.errstate(invalid="ignore", divide="ignore"):
    brightness = np.where(true_sum > 0, np.where(obj, inten, 0.0).sum(axis=(1, 2)) / true_sum, np.nan)
    extent = np.where(n_obj > 0, pred.sum(axis=(1, 2)) / n_obj, np.nan)
  return {"brightness": brightness, "extent": extent}


def load_model(spec: str):
  """``(model_config, params, config)`` of a finished study run folder or ``pretrained:NAME/VARIANT``."""
  if spec.startswith("pretrained:"):
    from nlosjax import inference
    name, _, variant = spec[len("pretrained:"):].partition("/")
    mcfg, params, provenance = inference.load_pretrained(name, variant or OURS)
    return mcfg, params, provenance["config"]
  from experiments.export_weights import MECHANISM_RECORDS, study_run
  from nlosjax import inference, train
  run = study_run(pathlib.Path(spec), MECHANISM_RECORDS)
  config = run["config"]
  typed = train.RunConfig.from_dict(config)
  mcfg = train.model_config_for(typed, inference.training_setup(typed), run["variant"])
  params, _ = inference.restore_params(run["checkpoints"], mcfg, step=run["step"],
                                       config_file=run["source"])
  return mcfg, params, config


def score_set(config, path, models: dict, settings: dict, thresholds: dict, log=print) -> dict:
  """Every classic method and model on the test split of ``path``: per-frame scores and ratios.

  ``config``: the :class:`~nlosjax.train.RunConfig` the file is read with.
  """
  from nlosjax.evaluation import protocol
  ev = protocol.evaluate(config, path, {k: [(m, p)] for k, (m, p) in models.items()},
                         classic_settings=settings, model_thresholds=thresholds, log=log)
  gt = ev["images"]["gt"]
  per = {}
  for method, im in ev["images"].items():
    if method == "gt":
      continue
    s = {k: np.asarray(v, np.float64).reshape(-1) for k, v in ev["scores"][method].items()
         if k in COLUMNS}
    s.update(object_ratios(im["intensity"], im["depth"], gt["intensity"], gt["depth"]))
    per[method] = s
  return {"per_frame": per, "sequence": np.asarray(ev["sequence"]), "images": ev["images"],
          "n_frames": ev["n_frames"]}


def tabulate(result: dict, models, best: str) -> tuple[list[str], dict]:
  """Markdown rows and the JSON summary of one test set; ``best``: the classic method chosen on validation."""
  from nlosjax import stats
  from nlosjax.evaluation import scores
  seq = result["sequence"]
  per = result["per_frame"]
  summary = {m: {k: stats.summarize(scores.by_sequence(v, seq)) for k, v in s.items()} for m, s in per.items()}
  classic = [m for m in per if m not in models]

  lines = ["| method | " + " | ".join(h for h, _ in COLUMNS.values()) + " |",
           "|---|" + "---|" * len(COLUMNS)]
  for m in list(models) + classic:
    name = f"{m} (best classic)" if m == best else m
    lines.append(f"| {name} | " + " | ".join(cell(summary[m].get(k), d) for k, (_, d) in COLUMNS.items())
                 + " |")
  diffs = {}
  lines.append("")
  for m in models:
    d = {k: stats.paired_difference(scores.by_sequence(per[m][k], seq), scores.by_sequence(per[best][k], seq))
         for k in ("psnr", "ssim", "recall")}
    diffs[m] = d
    verdict = "called" if stats.excludes_zero(d["psnr"]) else "not called (the interval holds 0)"
    lines.append(f"- **{m} − {best}**: intensity PSNR {cell(d['psnr'], 2, True)} dB ({verdict}); "
                 f"SSIM {cell(d['ssim'], 3, True)}; object recall {cell(d['recall'], 3, True)}.")
  return lines, {"summary": summary, "best_classic": best, "differences": diffs}



def plot(result: dict, models, best: str, path: pathlib.Path, n: int = 4) -> None:
  """The middle frame of up to ``n`` sequences: truth, best classic method, each model."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  seq = result["sequence"]
  firsts = [int(np.flatnonzero(seq == s)[len(np.flatnonzero(seq == s)) // 2])
            for s in sorted(set(seq.tolist()))[:n]]
  cols = ["gt", best] + list(models)
  fig, axes = plt.subplots(len(firsts), len(cols), figsize=(2.2 * len(cols), 2.2 * len(firsts)),
                           squeeze=False)
  for r, i in enumerate(firsts):
    for c, m in enumerate(cols):
      ax = axes[r, c]
      ax.imshow(np.clip(result["images"][m]["intensity"][i], 0, 1), cmap="gray", vmin=0, vmax=1)
      ax.set_xticks([]), ax.set_yticks([])
      if r == 0:
        ax.set_title("truth" if m == "gt" else m, fontsize=9)
  fig.tight_layout()
  fig.savefig(path, dpi=90)
  plt.close(fig)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--model", action="append", required=True, metavar="LABEL=RUN",
                      help="a finished study run folder or pretrained:NAME/VARIANT (repeatable)")
  parser.add_argument("--sequences", type=int, default=8)
  parser.add_argument("--frames", type=int, default=8)
  parser.add_argument("--seed", type=int, default=2026)
  parser.add_argument("--independent", default=None,
                      help="independent set file (default: the cpu preset's independent.path)")
  parser.add_argument("--out", default=str(RESULTS / "generalisation.md"))
  args = parser.parse_args(argv)
  argv = sys.argv[1:] if argv is None else list(argv)
  from experiments import configs
  from experiments.independent_set import GENERATOR_VERSION, ensure_independent_set
  from experiments.main_job import tune_classic
  from experiments.provenance import provenance
  from nlosjax import train as T
  from nlosjax.evaluation import protocol
  t0 = time.perf_counter()
  specs = {}
  for item in args.model:
    label, sep, spec = item.partition("=")
    if not sep or not label or not spec:
      raise SystemExit(f"--model takes LABEL=RUN, got {item!r}")
    if label in specs:
      raise SystemExit(f"--model: label {label!r} given twice")
    specs[label] = spec
  models, configs_of = {}, {}
  for label, spec in specs.items():
    mcfg, params, cfg = load_model(spec)
    models[label] = (mcfg, params)
    configs_of[label] = T.RunConfig.from_dict(cfg)
    print(f"[{label}] {spec}")
  first = configs_of[next(iter(models))]
  for cfg in configs_of.values():
    T.ensure_dataset(cfg, pathlib.Path(cfg.data.path))
  print("validation: tuning the classic methods and the models' surface thresholds ...")
  val_path = pathlib.Path(first.data.path)
  settings = tune_classic(first, val_path, print)
  best = max(settings, key=lambda m: settings[m]["psnr"])     # chosen on validation, as the main job
  learned = protocol.tune_model_thresholds(first, val_path, {k: [v] for k, v in models.items()})
  thresholds = {v: c["threshold"] for v, c in learned.items()}
  preset = configs.get_config("cpu")["independent"]
  ind_path = args.independent or preset["path"]
  ind = ensure_independent_set(ind_path, first.to_dict()["data"], args.sequences, args.frames, args.seed)
  sets = {"independent": (ind, first)}
  for label, cfg in configs_of.items():
    p = str(cfg.data.path)
    if p not in [v[0] for v in sets.values()]:
      sets[f"test split of {label}'s data"] = (p, cfg)    # read with the config it was made with
  out = pathlib.Path(args.out)
  out.parent.mkdir(parents=True, exist_ok=True)
  cmd = "python -m experiments.studies.generalisation " + " ".join(argv)
  text = ["# Objects at their true extent and brightness, off the training generator", ""]
  text += provenance(cmd.strip()) + [""]
  text += ["Models: " + "; ".join(f"`{k}` = `{v}`" for k, v in specs.items()) + ". Choices on the "
           f"validation split of `{val_path}` (classic settings, surface thresholds). Independent set: "
           f"`{ind_path}` (`{GENERATOR_VERSION}`, {args.sequences} sequences x {args.frames} frames, "
           f"seed {args.seed}). Intervals: 95 % bootstrap over sequences. Ratios over the true object "
           "pixels: brightness = summed intensity / summed true intensity; extent = predicted surface "
           f"pixels / true object pixels (module docstring). Best classic method, chosen on validation "
           f"intensity PSNR: {best}.", ""]
  record = {"models": specs, "sets": {}}
  for name, (path, cfg) in sets.items():
    print(f"scoring on {name}: {path} ...")
    result = score_set(cfg, path, models, settings, thresholds)
    lines, summary = tabulate(result, models, best)
    figure = out.with_name(f"{out.stem}_{'independent' if name == 'independent' else len(record['sets'])}.png")
    plot(result, models, summary["best_classic"], figure)
    text += [f"## {name}: `{path}`", "", f"{result['n_frames']} frames. Figure: `{figure.name}`.", ""]
    text += lines + [""]
    record["sets"][name] = {"path": str(path), **summary}
  text += [f"Wall time {time.perf_counter() - t0:.0f} s."]
  out.write_text("\n".join(text) + "\n")
  out.with_suffix(".json").write_text(json.dumps(record, indent=2, default=float) + "\n")
  print(out.read_text())
  return 0

"""The surface cut as a lever for object recall: every method's recall, precision and F1 over thresholds.

    python -m experiments.studies.surface_cut [--data runs/data/cpu-v3.h5]

A reconstructed pixel counts as surface where its intensity (peak 1) reaches the surface
threshold (:func:`nlosjax.evaluation.protocol.surface_cut`); the main job chooses each
method's threshold by validation surface F1. The shipped networks' F1-best threshold leaves
their object recall below the classic methods' (the main job's table), so the question is
whether another threshold, chosen on validation, reaches the best classic method's recall
while keeping F1 above the best classic method's: a lever that needs no training.

On the ``cpu`` preset's **validation split** only (the test split plays no part): the shipped
``cpu`` networks (Ours, Ours-S) and the five classic methods at their validation-tuned options
(:func:`experiments.main_job.tune_classic`, as the main job), each at every threshold of
:data:`THRESHOLDS`; per threshold the mean recall, precision and F1 over frames. Then, for
each network, the operating point that reaches the recall of the classic method with the
highest recall at its own chosen threshold (the highest F1 among the network's thresholds
whose mean recall is at least that), and there the paired difference of F1 with the best
classic method's (the highest F1 at its chosen threshold) and of precision with the
high-recall classic method's, each with a 95 % bootstrap interval over sequences.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

from experiments import provenance
from nlosjax.variants import OURS, OURS_S

#: This study's results folder.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"
NAME = "surface_cut"
#: Candidate thresholds (fractions of the peak intensity): the main job's grid and the steps between.
THRESHOLDS = (0.05, 0.1, 0.125, 0.15, 0.175, 0.2, 0.225, 0.25, 0.3, 0.4, 0.5)
SCORES = ("recall", "precision", "f1")


def frame_scores(intensity, depth, gt_depth, thresholds=THRESHOLDS) -> dict[float, dict[str, np.ndarray]]:
  """``threshold -> score -> [N]`` per-frame surface scores of one method's images at each threshold.

  ``intensity``, ``depth``: ``[N, H, W]`` (peak-normalised intensity; depth in metres, cut at no
  threshold); ``gt_depth`` ``[N, H, W]`` (0 = background).
  """
  from nlosjax import metrics
  from nlosjax.evaluation.protocol import surface_cut
  out = {}
  for th in thresholds:
    s = metrics.surface_scores(surface_cut(intensity, depth, th), gt_depth)
    out[float(th)] = {k: np.asarray(s[k], np.float64) for k in SCORES}
  return out


def mean_curve(per_frame: dict) -> dict[float, dict[str, float]]:
  """``threshold -> score -> mean over defined frames`` of :func:`frame_scores`' output."""
  return {th: {k: float(np.nanmean(v)) for k, v in s.items()} for th, s in per_frame.items()}


def operating_point(curve: dict[float, dict[str, float]], min_recall: float) -> float | None:
  """The threshold with the highest mean F1 among those whose mean recall is at least ``min_recall``
  (ties: the higher threshold); None where no threshold reaches it."""
  ok = [th for th, s in curve.items() if s["recall"] >= min_recall]
  if not ok:
    return None
  return max(ok, key=lambda th: (curve[th]["f1"], th))


def compare(per_frame: dict[str, dict], chosen: dict[str, float], sequence, networks) -> dict:
  """The study's verdicts from per-frame scores.

  Args:
    per_frame: ``method -> threshold -> score -> [N]``.
    chosen: each classic method's validation-chosen threshold.
    sequence: ``[N]`` sequence index of each frame.
    networks: the learned methods in ``per_frame``.
  Returns:
    ``{"high_recall": classic method, "target_recall", "best_f1": classic method,
    "target_f1", "networks": {name: {"threshold", "recall", "precision", "f1",
    "f1_minus_best", "precision_minus_high_recall"}}}`` (differences as
    :func:`nlosjax.stats.paired_difference`'s summaries; None where no threshold reaches the recall).
  """
  from nlosjax.evaluation.scores import by_sequence
  from nlosjax.stats import paired_difference
  curves = {m: mean_curve(s) for m, s in per_frame.items()}
  at_chosen = {m: curves[m][chosen[m]] for m in chosen}
  high = max(at_chosen, key=lambda m: at_chosen[m]["recall"])
  best = max(at_chosen, key=lambda m: at_chosen[m]["f1"])
  out = {"high_recall": high, "target_recall": at_chosen[high]["recall"], "best_f1": best,
         "target_f1": at_chosen[best]["f1"], "networks": {}}
  for net in networks:
    th = operating_point(curves[net], at_chosen[high]["recall"])
    row = {"threshold": th}
    if th is not None:
      row.update(curves[net][th])
      row["f1_minus_best"] = paired_difference(by_sequence(per_frame[net][th]["f1"], sequence),
                                               by_sequence(per_frame[best][chosen[best]]["f1"], sequence))
      row["precision_minus_high_recall"] = paired_difference(
          by_sequence(per_frame[net][th]["precision"], sequence),
          by_sequence(per_frame[high][chosen[high]]["precision"], sequence))
    out["networks"][net] = row
  return out


def measure(data_path: pathlib.Path, log=print) -> tuple[dict, dict, np.ndarray, dict]:
  """``(per_frame, chosen, sequence, options)`` on the validation split of ``data_path``."""
  from experiments import configs
  from experiments.main_job import tune_classic
  from nlosjax import inference, train
  from nlosjax.evaluation import baselines, protocol
  from nlosjax.evaluation.protocol import surface_cut
  d = configs.get_config("cpu")
  d["data"]["path"] = str(data_path)
  cfg = train.RunConfig.from_dict(d)
  train.ensure_dataset(cfg, data_path, log=log)
  settings = tune_classic(cfg, data_path, log)
  data = protocol.load_split(cfg, data_path, "val", batch_size=cfg.train.eval_batch)
  per_frame = {}
  try:
    for variant in (OURS, OURS_S):
      mcfg, params, _ = inference.load_pretrained("cpu", variant)
      im = protocol.model_images(mcfg, params, data["loader"])
      per_frame[variant] = frame_scores(im["intensity"], im["depth"], data["depth"])
      log(f"{variant}: scored at {len(THRESHOLDS)} thresholds")
    for method, s in settings.items():
      # Depth everywhere the intensity is nonzero; the cut is then the same rule as
      # nlosjax.physics.intensity_depth's threshold (checked below at the chosen one).
      intensity, depth = baselines.classic_images(data["measurement"], data["setup"], data["stride"],
                                                  method, s["options"], threshold=0.0)
      per_frame[method] = frame_scores(intensity, depth, data["depth"])
      _, direct = baselines.classic_images(data["measurement"], data["setup"], data["stride"], method,
                                           s["options"], threshold=s["threshold"])
      if not np.array_equal(surface_cut(intensity, depth, s["threshold"]), direct):
        raise AssertionError(f"{method}: the cut at {s['threshold']} differs from intensity_depth's")
      log(f"{method}: scored at {len(THRESHOLDS)} thresholds")
  finally:
    data["loader"].close()
  chosen = {m: float(s["threshold"]) for m, s in settings.items()}
  return per_frame, chosen, np.asarray(data["sequence"]), {m: s["options"] for m, s in settings.items()}


def report(per_frame: dict, chosen: dict, verdict: dict, options: dict, command: str, data_path) -> str:
  from nlosjax.evaluation.report import label
  from nlosjax.stats import excludes_zero, format_interval
  curves = {m: mean_curve(s) for m, s in per_frame.items()}
  n = len(next(iter(next(iter(per_frame.values())).values()))["f1"])
  lines = ["# The surface cut: recall, precision and F1 of every method over thresholds", ""]
  lines += provenance.provenance(command) + [""]
  lines += [f"Validation split of `{data_path}` ({n} frames; the test split plays no part). Shipped"
            " `cpu` networks; classic methods at their validation-tuned options ("
            + "; ".join(f"{label(m)} {o or 'defaults'}" for m, o in options.items()) + ")."
            " Each cell: mean recall / precision / F1 over frames; **bold**: the threshold the main"
            " job's rule (best validation F1) takes for a classic method.", "",
            "| threshold | " + " | ".join(label(m) for m in curves) + " |",
            "|---|" + "---|" * len(curves)]
  for th in sorted({t for c in curves.values() for t in c}):
    cells = []
    for m, c in curves.items():
      if th not in c:
        cells.append("—")
        continue
      s = c[th]
      text = f"{s['recall']:.3f} / {s['precision']:.3f} / {s['f1']:.3f}"
      cells.append(f"**{text}**" if chosen.get(m) == th else text)
    lines.append(f"| {th:g} | " + " | ".join(cells) + " |")
  hi, best = verdict["high_recall"], verdict["best_f1"]
  lines += ["", f"The classic method with the highest recall at its chosen threshold: {label(hi)}"
            f" ({verdict['target_recall']:.3f}); the highest F1: {label(best)} ({verdict['target_f1']:.3f}).",
            "", "| network | threshold reaching that recall (best F1 among them) | recall | precision | F1 |"
            f" F1 − {label(best)}'s | precision − {label(hi)}'s |", "|---|---|---|---|---|---|---|"]
  met = {}
  for net, r in verdict["networks"].items():
    if r["threshold"] is None:
      lines.append(f"| {label(net)} | none | — | — | — | — | — |")
      met[net] = False
      continue
    d = r["f1_minus_best"]
    met[net] = excludes_zero(d) and d["mean"] > 0
    lines.append(f"| {label(net)} | {r['threshold']:g} | {r['recall']:.3f} | {r['precision']:.3f} | {r['f1']:.3f} |"
                 f" {format_interval(d, 3, signed=True)} |"
                 f" {format_interval(r['precision_minus_high_recall'], 3, signed=True)} |")
  lines += ["", "Differences: mean over frames [95 % bootstrap interval over sequences], paired on the same"
            " frames."]
  if any(met.values()):
    lines.append("**The cut is a lever:** " + ", ".join(label(n) for n, ok in met.items() if ok)
                 + f" reaches {label(hi)}'s recall with F1 above {label(best)}'s (interval above 0).")
  else:
    lines.append(f"**The cut is not a lever for recall:** at the threshold where each network reaches"
                 f" {label(hi)}'s recall, its F1 is not above {label(best)}'s (the interval does not lie"
                 " above 0): along the threshold the networks trade recall for precision on about the"
                 " classic methods' curve, so a lower cut buys recall only with precision.")
  return "\n".join(lines) + "\n"


def figure(per_frame: dict, chosen: dict, path: pathlib.Path) -> None:
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  from nlosjax.evaluation.report import label
  fig, ax = plt.subplots(figsize=(5.5, 4.5))
  for m, s in per_frame.items():
    c = mean_curve(s)
    r = [c[t]["recall"] for t in sorted(c)]
    p = [c[t]["precision"] for t in sorted(c)]
    ax.plot(r, p, "-o" if m in (OURS, OURS_S) else "--.", label=label(m), ms=3)
    if m in chosen:
      ax.plot(c[chosen[m]]["recall"], c[chosen[m]]["precision"], "k*", ms=8)
  ax.set(xlabel="object recall", ylabel="surface precision",
         title="Validation: recall against precision over the surface threshold\n"
               "(* each classic method's chosen threshold)")
  ax.grid(alpha=0.3)
  ax.legend(fontsize=8)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--data", default="runs/data/cpu-v3.h5",
                 help="the cpu preset's dataset (made if absent; default: the main job's)")
  p.add_argument("--results", default=str(RESULTS), help="where the report goes")
  args = p.parse_args(argv)
  from experiments import xla_cache
  xla_cache.enable()
  data_path = pathlib.Path(args.data)
  per_frame, chosen, sequence, options = measure(data_path)
  verdict = compare(per_frame, chosen, sequence, (OURS, OURS_S))
  command = ("python -m experiments.studies.surface_cut " + " ".join(sys.argv[1:] if argv is None else argv)).strip()
  results = pathlib.Path(args.results)
  results.mkdir(parents=True, exist_ok=True)
  text = report(per_frame, chosen, verdict, options, command, data_path)
  (results / f"{NAME}.md").write_text(text)
  (results / f"{NAME}.json").write_text(json.dumps(
      {"curves": {m: {str(t): v for t, v in mean_curve(s).items()} for m, s in per_frame.items()},
       "chosen": chosen, "verdict": verdict}, indent=1, default=float) + "\n")
  figure(per_frame, chosen, results / f"{NAME}.png")
  print(text)
  return 0

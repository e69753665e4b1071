"""Markdown of an evaluation: Table 1 with intervals, the object-aware and temporal tables, paired comparisons.

Input is what :func:`nlosjax.evaluation.protocol.tabulate` returns: ``table``
(``method -> metric -> summary``) and ``comparisons`` (a list of ``{"a", "b",
"label", "diff": metric -> summary}``). Each cell is ``mean [lo, hi]``, the
95 % bootstrap interval over sequences (and seeds). The sentences under the
comparison table are written from the numbers: a difference is called only
where its interval excludes 0. The temporal table, and the temporal column
of the comparisons, appear where the table holds the temporal scores
(:data:`~nlosjax.evaluation.scores.TEMPORAL_METRICS`; a table written before
them renders as it did).
"""

from __future__ import annotations

import math

from nlosjax import stats
from nlosjax.evaluation.scores import HIGHER_IS_BETTER, TEMPORAL_METRICS
from nlosjax.variants import VARIANTS

__all__ = ["METHOD_LABELS", "TABLE_METHODS", "METRIC_LABELS", "label", "format_tables",
           "format_comparisons", "format_choices"]

METHOD_LABELS = {"fbp": "FBP", "lct": "LCT", "fk": "f-k", "phasor": "Phasor", "rsd": "RSD",
                 "csa": "CSA", **{name: v.label for name, v in VARIANTS.items()}}
#: Row order of every table: the classic methods, then the learned ones (baselines first).
TABLE_METHODS = ("fbp", "lct", "fk", "phasor", "rsd", *reversed(VARIANTS))
METRIC_LABELS = {"psnr": ("intensity PSNR", "dB", 2),
                 "psnr_zero": ("all-zero image's PSNR", "dB", 2),
                 "psnr_balanced": ("object-balanced PSNR", "dB", 2),
                 "psnr_balanced_zero": ("all-zero image's balanced PSNR", "dB", 2),
                 "intensity_mae_object": ("object intensity error", "", 3), "ssim": ("intensity SSIM", "", 3),
                 "rmse": ("depth RMSE", "m", 3), "mad": ("depth MAD", "m", 3),
                 "rmse_object": ("object depth RMSE", "m", 3),
                 "mad_object": ("object depth MAD", "m", 3),
                 "recall": ("object recall", "", 3), "precision": ("surface precision", "", 3),
                 "f1": ("surface F1", "", 3),
                 "temporal_rmse": ("temporal intensity error", "", 3),
                 "temporal_psnr": ("temporal intensity PSNR", "dB", 2),
                 "temporal_rmse_object": ("temporal depth error (objects)", "m", 3)}
PAPER_METRICS = ("psnr", "psnr_zero", "ssim", "rmse", "mad")
OBJECT_METRICS = ("intensity_mae_object", "psnr_balanced", "psnr_balanced_zero", "rmse_object", "mad_object",
                  "recall", "precision", "f1")
#: Columns of the paired-differences table (and the temporal intensity error where compared).
COMPARISON_METRICS = ("intensity_mae_object", "psnr_balanced", "recall", "f1", "rmse_object", "psnr", "ssim")


def label(method: str) -> str:
  """Display name of a method (the key itself when unknown)."""
  return METHOD_LABELS.get(method, method)


def _cell(s: dict, digits: int, signed: bool = False) -> str:
  return stats.format_interval(s, digits, signed, missing="n/a")


def _header(metric: str) -> str:
  name, unit, _ = METRIC_LABELS[metric]
  arrow = "↑" if HIGHER_IS_BETTER[metric] else "↓"
  return f"{name}{f' ({unit})' if unit else ''} {arrow}"


def _rows(table: dict) -> list[str]:
  return [m for m in TABLE_METHODS if m in table] + [m for m in table if m not in TABLE_METHODS]


def _grid(table: dict, metrics: tuple[str, ...], counts: str = "sequences / frames / seeds") -> list[str]:
  lines = ["| method | " + " | ".join(_header(k) for k in metrics) + f" | {counts} |",
           "|---|" + "---|" * len(metrics) + "---|"]
  for m in _rows(table):
    r = table[m]
    first = next(r[k] for k in metrics if k in r)
    counts = f"{first['n_sequences']} / {first['n_frames']} / {first.get('n_seeds', 1)}"
    # A table written before a metric existed shows n/a in its column.
    lines.append(f"| {label(m)} | " + " | ".join(_cell(r[k], METRIC_LABELS[k][2]) if k in r else "n/a"
                                                 for k in metrics) + f" | {counts} |")
  return lines


def format_tables(table: dict, caption: str = "") -> str:
  """Markdown: the object-aware scores first, then the paper's Table 1 metrics, then the temporal ones;
  ``mean [95 % CI]``, each PSNR beside the all-zero image's.

  The temporal table lists the methods whose row holds every metric of
  :data:`~nlosjax.evaluation.scores.TEMPORAL_METRICS`, and is left out when
  none does.
  """
  lines = ([caption, ""] if caption else [])
  lines += ["Mean [95 % bootstrap interval over sequences, and over training seeds where there "
            "are several]; a frame's scores count once per seed.", "",
            "**On the objects** (object intensity error: mean absolute intensity error over the "
            "true object pixels, which a dark background cannot lower; object-balanced PSNR: "
            "intensity PSNR with object and background pixels weighted equally, beside the all-zero "
            "image's; depth error over the true surface pixels; recall: share of "
            "them reconstructed as surface; precision: share of the reconstructed surface that is "
            "true surface; surface = depth >= 0.1 m for every method):", ""]
  lines += _grid(table, OBJECT_METRICS)
  lines += ["", "**The paper's metrics** (whole-image depth counts every background pixel; the all-zero "
            "image's PSNR is the floor an empty reconstruction reaches on the same frames):", ""]
  lines += _grid(table, PAPER_METRICS)
  temporal = {m: r for m, r in table.items() if all(k in r for k in TEMPORAL_METRICS)}
  if temporal:
    lines += ["", "**Over time** (per pair of consecutive evaluated frames of a test sequence, never "
              "across sequences or seeds: the error of the reconstruction's change between the two "
              "frames against the true change, `(ŷ_t − ŷ_{t−1}) − (y_t − y_{t−1})`; intensity RMSE, its "
              "PSNR with peak 1 as for intensity PSNR, and depth RMSE over the pixels that are true "
              "surface in both frames):", ""]
    lines += _grid(temporal, TEMPORAL_METRICS, counts="sequences / frame pairs / seeds")
  return "\n".join(lines) + "\n"


def _verdict(c: dict, metric: str) -> str:
  d = c["diff"][metric]
  name, unit, digits = METRIC_LABELS[metric]
  lo, hi = d["ci95"]
  span = f"{d['mean']:+.{digits}f}{f' {unit}' if unit else ''} [{lo:+.{digits}f}, {hi:+.{digits}f}]"
  if not math.isfinite(d["mean"]):
    return f"{c['label']}, {name}: undefined."
  if not stats.excludes_zero(d):
    return f"{c['label']}, {name}: {span}; the interval includes 0, no difference is called."
  better = (d["mean"] > 0) == HIGHER_IS_BETTER[metric]
  return (f"{c['label']}, {name}: {span}; {label(c['a'])} is "
          f"{'better' if better else 'worse'} than {label(c['b'])}.")


def format_comparisons(comparisons: list[dict], metrics=None) -> str:
  """Markdown table of paired differences ``a - b`` and one sentence per comparison and metric.

  ``metrics``: the columns; by default :data:`COMPARISON_METRICS`, then
  ``temporal_rmse`` where a comparison holds it (the sentences follow the
  same rule). A comparison without a column's metric shows "n/a".
  """
  if not comparisons:
    return ""
  called = ("intensity_mae_object", "psnr_balanced", "recall", "f1", "rmse_object", "psnr")
  if metrics is None:
    metrics = COMPARISON_METRICS
    if any("temporal_rmse" in c["diff"] for c in comparisons):
      metrics += ("temporal_rmse",)
      called += ("temporal_rmse",)
  lines = ["**Paired differences** (a - b on the same frames; 95 % bootstrap interval over "
           "sequences and seeds):", "",
           "| comparison | " + " | ".join(_header(k) for k in metrics) + " |",
           "|---|" + "---|" * len(metrics)]
  for c in comparisons:
    lines.append(f"| {c['label']} | " + " | ".join(
        _cell(c["diff"][k], METRIC_LABELS[k][2], signed=True) if k in c["diff"] else "n/a"
        for k in metrics) + " |")
  lines += [""] + [f"- {_verdict(c, k)}" for c in comparisons for k in called
                   if k in c["diff"]]
  return "\n".join(lines) + "\n"


def format_choices(validation: dict) -> str:
  """Markdown of the choices made on the validation split (classic settings, surface thresholds, checkpoints)."""
  lines = ["**Chosen on the validation split** (the test split only writes the tables above):", ""]
  classic = validation.get("classic", {})
  if classic:
    lines += ["| method | options | surface threshold | val. intensity PSNR (dB) | val. surface F1 | grid |",
              "|---|---|---|---|---|---|"]
    for m, c in classic.items():
      opts = ", ".join(f"{k}={v}" for k, v in c["options"].items()) or "none"
      lines.append(f"| {label(m)} | {opts} | {c['threshold']} | {c['psnr']:.2f} | {c['f1']:.3f} "
                   f"| {len(c['grid'])} option(s) x {len(c['grid'][0]['f1_by_threshold'])} thresholds |")
    if validation.get("best_classic"):
      lines += ["", f"Best classic method on validation (intensity PSNR): "
                f"{label(validation['best_classic'])}."]
  learned = validation.get("learned", {})
  if learned:
    ths = list(next(iter(learned.values()))["f1_by_threshold"])
    lines += ["", "Learned models' surface threshold (0: the model's own depth map), chosen by "
              "the same rule (mean validation surface F1 over seeds):", "",
              "| model | surface threshold | " + " | ".join(f"F1 at {t}" for t in ths) + " |",
              "|---|---|" + "---|" * len(ths)]
    for v, c in learned.items():
      lines.append(f"| {label(v)} | {c['threshold']} | "
                   + " | ".join(f"{c['f1_by_threshold'][t]:.3f}" for t in ths) + " |")
  checkpoints = validation.get("checkpoints", {})
  if checkpoints:
    lines += ["", "| model | seed | checkpoint step | chosen on | validation score (dB) at each kept step |",
              "|---|---|---|---|---|"]
    for c in checkpoints.values():
      metric = c.get("metric", "psnr")
      steps = ", ".join(f"{s}: {v:.2f}" for s, v in c.get("val_score", c["val_psnr"]).items())
      lines.append(f"| {label(c['variant'])} | {c['seed']} | {c['step']} | {METRIC_LABELS[metric][0]} | {steps} |")
  return "\n".join(lines) + "\n"

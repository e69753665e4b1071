"""The headroom report: objects tables, the breakdown by attribute, the gaps, and the figure, from the records.

Input is :func:`experiments.studies.headroom.study.load_records`'s dict. Sets are reported in
:data:`GROUPS` order; the held-out renderer's conditions are pooled into one group
(``heldout``, sequences kept apart by condition) and also listed condition by condition.
"""

from __future__ import annotations

import math

import numpy as np

from experiments.studies.headroom import breakdown
from experiments.studies.headroom.study import BOUNDS, CLASSIC, OBJECT_SCORES, ZERO
from nlosjax import stats
from nlosjax.evaluation import report as ereport
from nlosjax.evaluation.scores import HIGHER_IS_BETTER, by_sequence, compare_scores

__all__ = ["GROUPS", "COLUMNS", "GAP_BOUND", "groups", "method_order", "label", "summarise", "to_markdown",
           "plot"]

#: Report order of the sets (``heldout``: every ``heldout-<condition>`` set pooled).
GROUPS = ("test", "independent", "heldout")
GROUP_TITLES = {"test": "the `cpu` preset's test split", "independent": "the independent set",
                "heldout": "the held-out renderer (conditions pooled)"}
#: The objects table's columns (the whole-image PSNR last, as the guard).
COLUMNS = OBJECT_SCORES + ("psnr",)
#: The bound the gaps are measured to.
GAP_BOUND = "bound_bilinear"
#: Scores of the gaps table: the learned model against the reference classic method, and the bound against it.
GAP_SCORES = ("intensity_mae_object", "psnr_balanced", "recall", "f1")
#: Offset between the sequence numbers of two pooled held-out conditions.
_CONDITION_STRIDE = 1000


def label(method: str) -> str:
  """Display name of a method of the study."""
  return {ZERO: "all-zero image", "bound_bilinear": "truth at the scan points, bilinear",
          "bound_nearest": "truth at the scan points, nearest"}.get(method, ereport.label(method))


def _pool(entries: list[tuple[str, dict]]) -> dict:
  """One group of several sets: frames concatenated, sequence numbers kept apart per set."""
  methods = set.intersection(*(set(e["methods"]) for _, e in entries))
  out = {"sequence": np.concatenate([e["sequence"] + i * _CONDITION_STRIDE for i, (_, e) in enumerate(entries)]),
         "attributes": {k: np.concatenate([e["attributes"][k] for _, e in entries]) for k in breakdown.ATTRIBUTES},
         "methods": {}, "sets": [n for n, _ in entries]}
  for m in methods:
    out["methods"][m] = {"scores": {k: np.concatenate([e["methods"][m]["scores"][k] for _, e in entries])
                                    for k in entries[0][1]["methods"][m]["scores"]}}
  return out


def groups(records: dict) -> dict:
  """``group -> {"sequence", "attributes", "methods": method -> {"scores"}, "sets"}`` in :data:`GROUPS` order."""
  sets = records["sets"]
  out = {}
  for g in GROUPS:
    if g == "heldout":
      entries = [(n, e) for n, e in sets.items() if n.startswith("heldout-")]
      if entries:
        out[g] = _pool(entries)
    elif g in sets:
      out[g] = {**sets[g], "sets": [g]}
  return out


def method_order(methods) -> list[str]:
  """The floor, the classic methods, the learned ones (the shipped first), the bounds."""
  known = [ZERO, *CLASSIC, "ours_s", "ours"]
  learned = [m for m in methods if m not in known and m not in BOUNDS]
  return [m for m in known if m in methods] + sorted(learned) + [b for b in BOUNDS if b in methods]


def learned_methods(methods) -> list[str]:
  return [m for m in method_order(methods) if m not in (ZERO, *CLASSIC, *BOUNDS)]


def summarise(records: dict, n_boot: int | None = None) -> dict:
  """Every number of the report (JSON-ready): per group the table, the breakdown and the gaps."""
  kw = {} if n_boot is None else {"n_boot": n_boot}
  ref = records["choices"].get("reference", {})
  out = {"reference": ref, "groups": {}}
  for g, e in groups(records).items():
    seq = e["sequence"]
    methods = method_order(e["methods"])
    pick = {m: {k: e["methods"][m]["scores"][k] for k in COLUMNS + ("psnr_zero", "psnr_balanced_zero")}
            for m in methods}
    table = {m: {k: stats.summarize(by_sequence(v, seq), **kw) for k, v in s.items()} for m, s in pick.items()}
    gaps = {}
    for m in learned_methods(methods):
      if all(ref.get(k) in pick for k in GAP_SCORES):
        gaps[f"{m} - reference"] = {k: stats.paired_difference(by_sequence(pick[m][k], seq),
                                                                by_sequence(pick[ref[k]][k], seq), **kw)
                                    for k in GAP_SCORES}
      if GAP_BOUND in pick:
        gaps[f"{GAP_BOUND} - {m}"] = compare_scores({k: pick[GAP_BOUND][k] for k in GAP_SCORES},
                                                    {k: pick[m][k] for k in GAP_SCORES}, seq, **kw)
    split = {}
    for attr in breakdown.BREAKDOWN:
      values = e["attributes"][attr]
      edges = breakdown.tercile_edges(values)
      which = breakdown.bins(values, edges)
      ranges = []
      for b in range(3):
        v = values[which == b]
        ranges.append(None if v.size == 0 else {"lo": float(v.min()), "hi": float(v.max()),
                                                 "mean": float(v.mean()), "n_frames": int(v.size),
                                                 "n_sequences": int(np.unique(seq[which == b]).size)})
      per_method = {m: breakdown.bin_summaries({k: pick[m][k] for k in OBJECT_SCORES}, seq, which, **kw)
                    for m in methods}
      bin_gaps = {}
      for m in learned_methods(methods):
        if all(ref.get(k) in pick for k in GAP_SCORES):
          bin_gaps[f"{m} - reference"] = breakdown.bin_differences(
              {k: pick[m][k] for k in GAP_SCORES}, {k: pick[ref[k]][k] for k in GAP_SCORES}, seq, which, **kw)
        if GAP_BOUND in pick:
          bin_gaps[f"{GAP_BOUND} - {m}"] = breakdown.bin_differences(
              {k: pick[GAP_BOUND][k] for k in GAP_SCORES}, {k: pick[m][k] for k in GAP_SCORES}, seq, which, **kw)
      split[attr] = {"edges": [float(x) for x in edges], "bins": ranges, "methods": per_method, "gaps": bin_gaps}
    conditions = {}
    if g == "heldout":
      for n in e["sets"]:
        s = records["sets"][n]
        conditions[n.split("-", 1)[1]] = {
            m: {k: stats.summarize(by_sequence(s["methods"][m]["scores"][k], s["sequence"]), **kw)
                for k in ("intensity_mae_object", "f1", "psnr_balanced")}
            for m in method_order(s["methods"])}
    out["groups"][g] = {"sets": e["sets"], "n_frames": int(seq.size), "n_sequences": int(np.unique(seq).size),
                        "table": table, "gaps": gaps, "breakdown": split, "conditions": conditions}
  return out


# ---------------------------------------------------------------------- Markdown
def _digits(metric: str) -> int:
  return ereport.METRIC_LABELS[metric][2]


def _head(metric: str) -> str:
  name, unit, _ = ereport.METRIC_LABELS[metric]
  return f"{name}{f' ({unit})' if unit else ''} {'↑' if HIGHER_IS_BETTER[metric] else '↓'}"


def _mean(s: dict | None, digits: int) -> str:
  if s is None or s.get("mean") is None or not math.isfinite(s["mean"]):
    return "—"
  return f"{s['mean']:.{digits}f}"


def _range(r: dict | None, attr: str) -> str:
  if r is None:
    return "—"
  d = 0 if attr == "photons" else 2 if attr == "depth" else 3
  return f"{r['lo']:.{d}f}–{r['hi']:.{d}f}"


def _objects_table(table: dict) -> list[str]:
  lines = ["| method | " + " | ".join(_head(k) for k in COLUMNS) + " | sequences / frames |",
           "|---|" + "---|" * len(COLUMNS) + "---|"]
  for m, r in table.items():
    lines.append(f"| {label(m)} | " + " | ".join(stats.format_interval(r[k], _digits(k), missing="n/a")
                                                 for k in COLUMNS)
                 + f" | {r['psnr']['n_sequences']} / {r['psnr']['n_frames']} |")
  return lines


def _gap_label(key: str) -> str:
  a, b = key.split(" - ")
  return f"{label(a)} − {'the reference classic method' if b == 'reference' else label(b)}"


def _gaps_table(gaps: dict) -> list[str]:
  lines = ["| difference | " + " | ".join(_head(k) for k in GAP_SCORES) + " |",
           "|---|" + "---|" * len(GAP_SCORES)]
  for key, d in gaps.items():
    lines.append(f"| {_gap_label(key)} | " + " | ".join(
        stats.format_interval(d[k], _digits(k), signed=True, missing="n/a") for k in GAP_SCORES) + " |")
  return lines


def _breakdown_tables(split: dict) -> list[str]:
  attrs = list(split)
  lines = []
  header = "| method | " + " | ".join(f"{a} {i + 1}" for a in attrs for i in range(3)) + " |"
  ranges = "| *range* | " + " | ".join(_range(split[a]["bins"][i], a) for a in attrs for i in range(3)) + " |"
  counts = "| *sequences / frames* | " + " | ".join(
      "—" if split[a]["bins"][i] is None else f"{split[a]['bins'][i]['n_sequences']} / {split[a]['bins'][i]['n_frames']}"
      for a in attrs for i in range(3)) + " |"
  methods = list(next(iter(split.values()))["methods"])
  for metric in OBJECT_SCORES:
    lines += ["", f"*{_head(metric)}*, by tercile:", "", header, "|---|" + "---|" * (3 * len(attrs)), ranges, counts]
    for m in methods:
      cells = []
      for a in attrs:
        for s in split[a]["methods"][m]:
          cells.append(_mean(None if s is None else s[metric], _digits(metric)))
      lines.append(f"| {label(m)} | " + " | ".join(cells) + " |")
  return lines


def _bin_gaps_table(split: dict) -> list[str]:
  keys = list(next(iter(split.values()))["gaps"])
  if not keys:
    return []
  cols = [(key, k) for key in keys for k in GAP_SCORES]
  lines = ["| attribute: tercile (range) | " + " | ".join(f"{_gap_label(key)}: {ereport.METRIC_LABELS[k][0]}"
                                                         for key, k in cols) + " |",
           "|---|" + "---|" * len(cols)]
  for a, s in split.items():
    for i in range(3):
      diffs = [None if s["gaps"][key][i] is None else s["gaps"][key][i][k] for key, k in cols]
      lines.append(f"| {a} {i + 1} ({_range(s['bins'][i], a)}) | " + " | ".join(
          stats.format_interval(d, _digits(k), signed=True, missing="—") for d, (_, k) in zip(diffs, cols)) + " |")
  return lines


def _called(split: dict, key: str, metric: str) -> tuple[list[str], list[str]]:
  """The bins where ``key``'s difference on ``metric`` is called better / worse for its left side."""
  better, worse = [], []
  for a, s in split.items():
    for i in range(3):
      d = None if s["gaps"].get(key) is None or s["gaps"][key][i] is None else s["gaps"][key][i][metric]
      if d is None or not math.isfinite(d["mean"]) or not stats.excludes_zero(d):
        continue
      (better if (d["mean"] > 0) == HIGHER_IS_BETTER[metric] else worse).append(f"{a} {i + 1}")
  return better, worse


def _tighter(table: dict) -> list[str]:
  if not all(b in table for b in BOUNDS):
    return []
  out = []
  for k in ("intensity_mae_object", "psnr_balanced", "f1", "rmse_object"):
    a, b = (table[x][k]["mean"] for x in BOUNDS)
    sign = 1 if HIGHER_IS_BETTER[k] else -1
    best = BOUNDS[0] if sign * a >= sign * b else BOUNDS[1]
    out.append(f"{ereport.METRIC_LABELS[k][0]}: {best.split('_')[1]} "
               f"({a:.{_digits(k)}f} bilinear, {b:.{_digits(k)}f} nearest)")
  return ["- Of the two readings of the truth, the better on each score (the ceiling at this density is at "
          "least it): " + "; ".join(out) + "."]


def to_markdown(summary: dict, header: list[str], choices: dict, *, stride: int, grid, invocations=()) -> str:
  """The report's Markdown (``header``: the provenance lines; ``invocations``: the runs that wrote the
  records, ``{"args", "wall_s", "date"}`` each)."""
  h = tuple(int(g) for g in grid)
  low = tuple(-(-(n - stride // 2) // stride) for n in h)
  ref = summary["reference"]
  lines = ["# Headroom: every method's object scores beside what the input's scan grid supports", ""]
  lines += header + [""]
  lines += [
      f"Every method on the objects of each test set, at the input's {low[0]} × {low[1]} scan points "
      f"(stride {stride} of the {h[0]} × {h[1]} grid), beside two readings of the *truth* through the same "
      f"scan points: its intensity and depth at the {low[0]} × {low[1]} points, read back to the full grid "
      "bilinearly as the classic methods read the sparse scan (depth as a normalised convolution of the "
      "object indicator, surface where it reaches the cut chosen on validation), or from the nearest scan point "
      "(`experiments/studies/headroom/bounds.py`). They are no strict bound (each scan point of a confocal "
      "capture sees the whole scene, and a prior on shapes can place detail between the points); they say how "
      "much of each object score survives sampling the image itself at the input's density. The all-zero image "
      "is the floor of every score.",
      "",
      "Every choice is made on the `cpu` preset's validation split, as the main job makes it: the classic "
      "methods' settings and surface thresholds, the learned models' surface thresholds, the bilinear reading's "
      "cut, and for each object score the *reference classic method*, the one with the best validation mean "
      "on that score (" + ", ".join(f"{ereport.METRIC_LABELS[k][0]}: {label(v)}" for k, v in ref.items())
      + "). Means with 95 % bootstrap intervals over sequences; a difference is called where its interval "
      "excludes 0.", ""]
  for g, e in summary["groups"].items():
    lines += [f"## Objects on {GROUP_TITLES[g]}", "",
              f"{e['n_sequences']} sequences, {e['n_frames']} frames"
              + (f" ({', '.join(s.split('-', 1)[1] for s in e['sets'])})." if g == "heldout" else "."), ""]
    lines += _objects_table(e["table"])
    lines += [""] + _tighter(e["table"])
    if e["gaps"]:
      lines += ["", "Paired differences on the same frames:", ""] + _gaps_table(e["gaps"])
    if e["conditions"]:
      conds = list(e["conditions"])
      for metric in ("intensity_mae_object", "f1", "psnr_balanced"):
        lines += ["", f"*{_head(metric)}* by held-out condition:", "",
                  "| method | " + " | ".join(conds) + " |", "|---|" + "---|" * len(conds)]
        for m in e["conditions"][conds[0]]:
          lines.append(f"| {label(m)} | " + " | ".join(
              _mean(e["conditions"][c].get(m, {}).get(metric), _digits(metric)) for c in conds) + " |")
    lines += ["", f"### Broken down on {GROUP_TITLES[g]}", "",
              "Terciles of each attribute over this group's frames (object size: true object pixels as a share "
              "of the image; depth: their mean true depth; photons: the sequence's photon budget; motion: the "
              "dynamic object's speed over the input's three frames). Means per tercile; the intervals are in "
              "the JSON file and, for the differences, below."]
    lines += _breakdown_tables(e["breakdown"])
    gap_lines = _bin_gaps_table(e["breakdown"])
    if gap_lines:
      lines += ["", "Paired differences per tercile:", ""] + gap_lines
      for key in next(iter(e["breakdown"].values()))["gaps"]:
        for metric in ("intensity_mae_object", "f1"):
          better, worse = _called(e["breakdown"], key, metric)
          lines.append(f"- {_gap_label(key)}, {ereport.METRIC_LABELS[metric][0]}: called better in "
                       f"{', '.join(better) or 'no tercile'}; called worse in {', '.join(worse) or 'no tercile'}.")
    lines.append("")
  lines += _choices(choices)
  if invocations:
    lines += ["The records were written by " + "; ".join(
        f"`{r['args'] or '(no arguments)'}` on {r['date']} ({r['wall_s']:.0f} s)" for r in invocations)
        + " (an invocation reads the records that exist and writes the others).", ""]
  return "\n".join(lines) + "\n"


def _choices(choices: dict) -> list[str]:
  lines = ["## Chosen on the validation split", ""]
  classic = choices.get("classic", {})
  if classic:
    lines += ["| method | options | surface threshold | val. intensity PSNR (dB) | val. surface F1 |",
              "|---|---|---|---|---|"]
    for m, c in classic.items():
      opts = ", ".join(f"{k}={v}" for k, v in c["options"].items()) or "none"
      lines.append(f"| {label(m)} | {opts} | {c['threshold']} | {c['psnr']:.2f} | {c['f1']:.3f} |")
  for m, c in choices.get("models", {}).items():
    lines.append(f"\n{label(m)} (`{c['spec']}`): surface threshold {c['threshold']} (validation surface F1 "
                 f"{c['f1']:.3f}).")
  if "bound" in choices:
    b = choices["bound"]
    lines.append(f"\nThe bilinear reading's cut: {b['cut']} (validation surface F1 {b['f1']:.3f}; "
                 + ", ".join(f"{k}: {v:.3f}" for k, v in b["f1_by_cut"].items()) + ").")
  val = choices.get("validation_means", {})
  if val:
    lines += ["", "Validation means of the classic methods, from which each score's reference is chosen:", "",
              "| method | " + " | ".join(_head(k) for k in OBJECT_SCORES) + " |",
              "|---|" + "---|" * len(OBJECT_SCORES)]
    for m, r in val.items():
      lines.append(f"| {label(m)} | " + " | ".join(_mean({"mean": r[k]}, _digits(k)) for k in OBJECT_SCORES) + " |")
  return lines + [""]


# ---------------------------------------------------------------------- figure
def plot(summary: dict, path) -> None:
  """Object intensity error and surface F1 against object size (terciles), per group and method."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  gs = list(summary["groups"])
  metrics = ("intensity_mae_object", "f1")
  fig, axes = plt.subplots(len(metrics), len(gs), figsize=(4.2 * len(gs), 3.4 * len(metrics)), squeeze=False)
  grays = {"fbp": "0.75", "lct": "0.6", "fk": "0.85", "phasor": "0.45", "rsd": "0.3"}
  for c, g in enumerate(gs):
    split = summary["groups"][g]["breakdown"]["size"]
    x = [None if b is None else b["mean"] for b in split["bins"]]
    for r, metric in enumerate(metrics):
      ax = axes[r, c]
      for m, per_bin in split["methods"].items():
        y = [np.nan if s is None or s[metric]["mean"] is None else s[metric]["mean"] for s in per_bin]
        xs = [np.nan if v is None else 100 * v for v in x]
        if m in BOUNDS:
          kw = dict(color="k", ls="--" if m == "bound_bilinear" else ":", lw=1.8)
        elif m == ZERO:
          kw = dict(color="tab:red", ls="-.", lw=1.2)
        elif m in grays:
          kw = dict(color=grays[m], lw=1.2)
        else:
          kw = dict(lw=2.2, marker="o")
        ax.plot(xs, y, label=label(m), **kw)
      ax.set_xlabel("object size (% of the image, tercile mean)")
      ax.set_ylabel(ereport.METRIC_LABELS[metric][0] + (" ↓" if not HIGHER_IS_BETTER[metric] else " ↑"))
      if r == 0:
        ax.set_title(GROUP_TITLES[g].replace("`", ""), fontsize=9)
  axes[0, -1].legend(fontsize=7, loc="best")
  fig.tight_layout()
  fig.savefig(path, dpi=100)
  plt.close(fig)

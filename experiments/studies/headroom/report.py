"""The headroom report: objects tables, the breakdown by attribute, the gaps, and the figure, from the records.

Input is :func:`experiments.studies.headroom.study.load_records`'s dict. Sets are reported in
:data:`GROUPS` order; the held-out renderer's conditions are pooled into one group
(``heldout``, sequences kept apart by condition) and also listed condition by condition.
"""

from __future__ import annotations

import math

import numpy as np

from experiments.studies.headroom import breakdown
from experiments.studies.headroom.study import CLASSIC, INPUTS, OBJECT_SCORES, REFERENCE_SCORES, TRUTH, ZERO, oracle
from nlosjax import stats
from nlosjax.evaluation import report as ereport
from nlosjax.evaluation.scores import HIGHER_IS_BETTER, by_sequence, compare_scores
from nlosjax.variants import OURS, OURS_S

__all__ = ["GROUPS", "COLUMNS", "REFERENCE", "groups", "method_order", "label", "summarise", "to_markdown",
           "plot"]

#: Report order of the sets (``heldout``: every ``heldout-<condition>`` set pooled).
GROUPS = ("test", "independent", "heldout")
GROUP_TITLES = {"test": "the `cpu` preset's test split", "independent": "the independent set",
                "heldout": "the held-out renderer (conditions pooled)"}
#: The objects table's columns (the whole-image PSNR last, as the guard).
COLUMNS = REFERENCE_SCORES
#: The composite rows: per score, the reference classic method's score (that score's validation best) on
#: the input the networks read, and on each better input (:data:`~experiments.studies.headroom.study.INPUTS`).
REFERENCE = ("reference", *(f"reference@{src}" for src in INPUTS))
#: Scores of the whole-set differences.
GAP_SCORES = ("intensity_mae_object", "psnr_balanced", "recall", "f1")
#: Scores of the per-tercile differences.
BIN_GAP_SCORES = ("intensity_mae_object", "f1")
#: A tercile's difference is called only where its interval excludes 0 *and* it rests on at least this
#: many sequences (a bootstrap over one or two sequences gives an interval of no width).
MIN_CALL_SEQUENCES = 3
#: Offset between the sequence numbers of two pooled held-out conditions.
_CONDITION_STRIDE = 1000
_INPUT_WORDS = {"clean": "noise-free input", "full": "the full scan", "clean_full": "noise-free full scan"}


def label(method: str) -> str:
  """Display name of a method of the study."""
  fixed = {ZERO: "all-zero image", "truth_bilinear": "truth at the scan points, bilinear",
           "truth_nearest": "truth at the scan points, nearest", "reference": "reference classic method"}
  if method in fixed:
    return fixed[method]
  if method.startswith("reference@"):
    return f"reference classic, {_INPUT_WORDS[method.split('@', 1)[1]]}"
  if "@" in method:
    m, src = method.split("@", 1)
    return f"{ereport.label(m)}, {_INPUT_WORDS[src]}"
  return ereport.label(method)


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


def _with_reference(entry: dict, ref: dict) -> dict:
  """``entry`` with the composite :data:`REFERENCE` rows where every score's reference method was scored."""
  methods = dict(entry["methods"])
  for row in REFERENCE:
    src = row.split("@", 1)[1] if "@" in row else None
    names = {k: (m if src is None else oracle(m, src)) for k, m in ref.items() if k in COLUMNS}
    if len(names) == len(COLUMNS) and all(n in methods for n in names.values()):
      methods[row] = {"scores": {k: methods[n]["scores"][k] for k, n in names.items()}}
  return {**entry, "methods": methods}


def groups(records: dict) -> dict:
  """``group -> {"sequence", "attributes", "methods": method -> {"scores"}, "sets"}`` in :data:`GROUPS` order,
  with the composite reference rows."""
  sets = records["sets"]
  ref = records["choices"].get("reference", {})
  out = {}
  for g in GROUPS:
    if g == "heldout":
      entries = [(n, e) for n, e in sets.items() if n.startswith("heldout-")]
      if entries:
        out[g] = _with_reference(_pool(entries), ref)
    elif g in sets:
      out[g] = _with_reference({**sets[g], "sets": [g]}, ref)
  return out


def method_order(methods) -> list[str]:
  """The floor, the classic methods, the reference rows, the learned ones (the shipped first), the truth."""
  known = [ZERO, *CLASSIC, *REFERENCE, OURS_S, OURS]
  learned = [m for m in methods if m not in known and m not in TRUTH and "@" not in m]
  return [m for m in known if m in methods] + sorted(learned) + [b for b in TRUTH if b in methods]


def learned_methods(methods) -> list[str]:
  return [m for m in method_order(methods) if m not in (ZERO, *CLASSIC, *REFERENCE, *TRUTH)]


def _differences(methods) -> list[tuple[str, str]]:
  """``(a, b)`` pairs of the differences: each network − the reference; each better input's reference −
  the reference (what the input costs it); the reference on the full scan − each network (how far the
  network is from what the full capture gives the reference); the bilinear truth − each network."""
  pairs = [(m, "reference") for m in learned_methods(methods) if "reference" in methods]
  pairs += [(r, "reference") for r in REFERENCE[1:] if r in methods and "reference" in methods]
  pairs += [("reference@full", m) for m in learned_methods(methods) if "reference@full" in methods]
  pairs += [(TRUTH[0], m) for m in learned_methods(methods) if TRUTH[0] in methods]
  return pairs


def summarise(records: dict, n_boot: int | None = None) -> dict:
  """Every number of the report (JSON-ready): per group the table, the breakdown and the differences."""
  kw = {} if n_boot is None else {"n_boot": n_boot}
  ref = records["choices"].get("reference", {})
  out = {"reference": ref, "groups": {}}
  for g, e in groups(records).items():
    seq = e["sequence"]
    methods = method_order(e["methods"])
    pick = {m: {k: e["methods"][m]["scores"][k] for k in COLUMNS} for m in methods}
    table = {m: {k: stats.summarize(by_sequence(v, seq), **kw) for k, v in s.items()} for m, s in pick.items()}
    pairs = _differences(methods)
    gaps = {f"{a} - {b}": compare_scores({k: pick[a][k] for k in GAP_SCORES}, {k: pick[b][k] for k in GAP_SCORES},
                                         seq, **kw) for a, b in pairs}
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
      bin_gaps = {f"{a} - {b}": breakdown.bin_differences({k: pick[a][k] for k in BIN_GAP_SCORES},
                                                          {k: pick[b][k] for k in BIN_GAP_SCORES}, seq, which, **kw)
                  for a, b in pairs if b == "reference"}
      split[attr] = {"edges": [float(x) for x in edges], "bins": ranges, "methods": per_method, "gaps": bin_gaps}
    conditions = {}
    if g == "heldout":
      for n in e["sets"]:
        s = _with_reference(records["sets"][n], ref)
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
  return f"{label(a)} − {label(b)}"


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
      "—" if (r := split[a]["bins"][i]) is None else f"{r['n_sequences']} / {r['n_frames']}"
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


def _is_called(d: dict | None) -> bool:
  return (d is not None and math.isfinite(d["mean"]) and stats.excludes_zero(d)
          and d["n_sequences"] >= MIN_CALL_SEQUENCES)


def _bin_gaps_table(split: dict) -> list[str]:
  keys = list(next(iter(split.values()))["gaps"])
  if not keys:
    return []
  attrs = list(split)
  lines = ["| difference | " + " | ".join(f"{a} {i + 1}" for a in attrs for i in range(3)) + " |",
           "|---|" + "---|" * (3 * len(attrs))]
  for key in keys:
    for k in BIN_GAP_SCORES:
      cells = []
      for a in attrs:
        for d in split[a]["gaps"][key]:
          d = None if d is None else d[k]
          text = stats.format_interval(d, _digits(k), signed=True, missing="—")
          cells.append(f"**{text}**" if _is_called(d) else text)
      lines.append(f"| {_gap_label(key)}, {_head(k)} | " + " | ".join(cells) + " |")
  return lines


def _called(split: dict, key: str, metric: str) -> tuple[list[str], list[str]]:
  """The bins where ``key``'s difference on ``metric`` is called better / worse for its left side."""
  better, worse = [], []
  for a, s in split.items():
    for i in range(3):
      d = None if s["gaps"].get(key) is None or s["gaps"][key][i] is None else s["gaps"][key][i][metric]
      if not _is_called(d):
        continue
      (better if (d["mean"] > 0) == HIGHER_IS_BETTER[metric] else worse).append(f"{a} {i + 1}")
  return better, worse


def _truth_lines(table: dict) -> list[str]:
  """Which reading of the truth is the better on each score, and which methods do better than it."""
  if not all(b in table for b in TRUTH):
    return []
  out, above = [], []
  for k in ("intensity_mae_object", "psnr_balanced", "recall", "f1", "rmse_object"):
    a, b = (table[x][k]["mean"] for x in TRUTH)
    sign = 1 if HIGHER_IS_BETTER[k] else -1
    best = TRUTH[0] if sign * a >= sign * b else TRUTH[1]
    out.append(f"{ereport.METRIC_LABELS[k][0]}: {best.split('_')[1]} "
               f"({a:.{_digits(k)}f} bilinear, {b:.{_digits(k)}f} nearest)")
    level = table[best][k]["mean"]
    beat = [label(m) for m in table if m not in (ZERO, *TRUTH, *REFERENCE[1:]) and "@" not in m
            and sign * table[m][k]["mean"] > sign * level]
    above.append(f"{ereport.METRIC_LABELS[k][0]}: {', '.join(beat) if beat else 'none'}")
  return ["- Of the two readings of the truth at the scan points, the better on each score: " + "; ".join(out) + ".",
          "- Methods reading the 8 × 8 input that score better than that reading (means): " + "; ".join(above)
          + "."]


def to_markdown(summary: dict, header: list[str], choices: dict, *, stride: int, grid, invocations=()) -> str:
  """The report's Markdown (``header``: the provenance lines; ``invocations``: the runs that wrote the
  records, ``{"args", "wall_s", "date"}`` each)."""
  h = tuple(int(g) for g in grid)
  low = tuple(-(-(n - stride // 2) // stride) for n in h)
  ref = summary["reference"]
  lines = ["# Headroom: every method's object scores beside what the input supports", ""]
  lines += header + [""]
  lines += [
      f"Every method on the objects of each test set from the input's {low[0]} × {low[1]} scan points "
      f"(stride {stride} of the {h[0]} × {h[1]} grid), the all-zero image as the floor of every score, and "
      "two kinds of reference for what the input supports:",
      "",
      f"- **the truth at the scan points**: the true intensity and depth at the {low[0]} × {low[1]} points, "
      "read back to the full grid bilinearly as the classic methods read the sparse scan (depth as a "
      "normalised convolution of the object indicator, surface where it reaches the cut chosen on validation) "
      "or from the nearest scan point (`experiments/studies/headroom/bounds.py`). No strict bound: every scan "
      "point of a confocal capture sees the whole scene, so a reconstruction can place objects between the "
      "points;",
      "- **better inputs**: each score's *reference classic method* (the classic method with the best "
      "validation mean on that score) fed, with its settings and surface threshold chosen again on the "
      "validation split fed the same input, the noise-free transient at "
      f"the same {low[0]} × {low[1]} points (the file's stored clean transient: no Poisson noise, ambient light, "
      f"dark counts or jitter), the noisy capture at all {h[0]} × {h[1]} scan points the input is cut from, or "
      "both. What the reference gains there is what the input costs it.",
      "",
      "Every choice is made on the `cpu` preset's validation split, as the main job makes it: the classic "
      "methods' settings and surface thresholds, the learned models' surface thresholds, the bilinear reading's "
      "cut, and the reference classic method of each score (" + ", ".join(
          f"{ereport.METRIC_LABELS[k][0]}: {label(v)}" for k, v in ref.items())
      + "; the *reference classic* rows take each score from its reference). Means with 95 % bootstrap "
      "intervals over sequences; a difference is called where its interval excludes 0 (in a tercile, also "
      f"resting on at least {MIN_CALL_SEQUENCES} sequences; bold in the tercile tables).", ""]
  for g, e in summary["groups"].items():
    lines += [f"## Objects on {GROUP_TITLES[g]}", "",
              f"{e['n_sequences']} sequences, {e['n_frames']} frames"
              + (f" ({', '.join(s.split('-', 1)[1] for s in e['sets'])})." if g == "heldout" else "."), ""]
    lines += _objects_table(e["table"])
    if g == GROUPS[0]:
      lines += ["", "`headroom.png` draws the object intensity error and the surface F1 of the networks, the reference "
                "rows and the bilinear truth against the object-size terciles of every group."]
    lines += [""] + _truth_lines(e["table"])
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
              "of the image; depth: their mean true depth, m; photons: the sequence's photon budget per scan "
              "point and frame; motion: the dynamic object's speed over the input's three frames, m per frame). "
              "Means per tercile; every interval is in `headroom.json`, and those of the differences below."]
    lines += _breakdown_tables(e["breakdown"])
    gap_lines = _bin_gaps_table(e["breakdown"])
    if gap_lines:
      lines += ["", "Paired differences per tercile (bold: called):", ""] + gap_lines + [""]
      for key in next(iter(e["breakdown"].values()))["gaps"]:
        for metric in BIN_GAP_SCORES:
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
  for src, methods in choices.get("oracle", {}).items():
    for m, c in methods.items():
      opts = ", ".join(f"{k}={v}" for k, v in c["options"].items()) or "no options"
      lines.append(f"\n{label(m)} fed {_INPUT_WORDS[src]}: {opts}, surface threshold {c['threshold']} "
                   f"(validation intensity PSNR {c['psnr']:.2f} dB, surface F1 {c['f1']:.3f}).")
  val = choices.get("validation_means", {})
  if val:
    lines += ["", "Validation means of the classic methods, from which each score's reference is chosen:", "",
              "| method | " + " | ".join(_head(k) for k in REFERENCE_SCORES) + " |",
              "|---|" + "---|" * len(REFERENCE_SCORES)]
    for m, r in val.items():
      lines.append(f"| {label(m)} | " + " | ".join(_mean({"mean": r.get(k)}, _digits(k)) for k in REFERENCE_SCORES)
                   + " |")
  return lines + [""]


# ---------------------------------------------------------------------- figure
def plot(summary: dict, path) -> None:
  """Object intensity error and surface F1 against object size (terciles), per group: the networks, the
  reference classic method on its input and on the better inputs, the truth at the scan points, the floor."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  gs = list(summary["groups"])
  metrics = ("intensity_mae_object", "f1")
  fig, axes = plt.subplots(len(metrics), len(gs), figsize=(4.4 * len(gs), 3.5 * len(metrics)), squeeze=False)
  style = {"reference": dict(color="0.35", lw=2.0, marker="s"),
           "reference@clean": dict(color="tab:green", lw=1.4, ls="--"),
           "reference@full": dict(color="tab:purple", lw=1.4, ls="--"),
           "reference@clean_full": dict(color="tab:brown", lw=1.4, ls="--"),
           "truth_bilinear": dict(color="k", lw=1.8, ls=":"),
           OURS: dict(color="tab:blue", lw=2.4, marker="o"),
           OURS_S: dict(color="tab:orange", lw=2.0, marker="^")}
  for c, g in enumerate(gs):
    split = summary["groups"][g]["breakdown"]["size"]
    xs = [np.nan if b is None else 100 * b["mean"] for b in split["bins"]]
    for r, metric in enumerate(metrics):
      ax = axes[r, c]
      for m, per_bin in split["methods"].items():
        if m not in style and (m in (ZERO, *CLASSIC, *TRUTH) or "@" in m):
          continue
        y = [np.nan if s is None or s[metric]["mean"] is None else s[metric]["mean"] for s in per_bin]
        ax.plot(xs, y, label=label(m), **style.get(m, dict(lw=2.0, marker="d")))
      ax.set_xlabel("object size (% of the image; tercile means)")
      ax.set_ylabel(ereport.METRIC_LABELS[metric][0] + (" ↑" if HIGHER_IS_BETTER[metric] else " ↓"))
      ax.grid(alpha=0.3)
      if r == 0:
        ax.set_title(GROUP_TITLES[g].replace("`", ""), fontsize=9)
  axes[0, -1].legend(fontsize=7, loc="upper right")
  fig.suptitle("object intensity error (top, lower is better) and surface F1 (bottom) by object-size tercile; "
               "the all-zero image scores 0.42-0.54 and 0 (headroom.md)", fontsize=9)
  fig.tight_layout()
  fig.savefig(path, dpi=100)
  plt.close(fig)

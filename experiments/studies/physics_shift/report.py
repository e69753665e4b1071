"""The report of :mod:`experiments.studies.physics_shift`, rebuilt from its JSON records alone.

Per test set: each learned run's mean intensity PSNR and object recall with
95 % bootstrap intervals over sequences, the classic methods' (the best one
chosen on the tuning design's validation PSNR), and the paired differences
Ours - best classic and Ours - Ours-S.
"""

from __future__ import annotations

import json
import pathlib

import numpy as np

from experiments.studies.physics_shift import heldout, study
from nlosjax import stats
from nlosjax.variants import OURS, OURS_S

#: The goal margin over the best classic method on a held-out family or condition (dB).
GOAL_MARGIN_DB = 1.0
LABELS = {"base": "base (transport renderer only)", "mix": "mix (every family)",
          "wide": "wide (every family, wider scenes)",
          "wide_base": "wide_base (transport renderer only, wider scenes)",
          **{f"no_{f}": f"without {f}" for f in study.FAMILIES}}


def load(results) -> tuple[dict, dict]:
  """``(runs, classic)``: ``(design, variant) -> record`` and ``(design, set) -> record``."""
  folder = pathlib.Path(results) / "physics_shift"
  runs, classic = {}, {}
  for path in sorted(folder.glob("*.json")):
    r = json.loads(path.read_text())
    if path.name.startswith("classic-"):
      classic[(r["design"], r["set"])] = r
    elif path.name.startswith("tuning-"):
      continue
    else:
      runs[(r["design"], r["variant"])] = r
  return runs, classic


def _arr(values) -> np.ndarray:
  return np.asarray([np.nan if v is None else v for v in values], np.float64)


def _cell(s, digits=2, signed=False) -> str:
  return "(not run)" if s is None else stats.format_interval(s, digits, signed)


def _scores(record_set: dict, metric: str):
  return _arr(record_set["scores"][metric]), np.asarray(record_set["sequence"])


def compare(runs: dict, classic: dict, name: str, design: str) -> dict | None:
  """Ours and Ours-S of ``design`` on set ``name`` against the best classic method there."""
  from nlosjax.evaluation import scores
  c = classic.get((study.classic_design(name), name))
  ours = runs.get((design, OURS), {}).get("sets", {}).get(name)
  if c is None or ours is None:
    return None
  seq = np.asarray(c["sequence"])
  best = c["best"]

  def by(v):
    return scores.by_sequence(v, seq)

  out = {"best": best, "classic": {}, "learned": {}, "diff": {}}
  learned = [r for v in study.VARIANTS if (r := runs.get((design, v), {}).get("sets", {}).get(name))]
  # The object intensity error where every record has it (records written before it lack it).
  obj = "intensity_mae_object"
  metrics = ("psnr", "recall") + ((obj,) if all(obj in s for s in c["methods"].values())
                                  and all(obj in r["scores"] for r in learned) else ())
  for m, s in c["methods"].items():
    out["classic"][m] = {k: stats.summarize(by(_arr(s[k]))) for k in metrics}
  for variant in study.VARIANTS:
    r = runs.get((design, variant), {}).get("sets", {}).get(name)
    if r is None:
      continue
    if not np.array_equal(np.asarray(r["sequence"]), seq):
      raise ValueError(f"{design}-{variant} and the classic methods read {name} in different orders")
    out["learned"][variant] = {k: stats.summarize(by(_arr(r["scores"][k]))) for k in metrics}
    out["diff"][variant] = {k: stats.paired_difference(by(_arr(r["scores"][k])), by(_arr(c["methods"][best][k])))
                            for k in metrics}
  if OURS_S in out["learned"]:
    a, b = (_arr(runs[(design, v)]["sets"][name]["scores"]["psnr"]) for v in (OURS, OURS_S))
    out["ours_vs_ours_s"] = stats.paired_difference(by(a), by(b))
  return out


def choice(runs: dict, variant: str, name: str, design: str, against: str = "base") -> dict | None:
  """``design`` minus ``against`` (``variant``) on validation split ``name``: means and the paired difference."""
  from nlosjax.evaluation import scores
  a = runs.get((design, variant), {}).get("sets", {}).get(name)
  b = runs.get((against, variant), {}).get("sets", {}).get(name)
  if a is None or b is None:
    return None
  seq = np.asarray(a["sequence"])
  if not np.array_equal(seq, np.asarray(b["sequence"])):
    raise ValueError(f"{design}-{variant} and {against}-{variant} read {name} in different orders")
  pa, pb = (scores.by_sequence(_arr(r["scores"]["psnr"]), seq) for r in (a, b))
  return {"a": stats.summarize(pa), "b": stats.summarize(pb), "diff": stats.paired_difference(pa, pb)}


def _mean(runs: dict, design: str, variant: str, name: str) -> dict | None:
  """Mean intensity PSNR of a run on set ``name`` with its interval over sequences (None: not scored)."""
  from nlosjax.evaluation import scores
  r = runs.get((design, variant), {}).get("sets", {}).get(name)
  if r is None:
    return None
  return stats.summarize(scores.by_sequence(_arr(r["scores"]["psnr"]), np.asarray(r["sequence"])))


def _goal(c: dict) -> str:
  d = c["diff"].get(OURS)
  if d is None:
    return "—"
  psnr_ok = d["psnr"]["mean"] >= GOAL_MARGIN_DB
  recall_ok = d["recall"]["mean"] >= 0 if np.isfinite(d["recall"]["mean"]) else True
  s_ok = c.get("ours_vs_ours_s", {"mean": 0.0})["mean"] >= 0
  return "met" if psnr_ok and recall_ok and s_ok else "missed"


def _row(label: str, c: dict | None) -> str:
  if c is None:
    return f"| {label} | " + " | ".join(["(not run)"] * 7) + " |"
  lo, diff = c["learned"], c["diff"].get(OURS, {})
  best = c["best"]
  return (f"| {label} | {_cell(lo.get(OURS, {}).get('psnr'))} | {_cell(lo.get(OURS_S, {}).get('psnr'))} | "
          f"{best} {_cell(c['classic'][best]['psnr'])} | "
          f"{_cell(diff.get('psnr'), signed=True)} | "
          f"{_cell(diff.get('recall'), 3, signed=True)} | "
          f"{_cell(c.get('ours_vs_ours_s'), signed=True)} | {_goal(c)} |")


HEADER = ("| {what} | Ours PSNR (dB) | Ours-S PSNR (dB) | best classic PSNR (dB) | Ours − best classic (dB) "
          "| Ours − best classic, object recall | Ours − Ours-S (dB) | goal |")


def to_markdown(runs: dict, classic: dict, header: list[str], conditions) -> str:
  """The report (module docstring)."""
  lines = ["# Physics shift: learned models on forward models they were not trained on", ""]
  lines += header + [""]
  lines += [
      "Designs: **base** = trained on the preset's scenes rendered by the transport renderer alone (the "
      "data the preset's shipped weights were trained on, when it has no physics mix); **mix** = trained on "
      "sequences whose forward model is drawn per sequence from every family of "
      "`nlosjax.data.dataset.physics.PhysicsMix` (light-cone operator, transport with visibility and "
      "cosines, point scatterers; falloff, impulse response, background, gain and time-zero offset "
      "randomised); **wide** = the mix with wider scenes (`experiments.studies.physics_shift.study.wide_scene`); "
      "**without F** = the same mix without family F. Every learned run trains to the "
      "validation plateau of `experiments.studies.mechanisms` and picks its checkpoint and surface threshold on "
      "its own training data's validation split. The classic methods' settings, and which of them is "
      "best, are chosen on the validation split of the design that left the set's family out (held-out "
      "families) or of the mix (held-out renderer). Nothing is chosen on a test set. Intervals: 95 % "
      "bootstrap over sequences; differences are paired by frame.", "",
      f"Goal on every held-out family: Ours ≥ best classic + {GOAL_MARGIN_DB:g} dB intensity PSNR, object "
      "recall at least the best classic method's, and Ours ≥ Ours-S (each by its mean; the intervals say "
      "whether a difference is called).", ""]
  lines += ["## The choice, on validation", "",
            "Intensity PSNR of the candidates (" + ", ".join(f"**{d}** = {LABELS[d]}" for d in study.CANDIDATES)
            + ") on the validation split of each candidate's data, and the paired differences to base. "
            "The preset adopts the candidate ahead on the other candidates' validation splits "
            "(intervals above 0) without falling behind on base's.", "",
            "| variant | validation split | " + " | ".join(f"{d} (dB)" for d in study.CANDIDATES) + " | "
            + " | ".join(f"{d} − base (dB)" for d in study.CANDIDATES[1:]) + " |",
            "|---|---|" + "---|" * (2 * len(study.CANDIDATES) - 1)]
  for variant in study.VARIANTS:
    for name in (f"val:{d}" for d in study.CANDIDATES):
      means = [_cell(_mean(runs, d, variant, name)) for d in study.CANDIDATES]
      diffs = [choice(runs, variant, name, d) for d in study.CANDIDATES[1:]]
      lines.append(f"| {variant} | {name} | " + " | ".join(means) + " | "
                   + " | ".join(_cell(c["diff"], signed=True) if c else "(not run)" for c in diffs) + " |")
  lines += [""]
  lines += ["## Held-out families: trained without the family, tested on it", "",
            HEADER.format(what="left-out family"), "|---|---|---|---|---|---|---|---|"]
  for f in study.FAMILIES:
    lines.append(_row(f, compare(runs, classic, f"family:{f}", f"no_{f}")))
  lines += ["", "The same sets, the candidates (base, mix, wide) trained on every family they draw from:", "",
            HEADER.format(what="family (design)"), "|---|---|---|---|---|---|---|---|"]
  for f in study.FAMILIES:
    for design in study.CANDIDATES:
      lines.append(_row(f"{f} ({LABELS[design]})", compare(runs, classic, f"family:{f}", design)))
  lines += ["", "## Held-out renderer (`experiments/studies/physics_shift/heldout.py`, never trained on)", "",
            "Conditions (changes from objects at 0.5–1.5 m, 0.25–0.6 m across, no cosines, r⁻⁴, the "
            "preset's photon and ambient ranges): " + "; ".join(
                f"`{k}` {json.dumps(v) if v else '(none)'}" for k, v in heldout.CONDITIONS.items()
                if k in conditions) + ".", "",
            HEADER.format(what="condition (design)"), "|---|---|---|---|---|---|---|---|"]
  for cond in conditions:
    for design in study.CANDIDATES:
      lines.append(_row(f"{cond} ({LABELS[design]})", compare(runs, classic, f"heldout:{cond}", design)))
  lines += _wider_scenes(runs, classic, conditions)
  lines += ["", "## Runs", "", "| design | variant | steps (stop, best step) | best validation PSNR (dB) | "
            "train data | wall (s) | machine, commit |", "|---|---|---|---|---|---|---|"]
  for (design, variant), r in sorted(runs.items()):
    steps = (f"{r['steps_taken']} ({r['stop_reason']}, best {r['best_step']})" if "steps_taken" in r
             else r.get("source", "—"))
    val = f"{r['best_val_psnr']:.2f}" if r.get("best_val_psnr") is not None else "—"
    m = r.get("machine", {})
    lines.append(f"| {design} | {variant} | {steps} | {val} | `{r.get('data', '?')}` | {r.get('wall_s', '—')} | "
                 f"{m.get('cpu', '?')}, {m.get('commit', '?')} |")
  missing = [f"{d}-{v}" for d in study.DESIGNS for v in study.VARIANTS if (d, v) not in runs]
  lines += ["", "Runs still missing: " + (", ".join(missing) if missing else "none") + "."]
  return "\n".join(lines) + "\n"


#: The designs of the wider-scenes section: the preset's data and the same renderer with wider scenes.
WIDER = ("base", "wide_base")


def _wider_scenes(runs: dict, classic: dict, conditions) -> list[str]:
  """Whether wider training scenes buy larger and farther objects, and what they cost (``wide_base``)."""
  lines = ["", "## Wider training scenes: the preset's renderer, objects up to 1 m at up to 2 m", "",
           f"**wide_base** = {LABELS['wide_base']}: base's data with `wide_scene`'s ranges (objects "
           "0.15–1.0 m across instead of 0.25–0.6 m, 0.4–2.0 m away instead of 0.5–1.5 m, anchored "
           "within 0.7 m of the wall's centre instead of 0.5 m), so only the scene ranges differ from "
           "base. On validation, its intensity PSNR against base's (paired by frame):", "",
           "| variant | validation split | base (dB) | wide_base (dB) | wide_base − base (dB) |",
           "|---|---|---|---|---|"]
  for variant in study.VARIANTS:
    for name in (f"val:{d}" for d in study.CANDIDATES):
      c = choice(runs, variant, name, "wide_base")
      lines.append(f"| {variant} | {name} | " + (" | ".join(
          [_cell(c["b"]), _cell(c["a"]), _cell(c["diff"], signed=True)]) if c else "(not run) | " * 2
          + "(not run)") + " |")
  lines += ["", "On the held-out renderer: Ours of each design against the best classic method, in intensity "
            "PSNR and in object intensity error (mean absolute intensity error over the true object pixels, "
            "lower is better; `intensity_mae_object`; not scored in records written before it existed). "
            "`large` holds objects 0.6–1.0 m across, `far` objects at 0.9–1.8 m.", "",
            "| condition | design | Ours PSNR (dB) | Ours − best classic (dB) | Ours object error | "
            "best classic object error | Ours − best classic, object error | Ours − Ours-S (dB) |",
            "|---|---|---|---|---|---|---|---|"]
  for cond in conditions:
    for design in WIDER:
      c = compare(runs, classic, f"heldout:{cond}", design)
      if c is None or OURS not in c["learned"]:
        lines.append(f"| {cond} | {design} | " + " | ".join(["(not run)"] * 6) + " |")
        continue
      best, obj = c["best"], "intensity_mae_object"
      scored = obj in c["learned"][OURS]          # records written before it was scored lack it
      ours, diff = c["learned"][OURS], c["diff"][OURS]
      lines.append(f"| {cond} | {design} | {_cell(ours['psnr'])} | "
                   f"{_cell(diff['psnr'], signed=True)} | "
                   + (f"{_cell(ours[obj], 3)} | {best} {_cell(c['classic'][best][obj], 3)} | "
                      f"{_cell(diff[obj], 3, signed=True)} | " if scored else "not scored | " * 3)
                   + f"{_cell(c.get('ours_vs_ours_s'), signed=True)} |")
  return lines


def plot(runs: dict, classic: dict, conditions, path: pathlib.Path) -> None:
  """Ours − best classic (dB, 95 % interval) on every set, one bar per design."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  items = [(f"family:{f}", f"{f}\n(held out)", f"no_{f}") for f in study.FAMILIES]
  items += [(f"heldout:{c}", c, None) for c in conditions]
  designs = study.CANDIDATES
  fig, ax = plt.subplots(figsize=(1.1 * len(items) + 2, 3.6))
  width = 0.2
  for k, design in enumerate(designs + ("held-out design",)):
    xs, ys, lo, hi = [], [], [], []
    for i, (name, _, own) in enumerate(items):
      d = own if design == "held-out design" else design
      if d is None:
        continue
      c = compare(runs, classic, name, d)
      if c is None or OURS not in c["diff"]:
        continue
      s = c["diff"][OURS]["psnr"]
      xs.append(i + (k - 1.5) * width)
      ys.append(s["mean"])
      lo.append(s["mean"] - s["ci95"][0])
      hi.append(s["ci95"][1] - s["mean"])
    if xs:
      ax.bar(xs, ys, width, yerr=[lo, hi], capsize=2,
             label={"base": "base", "mix": "mix", "wide": "wide",
                    "held-out design": "trained without the family"}[design])
  ax.axhline(0, color="k", lw=0.8)
  ax.axhline(GOAL_MARGIN_DB, color="g", lw=0.8, ls="--", label=f"goal +{GOAL_MARGIN_DB:g} dB")
  ax.set_xticks(range(len(items)), [lab for _, lab, _ in items], fontsize=8)
  ax.set_ylabel("Ours − best classic (dB)")
  ax.legend(fontsize=8)
  fig.tight_layout()
  fig.savefig(path, dpi=90)
  plt.close(fig)

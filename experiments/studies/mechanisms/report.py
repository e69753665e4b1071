"""The report (``mechanisms.md``) and its figure, rebuilt from the run records alone."""

from __future__ import annotations

import json
import pathlib

import numpy as np

from experiments.studies.mechanisms.design import (
  COLUMNS,
  FIGURE,
  PAIRS,
  PROBE,
  REPORT,
  ROWS,
  STUDY_STOP,
  VERDICTS,
  check_consistent,
)
from experiments.studies.mechanisms.records import _array, load_runs
from experiments.studies.mechanisms.untrained import load_untrained, untrained_lines
from nlosjax import stats
from nlosjax.stats import format_interval as cell


def stack_scores(runs: list[dict], metric: str) -> np.ndarray:
  """``[K, N]`` test scores of ``metric`` over a row's runs (seeds)."""
  return np.stack([_array(r["test"]["scores"][metric]) for r in runs])


def same_frames(runs: list[dict]) -> bool:
  """Whether every run was scored on the same test sequences and frames, in the same order."""
  ref = runs[0]["test"]
  return all(r["test"]["sequence"] == ref["sequence"] and r["test"]["frame"] == ref["frame"] for r in runs)


def summarise(runs: dict, budgets, rows) -> dict:
  """Per budget: each row's summaries over its seeds, and the paired differences of :data:`PAIRS`.

  ``runs``: :func:`load_runs`. Differences use the seeds present in both rows,
  each seed of ``a`` paired with the same seed of ``b`` on the same frames.
  Returns ``budget -> {"rows": row -> {"seeds", metric -> summary}, "pairs":
  [{"a", "b", "seeds", "diff": metric -> summary}]}``.
  """
  from nlosjax.evaluation import scores
  out = {}
  for budget in budgets:
    by_row = {row: [runs[k] for k in sorted(runs) if k[0] == budget and k[1] == row] for row in rows}
    by_row = {row: rs for row, rs in by_row.items() if rs}
    present = [r for rs in by_row.values() for r in rs]
    if present and not same_frames(present):
      raise ValueError(f"budget {budget}: the runs were scored on different test frames")
    entry = {"rows": {}, "pairs": []}
    for row, rs in by_row.items():
      seq = rs[0]["test"]["sequence"]
      summary = scores.summarize_scores({m: stack_scores(rs, m) for m in COLUMNS}, seq)
      entry["rows"][row] = {"seeds": [r["seed"] for r in rs], **summary}
    for a, b in PAIRS:
      if a not in rows or b not in rows:
        continue
      ra = {r["seed"]: r for r in by_row.get(a, [])}
      rb = {r["seed"]: r for r in by_row.get(b, [])}
      common = sorted(set(ra) & set(rb))
      pair = {"a": a, "b": b, "seeds": common, "diff": None}
      if common:
        seq = ra[common[0]]["test"]["sequence"]
        pair["diff"] = scores.compare_scores({m: stack_scores([ra[s] for s in common], m) for m in COLUMNS},
                                             {m: stack_scores([rb[s] for s in common], m) for m in COLUMNS}, seq)
      entry["pairs"].append(pair)
    out[budget] = entry
  return out


def _budget_text(runs: dict, budget: str) -> str:
  r = next((r for k, r in sorted(runs.items()) if k[0] == budget), None)
  if r is None:
    return f"`{budget}`"
  d = r["config"]["data"]
  loss = (r["config"].get("train") or {}).get("loss")
  recipe = f"; loss weights over the paper's: {json.dumps(loss, sort_keys=True)}" if loss else ""
  return (f"`{budget}` (signal photons {tuple(d.get('photons', ()))}, ambient {tuple(d.get('ambient', ()))}"
          f" per scan point; `{d.get('path')}`{recipe})")


def _verdict(pair: dict, budget: str, n_seeds: int, metric: str = "psnr") -> str:
  """The plain sentence of one paired difference in ``metric`` (a key of :data:`VERDICTS`)."""
  a, b = pair["a"], pair["b"]
  name = f"full - {b}" if a == "full" else f"{a} - {b}"
  what, unit = VERDICTS[metric]
  if not pair["seeds"]:
    return (f"- **{name}** (`{budget}`, {what}): not computed yet: no seed has finished in both rows.")
  d = pair["diff"][metric]
  seeds = ", ".join(str(s) for s in pair["seeds"])
  text = (f"- **{name}** (`{budget}`, seeds {seeds}, {what}): {d['mean']:+.2f} {unit} "
          f"[{d['ci95'][0]:+.2f}, {d['ci95'][1]:+.2f}]. ")
  if d["n_sequences"] < 2:
    text += (f"Not called: {d['n_sequences']} test sequence(s) give no interval to judge by (the"
             " bootstrap resamples whole sequences).")
  elif stats.excludes_zero(d):
    better = ROWS[a][2] if d["mean"] > 0 else ROWS[b][2]
    text += f"Called: the interval excludes 0, {better} is better."
  else:
    text += "Not called: the interval includes 0, so this study cannot tell the two rows apart."
  if len(pair["seeds"]) < n_seeds:
    text += f" (Only {len(pair['seeds'])} of {n_seeds} seeds so far.)"
  return text


def barely_trained(records: list[dict]) -> list[dict]:
  """The runs whose best validation came at their first validation (learning never went past it)."""
  return [r for r in records if r["validation_curve"]
          and r["best_step"] == r["validation_curve"][0]["step"]]


def empty_output(records: list[dict]) -> list[dict]:
  """The runs whose best model reconstructs no object pixel on any test frame (object recall 0).

  Such a model outputs an empty image whatever its input (a collapse, not a plateau: its
  validation curve sits at the empty image's score), so a difference against it measures
  whether training collapsed, not what a mechanism adds.
  """
  out = []
  for r in records:
    recall = _array(r["test"]["scores"].get("recall", []))
    if np.isfinite(recall).any() and np.nanmax(recall) == 0.0:
      out.append(r)
  return out


def _steps_text(rs: list[dict]) -> str:
  return ", ".join(f"{r['steps_taken']} ({r['stop_reason']}, best {r['best_step']})" for r in rs)


def _probe_lines(runs: dict, budget: str) -> list[str]:
  r = runs.get((budget, *PROBE))
  if r is None or "probe" not in r:
    return []
  p = r["probe"]
  lines = ["", f"### SSM probe, `{budget}` budget: {ROWS[PROBE[0]][2]}, seed {PROBE[1]}", "",
           f"Validation split ({p['n_frames']} frames), the run's best model; each SSM's output replaced"
           " by its input at inference (no retraining). Drop = intact - bypassed (positive: the"
           " model needs it). Mean gate: mean of SiLU(z), the gate branch of the SSM's block, over"
           " every position, channel and validation input.", "",
           "| module | PSNR when bypassed (dB) | drop vs intact (dB) | mean gate of its block |",
           "|---|---|---|---|",
           f"| none (intact) | {p['intact_psnr']:.3f} | 0 | — |"]
  for m in p["modules"]:
    gate = "—" if m["gate_mean"] is None else f"{m['gate_mean']:.4f}"
    lines.append(f"| `{m['module']}` | {m['psnr']:.3f} | {m['drop_db']:+.3f} | {gate} |")
  lines.append(f"| every SSM | {p['all_bypassed_psnr']:.3f} | {p['all_drop_db']:+.3f} | — |")
  mixing = p.get("mixing") or {}
  if mixing:
    parts = []
    if "skip_gain" in mixing:
      parts.append(f"skip gain {mixing['skip_gain']:.3f}")
    if "skip_frame_weights" in mixing:
      parts.append("skip-frame weights (previous, middle, next) "
                   + ", ".join(f"{w:.3f}" for w in mixing["skip_frame_weights"]))
    lines += ["", "Learned mixing weights: " + "; ".join(parts) + "."]
  best = r.get("best_val_psnr")
  if best is not None and abs(best - p["intact_psnr"]) > 1e-9:
    lines += ["", f"Note: the intact PSNR differs from the run's best validation PSNR ({best:.3f} dB)."]
  return lines


def plot_curves(runs: dict, budgets, rows, path: pathlib.Path) -> None:
  """Validation PSNR against step, one panel per budget, one colour per row, one line per seed."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(1, len(budgets), figsize=(5.0 * len(budgets), 3.6), squeeze=False)
  colours = {row: f"C{i}" for i, row in enumerate(ROWS)}
  for ax, budget in zip(axes[0], budgets):
    for row in rows:
      for (b, r, seed), rec in sorted(runs.items()):
        if b != budget or r != row or not rec["validation_curve"]:
          continue
        steps = [p["step"] for p in rec["validation_curve"]]
        vals = [np.nan if p["val_psnr"] is None else p["val_psnr"] for p in rec["validation_curve"]]
        ax.plot(steps, vals, color=colours[row], alpha=0.8, lw=1.2,
                ls=("-", "--", ":")[seed % 3], label=f"{row} seed {seed}")
        if rec["best_step"] in steps:
          ax.plot([rec["best_step"]], [vals[steps.index(rec["best_step"])]], "o", color=colours[row], ms=4)
    ax.set_title(f"budget {budget}")
    ax.set_xlabel("step")
    ax.set_ylabel("validation intensity PSNR (dB)")
    ax.grid(alpha=0.3)
    if ax.lines:
      ax.legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def report(runs: dict, design: dict, command: str, untrained: dict | None = None) -> str:
  """The Markdown report of the runs present, against the ``design`` (budgets, rows, seeds).

  ``untrained``: ``budget -> record`` of :mod:`experiments.studies.mechanisms.untrained` (a section per budget).
  """
  untrained = untrained or {}
  from experiments.provenance import provenance
  budgets, seeds = list(design["budgets"]), list(design["seeds"])
  rows = list(design["rows"]) + [r for r in ROWS if r not in design["rows"] and any(k[1] == r for k in runs)]
  expected = [(b, r, s) for b in budgets for r in rows for s in seeds]
  missing = [k for k in expected if k not in runs]
  summary = summarise(runs, budgets, rows)
  stops = sorted({json.dumps(r["config"]["train"]["stop"], sort_keys=True) for r in runs.values()})
  machines = {}
  for r in runs.values():
    m = r["machine"]
    key = f"{m['cpu']}, {m['cores']} cores, commit {m['commit']}" + (
        f", code `{m['code_digest']}`" if m.get("code_digest") else "")   # older records carry a digest
    machines[key] = machines.get(key, 0) + 1
  lines = ["# Mechanisms: SSMs and neighbour frames, each model trained to its validation plateau", ""]
  lines += provenance(command) + [""]
  lines += [f"Rows: {', '.join(f'`{r}` ({ROWS[r][2]})' for r in rows)}; seeds {', '.join(map(str, seeds))};"
            " photon budgets " + "; ".join(_budget_text(runs, b) for b in budgets) + ".",
            "",
            "Every run trains until learning stops (`nlosjax.train.stopping`, plateau rule: "
            + ("; ".join(f"`{s}`" for s in stops) if stops else f"`{json.dumps(STUDY_STOP)}`")
            + "): the validation intensity PSNR is measured every `every` steps; the run stops when"
            " the best of the last `patience` validations is not more than `min_delta_db` above the"
            " best before them, or at `max_steps` (the cosine schedule's horizon); the best model on"
            " validation is kept, its surface threshold chosen on validation. Test split: mean"
            " [95 % bootstrap interval over sequences and seeds]; differences are paired seed by seed"
            " on the same frames, over the seeds present in both rows; a difference is called when its"
            " interval excludes 0. Every number below is read from the JSON files in"
            " `mechanisms/<budget>/<row>-seed<k>.json` (the per-frame scores, curves and each run's"
            " machine and commit).", ""]
  lines += ["Runs by machine and commit: " + ("; ".join(f"{k} ({n} run(s))" for k, n in machines.items())
                                           if machines else "none yet") + ".", ""]
  if missing:
    lines += [f"**Missing runs ({len(missing)} of {len(expected)})**: "
              + ", ".join(f"{b}/{r}-seed{s}" for b, r, s in missing)
              + ". The tables below cover only the runs present.", ""]
  else:
    lines += [f"All {len(expected)} runs of the design are present.", ""]
  for budget in budgets:
    entry = summary[budget]
    lines += [f"## Budget {_budget_text(runs, budget)}", ""]
    if not entry["rows"]:
      lines += ["No run of this budget has finished yet.", ""]
      continue
    lines += ["| row | seeds | " + " | ".join(h for h, _ in COLUMNS.values())
              + " | steps taken (stop, best step) per seed |",
              "|---|---|" + "---|" * len(COLUMNS) + "---|"]
    for row in rows:
      if row not in entry["rows"]:
        lines.append(f"| {row} | none yet |" + " — |" * len(COLUMNS) + " — |")
        continue
      s = entry["rows"][row]
      rs = [runs[(budget, row, k)] for k in s["seeds"]]
      lines.append(f"| {row} | {', '.join(map(str, s['seeds']))} | "
                   + " | ".join(cell(s[m], d) for m, (_, d) in COLUMNS.items())
                   + f" | {_steps_text(rs)} |")
    pairs = [p for p in entry["pairs"] if p["a"] in rows and p["b"] in rows
             and (p["b"] in design["rows"] or p["seeds"])]
    if pairs:
      lines += ["", "Paired differences (a - b; the same frames and seeds):", "",
                "| difference | seeds | " + " | ".join(h for h, _ in COLUMNS.values()) + " |",
                "|---|---|" + "---|" * len(COLUMNS)]
      for p in pairs:
        cells = (" | ".join(cell(p["diff"][m], d, True) for m, (_, d) in COLUMNS.items())
                 if p["diff"] else " | ".join("—" for _ in COLUMNS))
        lines.append(f"| {p['a']} - {p['b']} | {', '.join(map(str, p['seeds'])) or 'none'} | {cells} |")
      lines += [""] + [_verdict(p, budget, len(seeds), m) for p in pairs for m in VERDICTS]
    early = barely_trained([r for k, r in sorted(runs.items()) if k[0] == budget and k[1] in rows])
    if early:
      names = ", ".join(f"{r['row']}-seed{r['seed']}" for r in early)
      lines += ["", f"**Barely trained**: {names} validated best at their first validation (step"
                f" {early[0]['validation_curve'][0]['step']}) and never improved after it; their"
                " scores are those of a model that has hardly started to learn, and a difference"
                " involving them says little about the mechanism."]
    budget_runs = {k: r for k, r in runs.items() if k[0] == budget and k[1] in rows}
    empty = empty_output([r for _, r in sorted(budget_runs.items())])
    if empty:
      names = ", ".join(f"{r['row']}-seed{r['seed']}" for r in empty)
      lines += ["", f"**Empty output**: {names} reconstruct no object pixel on any test frame (object"
                " recall 0): training collapsed to an empty image, whose validation score the plateau"
                " rule then saw as a plateau. Every row's seeds are kept in the tables above."]
      collapsed = {(r["budget"], r["row"], int(r["seed"])) for r in empty}
      learned = {k: r for k, r in budget_runs.items() if k not in collapsed}
      sub = [p for p in summarise(learned, [budget], rows)[budget]["pairs"]
             if p["diff"] and any(r["row"] in (p["a"], p["b"]) for r in empty)]
      if sub:
        lines += ["", "The same differences over the seeds where neither run collapsed (a reading of"
                  " how the mechanism compares when both models learned, on fewer seeds):", "",
                  "| difference | seeds | " + " | ".join(h for h, _ in COLUMNS.values()) + " |",
                  "|---|---|" + "---|" * len(COLUMNS)]
        for p in sub:
          lines.append(f"| {p['a']} - {p['b']} | {', '.join(map(str, p['seeds']))} | "
                       + " | ".join(cell(p["diff"][m], d, True) for m, (_, d) in COLUMNS.items()) + " |")
    if budget in untrained:
      learned = {row: [r for k, r in sorted(runs.items()) if k[0] == budget and k[1] == row] for row in rows}
      lines += [""] + untrained_lines(untrained[budget], learned, budget)
    lines += _probe_lines(runs, budget)
    lines.append("")
  lines += [f"Validation curves: `{FIGURE}` (one panel per budget; a dot marks each run's best step).", ""]
  return "\n".join(lines)


def write_report(results: pathlib.Path, design: dict, command: str) -> str:
  """Rewrite ``RESULTS/mechanisms.md`` and ``RESULTS/mechanisms_curves.png`` from the JSON files alone."""
  results = pathlib.Path(results)
  runs = load_runs(results)
  check_consistent(runs)
  text = report(runs, design, command, load_untrained(results))
  results.mkdir(parents=True, exist_ok=True)
  (results / REPORT).write_text(text)
  rows = list(design["rows"]) + [r for r in ROWS if r not in design["rows"] and any(k[1] == r for k in runs)]
  plot_curves(runs, list(design["budgets"]), rows, results / FIGURE)
  return text

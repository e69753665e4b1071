"""The paper's Table 2 ablations at the CPU preset, with one shared training budget.

    python -m experiments.studies.ablations [--config cpu] [--steps 150] [--seeds 3] [--workdir runs/ablations]
                                   [--only full no_pf ...] [--out experiments/studies/ablations/results/table2.md]
                                   [--config.section.key=value ...]

Every row trains Ours (three frames, the main job's model and data) for the
same ``--steps`` from the same ``--seeds`` training seeds (the config's seed,
+1, ...), changing one thing, then scores the validation split (for the
weight-decay choice) and the test split (the table: mean and 95 % interval
over sequences and seeds, and each row's paired difference with the full
model, seed by seed on the same frames):

* loss items (paper Table 2, top): without the phasor-field loss ``L_pf``,
  without the regularisers ``L_ls``/``L_tv`` (``gamma = 0``), without both;
* Mamba mechanism (paper Table 2, bottom): every block temporal-then-spatial
  (``st``, the paper), temporal twice (``tt``), temporal only (``t``), spatial
  twice (``ss``), spatial only (``s``);
* optimiser: AdamW weight decay 0.95 (printed in the paper) against 1e-4
  (its predecessor USM's, our default);
* controls: ``no_ssm`` (every SSM replaced by the identity, all else equal:
  what the Mamba machinery adds over a gated MLP in the same place) and
  ``bidirectional`` (the temporal SSM runs both ways: the causality row of
  the paper's Table 3).

Each run lives in ``WORKDIR/<row>/`` (the config's seed) or
``WORKDIR/<row>-seed<k>/`` (resumable: a rerun reuses finished runs). Writes the Markdown
table to ``--out`` and the numbers to the same
path with ``.json``.
"""

from __future__ import annotations

import argparse
import copy
import json
import pathlib
import sys
import time

from nlosjax.stats import format_interval as cell
from nlosjax.variants import OURS

#: This study's results folder: its reports, figures and JSON records.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"

#: row -> (spatial, temporal, L_pf, L_reg, model overrides, loss overrides, optim overrides)
ROWS = {
    "no_pf_no_reg": ("S", "T", False, False, {}, {"phasor_field": 0.0, "gamma": 0.0}, {}),
    "no_pf": ("S", "T", False, True, {}, {"phasor_field": 0.0}, {}),
    "no_reg": ("S", "T", True, False, {}, {"gamma": 0.0}, {}),
    "full": ("S", "T", True, True, {}, {}, {}),
    "tt": ("T", "T", True, True, {"variant": "tt"}, {}, {}),
    "t": ("-", "T", True, True, {"variant": "t"}, {}, {}),
    "ss": ("S", "S", True, True, {"variant": "ss"}, {}, {}),
    "s": ("S", "-", True, True, {"variant": "s"}, {}, {}),
    "wd_0.95": ("S", "T", True, True, {}, {}, {"weight_decay": 0.95}),
    "no_ssm": ("-", "-", True, True, {"variant": "none"}, {}, {}),
    "bidirectional": ("S", "T<->", True, True, {"temporal_causal": False}, {}, {}),
}
MAMBA_NAMES = {"S": "S-Mamba", "T": "T-Mamba", "T<->": "T-Mamba (bidirectional)", "-": "-"}


def row_config(base: dict, row: str, steps: int, seed: int | None = None) -> dict:
  """The run config of one ablation row: ``base`` with the row's changes, ``steps`` and ``seed``."""
  *_, model, loss, optim = ROWS[row]
  cfg = copy.deepcopy(base)
  cfg["model"] = {**cfg.get("model", {}), **model}
  tr = cfg["train"]
  tr["steps"] = int(steps)
  tr["loss"] = {**tr.get("loss", {}), **loss}
  tr["optim"] = {**tr.get("optim", {}), **optim}
  tr["variants"] = (OURS,)
  if seed is not None:
    tr["seed"] = int(seed)
  return cfg


def run_row(base: dict, row: str, steps: int, workdir: pathlib.Path, seed: int | None = None) -> dict:
  """Train (or resume) one row with one seed; per-frame scores on the val and test splits.

  Cached in ``workdir/<row>[-seed<k>]/score.json`` (reused when its steps match).
  """
  from nlosjax import train as T
  from nlosjax.evaluation import protocol
  base_seed = int(base["train"].get("seed", 0))
  seed = base_seed if seed is None else int(seed)
  out = workdir / (row if seed == base_seed else f"{row}-seed{seed}")
  cached = out / "score.json"
  if cached.exists():
    saved = json.loads(cached.read_text())
    if saved.get("steps") == steps and "val" in saved:
      return saved
  cfg = row_config(base, row, steps, seed)
  data_path = pathlib.Path(cfg["data"]["path"])
  typed = T.RunConfig.from_dict(cfg)
  T.ensure_dataset(typed, data_path)
  t0 = time.perf_counter()
  mcfg, state = T.train_model(typed, data_path, out, OURS, log=lambda s: None)
  train_s = time.perf_counter() - t0
  result = {"row": row, "seed": seed, "steps": steps, "train_s": round(train_s, 1)}
  for split in ("val", "test"):
    ev = protocol.evaluate(typed, data_path, {OURS: (mcfg, state.params)}, split=split,
                           methods=(), log=lambda s: None)
    result[split] = {"sequence": ev["sequence"].tolist(),
                     "scores": {k: v[0].tolist() for k, v in ev["scores"][OURS].items()}}
  rows = T.read_metrics(out / OURS / "metrics.jsonl")
  result["final_loss"] = rows[-1]["loss"] if rows else None
  out.mkdir(parents=True, exist_ok=True)
  cached.write_text(json.dumps(result) + "\n")
  return result


def _scores(runs: list[dict], split: str) -> tuple[dict, list]:
  """``metric -> [K, N]`` over a row's K seeds (the same frames), and the frames' sequences."""
  import numpy as np
  seq = runs[0][split]["sequence"]
  if any(r[split]["sequence"] != seq for r in runs):
    raise ValueError("the seeds of a row were scored on different frames")
  keys = runs[0][split]["scores"]
  return {k: np.stack([np.asarray(r[split]["scores"][k], float) for r in runs]) for k in keys}, seq


def summarise(results: dict) -> dict:
  """Test-split summaries per row, paired differences row - ``full``, and the validation choices.

  ``results``: row -> list of per-seed results (:func:`run_row`), the same seeds in every row.
  """
  from nlosjax.evaluation import scores
  out = {"test": {}, "vs_full": {}, "val": {}}
  ref = results.get("full")
  for row, r in results.items():
    test, seq = _scores(r, "test")
    out["test"][row] = scores.summarize_scores(test, seq)
    val, vseq = _scores(r, "val")
    out["val"][row] = scores.summarize_scores({"psnr": val["psnr"]}, vseq)["psnr"]
    if ref is not None and row != "full":
      out["vs_full"][row] = scores.compare_scores(test, _scores(ref, "test")[0], seq)
  if "full" in results and "wd_0.95" in results:
    # The default (1e-4) changes only on evidence: the paired validation difference's interval
    # must exclude 0 (the rule every claim in the tables follows).
    val_wd, vseq = _scores(results["wd_0.95"], "val")
    val_full, _ = _scores(results["full"], "val")
    d = scores.compare_scores({"psnr": val_wd["psnr"]}, {"psnr": val_full["psnr"]}, vseq)["psnr"]
    out["val_wd_minus_full"] = d
    out["weight_decay_choice"] = "wd_0.95" if d["ci95"][0] > 0 else "full"
  return out


def to_markdown(results: dict, summary: dict, cmd: str, steps: int, base: dict) -> str:
  from experiments.provenance import provenance
  from nlosjax import stats
  tick = {True: "✓", False: "✗"}
  tr = base["train"]
  n = next(iter(summary["test"].values()))["psnr"]
  lines = ["# Table 2: ablations at the CPU preset (one shared budget)", ""] + provenance(cmd) + [
      "",
      f"Budget of every row: Ours (3 frames), {steps} steps of batch {tr['batch_size']}, seeds"
      f" {tr.get('seed', 0)}-{tr.get('seed', 0) + n['n_seeds'] - 1},"
      f" AdamW lr {tr['optim'].get('learning_rate')} (cosine, warm-up"
      f" {tr['optim'].get('warmup_steps')}), the CPU preset's data (`{base['data']['path']}`) and"
      f" model, the last checkpoint. Scored on the test"
      f" split ({n['n_sequences']} sequences, {n['n_frames'] // max(n['n_seeds'], 1)} frames):"
      " mean [95 % bootstrap interval over sequences and seeds]. Differences are paired with"
      " the full model seed by seed on the same frames. Train s: mean per seed.",
      "",
      "| row | Spatial | Temporal | L_pf | L_ls/tv | weight decay | PSNR (dB) ↑ | SSIM ↑ |"
      " object depth RMSE (m) ↓ | object recall ↑ | PSNR - full (dB) | recall - full | train s |",
      "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
  ]
  called = []
  for row, r in results.items():
    first, second, pf, reg, _, _, optim = ROWS[row]
    wd = optim.get("weight_decay", tr["optim"].get("weight_decay"))
    m = summary["test"][row]
    d = summary["vs_full"].get(row)
    dp = cell(d["psnr"], 2, True) if d else "—"
    dr = cell(d["recall"], 3, True) if d else "—"
    train_s = sum(x["train_s"] for x in r) / len(r)
    lines.append(
        f"| {row} | {MAMBA_NAMES[first]} | {MAMBA_NAMES[second]} | {tick[pf]} | {tick[reg]} | {wd:g} |"
        f" {cell(m['psnr'], 2)} | {cell(m['ssim'], 3)} | {cell(m['rmse_object'], 3)} |"
        f" {cell(m['recall'], 3)} | {dp} | {dr} | {train_s:.0f} |")
    if d and stats.excludes_zero(d["psnr"]):
      called.append(f"{row} ({d['psnr']['mean']:+.2f} dB)")
  lines += ["", "Rows whose test PSNR differs from the full model's (interval excludes 0): "
            + (", ".join(called) if called else "none") + "."]
  if "weight_decay_choice" in summary:
    v = summary["val"]
    d = summary["val_wd_minus_full"]
    chosen = summary["weight_decay_choice"]
    lines += ["", f"Weight decay, chosen on the validation split (mean intensity PSNR): 1e-4 row "
              f"{v['full']['mean']:.2f} dB, 0.95 row {v['wd_0.95']['mean']:.2f} dB, paired"
              f" difference {cell(d, 2, True)} dB -> `{chosen}`"
              + (" (the interval excludes 0)." if chosen == "wd_0.95" else
                 " (the default 1e-4 stays: the interval includes 0).")]
    preset_wd = tr["optim"].get("weight_decay")
    chosen_wd = ROWS[chosen][6].get("weight_decay", preset_wd)
    if chosen_wd != preset_wd:
      lines += ["", f"The preset this table ran on still trains with weight decay {preset_wd:g}"
                f" (`train.optim.weight_decay`); its Table 1 and main job do not yet use the"
                f" validation choice {chosen_wd:g}."]
  lines.append("")
  return "\n".join(lines)


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="cpu")
  parser.add_argument("--steps", type=int, default=150)
  parser.add_argument("--seeds", type=int, default=3, help="training seeds per row")
  parser.add_argument("--workdir", default="runs/ablations")
  parser.add_argument("--only", nargs="*", default=None, choices=list(ROWS))
  parser.add_argument("--out", default=str(RESULTS / "table2.md"))
  args, overrides = parser.parse_known_args(argv)
  from tqdm import tqdm

  from experiments.cli import load_config
  base = load_config(args.config, overrides)
  rows = args.only or list(ROWS)
  workdir = pathlib.Path(args.workdir)
  if args.seeds < 1:
    parser.error(f"--seeds must be >= 1, got {args.seeds}")
  import numpy as np
  base_seed = int(base["train"].get("seed", 0))
  jobs = [(row, base_seed + k) for k in range(args.seeds) for row in rows]  # seed by seed
  results = {row: [] for row in rows}
  for row, seed in tqdm(jobs, desc="ablations", unit="run"):
    r = run_row(base, row, args.steps, workdir, seed)
    results[row].append(r)
    tqdm.write(f"{row} seed {seed}: test PSNR {np.mean(r['test']['scores']['psnr']):.2f} dB "
               f"({r['train_s']:.0f} s)")
  cmd = "python -m experiments.studies.ablations " + " ".join(sys.argv[1:] if argv is None else argv)
  summary = summarise(results)
  text = to_markdown(results, summary, cmd.strip(), args.steps, base)
  out = pathlib.Path(args.out)
  out.parent.mkdir(parents=True, exist_ok=True)
  out.write_text(text)
  out.with_suffix(".json").write_text(json.dumps(summary, indent=2) + "\n")
  print(text)

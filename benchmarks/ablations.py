"""The paper's Table 2 ablations at the CPU preset, with one shared training budget.

    python -m benchmarks.ablations [--config cpu] [--steps 150] [--workdir runs/ablations]
                                   [--only full no_pf ...] [--out benchmarks/results/table2.md]

Every row trains Ours (three frames, the main job's model and data) for the
same ``--steps`` from the same seed, changing one thing, then scores the test
split (intensity PSNR/SSIM, depth RMSE/MAD, mean +- std over frames):

* loss items (paper Table 2, top): without the phasor-field loss ``L_pf``,
  without the regularisers ``L_ls``/``L_tv`` (``gamma = 0``), without both;
* Mamba mechanism (paper Table 2, bottom): every block temporal-then-spatial
  (``st``, the paper), temporal twice (``tt``), temporal only (``t``), spatial
  twice (``ss``), spatial only (``s``);
* optimiser: AdamW weight decay 0.95 (printed in the paper) against 1e-4
  (its predecessor USM's, our default).

Each run lives in ``WORKDIR/<row>/`` (resumable: a rerun reuses finished
rows). Writes the Markdown table to ``--out`` and the numbers to the same
path with ``.json``.
"""

from __future__ import annotations

import argparse
import copy
import datetime
import json
import os
import pathlib
import sys
import time

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
}
MAMBA_NAMES = {"S": "S-Mamba", "T": "T-Mamba", "-": "-"}


def row_config(base: dict, row: str, steps: int) -> dict:
  """The run config of one ablation row: ``base`` with the row's changes and ``steps``."""
  from nlosjax.train import with_defaults
  *_, model, loss, optim = ROWS[row]
  cfg = copy.deepcopy(with_defaults(base))
  cfg["model"] = {**cfg.get("model", {}), **model}
  tr = cfg["train"]
  tr["steps"] = int(steps)
  tr["loss"] = {**tr.get("loss", {}), **loss}
  tr["optim"] = {**tr.get("optim", {}), **optim}
  tr["variants"] = ("ours",)
  return cfg


def run_row(base: dict, row: str, steps: int, workdir: pathlib.Path) -> dict:
  """Train (or resume) one row and score it on the test split; cached in ``workdir/row/score.json``."""
  from nlosjax import train as T
  out = workdir / row
  cached = out / "score.json"
  if cached.exists():
    saved = json.loads(cached.read_text())
    if saved.get("steps") == steps:
      return saved
  cfg = row_config(base, row, steps)
  data_path = pathlib.Path(cfg["data"]["path"])
  T.ensure_dataset(cfg, data_path)
  t0 = time.perf_counter()
  mcfg, state = T.train_model(cfg, data_path, out, "ours", log=lambda s: None)
  train_s = time.perf_counter() - t0
  tables, images = T.evaluate(cfg, data_path, {"ours": (mcfg, state.params)}, methods=(),
                              log=lambda s: None)
  table = tables["ours"]
  rows = T.read_metrics(out / "ours" / "metrics.jsonl")
  result = {"row": row, "steps": steps, "train_s": round(train_s, 1), "metrics": table,
            "final_loss": rows[-1]["loss"] if rows else None,
            "frames": int(len(images["ours"]["intensity"]))}
  out.mkdir(parents=True, exist_ok=True)
  cached.write_text(json.dumps(result, indent=2) + "\n")
  return result


def _cell(m, key, spec):
  mean, std = m[key]
  return f"{mean:{spec}} ± {std:{spec}}"


def to_markdown(results: dict, info: dict, cmd: str, steps: int, base: dict) -> str:
  tick = {True: "✓", False: "✗"}
  tr = base["train"]
  lines = [
      "# Table 2: ablations at the CPU preset (one shared budget)",
      "",
      f"Command: `{cmd}`  ",
      f"Date: {datetime.date.today().isoformat()}  ",
      f"Machine: {info['cpu']}, {info['cores']} cores, {info['mem_gib']:.0f} GiB, JAX backend"
      f" {info['backend']} ({info['versions']}); shared with other jobs, so train times are"
      " indicative only.",
      "",
      f"Budget of every row: Ours (3 frames), {steps} steps of batch {tr['batch_size']}, seed"
      f" {tr.get('seed', 0)}, AdamW lr {tr['optim'].get('learning_rate')} (cosine, warm-up"
      f" {tr['optim'].get('warmup_steps')}), the CPU preset's data (`{base['data']['path']}`) and"
      f" model; scored on the test split ({next(iter(results.values()))['frames']} frames)."
      " Intensity PSNR (dB) / SSIM against the ground-truth intensity, depth RMSE / MAD (m),"
      " mean ± std over frames.",
      "",
      "| Spatial | Temporal | L_int/dep | L_t | L_pf | L_ls/tv | weight decay | PSNR ↑ | SSIM ↑ |"
      " RMSE ↓ | MAD ↓ | train s |",
      "|---|---|---|---|---|---|---|---|---|---|---|---|",
  ]
  for row, r in results.items():
    first, second, pf, reg, _, _, optim = ROWS[row]
    wd = optim.get("weight_decay", tr["optim"].get("weight_decay"))
    m = r["metrics"]
    lines.append(
        f"| {MAMBA_NAMES[first]} | {MAMBA_NAMES[second]} | ✓ | ✓ | {tick[pf]} | {tick[reg]} | {wd:g} |"
        f" {_cell(m, 'psnr', '.2f')} | {_cell(m, 'ssim', '.3f')} | {_cell(m, 'rmse', '.3f')} |"
        f" {_cell(m, 'mad', '.3f')} | {r['train_s']:.0f} |")
  lines.append("")
  return "\n".join(lines)


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="cpu")
  parser.add_argument("--steps", type=int, default=150)
  parser.add_argument("--workdir", default="runs/ablations")
  parser.add_argument("--only", nargs="*", default=None, choices=list(ROWS))
  parser.add_argument("--out", default="benchmarks/results/table2.md")
  args = parser.parse_args(argv)
  from experiments.cli import load_config
  from nlosjax.train import with_defaults
  from benchmarks.model import machine
  from tqdm import tqdm
  base = with_defaults(load_config(args.config))
  rows = args.only or list(ROWS)
  workdir = pathlib.Path(args.workdir)
  results = {}
  for row in tqdm(rows, desc="ablations", unit="row"):
    results[row] = run_row(base, row, args.steps, workdir)
    m = results[row]["metrics"]
    tqdm.write(f"{row}: PSNR {m['psnr'][0]:.2f} dB, SSIM {m['ssim'][0]:.3f}, depth RMSE"
               f" {m['rmse'][0]:.3f} m ({results[row]['train_s']:.0f} s)")
  cmd = "python -m benchmarks.ablations " + " ".join(sys.argv[1:] if argv is None else argv)
  text = to_markdown(results, machine(), cmd.strip(), args.steps, base)
  out = pathlib.Path(args.out)
  out.parent.mkdir(parents=True, exist_ok=True)
  out.write_text(text)
  out.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
  print(text)


if __name__ == "__main__":
  main()

"""Time to the validation plateau: the study's schedule against a shorter, hotter one (issue 62).

    python -m experiments.studies.time_to_plateau [--rows full ours_s] [--seeds 0 1 2]
                                         [--workdir runs/time_to_plateau] [--results DIR]
                                         [--study-results DIR] [--report-only]

The mechanism study (:mod:`experiments.studies.mechanisms`) trains each row of the ``cpu`` preset to its
validation plateau: peak learning rate 1e-3, a cosine schedule over 3000 steps, the plateau rule
(:data:`experiments.studies.mechanisms.design.STUDY_STOP`). Its records at the preset's photons
(``mechanisms/full/<row>-seed<s>.json`` in that study's results folder, ``--study-results``) are
this comparison's ``study`` side. The
``short`` side (:data:`SHORT`) trains the same row from the same seed on the same data, model,
loss, stopping rule and evaluation, changing two numbers: the peak learning rate and the cosine
horizon (the most steps). Records: ``RESULTS/time_to_plateau/<row>-seed<s>.json``, the study's
record format; the report: ``RESULTS/time_to_plateau.md``.

Time: both sides run the same train step and the same validation (one per 50 steps), so their
time to the plateau is in proportion to the steps taken; with a fixed seed the steps are the same
on any machine, and their ratio is the time ratio. Each record's wall time is shown with its
machine, not compared across machines. Accuracy: each seed's test scores paired with the same
seed's study run on the same frames, ``short - study``, with the bootstrap interval over
sequences and seeds (:func:`nlosjax.evaluation.scores.compare_scores`).

The ``real`` preset: the long-run study :mod:`experiments.studies.real_preset` trains the same
short schedule, unchanged, on its v5 candidate beside the candidate's own runs at 1e-3 (its schedule
probes, ``Run.schedule_probe``); the report's last section reads their committed states (validation
only: those runs are not scored on a test split, one seed each).
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np

from experiments import provenance
from experiments.studies.mechanisms.design import (
  COLUMNS,
  ROWS,
  STUDY_OPTIM,
  STUDY_STOP,
  run_config,
  run_dir,
  study_optim,
  study_recipe,
)
from experiments.studies.mechanisms.records import RESULTS as STUDY_RESULTS
from experiments.studies.mechanisms.records import _array, load_runs, write_json
from experiments.studies.mechanisms.report import same_frames, stack_scores
from nlosjax.variants import OURS_S

#: This study's results folder: its reports, figures and JSON records.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"

#: The short schedule: peak learning rate and cosine horizon (= the most steps); all else the study's.
SHORT = {"learning_rate": 3e-3, "max_steps": 400}
BUDGET = "full"
NAME = "time_to_plateau"
DEFAULT_ROWS = ("full", OURS_S)


def short_config(base: dict, row: str, seed: int) -> dict:
  """The study's run config of ``row``/``seed`` at the preset's photons, with :data:`SHORT`'s two numbers."""
  cfg = run_config(base, BUDGET, row, seed, {**STUDY_STOP, "max_steps": SHORT["max_steps"]})
  cfg["train"]["optim"] = {**cfg["train"]["optim"], "learning_rate": SHORT["learning_rate"]}
  return cfg


def record_path(results: pathlib.Path, row: str, seed: int) -> pathlib.Path:
  return pathlib.Path(results) / NAME / f"{row}-seed{seed}.json"


def run_short(base: dict, row: str, seed: int, workdir: pathlib.Path, results: pathlib.Path) -> dict:
  """Train (or reload) one short-schedule run, score it on test; writes and returns its record."""
  from experiments.studies.mechanisms.study import run_record, train_and_score
  from nlosjax import train as T
  cfg = short_config(base, row, seed)
  data_path = pathlib.Path(cfg["data"]["path"])
  T.ensure_dataset(T.RunConfig.from_dict(cfg), data_path)
  folder = run_dir(workdir, BUDGET, row, seed)
  folder.mkdir(parents=True, exist_ok=True)
  _, _, test = train_and_score(cfg, folder, ROWS[row][1], print)
  record = {**run_record(cfg, BUDGET, row, seed, folder, test), "schedule": dict(SHORT)}
  write_json(record_path(results, row, seed), record)
  return record


def _mean(r: dict, metric: str) -> float:
  return float(np.nanmean(_array(r["test"]["scores"][metric])))


def report(study: dict, short: dict, command: str, real: list | None = None) -> str:
  """The markdown report of ``(row, seed) -> record`` of both sides; ``real``: :func:`real_preset_pairs`."""
  from nlosjax.evaluation import scores
  from nlosjax.stats import format_interval as cell
  lines = ["# Time to the validation plateau: the study's schedule against a short one", ""]
  lines += provenance.provenance(command) + [""]
  lines += [f"`cpu` preset at its photons, each row trained until learning stops (plateau rule every "
            f"{STUDY_STOP['every']} steps, patience {STUDY_STOP['patience']}, {STUDY_STOP['min_delta_db']} dB) or "
            f"at the schedule's horizon. **study**: peak learning rate {STUDY_OPTIM['learning_rate']:g}, "
            f"cosine over {STUDY_STOP['max_steps']} "
            f"steps (`RESULTS/mechanisms/full/`). **short**: peak {SHORT['learning_rate']:g}, cosine over "
            f"{SHORT['max_steps']} steps. Same data, model, loss, seed, stopping rule and evaluation; both sides run "
            "the same step and validation, so the ratio of steps taken is the ratio of time on any machine.", "",
            "| row | seed | steps: study → short (ratio) | best step | validation PSNR (dB): study → short "
            "| test PSNR (dB): study → short | train wall s: study / short (their machines) |",
            "|---|---|---|---|---|---|---|"]
  rows = sorted({k[0] for k in short})
  for row, seed in sorted(short):
    a, b = study.get((row, seed)), short[(row, seed)]
    if a is None:
      lines.append(f"| {row} | {seed} | — → {b['steps_taken']} | {b['best_step']} | — → {b['best_val_psnr']:.2f} "
                   f"| — → {_mean(b, 'psnr'):.2f} | — / {b['train_wall_s']:.0f} |")
      continue
    steps = f"{a['steps_taken']} → {b['steps_taken']} ({b['steps_taken'] / a['steps_taken']:.2f})"
    lines.append(f"| {row} | {seed} | {steps} "
                 f"| {a['best_step']} → {b['best_step']} | {a['best_val_psnr']:.2f} → {b['best_val_psnr']:.2f} "
                 f"| {_mean(a, 'psnr'):.2f} → {_mean(b, 'psnr'):.2f} "
                 f"| {a['train_wall_s']:.0f} ({a['machine'].get('cpu', '?')}) / {b['train_wall_s']:.0f} "
                 f"({b['machine'].get('cpu', '?')}) |")
  lines += ["", "Paired on the same test frames and seeds, short − study (mean [95 % interval over sequences "
            "and seeds]); called where the interval excludes 0:", "",
            "| row | seeds | steps ratio (sum) | " + " | ".join(h for h, _ in COLUMNS.values()) + " |",
            "|---|---|---|" + "---|" * len(COLUMNS)]
  verdicts = []
  for row in rows:
    seeds = sorted(s for (r, s) in short if r == row and (r, s) in study)
    if not seeds:
      continue
    a = [study[(row, s)] for s in seeds]
    b = [short[(row, s)] for s in seeds]
    if not same_frames(a + b):
      raise ValueError(f"{row}: the runs were scored on different test frames")
    diff = scores.compare_scores({m: stack_scores(b, m) for m in COLUMNS},
                                 {m: stack_scores(a, m) for m in COLUMNS}, a[0]["test"]["sequence"])
    ratio = sum(r["steps_taken"] for r in b) / sum(r["steps_taken"] for r in a)
    lines.append(f"| {row} | {', '.join(map(str, seeds))} | {ratio:.2f} | "
                 + " | ".join(cell(diff[m], d, signed=True) for m, (_, d) in COLUMNS.items()) + " |")
    lo, hi = diff["psnr"]["ci95"]
    verdicts.append(f"- {row}: {ratio:.2f}x the steps (goal ≤ 0.50); test PSNR short − study "
                    f"{cell(diff['psnr'], 2, signed=True)} dB, "
                    + ("not called (the interval holds 0)." if lo <= 0 <= hi else
                       ("higher (called)." if lo > 0 else "lower (called).")))
  lines += ["", *verdicts]
  lines += real_section(real or [])
  return "\n".join(lines) + "\n"


def real_preset_pairs() -> list[tuple[dict, dict]]:
  """``(study, short)`` curves of the ``real`` preset: each schedule probe of the long-run study
  whose candidate, variant and seed also have a run at the candidate's own schedule, both finished.

  Each curve: ``{"run", "variant", "lr", "max_steps", "steps", "best_step", "best", "curve", "rule"}``
  (``curve``: ``[(step, validation PSNR in dB)]``, read from the committed state)."""
  import json

  from experiments.studies.real_preset import study as real_study

  def curve(run):
    path = real_study.state_folder(run) / run.variant / "validation_curve.json"
    if not path.exists():
      return None
    c = json.loads(path.read_text())
    if c.get("stop_reason") is None:
      return None
    points = [(int(p["step"]), float(p["val_psnr"])) for p in c["curve"]]
    config = real_study.run_config(run)
    return {"run": run.name, "variant": run.variant, "lr": config["train"]["optim"]["learning_rate"],
            "max_steps": config["train"]["stop"]["max_steps"], "steps": points[-1][0],
            "best_step": int(c["best_step"]), "best": float(c["best_val_psnr"]), "curve": points,
            "rule": dict(config["train"]["stop"])}

  pairs = []
  for probe in (r for r in real_study.RUNS if r.schedule_probe):
    base = next((r for r in real_study.RUNS if not r.probe and (r.config, r.variant, r.seed)
                 == (probe.config, probe.variant, probe.seed)), None)
    a, b = (curve(base) if base else None), curve(probe)
    if a and b:
      pairs.append((a, b))
  return pairs


def real_section(pairs: list[tuple[dict, dict]]) -> list[str]:
  """The report's lines on the ``real`` preset's pairs (:func:`real_preset_pairs`)."""
  if not pairs:
    return []
  lines = ["", "## The `real` preset (v5 candidate, `experiments.studies.real_preset`)", "",
           "The same short schedule on the `real` preset's v5 candidate (`experiments/configs/real_v5.py`) beside "
           "that candidate's runs at its own schedule, one seed each, from the committed states under "
           "`experiments/studies/real_preset/state/`. Validation PSNR only (these runs are not scored on a test "
           "split); one seed, so no interval: a difference here is not called.", "",
           "| variant | schedule: study → short | steps: study → short (ratio) | best step | "
           "best validation PSNR (dB): study → short | validation PSNR at step 50 (dB): study → short |",
           "|---|---|---|---|---|---|"]
  notes = []
  for a, b in pairs:
    at50 = [dict(x["curve"]).get(50) for x in (a, b)]
    lines.append(f"| {a['variant']} | {a['lr']:g}/{a['max_steps']} → {b['lr']:g}/{b['max_steps']} "
                 f"| {a['steps']} → {b['steps']} ({b['steps'] / a['steps']:.2f}) | {a['best_step']} → {b['best_step']} "
                 f"| {a['best']:.2f} → {b['best']:.2f} | {at50[0]:.2f} → {at50[1]:.2f} |")
    notes.append(f"{a['variant']} {at50[0] - a['best']:+.2f} dB")
  rule = pairs[0][0]["rule"]
  floor = rule["every"] * (rule["patience"] + 1)
  same = all(a["steps"] == b["steps"] and a["best_step"] == b["best_step"] for a, b in pairs)
  ratio = sum(b["steps"] for _, b in pairs) / sum(a["steps"] for a, _ in pairs)
  first = ("At this preset both schedules peak at the same step and the plateau rule stops both at the same "
           "step: the short schedule takes no fewer steps." if same else
           f"At this preset the short schedule takes {ratio:.2f}x the steps (sum over the variants).")
  lines += ["", f"{first} Learning here is nearly done by the first "
            f"validation (step 50, against each study run's best: {', '.join(notes)}), so the time to the "
            f"plateau is set by the rule itself (it stops no earlier than {floor} steps: one validation per "
            f"{rule['every']} steps and {rule['patience']} without gain), not by the schedule."]
  return lines


def load_short(results: pathlib.Path) -> dict:
  import json
  out = {}
  for path in sorted((pathlib.Path(results) / NAME).glob("*-seed*.json")):
    r = json.loads(path.read_text())
    out[(r["row"], int(r["seed"]))] = r
  return out


def main(argv=None) -> int:
  from experiments.cli import config_parser, parse_config
  parser = config_parser(__doc__.split("\n\n")[0])
  parser.add_argument("--rows", nargs="+", choices=list(ROWS), default=list(DEFAULT_ROWS))
  parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
  parser.add_argument("--workdir", default=f"runs/{NAME}")
  parser.add_argument("--results", default=str(RESULTS), help="its records and report")
  parser.add_argument("--study-results", default=str(STUDY_RESULTS),
                      help="the mechanism study's results folder (its records are the study side)")
  parser.add_argument("--report-only", action="store_true")
  args, base, overrides = parse_config(parser, argv)
  from experiments.studies.mechanisms.records import code_at_start
  code_at_start()                          # the commit and code this process loads, for the records
  base = study_recipe(base, overrides)     # the study side's model and loss, as experiments.studies.mechanisms runs it
  base["train"]["optim"] = study_optim(base, overrides)   # the study side's, as experiments.studies.mechanisms runs it
  results = pathlib.Path(args.results)
  if not args.report_only:
    for row in args.rows:
      for seed in args.seeds:
        if record_path(results, row, seed).exists():
          print(f"{NAME}: {record_path(results, row, seed)} exists; delete it to run again")
          continue
        run_short(base, row, seed, pathlib.Path(args.workdir), results)
  study = {k[1:]: r for k, r in load_runs(pathlib.Path(args.study_results)).items() if k[0] == BUDGET}
  short = load_short(results)
  if not short:
    raise SystemExit(f"{NAME}: no short-schedule record under {results / NAME}")
  command = "python -m experiments.studies.time_to_plateau " + " ".join(sys.argv[1:] if argv is None else argv)
  text = report(study, short, command.strip(), real_preset_pairs())
  (results / f"{NAME}.md").write_text(text)
  print(text)
  return 0

"""``python -m experiments.studies.objects``: train each recipe, score it on validation, write the report."""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import subprocess
import sys
import time

import numpy as np

from experiments.studies.objects import NOT_ELIGIBLE, OBJECT_SCORES, RESULTS, ROWS, SETS, SHIPPED, STATE
from nlosjax.variants import OURS, OURS_S

COMMAND = "python -m experiments.studies.objects"
#: Scores of every table: the object ones, then the whole-image PSNR and the floors.
TABLE_SCORES = OBJECT_SCORES + ("psnr", "psnr_zero", "psnr_balanced_zero")


#: ``experiments.train``'s exit status when ``--hours`` paused it (its state exported).
EXIT_PAUSED = 75


def run_row(row: str, workdir: pathlib.Path, variants, seeds: int, log=print, *,
            state: pathlib.Path | None = None, hours: float | None = None) -> bool:
  """The row's main job (``experiments.train``) in ``workdir``; resumes where it stopped.

  ``state``: the folder its resumable state is mirrored into (``--resume-from``; commit it to go
  on from a fresh clone). ``hours``: pause after that long. Returns False where it paused.
  """
  if (workdir / "results" / SETS["test"]).exists():
    log(f"[{row}] trained and scored already: {workdir}")
    return True
  variants = "(" + "".join(f'"{v}",' for v in variants) + ")"
  cmd = [sys.executable, "-m", "experiments.train", "--workdir", str(workdir),
         f"--config.train.seeds={seeds}", f"--config.train.variants={variants}", *ROWS[row][1]]
  if state is not None:
    cmd += ["--resume-from", str(state)]
    if hours is not None:
      cmd += ["--hours", f"{hours:g}"]
  log(f"[{row}] {' '.join(cmd[1:])}")
  t0 = time.perf_counter()
  workdir.mkdir(parents=True, exist_ok=True)
  with open(workdir.parent / f"{row}.log", "a") as out:
    done = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT)
  if done.returncode == EXIT_PAUSED:
    log(f"[{row}] paused after {time.perf_counter() - t0:.0f} s; its state is in {state}: commit it, "
        "and rerun the same command to go on")
    return False
  if done.returncode:
    raise SystemExit(f"[{row}] the main job failed (exit status {done.returncode}); "
                     f"see {workdir.parent / (row + '.log')}")
  log(f"[{row}] done in {time.perf_counter() - t0:.0f} s")
  return True


def score_validation(workdir: pathlib.Path, log=print) -> pathlib.Path:
  """Every model of the row and every classic method (at the row's settings) on the validation split,
  per frame, into ``results/val_scores.npz``."""
  from nlosjax import inference, train
  from nlosjax.evaluation import protocol
  out = workdir / "results" / SETS["validation"]
  if out.exists():
    return out
  config, trained = inference.load_run(workdir, seeds=True, log=log)
  cfg = train.RunConfig.from_dict(config)
  chosen = json.loads((workdir / "results" / "validation.json").read_text())
  thresholds = {v: c["threshold"] for v, c in chosen.get("learned", {}).items()}
  ev = protocol.evaluate(cfg, cfg.data.path, trained, split="val", classic_settings=chosen["classic"],
                         model_thresholds=thresholds, log=log)
  arrays = {f"{m}/{k}": np.asarray(v) for m, s in ev["scores"].items() for k, v in s.items()}
  np.savez_compressed(out, sequence=np.asarray(ev["sequence"]), frame=np.asarray(ev["frame"]), **arrays)
  return out


def score_shipped_validation(root: pathlib.Path, row: str, name: str = "cpu", log=print) -> pathlib.Path:
  """The shipped ``name`` weights (Ours and Ours-S, :func:`nlosjax.inference.load_pretrained`) on the
  validation split of ``row``'s data, per frame, into ``<root>/shipped/results/val_scores.npz``: what a
  new recipe must beat on validation before its model replaces them. Their surface thresholds are
  tuned on the same split, as the main job tunes its models'; no classic method is rerun."""
  from nlosjax import inference, train
  from nlosjax.evaluation import protocol
  out = root / SHIPPED / "results" / SETS["validation"]
  if out.exists():
    return out
  config, _ = inference.load_run(root / row, seeds=True, log=log)
  cfg = train.RunConfig.from_dict(config)
  models = {v: [inference.load_pretrained(name, v)[:2]] for v in (OURS_S, OURS)}
  tuned = protocol.tune_model_thresholds(cfg, cfg.data.path, models, log=log)
  ev = protocol.evaluate(cfg, cfg.data.path, models, split="val", methods=(),
                         model_thresholds={v: t["threshold"] for v, t in tuned.items()}, log=log)
  out.parent.mkdir(parents=True, exist_ok=True)
  arrays = {f"{m}/{k}": np.asarray(v) for m, s in ev["scores"].items() for k, v in s.items()}
  np.savez_compressed(out, sequence=np.asarray(ev["sequence"]), frame=np.asarray(ev["frame"]), **arrays)
  return out


def per_seed(scores: dict, variant: str, metric: str = "psnr_balanced") -> list[float]:
  """Mean of ``metric`` per training seed of ``variant`` (scores ``[K, N]`` or ``[N]``)."""
  a = np.asarray(scores[variant][metric], dtype=float)
  return [float(np.nanmean(r)) for r in (a if a.ndim == 2 else a[None])]


def read_scores(path: pathlib.Path) -> tuple[dict, np.ndarray]:
  """``(method -> metric -> [N] or [K, N], sequence [N])`` of a per-frame scores file."""
  out = {}
  with np.load(path) as f:
    for key in f.files:
      if "/" in key:
        method, metric = key.split("/", 1)
        out.setdefault(method, {})[metric] = f[key]
    return out, f["sequence"]


def choose(validation: dict) -> str | None:
  """The row whose Ours has the highest mean validation object-balanced PSNR (over its frames and seeds),
  among the rows the preset can take (:data:`NOT_ELIGIBLE` left out)."""
  means = {row: float(np.nanmean(s[OURS]["psnr_balanced"])) for row, s in validation.items()
           if OURS in s and row not in NOT_ELIGIBLE}
  return max(means, key=means.get) if means else None


def _cell(summary: dict, digits: int, signed: bool = False) -> str:
  from nlosjax.stats import format_interval
  return format_interval(summary, digits, signed, missing="n/a")


def table(per_frame: dict, sequence, methods=None) -> list[str]:
  """Markdown rows: each method's object scores, then the whole-image PSNR and both floors."""
  from nlosjax.evaluation import report, scores
  methods = methods or [m for m in report.TABLE_METHODS if m in per_frame]
  head = [report._header(k) for k in TABLE_SCORES]
  lines = ["| method | " + " | ".join(head) + " | sequences / frames / seeds |",
           "|---|" + "---|" * len(TABLE_SCORES) + "---|"]
  for m in methods:
    s = scores.summarize_scores({k: v for k, v in per_frame[m].items() if k in TABLE_SCORES}, sequence)
    first = s["psnr"]
    lines.append(f"| {report.label(m)} | " + " | ".join(
        _cell(s[k], report.METRIC_LABELS[k][2]) if k in s else "n/a" for k in TABLE_SCORES)
        + f" | {first['n_sequences']} / {first['n_frames']} / {first.get('n_seeds', 1)} |")
  return lines


def versus_classic(per_frame: dict, sequence) -> tuple[list[str], dict]:
  """Markdown rows of each learned model minus every classic method, paired on the same frames,
  and the verdicts ``{(a, b, metric): "better" | "worse" | "tie"}``."""
  from nlosjax.evaluation import baselines, report, scores
  metrics = OBJECT_SCORES + ("psnr",)
  lines = ["| comparison | " + " | ".join(report._header(k) for k in metrics) + " |",
           "|---|" + "---|" * len(metrics)]
  verdicts = {}
  learned = [v for v in (OURS, OURS_S) if v in per_frame]
  pairs = [(a, b) for a in learned for b in baselines.CLASSIC_METHODS if b in per_frame]
  if OURS in per_frame and OURS_S in per_frame:
    pairs.append((OURS, OURS_S))
  for a, b in pairs:
    d = scores.compare_scores({k: per_frame[a][k] for k in metrics}, {k: per_frame[b][k] for k in metrics}, sequence)
    cells = []
    for k in metrics:
      lo, hi = d[k]["ci95"]
      better = scores.HIGHER_IS_BETTER[k]
      verdicts[(a, b, k)] = ("tie" if not (lo > 0 or hi < 0) or math.isnan(d[k]["mean"])
                             else "better" if (lo > 0) == better else "worse")
      cells.append(_cell(d[k], report.METRIC_LABELS[k][2], signed=True))
    lines.append(f"| {report.label(a)} - {report.label(b)} | " + " | ".join(cells) + " |")
  return lines, verdicts


def goals(test: dict, verdicts: dict) -> list[str]:
  """Issue 87's goals on one set, each said met or not from the paired intervals of :func:`versus_classic`."""
  from nlosjax.evaluation import baselines
  out = []
  classic = [m for m in baselines.CLASSIC_METHODS if m in test]
  if OURS not in test:
    return out
  for k, what in (("intensity_mae_object", "object intensity error below every classic method's"),
                  ("recall", "object recall at least the best classic method's"),
                  ("f1", "surface F1 above every classic method's")):
    if k == "recall":
      best = max(classic, key=lambda m: float(np.nanmean(test[m][k])))
      ok = verdicts.get((OURS, best, k)) in ("better", "tie") and float(np.nanmean(test[OURS][k])) >= float(
          np.nanmean(test[best][k]))
      out.append(f"- {what} ({best}): {'met' if ok else 'not met'} ({verdicts.get((OURS, best, k))})")
    else:
      ok = all(verdicts.get((OURS, m, k)) == "better" for m in classic)
      worst = [m for m in classic if verdicts.get((OURS, m, k)) != "better"]
      out.append(f"- {what}: {'met' if ok else 'not met' + ' against ' + ', '.join(worst)}")
  ours = float(np.nanmean(test[OURS]["psnr"]))
  zero = float(np.nanmean(test[OURS]["psnr_zero"]))
  best = max(float(np.nanmean(test[m]["psnr"])) for m in classic)
  out.append(f"- intensity PSNR at least 3 dB above both the all-zero image ({zero:.2f} dB) and the best classic"
             f" method ({best:.2f} dB): Ours {ours:.2f} dB, {'met' if ours >= max(zero, best) + 3 else 'not met'}")
  if OURS_S in test:
    v = verdicts.get((OURS, OURS_S, "intensity_mae_object"))
    out.append(f"- Ours ahead of Ours-S on the object intensity error: {v}")
  return out


def shipped_section(shipped: dict, row: dict, chosen: str) -> list[str]:
  """Markdown: each training seed of the chosen row against the shipped weights on the validation
  object-balanced PSNR, and whether seed 0 (the one ``python -m experiments.train`` trains) is ahead:
  it replaces them only then. Taking seed 0 rather than the best seed keeps the shipped model the one
  the README's main job reproduces, and its validation score free of a choice among seeds."""
  from nlosjax.evaluation import report
  lines = ["### Against the weights shipped now, on validation", "",
           f"The shipped `cpu` weights (`nlosjax/weights/`) and each training seed of **{chosen}**, mean "
           "validation object-balanced PSNR (dB) and object intensity error. Seed 0, the model the main "
           "job trains, replaces the shipped model where it is ahead on the balanced PSNR.", "",
           "| model | shipped: balanced PSNR / intensity error | " + chosen + " seeds 0, 1, ...: balanced PSNR | "
           "intensity error | seed 0 replaces the shipped |", "|---|---|---|---|---|"]
  for v in (OURS, OURS_S):
    if v not in shipped or v not in row:
      continue
    ship = per_seed(shipped, v)[0]
    ship_mae = per_seed(shipped, v, "intensity_mae_object")[0]
    seeds, maes = per_seed(row, v), per_seed(row, v, "intensity_mae_object")
    lines.append(f"| {report.label(v)} | {ship:.3f} / {ship_mae:.3f} | " + ", ".join(f"{x:.3f}" for x in seeds)
                 + " | " + ", ".join(f"{x:.3f}" for x in maes) + f" | {'yes' if seeds[0] > ship else 'no'} |")
  return lines + [""]


def write_report(root: pathlib.Path, rows, out: pathlib.Path, command: str) -> str:
  """The report from every row's score files under ``root`` (see the package docstring)."""
  from experiments.provenance import provenance
  from nlosjax.evaluation import report
  found = {row: {name: root / row / "results" / f for name, f in SETS.items()
                 if (root / row / "results" / f).exists()} for row in rows}
  validation = {row: read_scores(f["validation"])[0] for row, f in found.items() if "validation" in f}
  chosen = choose(validation)
  lines = ["# Objects: the recipes of the cpu preset, chosen on the validation object scores", "",
           *provenance(command), "",
           "Each row is the `cpu` preset's main job with the overrides named (400 steps unless said; the",
           "checkpoint kept on validation; the classic methods tuned on validation). Mean [95 % bootstrap",
           "interval over sequences and training seeds]. The object scores first; the whole-image PSNR last,",
           "beside the all-zero image's.", ""]
  lines += ["## Rows", "", "| row | what | overrides |", "|---|---|---|"]
  lines += [f"| {row} | {ROWS[row][0]} | {' '.join(f'`{o}`' for o in ROWS[row][1]) or 'none'} |" for row in rows]
  lines += ["", "## The choice, on the validation split", ""]
  if validation:
    lines += ["Mean validation scores of each row's learned models (over seeds) and of the classic methods; "
              "the row chosen has the highest Ours object-balanced PSNR among the rows whose main job fits "
              f"the preset's 20-minute budget (not: {', '.join(NOT_ELIGIBLE)}).", "",
              "| row | model | " + " | ".join(report._header(k) for k in OBJECT_SCORES + ("psnr",)) + " |",
              "|---|---|" + "---|" * (len(OBJECT_SCORES) + 1)]
    for row, s in validation.items():
      for v in (OURS, OURS_S):
        if v in s:
          lines.append(f"| {row} | {report.label(v)} | " + " | ".join(
              f"{float(np.nanmean(s[v][k])):.3f}" for k in OBJECT_SCORES + ("psnr",)) + " |")
    from nlosjax.evaluation import baselines
    first = next(iter(validation.values()))        # the classic methods at the preset's tuned settings
    for m in (m for m in baselines.CLASSIC_METHODS if m in first):
      lines.append(f"| (classic) | {report.label(m)} | " + " | ".join(
          f"{float(np.nanmean(first[m][k])):.3f}" for k in OBJECT_SCORES + ("psnr",)) + " |")
    lines += ["", f"Chosen: **{chosen}**.", ""]
    shipped = root / SHIPPED / "results" / SETS["validation"]
    if chosen is not None and shipped.exists():
      lines += shipped_section(read_scores(shipped)[0], validation[chosen], chosen)
  else:
    lines += ["No row has been scored on validation yet.", ""]
  for row in dict.fromkeys(r for r in ("paper", chosen) if r in found):
    for name in ("test", "independent"):
      if name not in found.get(row, {}):
        continue
      per_frame, seq = read_scores(found[row][name])
      rows_, verdicts = versus_classic(per_frame, seq)
      lines += [f"## {row}: {name} set", "", *table(per_frame, seq), "",
                "Paired differences (a - b on the same frames):", "", *rows_, "",
                "Goals (issue 87):", "", *goals(per_frame, verdicts), ""]
  text = "\n".join(lines) + "\n"
  out.parent.mkdir(parents=True, exist_ok=True)
  out.write_text(text)
  return text


def main(argv=None) -> int:
  from experiments import store
  p = argparse.ArgumentParser(prog=COMMAND, description=__doc__)
  p.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
  p.add_argument("--variants", nargs="+", default=[OURS_S, OURS], choices=[OURS_S, OURS])
  p.add_argument("--seeds", type=int, default=3, help="training seeds per model (default 3)")
  p.add_argument("--workdir", type=pathlib.Path, default=None,
                 help="folder of the rows' run folders (default: the store's runs/objects)")
  p.add_argument("--state", type=pathlib.Path, default=STATE,
                 help="folder of each row's committed resumable state, STATE/<row> (default: the study's state/)")
  p.add_argument("--hours", type=float, default=None,
                 help="pause after this many hours (state exported; exit status 75; rerun to go on)")
  p.add_argument("--report-only", action="store_true", help="rewrite the report from the score files only")
  p.add_argument("--out", type=pathlib.Path, default=RESULTS / "objects.md")
  args = p.parse_args(argv)
  root = args.workdir or store.home() / "runs" / "objects"
  root.mkdir(parents=True, exist_ok=True)
  if args.hours is not None and not args.hours > 0:
    p.error(f"--hours must be > 0, got {args.hours}")
  if not args.report_only:
    deadline = None if args.hours is None else time.monotonic() + 3600 * args.hours
    for row in args.rows:
      hours = None if deadline is None else max(deadline - time.monotonic(), 60) / 3600
      if not run_row(row, root / row, args.variants, args.seeds, state=args.state / row, hours=hours):
        return EXIT_PAUSED
      score_validation(root / row)
    validation = {row: read_scores(root / row / "results" / SETS["validation"])[0] for row in args.rows}
    chosen = choose(validation)
    if chosen is not None:
      score_shipped_validation(root, chosen)
  command = " ".join([COMMAND, *(argv if argv is not None else sys.argv[1:])])
  write_report(root, args.rows, args.out, command)
  print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

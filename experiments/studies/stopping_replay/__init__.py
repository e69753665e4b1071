"""The plateau rule replayed: would stopping sooner have kept the same validation score? (issue 62)

    python -m experiments.studies.stopping_replay [--results DIR]

Every plateau-trained run we keep has its validation curve on file: the mechanism study's and
the time-to-plateau records (:data:`RECORDS`: ``mechanisms/<budget>/*.json`` and
``time_to_plateau/*.json`` in those studies' results folders) and the committed states of the long-run studies
(``validation_curve.json`` under ``experiments/studies/*/state``, the mechanism study's
aside, read from its records). Those runs validated every 50 steps and stopped after 4
validations without a gain above 0.05 dB (``nlosjax.train.StopRule``'s defaults).

A rule that validates at a subset of those steps and stops no later sees exactly the same
curve up to its stop: the schedule's horizon is ``max_steps``, not the patience, validation
reads the parameters without changing them, and the batches and keys are functions of the
step. So each candidate rule is replayed on each curve exactly, without training anything:
where it stops, the training time to there (the curve's ``time_s``, less the validations it
skips), and the best validation PSNR it keeps. A run where a candidate would train past the
recorded curve's end is not replayable for it and is counted apart.

Per candidate: the time ratio (candidate / recorded, per run) and the change of the best
validation PSNR (candidate - recorded, dB), each the mean over runs with a 95 % bootstrap
interval over runs. Only validation scores: the test split plays no part in choosing a rule.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

from experiments import provenance

#: This study's results folder: its reports, figures and JSON records.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"

ROOT = provenance.ROOT
NAME = "stopping_replay"
#: The rule every replayed run was trained with (every, patience); candidates are replayed against it.
RECORDED = (50, 4)
#: Candidate rules ``(every, patience)``: fewer validations without gain, or validations half as often.
CANDIDATES = ((50, 3), (50, 2), (50, 1), (100, 2), (100, 1))
MIN_DELTA_DB = 0.05
#: The studies whose run records are replayed: record folder -> the results folder that holds it.
RECORDS = {name: ROOT / "experiments" / "studies" / name / "results" for name in ("mechanisms", "time_to_plateau")}


def curves(records: dict[str, pathlib.Path] | None = None, root: pathlib.Path = ROOT) -> dict[str, dict]:
  """``name -> {"points": [(step, val_psnr, time_s, val_s)], "rule": dict, "stop_reason"}`` of every kept run.

  ``records``: ``folder -> results folder`` holding ``folder/**/*-seed*.json`` (default :data:`RECORDS`).
  """
  out = {}
  for folder, results in (RECORDS if records is None else records).items():
    for path in sorted((results / folder).rglob("*-seed*.json")):
      r = json.loads(path.read_text())
      if not r.get("validation_curve"):
        continue
      out[f"{folder}/{path.relative_to(results / folder).with_suffix('')}"] = {
          "points": [(int(p["step"]), float(p["val_psnr"]), float(p["time_s"]), float(p["val_s"]))
                     for p in r["validation_curve"]],
          "rule": r["config"]["train"]["stop"], "stop_reason": r.get("stop_reason")}
  studies = root / "experiments" / "studies"
  states = sorted(p for p in studies.glob("*/state/**/validation_curve.json")
                  if p.relative_to(studies).parts[0] != "mechanisms")     # its runs are read above
  for path in states:
    c = json.loads(path.read_text())
    if c.get("stop_reason") is None:                 # a run still training
      continue
    # Replayed on the score the run stopped on: the whole-image PSNR, or its rule's metric
    # (the objects recipe's object-balanced PSNR), recorded as each point's "score".
    out[str(path.parent.relative_to(root))] = {
        "points": [(int(p["step"]), float(p.get("score", p["val_psnr"])), float(p["time_s"]), float(p["val_s"]))
                   for p in c["curve"]],
        "rule": c["rule"], "stop_reason": c["stop_reason"]}
  return out


def replay(points, every: int, patience: int, min_delta_db: float = MIN_DELTA_DB) -> dict | None:
  """Where the rule ``(every, patience)`` stops on ``points`` (recorded every 50 steps); None if past their end.

  The plateau test is :func:`nlosjax.train.stopping.plateau_reached`'s, on the validations the
  rule makes. Returns ``{"step", "time_s", "best", "best_step", "validations"}``.
  """
  from nlosjax.train.stopping import plateau_reached
  seen, skipped_s = [], 0.0
  for step, val, time_s, val_s in points:
    if step % every:
      skipped_s += val_s
      continue
    seen.append((step, val))
    if plateau_reached([v for _, v in seen], patience, min_delta_db):
      best_step, best = max(seen, key=lambda sv: (sv[1], -sv[0]))
      return {"step": step, "time_s": time_s - skipped_s, "best": best, "best_step": best_step,
              "validations": len(seen)}
  return None


def recorded(run: dict) -> dict:
  """The recorded run's own stop, best score and time (its whole curve)."""
  step, _, time_s, _ = run["points"][-1]
  best_step, best = max(((s, v) for s, v, _, _ in run["points"]), key=lambda sv: (sv[1], -sv[0]))
  return {"step": step, "time_s": time_s, "best": best, "best_step": best_step}


def _interval(x: np.ndarray) -> tuple[float, float]:
  """95 % bootstrap interval of the mean over runs (:func:`nlosjax.stats.summarize`, one value a run)."""
  from nlosjax import stats
  lo, hi = stats.summarize(x[:, None])["ci95"]
  return lo, hi


def compare(runs: dict[str, dict]) -> list[dict]:
  """Per candidate: time ratio and validation change over the replayable runs, with intervals."""
  usable = {k: r for k, r in runs.items()
            if (int(r["rule"]["every"]), int(r["rule"]["patience"])) == RECORDED
            and float(r["rule"].get("min_delta_db", MIN_DELTA_DB)) == MIN_DELTA_DB}
  rows = []
  for every, patience in CANDIDATES:
    ratio, change, same, lost = [], [], 0, []
    for name, run in usable.items():
      ref = recorded(run)
      got = replay(run["points"], every, patience)
      if got is None:
        if run["stop_reason"] == "max_steps":       # both run to the horizon: the same run
          got = {**ref, "validations": sum(1 for s, *_ in run["points"] if s % every == 0)}
        else:
          lost.append(name)
          continue
      ratio.append(got["time_s"] / ref["time_s"])
      change.append(got["best"] - ref["best"])
      same += got["best_step"] == ref["best_step"]
    ratio, change = np.array(ratio), np.array(change)
    rows.append({"every": every, "patience": patience, "runs": len(ratio), "not_replayable": lost,
                 "time_ratio": float(ratio.mean()), "time_ratio_ci95": _interval(ratio),
                 "val_change_db": float(change.mean()), "val_change_ci95": _interval(change),
                 "worst_db": float(change.min()), "same_best": same,
                 "lost_over_0p1db": int((change < -0.1).sum())})
  return rows


def report(rows: list[dict], runs: dict[str, dict], command: str) -> str:
  lines = ["# The plateau rule replayed on every kept validation curve", ""]
  lines += provenance.provenance(command) + [""]
  n = sum(1 for r in runs.values() if (int(r["rule"]["every"]), int(r["rule"]["patience"])) == RECORDED)
  lines += [f"Replayed on {n} runs trained with the rule of validating every {RECORDED[0]} steps and stopping "
            f"after {RECORDED[1]} validations without a gain above {MIN_DELTA_DB} dB (the `cpu` preset's "
            "mechanism and time-to-plateau runs, both photon budgets, and the committed long-run states of "
            "the `real` preset and the physics-shift study). Exact, not simulated: a rule that validates "
            "at a subset of the recorded steps and stops no later sees the same curve (module docstring). "
            "Validation split only.", "",
            "| rule (every, patience) | runs | training time / recorded | best validation PSNR change (dB) "
            "| worst run (dB) | runs losing > 0.1 dB | same best step | not replayable |",
            "|---|---|---|---|---|---|---|---|"]
  for r in rows:
    t_lo, t_hi = r["time_ratio_ci95"]
    v_lo, v_hi = r["val_change_ci95"]
    lines.append(f"| {r['every']}, {r['patience']} | {r['runs']} | {r['time_ratio']:.2f} [{t_lo:.2f}, {t_hi:.2f}] "
                 f"| {r['val_change_db']:+.2f} [{v_lo:+.2f}, {v_hi:+.2f}] | {r['worst_db']:+.2f} "
                 f"| {r['lost_over_0p1db']} | {r['same_best']} of {r['runs']} | {len(r['not_replayable'])} |")
  free = [r for r in rows if r["val_change_ci95"][0] > -0.05]
  lines += ["", "Mean over runs [95 % bootstrap interval over runs]. A rule counts as free when the interval of "
            "its validation change stays above -0.05 dB (the rule's own resolution)."]
  if free:
    lines.append("Free: " + ", ".join(f"({r['every']}, {r['patience']}) at {r['time_ratio']:.2f}x the time"
                                      for r in free) + ".")
  else:
    lines.append("**No candidate is free:** every rule that stops sooner loses validation PSNR on average, "
                 "because these curves still rise after several flat validations; the recorded rule stays.")
  return "\n".join(lines) + "\n"


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--results", default=str(RESULTS), help="where the report goes")
  args = p.parse_args(argv)
  results = pathlib.Path(args.results)
  runs = curves()
  if not runs:
    raise SystemExit(f"{NAME}: no validation curve under {' or '.join(map(str, RECORDS.values()))}")
  rows = compare(runs)
  command = ("python -m experiments.studies.stopping_replay "
             + " ".join(sys.argv[1:] if argv is None else argv)).strip()
  text = report(rows, runs, command)
  (results / f"{NAME}.md").write_text(text)
  print(text)
  return 0

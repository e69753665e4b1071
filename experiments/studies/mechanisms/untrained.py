"""Table 1's methods without training, on the study's test frames (``--untrained``).

The paper's Table 1 sets the learned models beside LCT, RSD, f-k and CSA. The study's learned
rows are trained to their plateau per budget; this module scores the methods that need no
training on the same test frames of the same data, so the report can pair each learned row
with each of them, seed by seed, frame by frame:

* the five classic methods (FBP, LCT, f-k, phasor, RSD) on the under-scanned input interpolated
  to the full grid, their options and surface threshold tuned on the validation split
  (:func:`nlosjax.evaluation.baselines.tune`, as the main job's Table 1);
* CSA (:mod:`nlosjax.physics.methods.csa`) on the sparse scan itself, a masked full grid; its
  l1 weight and falloff chosen on ``baselines.CSA_VAL_FRAMES`` validation frames spread over
  the sequences, its threshold by surface F1 on them (:func:`nlosjax.evaluation.baselines.tune_csa`).

Nothing here reads the test split before the settings are fixed. Each budget's scores go to
``RESULTS/mechanisms/untrained-<budget>.json``: ``{"budget", "data", "machine", "methods": {method:
{"settings", "test": {"sequence", "frame", "scores": metric -> [N]}}}}``.
"""

from __future__ import annotations

import pathlib
import time
from typing import Callable

import numpy as np

from nlosjax.variants import OURS_S

#: The methods scored: the classic five and CSA, in the paper's Table 1 order where it has them.
UNTRAINED = ("lct", "rsd", "fk", "csa", "fbp", "phasor")


def untrained_json(results: pathlib.Path, budget: str) -> pathlib.Path:
  return pathlib.Path(results) / "mechanisms" / f"untrained-{budget}.json"


def score_untrained(cfg: dict, *, methods=UNTRAINED, csa_frames: int | None = None,
                    log: Callable[[str], None] = print) -> dict:
  """Every method of ``methods`` tuned on ``cfg``'s validation split and scored on its test split.

  Returns the JSON record of the module docstring (without ``budget`` and ``machine``).
  """
  from nlosjax.evaluation import baselines, protocol, scores
  from nlosjax.physics import intensity_depth
  from nlosjax.train import RunConfig, ensure_dataset
  data_path = pathlib.Path(cfg["data"]["path"])
  typed = RunConfig.from_dict(cfg)
  ensure_dataset(typed, data_path)
  bs = int(cfg["train"].get("eval_batch_size", cfg["train"]["batch_size"]))
  classic = tuple(m for m in methods if m in baselines.CLASSIC_METHODS)
  t0 = time.perf_counter()
  val = protocol.load_split(typed, data_path, "val", batch_size=bs)
  val["loader"].close()
  settings = baselines.tune(val["measurement"], val["intensity"], val["depth"], val["setup"], val["stride"],
                            methods=classic, log=log) if classic else {}
  if "csa" in methods:
    pick = baselines.spread_frames(len(val["measurement"]), csa_frames or baselines.CSA_VAL_FRAMES)
    settings["csa"] = {**baselines.tune_csa(val["measurement"][pick], val["intensity"][pick],
                                            val["depth"][pick], val["setup"], val["stride"], log=log),
                       "val_frames": [int(i) for i in pick]}
  out = {"data": str(data_path), "methods": {}}
  ev = protocol.evaluate(typed, data_path, {}, split="test", methods=classic, classic_settings=settings, log=log)
  for m in classic:
    out["methods"][m] = {"settings": _plain_setting(settings[m]),
                         "test": {"sequence": ev["sequence"], "frame": ev["frame"],
                                  "scores": {k: np.asarray(v) for k, v in ev["scores"][m].items()}}}
  if "csa" in methods:
    test = protocol.load_split(typed, data_path, "test", batch_size=bs)
    test["loader"].close()
    s = settings["csa"]
    vol = np.concatenate([np.asarray(baselines.csa_volume(test["measurement"][i:i + bs], test["setup"],
                                                          test["stride"], s["options"]))
                          for i in range(0, len(test["measurement"]), bs)])
    inten, depth = (np.asarray(a) for a in intensity_depth(vol, test["setup"], threshold=s["threshold"]))
    per_frame = scores.frame_scores(inten, depth, test["intensity"], test["depth"],
                                    sequence=test["sequence"], frame=test["frame"])
    out["methods"]["csa"] = {"settings": _plain_setting(s),
                             "test": {"sequence": test["sequence"], "frame": test["frame"],
                                      "scores": {k: np.asarray(v) for k, v in per_frame.items()}}}
  out["wall_s"] = round(time.perf_counter() - t0, 1)
  return out


def _plain_setting(setting: dict) -> dict:
  """A tuned setting without its per-option grid of F1 tables (kept: options, threshold, scores)."""
  keep = ("options", "threshold", "psnr", "f1", "val_frames")
  out = {k: setting[k] for k in keep if k in setting}
  if "grid" in setting:
    out["grid_psnr"] = [[g["options"], g["psnr"]] for g in setting["grid"]]
  return out


def load_untrained(results: pathlib.Path) -> dict:
  """``budget -> record`` of every ``untrained-<budget>.json`` under ``RESULTS/mechanisms/``."""
  import json
  out = {}
  for path in sorted((pathlib.Path(results) / "mechanisms").glob("untrained-*.json")):
    r = json.loads(path.read_text())
    out[r["budget"]] = r
  return out


#: The learned rows each method without training is paired with.
PAIRED_WITH = ("full", OURS_S)


def untrained_lines(record: dict, learned: dict, budget: str) -> list[str]:
  """The report's section for one budget: each method's row and its paired differences.

  ``learned``: ``row -> [run record per seed]`` of the budget
  (:func:`~experiments.studies.mechanisms.records.load_runs`).
  """
  from experiments.studies.mechanisms.design import COLUMNS, ROWS
  from experiments.studies.mechanisms.records import _array
  from nlosjax import stats
  from nlosjax.evaluation import scores
  from nlosjax.evaluation.report import METHOD_LABELS
  from nlosjax.stats import format_interval as cell
  methods = record["methods"]
  lines = [f"### Methods without training, `{budget}` budget "
           "(`python -m experiments.studies.mechanisms --untrained`)", "",
           "Table 1's other rows on the same test frames: the classic methods on the input interpolated to"
           " the full grid, options and surface threshold tuned on the validation split"
           " (`nlosjax.evaluation.baselines.tune`); CSA on the sparse scan itself, its l1 weight and falloff"
           " chosen on validation frames (`nlosjax.evaluation.baselines.tune_csa`). Deterministic: one score"
           " per frame, paired with each seed of the learned row.", "",
           "| method | chosen on validation | " + " | ".join(h for h, _ in COLUMNS.values()) + " |",
           "|---|---|" + "---|" * len(COLUMNS)]
  for m, r in methods.items():
    seq = r["test"]["sequence"]
    summ = scores.summarize_scores({k: _array(r["test"]["scores"][k]) for k in COLUMNS}, seq)
    opts = r["settings"].get("options") or {}
    chosen = ", ".join(f"{k} {v}" for k, v in opts.items()) or "defaults"
    lines.append(f"| {METHOD_LABELS.get(m, m)} | {chosen}; threshold {r['settings'].get('threshold')} | "
                 + " | ".join(cell(summ[k], d) for k, (_, d) in COLUMNS.items()) + " |")
  pairs = []
  for row in PAIRED_WITH:
    rs = sorted(learned.get(row, []), key=lambda r: r["seed"])
    if not rs:
      continue
    for m, r in methods.items():
      same = all(list(x["test"]["sequence"]) == list(r["test"]["sequence"])
                 and list(x["test"]["frame"]) == list(r["test"]["frame"]) for x in rs)
      if not same:
        raise ValueError(f"budget {budget}: {m} was scored on other test frames than {row}")
      a = {k: np.stack([_array(x["test"]["scores"][k]) for x in rs]) for k in COLUMNS}
      b = {k: _array(r["test"]["scores"][k]) for k in COLUMNS}
      pairs.append((row, m, [x["seed"] for x in rs], scores.compare_scores(a, b, r["test"]["sequence"])))
  if pairs:
    lines += ["", "| difference | seeds | " + " | ".join(h for h, _ in COLUMNS.values()) + " |",
              "|---|---|" + "---|" * len(COLUMNS)]
    for row, m, seeds, diff in pairs:
      lines.append(f"| {row} - {m} | {', '.join(map(str, seeds))} | "
                   + " | ".join(cell(diff[k], d, True) for k, (_, d) in COLUMNS.items()) + " |")
    lines.append("")
    for row, m, _, diff in pairs:
      d = diff["psnr"]
      verdict = ("called: " + (ROWS[row][2] if d["mean"] > 0 else METHOD_LABELS.get(m, m)) + " is better"
                 if stats.excludes_zero(d) else "not called")
      lines.append(f"- **{row} - {m}** (`{budget}`, intensity PSNR): {d['mean']:+.2f} dB"
                   f" [{d['ci95'][0]:+.2f}, {d['ci95'][1]:+.2f}], {verdict}.")
  return lines + [""]

"""Mechanisms: does Ours use its SSMs and its neighbour frames, every model trained until learning stops?

    python -m benchmarks.mechanisms [--config cpu] [--budgets full tenth] [--rows full ours_s no_ssm]
                                    [--extra-rows] [--seeds 0 1 2] [--max-runs N] [--time-limit-s S]
                                    [--workdir runs/mechanisms] [--results benchmarks/results]
                                    [--report-only] [--probe RUN_DIR] [--tiny]
                                    [--config.section.key=value ...]

Rows (:data:`ROWS`, built with :func:`benchmarks.ablations.row_config`):
``full`` (Ours, three frames), ``ours_s`` (Ours-S, the middle frame alone) and
``no_ssm`` (Ours with every SSM replaced by the identity, all else equal);
``--extra-rows`` adds ``bidirectional`` (the temporal SSM runs both ways) and
``no_pf`` (no phasor-field loss). Each row is trained from seeds 0, 1 and 2 at
two photon budgets (:data:`BUDGETS`): the preset's (``full``) and one tenth of
its signal and ambient photons (``tenth``: the preset's ``data.photons`` and
``data.ambient`` divided by 10 and its own dataset file,
``<path stem>-exposure-0.1.h5``; for the cpu preset exactly the
``--config.data.photons=(5.0,200.0) --config.data.ambient=(5.0,50.0)
--config.data.path=runs/data/cpu-v3-exposure-0.1.h5`` of the low-photon tables).
A missing dataset is generated (``nlosjax.train.ensure_dataset``).

Every run trains until learning stops: the plateau rule of
:mod:`nlosjax.train.stopping` (:data:`STUDY_STOP`: validate every 50 steps,
stop when the best validation intensity PSNR has not risen by more than 0.05 dB
over the last 4 validations, at most 3000 steps, keep the best model on
validation; the cosine schedule spans the 3000 steps). ``--config.train.stop.KEY=V``
changes it. The model's surface threshold is then chosen on validation as in
the main job, and the test split is scored frame by frame.

Each finished run writes one small JSON file,
``RESULTS/mechanisms/<budget>/<row>-seed<k>.json`` (:func:`run_record`: config
essentials, machine and commit, steps taken and stop reason, the validation
curve, a subsampled training-loss curve, every per-frame test score
``protocol.evaluate`` returns for the model with sequence and frame indices).
A run whose JSON exists is skipped, so the command resumes anywhere (a run
killed mid-training resumes from its checkpoint in ``WORKDIR/<budget>/<row>-seed<k>/``)
and no run is trained twice; ``--budgets/--rows/--seeds``, ``--max-runs`` and
``--time-limit-s`` (no run starts after that many seconds; a started one
finishes) run a subset. Runs go seed by seed, so every row has seed 0 first.

After the full row's seed 0 of a budget, the SSM probe (:func:`probe_model`)
runs on that model and goes into its JSON: the validation PSNR with each SSM's
output replaced by its input at inference (no retraining), with all of them
replaced, and the mean SiLU gate of every block
(:mod:`nlosjax.models.probe`). ``--probe RUN_DIR`` probes any finished run
folder (``WORKDIR/<budget>/<row>-seed<k>``) and stores it in that run's JSON.

The report, ``RESULTS/mechanisms.md`` with ``RESULTS/mechanisms_curves.png``, is
rewritten from the JSON files alone after every invocation (``--report-only``:
nothing else): per row and budget the mean test intensity PSNR, SSIM, object
depth RMSE and object recall with 95 % bootstrap intervals over sequences and
seeds, the paired differences full - no_ssm and full - ours_s (same frames,
seeds present in both rows), the steps every run took, the runs still missing,
and the probe. ``--tiny`` runs the tiny config of ``tests/tiny_run.py`` (two
runs of a few steps, seconds each once compiled) into ``--workdir`` (default
``runs/mechanisms-tiny``) and ``--results`` (default ``runs/mechanisms-tiny/results``).
"""

from __future__ import annotations

import copy
import json
import math
import os
import pathlib
import sys
import time
from typing import Callable

import numpy as np

from benchmarks.ablations import ROWS as ABLATION_ROWS
from benchmarks.ablations import row_config
from nlosjax import stats
from nlosjax.stats import format_interval as cell

#: row -> (row of benchmarks.ablations.ROWS it is built from, variant trained, label).
ROWS = {
    "full": ("full", "ours", "Ours"),
    "ours_s": ("full", "ours_s", "Ours-S (middle frame only)"),
    "no_ssm": ("no_ssm", "ours", "Ours, every SSM the identity"),
    "bidirectional": ("bidirectional", "ours", "Ours, bidirectional T-Mamba"),
    "no_pf": ("no_pf", "ours", "Ours without L_pf"),
}
MAIN_ROWS = ("full", "ours_s", "no_ssm")
EXTRA_ROWS = ("bidirectional", "no_pf")
#: Photon budget -> divisor of the preset's ``data.photons`` and ``data.ambient``.
BUDGETS = {"full": 1, "tenth": 10}
#: Loss weights per budget over the config's ``train.loss``, chosen on validation. At a tenth
#: of the photons the preset's recipe (object_intensity 3) validated best at step 50 (15.80 dB)
#: and declined while the training loss fell; a screen of full/seed 0 runs to the plateau
#: (``--budgets tenth --rows full --seeds 0`` with ``--workdir``/``--results`` elsewhere) gave
#: the best validation PSNR 16.18 dB at step 350 with the depth weight alpha2 0.25, and 17.36 dB
#: at step 400 with object_intensity 1, whose curve rose from the start: the tenth budget trains
#: with object_intensity 1. The full budget keeps the preset's recipe.
BUDGET_LOSS = {"full": {}, "tenth": {"object_intensity": 1.0}}
SEEDS = (0, 1, 2)
#: The stopping rule of every run (``train.stop``; :class:`nlosjax.train.StopRule`).
STUDY_STOP = {"rule": "plateau", "every": 50, "patience": 4, "min_delta_db": 0.05, "max_steps": 3000}
#: ``--tiny``: a few steps, validating every 2.
TINY_STOP = {"rule": "plateau", "every": 2, "patience": 1, "min_delta_db": 0.05, "max_steps": 6}
TINY_DESIGN = {"budgets": ("full",), "rows": ("full", "no_ssm"), "seeds": (0,)}
#: The run whose model the SSM probe reads (per budget).
PROBE = ("full", 0)
#: Paired differences of the report: (a, b) -> a - b.
PAIRS = (("full", "no_ssm"), ("full", "ours_s"), ("full", "bidirectional"), ("full", "no_pf"))
#: Report columns: metric -> (header, digits).
COLUMNS = {"psnr": ("PSNR (dB) ↑", 2), "ssim": ("SSIM ↑", 3), "rmse_object": ("object depth RMSE (m) ↓", 3),
           "recall": ("object recall ↑", 3), "temporal_psnr": ("temporal PSNR (dB) ↑", 2)}
#: Verdict sentences: metric -> (name in the sentence, unit); each pair gets one per metric.
VERDICTS = {"psnr": ("intensity PSNR", "dB"),
            "temporal_psnr": ("temporal PSNR (frame-to-frame change against the truth's)", "dB")}
LOSS_POINTS = 100
REPORT = "mechanisms.md"
FIGURE = "mechanisms_curves.png"

assert all(v[0] in ABLATION_ROWS for v in ROWS.values())


# ------------------------------------------------------------------ configs
def budget_config(base: dict, budget: str, keep_loss=()) -> dict:
  """``base`` at photon budget ``budget``: photons and ambient divided by :data:`BUDGETS` ``[budget]``.

  The divided budget reads its own dataset file: ``<stem>-exposure-<1/divisor>.h5``
  beside the preset's (``runs/data/cpu-v3.h5`` -> ``runs/data/cpu-v3-exposure-0.1.h5``),
  and trains with :data:`BUDGET_LOSS` ``[budget]`` over the config's loss weights,
  except the weights named in ``keep_loss`` (those the user set on the command line:
  an explicit ``--config.train.loss.K=V`` wins over the budget's recipe).
  """
  if budget not in BUDGETS:
    raise ValueError(f"budget must be one of {tuple(BUDGETS)}, got {budget!r}")
  cfg = copy.deepcopy(base)
  divisor = BUDGETS[budget]
  if divisor != 1:
    data = cfg["data"]
    data["photons"] = tuple(float(p) / divisor for p in data["photons"])
    data["ambient"] = tuple(float(a) / divisor for a in data["ambient"])
    path = pathlib.PurePosixPath(data["path"])
    data["path"] = str(path.with_name(f"{path.stem}-exposure-{1 / divisor:g}{path.suffix}"))
  if BUDGET_LOSS[budget]:
    train = cfg.setdefault("train", {})
    budget_loss = {k: v for k, v in BUDGET_LOSS[budget].items() if k not in set(keep_loss)}
    train["loss"] = {**train.get("loss", {}), **budget_loss}
  return cfg


def study_stop(base: dict) -> dict:
  """The run's ``train.stop``: :data:`STUDY_STOP` with the config's own ``train.stop`` entries over it."""
  stop = {**STUDY_STOP, **base.get("train", {}).get("stop", {})}
  if stop["rule"] != "plateau":
    raise SystemExit(f"benchmarks.mechanisms trains to the validation plateau; train.stop.rule "
                     f"{stop['rule']!r} is not allowed")
  return stop


def run_config(base: dict, budget: str, row: str, seed: int, stop: dict, keep_loss=()) -> dict:
  """The config of one run: ``base`` at ``budget``, the row's changes, ``seed``, the stopping rule.

  ``keep_loss``: loss weights the user set, kept over :data:`BUDGET_LOSS` (:func:`budget_config`).
  """
  from nlosjax.train import StopRule
  ablation_row, variant, _ = ROWS[row]
  cfg = row_config(budget_config(base, budget, keep_loss), ablation_row, StopRule(**stop).max_steps, seed)
  cfg["train"]["stop"] = dict(stop)
  cfg["train"]["variants"] = (variant,)
  return cfg


def essentials(cfg: dict) -> dict:
  """The parts of a run config its numbers depend on (JSON-ready)."""
  data_keys = ("path", "grid", "num_bins", "bin_width", "wall_size", "input_stride", "frames",
               "num_sequences", "seed", "efficiency", "photons", "ambient", "dark_counts", "renderer")
  tr = cfg["train"]
  return {"data": {k: cfg["data"][k] for k in data_keys if k in cfg["data"]},
          "model": dict(cfg.get("model", {})),
          "train": {k: tr.get(k) for k in ("seed", "batch_size", "eval_batch_size", "optim", "loss", "stop")}}


def check_same_data(results: pathlib.Path, budget: str, cfg: dict) -> None:
  """Refuse a run whose data or recipe differ from those of the budget's finished runs.

  The study pairs runs sequence by sequence and compares rows trained the same way.
  Compares :func:`essentials` ``["data"]`` with every run of the budget and, when
  ``cfg["_study_row"]`` names the run's row, ``["train"]`` (all but the seed) with
  that row's runs, on the keys both records hold (a record written before a key was recorded is not held to
  it). A preset whose data or recipe change starts a study of its own: ``--results``
  elsewhere (or the budget's old records move away).
  """
  def flat(e, recipe: bool):
    parts = ("data", "train") if recipe else ("data",)   # a row's own changes (no_pf's loss) differ
    return {f"{part}.{k}": v for part in parts for k, v in _shared(e, part).items()}

  mine = json.loads(json.dumps(essentials(cfg)))
  row_of = cfg.get("_study_row")
  for (b, row, seed), r in sorted(load_runs(results).items()):
    if b != budget:
      continue
    same_row = row_of is not None and row == row_of
    want, have = flat(mine, same_row), flat(r["config"], same_row)
    differ = _differing(want, have)
    if differ:
      what = ", ".join(f"{k}: {have[k]!r} there, {want[k]!r} now" for k in differ)
      raise SystemExit(f"mechanisms: the data or recipe of this run differ from those of {budget}/{row}-seed{seed}"
                       f" in {results / 'mechanisms'} ({what});"
                       " the study pairs runs on the same sequences: keep the preset's data or give --results"
                       " another folder")


def _shared(config: dict, part: str) -> dict:
  """``config[part]`` as runs that are compared must share it: ``"train"`` without its seed."""
  return {k: v for k, v in config.get(part, {}).items() if not (part == "train" and k == "seed")}


def _differing(a: dict, b: dict) -> list[str]:
  """The keys both dicts hold with different values, sorted (a key one lacks is not compared)."""
  return sorted(k for k in set(a) & set(b) if a[k] != b[k])


def check_consistent(runs: dict) -> None:
  """Refuse records that :func:`check_same_data` would have refused to train beside each other.

  At report time, for JSON files copied in from another machine or folder: within a
  budget every record's ``config["data"]`` must agree, and within a row its ``config["train"]``
  (all but the seed), on the keys both hold. Raises ``ValueError`` naming the two runs.
  """
  first: dict = {}
  for (b, row, seed), r in sorted(runs.items()):
    for scope, part, key in (("budget", "data", b), ("row", "train", (b, row))):
      here = _shared(r["config"], part)
      if key not in first:
        first[key] = (f"{b}/{row}-seed{seed}", here)
        continue
      name, there = first[key]
      differ = _differing(here, there)
      if differ:
        raise ValueError(f"mechanisms: {b}/{row}-seed{seed} and {name} share a {scope} but differ in "
                         f"{part}: " + ", ".join(f"{k} ({there[k]!r} against {here[k]!r})" for k in differ))


def run_json(results: pathlib.Path, budget: str, row: str, seed: int) -> pathlib.Path:
  return pathlib.Path(results) / "mechanisms" / budget / f"{row}-seed{seed}.json"


def run_dir(workdir: pathlib.Path, budget: str, row: str, seed: int) -> pathlib.Path:
  return pathlib.Path(workdir) / budget / f"{row}-seed{seed}"


# --------------------------------------------------------------- provenance
_CODE_AT_START: dict = {}


def code_at_start() -> dict:
  """The commit and code digest of this process's code, read once, before its first run.

  A study runs for hours: read at the end of a run, ``git`` and the files on disk may
  already show a later commit or someone's uncommitted edits that this process never
  loaded. :func:`main` calls this first; :func:`machine` reports what it read then.
  """
  if not _CODE_AT_START:
    from experiments import provenance as P
    _CODE_AT_START.update(commit=P.git_commit(), code_digest=P.code_digest(P.code_modules(P.command_roots())))
  return dict(_CODE_AT_START)


def machine() -> dict:
  """Where and from which code a run's numbers came (:func:`experiments.provenance.machine_record`;
  the commit and code digest as at the start of the process)."""
  from experiments import provenance as P
  return {**P.machine_record(), **code_at_start()}


# --------------------------------------------------------------- JSON I/O
def _plain(x):
  """JSON-ready copy: tuples -> lists, NumPy -> Python, NaN/inf -> None (strict JSON)."""
  if isinstance(x, dict):
    return {str(k): _plain(v) for k, v in x.items()}
  if isinstance(x, (list, tuple)):
    return [_plain(v) for v in x]
  if isinstance(x, np.ndarray):
    return _plain(x.tolist())
  if isinstance(x, (np.floating, float)):
    return float(x) if math.isfinite(float(x)) else None
  if isinstance(x, np.integer):
    return int(x)
  return x


def write_json(path: pathlib.Path, obj) -> None:
  """Write ``obj`` as strict JSON, atomically (a temporary file renamed over ``path``)."""
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = path.with_name(path.name + ".tmp")
  tmp.write_text(json.dumps(_plain(obj), indent=1, allow_nan=False) + "\n")
  os.replace(tmp, path)


def load_runs(results: pathlib.Path) -> dict:
  """``(budget, row, seed) -> run record`` of every JSON file under ``RESULTS/mechanisms/``."""
  runs = {}
  for path in sorted((pathlib.Path(results) / "mechanisms").glob("*/*.json")):
    r = json.loads(path.read_text())
    runs[(r["budget"], r["row"], int(r["seed"]))] = r
  return runs


def _array(values) -> np.ndarray:
  """A JSON list (None = NaN) as float64."""
  return np.asarray([np.nan if v is None else v for v in values], np.float64)


# --------------------------------------------------------------- one run
def _subsample(rows: list[dict], n: int = LOSS_POINTS) -> list[dict]:
  """At most about ``n`` evenly spaced rows of a training log (always the last)."""
  if not rows:
    return []
  every = max(1, math.ceil(len(rows) / n))
  keep = rows[::every]
  if keep[-1] is not rows[-1]:
    keep.append(rows[-1])
  return [{k: r[k] for k in ("step", "loss", "time_s") if k in r} for r in keep]


def test_frames(cfg: dict, data_path) -> tuple[np.ndarray, np.ndarray]:
  """``(sequence [N], frame [N])`` of the test split's examples in evaluation order (middle frame index)."""
  from nlosjax.train import make_loader
  bs = int(cfg["train"].get("eval_batch_size", cfg["train"]["batch_size"]))
  loader = make_loader(cfg, data_path, "test", batch_size=bs, shuffle=False, seed=0)
  try:
    batches = [loader.batch(i) for i in range(len(loader))]
  finally:
    loader.close()
  return (np.concatenate([b["sequence"] for b in batches]).astype(int),
          np.concatenate([b["frame"] for b in batches]).astype(int))


def train_and_score(cfg: dict, folder: pathlib.Path, variant: str, log: Callable[[str], None]):
  """Train (or resume, or reload) one run to its plateau; returns ``(mcfg, params, test record)``."""
  from nlosjax import train as T
  from nlosjax.evaluation import protocol
  data_path = pathlib.Path(cfg["data"]["path"])
  validate = protocol.validation_psnr(cfg, data_path)
  mcfg, state = T.train_model(cfg, data_path, folder, variant, folder="model", validate=validate,
                              log=log)
  params = T.to_host(state.params)
  t0 = time.perf_counter()
  tuned = protocol.tune_model_thresholds(cfg, data_path, {variant: [(mcfg, params)]}, log=log)[variant]
  ev = protocol.evaluate(cfg, data_path, {variant: [(mcfg, params)]}, split="test", methods=(),
                         model_thresholds={variant: tuned["threshold"]}, log=log)
  sequence, frame = test_frames(cfg, data_path)
  if not np.array_equal(sequence, np.asarray(ev["sequence"])):
    raise RuntimeError("the test loader's sequence order differs from protocol.evaluate's")
  test = {"split": "test", "data": str(data_path), "sequence": sequence, "frame": frame,
          "surface_threshold": tuned["threshold"], "threshold_val_f1": tuned["f1"],
          "scores": {k: np.asarray(v)[0] for k, v in ev["scores"][variant].items()},
          "eval_s": round(time.perf_counter() - t0, 1)}
  return mcfg, params, test


def run_record(cfg: dict, budget: str, row: str, seed: int, folder: pathlib.Path, test: dict) -> dict:
  """The JSON record of one finished run (module docstring)."""
  from nlosjax import train as T
  model = folder / "model"
  curve = T.read_curve(model)
  selection = T.read_selection(model) or {}
  return {"budget": budget, "row": row, "seed": seed, "variant": ROWS[row][1], "label": ROWS[row][2],
          "config": essentials(cfg), "machine": machine(),
          "steps_taken": curve["steps_taken"], "stop_reason": curve["stop_reason"],
          "best_step": curve["best_step"], "best_val_psnr": curve["best_val_psnr"],
          "train_wall_s": curve["curve"][-1]["time_s"] if curve["curve"] else None,
          "validation_curve": curve["curve"], "selection_step": selection.get("step"),
          "loss_curve": _subsample(T.read_metrics(model / "metrics.jsonl")), "test": test}


def run_one(base: dict, budget: str, row: str, seed: int, stop: dict, workdir: pathlib.Path,
            results: pathlib.Path, log: Callable[[str], None] = print, keep_loss=()) -> dict:
  """Train, score and (for :data:`PROBE`) probe one run; writes and returns its JSON record."""
  from nlosjax import train as T
  cfg = run_config(base, budget, row, seed, stop, keep_loss)
  data_path = pathlib.Path(cfg["data"]["path"])
  T.ensure_dataset(cfg, data_path, log=log)
  folder = run_dir(workdir, budget, row, seed)
  folder.mkdir(parents=True, exist_ok=True)
  write_json(folder / "run.json", {"budget": budget, "row": row, "seed": seed, "config": cfg})
  mcfg, params, test = train_and_score(cfg, folder, ROWS[row][1], log)
  record = run_record(cfg, budget, row, seed, folder, test)
  if (row, seed) == PROBE:
    record["probe"] = probe_model(cfg, data_path, mcfg, params, log=log)
  write_json(run_json(results, budget, row, seed), record)
  return record


# --------------------------------------------------------------- the probe
def probe_model(cfg: dict, data_path, mcfg, params, log: Callable[[str], None] = print) -> dict:
  """Validation PSNR with each SSM bypassed (its output replaced by its input) and the mean gates.

  Scored as :func:`nlosjax.evaluation.protocol.validation_psnr` scores a
  checkpoint (mean over the validation frames of the clamped intensity's PSNR).
  ``intact_psnr`` is computed by that very function, so it equals the run's
  best validation PSNR bit for bit. The bypassed passes run the probe's own
  program (:func:`nlosjax.models.probe.probed_apply`, a different XLA program,
  which may round differently in the last place, and which a process may have
  compiled under other XLA options than the validation forward it cached);
  each ``drop_db`` is measured against that program's pass with nothing
  bypassed (``probe_intact_psnr``), so an SSM the network ignores drops by
  exactly 0.

  Returns:
    ``{"split": "val", "n_frames", "intact_psnr", "probe_intact_psnr",
    "all_bypassed_psnr", "all_drop_db", "modules": [{"module", "block", "psnr",
    "drop_db", "gate_mean"}], "gates": {block: mean SiLU(z)}, "mixing": learned
    mixing weights}``; ``drop_db`` is intact minus bypassed (positive: the model
    needs that SSM).
  """
  import jax.numpy as jnp
  from tqdm import tqdm

  from nlosjax import metrics
  from nlosjax.evaluation import protocol
  from nlosjax.models import probe as P
  from nlosjax.train import select_frames
  ssms, blocks = P.ssm_paths(params), P.gate_paths(params)
  fn = P.probed_apply(mcfg, ssms, blocks)
  bs = int(cfg["train"].get("eval_batch_size", cfg["train"]["batch_size"]))
  data = protocol.load_split(cfg, data_path, "val", batch_size=bs)
  try:
    inputs = [select_frames(data["loader"].batch(i)["measurement"], mcfg.frames)
              for i in range(len(data["loader"]))]
  finally:
    data["loader"].close()
  masks = [("none", np.zeros(len(ssms), bool))]
  masks += [(p, np.arange(len(ssms)) == i) for i, p in enumerate(ssms)]
  masks += [("all", np.ones(len(ssms), bool))]
  psnr, gate_sums = {}, {}
  for name, mask in tqdm(masks, desc="SSM probe", unit="pass"):
    inten = []
    for x in inputs:
      out, gates = fn(params, jnp.asarray(x), jnp.asarray(mask))
      inten.append(np.clip(np.asarray(out["intensity"]), 0.0, 1.0))
      if name == "none":
        for block, v in gates.items():
          gate_sums[block] = gate_sums.get(block, 0.0) + np.asarray(v, np.float64)
    psnr[name] = float(np.mean(np.asarray(metrics.psnr(np.concatenate(inten), data["intensity"]))))
  gates = {b: float(s[0] / s[1]) for b, s in gate_sums.items()}
  modules = []
  for p in ssms:
    block = next((b for b in blocks if p.startswith(b + "/")), None)
    modules.append({"module": p, "block": block, "psnr": psnr[p], "drop_db": psnr["none"] - psnr[p],
                    "gate_mean": gates.get(block)})
  log(f"[probe] intact {psnr['none']:.2f} dB; every SSM bypassed {psnr['all']:.2f} dB")
  intact = protocol.validation_psnr(cfg, data_path)(mcfg, params)
  return {"split": "val", "n_frames": int(len(data["intensity"])), "intact_psnr": intact,
          "probe_intact_psnr": psnr["none"],
          "all_bypassed_psnr": psnr["all"], "all_drop_db": psnr["none"] - psnr["all"],
          "modules": modules, "gates": gates, "mixing": P.mixing_weights(params)}


def probe_run_dir(folder: pathlib.Path, results: pathlib.Path, log: Callable[[str], None] = print) -> dict:
  """``--probe RUN_DIR``: probe a finished run's best model; stored in its JSON when that exists."""
  from nlosjax import train as T
  from nlosjax.evaluation import protocol
  folder = pathlib.Path(folder)
  meta_path = folder / "run.json"
  if not meta_path.exists():
    raise SystemExit(f"--probe: {folder} is not a run folder of this benchmark (no run.json)")
  meta = json.loads(meta_path.read_text())
  selection = T.read_selection(folder / "model") or {}
  if "stop_reason" not in selection:
    raise SystemExit(f"--probe: the run in {folder} has not finished (no stop reason in "
                     "model/selection.json); run the study first")
  cfg = meta["config"]
  data_path = pathlib.Path(cfg["data"]["path"])
  variant = ROWS[meta["row"]][1]
  mcfg, state = T.train_model(cfg, data_path, folder, variant, folder="model",
                              validate=protocol.validation_psnr(cfg, data_path), log=log)
  result = probe_model(cfg, data_path, mcfg, T.to_host(state.params), log=log)
  path = run_json(results, meta["budget"], meta["row"], int(meta["seed"]))
  if path.exists():
    record = json.loads(path.read_text())
    record["probe"] = result
    write_json(path, record)
    log(f"[probe] written into {path}")
  return result


# --------------------------------------------------------------- the report
def _stack(runs: list[dict], metric: str) -> np.ndarray:
  """``[K, N]`` test scores of ``metric`` over a row's runs (seeds)."""
  return np.stack([_array(r["test"]["scores"][metric]) for r in runs])


def _same_frames(runs: list[dict]) -> bool:
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
    if present and not _same_frames(present):
      raise ValueError(f"budget {budget}: the runs were scored on different test frames")
    entry = {"rows": {}, "pairs": []}
    for row, rs in by_row.items():
      seq = rs[0]["test"]["sequence"]
      summary = scores.summarize_scores({m: _stack(rs, m) for m in COLUMNS}, seq)
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
        pair["diff"] = scores.compare_scores({m: _stack([ra[s] for s in common], m) for m in COLUMNS},
                                             {m: _stack([rb[s] for s in common], m) for m in COLUMNS}, seq)
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


def report(runs: dict, design: dict, command: str) -> str:
  """The Markdown report of the runs present, against the ``design`` (budgets, rows, seeds)."""
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
    key = f"{m['cpu']}, {m['cores']} cores, commit {m['commit']}, code `{m['code_digest']}`"
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
    lines += _probe_lines(runs, budget)
    lines.append("")
  lines += [f"Validation curves: `{FIGURE}` (one panel per budget; a dot marks each run's best step).", ""]
  return "\n".join(lines)


def write_report(results: pathlib.Path, design: dict, command: str) -> str:
  """Rewrite ``RESULTS/mechanisms.md`` and ``RESULTS/mechanisms_curves.png`` from the JSON files alone."""
  results = pathlib.Path(results)
  runs = load_runs(results)
  check_consistent(runs)
  text = report(runs, design, command)
  results.mkdir(parents=True, exist_ok=True)
  (results / REPORT).write_text(text)
  rows = list(design["rows"]) + [r for r in ROWS if r not in design["rows"] and any(k[1] == r for k in runs)]
  plot_curves(runs, list(design["budgets"]), rows, results / FIGURE)
  return text


# --------------------------------------------------------------- the command
def tiny_base(workdir: pathlib.Path) -> dict:
  """The tiny config of ``tests/tiny_run.py`` with its data under ``workdir``."""
  try:
    from tests.tiny_run import tiny_config
  except ImportError as e:
    raise SystemExit(f"--tiny needs the repository's tests/ package on the path ({e}); run from the "
                     "repository root") from None
  return tiny_config(pathlib.Path(workdir) / "data" / "tiny.h5", stop=dict(TINY_STOP))


def main(argv=None) -> int:
  from experiments.cli import config_parser, parse_config
  code_at_start()                          # before any run: the code this process loads
  parser = config_parser(__doc__.split("\n\n")[0])
  parser.add_argument("--budgets", nargs="+", choices=list(BUDGETS), default=None,
                      help="photon budgets to run (default: all; --tiny: full)")
  parser.add_argument("--rows", nargs="+", choices=list(ROWS), default=None,
                      help=f"rows to run (default: {' '.join(MAIN_ROWS)}, plus --extra-rows)")
  parser.add_argument("--extra-rows", action="store_true", help=f"also run {' and '.join(EXTRA_ROWS)}")
  parser.add_argument("--seeds", nargs="+", type=int, default=None, help="training seeds (default: 0 1 2)")
  parser.add_argument("--max-runs", type=int, default=None, help="train at most this many runs")
  parser.add_argument("--time-limit-s", type=float, default=None,
                      help="start no run after this many seconds (a started run finishes)")
  parser.add_argument("--workdir", default=None, help="run folders (default: runs/mechanisms)")
  parser.add_argument("--results", default=None, help="JSON files and report (default: benchmarks/results)")
  parser.add_argument("--report-only", action="store_true", help="only rewrite the report from the JSON files")
  parser.add_argument("--probe", metavar="RUN_DIR", default=None,
                      help="probe the SSMs of a finished run folder, store it in its JSON, rewrite the report")
  parser.add_argument("--tiny", action="store_true", help="the tiny config of tests/tiny_run.py (a smoke run)")
  argv = sys.argv[1:] if argv is None else list(argv)
  args, base, overrides = parse_config(parser, argv)
  from experiments.cli import override_key
  keep_loss = tuple(k[2] for k, _ in map(override_key, overrides) if k[:2] == ("train", "loss") and len(k) == 3)
  command = "python -m benchmarks.mechanisms " + " ".join(argv)
  workdir = pathlib.Path(args.workdir or ("runs/mechanisms-tiny" if args.tiny else "runs/mechanisms"))
  results = pathlib.Path(args.results or (workdir / "results" if args.tiny else "benchmarks/results"))
  if args.tiny:
    base = tiny_base(workdir)
    design = dict(TINY_DESIGN)
  else:
    from nlosjax.train import with_defaults
    stop = study_stop(base)
    base = with_defaults(base)
    base["train"]["stop"] = stop
    design = {"budgets": tuple(BUDGETS), "rows": MAIN_ROWS, "seeds": SEEDS}
  if args.extra_rows:
    design["rows"] = tuple(design["rows"]) + EXTRA_ROWS
  budgets = tuple(args.budgets or design["budgets"])
  rows = tuple(args.rows or design["rows"])
  seeds = tuple(args.seeds if args.seeds is not None else design["seeds"])
  if args.probe:
    probe_run_dir(pathlib.Path(args.probe), results)
  elif not args.report_only:
    from tqdm import tqdm
    stop = dict(base["train"]["stop"])
    jobs = [(b, r, s) for s in seeds for b in budgets for r in rows]
    todo = [j for j in jobs if not run_json(results, *j).exists()]
    print(f"mechanisms: {len(jobs) - len(todo)} of {len(jobs)} runs already have their JSON "
          f"in {results / 'mechanisms'}; {len(todo)} to train")
    for budget, row, seed in todo:
      check_same_data(results, budget,
                      {**run_config(base, budget, row, seed, stop, keep_loss), "_study_row": row})
    t0, trained = time.perf_counter(), 0
    for budget, row, seed in tqdm(todo, desc="mechanisms", unit="run"):
      if args.max_runs is not None and trained >= args.max_runs:
        tqdm.write(f"mechanisms: --max-runs {args.max_runs} reached")
        break
      if args.time_limit_s is not None and time.perf_counter() - t0 > args.time_limit_s:
        tqdm.write(f"mechanisms: --time-limit-s {args.time_limit_s:g} passed; no new run starts")
        break
      rec = run_one(base, budget, row, seed, stop, workdir, results, log=tqdm.write, keep_loss=keep_loss)
      trained += 1
      tqdm.write(f"mechanisms: {budget}/{row}-seed{seed}: {rec['steps_taken']} steps "
                 f"({rec['stop_reason']}), best step {rec['best_step']}, test PSNR "
                 f"{np.nanmean(_array(rec['test']['scores']['psnr'])):.2f} dB")
  text = write_report(results, design, command.strip())
  print(text)
  return 0


if __name__ == "__main__":
  sys.exit(main())

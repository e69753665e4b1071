"""The study's design: rows, photon budgets, seeds, stopping rule, and each run's config and paths."""

from __future__ import annotations

import copy
import json
import pathlib

from experiments import configs
from experiments.studies.ablations import ROWS as ABLATION_ROWS
from experiments.studies.ablations import row_config
from experiments.studies.mechanisms.records import load_runs
from nlosjax.variants import IK, LFE, OURS, OURS_S, USM

#: row -> (row of experiments.studies.ablations.ROWS it is built from, variant trained, label).
ROWS = {
    "full": ("full", OURS, "Ours"),
    OURS_S: ("full", OURS_S, "Ours-S (middle frame only)"),
    "no_ssm": ("no_ssm", OURS, "Ours, every SSM the identity"),
    "bidirectional": ("bidirectional", OURS, "Ours, bidirectional T-Mamba"),
    "no_pf": ("no_pf", OURS, "Ours without L_pf"),
    USM: ("full", USM, "USM"),
    LFE: ("full", LFE, "LFE"),
    IK: ("full", IK, "I-K (approximation)"),
}
MAIN_ROWS = ("full", OURS_S, "no_ssm")
EXTRA_ROWS = ("bidirectional", "no_pf")
#: Rows beside the study for Table 1 at the plateau (``--rows usm lfe ik``): the learned baselines
#: USM, LFE and I-K (:mod:`nlosjax.models.ik`, an approximation from its public summary) on the
#: same data, under the same stopping rule and recipe as Ours (``usm.recipe = "ours"``; LFE and
#: I-K always train with Ours' recipe); the report pairs each with Ours and Ours-S seed by seed.
TABLE1_ROWS = (USM, LFE, IK)
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
#: The optimiser entries of every run over the config's ``train.optim``: the peak learning rate
#: (AdamW, cosine over ``max_steps``) the study's runs were trained with. It was the cpu preset's
#: until the preset's main job took the short schedule of ``experiments/studies/time_to_plateau.py``.
STUDY_OPTIM = {"learning_rate": 1e-3}
#: The model and loss the study's runs were trained with: the cpu preset's before it took the recipe
#: for the hidden objects (experiments/studies/objects), :data:`experiments.configs.WHOLE_IMAGE_RECIPE`.
#: Key path -> value (None: the key unset, the library's default). :func:`study_recipe` puts them back
#: where a config took the preset's new ones.
STUDY_RECIPE = configs.WHOLE_IMAGE_RECIPE
#: ``--tiny``: a few steps, validating every 2.
TINY_STOP = {"rule": "plateau", "every": 2, "patience": 1, "min_delta_db": 0.05, "max_steps": 6}
TINY_DESIGN = {"budgets": ("full",), "rows": ("full", "no_ssm"), "seeds": (0,)}
#: The run whose model the SSM probe reads (per budget).
PROBE = ("full", 0)
#: Paired differences of the report: (a, b) -> a - b.
PAIRS = (("full", "no_ssm"), ("full", OURS_S), ("full", "bidirectional"), ("full", "no_pf"),
         ("full", USM), (OURS_S, USM), ("full", LFE), (OURS_S, LFE), ("full", IK), (OURS_S, IK))
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
    raise SystemExit(f"experiments.studies.mechanisms trains to the validation plateau; train.stop.rule "
                     f"{stop['rule']!r} is not allowed")
  return stop


def study_recipe(base: dict, overrides=()) -> dict:
  """``base`` with :data:`STUDY_RECIPE` where it holds the ``cpu`` preset's own value of a key and the
  command line (``overrides``) did not set it: a study built on the ``cpu`` preset keeps training the
  recipe its committed runs were trained with, and another preset (``real``, ``paper``) is unchanged."""
  from experiments.cli import override_key

  get = configs.get_path
  cpu, mine, out = configs.get_config("cpu"), set(map(override_key, overrides)), copy.deepcopy(base)
  for path, value in STUDY_RECIPE.items():
    if path in mine or get(out, path) is configs.MISSING or get(out, path) != get(cpu, path):
      continue
    if value is None:
      configs.del_path(out, path)
    else:
      configs.set_path(out, path, value)
  return out


def study_optim(base: dict, overrides=()) -> dict:
  """The runs' ``train.optim``: the config's, with :data:`STUDY_OPTIM` over it except the keys
  set on the command line (``overrides``: the ``--config.train.optim.KEY=VALUE`` arguments)."""
  from experiments.cli import override_key
  mine = {k[2] for k in map(override_key, overrides) if k[:2] == ("train", "optim") and len(k) == 3}
  return {**base.get("train", {}).get("optim", {}), **{k: v for k, v in STUDY_OPTIM.items() if k not in mine}}


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
  out = {"data": {k: cfg["data"][k] for k in data_keys if k in cfg["data"]},
         "model": dict(cfg.get("model", {})),
         "train": {k: tr.get(k) for k in ("seed", "batch_size", "eval_batch_size", "optim", "loss", "stop")}}
  for baseline in (USM, LFE, IK):       # a learned baseline's widths and recipe
    if baseline in tuple(tr.get("variants", ())):
      out[baseline] = dict(cfg.get(baseline, {}))
  return out


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


def state_dir(state: pathlib.Path, budget: str, row: str, seed: int) -> pathlib.Path:
  """A run's committed resumable state (``--state``): ``STATE/<budget>/<row>-seed<k>``."""
  return pathlib.Path(state) / budget / f"{row}-seed{seed}"


def run_dir(workdir: pathlib.Path, budget: str, row: str, seed: int) -> pathlib.Path:
  return pathlib.Path(workdir) / budget / f"{row}-seed{seed}"

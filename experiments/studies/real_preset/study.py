"""The real preset study's runs, its runner and its status (package docstring)."""

from __future__ import annotations

import copy
import dataclasses
import json
import pathlib
import time
from typing import Callable

from experiments import configs, store
from nlosjax.variants import OURS, OURS_S

STUDY = "real_preset"
#: Where the committed run states live: ``state/<run>/<model folder>/``.
STATE_DIR = pathlib.Path(__file__).resolve().parent / "state"


@dataclasses.dataclass(frozen=True)
class Run:
  """One long run: a candidate's data config (a preset name or a ``.py`` file) and a variant.

  ``learning_rate`` and ``max_steps``, when set, replace the config's peak learning rate and
  its plateau rule's ``max_steps`` (the cosine schedule's horizon): a schedule probe of the
  same candidate, never a candidate itself (:func:`candidate_workdir` skips it).
  """

  name: str
  config: str
  variant: str
  seed: int = 0
  learning_rate: float | None = None
  max_steps: int | None = None
  recipe: str | None = None

  @property
  def schedule_probe(self) -> bool:
    return self.learning_rate is not None or self.max_steps is not None

  @property
  def probe(self) -> bool:
    """A run of another schedule or recipe than its candidate's: never a candidate's model itself."""
    return self.schedule_probe or self.recipe is not None


#: ``Run.recipe`` -> the keys it takes from the ``cpu`` preset: ``"objects"`` is the recipe the
#: ``cpu`` preset trains for the hidden objects (experiments/studies/objects/results/objects.md):
#: object-balanced losses, no object term, the plateau rule and checkpoint on the validation
#: object-balanced PSNR, width 16. Its keys are those of the whole-image recipe it replaces
#: (:data:`experiments.configs.WHOLE_IMAGE_RECIPE`, the one every real weight was trained with).
RECIPES = {"objects": tuple(configs.WHOLE_IMAGE_RECIPE)}


def apply_recipe(config: dict, recipe: str) -> dict:
  """``config`` (a run's config dict) with the :data:`RECIPES` keys of ``recipe`` set to the ``cpu``
  preset's values; every other key as it was. Raises ValueError for an unknown recipe."""
  if recipe not in RECIPES:
    raise ValueError(f"unknown recipe {recipe!r}; choose one of {sorted(RECIPES)}")
  source = configs.get_config("cpu")
  out = copy.deepcopy(config)
  for path in RECIPES[recipe]:
    value = configs.get_path(source, path)
    if value is configs.MISSING:
      raise KeyError(path)
    configs.set_path(out, path, value)
  return out


#: The runs, in the order they are trained. ``real_v5``: the candidate whose simulated inputs
#: a held-out classifier tells from the measured scans' 57 % of the time
#: (experiments/studies/realism/results/realism_v5.md; v4: 92 %, the shipped weights' data: 97 %).
RUNS = (
    Run("v5-ours_s", "experiments/configs/real_v5.py", OURS_S),
    Run("v5-ours", "experiments/configs/real_v5.py", OURS),
    # A second seed of the candidate preset_choice_real.md preferred for Ours-S, so its lead
    # over the shipped weights can carry an interval over seeds too.
    Run("v5-ours_s-seed1", "experiments/configs/real_v5.py", OURS_S, seed=1),
    # The cpu preset's short schedule (experiments/studies/time_to_plateau.py, SHORT: peak 3e-3, cosine
    # over 400 steps), unchanged, on the v5 candidate: does it reach the plateau sooner here too?
    Run("v5-ours_s-short", "experiments/configs/real_v5.py", OURS_S, learning_rate=3e-3, max_steps=400),
    Run("v5-ours-short", "experiments/configs/real_v5.py", OURS, learning_rate=3e-3, max_steps=400),
    # The cpu preset's recipe for the hidden objects (RECIPES["objects"]) on the v5 candidate, under the
    # preset's own plateau rule: does it win on validation here too, and does it stop costing on the
    # measured scans?
    Run("v5-ours_s-objects", "experiments/configs/real_v5.py", OURS_S, recipe="objects"),
    Run("v5-ours-objects", "experiments/configs/real_v5.py", OURS, recipe="objects"),
)


def run_config(run: Run) -> dict:
  """The run's training config: its candidate's, with the dataset in the store and the run's seed."""
  from experiments.cli import load_config
  config = load_config(run.config)
  config["data"]["path"] = str(store.data_path(pathlib.Path(config["data"]["path"]).name))
  config["train"] = {**config["train"], "seed": run.seed, "variants": (run.variant,)}
  if run.learning_rate is not None:
    config["train"]["optim"] = {**config["train"]["optim"], "learning_rate": run.learning_rate}
  if run.max_steps is not None:
    config["train"]["stop"] = {**config["train"]["stop"], "max_steps": run.max_steps}
  if run.recipe is not None:
    config = apply_recipe(config, run.recipe)
  return config


def workdir(run: Run) -> pathlib.Path:
  return store.run_path(STUDY, run.name)


def state_folder(run: Run) -> pathlib.Path:
  """The run's committed export root (its model folder inside: ``<this>/<variant>``)."""
  return STATE_DIR / run.name


def status(run: Run) -> dict:
  """What the committed state says of ``run``: steps, best, rate, hours left (module docstring)."""
  from nlosjax.train import StopRule
  from nlosjax.train.run_state import read_meta
  config = run_config(run)
  rule = StopRule.from_config(config["train"]["stop"])
  folder = state_folder(run) / run.variant
  meta = read_meta(folder)
  out = {"run": run.name, "config": run.config, "variant": run.variant, "step": 0, "done": False,
         "best_step": None, "best_val_psnr": None, "s_per_step": None, "hours_left": None,
         "workdir": str(workdir(run)), "state": str(folder)}
  if meta is None:
    out["steps_left"] = (rule.every * (rule.patience + 1), rule.max_steps)
    return out
  out["step"] = int(meta["step"])
  curve_path = folder / "validation_curve.json"
  curve = json.loads(curve_path.read_text()) if curve_path.exists() else None
  if curve and curve["curve"]:
    points = curve["curve"]
    out["best_step"], out["best_val_psnr"] = curve["best_step"], curve["best_val_psnr"]
    out["done"] = curve.get("stop_reason") is not None
    out["s_per_step"] = points[-1]["time_s"] / max(points[-1]["step"], 1)
    # With no further gain the rule stops once ``patience`` validations follow the best.
    best_index = max(i for i, p in enumerate(points) if p["step"] == curve["best_step"])
    fewest = 0 if out["done"] else rule.every * max(best_index + 1 + rule.patience - len(points), 0)
    most = 0 if out["done"] else rule.max_steps - out["step"]
    out["steps_left"] = (min(fewest, most), most)
    out["hours_left"] = tuple(round(s * out["s_per_step"] / 3600, 2) for s in out["steps_left"])
  else:
    out["steps_left"] = (rule.every * (rule.patience + 1) - out["step"], rule.max_steps - out["step"])
  return out


def format_status(rows: list[dict]) -> str:
  """The status table (Markdown)."""
  lines = ["| run | variant | step | best val PSNR (step) | s / step | steps left | hours left | state |",
           "|---|---|---|---|---|---|---|---|"]
  total = [0.0, 0.0]
  for r in rows:
    best = "—" if r["best_val_psnr"] is None else f"{r['best_val_psnr']:.2f} dB ({r['best_step']})"
    rate = "—" if r["s_per_step"] is None else f"{r['s_per_step']:.2f}"
    left = "done" if r["done"] else f"{r['steps_left'][0]}–{r['steps_left'][1]}"
    hours = "0" if r["done"] else ("not measured" if r["hours_left"] is None
                                   else f"{r['hours_left'][0]:.1f}–{r['hours_left'][1]:.1f}")
    if r["hours_left"] is not None:
      total = [total[0] + r["hours_left"][0], total[1] + r["hours_left"][1]]
    lines.append(f"| {r['run']} | {r['variant']} | {r['step']} | {best} | {rate} | {left} | {hours} | "
                 f"`{pathlib.Path(r['state']).relative_to(STATE_DIR.parents[3])}` |")
  lines.append("")
  lines.append(f"Hours left over the measured runs: {total[0]:.1f}–{total[1]:.1f} (from the fewest steps "
               "the plateau rule could stop at to max_steps, at each run's measured time per step; "
               "runs not started are not counted).")
  return "\n".join(lines)


def train_run(run: Run, *, deadline: float | None, allow_data_change: bool = False,
              log: Callable[[str], None] = print) -> bool:
  """Train ``run`` from its committed state until it stops or ``deadline``; True when it is done."""
  from nlosjax import train
  from nlosjax.data.dataset import dataset_identity
  from nlosjax.evaluation import protocol
  config = run_config(run)
  typed = train.RunConfig.from_dict(config)
  data_path = pathlib.Path(config["data"]["path"])
  data_path.parent.mkdir(parents=True, exist_ok=True)
  train.ensure_dataset(typed, data_path, log=log)   # a file of another config is refused
  digest, fingerprint = dataset_identity(data_path)
  log(f"[{run.name}] data {data_path} (content digest {digest})")
  export = train.StateExport(state_folder(run), data_digest=digest, data_fingerprint=fingerprint,
                             deadline=deadline, allow_data_change=allow_data_change)
  _record_invocation(run, digest)
  # Every validation score, as the main job: the run's train.stop.metric decides among them.
  validate = protocol.validation_scores(typed, data_path)
  wd = workdir(run)
  wd.mkdir(parents=True, exist_ok=True)
  (wd / "config.json").write_text(json.dumps(config, indent=2, default=str) + "\n")
  try:
    train.train_model(typed, data_path, wd, run.variant, validate=validate, log=log, export=export)
  except train.TrainingPaused as e:
    log(str(e))
    return False
  return True


def _record_invocation(run: Run, digest: str) -> None:
  """Append this stretch's commit, machine and data digest to the run's committed ``invocations.jsonl``."""
  import sys

  from experiments.provenance import run_record
  folder = state_folder(run)
  folder.mkdir(parents=True, exist_ok=True)
  record = run_record("python -m experiments.studies.real_preset " + " ".join(sys.argv[1:]))
  with open(folder / "invocations.jsonl", "a") as f:
    f.write(json.dumps({**record, "run": run.name, "data_digest": digest}) + "\n")


def run_study(names=None, *, hours: float | None = None, allow_data_change: bool = False,
              log: Callable[[str], None] = print) -> list[dict]:
  """Train the named runs (default: all, in order) until each is done or ``hours`` have passed.

  The first unfinished run is always started (a deadline already past pauses it after one
  step), so every invocation makes progress; later runs start only before the deadline.
  Returns :func:`status` of every run.
  """
  runs = select(names)
  deadline = None if hours is None else time.time() + 3600 * hours
  started = False
  for run in runs:
    if status(run)["done"]:
      log(f"[{run.name}] done (committed state)")
      continue
    if started and deadline is not None and time.time() >= deadline:
      break                             # the first unfinished run always makes progress
    started = True
    if not train_run(run, deadline=deadline, allow_data_change=allow_data_change, log=log):
      break
  return [status(r) for r in RUNS]


def candidate_workdir(config: str) -> pathlib.Path:
  """One workdir holding every finished variant of the candidate ``config`` (for ``preset_choice``; seed 0).

  ``<store>/runs/real_preset/<config stem>``: the first run's ``config.json`` with its
  ``train.variants`` the union of the candidate's runs, and a link per variant to that run's
  folder in the store, so :func:`nlosjax.inference.load_run` sees one run of both variants.
  Raises:
    FileNotFoundError: a run of the candidate has no folder in this store (train it first).
  """
  import json
  # seed 0 and the preset's schedule: one model a variant
  runs = [r for r in RUNS if r.config == config and r.seed == 0 and not r.probe]
  if not runs:
    raise ValueError(f"no run of {config!r}; the runs: {[r.name for r in RUNS]}")
  for r in runs:
    if not (workdir(r) / r.variant).is_dir():
      raise FileNotFoundError(f"{workdir(r) / r.variant}: not in this store; train {r.name} first")
  out = store.run_path(STUDY, pathlib.Path(config).stem)
  out.mkdir(parents=True, exist_ok=True)
  cfg = json.loads((workdir(runs[0]) / "config.json").read_text())
  cfg["train"]["variants"] = [r.variant for r in runs]
  (out / "config.json").write_text(json.dumps(cfg, indent=1) + "\n")
  for r in runs:
    link = out / r.variant
    if link.is_symlink() or link.exists():
      link.unlink()
    link.symlink_to(workdir(r) / r.variant, target_is_directory=True)
  return out


def run_alignments(files, names=None, *, hours: float | None = None,
                   log: Callable[[str], None] = print) -> list[dict]:
  """Align the named :data:`ALIGNMENTS` (default all, in order) until done or ``hours`` have passed.

  ``files``: the measured scans (``experiments.studies.real_undersampling.default_files``). As
  :func:`run_study`, the first unfinished fold always starts. Returns each alignment's status.
  """
  from experiments.studies.real_undersampling import scene_name
  unknown = set(names or ()) - {a.name for a in ALIGNMENTS}
  if unknown:
    raise ValueError(f"unknown alignment(s) {sorted(unknown)}; the study's: {[a.name for a in ALIGNMENTS]}")
  chosen = [a for a in ALIGNMENTS if not names or a.name in names]
  scenes = [scene_name(pathlib.Path(f)) for f in files]
  deadline = None if hours is None else time.time() + 3600 * hours
  started = False
  for a in chosen:
    if not alignment_status(a, scenes)["left"]:
      log(f"[{a.name}] done (committed state)")
      continue
    if started and deadline is not None and time.time() >= deadline:
      break
    done, began = run_alignment(a, files, deadline=deadline, start_one=not started, log=log)
    started = started or began
    if not done:
      break
  return [alignment_status(a, scenes) for a in ALIGNMENTS]


def select(names) -> list[Run]:
  by_name = {r.name: r for r in RUNS}
  if not names:
    return list(RUNS)
  unknown = [n for n in names if n not in by_name]
  if unknown:
    raise ValueError(f"unknown run(s) {unknown}; the study's runs: {sorted(by_name)}")
  return [by_name[n] for n in names]


@dataclasses.dataclass(frozen=True)
class Alignment:
  """The alignment stage (:mod:`experiments.studies.align`, leave one scan out) of one shipped network.

  ``source``: ``pretrained:NAME``, the weights shipped as ``NAME-<variant>`` (so a fresh
  clone has them); their training data are made in the store from the provenance's config.
  ``lam``: ``experiments.studies.align``'s ``--lam`` (a number or ``"balanced"``); ``folder``: the
  workdir's name in the store and in ``state/`` (the alignments of one ``lam`` and layer rule
  share one, so one ``--aligned`` scores them together); ``layer``: its ``--layer`` (a layer or
  ``"auto"``).
  """

  name: str
  source: str
  variant: str
  lam: float | str = 1.0
  folder: str = "align"
  layer: str = "st_mamba0"


#: Alignment from the winner of each variant on validation
#: (experiments/studies/preset_choice/results/preset_choice_real.md), both shipped as ``real``: Ours-S trained on the
#: v5 candidate's data (``v5-ours_s``), Ours on the preset's own. Steps, ``lam`` and the
#: learning rate are the CLI's defaults, fixed before any score was seen. At ``lam = 1`` the
#: MMD term stayed 0.000-0.1 against a synthetic loss of about 2 (the stage was inert), so
#: the ``balanced`` pair sets ``lam`` per fold from the training side alone: the MMD
#: gradient as large as the synthetic one at the start (``experiments.studies.align --lam balanced``).
ALIGNMENTS = (
    Alignment("align-ours_s", "pretrained:real", OURS_S),
    Alignment("align-ours", "pretrained:real", OURS),
    Alignment("align-ours_s-balanced", "pretrained:real", OURS_S, "balanced", "align-balanced"),
    Alignment("align-ours-balanced", "pretrained:real", OURS, "balanced", "align-balanced"),
    # The first block's features of measured and simulated inputs differ by no more than the
    # MMD's own noise (real_adapt.md), so these align, per fold, the layer where the fold's
    # training scans stand furthest off (experiments.studies.align --layer auto), lam balanced there.
    Alignment("align-ours_s-layer", "pretrained:real", OURS_S, "balanced", "align-layer", "auto"),
    Alignment("align-ours-layer", "pretrained:real", OURS, "balanced", "align-layer", "auto"),
)


def alignment_workdir(a: Alignment) -> pathlib.Path:
  """``<store>/runs/real_preset/<a.folder>``: ``experiments.studies.align``'s ``--workdir``, one folder a fold.

  One folder for the alignments of one ``folder`` (one ``lam`` and layer rule; the folds are named
  by variant and scan),
  so one ``python -m experiments.studies.real_undersampling --aligned`` scores them together.
  """
  return store.run_path(STUDY, a.folder)


def alignment_state(a: Alignment) -> pathlib.Path:
  """``state/<a.folder>/``: the committed finished folds of the alignments of that folder."""
  return STATE_DIR / a.folder


def sync_alignment(a: Alignment) -> list[str]:
  """Copy finished folds both ways between the store and ``state/align/``; returns the finished folds.

  Only ``a``'s folds (``<variant>-without-<scan>``) are copied. The committed state holds
  each finished fold's ``params.npz`` (the aligned network, about 100 KB) and
  ``align.json``; a fold still training has nothing to keep (a fold is about 15 minutes of
  2 cores: it restarts).
  """
  import shutil

  from experiments.studies.align import fold_files
  done = set()
  work, state = alignment_workdir(a), alignment_state(a)
  for src_root, dst_root in ((state, work), (work, state)):
    if not src_root.is_dir():
      continue
    for folder in sorted(p for p in src_root.iterdir() if p.is_dir()):
      if not folder.name.startswith(f"{a.variant}-without-") or not fold_files(folder):
        continue
      done.add(folder.name)
      target = dst_root / folder.name
      target.mkdir(parents=True, exist_ok=True)
      for f in fold_files(folder):
        if not (target / f.name).exists():
          shutil.copy2(f, target / f.name)
  return sorted(done)


def run_alignment(a: Alignment, files, *, deadline: float | None, start_one: bool = True,
                  log: Callable[[str], None] = print) -> tuple[bool, bool]:
  """Align ``a`` fold by fold until every scan is done or ``deadline``: ``(done, started a fold)``.

  :func:`experiments.studies.align.align_folds` (as ``python -m experiments.studies.align --checkpoint
  <source> --variants <variant>``) with the store's workdir and data, ``deadline`` checked
  before each fold starts (with ``start_one``, not before the first), and each finished fold
  copied into the committed state.
  """
  from experiments.studies import align as cli
  from nlosjax import train
  from nlosjax.evaluation import protocol
  config, trained = cli.load_source(a.source, [a.variant])
  config = train.RunConfig.from_dict(config)
  data_path = store.data_path(pathlib.Path(config.data.path).name)   # made in the store, checked strictly
  data_path.parent.mkdir(parents=True, exist_ok=True)
  train.ensure_dataset(config, data_path, log=log)   # a file of another config is refused
  validate = protocol.validation_psnr(config, data_path)
  mcfg, params = trained[a.variant]
  sync_alignment(a)
  started = []

  def before_fold(scene: str) -> bool:
    return deadline is None or time.time() < deadline or (start_one and not started)

  def after_fold(folder: pathlib.Path) -> None:
    started.append(folder.name)
    sync_alignment(a)

  return cli.align_folds(config, data_path, mcfg, params, cli.measured_inputs(files, mcfg),
                         alignment_workdir(a), a.variant, lam=a.lam, layer=a.layer, validate=validate,
                         before_fold=before_fold, after_fold=after_fold, log=log)


def _fold_seconds(a: Alignment, scenes) -> tuple[list[str], list[float]]:
  from experiments.studies.align import fold_files
  state = alignment_state(a)
  done = [s for s in scenes if fold_files(state / f"{a.variant}-without-{s}")]
  return done, [json.loads((state / f"{a.variant}-without-{s}" / "align.json").read_text())["seconds"]
                for s in done]


def alignment_status(a: Alignment, scenes) -> dict:
  """What the committed state says of ``a``: folds done and left, seconds a fold, hours left.

  Before ``a`` has a finished fold, the rate is that of another alignment of the same
  variant (``"estimated": True``), else unknown.
  """
  done, seconds = _fold_seconds(a, scenes)
  estimated = not seconds
  if estimated:
    seconds = [t for b in ALIGNMENTS if b.variant == a.variant and b != a for t in _fold_seconds(b, scenes)[1]]
  rate = sum(seconds) / len(seconds) if seconds else None
  left = len(scenes) - len(done)
  return {"name": a.name, "source": a.source, "variant": a.variant, "lam": a.lam, "done": done, "left": left,
          "s_per_fold": rate, "estimated": estimated and rate is not None,
          "hours_left": None if rate is None else round(left * rate / 3600, 2)}


def format_alignment_status(rows: list[dict]) -> str:
  """The alignment table (Markdown); a rate borrowed from another alignment of the variant is marked *est.*"""
  lines = ["| alignment | source | variant | lam | folds done | folds left | s / fold | hours left |",
           "|---|---|---|---|---|---|---|---|"]
  for r in rows:
    est = " (est.)" if r.get("estimated") else ""
    rate = "—" if r["s_per_fold"] is None else f"{r['s_per_fold']:.0f}{est}"
    hours = "0" if not r["left"] else ("not measured" if r["hours_left"] is None else f"{r['hours_left']:.1f}{est}")
    lines.append(f"| {r['name']} | `{r['source']}` | {r['variant']} | {r.get('lam', 1.0)} | {len(r['done'])} | "
                 f"{r['left']} | {rate} | {hours} |")
  return "\n".join(lines)

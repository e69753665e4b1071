"""The runs of :mod:`experiments.studies.physics_shift`: configs, training to the plateau, scoring, JSON records.

Designs (:data:`DESIGNS`), every one trained here: ``base`` on the preset's
scenes rendered by the transport renderer alone, without a physics mix (the
preset's own data where it has none); ``mix`` on sequences whose forward model
is drawn from every family of :class:`nlosjax.data.dataset.physics.PhysicsMix`;
``wide`` on the mix with wider scenes; ``no_<family>`` on every family but
one; ``wide_base`` on the preset's renderer with the wider scenes. Each learned
run trains to the plateau rule of :mod:`experiments.studies.mechanisms`
and writes ``RESULTS/physics_shift/<design>-<variant>.json``; each classic
method's per-frame scores on a test set, with settings tuned on a design's
validation split, go to ``RESULTS/physics_shift/classic-<design>-<set>.json``.
A file that exists is not recomputed, so the command resumes anywhere; with
``--state DIR`` a run in progress also exports its resumable state there
(:mod:`nlosjax.train.run_state`), so a fresh clone continues it.
"""

from __future__ import annotations

import copy
import json
import pathlib
import time
from typing import Callable

import numpy as np

from nlosjax.data.dataset.physics import FAMILIES, PhysicsMix
from nlosjax.variants import OURS, OURS_S

#: design -> the families its training data draws from (``base``: the preset's own data).
#: ``wide``: every family, and scenes wider than the preset's (:func:`wide_scene`).
#: ``wide_base``: the preset's own renderer with those wider scenes (the scene ranges alone changed).
DESIGNS = {"base": None, "mix": FAMILIES, "wide": FAMILIES,
           **{f"no_{f}": tuple(g for g in FAMILIES if g != f) for f in FAMILIES},
           "wide_base": None}
#: Designs compared on validation to choose the preset's data.
CANDIDATES = ("base", "mix", "wide")
#: Designs scored on every set (the candidates' validation splits, every family, every condition).
SCORED_ON_ALL = CANDIDATES + ("wide_base",)


def wide_scene(scene: dict) -> dict:
  """The preset's scene distribution widened: objects 0.6x to 1.67x its sizes, anchored 1.4x as far
  from the wall centre, 0.8x to 1.33x its depths (cpu: 0.15-1.0 m across, within 0.7 m, 0.4-2.0 m)."""
  (s0, s1), (z0, z1) = scene["size_range"], scene["depth_range"]
  return {**scene, "size_range": (round(0.6 * s0, 4), round(s1 * 5 / 3, 4)),
          "lateral_extent": round(1.4 * scene["lateral_extent"], 4),
          "depth_range": (round(0.8 * z0, 4), round(z1 * 4 / 3, 4))}
VARIANTS = (OURS, OURS_S)
#: Test sequences per set and frames per sequence.
SEQUENCES, FRAMES = 8, 8
#: Seed of the held-out renderer's sets.
HELDOUT_SEED = 4048


def physics_digest(physics: dict | None) -> str:
  """Six hex digits naming a mix's physics (its families aside): files of two mixes never collide."""
  import hashlib

  from nlosjax.data.dataset.physics import PhysicsMix
  d = PhysicsMix.from_dict({k: v for k, v in (physics or {}).items() if k != "families"}).to_dict()
  d.pop("families")
  return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:6]


def data_stem(base: dict, physics: dict | None = None) -> str:
  """``runs/data/<stem>`` of the preset's mix files: the preset file's stem, ``-mix`` and the physics digest."""
  stem = pathlib.PurePosixPath(base["data"]["path"]).stem.split("-mix")[0]
  if physics is None:
    physics = base["data"].get("physics")
  return f"{stem}-mix-{physics_digest(physics)}"


def design_config(base: dict, design: str, physics: dict | None = None) -> dict:
  """The preset config ``base`` with the data of ``design`` (its own file under ``runs/data``)."""
  cfg = copy.deepcopy(base)
  data = cfg["data"]
  if design in ("base", "wide_base"):
    if data.get("renderer") == "mix":     # the preset's scenes by transport alone
      retro = PhysicsMix.from_dict(data.get("physics") or {}).retroreflective
      data.update(renderer="transport", retroreflective=retro)
      data.pop("physics")
      data["path"] = str(pathlib.PurePosixPath(data["path"]).with_name(
          f"{data_stem(base).rsplit('-mix-', 1)[0]}-transport.h5"))
    if design == "wide_base":
      data["scene"] = wide_scene(data["scene"])
      path = pathlib.PurePosixPath(data["path"])
      data["path"] = str(path.with_name(f"{path.stem}-wide{path.suffix}"))
    return cfg
  families = DESIGNS[design]
  data["renderer"] = "mix"
  data["retroreflective"] = 0.0
  physics = physics if physics is not None else data.get("physics") or {}
  data["physics"] = {**physics, "families": list(families)}
  if design == "wide":
    data["scene"] = wide_scene(data["scene"])
  name = data_stem(base, physics) + ("" if design == "mix" else f"-{design.replace('_', '-')}")
  data["path"] = str(pathlib.PurePosixPath(data["path"]).with_name(f"{name}.h5"))
  return cfg


def family_set_config(base: dict, family: str, physics: dict | None = None) -> dict:
  """The config of family ``family``'s test set: the mix restricted to it, test split only."""
  cfg = design_config(base, "mix", physics)
  data = cfg["data"]
  data["physics"]["families"] = [family]
  data["num_sequences"] = {"train": 0, "test": SEQUENCES}
  data["frames"] = FRAMES
  name = f"{data_stem(base, physics)}-only-{family}.h5"
  data["path"] = str(pathlib.PurePosixPath(data["path"]).with_name(name))
  return cfg


def heldout_path(base: dict, condition: str) -> pathlib.Path:
  """The held-out renderer's file of ``condition`` at the preset's capture."""
  from experiments.studies.physics_shift import heldout
  version = heldout.GENERATOR_VERSION.rsplit("/", 1)[1]
  stem = pathlib.PurePosixPath(base["data"]["path"]).stem.split("-")[0]
  return pathlib.Path(base["data"]["path"]).with_name(f"heldout{version}-{stem}-{condition}.h5")


def test_sets(base: dict, conditions, physics=None) -> dict:
  """``set name -> (path, config to read it with[, split])``: each family's set, each held-out condition,
  and the validation splits of the candidates' data (``val:base``, ``val:mix``, ``val:wide``), on which
  the candidates are compared to choose the preset's data."""
  from experiments.studies.physics_shift import heldout
  from nlosjax import train as T
  sets = {}
  for design in CANDIDATES:
    cfg = design_config(base, design, physics)
    T.ensure_dataset(T.RunConfig.from_dict(cfg), pathlib.Path(cfg["data"]["path"]))
    sets[f"val:{design}"] = (pathlib.Path(cfg["data"]["path"]), cfg, "val")
  for family in FAMILIES:
    cfg = family_set_config(base, family, physics)
    T.ensure_dataset(T.RunConfig.from_dict(cfg), pathlib.Path(cfg["data"]["path"]))
    sets[f"family:{family}"] = (pathlib.Path(cfg["data"]["path"]), cfg)
  for cond in conditions:
    path = heldout.ensure_condition(heldout_path(base, cond), base["data"], cond, SEQUENCES, FRAMES,
                                    HELDOUT_SEED)
    sets[f"heldout:{cond}"] = (path, base)
  return sets


def sets_of(design: str, sets: dict) -> list[str]:
  """The sets a design is scored on: every set (:data:`SCORED_ON_ALL`) or its held-out family."""
  if design in SCORED_ON_ALL:
    return list(sets)
  return [f"family:{design[3:]}"]


def scored_by_classic(sets: dict) -> list[str]:
  """The test sets the classic methods are scored on (not the validation splits)."""
  return [n for n in sets if not n.startswith("val:")]


def _scores(ev: dict, method: str) -> dict:
  s = ev["scores"][method]
  return {k: np.asarray(v).reshape(-1) for k, v in s.items()}


def _set_reader(set_cfg: dict, cfg: dict):
  """The :class:`nlosjax.train.RunConfig` that reads a scored set: its own data, the run's train section."""
  from nlosjax import train as T
  return T.RunConfig.from_dict({**set_cfg, "train": cfg["train"]})


def score_model(cfg: dict, val_path, mcfg, params, variant: str, sets: dict, names,
                log: Callable[[str], None] = print) -> dict:
  """The model's surface threshold on ``val_path``'s validation split, then per-frame scores on each set."""
  from nlosjax import train as T
  from nlosjax.evaluation import protocol
  tuned = protocol.tune_model_thresholds(T.RunConfig.from_dict(cfg), val_path, {variant: [(mcfg, params)]},
                                         log=log)[variant]
  out = {"surface_threshold": tuned["threshold"], "sets": {}}
  for name in names:
    path, set_cfg, *split = sets[name]
    ev = protocol.evaluate(_set_reader(set_cfg, cfg), path, {variant: [(mcfg, params)]}, methods=(),
                           split=(split or ["test"])[0], model_thresholds={variant: tuned["threshold"]}, log=log)
    out["sets"][name] = {"sequence": np.asarray(ev["sequence"]), "frame": np.asarray(ev["frame"]),
                         "scores": _scores(ev, variant)}
  return out


def classic_record(cfg: dict, val_path, settings: dict, sets: dict, name: str, log=print) -> dict:
  """Every classic method on set ``name`` with ``settings`` (tuned on ``val_path``'s validation split)."""
  from nlosjax.evaluation import baselines, protocol
  path, set_cfg, *_ = sets[name]
  ev = protocol.evaluate(_set_reader(set_cfg, cfg), path, {}, classic_settings=settings, log=log)
  return {"set": name, "tuned_on": str(val_path), "best": max(settings, key=lambda m: settings[m]["psnr"]),
          "val_psnr": {m: settings[m]["psnr"] for m in settings},
          "sequence": np.asarray(ev["sequence"]), "frame": np.asarray(ev["frame"]),
          "methods": {m: _scores(ev, m) for m in baselines.CLASSIC_METHODS}}


def run_meta(cfg: dict, design: str, variant: str, preset: str, results) -> dict:
  """The run folder's ``run.json``: what ``experiments.export_weights`` reads of a study run."""
  return {"config": cfg, "command": f"python -m experiments.studies.physics_shift --config {preset} --designs {design} "
                                    f"--variants {variant}",
          "record": str(run_path(results, design, variant)),
          "study": {"study": "physics_shift", "design": design, "variant": variant}}


def train_run(cfg: dict, folder: pathlib.Path, variant: str, stop: dict, log=print, meta=None,
              state: pathlib.Path | None = None, deadline: float | None = None):
  """Train (or resume) one learned run to its plateau; ``(mcfg, params, curve record)``.

  ``meta``: written to ``folder/run.json`` with the run's config (:func:`run_meta`).
  ``state``: a folder that receives the run's resumable state at every checkpoint (its ``model``
  sub-folder) and is resumed from when ahead of ``folder``; ``deadline`` (``time.time()``, with
  ``state``): pause there, raising :class:`nlosjax.train.TrainingPaused`.
  """
  from experiments.studies.mechanisms.records import write_json
  from experiments.studies.mechanisms.study import _subsample
  from nlosjax import train as T
  from nlosjax.evaluation import protocol
  cfg = copy.deepcopy(cfg)
  cfg["train"]["stop"] = dict(stop)
  cfg["train"]["variants"] = (variant,)
  if meta is not None:
    write_json(folder / "run.json", {**meta, "config": cfg})
  data_path = pathlib.Path(cfg["data"]["path"])
  typed = T.RunConfig.from_dict(cfg)
  T.ensure_dataset(typed, data_path, log=log)
  validate = protocol.validation_psnr(typed, data_path)
  export = None
  if state is not None:
    from nlosjax.data.dataset import dataset_identity
    digest, fingerprint = dataset_identity(data_path)
    export = T.StateExport(state, data_digest=digest, data_fingerprint=fingerprint, deadline=deadline)
  mcfg, trained = T.train_model(typed, data_path, folder, variant, folder="model", validate=validate, log=log,
                                export=export)
  curve = T.read_curve(folder / "model")
  record = {"steps_taken": curve["steps_taken"], "stop_reason": curve["stop_reason"],
            "best_step": curve["best_step"], "best_val_psnr": curve["best_val_psnr"],
            "validation_curve": curve["curve"],
            "loss_curve": _subsample(T.read_metrics(folder / "model" / "metrics.jsonl"))}
  return mcfg, T.to_host(trained.params), record


def state_dir(state: pathlib.Path, design: str, variant: str) -> pathlib.Path:
  """A run's committed resumable state (``--state``): ``STATE/<design>-<variant>``."""
  return pathlib.Path(state) / f"{design}-{variant}"


def run_design(base: dict, design: str, variant: str, sets: dict, stop: dict, workdir: pathlib.Path,
               results: pathlib.Path, preset: str, physics=None, log=print,
               state: pathlib.Path | None = None, deadline: float | None = None) -> dict:
  """One learned run, trained to its plateau and scored on its sets; writes and returns its record.

  A record that exists already is completed: the sets it lacks are scored
  (the run is restored, not trained again) and added. ``state``, ``deadline``: as
  :func:`train_run` (the run's folder is :func:`state_dir`).
  """
  from experiments.studies.mechanisms import machine, write_json
  t0 = time.perf_counter()
  path = run_path(results, design, variant)
  old = json.loads(path.read_text()) if path.exists() else None
  cfg = design_config(base, design, physics)
  mcfg, params, record = train_run(cfg, workdir / f"{design}-{variant}", variant, stop, log,
                                   meta=run_meta(cfg, design, variant, preset, results),
                                   state=None if state is None else state_dir(state, design, variant),
                                   deadline=deadline)
  val_path = pathlib.Path(cfg["data"]["path"])
  names = [n for n in sets_of(design, sets) if old is None or n not in old["sets"]]
  scored = score_model(cfg, val_path, mcfg, params, variant, sets, names, log)
  if old is not None:
    if old["surface_threshold"] != scored["surface_threshold"]:
      raise RuntimeError(f"{path}: the restored run chose another surface threshold than its record")
    old["sets"].update(scored["sets"])
    old.setdefault("rescored", []).append({"sets": names, "machine": machine()})
    write_json(path, old)
    return old
  record.update(design=design, variant=variant, families=DESIGNS[design], data=str(val_path),
                physics=cfg["data"].get("physics"), machine=machine(), **scored)
  record["wall_s"] = round(time.perf_counter() - t0, 1)
  write_json(path, record)
  return record


def incomplete(results, design: str, variant: str, sets: dict) -> bool:
  """Whether the run has no record, or one that lacks a set it is scored on."""
  path = run_path(results, design, variant)
  if not path.exists():
    return True
  have = json.loads(path.read_text())["sets"]
  return any(n not in have for n in sets_of(design, sets))


def run_path(results, design: str, variant: str) -> pathlib.Path:
  return pathlib.Path(results) / "physics_shift" / f"{design}-{variant}.json"


def classic_path(results, design: str, name: str) -> pathlib.Path:
  return pathlib.Path(results) / "physics_shift" / f"classic-{design}-{name.replace(':', '-')}.json"


def run_classic(base: dict, design: str, name: str, sets: dict, results, preset: str, physics=None,
                log=print) -> dict:
  """The classic methods on set ``name`` with settings tuned on ``design``'s validation split."""
  from experiments.main_job import tune_classic
  from experiments.studies.mechanisms import machine, write_json
  from nlosjax import train as T
  cfg = design_config(base, design, physics)
  val_path = pathlib.Path(cfg["data"]["path"])
  tuning = pathlib.Path(results) / "physics_shift" / f"tuning-{design}.json"
  if tuning.exists():
    settings = json.loads(tuning.read_text())["settings"]
  else:
    typed = T.RunConfig.from_dict(cfg)
    T.ensure_dataset(typed, val_path, log=log)
    settings = tune_classic(typed, val_path, log)
    write_json(tuning, {"design": design, "tuned_on": str(val_path), "settings": settings,
                        "machine": machine()})
  record = classic_record(cfg, val_path, settings, sets, name, log)
  record.update(design=design, machine=machine())
  write_json(classic_path(results, design, name), record)
  return record


def classic_design(name: str) -> str:
  """Whose validation split tunes the classic methods on set ``name``: the design that left it out."""
  return f"no_{name.split(':')[1]}" if name.startswith("family:") else "mix"

"""The scripts' probes of ``benchmarks.equivalence --probe scripts``, run as a script on a tree.

    PYTHONPATH=TREE python benchmarks/equivalence_probe_scripts.py OUT.npz

(whichever tree is first on ``sys.path``; ``equivalence_probe_measured.py`` beside it.)

The other probes run the library, the main job and three studies; this one runs the code of
the performance benchmarks and of the studies they leave out, between a preset and the
library: how each builds its config, its model and what it times. A performance file's
numbers are times, which no two runs share; what carries it forward is that the programs it
times are the same, so this probe keeps their fingerprints (the SHA-256 of each lowered
program's text, of each model config's ``repr``) and every number that is not a time.
Each command runs end to end where it can, on the tiny preset of ``experiments/tiny_run.py``
under the name :data:`TINY` (``experiments.configs.get_config`` answers it), its results
file written into a temporary folder; functions of the command are wrapped to keep what they
return. Probes, each on fixed seeds:

* ``scripts/compile``: ``benchmarks.compile``'s programs (the train step and the forward pass,
  with the physics operators as constants and as arguments): each lowered text's fingerprint
  and the model config's;
* ``scripts/dry_run``: ``python -m benchmarks.dry_run --config TINY``: the dry run's plan of
  each variant, times left out (:data:`UNTIMED`);
* ``scripts/hlo_gpu``: ``python -m benchmarks.hlo_gpu --config TINY --batch 2``: the lowered
  step's HLO and StableHLO texts (for CUDA and for this machine), fingerprinted without the
  HLO's source locations (a file's lines, the checkout's path);
* ``scripts/model``: ``benchmarks.model``'s model configs of the ``cpu`` preset (Ours, USM);
* ``scripts/step_profile``: ``python -m benchmarks.step_profile --config TINY --steps 1``:
  the input shape and the names of the profiled parts and op kinds;
* ``scripts/prefetch``: ``python -m benchmarks.prefetch --config TINY --steps 8 --rounds 1``:
  the parameters after training, read ahead and not;
* ``scripts/depth_range``: ``benchmarks.depth_range``'s study of the tiny test split (LCT, two
  frames): every score and estimated range (the shipped scans' half is the physics' own code,
  in the main probe's closure, and is not run);
* ``scripts/realism``: the realism audit's simulated inputs of the tiny preset;
* ``scripts/preset_choice``: ``python -m experiments.studies.preset_choice`` with two candidates
  (the same tiny main-job run twice), every number of its record;
* ``scripts/independent_test``: ``python -m experiments.studies.independent_test`` on that run
  (a two-sequence independent set), every score;
* ``scripts/generalisation``: the generalisation study's model loader on a study run folder (a
  mechanisms run of Ours-S to the tiny plateau) and its scoring of the tiny test split;
* ``scripts/export``: ``python -m experiments.export_weights`` of that study run: the
  parameters written and the validation numbers recomputed;
* ``scripts/time_to_plateau``: the time-to-plateau study's short schedule, cut to 4 steps:
  every number of its record;
* ``scripts/real_preset``: the real-preset study's ``train_run`` on the tiny preset (state
  exported, trained to its stop): every parameter and the validation curve;
* ``scripts/align``: the alignment stage's leave-one-scan-out folds (``align_folds``, 2 steps,
  ``lam`` balanced, layer ``auto``, each rule on 2 batches or draws) on two stand-in measured
  scans of the tiny main-job run's Ours: every number of each fold's record and the aligned
  parameters;
* ``scripts/csa``: ``python -m experiments.studies.csa``'s scoring (``score``, ``choose``) on one
  validation frame of the tiny data, one stride, two prior weights: every PSNR and FISTA count;
* ``scripts/stopping_replay``: the stopping-rule replay on the committed records of the
  mechanism and time-to-plateau studies (each tree reads its own copy, where it keeps them):
  every replayed curve and every candidate rule's row.

Like the other probes it uses interfaces the compared commits share (a function whose
argument became a typed config is handed what each tree's library takes).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import hashlib
import io
import json
import pathlib
import re
import sys
import tempfile
import time

import numpy as np

#: The preset name the probe's commands are given; ``experiments.configs.get_config`` answers it.
TINY = "tiny-probe"
#: Keys that hold times, machine facts or paths, not computed numbers.
UNTIMED = frozenset({"time_s", "eval_s", "val_s", "train_wall_s", "wall_s", "seconds", "machine", "date",
                     "data", "path", "commit", "code_digest", "compile_s", "step_s", "run_s", "op_s",
                     "lower_s", "trace_s", "events_per_step", "with_metadata", "t_full", "t_gated",
                     "t_compile", "t_estimate",
                     "source", "exported", "command", "checkpoint", "workdir", "dataset", "record",
                     "memory_bytes", "memory_source", "load"})


def leaves(value, prefix: str, out: dict) -> None:
  """Every number of a JSON value into ``out`` by its path, :data:`UNTIMED` keys left out."""
  from equivalence_probe_measured import json_arrays
  json_arrays(value, prefix, out, UNTIMED)


def fingerprint(text: str) -> np.ndarray:
  """The SHA-256 of ``text`` as 32 numbers: equal texts, equal arrays; any change moves it."""
  return np.frombuffer(hashlib.sha256(text.encode()).digest(), np.uint8).astype(np.float64)


#: An HLO text's source locations (``debug_info``): which file and line traced an op, not the
#: program; in an op's metadata, and the module's tables of files, functions, lines and frames.
SOURCE = re.compile(r'\s*(?:source_(?:file="[^"]*"|line=\d+|end_line=\d+|column=\d+|end_column=\d+)'
                    r'|stack_frame_id=\d+)')
FRAMES = re.compile(r"^(?:FileNames|FunctionNames|FileLocations|StackFrames)\n(?:.+\n)*\n?", re.M)


def program_fingerprint(hlo: str) -> np.ndarray:
  """:func:`fingerprint` of an HLO text without its source locations: the same program traced from
  another checkout, or from a file whose lines moved, has the same fingerprint."""
  return fingerprint(SOURCE.sub("", FRAMES.sub("", hlo)))


def plain(value):
  """``value`` as JSON (dataclasses and arrays as their fields and lists; anything else by ``repr``)."""
  return json.loads(json.dumps(value, default=lambda v: (dataclasses.asdict(v) if dataclasses.is_dataclass(v)
                                                         else np.asarray(v).tolist() if hasattr(v, "shape")
                                                         else repr(v))))


def typed(config: dict):
  """What this tree's library takes for a run config: the typed one where it refuses dicts."""
  from nlosjax import train
  if hasattr(train, "read_preset"):                # before the presets were ConfigDicts
    return train.read_preset(config) if hasattr(train, "require_run_config") else train.with_defaults(config)
  return train.RunConfig.from_dict(config)


@contextlib.contextmanager
def wrapped(module, name: str, kept: list):
  """``module.name`` replaced for the block by a wrapper that appends each call's result to ``kept``
  (a dict as a shallow copy: what the function returned, whatever its caller then pops)."""
  original = getattr(module, name)

  def wrapper(*args, **kwargs):
    result = original(*args, **kwargs)
    kept.append(dict(result) if isinstance(result, dict) else result)    # as returned, before the caller pops
    return result
  setattr(module, name, wrapper)
  try:
    yield kept
  finally:
    setattr(module, name, original)


@contextlib.contextmanager
def tiny_preset(config: dict):
  """``experiments.configs.get_config(TINY)`` answers a copy of ``config`` for the block."""
  from experiments import configs
  original = configs.get_config

  def get_config(name=configs.DEFAULT):
    return copy.deepcopy(config) if name == TINY else original(name)
  configs.get_config = get_config
  try:
    yield
  finally:
    configs.get_config = original


def quiet():
  return contextlib.redirect_stdout(io.StringIO())


def tiny(tmp: pathlib.Path, name: str, **kw) -> dict:
  from experiments.tiny_run import tiny_config
  return tiny_config(tmp / "data" / f"{name}.h5", **kw)


# ---- the performance benchmarks

def probe_compile(tmp: pathlib.Path, out: dict) -> None:
  from benchmarks import compile as C
  with tiny_preset(tiny(tmp, "tiny")):
    mcfg, programs = C._programs(TINY, "ours", 1)
  out["scripts/compile/model_config"] = fingerprint(repr(mcfg))
  for name, (const_fn, bound_fn, args, _) in programs.items():
    for way, fn in (("constants", const_fn), ("arguments", bound_fn)):
      out[f"scripts/compile/{name}/{way}"] = fingerprint(fn.lower(*args).as_text())


def probe_dry_run(tmp: pathlib.Path, out: dict) -> None:
  from benchmarks import dry_run as D
  from nlosjax import plan
  with tiny_preset(tiny(tmp, "tiny")), wrapped(plan, "dry_run", []) as kept, quiet():
    D.main(["--config", TINY, "--out", str(tmp / "dry_run.md")])
  report = plain(kept[0])
  for variant, v in report["variants"].items():
    v["model_config"] = None                              # fingerprinted below, not a number
    out[f"scripts/dry_run/{variant}/model_config"] = fingerprint(repr(kept[0]["variants"][variant]["model_config"]))
  leaves(report, "scripts/dry_run", out)


def probe_hlo_gpu(tmp: pathlib.Path, out: dict) -> None:
  from benchmarks import hlo_gpu as H
  with tiny_preset(tiny(tmp, "tiny")), wrapped(H, "lower_step", []) as kept, quiet():
    H.main(["--config", TINY, "--batch", "2", "--out", str(tmp / "hlo_gpu.md")])
  for i, info in enumerate(kept):
    for key in ("hlo", "stablehlo"):
      out[f"scripts/hlo_gpu/{i}/{key}"] = program_fingerprint(info[key])
    leaves(plain({k: v for k, v in info.items() if k not in ("hlo", "stablehlo")}), f"scripts/hlo_gpu/{i}", out)


def probe_model(tmp: pathlib.Path, out: dict) -> None:
  from benchmarks import model as M
  for name, frames in (("cpu", 3), ("usm", 1), ("cpu", 5)):
    out[f"scripts/model/{name}-{frames}"] = fingerprint(repr(M._config(name, frames)))


def probe_step_profile(tmp: pathlib.Path, out: dict) -> None:
  from benchmarks import step_profile as S
  with tiny_preset(tiny(tmp, "tiny")), wrapped(S, "profile_variant", []) as kept, quiet():
    S.main(["--config", TINY, "--variants", "ours_s", "--steps", "1", "--out", str(tmp / "step_profile.md")])
  for r in kept:
    out[f"scripts/step_profile/{r['variant']}/input"] = np.asarray(r["input"], np.float64)
    out[f"scripts/step_profile/{r['variant']}/parts"] = fingerprint(json.dumps(sorted(map(str, r["parts"]))))
    out[f"scripts/step_profile/{r['variant']}/kinds"] = fingerprint(json.dumps(sorted(r["kinds"])))


def probe_prefetch(tmp: pathlib.Path, out: dict) -> None:
  import jax

  from benchmarks import prefetch as P
  with tiny_preset(tiny(tmp, "tiny")), wrapped(P, "train_seconds_per_step", []) as kept, quiet():
    P.main(["--config", TINY, "--steps", "8", "--rounds", "1", "--out", str(tmp / "prefetch.md")])
  for i, (_, params) in enumerate(kept):
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
      out[f"scripts/prefetch/{i}/{jax.tree_util.keystr(path)}"] = np.asarray(leaf)


def probe_depth_range(tmp: pathlib.Path, out: dict) -> None:
  from benchmarks import depth_range as R
  with quiet():
    study = R.split_study(typed(tiny(tmp, "tiny")), ["lct"], max_frames=2, log=lambda s: None)
  leaves(plain(study), "scripts/depth_range", out)


# ---- the studies the studies probe leaves out

def probe_realism(tmp: pathlib.Path, out: dict) -> None:
  from experiments.studies import realism
  inputs, sequence = realism.simulated_inputs(tiny(tmp, "tiny"))
  out["scripts/realism/inputs"] = np.asarray(inputs)
  out["scripts/realism/sequence"] = np.asarray(sequence, np.float64)


def main_job_run(tmp: pathlib.Path) -> pathlib.Path:
  """A tiny main-job run (Ours-S and Ours, 2 steps), made once: the candidates' and tests' source."""
  workdir = tmp / "main_job"
  if not (workdir / "config.json").exists():
    from experiments.main_job import train_and_evaluate
    cfg = tiny(tmp, "tiny", steps=2)
    cfg["train"]["variants"] = ["ours_s", "ours"]
    with quiet():
      train_and_evaluate(typed(cfg), workdir, log=lambda s: None)
  return workdir


def probe_preset_choice(tmp: pathlib.Path, out: dict) -> None:
  from experiments.studies import preset_choice
  run = main_job_run(tmp)
  target = tmp / "preset_choice.md"
  with quiet():
    preset_choice.main(["--model", f"a={run}", "--model", f"b={run}", "--variants", "ours_s",
                        "--methods", "lct", "--out", str(target)])
  leaves(json.loads(target.with_suffix(".json").read_text()), "scripts/preset_choice", out)


def probe_independent_test(tmp: pathlib.Path, out: dict) -> None:
  from experiments.studies import independent_test
  run = main_job_run(tmp)
  target = tmp / "independent.md"
  with quiet():
    independent_test.main(["--checkpoint", str(run), "--data", str(tmp / "data" / "independent.h5"),
                           "--sequences", "2", "--frames", "3", "--out", str(target)])
  leaves(json.loads(target.with_suffix(".json").read_text()), "scripts/independent_test", out)


def probe_time_to_plateau(tmp: pathlib.Path, out: dict) -> None:
  from experiments.studies import time_to_plateau as P
  schedule = P.SHORT
  P.SHORT = {**schedule, "max_steps": 4}
  try:
    with quiet():
      record = P.run_short(tiny(tmp, "tiny"), "ours_s", 0, tmp / "time_to_plateau", tmp / "ttp-results")
  finally:
    P.SHORT = schedule
  leaves(record, "scripts/time_to_plateau", out)


def study_run(tmp: pathlib.Path) -> pathlib.Path:
  """A mechanisms-study run folder (Ours-S, the tiny plateau; ``run.json`` beside ``model/``), made once:
  what the generalisation study and the weights export read."""
  from experiments.studies import mechanisms as M
  folder = M.run_dir(tmp / "mechanisms", "full", "ours_s", 0)
  if not (folder / "model" / "selection.json").exists():
    base = tiny(tmp, "tiny", stop=dict(M.TINY_STOP))
    with quiet():
      M.run_one(base, "full", "ours_s", 0, dict(M.TINY_STOP), tmp / "mechanisms", tmp / "mechanisms-results",
                log=lambda s: None)
  return folder


def probe_generalisation(tmp: pathlib.Path, out: dict) -> None:
  from experiments.studies import generalisation as G
  folder = study_run(tmp)
  with quiet():
    mcfg, params, config = G.load_model(str(folder))
    models = {"ours_s": (mcfg, params)}
    result = G.score_set(typed(config), tmp / "data" / "tiny.h5", models, {}, {"ours_s": 0.0},
                         log=lambda s: None)
  out["scripts/generalisation/model_config"] = fingerprint(repr(mcfg))
  leaves(plain(result), "scripts/generalisation", out)


def probe_export(tmp: pathlib.Path, out: dict) -> None:
  import jax

  from experiments import export_weights
  from nlosjax import pretrained
  folder = study_run(tmp)
  root = tmp / "weights"
  with quiet():
    export_weights.main([str(folder), "--name", "probe", "--variant", "ours_s", "--root", str(root),
                         "--results", str(tmp / "mechanisms-results"), "--commit", "0" * 40])
  (params, prov), = [pretrained.read_weights(p) for p in sorted(root.iterdir()) if p.is_dir()]
  for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
    out[f"scripts/export/params/{jax.tree_util.keystr(path)}"] = np.asarray(leaf)
  leaves({"validation": prov["validation"], "steps_taken": prov.get("steps_taken"),
          "best_step": prov.get("best_step"), "num_params": prov["num_params"]}, "scripts/export", out)


def probe_real_preset(tmp: pathlib.Path, out: dict) -> None:
  from experiments.studies.mechanisms import TINY_STOP
  from experiments.studies.real_preset import study as R
  saved = R.run_config, R.STATE_DIR, R.workdir
  run = R.RUNS[0]
  cfg = tiny(tmp, "real", stop=dict(TINY_STOP))
  R.run_config = lambda r: copy.deepcopy(cfg)
  R.STATE_DIR = tmp / "repo" / "experiments" / "studies" / "real_preset" / "state"
  R.workdir = lambda r: tmp / "real_preset" / r.name
  try:
    with quiet():
      done = R.train_run(run, deadline=None, log=lambda s: None)
  finally:
    R.run_config, R.STATE_DIR, R.workdir = saved
  out["scripts/real_preset/done"] = np.asarray(float(done))
  model = tmp / "real_preset" / run.name / run.variant
  curve = json.loads((model / "validation_curve.json").read_text())
  leaves(curve, "scripts/real_preset/curve", out)
  from nlosjax import train
  rows = train.read_metrics(model / "metrics.jsonl")
  out["scripts/real_preset/loss"] = np.asarray([r["loss"] for r in rows], np.float64)


def probe_align(tmp: pathlib.Path, out: dict) -> None:
  from experiments.studies import align as cli
  from nlosjax import inference
  run = main_job_run(tmp)
  config, trained = inference.load_run(run)
  config = typed(config)
  mcfg, params = trained["ours"]
  rng = np.random.default_rng(7)
  shape = (2, mcfg.frames) + tuple(mcfg.input_shape(1)[2:])
  inputs = {f"scan{i}": rng.poisson(2.0, shape).astype(np.float32) for i in range(2)}
  data_path = tmp / "data" / "tiny.h5"
  rules = {k: getattr(cli, k) for k in ("AUTO_LAYER_BATCHES", "AUTO_LAYER_DRAWS", "BALANCED_BATCHES")}
  for k in rules:                                         # the rules' own paths, on fewer draws
    setattr(cli, k, 2)
  try:
    with quiet():
      cli.align_folds(config, data_path, mcfg, params, inputs, tmp / "align", "ours", steps=2,
                      lam="balanced", layer="auto", log=lambda s: None)
  finally:
    for k, v in rules.items():
      setattr(cli, k, v)
  for fold in sorted((tmp / "align").rglob("align.json")):
    name = fold.parent.relative_to(tmp / "align")
    leaves(json.loads(fold.read_text()), f"scripts/align/{name}", out)
  for fold in sorted((tmp / "align").rglob("params.npz")):
    with np.load(fold) as f:
      for k in f.files:
        out[f"scripts/align/{fold.parent.relative_to(tmp / 'align')}/{k}"] = f[k]


def probe_csa(tmp: pathlib.Path, out: dict) -> None:
  from experiments.studies.csa import __main__ as study  # its command's own module
  main_job_run(tmp)  # makes the tiny data
  with quiet():
    res = study.score(tmp / "data" / "tiny.h5", 1, [1], [4], [0.03, 0.3], log=lambda s: None)
  for key in ("csa", "iterations"):
    for (s, t), v in sorted(res[key].items()):
      out[f"scripts/csa/{key}/{s}/{t:g}"] = np.asarray(v, np.float64)
  for m in study.CLASSIC:
    out[f"scripts/csa/{m}/4"] = np.asarray(res[m][4], np.float64)
  out["scripts/csa/chosen"] = np.asarray(study.choose(res, [4], [0.03, 0.3])[4], np.float64)


def probe_stopping_replay(tmp: pathlib.Path, out: dict) -> None:
  import inspect

  from experiments.studies import stopping_replay as S
  if "records" in inspect.signature(S.curves).parameters:     # today: each study's own results folder
    runs = S.curves()
  else:                                                        # before studies kept their own results
    runs = S.curves(S.ROOT / "benchmarks" / "results")
  for name, run in sorted(runs.items()):
    out[f"scripts/stopping_replay/curve/{name}"] = np.asarray(run["points"], np.float64)
  leaves(plain(S.compare(runs)), "scripts/stopping_replay/compare", out)


PROBES = {"compile": probe_compile, "dry_run": probe_dry_run, "hlo_gpu": probe_hlo_gpu, "model": probe_model,
          "step_profile": probe_step_profile, "prefetch": probe_prefetch, "depth_range": probe_depth_range,
          "realism": probe_realism, "preset_choice": probe_preset_choice,
          "independent_test": probe_independent_test, "time_to_plateau": probe_time_to_plateau,
          "generalisation": probe_generalisation, "export": probe_export, "real_preset": probe_real_preset,
          "align": probe_align, "csa": probe_csa, "stopping_replay": probe_stopping_replay}


def main(argv=None) -> int:
  argv = sys.argv[1:] if argv is None else argv
  from equivalence_probe_measured import save
  only = set(argv[1:])                                     # a subset, while writing a probe
  out: dict[str, np.ndarray] = {}
  times = {}
  with tempfile.TemporaryDirectory() as d:
    for name, probe in PROBES.items():
      if only and name not in only:
        continue
      t0 = time.perf_counter()
      probe(pathlib.Path(d), out)
      times[name] = time.perf_counter() - t0
      print(f"{name}: {times[name]:.0f} s, {len(out)} arrays", file=sys.stderr, flush=True)
  save(pathlib.Path(argv[0]), out, times)
  return 0


if __name__ == "__main__":
  sys.exit(main())

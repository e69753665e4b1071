"""Export a finished training run as weights shipped inside the package: ``nlosjax/weights/<name>-<variant>/``.

    python -m experiments.export_weights runs/mechanisms/full/full-seed0 --name cpu --variant ours
    python -m experiments.export_weights runs/mechanisms/full/ours_s-seed0 --name cpu --variant ours_s
    python -m experiments.export_weights runs/default --name cpu --variant ours --command "python -m experiments.train"
    python -m experiments.export_weights experiments/studies/mechanisms/state/full/lfe-seed0 --name cpu --variant lfe

RUN is one of

* a run folder of the mechanism study (``python -m experiments.studies.mechanisms``,
  ``runs/mechanisms/<budget>/<row>-seed<k>``): ``run.json`` (``budget``,
  ``row``, ``seed``, ``config``) and ``model/`` (orbax ``checkpoints/`` and
  ``best_checkpoint/``, ``selection.json`` naming the selected step and the
  stop reason). The run's machine and commit come from ``run.json`` or else
  its record ``RESULTS/mechanisms/<budget>/<row>-seed<k>.json`` (``--results``,
  default ``experiments/studies/mechanisms/results``); the default command is ``python -m
  experiments.studies.mechanisms --budgets <budget> --rows <row> --seeds <k>``;
* a run state committed by a study (``--state``, e.g.
  ``experiments/studies/mechanisms/state/<budget>/<row>-seed<k>``: ``model/params.npz``,
  ``model/selection.json`` and ``model/run_state.json`` of
  :mod:`nlosjax.train.run_state`), with its record
  ``RESULTS/mechanisms/<budget>/<row>-seed<k>.json`` for the machine, the
  commit and the parts of the config the run's numbers depend on. The config is
  rebuilt as the study built it: the preset (``--preset``, default ``cpu``, the
  study's default base) with those parts over it, and the run trains the one
  variant. The parameters are those of ``params.npz`` (``best.npz`` in an export not yet
  finished: the plateau rule's best state, whose step must be the selected one); the model config rebuilt from the
  config must be the one the state's signature recorded, and the dataset file
  must have the content digest the run trained on;
* a main-job workdir (``python -m experiments.train``: ``config.json`` and
  ``<variant>/checkpoints``, ``<variant>/selection.json``), or one of its
  variant folders. The command, commit and machine come from the workdir's
  ``invocations.jsonl`` (written by ``python -m experiments.train``); for a
  workdir from before that file existed pass ``--commit``.

The selected step (``selection.json``; the latest checkpoint without one) is
restored with :func:`nlosjax.inference.restore_params` (parameters only), the
model config rebuilt from the run's config as
:func:`nlosjax.inference.load_trained` does. A checkpoint written before a
field was added to the model config (its recorded ``repr`` lacks the field, at
its default now) is accepted and said so in the provenance
(``checkpoint_model_config``).

At export the validation score is recomputed on the dataset file the config
names (``config["data"]["path"]``, or ``--data``) with
:mod:`nlosjax.evaluation.protocol` (mean over the val split's frames of the
intensity PSNR, intensity clamped to [0, 1]: the score the run selected its
checkpoint by), with the mean over each val sequence's frames beside it. The
export is refused when the score differs from the run's recorded one by more
than ``--tolerance-db`` (1e-3 dB), or when the file's data specification is not
the config's. The written folder is read back with
:func:`nlosjax.inference.load_pretrained` before the command reports success.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import platform
import shutil
import sys
import tempfile
import time

import numpy as np

from nlosjax.variants import VARIANTS

REPO = pathlib.Path(__file__).resolve().parents[1]
#: The mechanism study's results folder, whose run records name the machine a run trained on.
MECHANISM_RECORDS = REPO / "experiments" / "studies" / "mechanisms" / "results"
TOLERANCE_DB = 1e-3


def _shown(path) -> str:
  """``path`` relative to the repository when inside it (portable provenance), else absolute."""
  p = pathlib.Path(path).absolute()
  return str(p.relative_to(REPO)) if p.is_relative_to(REPO) else str(p)


def _mtime(path: pathlib.Path) -> str:
  return datetime.datetime.fromtimestamp(path.stat().st_mtime, datetime.timezone.utc).isoformat(
      timespec="seconds")


def _best_checkpoint_folder(model: pathlib.Path, step: int) -> pathlib.Path:
  """``model/best_checkpoint`` when it holds ``step`` (the plateau rule's best), else ``model/checkpoints``."""
  from nlosjax.train.stopping import BEST_FOLDER
  best = model / BEST_FOLDER
  return best if (best / str(step)).is_dir() else model / "checkpoints"


def study_run(folder, results) -> dict:
  """What a study's run folder says about its model (module docstring); ValueError naming the file.

  A run of ``experiments.studies.mechanisms`` (``run.json`` with ``budget``, ``row``,
  ``seed``) or of another study whose ``run.json`` names its ``command``,
  ``record`` (its results JSON, for the machine) and ``study`` (what the run is
  within it), e.g. ``experiments.studies.physics_shift``.
  """
  from nlosjax.train import read_selection
  folder = pathlib.Path(folder)
  meta_path = folder / "run.json"
  try:
    meta = json.loads(meta_path.read_text())
    config = meta["config"]
    if "command" in meta:
      command, study, record = meta["command"], dict(meta["study"]), pathlib.Path(meta["record"])
    else:
      budget, row, seed = meta["budget"], meta["row"], int(meta["seed"])
      command = f"python -m experiments.studies.mechanisms --budgets {budget} --rows {row} --seeds {seed}"
      study = {"budget": budget, "row": row, "seed": seed}
      record = pathlib.Path(results) / "mechanisms" / budget / f"{row}-seed{seed}.json"
  except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
    raise ValueError(f"{meta_path}: not a run record of a study ({e})") from None
  variants = list(config.get("train", {}).get("variants", ()))
  if len(variants) != 1:
    raise ValueError(f"{meta_path}: config train.variants is {variants}, expected the one variant trained")
  model = folder / "model"
  selection = read_selection(model)
  if not selection or "stop_reason" not in selection:
    raise ValueError(f"{model / 'selection.json'}: missing or without a stop reason: the run has not finished")
  step = int(selection["step"])
  if step not in selection["val_psnr"]:
    raise ValueError(f"{model / 'selection.json'}: no validation score of the selected step {step}")
  machine = meta.get("machine")
  if machine is None and record.is_file():
    machine = json.loads(record.read_text()).get("machine")
  machine = dict(machine or {})
  return {"kind": "study run", "source": folder, "config": config, "variant": variants[0],
          "checkpoints": _best_checkpoint_folder(model, step), "step": step,
          "recorded_val_psnr": float(selection["val_psnr"][step]),
          "steps_taken": int(selection["steps_taken"]), "stop_reason": selection["stop_reason"],
          "best_step": step, "machine": machine, "machine_source": _shown(record) if machine else None,
          "commit": machine.get("commit", "unknown"),
          "date": machine.get("date") or _mtime(model / "selection.json"),
          "command": command, "study": study}


def state_run(folder, results, preset: str = "cpu") -> dict:
  """What a study's committed run state says about its model (module docstring); ValueError naming the file."""
  from experiments import configs
  from nlosjax.train import read_selection
  from nlosjax.train.run_state import BEST_FILE, PARAMS_FILE, read_meta
  folder = pathlib.Path(folder)
  model = folder / "model"
  budget, name = folder.parent.name, folder.name
  row, sep, seed = name.rpartition("-seed")
  record_path = pathlib.Path(results) / "mechanisms" / budget / f"{name}.json"
  if not sep or not seed.isdigit():
    raise ValueError(f"{folder}: a committed run state is named <row>-seed<k>")
  try:
    record = json.loads(record_path.read_text())
    parts, variant = record["config"], record["variant"]
  except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
    raise ValueError(f"{record_path}: not the run's record ({e})") from None
  # The record keeps the parts of the run's config its numbers depend on; the rest is the preset's.
  config = configs.get_config(preset)
  for section, values in parts.items():
    config[section] = {**config.get(section, {}), **values}
  config["train"]["variants"] = [variant]
  selection = read_selection(model)
  meta = read_meta(model)
  if not selection or "stop_reason" not in selection or meta is None:
    raise ValueError(f"{model}: selection.json with a stop reason and run_state.json needed: the run has not"
                     " finished")
  step = int(selection["step"])
  if step not in selection["val_psnr"] or meta.get("best_step") != step:
    raise ValueError(f"{model}: the selected step {step} is not the best state's ({meta.get('best_step')}) or has"
                     " no validation score")
  machine = dict(record.get("machine") or {})
  return {"kind": "committed run state", "source": folder, "config": config, "variant": variant,
          "params_file": model / (PARAMS_FILE if meta.get("finished") else BEST_FILE),
          "signature": meta.get("signature", {}),
          "data_digest": meta.get("data_digest"), "step": step,
          "recorded_val_psnr": float(selection["val_psnr"][step]),
          "steps_taken": int(selection["steps_taken"]), "stop_reason": selection["stop_reason"],
          "best_step": step, "machine": machine, "machine_source": _shown(record_path),
          "commit": machine.get("commit", "unknown"), "date": machine.get("date") or meta.get("written"),
          "command": f"python -m experiments.studies.mechanisms --budgets {budget} --rows {row} --seeds {seed}"
                     f" --state {_shown(folder.parent.parent)}",
          "study": {"budget": budget, "row": row, "seed": int(seed)}}


def state_params(run: dict, mcfg) -> tuple[dict, dict]:
  """The parameters of a :func:`state_run`'s ``params.npz`` (``best.npz`` before the run's export was
  finished) and a :func:`restore_params`-like record.

  Raises ValueError when the file's step is not the selected one, the model config
  rebuilt from the record is not the one the state's signature recorded, or the file's
  parameters are not the tree that config initialises (a leaf missing, extra or of
  another shape or dtype: :func:`nlosjax.train.run_state.arrays_tree`).
  """
  import jax

  from nlosjax import train
  from nlosjax.train.run_state import arrays_tree
  recorded = run["signature"].get("model")
  if recorded is not None and json.loads(json.dumps(train.model_record(mcfg))) != recorded:
    raise ValueError(f"{run['source']}: the model config rebuilt from its record is not the one its run state"
                     " recorded")
  # The tree the model initialises, as the template run_state reads its exports against.
  shapes = jax.eval_shape(mcfg.module().init, jax.random.key(0),
                          jax.ShapeDtypeStruct(mcfg.input_shape(), np.float32))["params"]
  template = {"params": jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), shapes)}
  with np.load(run["params_file"], allow_pickle=False) as f:
    step = int(f["['step']"])
    arrays = {k: f[k] for k in f.files if k.startswith("['params']")}
  try:
    params = arrays_tree(arrays, template)["params"]
  except ValueError as e:
    raise ValueError(f"{run['params_file']}: {e}") from None
  if step != run["step"]:
    raise ValueError(f"{run['params_file']}: holds step {step}, the selected step is {run['step']}")
  return params, {"step": step, "checkpoint": run["params_file"], "added_fields": []}


def main_job_run(path, variant: str | None) -> dict:
  """What a main-job workdir (or a variant's folder) says about one variant's model."""
  from nlosjax.inference import find_checkpoints
  from nlosjax.train import read_selection
  workdir, variant, ckpt = find_checkpoints(path, variant)
  config_path = workdir / "config.json"
  try:
    config = json.loads(config_path.read_text())
  except (OSError, json.JSONDecodeError) as e:
    raise ValueError(f"{config_path}: not readable ({e})") from None
  folder = ckpt.parent
  selection = read_selection(folder) or {}
  steps = sorted(int(p.name) for p in ckpt.iterdir() if p.name.isdigit())
  step = int(selection.get("step", steps[-1]))
  recorded = selection.get("val_psnr", {}).get(step)
  tr = config.get("train", {})
  stamp = folder / "selection.json" if selection else ckpt / str(step)
  return {"kind": "main-job workdir", "source": folder, "config": config, "variant": variant,
          "checkpoints": _best_checkpoint_folder(folder, step), "step": step,
          "recorded_val_psnr": None if recorded is None else float(recorded),
          "steps_taken": int(selection.get("steps_taken", tr.get("steps", step))),
          "stop_reason": selection.get("stop_reason", "steps"), "best_step": step,
          **_invocations(workdir), "date": _mtime(stamp)}


def _invocations(workdir: pathlib.Path) -> dict:
  """``machine``, ``machine_source``, ``commit`` and ``command`` from ``workdir/invocations.jsonl``.

  ``python -m experiments.train`` appends one record per invocation
  (:func:`experiments.train.record_invocation`). The first record names the
  command, the commit and the machine; a run resumed at other commits says so
  in ``commit``. Without the file (runs from before it existed): commit
  ``"unknown"``, no machine, and a command built from the workdir.
  """
  from experiments.train import INVOCATIONS
  path = workdir / INVOCATIONS
  records = []
  if path.is_file():
    try:
      records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except json.JSONDecodeError as e:
      raise ValueError(f"{path}: not JSON lines ({e})") from None
  if not records:
    return {"machine": {}, "machine_source": None, "commit": "unknown",
            "command": f"python -m experiments.train --workdir {_shown(workdir)}"
                       " (config: the run's config.json)"}
  first = records[0]
  commits = list(dict.fromkeys(r.get("commit", "unknown") for r in records))
  commit = commits[0] + (f" (resumed at {', '.join(commits[1:])})" if len(commits) > 1 else "")
  machine = {k: v for k, v in first.items() if k != "command"}
  return {"machine": machine, "machine_source": _shown(path), "commit": commit,
          "command": first.get("command", "python -m experiments.train")}


def find_run(path, variant: str, results, preset: str = "cpu") -> dict:
  """:func:`study_run` where ``path`` holds ``run.json``, :func:`state_run` where it holds
  ``model/run_state.json``, else :func:`main_job_run`; checks ``variant``."""
  path = pathlib.Path(path)
  if not path.is_dir():
    raise ValueError(f"{path}: no such run folder")
  if (path / "run.json").is_file():
    run = study_run(path, results)
  elif (path / "model" / "run_state.json").is_file():
    run = state_run(path, results, preset)
  else:
    return main_job_run(path, variant)
  if run["variant"] != variant:
    raise ValueError(f"{path}: the run trained variant {run['variant']!r}, not --variant {variant!r}")
  return run


class _Progress:
  """A loader that advances a tqdm bar at every batch (``len`` and ``batch`` as the loader's)."""

  def __init__(self, loader, bar):
    self.loader, self.bar = loader, bar

  def __len__(self):
    return len(self.loader)

  def batch(self, step):
    out = self.loader.batch(step)
    self.bar.update(1)
    return out


def validation_scores(config: dict, data_path, model_config, params, *, split: str = "val") -> dict:
  """The validation score of :func:`nlosjax.evaluation.protocol.validation_psnr`, per frame and per sequence.

  Returns:
    ``{"split", "psnr_db": mean over the split's frames (dB; the same numbers
    and order as ``validation_psnr``), "n_frames", "per_sequence_psnr_db":
    {sequence name: mean over its frames}, "frames_per_sequence": {name: count}}``.
  """
  from tqdm import tqdm

  from nlosjax import metrics, train
  from nlosjax.evaluation import protocol
  batch_size = int(config["train"].get("eval_batch_size", config["train"]["batch_size"]))
  data = protocol.load_split(train.RunConfig.from_dict(config), data_path, split, batch_size=batch_size)
  loader = data["loader"]
  try:
    with tqdm(total=len(loader), desc=f"{split} split", unit="batch", dynamic_ncols=True) as bar:
      images = protocol.model_images(model_config, params, _Progress(loader, bar))
    names = list(loader.names)
  finally:
    loader.close()
  psnr = np.asarray(metrics.psnr(images["intensity"], data["intensity"]))
  sequence = np.asarray(data["sequence"]).astype(int)
  per_seq = {names[s]: float(np.mean(psnr[sequence == s])) for s in sorted(set(sequence.tolist()))}
  counts = {names[s]: int(np.sum(sequence == s)) for s in sorted(set(sequence.tolist()))}
  return {"split": split, "psnr_db": float(np.mean(psnr)), "n_frames": int(psnr.size),
          "per_sequence_psnr_db": per_seq, "frames_per_sequence": counts}


def dataset_facts(data_path, config: dict) -> dict:
  """The dataset file's identity (path, sha256, generator version, creation) after checking it is the config's.

  Raises:
    ValueError: naming the file when it is missing or its data specification
      (everything that decides a sequence's content) differs from the config's.
  """
  import h5py

  from nlosjax.data.dataset import DatasetSpec
  from nlosjax.pretrained import sha256_file
  data_path = pathlib.Path(data_path)
  if not data_path.is_file():
    raise ValueError(f"{data_path}: the run's dataset file is missing (config data.path); make it with"
                     " python -m experiments.make_dataset and the run's config, or pass --data")
  spec = DatasetSpec.from_config(config["data"])
  try:
    with h5py.File(data_path, "r") as f:
      attrs = {k: f.attrs[k] for k in ("spec", "generator_version", "created") if k in f.attrs}
    stored = DatasetSpec.from_config(json.loads(attrs["spec"]))
  except (OSError, KeyError, ValueError) as e:
    raise ValueError(f"{data_path}: not a readable nlosjax dataset ({e})") from None
  if stored.generation_key() != spec.generation_key():
    raise ValueError(f"{data_path}: its data specification differs from the run config's data section,"
                     " so the config does not describe the data the model was selected on")
  return {"path": str(data_path), "sha256": sha256_file(data_path),
          "generator_version": str(attrs.get("generator_version")), "created": str(attrs.get("created")),
          "num_sequences": stored.to_dict()["num_sequences"]}


def export(run_path, name: str, variant: str, *, command: str | None = None, commit: str | None = None,
           results=MECHANISM_RECORDS, data=None, root=None, overwrite: bool = False,
           tolerance_db: float = TOLERANCE_DB, export_command: str = "", preset: str = "cpu",
           log=print) -> dict:
  """Export one finished run (module docstring); returns the provenance written.

  Raises:
    ValueError: an unfinished or unreadable run, a missing dataset, or a
      recomputed validation score more than ``tolerance_db`` from the recorded one.
  """
  import jax

  from experiments.provenance import cpu_model, git_commit
  from nlosjax import inference, pretrained, train
  from nlosjax.data.dataset import DatasetSpec
  t0 = time.perf_counter()
  folder = pretrained.weights_folder(name, variant, root)
  if folder.exists() and not overwrite:
    raise ValueError(f"{folder}: exists; pass --overwrite to replace it")
  run = find_run(run_path, variant, results, preset)
  config = run["config"]
  typed = train.RunConfig.from_dict(config)
  mcfg = train.model_config_for(typed, inference.training_setup(typed), variant)
  if "params_file" in run:
    params, restored = state_params(run, mcfg)
  else:
    params, restored = inference.restore_params(run["checkpoints"], mcfg, step=run["step"],
                                                config_file=run["source"])
  params = jax.tree.map(np.asarray, params)
  log(f"restored step {restored['step']} from {restored['checkpoint']} ({time.perf_counter() - t0:.1f} s)"
      + (f"; its recorded model config predates the fields {restored['added_fields']} (at their defaults)"
         if restored["added_fields"] else ""))
  data_path = pathlib.Path(data if data is not None else config["data"]["path"])
  dataset = dataset_facts(data_path, config)
  if run.get("data_digest"):
    from nlosjax.data.dataset import dataset_identity
    digest = dataset_identity(data_path)[0]
    if digest != run["data_digest"]:
      raise ValueError(f"{data_path}: content digest {digest}, the run trained on {run['data_digest']}:"
                       " not the run's data")
  t1 = time.perf_counter()
  val = validation_scores(config, data_path, mcfg, params)
  log(f"validation: {val['psnr_db']:.6f} dB over {val['n_frames']} frames of {data_path}"
      f" ({time.perf_counter() - t1:.1f} s); recorded {run['recorded_val_psnr']}")
  recorded = run["recorded_val_psnr"]
  if recorded is None:
    log("note: the run recorded no validation score for this step; the recomputed one is recorded alone")
  elif not abs(val["psnr_db"] - recorded) <= tolerance_db:      # a NaN score fails too
    raise ValueError(f"{run['source']}: the validation PSNR recomputed on {data_path} is"
                     f" {val['psnr_db']:.6f} dB, the run recorded {recorded:.6f} dB (difference"
                     f" {val['psnr_db'] - recorded:+.6f} dB > {tolerance_db:g} dB): the data or the"
                     " model code changed since training; not exported")
  spec = DatasetSpec.from_config(config["data"])
  prov = {
      "command": command or run["command"],
      "commit": commit or run["commit"],
      "date": run["date"],
      "machine": run["machine"],
      "machine_source": run["machine_source"],
      "source": {"kind": run["kind"], "run": _shown(run["source"]),
                 "checkpoint": _shown(restored["checkpoint"]), **run.get("study", {})},
      "config": config,
      "data_spec": spec.to_dict(),
      "data_seed": spec.seed,
      "dataset": dataset,
      "training_seed": int(config.get("train", {}).get("seed", 0)),
      "steps_taken": run["steps_taken"],
      "stop_reason": run["stop_reason"],
      "best_step": run["best_step"],
      "validation": {**val, "data": _shown(data_path), "recorded_psnr_db": recorded,
                     "metric": "mean over the split's frames of the intensity PSNR (dB), the model's"
                               " intensity clamped to [0, 1] (nlosjax.evaluation.protocol.validation_psnr);"
                               " per sequence: the mean over that sequence's frames"},
      "model_config": train.model_record(mcfg),
      "param_fingerprint": train.param_fingerprint(params),
      "exported": {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                   "commit": git_commit(), "command": export_command, "cpu": cpu_model(),
                   "python": platform.python_version(), "jax": jax.__version__, "numpy": np.__version__},
  }
  if restored["added_fields"]:
    prov["checkpoint_model_config"] = {"recorded": restored["recorded_model"],
                                       "added_fields": restored["added_fields"]}
  # Written beside the destination and read back there first: a failed check leaves nothing in place.
  folder.parent.mkdir(parents=True, exist_ok=True)
  stage = pathlib.Path(tempfile.mkdtemp(prefix=".export-", dir=folder.parent))
  try:
    written = pretrained.write_weights(stage / folder.name, params, prov)
    got_cfg, got, _ = inference.load_pretrained(name, variant, root=stage)
    same = jax.tree.map(lambda a, b: bool(np.array_equal(np.asarray(a), b)), got, params)
    if got_cfg != mcfg or not all(jax.tree.leaves(same)):
      raise RuntimeError(f"{stage / folder.name}: reading the weights back does not give the exported model")
    if folder.exists():
      shutil.rmtree(folder)                 # --overwrite (checked above)
    os.replace(stage / folder.name, folder)
  finally:
    shutil.rmtree(stage, ignore_errors=True)
  size = (folder / pretrained.PARAMS_FILE).stat().st_size
  log(f"wrote {_shown(folder)}: {pretrained.PARAMS_FILE} {size / 1024:.1f} KiB ({written['num_params']}"
      f" parameters), sha256 {written['params_sha256'][:16]}...; total {time.perf_counter() - t0:.1f} s")
  return written


def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m experiments.export_weights", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("run", help="a mechanism-study run folder, a study's committed run state, or a main-job"
                             " workdir (or variant folder)")
  p.add_argument("--name", required=True, help="weights name, e.g. cpu (folder nlosjax/weights/<name>-<variant>)")
  p.add_argument("--variant", required=True, choices=tuple(VARIANTS))
  p.add_argument("--command", default=None, help="the training command to record (default: see above)")
  p.add_argument("--commit", default=None, help="the training commit to record (default: the run's record)")
  p.add_argument("--results", default=str(MECHANISM_RECORDS),
                 help="where the mechanism study's run records are (default experiments/studies/mechanisms/results)")
  p.add_argument("--data", default=None, help="dataset file (default: the run config's data.path)")
  p.add_argument("--root", default=None, help="weights folder (default: nlosjax/weights of this checkout)")
  p.add_argument("--tolerance-db", type=float, default=TOLERANCE_DB,
                 help="largest accepted |recomputed - recorded| validation PSNR, dB (default 1e-3)")
  p.add_argument("--overwrite", action="store_true", help="replace existing weights of that name")
  p.add_argument("--preset", default="cpu",
                 help="a committed run state: the preset its study ran on (default cpu)")
  args = p.parse_args(argv)
  argv = sys.argv[1:] if argv is None else list(argv)
  try:
    export(args.run, args.name, args.variant, command=args.command, commit=args.commit,
           results=args.results, data=args.data, root=args.root, overwrite=args.overwrite,
           tolerance_db=args.tolerance_db, preset=args.preset,
           export_command="python -m experiments.export_weights " + " ".join(argv))
  except ValueError as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  return 0


if __name__ == "__main__":
  sys.exit(main())

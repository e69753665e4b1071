"""The runs of :mod:`experiments.studies.headroom`: sets, choices on validation, per-frame records.

Every record is one JSON file under ``RESULTS/headroom/``:

* ``choices.json``: what the validation split chose (the classic methods' settings and surface
  thresholds, :func:`nlosjax.evaluation.baselines.tune`; each learned model's surface threshold,
  :func:`nlosjax.evaluation.protocol.tune_model_thresholds`; the bilinear reading's surface cut;
  for each score, the *reference* classic method with the best validation mean; each reference
  method's settings and threshold for each better input, chosen on validation fed that input);
* ``<set>/attributes.json``: each evaluated frame's sequence, frame and attributes
  (:func:`experiments.studies.headroom.breakdown.frame_attributes`);
* ``<set>/<method>.json``: a method's per-frame scores on the set
  (:data:`nlosjax.evaluation.scores.METRICS`), ``<set>`` one of ``val``, ``test``,
  ``independent``, ``heldout-<condition>``.

A record that exists is not recomputed (a model's is, where its ``--model`` names another run
than the record's), so the command resumes anywhere, and the report is rebuilt from the
records alone.
"""

from __future__ import annotations

import json
import pathlib
from typing import Callable

import numpy as np

from experiments.studies.headroom import bounds, breakdown
from nlosjax.evaluation import baselines
from nlosjax.variants import OURS, OURS_S

__all__ = ["CLASSIC", "ZERO", "TRUTH", "INPUTS", "OBJECT_SCORES", "REFERENCE_SCORES", "DEFAULT_MODELS",
           "HELDOUT_CONDITIONS", "preset", "set_files", "reference_classic", "oracle", "load_records", "Study"]

#: The classic methods, in table order.
CLASSIC = ("fbp", "lct", "fk", "phasor", "rsd")
#: The all-zero image: the floor of every score.
ZERO = "zero"
#: The truth read through the input's scan grid (:mod:`~experiments.studies.headroom.bounds`).
TRUTH = tuple(f"truth_{r}" for r in bounds.READINGS)
#: Better inputs than the network's, each fed to the reference classic methods as chosen on validation:
#: ``clean`` the noise-free transient at the same 8 x 8 points (the file's stored ``clean``: no Poisson
#: noise, ambient light, dark counts or jitter), ``full`` the noisy capture at every scan point the
#: input is cut from, ``clean_full`` both. Record ``<method>@<input>``.
INPUTS = ("clean", "full", "clean_full")
#: The object scores the study is about.
OBJECT_SCORES = ("intensity_mae_object", "psnr_balanced", "rmse_object", "recall", "precision", "f1")
#: The scores a reference classic method is chosen for: the object scores and the whole-image PSNR (the
#: main job's choice of the best classic method), the guard beside them.
REFERENCE_SCORES = OBJECT_SCORES + ("psnr",)
#: The networks scored when no ``--model`` is given: the shipped ``cpu`` weights.
DEFAULT_MODELS = {OURS: f"pretrained:cpu/{OURS}", OURS_S: f"pretrained:cpu/{OURS_S}"}
#: The held-out renderer's conditions scored by default: its base and the conditions that move one
#: of the breakdown's attributes (object size, depth, photons); the other conditions change the
#: physics, which the physics_shift study covers.
HELDOUT_CONDITIONS = ("base", "small", "large", "far", "tenth", "bright")


def preset(tiny_dir: pathlib.Path | None = None) -> dict:
  """The ``cpu`` preset's config dict (with ``--tiny``: the tiny run's, its files under ``tiny_dir``)."""
  from experiments import configs
  if tiny_dir is None:
    return configs.get_config("cpu")
  from experiments.tiny_run import tiny_config
  cfg = tiny_config(pathlib.Path(tiny_dir) / "tiny.h5")
  cfg["independent"] = {"path": str(pathlib.Path(tiny_dir) / "tiny-independent.h5"), "sequences": 2,
                        "frames": 4, "seed": 2026}
  return cfg


def set_files(cfg: dict, sets, conditions, log: Callable[[str], None] = print, *, tiny: bool = False
              ) -> dict:
  """``set name -> (path, split)`` of every set scored, each file written where absent.

  ``val`` (choices only) and ``test`` are the preset's own splits; ``independent`` is the preset's
  independent set (:mod:`experiments.independent_set`); ``heldout-<condition>`` the held-out
  renderer's sets at the preset's capture (:mod:`experiments.studies.physics_shift.heldout`, the
  files, seed and sizes of that study).
  """
  from experiments.independent_set import ensure_independent_set
  from experiments.studies.physics_shift import heldout
  from experiments.studies.physics_shift import study as shift
  from nlosjax import train as T
  data_path = pathlib.Path(cfg["data"]["path"])
  T.ensure_dataset(T.RunConfig.from_dict(cfg), data_path, log=log)
  out = {"val": (data_path, "val")}
  if "test" in sets:
    out["test"] = (data_path, "test")
  if "independent" in sets:
    ind = cfg["independent"]
    out["independent"] = (ensure_independent_set(ind["path"], cfg["data"], ind["sequences"], ind["frames"],
                                                  ind["seed"], log=log), "test")
  if "heldout" in sets:
    n = 2 if tiny else shift.SEQUENCES
    frames = 4 if tiny else shift.FRAMES
    for cond in conditions:
      path = (data_path.with_name(f"tiny-heldout-{cond}.h5") if tiny else shift.heldout_path(cfg, cond))
      out[f"heldout-{cond}"] = (heldout.ensure_condition(path, cfg["data"], cond, n, frames,
                                                         shift.HELDOUT_SEED), "test")
  return out


def _read(path: pathlib.Path) -> dict:
  return json.loads(path.read_text())


def _arrays(record: dict) -> dict:
  """A record's per-frame scores as float64 arrays (JSON null -> NaN)."""
  return {k: np.asarray(v, np.float64) for k, v in record["scores"].items()}


def load_records(results: pathlib.Path) -> dict:
  """``{"choices": ..., "sets": set -> {"attributes": ..., "methods": method -> record}}`` from the files."""
  root = pathlib.Path(results) / "headroom"
  out = {"choices": _read(root / "choices.json") if (root / "choices.json").exists() else {}, "sets": {},
         "invocations": _read(root / "invocations.json")["invocations"] if (root / "invocations.json").exists()
         else []}
  for folder in sorted(p for p in root.iterdir() if p.is_dir()) if root.exists() else []:
    attrs = folder / "attributes.json"
    if not attrs.exists():
      continue
    a = _read(attrs)
    entry = {"path": a["path"], "split": a["split"], "sequence": np.asarray(a["sequence"], np.int64),
             "frame": np.asarray(a["frame"], np.int64), "name": a["name"],
             "attributes": {k: np.asarray(a["attributes"][k], np.float64) for k in breakdown.ATTRIBUTES},
             "methods": {}}
    for p in sorted(folder.glob("*.json")):
      if p.name == "attributes.json":
        continue
      r = _read(p)
      if r["sequence"] != a["sequence"] or r["frame"] != a["frame"]:
        raise ValueError(f"{p}: its frames are not those of {attrs}; delete the set's folder to rescore it")
      entry["methods"][r["method"]] = {**r, "scores": _arrays(r)}
    out["sets"][folder.name] = entry
  return out


def oracle(method: str, source: str) -> str:
  """The record name of classic ``method`` fed input ``source`` (:data:`INPUTS`)."""
  return f"{method}@{source}"


def reference_classic(means: dict) -> dict:
  """``metric -> method``: for each of :data:`REFERENCE_SCORES` the method of ``means`` (``method -> metric
  -> mean``, in priority order) with the best mean; ties keep the earlier."""
  from nlosjax.evaluation.scores import HIGHER_IS_BETTER
  out = {}
  for metric in REFERENCE_SCORES:
    sign = 1.0 if HIGHER_IS_BETTER[metric] else -1.0
    order = list(means)
    out[metric] = max(order, key=lambda m: (sign * means[m][metric], -order.index(m)))
  return out


def weights_identity(spec: str) -> str:
  """``spec`` as records store it: ``pretrained:NAME/VARIANT`` gets ``@sha256:<first 12>`` of the
  shipped ``params.npz`` (weights replaced under the same name are other weights); a run folder is
  itself."""
  if not spec.startswith("pretrained:"):
    return spec
  from nlosjax import pretrained
  from nlosjax.variants import OURS
  name, _, variant = spec[len("pretrained:"):].partition("/")
  sha = pretrained.sha256_file(pretrained.weights_folder(name, variant or OURS) / "params.npz")
  return f"{spec}@sha256:{sha[:12]}"


class Study:
  """Scores every method on every set into ``results/headroom/``, each record once.

  Args:
    cfg: the preset's config dict (:func:`preset`).
    results: the results folder (records under ``results/headroom``).
    models: ``label -> RUN`` (a study run folder or ``pretrained:NAME/VARIANT``).
    methods: the classic methods to score.
    log: progress lines.
  """

  def __init__(self, cfg: dict, results, models: dict, methods=CLASSIC, log: Callable[[str], None] = print):
    from experiments.studies.mechanisms import write_json
    from nlosjax import train as T
    self.cfg, self.typed = cfg, T.RunConfig.from_dict(cfg)
    self.root = pathlib.Path(results) / "headroom"
    self.models, self.methods, self.log = dict(models), tuple(methods), log
    # What a record was made with: the spec, and for shipped weights their sha256 too, so records of
    # weights that have since been replaced are scored again.
    self.specs = {label: weights_identity(spec) for label, spec in self.models.items()}
    self._write_json = write_json
    self._loaded = {}

  # ------------------------------------------------------------------ helpers
  def _path(self, set_name: str, method: str) -> pathlib.Path:
    return self.root / set_name / f"{method}.json"

  def _write(self, path: pathlib.Path, obj: dict) -> None:
    from experiments.studies.mechanisms import machine
    self._write_json(path, {**obj, "machine": machine()})

  def model(self, label: str):
    """``(model_config, params)`` of ``--model`` ``label`` (loaded once)."""
    if label not in self._loaded:
      from experiments.studies.generalisation import load_model
      mcfg, params, _ = load_model(self.models[label])
      self._loaded[label] = (mcfg, params)
    return self._loaded[label]

  def _truth(self, path, split):
    from nlosjax.evaluation import protocol
    data = protocol.load_split(self.typed, path, split, batch_size=self.typed.train.eval_batch)
    data["loader"].close()
    return data

  # ------------------------------------------------------------------ choices
  def choices(self, val_path) -> dict:
    """What validation chooses (module docstring); read from ``choices.json`` where it holds it."""
    from experiments.main_job import tune_classic
    from nlosjax.evaluation import protocol
    path = self.root / "choices.json"
    ch = _read(path) if path.exists() else {}
    changed = False
    missing = [m for m in self.methods if m not in ch.get("classic", {})]
    if missing:
      self.log(f"validation: tuning the classic methods {missing} ...")
      tuned = tune_classic(self.typed, val_path, self.log)
      ch["classic"] = {**ch.get("classic", {}), **{m: tuned[m] for m in self.methods if m in tuned}}
      changed = True
    models = ch.setdefault("models", {})
    for label, spec in self.specs.items():
      if models.get(label, {}).get("spec") != spec:
        tuned = protocol.tune_model_thresholds(self.typed, val_path, {label: [self.model(label)]}, log=self.log)
        models[label] = {"spec": spec, **tuned[label]}
        changed = True
    if "bound" not in ch:
      data = self._truth(val_path, "val")
      ch["bound"] = self._choose_cut(data)
      changed = True
    if changed:
      self._write(path, ch)
    return ch

  def _choose_cut(self, data) -> dict:
    from nlosjax import metrics
    f1 = {}
    for cut in bounds.CUTS:
      _, depth = bounds.bound_images(data["intensity"], data["depth"], data["stride"], "bilinear", cut)
      f1[str(cut)] = float(np.nanmean(np.asarray(metrics.surface_scores(depth, data["depth"])["f1"])))
    best = max(f1, key=lambda c: (f1[c], -list(f1).index(c)))
    self.log(f"validation: the bilinear bound's surface cut {best} (surface F1 {f1[best]:.3f})")
    return {"cut": float(best), "f1": f1[best], "f1_by_cut": f1}

  def reference(self, val: dict) -> dict:
    """For each object score, the classic method with the best mean on the validation records ``val``
    (``method -> record``; ties: the earlier in :data:`CLASSIC`), written into ``choices.json``."""
    path = self.root / "choices.json"
    ch = _read(path)
    means = {m: {k: float(np.nanmean(val[m]["scores"][k])) for k in REFERENCE_SCORES} for m in CLASSIC if m in val}
    ref = reference_classic(means)
    if ch.get("reference") != ref or ch.get("validation_means") != means:
      ch.update(reference=ref, validation_means=means)
      self._write(path, ch)
    return ref

  def oracle_choices(self, val_path) -> dict:
    """Each reference method's settings and surface threshold for each better input, chosen on the
    validation split fed that input (:func:`nlosjax.evaluation.baselines.tune`); kept in ``choices.json``."""
    path = self.root / "choices.json"
    ch = _read(path)
    refs = sorted(set(ch["reference"].values()) & set(self.methods))
    have = ch.setdefault("oracle", {})
    missing = [(src, m) for src in INPUTS for m in refs if m not in have.get(src, {})]
    if missing:
      data = self._truth(val_path, "val")
      inputs = self._better_inputs(val_path, "val", data)
      for src, m in missing:
        self.log(f"validation: tuning {m} on the {src} input ...")
        x, stride = inputs[src]
        tuned = baselines.tune(x, data["intensity"], data["depth"], data["setup"], stride, methods=(m,),
                               batch_size=self.typed.train.eval_batch, log=self.log)[m]
        have.setdefault(src, {})[m] = tuned
      self._write(path, ch)
    return have

  def log_invocation(self, args: str, wall_s: float) -> None:
    """Append this invocation's arguments and wall time to ``invocations.json`` (the report lists them)."""
    import datetime
    path = self.root / "invocations.json"
    runs = _read(path)["invocations"] if path.exists() else []
    runs.append({"args": args, "wall_s": round(wall_s, 1),
                 "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")})
    self._write_json(path, {"invocations": runs})

  def _better_inputs(self, path, split, data) -> dict:
    """``source -> ([N, T, h, w] counts, stride)`` of each of :data:`INPUTS`, on ``data``'s frames in order."""
    from nlosjax.data.dataset import TripletLoader
    from nlosjax.data.dataset.undersampling import undersample
    opts = self.typed.data.loader
    loader = TripletLoader(path, split=split, batch_size=self.typed.train.eval_batch, stride=1, offset=0,
                           shuffle=False, drop_remainder=False, ends=opts.ends, target="clean")
    noisy, clean, seq, frm = [], [], [], []
    try:
      for step in range(len(loader)):
        b = loader.batch(step)
        noisy.append(b["measurement"][:, b["measurement"].shape[1] // 2])
        clean.append(b["transient"])
        seq.append(b["sequence"])
        frm.append(b["frame"])
    finally:
      loader.close()
    if not (np.array_equal(np.concatenate(seq), data["sequence"])
            and np.array_equal(np.concatenate(frm), data["frame"])):
      raise RuntimeError(f"{path}: the full-grid loader reads other frames than the protocol's")
    noisy, clean = np.concatenate(noisy), np.concatenate(clean)
    stride = data["stride"]
    return {"clean": (undersample(clean, stride, stride // 2), stride), "full": (noisy, 1),
            "clean_full": (clean, 1)}

  # ------------------------------------------------------------------ scoring
  def score_set(self, set_name: str, path, split: str, choices: dict, *, learned: bool = True) -> None:
    """Every method's record on one set (those that exist are kept); ``learned=False``: no model and no
    better input (the validation split, where the references are chosen)."""
    from nlosjax.evaluation import protocol, scores
    folder = self.root / set_name
    data = None
    frames = None
    attrs_path = folder / "attributes.json"
    if attrs_path.exists():
      a = _read(attrs_path)
      frames = {"sequence": a["sequence"], "frame": a["frame"]}
    todo = [m for m in self.methods if not self._path(set_name, m).exists()]
    todo += [label for label, spec in (self.specs.items() if learned else ())
             if not self._path(set_name, label).exists()
             or _read(self._path(set_name, label)).get("spec") != spec]
    fixed = [m for m in (ZERO, *TRUTH) if not self._path(set_name, m).exists()]
    refs = sorted(set(choices.get("reference", {}).values()) & set(self.methods)) if learned else []
    oracles = [(m, src) for m in refs for src in INPUTS if not self._path(set_name, oracle(m, src)).exists()]
    if frames is None or fixed or todo or oracles:
      data = self._truth(path, split)
      seq, frm = data["sequence"].tolist(), data["frame"].tolist()
      if frames is not None and (frames["sequence"] != seq or frames["frame"] != frm):
        raise ValueError(f"{attrs_path}: the file {path} now holds other frames; delete {folder} to rescore")
      if frames is None:
        attrs = breakdown.frame_attributes(path, split, data["sequence"], data["frame"], data["depth"])
        name = attrs.pop("name")
        self._write(attrs_path, {"set": set_name, "path": str(path), "split": split, "sequence": seq,
                                 "frame": frm, "name": name, "attributes": attrs})
        frames = {"sequence": seq, "frame": frm}
    base = {"set": set_name, **frames}
    metrics = scores.METRICS

    def record(method, inten, depth, **extra):
      s = scores.frame_scores(inten, depth, data["intensity"], data["depth"])
      self._write(self._path(set_name, method), {**base, "method": method, **extra,
                                                  "scores": {k: s[k] for k in metrics}})

    for m in fixed:
      if m == ZERO:
        z = np.zeros_like(data["intensity"])
        record(ZERO, z, z)
      else:
        reading = m.split("_", 1)[1]
        cut = choices["bound"]["cut"] if reading == "bilinear" else 1.0
        i, d = bounds.bound_images(data["intensity"], data["depth"], data["stride"], reading, cut)
        record(m, i, d, cut=cut)
    if oracles:
      inputs = self._better_inputs(path, split, data)
      for m, src in oracles:
        self.log(f"[{set_name}] {oracle(m, src)} ...")
        x, stride = inputs[src]
        setting = choices["oracle"][src][m]
        out_i, out_d = [], []
        for s in range(0, len(x), self.typed.train.eval_batch):
          i, d = baselines.classic_images(x[s:s + self.typed.train.eval_batch], data["setup"], stride, m,
                                          setting["options"], setting["threshold"])
          out_i.append(i)
          out_d.append(d)
        record(oracle(m, src), np.concatenate(out_i), np.concatenate(out_d), options=setting["options"],
               threshold=setting["threshold"], input=src)
    for m in todo:
      self.log(f"[{set_name}] {m} ...")
      if m in self.methods:
        ev = protocol.evaluate(self.typed, path, {}, split=split, methods=(m,),
                               classic_settings={m: choices["classic"][m]}, log=self.log)
        extra = {"options": choices["classic"][m]["options"], "threshold": choices["classic"][m]["threshold"]}
      else:
        th = choices["models"][m]["threshold"]
        ev = protocol.evaluate(self.typed, path, {m: [self.model(m)]}, split=split, methods=(),
                               model_thresholds={m: th}, log=self.log)
        extra = {"spec": self.specs[m], "threshold": th}
      s = {k: np.asarray(v, np.float64).reshape(-1) for k, v in ev["scores"][m].items() if k in metrics}
      self._write(self._path(set_name, m), {**base, "method": m, **extra, "scores": s})

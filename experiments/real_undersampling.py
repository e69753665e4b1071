"""Under-scanning on measured scans: every method on 16 x 16 and 8 x 8 subsets of real 64 x 64 scans.

    python -m experiments.real_undersampling                      # -> benchmarks/results/real.md
    python -m experiments.real_undersampling --data-dir DIR --checkpoint runs/real --out FILE.md
    python -m experiments.real_undersampling --pretrained cpu --no-timing

Protocol (the paper's under-scanning experiment, on measured data):

* each 64 x 64 scan (O'Toole et al. 2018 ``lct_mat`` files: ``--data-dir``,
  default ``../shared/data/real`` next to the repository when it exists, else
  the shipped exit-sign scan) is loaded with the published preparation
  (16 ps, 512 bins);
* the references are the five classic reconstructions of the full 64 x 64
  scan (FBP, LCT, f-k, phasor, RSD with the options below); their intensity
  images (max over depth, normalised) are the targets. A method is scored
  against every reference except its own full-scan image (a phasor-only
  reference favours phasor and RSD by construction), one column each, and
  their mean is its score;
* the scan is interval-sampled with stride 4 (16 x 16) and 8 (8 x 8) at the
  points ``stride // 2 + stride i`` (the network's convention);
* classic methods (FBP, LCT, f-k, phasor, RSD) reconstruct the sparse scan
  linearly interpolated back to 64 x 64 (``nlosjax.evaluation.baselines.upsample_scan``), with
  the options these retroreflective scenes were published with (LCT snr 0.8
  and FBP with the t^2 falloff; f-k, phasor, RSD defaults);
* the trained networks (Ours-S, Ours and, where trained, USM of ``--checkpoint``,
  e.g. ``runs/real``: ``python -m experiments.train --config real --workdir
  runs/real``, trained on synthetic 64 x 64 scans of a 0.6 m wall at stride 4
  with 64 ps bins; see ``experiments/configs/real.py``; without
  ``--checkpoint``, the weights shipped inside the package under
  ``--pretrained NAME``, default ``real``, each variant shipped under that
  name; ``--checkpoint none``: classic methods only) read the sparse scan
  with time summed to the trained bin width (4 x 16 ps), the physics layer
  rebuilt for the scan's wall and grid
  (``nlosjax.inference.adapt_to_capture``). At their trained stride they
  output the 64 x 64 grid directly. At twice that stride (8) the network keeps
  its trained stride and outputs a 32 x 32 grid of every other scan point
  (full-grid points ``0, 2, ..., 62``, so its inputs ``2 + 4 i`` are the full
  grid's ``4 + 8 i``), which is linearly interpolated to 64 x 64. "Ours" reads
  each static scan as three identical frames;
* scores: intensity PSNR (dB) and SSIM (``nlosjax.metrics``) against each
  reference, per scene and averaged over scenes. Nothing is tuned on these
  scenes;
* to separate what the networks' time bins cost from what the networks do,
  phasor and RSD are also scored on the sparse scans summed to the networks'
  bins (:func:`binned_classic`).

An in-domain check runs the same code on the networks' own data (the synthetic
test split of ``--synthetic``, default the checkpoint's own dataset when present,
scored against its ground truth), to tell a reading or adaptation bug from the
synthetic-to-real gap.

To tell what the networks' learned parts give or take on measured scans, each
ST-Mamba network also runs with its refinement zeroed, and with both its
spreading residual and its refinement zeroed (the interpolated scan through its
physics layer; :func:`ablated_models`; ``--no-ablation`` skips it).

Each method's seconds per scan, as the run above measured them (its first call,
with tracing and compilation, and the median over scenes of a second call on the
same scan), go in a table under the scores. Also times ``python -m
experiments.reconstruct`` against the NumPy/SciPy twins of the public
algorithms (``experiments/numpy_twins.py``) for LCT, f-k and phasor on one
64 x 64 x 512 scan (``--no-timing`` skips it).

Writes the Markdown report (``--out``, say ``real.md``) and, beside it, ``real_<scene>.png``
(one image row per method, columns full scan / 16 x 16 / 8 x 8) and
``real_summary.png`` (mean PSNR and SSIM per method and input), named after the
report's stem (``real_public.md`` writes ``real_public_<scene>.png``).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
CLASSIC = ("fbp", "lct", "fk", "phasor", "rsd")
VARIANTS = ("ours_s", "ours", "usm")
LABELS = {"fbp": "FBP", "lct": "LCT", "fk": "f-k", "phasor": "Phasor", "rsd": "RSD",
          "ours_s": "Ours-S", "ours": "Ours", "usm": "USM"}
#: Options of the classic methods on these retroreflective scans (O'Toole et al. 2018: snr 0.8, t^2).
OPTIONS = {"fbp": {"falloff": "retroreflective"}, "lct": {"snr": 0.8, "falloff": "retroreflective"},
           "fk": {}, "phasor": {}, "rsd": {}}
#: The full-scan reconstructions a sparse-scan image is scored against (each but its own).
REFERENCES = CLASSIC
#: Bin width of the measured scans after the published preparation (s).
CAPTURE_BIN_WIDTH = 16e-12
#: Shipped weights used when neither --checkpoint nor --pretrained is given.
DEFAULT_PRETRAINED = "real"


def default_files(data_dir=None) -> list[pathlib.Path]:
  """The real scans: ``data_dir/*.mat``, else ``../shared/data/real``, else the shipped scan."""
  from nlosjax.data import io
  if data_dir is not None:
    files = sorted(pathlib.Path(data_dir).glob("*.mat"))
    if not files:
      raise SystemExit(f"--data-dir {data_dir}: no .mat file")
    return files
  shared = REPO.parent / "shared" / "data" / "real"
  if shared.is_dir() and sorted(shared.glob("*.mat")):
    return sorted(shared.glob("*.mat"))
  return [io.shipped_scan_path()]


def scene_name(path: pathlib.Path) -> str:
  stem = path.stem
  return stem[5:] if stem.startswith("data_") else stem


def interpolate_every_other(image: np.ndarray, full: int) -> np.ndarray:
  """``[..., n, n]`` on full-grid points ``0, 2, ..., 2 (n - 1)`` -> ``[..., full, full]`` (linear, edges held)."""
  n = image.shape[-1]
  pos = np.clip(np.arange(full) / 2.0, 0, n - 1)
  lo = np.minimum(np.floor(pos).astype(int), n - 2)
  frac = pos - lo
  m = np.zeros((full, n))
  m[np.arange(full), lo] += 1 - frac
  m[np.arange(full), lo + 1] += frac
  return np.einsum("Hh,...hw,Ww->...HW", m, image, m)


def classic_intensity(transient, setup, method: str, stride: int, options=None) -> np.ndarray:
  """Intensity ``[H, W]`` of a classic method on the scan under-scanned by ``stride`` (1: full)."""
  from experiments.reconstruct import reconstruct_classic
  options = OPTIONS[method] if options is None else options
  _, intensity, _ = reconstruct_classic(transient[None], setup, method, options,
                                        stride if stride > 1 else None)
  return intensity[0]


def model_intensity(trained, transient, setup, stride: int) -> np.ndarray:
  """Intensity ``[H, W]`` of a trained network on the scan under-scanned by ``stride``.

  ``trained``: ``(model_config, params)``, or ``(model_config, params, True)`` to fit the
  network to the scan first (:func:`nlosjax.adaptation.adapt`, its defaults, the
  retroreflective forward model of these targets).
  """
  import dataclasses

  from nlosjax import inference as cio
  from nlosjax.models.network import underscan
  mcfg, params, *fit = trained
  H, W = setup.grid

  def apply(model_config, sparse):
    p = params
    if fit and fit[0]:
      from nlosjax.adaptation import adapt
      p = adapt(model_config, params, sparse[None], falloff="retroreflective").params
    return cio.run_model(model_config, p, sparse[None])["intensity"][0]

  if stride == mcfg.stride:
    adapted = cio.adapt_to_capture(mcfg, setup)
    sparse = np.asarray(underscan(adapted.prepare(transient), stride))
    return apply(adapted.model_config, sparse)
  if stride == 2 * mcfg.stride:
    # Output grid: every other full-grid point (0, 2, ..., H - 2), spanning (H - 2) spacings.
    half = dataclasses.replace(setup, grid=(H // 2, W // 2),
                               wall_size=setup.wall_size * (H - 2) / (H - 1))
    adapted = cio.adapt_to_capture(mcfg, half)
    sparse = np.asarray(underscan(adapted.prepare(transient), stride))   # full-grid 4 + 8 i
    assert sparse.shape[-2:] == adapted.model_config.input_grid
    image = apply(adapted.model_config, sparse)
    return np.clip(interpolate_every_other(image, H), 0.0, 1.0)
  raise ValueError(f"the network was trained on stride {mcfg.stride}; stride {stride} is not supported")


def load_models(checkpoint=None, pretrained=None, log=print) -> dict:
  """``variant -> (model_config, params)``: every variant of ``checkpoint``, else the shipped ``pretrained`` ones.

  ``checkpoint``: a training run (workdir, variant folder or checkpoints
  folder); its variants that are not trained are skipped. Without it,
  every variant shipped under ``pretrained`` (default :data:`DEFAULT_PRETRAINED`;
  :func:`nlosjax.inference.load_pretrained`).

  Raises:
    ValueError: both given, or no weights shipped under ``pretrained`` (the
      message lists the shipped names).
  """
  from nlosjax import inference as cio
  trained = {}
  if checkpoint is not None:
    if pretrained is not None:
      raise ValueError(f"--checkpoint {checkpoint} and --pretrained {pretrained}: give one")
    for v in VARIANTS:
      try:
        mcfg, params, info = cio.load_trained(checkpoint, v)
      except ValueError as e:
        log(f"skipping {v}: {e}")
        continue
      trained[v] = (mcfg, params)
      log(f"{LABELS[v]}: step {info['step']} of {info['checkpoint']}")
    return trained
  name = pretrained or DEFAULT_PRETRAINED
  shipped = cio.pretrained_names()
  variants = [v for v in VARIANTS if (name, v) in shipped]
  if not variants:
    have = ", ".join(f"{n} ({v})" for n, v in shipped) or "none"
    raise ValueError(f"no shipped weights named {name!r} (shipped: {have}); pass --checkpoint WORKDIR"
                     " (a run of python -m experiments.train), --pretrained cpu, or --checkpoint none"
                     " for the classic methods alone")
  for v in variants:
    mcfg, params, prov = cio.load_pretrained(name, v)
    trained[v] = (mcfg, params)
    log(f"{LABELS[v]}: shipped weights {name}-{v} (step {prov.get('best_step')} of"
        f" {prov.get('command')})")
  return trained


def run(files, strides, checkpoint, log=print, *, trained: dict | None = None,
        classic: bool = True, references: dict | None = None) -> dict:
  """Every method on every scan and stride; returns the images and scores.

  The networks: ``trained`` (``variant -> (model_config, params)``, e.g.
  :func:`load_models`), else every variant of ``checkpoint`` (None: none).
  ``classic=False`` runs the networks alone. ``references``: ``scene -> {method:
  [H, W] full-scan image}`` of an earlier run of the same files (its
  ``results["scenes"][scene]["references"]``), used instead of reconstructing them again.
  """
  from tqdm import tqdm

  from nlosjax.data import io
  if trained is None:
    trained = load_models(checkpoint, log=log) if checkpoint is not None else {}
  methods = (CLASSIC if classic else ()) + tuple(trained)
  results = {"strides": list(strides), "methods": list(methods), "scenes": {}, "trained": trained}
  jobs = len(files) * ((0 if references else len(REFERENCES)) + len(methods) * len(strides))
  bar = tqdm(total=jobs, desc="reconstructions", unit="recon", dynamic_ncols=True)
  for path in files:
    transient, setup = io.load_measurement(path)
    scene = scene_name(path)
    if references:
      refs = references[scene]
    else:
      refs = {}
      for m in REFERENCES:
        refs[m] = classic_intensity(transient, setup, m, 1)
        bar.update(1)
    entry = {"file": str(path), "setup": repr(setup), "references": refs, "images": {},
             "scores": {}}
    for method in methods:
      for stride in (1,) + tuple(strides):
        if stride == 1 and (method in trained or method in refs):
          if method in refs:
            entry["images"][(method, 1)] = refs[method]
          continue
        times = []
        fitted = method in trained and len(trained[method]) > 2
        for _ in range(1 if fitted else 2):   # the second call reuses what the first compiled
          t0 = time.perf_counter()
          if method in trained:
            image = model_intensity(trained[method], transient, setup, stride)
          else:
            image = classic_intensity(transient, setup, method, stride)
          times.append(time.perf_counter() - t0)
        entry["images"][(method, stride)] = image
        entry["scores"][(method, stride)] = {**score_against(image, refs, method), "time_s": times[0],
                                             **({} if fitted else {"again_s": times[1]})}
        bar.update(1)
    results["scenes"][scene] = entry
  bar.close()
  return results


def score_against(image, references: dict, method: str) -> dict:
  """PSNR / SSIM of ``image`` against every reference but ``method``'s own, and their means.

  Returns ``{"vs": {reference: {"psnr", "ssim"}}, "psnr": mean, "ssim": mean}``.
  """
  from nlosjax import metrics
  vs = {r: {"psnr": float(metrics.psnr(image, ref)), "ssim": float(metrics.ssim(image, ref))}
        for r, ref in references.items() if r != method}
  return {"vs": vs, "psnr": float(np.mean([v["psnr"] for v in vs.values()])),
          "ssim": float(np.mean([v["ssim"] for v in vs.values()]))}


def binned_classic(results, methods=("phasor", "rsd"), refined=("phasor",)) -> dict | None:
  """Classic methods on the sparse scans summed to the networks' time bins (mean scores over scenes).

  Tells what the networks' coarser bins cost from what the networks do: the
  same sparse scans, interpolation and reference as :func:`run`, but time
  summed over the bin factor :func:`nlosjax.inference.adapt_to_capture`
  uses, and phasor / RSD with the wavelength raised
  to 3 bins per period where their default is unresolved on those bins
  (``nlosjax.evaluation.baselines.default_options``).

  ``refined``: methods also run with ``variant="refined"``, the operators of
  a physics layer with ``ModelConfig.physics_variant="refined"`` (the
  default; ``nlosjax.models.blocks.FeatureTransform``: the centred wavelet,
  plain bin averaging from t to v), keyed ``"<method>/refined"``, at the
  capture's bins as well (``psnr_16``, ``ssim_16``). With the public
  operators (the classic rows, and ``physics_variant="public"``) beside
  them: what a physics layer's operators cost on these scans, apart from
  anything learned.

  Returns ``None`` without a trained network, else ``{"bin_factor": k,
  "bin_width": s, "scores": {(method, stride): {"psnr": dB, "ssim": ...}},
  "options": {method: [options per scene]}}`` with the scores averaged over scenes.
  """
  trained = results.get("trained") or {}
  if not trained:
    return None
  from nlosjax.data import io
  from nlosjax.evaluation.baselines import default_options as classic_options
  from nlosjax.inference import adapt_to_capture
  mcfg = next(iter(trained.values()))[0]
  rows, options, extra = {}, {}, {}
  for entry in results["scenes"].values():
    full, capture = io.load_measurement(entry["file"])
    adapted = adapt_to_capture(mcfg, capture)                  # the networks' time binning
    transient, setup = np.asarray(adapted.prepare(full)), adapted.setup
    for method in methods:
      opts = {**OPTIONS[method], **classic_options(method, setup)}
      options.setdefault(method, []).append(opts)
      for stride in results["strides"]:
        image = classic_intensity(transient, setup, method, stride, opts)
        sc = score_against(image, entry["references"], method)
        rows.setdefault((method, stride), []).append((sc["psnr"], sc["ssim"]))
        if method in refined:
          fine = {**OPTIONS[method], "variant": "refined"}      # as run() at 16 ps
          for key, (x, s, o) in (("", (transient, setup, dict(opts, variant="refined"))),
                                 ("_16", (full, capture, fine))):
            sc = score_against(classic_intensity(x, s, method, stride, o), entry["references"], method)
            extra.setdefault((f"{method}/refined", stride), {}).setdefault(key, []).append(
                (sc["psnr"], sc["ssim"]))
  scores = {k: {"psnr": float(np.mean([v[0] for v in vals])), "ssim": float(np.mean([v[1] for v in vals]))}
            for k, vals in rows.items()}
  for k, by in extra.items():
    scores[k] = {f"{q}{key}": float(np.mean([v[i] for v in vals]))
                 for key, vals in by.items() for i, q in enumerate(("psnr", "ssim"))}
  return {"bin_factor": adapted.bin_factor, "bin_width": setup.bin_width, "scores": scores,
          "options": options}


def synthetic_check(path, trained, *, sequences: int = 4, frames=(2, 5)) -> dict | None:
  """The same pipeline on the networks' own domain: the synthetic test split, stride 4.

  Scores (mean over ``sequences`` x ``frames`` test frames) against the ground-truth
  intensity: the adaptation there is the identity (bin factor 1, the trained wavelet),
  so a network that beats the classic methods here but not on the measured scans
  points at the domain gap, not at the reading or the adaptation.
  """
  from nlosjax import metrics
  from nlosjax.data import dataset, io
  from nlosjax.evaluation import baselines as B
  path = pathlib.Path(path)
  if not path.is_file() or not trained:
    return None
  stride = next(iter(trained.values()))[0].stride
  scores = {m: {"psnr": [], "ssim": []} for m in CLASSIC + tuple(trained)}
  with dataset.open_dataset(path) as ds:
    names = ds.names("test")[:sequences]
    for name in names:
      for fr in frames:
        x, setup = io.load_measurement(path, sequence=name, frame=fr)
        gt = ds.read(name, "intensity", frames=fr)
        for m in scores:
          image = (model_intensity(trained[m], x, setup, stride) if m in trained
                   else classic_intensity(x, setup, m, stride, options=B.default_options(m, setup)))
          scores[m]["psnr"].append(float(metrics.psnr(image, gt)))
          scores[m]["ssim"].append(float(metrics.ssim(image, gt)))
  shown = path.resolve()
  shown = shown.relative_to(REPO) if shown.is_relative_to(REPO) else shown
  return {"file": str(shown), "frames": len(scores[CLASSIC[0]]["psnr"]), "stride": stride,
          "options": {m: B.default_options(m, setup) for m in CLASSIC},
          "scores": {m: {k: float(np.mean(v)) for k, v in d.items()} for m, d in scores.items()}}


# ------------------------------------------------------------------ ablation
#: What each ablation zeroes in an ST-Mamba network (parameter path prefixes). With
#: ``spread/to_transient`` zero the recovered transient is the skip alone: the sparse
#: scan bilinearly interpolated (times ``skip_gain``); with ``volume/refine/to_volume``
#: zero the volume is the physics layer's normalised reconstruction of that transient.
ABLATIONS = {"no_refinement": ("volume/refine/to_volume",),
             "physics_only": ("spread/to_transient", "volume/refine/to_volume")}
ABLATION_TEXT = {"no_refinement": "refinement zeroed",
                 "physics_only": "spreading residual and refinement zeroed (interpolated scan, physics layer)"}


def _zeroed(params, prefixes):
  """``params`` with every leaf under one of ``prefixes`` (``/``-joined paths) set to 0.

  None unless every prefix names at least one leaf (a network without those parts).
  """
  import jax
  hit = []

  def leaf(path, v):
    name = "/".join(str(getattr(k, "key", k)) for k in path)
    if name.startswith(prefixes):
      hit.append(name)
      return np.zeros_like(v)
    return v
  out = jax.tree_util.tree_map_with_path(leaf, params)
  return out if {p for p in prefixes if any(h.startswith(p) for h in hit)} == set(prefixes) else None


def ablated_models(trained: dict) -> dict:
  """``"<variant>|<ablation>" -> (model_config, params)`` for each network that has the ablated parts.

  USM has no such parts and is skipped. The ablations (:data:`ABLATIONS`) ask how
  much of a network's score on measured scans its learned residuals give or take.
  """
  out = {}
  for v, (mcfg, params) in trained.items():
    for name, prefixes in ABLATIONS.items():
      zeroed = _zeroed(params, prefixes)
      if zeroed is not None:
        out[f"{v}|{name}"] = (mcfg, zeroed)
  return out


def aligned_run(files, strides, results, workdir) -> dict:
  """Each scan scored by the networks of ``python -m experiments.align --workdir WORKDIR`` that left it out.

  Returns the :func:`run` results of ``"<variant>|aligned"`` (scenes without such a network are absent).
  """
  from experiments.align import fold_folder
  from nlosjax.pretrained import unflatten_params
  merged = {"strides": list(strides), "methods": [], "scenes": {}, "trained": {}}
  for path in files:
    scene = scene_name(path)
    models = {}
    for v, (mcfg, _) in results["trained"].items():
      f = fold_folder(workdir, v, scene) / "params.npz"
      if f.exists():
        with np.load(f) as z:
          models[f"{v}|aligned"] = (mcfg, unflatten_params({k: z[k] for k in z.files}))
    if not models:
      continue
    part = run([path], strides, None, trained=models, classic=False,
               references={scene: results["scenes"][scene]["references"]})
    merged["scenes"][scene] = part["scenes"][scene]
    merged["methods"] = sorted(set(merged["methods"]) | set(models))
  return merged


def adapted_models(trained: dict) -> dict:
  """``"<variant>|adapted" -> (model_config, params, True)`` for each ST-Mamba network (not USM)."""
  return {f"{v}|adapted": (mcfg, params, True) for v, (mcfg, params) in trained.items() if v != "usm"}


ADAPTATION_TEXT = ("Each network fitted to each scan before reconstructing it (`nlosjax.adaptation.adapt` with"
                   " its defaults and the retroreflective forward model, nothing chosen on these scans):"
                   " intensity PSNR (dB), mean over the references, as trained → fitted, per scan and mean;"
                   " last column the seconds per scan the fitted network took, fitting included:")
ALIGNED_TEXT = ("Each network after the second training stage on unlabelled measured inputs"
                " (`python -m experiments.align`: the synthetic loss plus the MMD² of the first ST-Mamba"
                " block's features to measured inputs), one network per scan, trained on the *other*"
                " scans' inputs only: intensity PSNR (dB), mean over the references, as trained → aligned"
                " without that scan, per scan and mean; last column the seconds per scan:")


def _adaptation_lines(results, adaptation, suffix: str = "adapted", text: str = ADAPTATION_TEXT) -> list[str]:
  """Each network as trained and as ``"<variant>|<suffix>"`` in ``adaptation``, per scan and mean."""
  if not adaptation:
    return []
  scenes = list(results["scenes"])
  lines = [text, "", "| network | input | " + " | ".join(scenes) + " | mean | s per scan |",
           "|---|---|" + "---|" * (len(scenes) + 2)]
  for v in [m for m in results["methods"] if f"{m}|{suffix}" in adaptation["methods"]]:
    for stride in results["strides"]:
      g = 64 // stride
      cells, before, after, secs = [], [], [], []
      for sc in scenes:
        a = results["scenes"][sc]["scores"].get((v, stride))
        b = adaptation["scenes"].get(sc, {}).get("scores", {}).get((f"{v}|{suffix}", stride))
        if a is None or b is None:
          cells.append("–")
          continue
        cells.append(f"{a['psnr']:.2f} → {b['psnr']:.2f}")
        before.append(a["psnr"])
        after.append(b["psnr"])
        secs.append(b["time_s"])
      mean = f"**{np.mean(before):.2f} → {np.mean(after):.2f}**" if before else "–"
      lines.append(f"| {LABELS[v]} | {g} × {g} | " + " | ".join(cells) + f" | {mean} | "
                   f"{np.median(secs) if secs else float('nan'):.1f} |")
  return lines + [""]


def _ablation_lines(results, ablation) -> list[str]:
  """Mean intensity PSNR / SSIM of each network as trained and with its residuals zeroed."""
  if not ablation:
    return []
  cols = list(ABLATIONS)
  lines = ["What the networks' learned residuals do on these scans: each network as trained, and with"
           " parts of it zeroed (" + "; ".join(f"*{c}*: {ABLATION_TEXT[c]}" for c in cols)
           + "; means over scenes of the mean over references, PSNR (dB) / SSIM):", "",
           "| network | input | as trained | " + " | ".join(cols) + " |",
           "|---|---|---|" + "---|" * len(cols)]

  def mean(res, m, stride):
    vals = _over_scenes(res, m, stride)
    return (f"{np.mean([v['psnr'] for v in vals]):.2f} / {np.mean([v['ssim'] for v in vals]):.3f}"
            if vals else "–")
  for v in [m for m in results["methods"] if m not in CLASSIC]:
    if not any(f"{v}|{c}" in ablation["methods"] for c in cols):
      continue
    for stride in results["strides"]:
      g = 64 // stride
      lines.append(f"| {LABELS[v]} | {g} × {g} | {mean(results, v, stride)} | "
                   + " | ".join(mean(ablation, f"{v}|{c}", stride) for c in cols) + " |")
  return lines + [""]


# ------------------------------------------------------------------ timing
_TWIN_SCRIPT = r"""
import json, sys, time
t0 = time.perf_counter()
import numpy as np, scipy.io
from experiments import numpy_twins as twins
from nlosjax.physics.setup import Setup
t1 = time.perf_counter()
raw = scipy.io.loadmat(sys.argv[1], variable_names=("rect_data", "width"))
rect = raw["rect_data"].astype(np.float32)
rect[:, :, :600] = 0
x = np.ascontiguousarray(rect.reshape(rect.shape[0], rect.shape[1], -1, 4).sum(-1).transpose(2, 1, 0))
setup = Setup(wall_size=2 * float(raw["width"].squeeze()), grid=x.shape[1:], bin_width=16e-12,
              num_bins=x.shape[0])
t2 = time.perf_counter()
ops = twins.build(setup, sys.argv[2], **json.loads(sys.argv[3]))
t3 = time.perf_counter()
vol = twins.run(x, sys.argv[2], ops)
t4 = time.perf_counter()
vol = twins.run(x, sys.argv[2], ops)
t5 = time.perf_counter()
print(json.dumps({"load_s": t2 - t1, "build_s": t3 - t2, "run_s": t4 - t3, "warm_run_s": t5 - t4,
                  "import_s": t1 - t0}))
"""


def _python_env() -> dict:
  env = dict(os.environ)
  env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
  return env


def time_cli(path, methods=("lct", "fk", "phasor"), repeats: int = 3, log=print) -> dict:
  """Wall times of ``experiments.reconstruct`` (cold and with a warm XLA cache) and of the NumPy twins.

  Each configuration runs ``repeats`` times in fresh processes, alternating
  methods; the median is kept. Returns ``method -> {...}``.
  """
  env = _python_env()
  out = {}
  with tempfile.TemporaryDirectory() as tmp:
    for method in methods:
      opts = OPTIONS[method]
      flags = []
      if "snr" in opts:
        flags += ["--snr", str(opts["snr"])]
      if "falloff" in opts:
        flags += ["--falloff", opts["falloff"]]
      rows = {"cold": [], "cached": [], "twin": []}
      cache = pathlib.Path(tmp) / f"xla_{method}"
      for r in range(repeats):
        for kind in ("cold", "cached", "twin"):
          t0 = time.perf_counter()
          if kind == "twin":
            res = subprocess.run([sys.executable, "-c", _TWIN_SCRIPT, str(path), method, json.dumps(opts)],
                                 env=env, cwd=REPO, capture_output=True, text=True, check=True)
            rec = json.loads(res.stdout.strip().splitlines()[-1])
          else:
            e = dict(env, NLOSJAX_CACHE_DIR=str(cache))
            cmd = [sys.executable, "-m", "experiments.reconstruct", str(path), "--method", method,
                   "--out", str(pathlib.Path(tmp) / f"{method}_{kind}"), "--quiet", *flags]
            if kind == "cold":
              cmd.append("--no-cache")
            elif r == 0:      # fill the cache once before the timed cached runs
              subprocess.run(cmd, env=e, cwd=REPO, capture_output=True, check=True)
              t0 = time.perf_counter()
            subprocess.run(cmd, env=e, cwd=REPO, capture_output=True, check=True)
            rec = json.loads((pathlib.Path(tmp) / f"{method}_{kind}" / "timings.json").read_text())
          rec["process_s"] = time.perf_counter() - t0
          rows[kind].append(rec)
      med = lambda rs, k: float(np.median([x[k] for x in rs]))
      out[method] = {
          "cli_cold": {k: med(rows["cold"], k) for k in ("load_s", "reconstruct_s", "process_s")},
          "cli_cached": {k: med(rows["cached"], k) for k in ("load_s", "reconstruct_s", "process_s")},
          "twin": {k: med(rows["twin"], k) for k in ("load_s", "build_s", "run_s", "warm_run_s",
                                                     "import_s", "process_s")},
          "repeats": repeats}
      log(f"timing {method}: {json.dumps(out[method])}")
  return out


def time_warm(path, methods=("lct", "fk", "phasor"), repeats: int = 5) -> dict:
  """In-process warm run times (compiled, operators built): JAX ``reconstruct`` vs the twin's run."""
  import jax

  from experiments import numpy_twins as twins
  from nlosjax import physics
  from nlosjax.data import io
  x, setup = io.load_measurement(path)
  out = {}
  for m in methods:
    fn = lambda a, m=m: physics.reconstruct(a, setup, m, **OPTIONS[m])   # jitted inside
    jax.block_until_ready(fn(x))
    ops = twins.build(setup, m, **OPTIONS[m])
    twins.run(x, m, ops)
    tj, tn = [], []
    for _ in range(repeats):
      t0 = time.perf_counter()
      jax.block_until_ready(fn(x))
      tj.append(time.perf_counter() - t0)
      t0 = time.perf_counter()
      twins.run(x, m, ops)
      tn.append(time.perf_counter() - t0)
    out[m] = {"jax_run_s": float(np.median(tj)), "twin_run_s": float(np.median(tn))}
  return out


# ------------------------------------------------------------------ report
def _table(results) -> list[str]:
  strides = results["strides"]
  methods = results["methods"]
  scenes = list(results["scenes"])
  lines = []
  for stride in strides:
    grid = 64 // stride
    rows, by_ref = [], []
    for m in methods:
      cells, ps, ss = [], [], []
      per_ref = {r: [] for r in REFERENCES}
      for sc in scenes:
        s = results["scenes"][sc]["scores"].get((m, stride))
        if s is None:
          cells.append("–")
          continue
        cells.append(f"{s['psnr']:.2f} / {s['ssim']:.3f}")
        ps.append(s["psnr"])
        ss.append(s["ssim"])
        for r, v in s["vs"].items():
          per_ref[r].append(v)
      mean = f"**{np.mean(ps):.2f} / {np.mean(ss):.3f}**" if ps else "–"
      rows.append(f"| {LABELS[m]} | " + " | ".join(cells) + f" | {mean} |")
      ref_cells = [(f"{np.mean([v['psnr'] for v in per_ref[r]]):.2f} / "
                    f"{np.mean([v['ssim'] for v in per_ref[r]]):.3f}") if per_ref[r] else "(own)"
                   for r in REFERENCES]
      by_ref.append(f"| {LABELS[m]} | " + " | ".join(ref_cells) + f" | {mean} |")
    lines += [f"### Input {grid} × {grid} (stride {stride}): intensity PSNR (dB) / SSIM, mean over scenes, "
              "against each full-scan reconstruction", "",
              "| method | " + " | ".join(f"vs {LABELS[r]} 64 × 64" for r in REFERENCES)
              + " | mean of the columns |",
              "|---|" + "---|" * (len(REFERENCES) + 1), *by_ref, "",
              f"Per scene (input {grid} × {grid}; each cell the mean over the references but the "
              "method's own):", "",
              "| method | " + " | ".join(scenes) + " | mean |",
              "|---|" + "---|" * (len(scenes) + 1), *rows, ""]
  return lines


def _over_scenes(results, method: str, stride: int) -> list[dict]:
  """The score records of ``method`` at ``stride``, one per scene that has one, in scene order."""
  return [e["scores"][(method, stride)] for e in results["scenes"].values()
          if (method, stride) in e["scores"]]


def _time_lines(results) -> list[str]:
  """Seconds per scan of each method and input, as :func:`run` measured them (one frame each).

  *first*: the first scene's first call, which pays tracing and XLA
  compilation where nothing compiled it before (the classic methods' full-scan
  references have the same shape and compiled it already); *per frame*: the
  median over scenes of a second call on the same scan, compiled.
  """
  scenes = list(results["scenes"])
  if not scenes:
    return []
  lines = ["Seconds per scan in this process, on the machine above (*first*: the first call on"
           f" {scenes[0]}, tracing and compilation included; *per frame*: the median over the scenes of"
           " a second call on the same scan, compiled; the networks' times include moving the physics"
           " layer to the scan's setup and the time binning):", "",
           "| method | " + " | ".join(f"{64 // s} × {64 // s} first | {64 // s} × {64 // s} per frame"
                                      for s in results["strides"]) + " |",
           "|---|" + "---|---|" * len(results["strides"])]
  for m in results["methods"]:
    cells = []
    for stride in results["strides"]:
      rows = _over_scenes(results, m, stride)
      again = [r["again_s"] for r in rows if "again_s" in r]
      cells += [f"{rows[0]['time_s']:.2f}" if rows else "–",
                f"{np.median(again):.2f}" if again else "–"]
    lines.append(f"| {LABELS[m]} | " + " | ".join(cells) + " |")
  return lines + [""]


def _winner_lines(results) -> list[str]:
  lines = []
  classic = [m for m in results["methods"] if m in CLASSIC]
  models = [m for m in results["methods"] if m not in CLASSIC]
  for stride in results["strides"]:
    means = {}
    for m in results["methods"]:
      vals = _over_scenes(results, m, stride)
      if vals:
        means[m] = (np.mean([v["psnr"] for v in vals]), np.mean([v["ssim"] for v in vals]))
    if not classic or not means:
      continue
    best_c = max(classic, key=lambda m: means[m][0])
    best_cs = max(classic, key=lambda m: means[m][1])
    for v in models:
      if v not in means:
        continue
      beats_p = means[v][0] > means[best_c][0]
      beats_s = means[v][1] > means[best_cs][1]
      lines.append(
          f"- stride {stride}: {LABELS[v]} mean PSNR {means[v][0]:.2f} dB vs the best classic"
          f" ({LABELS[best_c]}) {means[best_c][0]:.2f} dB -> {'beats' if beats_p else 'does not beat'}"
          f" every classic method; mean SSIM {means[v][1]:.3f} vs best ({LABELS[best_cs]})"
          f" {means[best_cs][1]:.3f} -> {'beats' if beats_s else 'does not beat'}.")
  return lines


def write_figures(results, out_dir: pathlib.Path, prefix: str = "real") -> list[str]:
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  names = []
  strides = results["strides"]
  methods = results["methods"]
  cols = [1] + list(strides)
  for scene, entry in results["scenes"].items():
    fig, axes = plt.subplots(len(methods), len(cols), figsize=(2.1 * len(cols), 2.1 * len(methods)),
                             squeeze=False)
    for r, m in enumerate(methods):
      for c, s in enumerate(cols):
        ax = axes[r, c]
        ax.set_xticks([])
        ax.set_yticks([])
        img = entry["images"].get((m, s))
        if img is None:
          ax.set_facecolor("0.85")
          ax.text(0.5, 0.5, "needs a\nsparse scan", ha="center", va="center", fontsize=7,
                  transform=ax.transAxes)
        else:
          ax.imshow(img, cmap="gray", vmin=0, vmax=1)
          sc = entry["scores"].get((m, s))
          tag = "full-scan reference" if (s == 1 and m in REFERENCES) else (
              f"{sc['psnr']:.1f} dB / {sc['ssim']:.2f}" if sc else "")
          ax.set_title(tag, fontsize=7)
        if c == 0:
          ax.set_ylabel(LABELS[m], fontsize=9)
        if r == 0:
          g = 64 // s
          ax.set_xlabel(f"{g} × {g}" + (" (full)" if s == 1 else f" (stride {s})"), fontsize=8)
          ax.xaxis.set_label_position("top")
    fig.suptitle(f"{scene}: intensity per method (PSNR / SSIM: mean vs the other methods' full-scan images)",
                 fontsize=8)
    fig.tight_layout()
    name = f"{prefix}_{scene}.png"
    fig.savefig(out_dir / name, dpi=100)
    plt.close(fig)
    names.append(name)
  # summary bars
  fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
  width = 0.8 / max(1, len(strides))
  for k, s in enumerate(strides):
    ps, ss = [], []
    for m in methods:
      vals = _over_scenes(results, m, s)
      ps.append(np.mean([v["psnr"] for v in vals]) if vals else np.nan)
      ss.append(np.mean([v["ssim"] for v in vals]) if vals else np.nan)
    x = np.arange(len(methods)) + (k - (len(strides) - 1) / 2) * width
    axes[0].bar(x, ps, width, label=f"{64 // s} × {64 // s}")
    axes[1].bar(x, ss, width, label=f"{64 // s} × {64 // s}")
  for ax, t in zip(axes, ("mean intensity PSNR (dB)", "mean intensity SSIM")):
    ax.set_xticks(np.arange(len(methods)))
    ax.set_xticklabels([LABELS[m] for m in methods], fontsize=8)
    ax.set_title(t, fontsize=9)
  axes[0].legend(fontsize=8)
  fig.tight_layout()
  fig.savefig(out_dir / f"{prefix}_summary.png", dpi=100)
  plt.close(fig)
  return names + [f"{prefix}_summary.png"]


def _network_text(results) -> str:
  """How the networks read the scans: trained geometry and the time binning."""
  trained = results.get("trained") or {}
  if not trained:
    return "no trained network."
  from nlosjax.inference import default_bin_factor
  mcfg = next(iter(trained.values()))[0]
  s = mcfg.setup
  factor = default_bin_factor(s.bin_width, CAPTURE_BIN_WIDTH)   # what adapt_to_capture sums
  return (f"the networks on the sparse scan with time summed {factor} × 16 ps ="
          f" {factor * 16} ps (trained on {s.bin_width * 1e12:.0f} ps bins, {s.grid[0]} × {s.grid[1]}"
          f" scans of a {s.wall_size:g} m wall at stride {mcfg.stride}).")


def _layer_variants(results) -> str:
  """Which operators each network's physics layer uses (``physics_variant``; USM: refined LCT)."""
  parts = []
  for v, (mcfg, _) in (results.get("trained") or {}).items():
    variant = getattr(mcfg, "physics_variant", "refined")
    method = getattr(mcfg, "physics", "lct")
    parts.append(f"{LABELS[v]} {variant} {'phasor' if method == 'phasor' else 'LCT'}")
  return ", ".join(parts) or "none"


def _binned_lines(results, binned) -> list[str]:
  """The table of :func:`binned_classic`: classic scores at 16 ps beside those at the networks' bins."""
  if not binned:
    return []
  width = f"{binned['bin_width'] * 1e12:.0f} ps"
  lines = [
      f"What the networks' time bins cost: phasor and RSD on the same sparse scans summed to"
      f" {binned['bin_factor']} × 16 ps = {width}, the networks' input (`binned_classic`;"
      + "".join(f" {LABELS[m]} sampling_coeff per scene "
                + " / ".join(f"{o.get('sampling_coeff', 2.0):.3g}" for o in opts) + ";"
                for m, opts in binned["options"].items())
      + " means over scenes, PSNR (dB) / SSIM: mean over the same references). A *refined operators*"
      " row is that method with the refined operators (`variant=\"refined\"`: centred wavelet, plain"
      " bin averaging from t to v) in place of the public ones: on the same input, what a physics"
      " layer's operators cost or gain before anything learned acts. The networks' physics layers: "
      + _layer_variants(results) + ":", "",
      f"| method | input | at 16 ps | at {width} |", "|---|---|---|---|"]
  for (m, stride), r in binned["scores"].items():
    base, _, variant = m.partition("/")
    if variant:     # its own scores at 16 ps
      p16, s16 = r["psnr_16"], r["ssim_16"]
      label = f"{LABELS[base]}, {variant} operators"
    else:
      vals = _over_scenes(results, m, stride)
      p16, s16, label = np.mean([v["psnr"] for v in vals]), np.mean([v["ssim"] for v in vals]), LABELS[m]
    g = 64 // stride
    lines.append(f"| {label} | {g} × {g} | {p16:.2f} / {s16:.3f} | {r['psnr']:.2f} / {r['ssim']:.3f} |")
  return lines + [""]


def write_report(results, out: pathlib.Path, *, timing=None, warm=None, synthetic=None,
                 binned=None, ablation=None, adaptation=None, aligned=None, facts: list[str],
                 elapsed: float, figures: list[str], notes: str = "") -> None:
  lines = ["# Under-scanning on measured scans", ""] + facts + [
      f"- Wall time: {elapsed / 60:.1f} min; numpy {np.__version__}",
      "- Scans: " + ", ".join(f"`{pathlib.Path(e['file']).name}`" for e in results["scenes"].values()) +
      " (O'Toole et al. 2018, 64 × 64 × 512 after the published preparation, 16 ps bins)",
      "- Protocol: see the docstring of `experiments/real_undersampling.py`: references = each"
      " classic method on the full 64 × 64 scan, a method scored against every reference but its"
      " own; sparse scans = scan points `stride // 2 + stride i`;"
      " classic methods on the sparse scan interpolated to 64 × 64 (LCT snr 0.8 and FBP with"
      " the retroreflective t² falloff, f-k / phasor / RSD defaults); " + _network_text(results),
      "",
  ]
  lines += _table(results)
  lines += _time_lines(results)
  if notes:
    lines += [notes, ""]
  wl = _winner_lines(results)
  if wl:
    lines += ["Does the trained network beat every classic method (means over scenes)?", "", *wl, ""]
  lines += _binned_lines(results, binned)
  lines += _ablation_lines(results, ablation)
  lines += _adaptation_lines(results, adaptation)
  lines += _adaptation_lines(results, aligned, "aligned", ALIGNED_TEXT)
  if synthetic:
    lines += [
        f"In-domain check (same code, the networks' own data): {synthetic['frames']} frames of"
        f" the synthetic test split of `{synthetic['file']}` at stride {synthetic['stride']},"
        " scored against the ground-truth intensity (classic methods with default options"
        + "".join(f", {LABELS[m]} " + ", ".join(f"{k} {v:.3g}" for k, v in o.items())
                  for m, o in synthetic.get("options", {}).items() if o)
        + "; the adaptation is the identity there: bin factor 1, the trained wavelet):", "",
        "| method | PSNR (dB) | SSIM |", "|---|---|---|"]
    for m, r in synthetic["scores"].items():
      lines.append(f"| {LABELS[m]} | {r['psnr']:.2f} | {r['ssim']:.3f} |")
    lines.append("")
  lines += ["Figures: " + ", ".join(f"[{f}]({f})" for f in figures), ""]
  for f in figures:
    lines += [f"![{f}]({f})", ""]
  if timing:
    lines += [
        "## `experiments.reconstruct` vs the NumPy/SciPy twins (64 × 64 × 512)",
        "",
        f"Scan `{timing['file']}`; median of {timing['repeats']} fresh processes each. CLI columns"
        " are what `python -m experiments.reconstruct FILE --method M --out DIR` reports: *load*"
        " (read + prepare the .mat) and *reconstruct* (operators, tracing, XLA compilation and"
        " the run), without the Python/JAX import and the PNG writing; *cold* = no compilation"
        " cache (`--no-cache`), *cached* = the persistent XLA cache filled by an earlier run."
        " Twin = `experiments/numpy_twins.py` (NumPy/SciPy ports of the public code, `scipy.fft`"
        " on all cores, complex64): load (`scipy.io.loadmat` + the same preparation) + operator"
        " build + one run. *Process* columns are whole `python` processes (imports, writing"
        " PNGs included; the twin's process also imports JAX through `nlosjax.physics.setup`).",
        "",
        "| method | CLI cold load + reconstruct s | CLI cached load + reconstruct s | twin load + build + run s"
        " | CLI cold process s | CLI cached process s | twin process s |",
        "|---|---|---|---|---|---|---|"]
    for m, r in timing["methods"].items():
      c, k, t = r["cli_cold"], r["cli_cached"], r["twin"]
      lines.append(f"| {m} | {c['load_s'] + c['reconstruct_s']:.2f} | {k['load_s'] + k['reconstruct_s']:.2f} |"
                   f" {t['load_s'] + t['build_s'] + t['run_s']:.2f} | {c['process_s']:.2f} |"
                   f" {k['process_s']:.2f} | {t['process_s']:.2f} |")
    lines.append("")
  if warm:
    lines += ["Warm runs in one process (operators built, compiled; median of 5):", "",
              "| method | JAX `reconstruct` s | twin run s |", "|---|---|---|"]
    for m, r in warm.items():
      lines.append(f"| {m} | {r['jax_run_s']:.3f} | {r['twin_run_s']:.3f} |")
    lines.append("")
  out.write_text("\n".join(lines))


def training_data(checkpoint) -> str:
  """The dataset a trained run read (``data.path`` of its ``config.json``), else the cpu preset's.

  ``checkpoint`` is a workdir, a variant's folder or its ``checkpoints``
  folder; the run's ``config.json`` is in the workdir.
  """
  from experiments.configs import get_config
  default = get_config("cpu")["data"]["path"]
  if not checkpoint:
    return default
  here = pathlib.Path(checkpoint).absolute()
  config = next((d / "config.json" for d in (here, *list(here.parents)[:2])
                 if (d / "config.json").is_file()), None)
  if config is None:
    return default
  return str(json.loads(config.read_text()).get("data", {}).get("path", default))


def pretrained_data(name=None) -> str:
  """The dataset the shipped weights ``name`` were validated on (their provenance's ``data.path``)."""
  from nlosjax import pretrained
  name = name or DEFAULT_PRETRAINED
  variant = next(v for n, v in pretrained.shipped() if n == name)
  prov = pretrained.read_provenance(pretrained.weights_folder(name, variant))
  return str(prov["config"]["data"]["path"])


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--data-dir", default=None,
                      help="folder of real .mat scans (default ../shared/data/real, else the shipped scan)")
  parser.add_argument("--checkpoint", default=None,
                      help="trained run (workdir of python -m experiments.train); 'none' for classic only;"
                           " default: the shipped weights of --pretrained")
  parser.add_argument("--pretrained", default=None, metavar="NAME",
                      help=f"weights shipped in the package, used without --checkpoint (default"
                           f" {DEFAULT_PRETRAINED!r}; nlosjax.inference.pretrained_names() lists them)")
  parser.add_argument("--strides", type=int, nargs="+", default=[4, 8])
  parser.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "real.md"))
  parser.add_argument("--no-timing", action="store_true", help="skip the CLI vs twin timing")
  parser.add_argument("--timing-repeats", type=int, default=3)
  parser.add_argument("--json", default=None, help="also write the scores as JSON here")
  parser.add_argument("--synthetic", default=None,
                      help="dataset file for the in-domain check (default: the data.path of the"
                           " checkpoint's config.json, else runs/data/cpu.h5; 'none' to skip;"
                           " skipped if absent)")
  parser.add_argument("--notes", default=None, help="a Markdown file whose text is added after the tables")
  parser.add_argument("--no-ablation", action="store_true",
                      help="skip the networks with their learned residuals zeroed (ablated_models)")
  parser.add_argument("--adapt", action="store_true",
                      help="also fit each network to each scan before reconstructing it (adapted_models)")
  parser.add_argument("--aligned", default=None, metavar="WORKDIR",
                      help="also score each scan with the networks of python -m experiments.align --workdir"
                           " WORKDIR that left it out (aligned_models)")
  args = parser.parse_args(argv)
  t0 = time.perf_counter()
  command = "python -m experiments.real_undersampling " + " ".join(
      sys.argv[1:] if argv is None else argv)
  from experiments.provenance import provenance
  facts = provenance(command.strip())              # the commit the run starts from
  files = default_files(args.data_dir)
  classic_only = args.checkpoint is not None and args.checkpoint.lower() == "none"
  checkpoint = None if classic_only else args.checkpoint
  try:
    trained = {} if classic_only else load_models(checkpoint, args.pretrained)
  except ValueError as e:
    parser.error(str(e))
  results = run(files, args.strides, checkpoint, trained=trained)
  out = pathlib.Path(args.out)
  out.parent.mkdir(parents=True, exist_ok=True)
  figures = write_figures(results, out.parent, prefix=out.stem)   # beside another report: its own names
  timing = warm = None
  if not args.no_timing:
    timing = {"file": files[0].name, "repeats": args.timing_repeats,
              "methods": time_cli(files[0], repeats=args.timing_repeats)}
    warm = time_warm(files[0])
  synthetic = None
  synthetic_path = args.synthetic or (training_data(checkpoint) if checkpoint or classic_only
                                      else pretrained_data(args.pretrained))
  if synthetic_path.lower() != "none":
    synthetic = synthetic_check(synthetic_path, results["trained"])
  binned = binned_classic(results)
  ablated = {} if args.no_ablation else ablated_models(results["trained"])
  ablation = None
  if ablated:
    ablation = run(files, args.strides, None, trained=ablated, classic=False,
                   references={sc: e["references"] for sc, e in results["scenes"].items()})
  adaptation = None
  if args.adapt and results["trained"]:
    adaptation = run(files, args.strides, None, trained=adapted_models(results["trained"]), classic=False,
                     references={sc: e["references"] for sc, e in results["scenes"].items()})
  aligned = aligned_run(files, args.strides, results, args.aligned) if args.aligned else None
  notes = pathlib.Path(args.notes).read_text() if args.notes else ""
  write_report(results, out, timing=timing, warm=warm, synthetic=synthetic, binned=binned,
               ablation=ablation, adaptation=adaptation, aligned=aligned, facts=facts,
               elapsed=time.perf_counter() - t0, figures=figures, notes=notes)
  if args.json:
    scores = {sc: {f"{m}@{s}": v for (m, s), v in e["scores"].items()}
              for sc, e in results["scenes"].items()}
    binned_json = None if binned is None else {
        **binned, "scores": {f"{m}@{s}": v for (m, s), v in binned["scores"].items()}}
    if ablation:
      scores["ablation"] = {sc: {f"{m}@{s}": v for (m, s), v in e["scores"].items()}
                            for sc, e in ablation["scenes"].items()}
    pathlib.Path(args.json).write_text(json.dumps({"scores": scores, "timing": timing, "warm": warm,
                                                   "synthetic": synthetic, "binned": binned_json},
                                                  indent=2) + "\n")
  print(out.read_text())


if __name__ == "__main__":
  main()

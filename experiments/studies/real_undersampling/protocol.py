"""The measured-scan protocol: scans, sparse inputs, every method's image, scores against each reference."""

from __future__ import annotations

import pathlib
import time

import numpy as np

from experiments.provenance import ROOT as REPO
from experiments.reconstruct import DEFAULT_PRETRAINED
from nlosjax.evaluation.baselines import CLASSIC_METHODS
from nlosjax.evaluation.report import METHOD_LABELS
from nlosjax.variants import OURS, OURS_S, USM

CLASSIC = CLASSIC_METHODS
VARIANTS = (OURS_S, OURS, USM)
LABELS = METHOD_LABELS
#: CSA's l1 weight (a share of max(A^T b)) by stride, from csa_choice.md.
CSA_TAU_REL = {4: 0.1, 8: 0.03}
#: Options of the classic methods on these retroreflective scans (O'Toole et al. 2018: snr 0.8, t^2).
OPTIONS = {"fbp": {"falloff": "retroreflective"}, "lct": {"snr": 0.8, "falloff": "retroreflective"},
           "fk": {}, "phasor": {}, "rsd": {},
           # tau_rel: chosen on the real preset's simulated validation split, never on these scans
           # (experiments/studies/csa/results/csa_choice.md, python -m experiments.studies.csa); t^2 as LCT's.
           "csa": {"falloff": "retroreflective"}}
#: The iterative method made for under-scanned scans: scored on the masked sparse scan itself.
ITERATIVE = ("csa",)
#: Every method that needs no training (the classic ones and CSA), the networks' bar.
UNTRAINED = CLASSIC + ITERATIVE
#: The full-scan reconstructions a sparse-scan image is scored against (each but its own).
REFERENCES = CLASSIC
#: Bin width of the measured scans after the published preparation (s).
CAPTURE_BIN_WIDTH = 16e-12


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


def fold_folder(workdir, variant: str, scene: str) -> pathlib.Path:
  """``<workdir>/<variant>-without-<scene>``: one leave-one-scan-out fold (``experiments.studies.align``)."""
  return pathlib.Path(workdir) / f"{variant}-without-{scene}"


def fold_files(folder) -> list[pathlib.Path]:
  """A finished fold's files (``params.npz``, then ``align.json``, written last), or [] if unfinished."""
  files = [pathlib.Path(folder) / "params.npz", pathlib.Path(folder) / "align.json"]
  return files if all(f.exists() for f in files) else []


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
  """Intensity ``[H, W]`` of a classic method or CSA on the scan under-scanned by ``stride`` (1: full).

  Classic methods see the sparse scan interpolated to the full grid, CSA the
  sparse scan as a masked full grid (``experiments.reconstruct.reconstruct_classic``).
  """
  from experiments.reconstruct import reconstruct_classic
  if options is None:
    options = OPTIONS[method]
    if method == "csa":
      options = {**options, "tau_rel": CSA_TAU_REL[stride]}
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
    adapted = cio.for_capture(mcfg, setup)
    sparse = np.asarray(underscan(adapted.prepare(transient), stride))
    return apply(adapted.model_config, sparse)
  if stride == 2 * mcfg.stride:
    # Output grid: every other full-grid point (0, 2, ..., H - 2), spanning (H - 2) spacings.
    half = dataclasses.replace(setup, grid=(H // 2, W // 2),
                               wall_size=setup.wall_size * (H - 2) / (H - 1))
    adapted = cio.for_capture(mcfg, half)
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
  methods = (UNTRAINED if classic else ()) + tuple(trained)
  results = {"strides": list(strides), "methods": list(methods), "scenes": {}, "trained": trained}
  jobs = len(files) * ((0 if references else len(REFERENCES)) + len(methods) * len(strides))
  bar = tqdm(total=jobs, desc="reconstructions", unit="recon", dynamic_ncols=True)
  for index, path in enumerate(files):
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
        if stride == 1 and method in ITERATIVE:     # made for sparse scans; not a reference
          continue
        if stride == 1 and (method in trained or method in refs):
          if method in refs:
            entry["images"][(method, 1)] = refs[method]
          continue
        times = []
        fitted = method in trained and len(trained[method]) > 2
        # The second call reuses what the first compiled; an iterative solve (a minute a scan)
        # is timed twice on the first scan only.
        once = fitted or (method in ITERATIVE and index > 0)
        for _ in range(1 if once else 2):
          t0 = time.perf_counter()
          if method in trained:
            image = model_intensity(trained[method], transient, setup, stride)
          else:
            image = classic_intensity(transient, setup, method, stride)
          times.append(time.perf_counter() - t0)
        entry["images"][(method, stride)] = image
        entry["scores"][(method, stride)] = {**score_against(image, refs, method), "time_s": times[0],
                                             **({} if once else {"again_s": times[1]})}
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
  summed over the bin factor :func:`nlosjax.inference.for_capture`
  uses, and phasor / RSD with the wavelength raised
  to 3 bins per period where their default is unresolved on those bins
  (``nlosjax.evaluation.baselines.default_options``).

  ``refined``: methods also run with ``variant="refined"``, the operators of
  a physics layer with ``ModelConfig.physics_variant="refined"`` (the
  default; ``nlosjax.models.physics_layer.FeatureTransform``: the centred wavelet,
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
  from nlosjax.inference import for_capture
  mcfg = next(iter(trained.values()))[0]
  rows, options, extra = {}, {}, {}
  for entry in results["scenes"].values():
    full, capture = io.load_measurement(entry["file"])
    adapted = for_capture(mcfg, capture)                  # the networks' time binning
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
  scores = {m: {"psnr": [], "ssim": []} for m in UNTRAINED + tuple(trained)}
  with dataset.open_dataset(path) as ds:
    names = ds.names("test")[:sequences]
    for name in names:
      for fr in frames:
        x, setup = io.load_measurement(path, sequence=name, frame=fr)
        gt = ds.read(name, "intensity", frames=fr)
        for m in scores:
          if m in trained:
            image = model_intensity(trained[m], x, setup, stride)
          elif m in ITERATIVE:                 # the measured protocol's options
            image = classic_intensity(x, setup, m, stride)
          else:
            image = classic_intensity(x, setup, m, stride, options=B.default_options(m, setup))
          scores[m]["psnr"].append(float(metrics.psnr(image, gt)))
          scores[m]["ssim"].append(float(metrics.ssim(image, gt)))
  shown = path.resolve()
  shown = shown.relative_to(REPO) if shown.is_relative_to(REPO) else shown
  return {"file": str(shown), "frames": len(scores[CLASSIC[0]]["psnr"]), "stride": stride,
          "options": {m: B.default_options(m, setup) for m in CLASSIC},
          "scores": {m: {k: float(np.mean(v)) for k, v in d.items()} for m, d in scores.items()}}


def over_scenes(results, method: str, stride: int) -> list[dict]:
  """The score records of ``method`` at ``stride``, one per scene that has one, in scene order."""
  return [e["scores"][(method, stride)] for e in results["scenes"].values()
          if (method, stride) in e["scores"]]

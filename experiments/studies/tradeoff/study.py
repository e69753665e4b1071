"""The study: every measurement of every configuration, in one run (:func:`run`).

What is measured and how is described in :mod:`experiments.studies.tradeoff`. The configurations
are evaluated in order under one progress bar, then every executable is timed side by side.
"""

from __future__ import annotations

import dataclasses
import pathlib
import statistics
import time

import numpy as np

from experiments.studies.tradeoff.accuracy import in_range_accuracy, scores
from experiments.studies.tradeoff.configs import (
  CLASSIC,
  DENSITY_STRIDES,
  EXPOSURES,
  LABELS,
  LEARNED,
  LEARNING_RATE,
  METHODS_LEARNED,
  depth_ranges,
  gated_setup,
)
from experiments.studies.tradeoff.data import TestSplit
from experiments.studies.tradeoff.pipelines import classic_pipeline, csa_pipeline, learned_pipeline
from experiments.studies.tradeoff.runners import evaluate, interleaved_times
from experiments.studies.tradeoff.stages import lct_stage_executables, network_volume_executable
from experiments.studies.tradeoff.training import train_learned
from nlosjax.evaluation import baselines
from nlosjax.variants import OURS, OURS_S


def run(args) -> dict:
  """Every measurement; returns the JSON-able results (see the module docstring)."""
  from tqdm import tqdm

  from experiments.configs import get_config
  from nlosjax.evaluation.baselines import upsample_scan
  from nlosjax.evaluation.report import METHOD_LABELS
  from nlosjax.train import RunConfig, ensure_dataset, make_loader
  t_start = time.perf_counter()
  config = RunConfig.from_dict(get_config("cpu"))
  config = dataclasses.replace(config, train=dataclasses.replace(
      config.train, steps=args.steps,
      optim=dataclasses.replace(config.train.optim, learning_rate=LEARNING_RATE)))
  data_path = pathlib.Path(config.data.path)
  ensure_dataset(config, data_path)
  test = TestSplit.load(data_path)
  setup = test.setup
  stride = config.data.stride()
  depth_range = tuple(config.data.spec().scene.depth_range)
  gt_i, gt_d = test.gt()
  B = args.batch
  res: dict = {"configs": [], "gating": {}, "stages": {}, "steps": args.steps, "batch": B,
               "max_depth": setup.max_depth, "wall_size": setup.wall_size, "grid": list(setup.grid),
               "num_bins": setup.num_bins, "bin_width": setup.bin_width, "stride": stride,
               "depth_range": list(depth_range), "rounds": args.repeats, "frames": len(test),
               "data": str(data_path), "knobs": sorted(args.knobs)}
  labels = {**LABELS, **METHOD_LABELS}

  def add(knob: str, name: str, label: str, kind: str, m: dict, *, capture: str = "default",
          setting: str = "") -> None:
    o = m["outputs"]
    res["configs"].append({
        "knob": knob, "name": name, "label": label, "kind": kind, "capture": capture,
        "setting": setting, "key": m["key"], "compile_s": m["compile_s"], "mem_mib": m["mem_mib"],
        **scores(o["intensity"], o["depth"], gt_i, gt_d)})

  # ---- learned configurations: trained or restored on first use
  root = pathlib.Path(args.workdir) / f"s{args.steps}"
  window = max(s.frames for s in LEARNED)

  def get_loader():
    return make_loader(config, data_path, "train", batch_size=config.train.batch_size, shuffle=True,
                       seed=config.train.seed, window=window)

  specs = {spec.name: spec for spec in LEARNED}
  models: dict = {}

  def trained(name: str):
    """``(model_config, params)`` of a learned configuration, trained or restored on first use."""
    if name not in models:
      models[name] = train_learned(specs[name], config, setup, root, get_loader)
    return models[name]

  inputs = {f: test.windows(stride, f) for f in (1, 3, 5)}
  cache: dict = {}       # computation -> executable; every one is timed at the end

  def classic(method, s=stride, meas=None, su=setup):
    x = inputs[1][:, 0] if (s == stride and meas is None) else test.windows(s, 1, meas)[:, 0]
    return evaluate(classic_pipeline(method, su, s), x, batch=B, cache=cache,
                    key=("classic", method, s, su))

  def learned(name, mcfg=None, meas=None):
    base, params = trained(name)
    mcfg = mcfg or base
    x = inputs[mcfg.frames] if meas is None else test.windows(stride, mcfg.frames, meas)
    return evaluate(learned_pipeline(mcfg), x, batch=B, params=params, cache=cache,
                    key=("learned", name, mcfg))

  jobs: list = []        # (knob, description, callable) run in order under one progress bar
  default: dict = {}     # method -> its default-capture evaluation

  def job_method(method):
    m = classic(method) if method in CLASSIC else learned(method)
    default[method] = m
    add("method", method, labels[method], "classic" if method in CLASSIC else "learned", m,
        setting=labels[method])

  for method in CLASSIC + METHODS_LEARNED:
    jobs.append(("method", f"method {method}", lambda method=method: job_method(method)))

  def job_csa():
    """CSA: l1 weight and falloff chosen on validation frames (``baselines.tune_csa``), then the test split."""
    val = TestSplit.load(data_path, "val")
    pick = baselines.spread_frames(len(val), baselines.CSA_VAL_FRAMES)
    gv_i, gv_d = (g[pick] for g in val.gt())
    choice = baselines.tune_csa(val.windows(stride, 1)[pick, 0], gv_i, gv_d, setup, stride,
                                thresholds=(baselines.DEFAULT_THRESHOLD,), batch_size=B, log=lambda _: None)
    tau, falloff = choice["options"]["tau_rel"], choice["options"]["falloff"]
    res["csa_choice"] = {"frames": len(pick), "chosen": [falloff, tau],
                         "psnr": [[g["options"]["falloff"], g["options"]["tau_rel"], g["psnr"]]
                                  for g in choice["grid"]]}
    m = evaluate(csa_pipeline(setup, stride, tau_rel=tau, falloff=falloff), inputs[1][:, 0],
                 batch=B, cache=cache, key=("csa", tau, falloff))
    default["csa"] = m
    add("method", "csa", labels["csa"], "classic", m, setting=f"tau_rel {tau:g}, {falloff}")

  jobs.append(("method", "method csa (chosen on validation)", job_csa))

  def job_density(method, s):
    n = len(range(s // 2, setup.grid[0], s))
    add("density", f"{method}@{n}x{n}", f"{LABELS[method]}, {n}x{n}", "classic",
        classic(method, s), capture=f"{n}x{n}", setting=f"{n}x{n}")

  for method in CLASSIC:
    for s in DENSITY_STRIDES:
      if s != stride:
        jobs.append(("density", f"density {method} {s}",
                     lambda method=method, s=s: job_density(method, s)))

  noisy: dict = {}

  def job_exposure(method, e):
    if e not in noisy:
      noisy.clear()
      noisy[e] = test.renoised(e, seed=1)
    m = classic(method, meas=noisy[e]) if method in CLASSIC else learned(method, meas=noisy[e])
    add("exposure", f"{method}@x{e:g}", f"{labels[method]}, exposure x{e:g}",
        "classic" if method in CLASSIC else "learned", m, capture=f"x{e:g}", setting=f"x{e:g}")

  for e in EXPOSURES:
    for method in CLASSIC + METHODS_LEARNED:
      jobs.append(("exposure", f"exposure {method} x{e:g}",
                   lambda method=method, e=e: job_exposure(method, e)))

  for spec in LEARNED:
    if spec.name not in METHODS_LEARNED:
      knob = "frames" if spec.model == () else "model"
      jobs.append((knob, f"{knob} {spec.name}", lambda spec=spec, knob=knob: add(
          knob, spec.name, spec.label, "learned", learned(spec.name), setting=spec.label)))

  for method in ("associative", "chunked"):
    jobs.append(("kernel", f"kernel {method}", lambda method=method: add(
        "kernel", f"ours@{method}", f"Ours, {method} scan", "learned",
        learned(OURS, trained(OURS)[0].replace(scan_method=method)), setting=method)))
  jobs.append(("kernel", "precision bfloat16", lambda: add(
      "kernel", "ours@bf16", "Ours, bfloat16 activations", "learned",
      learned(OURS, trained(OURS)[0].replace(dtype="bfloat16")), setting="bfloat16")))

  # ---- time gating: accuracy inside each range; the stage profile's executables
  ranges = depth_ranges(depth_range, setup.max_depth,
                        args.aperture)
  res["aperture"] = args.aperture
  gating: dict = {}
  extra: dict = {}       # (name, range label) -> (fn, args): stage executables, timed with the rest

  def job_gating(method):
    gating[method] = {}
    for label, rng, ap in ranges:
      su = gated_setup(setup, rng, ap)
      if rng is None:
        m = default[method]
      elif method in CLASSIC:
        m = classic(method, su=su)
      else:
        m = learned(method, trained(method)[0].with_setup(su))
      acc = in_range_accuracy(m["outputs"], default[method]["outputs"], gt_d, su)
      sc = scores(m["outputs"]["intensity"], m["outputs"]["depth"], gt_i, gt_d)
      gating[method][label] = {"range": rng, "aperture": ap, "depth_bins": list(su.depth_bins),
                               "time_bins": list(su.time_bins), "key": m["key"],
                               "compile_s": m["compile_s"], "mem_mib": m["mem_mib"], **acc,
                               "psnr": sc["psnr"], "rmse": sc["rmse"]}
      if label == "R":
        add("gating", f"{method}@R", f"{labels[method]}, gated {rng[0]:g}-{rng[1]:g} m",
            "classic" if method in CLASSIC else "learned", m, setting=f"{rng[0]:g}-{rng[1]:g} m")

  for method in CLASSIC + (OURS,):
    jobs.append(("gating", f"gating {method}", lambda method=method: job_gating(method)))

  def job_gated_ours_s():
    z = depth_range
    m = learned(OURS_S, trained(OURS_S)[0].with_setup(setup.with_depth_range(*z)))
    add("gating", "ours_s@R", f"{labels[OURS_S]}, gated {z[0]:g}-{z[1]:g} m", "learned", m,
        setting=f"{z[0]:g}-{z[1]:g} m")

  jobs.append(("gating", "gating ours_s (R only)", job_gated_ours_s))

  def job_stages():
    x_full = np.asarray(upsample_scan(inputs[1][:B, 0], setup.grid, stride))
    stages: dict = {"lct": {}, OURS: {}}
    for label, rng, ap in ranges:
      su = gated_setup(setup, rng, ap)
      ex, stages["lct"][label] = lct_stage_executables(su, x_full)
      for k, v in ex.items():
        extra[(f"lct:{k}", label)] = v
      fn, fargs, tw = network_volume_executable(trained(OURS)[0].with_setup(su),
                                                trained(OURS)[1], B)
      extra[("ours:volume", label)] = (fn, fargs)
      stages[OURS][label] = {"tw": tw}
    res["stages"] = stages

  jobs.append(("gating", "stage profile", job_stages))

  jobs = [j for j in jobs if j[0] in args.knobs]
  with tqdm(total=len(jobs), desc="configurations", unit="job", dynamic_ncols=True) as bar:
    for _, desc, job in jobs:
      bar.set_postfix_str(desc)
      job()
      bar.update(1)

  # ---- every executable timed side by side
  fns = {("x",) + k: v["executable"] for k, v in cache.items()}
  fargs = {("x",) + k: v["args"] for k, v in cache.items()}
  fns.update({("s",) + k: v[0] for k, v in extra.items()})
  fargs.update({("s",) + k: v[1] for k, v in extra.items()})
  print(f"timing {len(fns)} executables in {args.repeats} interleaved rounds ...", flush=True)
  t = time.perf_counter()
  rounds = interleaved_times(fns, fargs, rounds=args.repeats)
  res["timing_s"] = time.perf_counter() - t
  res["executables"] = len(fns)
  per_call = {k[1:]: statistics.median(v) for k, v in rounds.items()}
  spread = {k[1:]: (min(v), max(v)) for k, v in rounds.items()}
  for r in res["configs"]:
    r["time"] = per_call[r["key"]] / B
    r["time_range"] = [spread[r["key"]][0] / B, spread[r["key"]][1] / B]
  for rr in gating.values():
    for g in rr.values():
      g["time"] = per_call[g["key"]] / B
  for label, _, _ in (ranges if res["stages"] else []):
    st = res["stages"]["lct"][label]
    for k in ("input", "v-axis", "output"):
      st[k] = per_call[(f"lct:{k}", label)]
    net = res["stages"][OURS][label]
    net["volume"] = per_call[("ours:volume", label)]
    net["whole"] = gating[OURS][label]["time"] * B
    net["front"] = max(net["whole"] - net["volume"], 0.0)
  for d in [*res["configs"], *(g for rr in gating.values() for g in rr.values())]:
    d["key"] = repr(d["key"])
  res["gating"] = gating
  cache.clear()
  extra.clear()
  res["wall_s"] = time.perf_counter() - t_start
  return res

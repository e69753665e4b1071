"""Benchmark the ST-Mamba network: one training step (forward + backward) per config.

    python -m benchmarks.model [--configs cpu usm paper] [--frames 3] [--batch 1] [--repeats 1]
                               [--forward] [--reference] [--time-limit 600]
                               [--out benchmarks/results/model.md]

For every config (``cpu`` = the model ``python -m experiments.train`` trains,
the ``cpu`` preset's ``Ours`` on its data's Setup; ``usm`` = the USM baseline
that preset trains when ``train.variants`` holds ``"usm"``, one frame whatever
``--frames`` says; ``paper`` = :meth:`ModelConfig.paper`: 16 x 16 x 512 in,
128 x 128 out), in a fresh child process:

* parameters and FLOPs per frame from :func:`nlosjax.models.model_summary`
  (``jax.eval_shape`` and XLA's cost analysis of the lowered program, plus the
  FFT and scan estimates it documents; nothing allocated);
* the parameters are initialised on a *small* Setup with the same
  architecture (parameter shapes do not depend on the Setup; the benchmark
  checks the tree against ``eval_shape`` at the target Setup), so no
  paper-sized forward pass runs just to initialise;
* ``step = jax.jit(value_and_grad(loss))`` with ``loss`` the sum of the mean
  squares of the four outputs (every layer gets a gradient): compile time
  (``.lower(...).compile()``), XLA's planned memory (``memory_analysis``:
  temp + arguments + outputs; constants such as the physics operators are not
  counted), the first call and the median of ``--repeats`` more calls, each
  ended by ``block_until_ready``; the process's peak resident memory
  (``ru_maxrss``, compile included);
* with ``--forward``, the same for the forward pass alone;
* with ``--reference``, the same step on the slow reference path
  (``conv_impl="fold"``: every 3-D convolution a time-folded 2-D convolution)
  beside the default fast path, both compiled in the same child and timed
  interleaved (``--repeats`` rounds of one call each, medians), their ratio,
  and how far the fast path's loss and gradients are from the reference's
  (largest difference over each gradient leaf's largest magnitude). Configs
  without ``conv_impl`` (``usm``) are timed as before.

Input: Poisson counts (rate 0.05 per bin, a low photon budget). A case that
runs out of its ``--time-limit`` is recorded as a timeout. The Markdown
table goes to ``--out``; the machine (CPU model and cores, memory, JAX
backend and device) and the load average before and after are recorded with it,
since the machine may be shared.
"""

from __future__ import annotations

import argparse
import datetime
import multiprocessing
import os
import pathlib
import resource
import statistics
import sys
import time
import traceback

from experiments import provenance as _machine_facts
from nlosjax.variants import OURS, USM

DEFAULT_OUT = pathlib.Path(__file__).resolve().parent / "results" / "model.md"
GIB = 1024.0 ** 3


def _config(name: str, frames: int):
  import dataclasses

  from nlosjax.models import ModelConfig
  if name in ("cpu", USM):   # what the cpu preset trains, on its data's Setup
    from experiments import configs
    from nlosjax import train
    preset = train.RunConfig.from_dict(configs.get_config("cpu"))
    setup = preset.data.spec().setup
    if name == USM:                  # USM reconstructs one frame
      return train.model_config_for(preset, setup, USM)
    return dataclasses.replace(train.model_config_for(preset, setup, OURS), frames=frames)
  if name == "paper":
    return ModelConfig.paper(frames=frames)
  raise ValueError(f"unknown config {name!r}; choose cpu, usm or paper")


def _small_setup(cfg):
  """A small Setup with the same architecture (same stride, same time strides)."""
  from nlosjax.physics import Setup
  n = max(2 * cfg.stride, 8)
  return Setup(wall_size=cfg.setup.wall_size, grid=(n, n), bin_width=cfg.setup.bin_width,
               num_bins=64)


def _timed(fn, *args, repeats: int):
  import jax
  t = time.perf_counter()
  jax.block_until_ready(fn(*args))
  first = time.perf_counter() - t
  runs = []
  for _ in range(repeats):
    t = time.perf_counter()
    jax.block_until_ready(fn(*args))
    runs.append(time.perf_counter() - t)
  return first, (statistics.median(runs) if runs else float("nan"))


def compare_reference(cfg, params, x, repeats: int) -> dict:
  """Step time and agreement of ``cfg`` (the fast path) against ``cfg.replace(conv_impl="fold")``.

  Both ``jit(value_and_grad(loss))`` are compiled first, then timed interleaved
  (``max(repeats, 3)`` rounds, one call of each per round) so that a shared
  machine's load falls on both alike. Returns ``ref_step_s``, ``fast_step_s``,
  ``speedup`` (ratio of the medians), ``loss_rel_diff`` and ``grad_rel_err``
  (the largest ``max |g_fast - g_ref| / max |g_ref|`` over the gradient leaves).
  """
  import jax
  import jax.numpy as jnp

  def make(c):
    model = c.module()

    def loss(p):
      o = model.apply({"params": p}, x)
      return sum(jnp.mean(jnp.square(o[k])) for k in ("transient", "volume", "intensity", "depth"))
    return jax.jit(jax.value_and_grad(loss)).lower(params).compile()

  steps = {"ref": make(cfg.replace(conv_impl="fold")), "fast": make(cfg)}
  results = {k: f(params) for k, f in steps.items()}
  jax.block_until_ready(results)
  times = {k: [] for k in steps}
  for _ in range(max(repeats, 3)):
    for k, f in steps.items():
      t = time.perf_counter()
      jax.block_until_ready(f(params))
      times[k].append(time.perf_counter() - t)
  (v_ref, g_ref), (v_fast, g_fast) = results["ref"], results["fast"]
  err = max(float(jnp.max(jnp.abs(a - b)) / jnp.maximum(jnp.max(jnp.abs(a)), 1e-30))
            for a, b in zip(jax.tree.leaves(g_ref), jax.tree.leaves(g_fast)))
  ref_s, fast_s = statistics.median(times["ref"]), statistics.median(times["fast"])
  return {"ref_step_s": ref_s, "fast_step_s": fast_s, "speedup": ref_s / fast_s,
          "loss_rel_diff": abs(float(v_fast) - float(v_ref)) / max(abs(float(v_ref)), 1e-30),
          "grad_rel_err": err}


def run_case(name: str, frames: int, batch: int, repeats: int, forward: bool,
             reference: bool = False) -> dict:
  """One config in this process; returns the measured numbers."""
  import jax
  import jax.numpy as jnp

  from nlosjax.models import model_summary

  cfg = _config(name, frames)
  out = {"config": name, "frames": cfg.frames, "batch": batch,
         "input": cfg.input_shape(batch), "grid": cfg.setup.grid, "bins": cfg.setup.num_bins}
  t = time.perf_counter()
  summary = model_summary(cfg)
  out.update(params=summary["params"], gflop=summary["flops"] / 1e9,
             summary_s=time.perf_counter() - t)

  small = cfg.with_setup(_small_setup(cfg))
  key = jax.random.key(0)
  xs = jnp.zeros(small.input_shape(1), jnp.float32)
  params = jax.jit(small.module().init)(key, xs)["params"]
  model = cfg.module()
  x = jax.random.poisson(jax.random.key(1), 0.05, cfg.input_shape(batch)).astype(jnp.float32)
  expected = jax.eval_shape(model.init, key, x)["params"]
  if jax.tree.structure(expected) != jax.tree.structure(params) or jax.tree.leaves(
      jax.tree.map(lambda a, b: a.shape != b.shape, expected, params)).count(True):
    raise RuntimeError("parameter tree differs between Setups")

  def loss(p):
    o = model.apply({"params": p}, x)
    return sum(jnp.mean(jnp.square(o[k])) for k in ("transient", "volume", "intensity", "depth"))

  step = jax.jit(jax.value_and_grad(loss))
  t = time.perf_counter()
  compiled = step.lower(params).compile()
  out["compile_s"] = time.perf_counter() - t
  mem = compiled.memory_analysis()
  out["xla_gib"] = (mem.temp_size_in_bytes + mem.argument_size_in_bytes
                    + mem.output_size_in_bytes) / GIB if mem is not None else float("nan")
  out["first_s"], out["step_s"] = _timed(compiled, params, repeats=repeats)
  value, grads = compiled(params)
  out["finite"] = bool(jnp.isfinite(value)) and all(
      bool(jnp.all(jnp.isfinite(g))) for g in jax.tree.leaves(grads))
  if forward:
    fwd = jax.jit(lambda p: model.apply({"params": p}, x))
    t = time.perf_counter()
    fc = fwd.lower(params).compile()
    out["fwd_compile_s"] = time.perf_counter() - t
    out["fwd_first_s"], out["fwd_s"] = _timed(fc, params, repeats=repeats)
  if reference and hasattr(cfg, "conv_impl"):
    out.update(compare_reference(cfg, params, x, repeats))
  out["max_rss_gib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / GIB
  return out


def _child(queue, *args):
  try:
    queue.put(("ok", run_case(*args)))
  except BaseException:  # noqa: BLE001 (report anything, including MemoryError)
    queue.put(("error", traceback.format_exc(limit=4)))


def run_isolated(name, frames, batch, repeats, forward, time_limit, reference=False) -> dict:
  ctx = multiprocessing.get_context("spawn")
  queue = ctx.Queue()
  proc = ctx.Process(target=_child, args=(queue, name, frames, batch, repeats, forward, reference))
  t = time.perf_counter()
  proc.start()
  proc.join(time_limit)
  wall = time.perf_counter() - t
  if proc.is_alive():
    proc.kill()
    proc.join()
    return {"config": name, "frames": frames, "batch": batch, "status": f"timeout after {wall:.0f} s"}
  if queue.empty():
    return {"config": name, "frames": frames, "batch": batch,
            "status": f"child died (exit code {proc.exitcode}; out of memory?)"}
  status, value = queue.get()
  if status != "ok":
    return {"config": name, "frames": frames, "batch": batch, "status": "error: " + value}
  value["status"] = "ok"
  value["wall_s"] = wall
  return value


def _fmt(v, spec=".2f"):
  if isinstance(v, float):
    return format(v, spec)
  return str(v)


NOTES = """
## What is measured, and how the model departs from the paper

- Shapes: `paper` = `ModelConfig.paper` (16 x 16 scan points x 512 bins of 33 ps, stride 8
  from a 128 x 128 scan of a 2 m wall); `cpu` = the model `python -m experiments.train`
  trains (the cpu preset's Ours on its data Setup); inputs and outputs are in the table.
- Widths are ours (the paper gives none): see `ModelConfig.paper` and the cpu preset.
- 3-D convolutions run as 2-D convolutions of time-folded channels (`Conv3D`): the same
  sums, chosen because XLA:CPU's 3-D convolutions were slower, forward and backward; the
  unstrided ones with at most 4 = Cin x Cout channel pairs (the refinement's) as fused sums of
  shifted slices with their own VJP (`conv_impl="auto"`, the default; `--reference` times
  the all-folded path beside it).
- The stride-2 3-D transposed convolutions of the transient spreading are sub-pixel
  convolutions (`Upsample3D`: conv to 8x the channels, then depth-to-space), a family that
  contains them, chosen because XLA:CPU's transposed 3-D convolutions were much slower.
- "Interleaved extraction" is read as a lossless polyphase time downsampling (r consecutive
  bins -> channels) then interlaced blocks; "interlaced" residual blocks are parallel 3x3x3
  convolutions with temporal dilations 1, 2, 4, channels interlaced and fused by a 1x1x1 conv.
- The recovered transient adds the measured frame interpolated bilinearly from its scan
  points (a learned gain) to the learned residual; the volume adds the normalised physics
  reconstruction of the recovered transient (feature channel 0) to the refinement output.
- The physics layer is `nlosjax.physics`' phasor-field pipeline (operators from
  `lct_operators`, wavelet from `illumination_wavelet`, oversample 1) applied per feature
  channel at half the time resolution; it gates time and crops depth to a Setup's depth range.
- `usm` = the learned baseline USM (`nlosjax.models.usm`) as the cpu preset trains it: one
  frame in, its transient recovery on the full 32 x 32 x 128 grid (branches cut to 2
  channels); the same loss here (sum of the mean squares of the four outputs).
- Intensity = max-projection normalised per image; depth = soft-argmax along depth of each
  column normalised by its maximum (temperature 0.05), blended to 0 m where the intensity is
  below 0.1 through a sigmoid of width 0.02: differentiable everywhere.
- Counts are divided by their per-sample root mean square (guarded; outputs report it as
  `scale`), so a 30x photon budget gives the same reconstruction.
- The cross ST-Mamba averages the two branches before the shared gate (Vision Mamba's
  halving); the aligned features of the t-1 and t+1 blocks (own weights) are averaged and
  added to the target features.
"""


def to_markdown(rows, cmd, load_before, load_after) -> str:
  lines = [
      "# ST-Mamba network: one training step (forward + backward)",
      "",
      f"Produced by `{cmd}`.",
      "",
      f"- Date: {datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')}",
      f"- Commit: {_machine_facts.git_commit()}",
      f"- Machine: {_machine_facts.machine_text()}",
      f"- Versions: {_machine_facts.versions_text()}",
      f"- Load average (1, 5, 15 min) before: {load_before}; after: {load_after}. The machine was"
      " shared with other jobs while this ran, so times are upper bounds for an idle machine.",
      "",
      "Columns: params and GFLOP/frame (forward, one frame = one reconstructed middle frame)"
      " from `model_summary`; compile = `jit(value_and_grad(loss)).lower().compile()`; first"
      " step = first call; step = median of the repeats; XLA GiB = temp + argument + output"
      " bytes planned by XLA (constants not counted); max RSS = peak resident memory of the"
      " child process, compile included.",
      "",
      "| config | frames | input [B,F,T,h,w] | output grid x bins | params | GFLOP/frame |"
      " compile s | first step s | step s | XLA GiB | max RSS GiB | grads finite | status |",
      "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
  ]
  for r in rows:
    if r.get("status") != "ok":
      lines.append(f"| {r['config']} | {r['frames']} | | | | | | | | | | | {r['status']} |")
      continue
    lines.append(
        f"| {r['config']} | {r['frames']} | {list(r['input'])} | {r['grid'][0]}x{r['grid'][1]}"
        f" x {r['bins']} | {r['params']:,} | {r['gflop']:.1f} | {r['compile_s']:.1f} |"
        f" {r['first_s']:.1f} | {_fmt(r['step_s'], '.1f')} | {r['xla_gib']:.2f} |"
        f" {r['max_rss_gib']:.2f} | {r['finite']} | ok |")
  fwd = [r for r in rows if r.get("status") == "ok" and "fwd_s" in r]
  if fwd:
    lines += ["", "Forward pass alone:", "",
              "| config | frames | compile s | first call s | call s |", "|---|---|---|---|---|"]
    for r in fwd:
      lines.append(f"| {r['config']} | {r['frames']} | {r['fwd_compile_s']:.1f} |"
                   f" {r['fwd_first_s']:.1f} | {_fmt(r['fwd_s'], '.1f')} |")
  ref = [r for r in rows if r.get("status") == "ok" and "speedup" in r]
  if ref:
    lines += ["", "Reference path (`conv_impl=\"fold\"`) against the default fast path, the same"
              " step timed interleaved in one process (medians); agreement of the fast path with"
              " the reference: |loss difference| / |loss| and the largest"
              " max |g_fast - g_ref| / max |g_ref| over the gradient leaves:", "",
              "| config | frames | reference step s | fast step s | speedup | loss rel. diff |"
              " grad rel. err |", "|---|---|---|---|---|---|---|"]
    for r in ref:
      lines.append(f"| {r['config']} | {r['frames']} | {r['ref_step_s']:.3f} | {r['fast_step_s']:.3f} |"
                   f" {r['speedup']:.2f}x | {r['loss_rel_diff']:.1e} | {r['grad_rel_err']:.1e} |")
  return "\n".join(lines) + "\n" + NOTES


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--configs", nargs="+", default=["cpu", USM, "paper"],
                 choices=["cpu", USM, "paper"])
  p.add_argument("--frames", type=int, nargs="+", default=[3])
  p.add_argument("--batch", type=int, default=1)
  p.add_argument("--repeats", type=int, default=1)
  p.add_argument("--forward", action="store_true", help="also time the forward pass alone")
  p.add_argument("--reference", action="store_true",
                 help="also time the reference path (conv_impl='fold') beside the fast one, interleaved")
  p.add_argument("--time-limit", type=float, default=600.0, help="seconds per case")
  p.add_argument("--out", type=pathlib.Path, default=DEFAULT_OUT)
  p.add_argument("--no-write", action="store_true", help="print only")
  args = p.parse_args(argv)
  load_before = tuple(round(v, 2) for v in os.getloadavg())
  rows = []
  for name in args.configs:
    for frames in ([1] if name == USM else args.frames):     # USM reconstructs one frame
      r = run_isolated(name, frames, args.batch, args.repeats, args.forward, args.time_limit,
                       args.reference)
      print({k: v for k, v in r.items()}, flush=True)
      rows.append(r)
  load_after = tuple(round(v, 2) for v in os.getloadavg())
  cmd = "python -m benchmarks.model " + " ".join(argv if argv is not None else sys.argv[1:])
  text = to_markdown(rows, cmd.strip(), load_before, load_after)
  print(text)
  if not args.no_write:
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)


if __name__ == "__main__":
  main()

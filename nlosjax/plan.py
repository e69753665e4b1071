"""Predict a training run's memory and time before any data or parameters exist (the dry run).

``python -m experiments.train --config paper --dry-run`` calls :func:`dry_run`:
for each variant of the config it

1. builds the model config from the dataset spec (no data is generated) and
   the optimiser, and lowers and compiles the real jitted train step
   (:func:`nlosjax.train.make_train_step`, state donated, batch split over the
   data-parallel mesh) and the inference step (``model.apply`` at
   ``train.eval_batch_size`` on one device) from abstract shapes
   (``jax.ShapeDtypeStruct``: nothing the size of the model is allocated);
2. reads XLA's plan per device: ``compiled.memory_analysis()`` (peak =
   arguments + outputs + temporaries - donated aliases) and
   ``compiled.cost_analysis()`` FLOPs, plus the FFT and scan FLOPs XLA does
   not count (``analytic_flops``, as :func:`nlosjax.models.network.model_summary`);
3. measures a few real steps of the same model at two reduced Setups (grid
   and bins divided by ``r``, same stride and time strides, same wall and
   depth range) and extrapolates ``time = a + b x FLOPs`` through them to
   the full size (:func:`estimate_step_s`): an *estimate*, which assumes the
   large step runs at the FLOP rate of the two smaller ones (on a GPU small
   steps underuse the device, so it errs high there). Where the full size
   is among the sizes tried (small configs), it is measured, not estimated;
4. compares the planned peak with the device's memory and, when it does not
   fit, names the fix: the largest batch that fits, rematerialisation,
   physics chunking, more devices.

:func:`check_fits` is step 1, 2 and 4 alone; the main job calls it before
generating data when ``train.check_memory`` is set (the paper preset sets it)
and refuses with :class:`DoesNotFit`.
"""

from __future__ import annotations

import dataclasses
import os
import time
import warnings
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from nlosjax import train
from nlosjax.models.network import flop_counts
from nlosjax.physics import Setup, operator_args
from nlosjax.train.config import RunConfig

GIB = 2 ** 30
#: Fraction of the device memory a plan may use (XLA needs some room beyond its plan:
#: code, constants, the runtime, and on a CPU the data loader and the OS).
MEMORY_FRACTION = 0.9


class DoesNotFit(ValueError):
  """The planned peak memory of a step exceeds the device's memory; the message names the fix."""


@dataclasses.dataclass(frozen=True)
class StepPlan:
  """XLA's plan for one compiled step, per device.

  Attributes:
    kind: ``"train"`` or ``"inference"``.
    batch: global batch of the step; ``devices``: devices it is split over.
    argument_bytes, output_bytes, temp_bytes, alias_bytes: ``memory_analysis()``.
    flops: per device per step, XLA's count plus FFT and scan estimates.
    compile_s: wall time of lowering + compiling.
  """

  kind: str
  batch: int
  devices: int
  argument_bytes: int
  output_bytes: int
  temp_bytes: int
  alias_bytes: int
  flops: float
  compile_s: float

  @property
  def peak_bytes(self) -> int:
    """Planned peak per device: arguments + outputs + temporaries - donated (aliased) buffers."""
    return self.argument_bytes + self.output_bytes + self.temp_bytes - self.alias_bytes


def device_memory(device=None) -> tuple[int | None, str]:
  """``(bytes, source)`` a step may plan for on ``device`` (default: the first local device).

  GPU/TPU: ``memory_stats()["bytes_limit"]`` (what XLA's allocator may use).
  CPU: the host's available memory (``MemAvailable``, else physical memory)
  shared by its local devices. ``(None, why)`` where neither is known.
  """
  device = device or jax.local_devices()[0]
  if device.platform != "cpu":
    try:
      stats = device.memory_stats() or {}
    except Exception:                            # some backends do not implement it
      stats = {}
    if "bytes_limit" in stats:
      return int(stats["bytes_limit"]), f"{device.platform} memory_stats()['bytes_limit']"
    return None, f"{device.platform}: memory_stats() has no bytes_limit"
  total, source = None, ""
  try:
    with open("/proc/meminfo") as f:
      info = dict(line.split(":", 1) for line in f)
    total, source = int(info["MemAvailable"].split()[0]) * 1024, "host MemAvailable"
  except (OSError, KeyError, ValueError):
    try:
      total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
      source = "host physical memory"
    except (ValueError, OSError, AttributeError):
      return None, "cpu: host memory unknown"
  n = jax.local_device_count()
  return total // n, source + (f" / {n} local devices" if n > 1 else "")


def _flops(compiled, mcfg, batch: int, devices: int, backward: bool) -> float:
  """FLOPs per device of one compiled step: XLA's per-device count plus the global FFT and scan estimates split."""
  xla, fft, scan = flop_counts(compiled.cost_analysis(), mcfg, batch, backward=backward)
  return xla + (fft + scan) / devices


def _step_plan(kind, compiled, mcfg, batch, devices, compile_s, backward) -> StepPlan:
  mem = compiled.memory_analysis()
  if mem is None:
    raise RuntimeError(f"{jax.devices()[0].platform}: XLA gives no memory_analysis() for the {kind} step")
  return StepPlan(kind=kind, batch=int(batch), devices=int(devices),
                  argument_bytes=int(mem.argument_size_in_bytes),
                  output_bytes=int(mem.output_size_in_bytes), temp_bytes=int(mem.temp_size_in_bytes),
                  alias_bytes=int(getattr(mem, "alias_size_in_bytes", 0) or 0),
                  flops=_flops(compiled, mcfg, batch, devices, backward), compile_s=float(compile_s))


def _abstract_batch(mcfg, batch: int, mesh) -> dict:
  """The batch as shapes, split over ``mesh``.

  ``measurement [B, F, T, h, w]``, ``transient [B, T, H, W]``, ``intensity`` and ``depth [B, H, W]``.
  """
  s = mcfg.setup
  split = NamedSharding(mesh, P("data"))
  shapes = {"measurement": tuple(mcfg.input_shape(batch)),
            "transient": (batch, s.num_bins) + tuple(s.grid),
            "intensity": (batch,) + tuple(s.grid), "depth": (batch,) + tuple(s.grid)}
  return {k: jax.ShapeDtypeStruct(v, jnp.float32, sharding=split) for k, v in shapes.items()}


def compile_train_step(config: RunConfig, mcfg, variant: str, mesh):
  """``(compiled, abstract_state, abstract_batch)``: the run's real train step, compiled from shapes."""
  tr = config.train
  batch = tr.batch_size
  n = mesh.devices.size
  if batch % n:
    raise DoesNotFit(f"train.batch_size = {batch} does not split over the {n} devices of the mesh; "
                     f"use a multiple of {n} (or train.devices)")
  optim, weights = train.training_recipe(config, variant)
  tx = train.make_optimizer(optim, tr.steps)
  state = train.abstract_train_state(train.network(mcfg), tuple(mcfg.input_shape(batch)), tx, mesh)
  batch_shapes = _abstract_batch(mcfg, batch, mesh)
  key = jax.eval_shape(lambda: jax.random.key(0))
  step = train.make_train_step(mcfg, weights, mesh)
  return step.lower(state, batch_shapes, key).compile(), state, batch_shapes


def _compile_inference(mcfg, batch: int):
  model = train.network(mcfg)
  x = jax.ShapeDtypeStruct(tuple(mcfg.input_shape(batch)), jnp.float32)
  params = jax.eval_shape(model.init, jax.random.key(0), x)["params"]
  forward = operator_args.bind(lambda p, xx: model.apply({"params": p}, xx), mcfg.physics_operators())
  return forward.lower(params, x).compile()


def plan_variant(config: RunConfig, setup: Setup, variant: str, mesh, *, inference: bool = True) -> dict:
  """Compile ``variant``'s train (and inference) step for ``setup``: ``{"model_config", "train", "inference"}``."""
  mcfg = train.model_config_for(config, setup, variant)
  t = time.perf_counter()
  compiled, _, _ = compile_train_step(config, mcfg, variant, mesh)
  out = {"model_config": mcfg,
         "train": _step_plan("train", compiled, mcfg, config.train.batch_size,
                             mesh.devices.size, time.perf_counter() - t, backward=True)}
  if inference:
    b = config.train.eval_batch
    t = time.perf_counter()
    compiled = _compile_inference(mcfg, b)
    out["inference"] = _step_plan("inference", compiled, mcfg, b, 1, time.perf_counter() - t,
                                  backward=False)
  return out


def reduced_setup(setup: Setup, stride: int, factor: int) -> Setup | None:
  """``setup`` with grid and bins divided by ``factor`` (same wall, same depth range), or None if it does not divide."""
  if isinstance(factor, bool) or not isinstance(factor, int) or factor < 1:
    raise ValueError(f"factor must be an integer >= 1, got {factor!r}")
  H, W = setup.grid
  T = setup.num_bins
  if H % (factor * stride) or W % (factor * stride) or T % factor:
    return None
  with warnings.catch_warnings():          # coarse bins are the point here, not a unit slip
    warnings.simplefilter("ignore")
    return Setup(wall_size=setup.wall_size, grid=(H // factor, W // factor),
                 bin_width=setup.bin_width * factor, num_bins=T // factor)


def measure_reduced(config: RunConfig, setup: Setup, variant: str, mesh, *, steps: int = 3,
                    factors=(8, 4, 2, 1), points: int = 2,
                    log: Callable[[str], None] = print) -> list[dict]:
  """Time real train steps of ``variant`` at the ``points`` largest reductions of ``setup`` the model accepts.

  Returns one ``{"factor", "setup", "step_s" (median of ``steps``), "flops"
  (per device per step)}`` per size, smallest first. A factor is skipped
  where the grid or bins do not divide, the input would be under 4 x 4 scan
  points or 32 bins, or the model rejects the Setup.
  """
  stride = config.data.stride()
  batch = config.train.batch_size
  found, last_error = [], None
  for r in factors:
    small = reduced_setup(setup, stride, r)
    if small is None or small.grid[0] // stride < 4 or small.num_bins < 32:
      continue
    try:
      mcfg = train.model_config_for(config, small, variant)
      compiled, _, batch_shapes = compile_train_step(config, mcfg, variant, mesh)
    except (ValueError, TypeError) as e:
      last_error = e
      continue
    optim, _ = train.training_recipe(config, variant)
    tx = train.make_optimizer(optim, config.train.steps)
    state = train.create_train_state(train.network(mcfg), mcfg.input_shape(batch), tx,
                                     jax.random.key(0), mesh)
    rng = np.random.default_rng(0)
    host = {k: (rng.poisson(0.5, s.shape) if k == "measurement" else rng.random(s.shape)).astype(np.float32)
            for k, s in batch_shapes.items()}
    data = train.shard_batch(host, mesh)
    key = jax.random.key(1)
    state, m = compiled(state, data, key)                      # warm-up
    jax.block_until_ready(m)
    times = []
    for _ in range(steps):
      t = time.perf_counter()
      state, m = compiled(state, data, key)
      jax.block_until_ready(m)
      times.append(time.perf_counter() - t)
    del state
    log(f"[{variant}] measured at 1/{r} size ({small.grid[0]}x{small.grid[1]} x {small.num_bins}):"
        f" {np.median(times):.3f} s per step")
    found.append({"factor": r, "setup": small, "step_s": float(np.median(times)),
                  "flops": _flops(compiled, mcfg, batch, mesh.devices.size, backward=True)})
    if len(found) == points:
      break
  if not found:
    raise ValueError(f"no reduced Setup of {setup} runs {variant!r} (last error: {last_error})")
  return found


def estimate_step_s(measured: list[dict], flops: float) -> float:
  """Seconds per step at ``flops`` from :func:`measure_reduced`'s points.

  The full size itself when it was measured; else ``a + b * flops`` through
  the two points (``a >= 0``: a fixed per-step cost that FLOP scaling alone
  would multiply), or ``t * flops / f`` from one point.
  """
  for m in measured:
    if m["factor"] == 1:
      return m["step_s"]
  if len(measured) >= 2:
    (f0, t0), (f1, t1) = sorted((m["flops"], m["step_s"]) for m in measured[:2])
    if f1 > f0:
      b = max((t1 - t0) / (f1 - f0), 0.0)
      a = max(t1 - b * f1, 0.0)
      if b > 0:
        return a + b * flops
  m = max(measured, key=lambda m: m["flops"])
  return m["step_s"] * flops / max(m["flops"], 1.0)


def _fixes(config: RunConfig, plan: StepPlan, limit: int) -> list[str]:
  """What would make ``plan`` fit in ``limit`` bytes, most direct first."""
  model = config.model
  fixes = []
  per_device = plan.batch // plan.devices
  fixed = plan.peak_bytes - plan.temp_bytes          # state and arguments: do not shrink with the batch
  if per_device > 1 and plan.temp_bytes > 0:
    fits = int((limit - fixed) / (plan.temp_bytes / per_device))
    if fits >= 1:
      b = min(fits, per_device - 1) * plan.devices
      fixes.append(f"train.batch_size={b} (about {(fixed + plan.temp_bytes * b / plan.batch) / GIB:.1f}"
                   " GiB per device, linear in the batch)")
  if not model.get("remat", False):
    fixes.append("model.remat=True (recompute activations in the backward pass)")
  if model.get("physics_chunk") is None and "physics_chunk" in _model_fields(config):
    fixes.append("model.physics_chunk=1 (the physics layer one feature channel at a time)")
  fixes.append(f"more devices: the batch is split over the data-parallel mesh ({plan.devices} now;"
               " per-device activations shrink in proportion)")
  return fixes


def _model_fields(config) -> set:
  from nlosjax.models.network import ModelConfig
  return {f.name for f in dataclasses.fields(ModelConfig)}


def verdict(config: RunConfig, plan: StepPlan, memory: int | None, variant: str) -> str | None:
  """None when ``plan`` fits ``MEMORY_FRACTION`` of ``memory`` (or memory is unknown), else the error message."""
  if memory is None:
    return None
  limit = int(MEMORY_FRACTION * memory)
  if plan.peak_bytes <= limit:
    return None
  fixes = "\n".join(f"  - {f}" for f in _fixes(config, plan, limit))
  return (f"[{variant}] the {plan.kind} step plans {plan.peak_bytes / GIB:.2f} GiB per device, more than "
          f"{MEMORY_FRACTION:.0%} of the device's {memory / GIB:.2f} GiB ({limit / GIB:.2f} GiB); "
          f"batch {plan.batch} over {plan.devices} device(s). Fixes:\n{fixes}")


def check_fits(config: RunConfig, *, log: Callable[[str], None] = print) -> None:
  """Compile every variant's train step from shapes; raise :class:`DoesNotFit` if one would not fit."""
  setup, mesh = config.data.spec().setup, train.mesh_for(config)
  memory, _ = device_memory()
  for variant in config.train.variants:
    p = plan_variant(config, setup, variant, mesh, inference=False)["train"]
    log(f"[{variant}] planned train step: {p.peak_bytes / GIB:.2f} GiB per device")
    message = verdict(config, p, memory, variant)
    if message:
      raise DoesNotFit(message + "\n(train.check_memory=False skips this check)")


def dry_run(config: RunConfig, *, measure: bool = True, log: Callable[[str], None] = print) -> dict:
  """The dry run (module docstring): plans, estimates and verdicts per variant; nothing is trained or written.

  Returns ``{"devices", "platform", "memory_bytes", "memory_source", "steps",
  "variants": {variant: {"model_config", "train": StepPlan, "inference":
  StepPlan, "reduced": {...} | None, "step_s", "run_s", "fits": bool,
  "problem": str | None}}}``; times are estimates (module docstring, step 3).
  """
  setup, mesh = config.data.spec().setup, train.mesh_for(config)
  memory, source = device_memory()
  steps = config.train.steps
  out = {"devices": mesh.devices.size, "platform": jax.devices()[0].platform,
         "device_kind": jax.devices()[0].device_kind, "memory_bytes": memory,
         "memory_source": source, "steps": steps, "setup": setup, "variants": {}}
  for variant in config.train.variants:
    log(f"[{variant}] compiling the train and inference steps from shapes ...")
    v = plan_variant(config, setup, variant, mesh)
    problems = [m for m in (verdict(config, v[k], memory, variant) for k in ("train", "inference")) if m]
    v["problem"] = "\n".join(problems) or None
    v["fits"] = not problems
    v["reduced"] = v["step_s"] = v["run_s"] = None
    if measure:
      v["reduced"] = measure_reduced(config, setup, variant, mesh, log=log)
      v["step_s"] = estimate_step_s(v["reduced"], v["train"].flops)
      v["run_s"] = v["step_s"] * steps
    out["variants"][variant] = v
  return out


def _duration(s: float | None) -> str:
  if s is None:
    return "not measured"
  if s < 120:
    return f"{s:.1f} s"
  if s < 7200:
    return f"{s / 60:.1f} min"
  return f"{s / 3600:.1f} h"


def format_plan(plan: dict) -> str:
  """The dry run's report: a table per variant and the verdicts."""
  s = plan["setup"]
  mem = plan["memory_bytes"]
  lines = [f"Dry run: {plan['devices']} x {plan['device_kind']} ({plan['platform']}); memory per device"
           f" {'unknown' if mem is None else f'{mem / GIB:.2f} GiB'} ({plan['memory_source']});"
           f" data {s.grid[0]}x{s.grid[1]} x {s.num_bins} bins of {s.bin_width * 1e12:.0f} ps;"
           f" {plan['steps']} steps.", "",
           "| variant | step | batch / devices | planned peak GiB/device (args + out + temp - alias) |"
           " GFLOP/device | compile s | est. s/step | est. run |",
           "|---|---|---|---|---|---|---|---|"]
  for name, v in plan["variants"].items():
    for kind in ("train", "inference"):
      p = v[kind]
      est = (f"{v['step_s']:.3g}", _duration(v["run_s"])) if kind == "train" and v["step_s"] else ("", "")
      lines.append(
          f"| {name} | {kind} | {p.batch} / {p.devices} | {p.peak_bytes / GIB:.3g} ({p.argument_bytes / GIB:.3g}"
          f" + {p.output_bytes / GIB:.3g} + {p.temp_bytes / GIB:.3g} - {p.alias_bytes / GIB:.3g}) |"
          f" {p.flops / 1e9:.1f} | {p.compile_s:.1f} | {est[0]} | {est[1]} |")
  lines.append("")
  for name, v in plan["variants"].items():
    if v.get("reduced"):
      points = "; ".join(f"1/{r['factor']} size ({r['setup'].grid[0]}x{r['setup'].grid[1]} x"
                         f" {r['setup'].num_bins}): {r['step_s']:.3f} s, {r['flops'] / 1e9:.2f} GFLOP"
                         for r in v["reduced"])
      how = ("measured at full size" if any(r["factor"] == 1 for r in v["reduced"])
             else "extrapolated in FLOPs (time = a + b x FLOPs through the measured points)")
      lines.append(f"- {name}: time per step {how}; measured {points}. Training only: data"
                   " generation and evaluation not included.")
    lines.append(f"- {name}: " + ("fits." if v["fits"] else "DOES NOT FIT:\n" + v["problem"]))
  return "\n".join(lines)

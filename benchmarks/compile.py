"""Compile time with the physics operators as constants and as arguments, side by side.

    python -m benchmarks.compile [--config paper] [--variant ours] [--batch 1] [--repeats 2]
                                 [--out benchmarks/results/compile.md]

For the preset's model (its Setup, the train recipe's loss) two programs are
lowered and compiled, each two ways, alternating round by round so background
load hits both alike:

* train step: :func:`nlosjax.train.make_train_step` (the operators an argument,
  :mod:`nlosjax.physics.operator_args`) against the same function under a plain
  ``jax.jit`` (the operators read as constants);
* forward: ``model.apply`` bound to :meth:`~nlosjax.models.network.ModelConfig.physics_operators`
  against a plain ``jax.jit``.

Reported per program and way: the median lower and compile seconds, the
lowered text's size (the constants are written into it), and the compiled
program's outputs on one random batch compared (the same numbers, float32
rounding apart). Nothing runs a step: shapes only, plus one forward each way.
"""

from __future__ import annotations

import argparse
import functools
import pathlib
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import provenance as _machine
from nlosjax.variants import OURS

DEFAULT_OUT = pathlib.Path(__file__).resolve().parent / "results" / "compile.md"
MB = 1e6


def _programs(config_name: str, variant: str, batch: int):
  """``{name: (constants_fn, bound_fn, abstract_args, concrete_args or None)}`` for the preset's model."""
  from experiments.cli import load_config
  from nlosjax import train as T
  from nlosjax.physics import illumination_wavelet, operator_args
  from nlosjax.train.sharding import make_mesh
  from nlosjax.train.step import train_step

  cfg = T.RunConfig.from_dict(load_config(config_name))
  setup = cfg.data.spec().setup
  mcfg = T.model_config_for(cfg, setup, variant)
  model = T.network(mcfg)
  optim, weights = T.training_recipe(cfg, variant)
  mesh = make_mesh()
  tx = T.make_optimizer(optim, cfg.train.steps)
  state = T.abstract_train_state(model, tuple(mcfg.input_shape(batch)), tx, mesh)
  H, W = setup.grid
  f32 = jnp.float32
  batch_shapes = {"measurement": jax.ShapeDtypeStruct(tuple(mcfg.input_shape(batch)), f32),
                  "transient": jax.ShapeDtypeStruct((batch, setup.num_bins, H, W), f32),
                  "intensity": jax.ShapeDtypeStruct((batch, H, W), f32),
                  "depth": jax.ShapeDtypeStruct((batch, H, W), f32)}
  key = jax.eval_shape(lambda: jax.random.key(0))
  wavelet = (illumination_wavelet(setup, cycles=mcfg.wavelet_cycles, sampling_coeff=mcfg.wavelet_sampling)
             if weights.phasor_field else None)
  step = functools.partial(train_step, weights=weights, wavelet=wavelet, time_window=mcfg.time_window)
  x = jax.ShapeDtypeStruct(tuple(mcfg.input_shape(batch)), f32)
  params = jax.eval_shape(model.init, jax.random.key(0), x)["params"]

  def forward(p, xx):
    return model.apply({"params": p}, xx)["intensity"]

  return mcfg, {
      "train step": (jax.jit(step, donate_argnums=0), T.make_train_step(mcfg, weights, mesh),
                     (state, batch_shapes, key), None),
      "forward": (jax.jit(forward), operator_args.bind(forward, mcfg.physics_operators()),
                  (params, x), x)}


def measure(config_name: str, variant: str, batch: int, repeats: int, log=print) -> dict:
  mcfg, programs = _programs(config_name, variant, batch)
  ops_bytes = sum(a.nbytes for a in jax.tree.leaves(mcfg.physics_operators()))
  out = {"model_config": mcfg, "operator_bytes": ops_bytes, "programs": {}}
  for name, (const_fn, bound_fn, args, x_abs) in programs.items():
    rows = {"constants": {"lower": [], "compile": []}, "arguments": {"lower": [], "compile": []}}
    compiled = {}
    for r in range(repeats):
      for way, fn in (("constants", const_fn), ("arguments", bound_fn)):
        jax.clear_caches()
        t0 = time.perf_counter()
        lowered = fn.lower(*args)
        t1 = time.perf_counter()
        c = lowered.compile()
        t2 = time.perf_counter()
        rows[way]["lower"].append(t1 - t0)
        rows[way]["compile"].append(t2 - t1)
        if r == 0:
          rows[way]["text_mb"] = len(lowered.as_text()) / MB
        compiled[way] = c
        log(f"[compile] {name} / {way} round {r + 1}: lower {t1 - t0:.1f} s, compile {t2 - t1:.1f} s")
    for way in rows:
      rows[way]["lower_s"] = statistics.median(rows[way].pop("lower"))
      rows[way]["compile_s"] = statistics.median(rows[way].pop("compile"))
    if x_abs is not None:                     # the same numbers both ways, on one random input
      params = jax.jit(mcfg.module().init)(jax.random.key(1), jnp.zeros(x_abs.shape, x_abs.dtype))["params"]
      xin = jax.random.uniform(jax.random.key(2), x_abs.shape) * 10.0
      a = np.asarray(compiled["constants"](params, xin))
      b = np.asarray(compiled["arguments"](params, xin))
      rows["max_abs_difference"] = float(np.max(np.abs(a - b)))
      rows["max_abs_value"] = float(np.max(np.abs(a)))
    out["programs"][name] = rows
  return out


def report(result: dict, command: str) -> str:
  mcfg = result["model_config"]
  lines = ["# Compile time: the physics operators as constants and as arguments", "",
           *_machine.provenance(command), "",
           f"Model: {type(mcfg).__name__} on {mcfg.setup}; stride {mcfg.stride}; {mcfg.frames} frame(s)."
           f" The operators the model reads: {result['operator_bytes'] / MB:.1f} MB.", "",
           "| program | operators | lower (s) | compile (s) | lowered text (MB) |",
           "|---|---|---|---|---|"]
  for name, rows in result["programs"].items():
    for way in ("constants", "arguments"):
      r = rows[way]
      lines.append(f"| {name} | {way} | {r['lower_s']:.1f} | {r['compile_s']:.1f} | {r['text_mb']:.1f} |")
  lines.append("")
  for name, rows in result["programs"].items():
    c, a = rows["constants"], rows["arguments"]
    total_c, total_a = c["lower_s"] + c["compile_s"], a["lower_s"] + a["compile_s"]
    text = (f"- {name}: lower + compile {total_c:.1f} s with constants, {total_a:.1f} s with arguments"
            f" ({total_c / max(total_a, 1e-9):.2f}x)")
    if "max_abs_difference" in rows:
      text += (f"; outputs on one random batch differ by at most {rows['max_abs_difference']:.2g}"
               f" (largest value {rows['max_abs_value']:.3g})")
    lines.append(text + ".")
  lines += ["", "Medians over the rounds; `jax.clear_caches()` before each compile, so no"
            " trace or executable is reused. The train step is the run's own"
            " (`make_train_step`: operators an argument) against the same function under a plain"
            " `jax.jit` (operators read as constants).", ""]
  return "\n".join(lines)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="paper", help="preset name or .py file (default: paper)")
  parser.add_argument("--variant", default=OURS, help="model variant (default: ours)")
  parser.add_argument("--batch", type=int, default=1, help="batch of the compiled programs (default: 1)")
  parser.add_argument("--repeats", type=int, default=2, help="rounds per way (default: 2)")
  parser.add_argument("--out", default=str(DEFAULT_OUT), help="results file ('-': print only)")
  argv = sys.argv[1:] if argv is None else list(argv)
  args = parser.parse_args(argv)
  result = measure(args.config, args.variant, args.batch, args.repeats)
  text = report(result, "python -m benchmarks.compile " + " ".join(argv))
  print(text)
  if args.out != "-":
    pathlib.Path(args.out).write_text(text)
  return 0


if __name__ == "__main__":
  sys.exit(main())

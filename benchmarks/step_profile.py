"""Where a training step's time goes: XLA's profile of the preset's train step, by model part and op kind.

    python -m benchmarks.step_profile [--config cpu] [--variants ours_s ours] [--steps 5]
                                      [--out benchmarks/results/step_profile.md]

For each variant, in this process: the run's own train step (``nlosjax.plan.compile_train_step``:
the preset's batch, mesh, optimiser and loss weights, compiled once; the profiled program is the
one whose HLO text is read) on a fixed synthetic batch of the preset's shapes
(Poisson counts, rate 0.5 per bin); 3 warm steps, ``--steps`` timed steps (median), then
``--steps`` more under ``jax.profiler.trace``. Each XLA op the profile records (``hlo_op``) is
looked up in the compiled step's HLO text, whose ``op_name`` metadata names the JAX code it came
from: the network's module path (``extract``, ``st_mamba0/ssm``, ``volume/refine``, ...),
forward (``jvp``) or backward (``transpose(jvp)``), or neither (the loss and the optimiser's
update); ops XLA inserted without metadata (layout copies) are counted as such.

Times are each op's self time (a ``while`` loop's own time, not its body's ops, which are counted
where they come from), summed over the two threads XLA:CPU runs ops on, per step. Their sum can
exceed the step's wall time (ops overlap on the threads) and falls short of it by what is not an
op (the host's dispatch, waiting). Shares are of the summed op time. On a machine with other
jobs (load average above) times are upper bounds; the shares move less.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import pathlib
import re
import statistics
import sys
import tempfile
import time

from experiments import provenance as _machine
from nlosjax.variants import OURS, OURS_S

DEFAULT_OUT = pathlib.Path(__file__).resolve().parent / "results" / "step_profile.md"
RATE = 0.5           # Poisson rate per bin of the synthetic measurement
WARM = 3
SMALL = 0.01         # parts below this share of the op time share one row
#: Top-level modules whose parts are told apart one level down (the volume stage's physics and
#: refinement; each ST-Mamba block's SSMs, norms and projections).
TWO_LEVELS = ("volume", "st_mamba", "cross_")

#: Op kinds by the name XLA gives a thunk: the first rule whose pattern the name (its index
#: dropped) matches wins.
KINDS = (("FFT", r"fft"),
         ("convolution and matmul", r"ynn|dot|convolution|custom-call"),
         ("loop control (while, call)", r"^(while|call|conditional)$"),
         ("data movement (copy, transpose, pad, broadcast, concatenate, slice)",
          r"^(wrapped_)?((copy|transpose|pad|broadcast|concatenate|slice|dynamic-slice|"
          r"dynamic-update-slice|bitcast|reshape|gather|scatter|iota)_?)+(fusion)?$"),
         ("elementwise and reductions", r"."))


def op_kind(name: str) -> str:
  """The kind (:data:`KINDS`) of a thunk named ``name`` (e.g. ``"multiply_add_fusion.615"``)."""
  base = re.sub(r"\.\d+$", "", name)
  return next(kind for kind, pattern in KINDS if re.search(pattern, base))


def op_part(op_name: str | None, model: str = "STMambaNet") -> tuple[str, str]:
  """``(part, direction)`` of one HLO op from its ``op_name`` metadata.

  ``model``: the network's class name, as JAX writes it in ``op_name``. ``part``: the network's
  module path, two levels deep under :data:`TWO_LEVELS` (``"volume/refine"``) and one elsewhere
  (``"extract"``), or ``"loss and optimiser"`` for traced code outside the network, or
  ``"XLA-inserted (no metadata)"``. ``direction``: ``"forward"``, ``"backward"`` or ``"-"``.
  """
  if not op_name:
    return "XLA-inserted (no metadata)", "-"
  m = re.search(rf"(transpose\()?jvp\({re.escape(model)}\)\)?/(.*)", op_name)
  if m is None:
    return "loss and optimiser", "-"
  direction = "backward" if m.group(1) else "forward"
  path = [p for p in m.group(2).split("/") if p and not p.startswith(("jit(", "while", "body",
                                                                      "closed_call"))]
  modules = [p for p in path[:-1] if re.fullmatch(r"[A-Za-z_]+\d*(_\d+)?", p)]  # the op itself is last
  if not modules:
    return "network (top level)", direction
  depth = 2 if modules[0].startswith(TWO_LEVELS) else 1
  return "/".join(modules[:depth]), direction


def hlo_op_names(hlo_text: str) -> dict[str, str]:
  """``{instruction name: op_name}`` from a compiled module's HLO text (instructions with metadata)."""
  out = {}
  for m in re.finditer(r"^\s*(?:ROOT\s+)?%?([\w.\-]+) = .*?metadata=\{[^}]*?op_name=\"([^\"]*)\"",
                       hlo_text, re.M):
    out[m.group(1)] = m.group(2)
  return out


def self_times(events: list[dict]) -> dict[str, float]:
  """``{hlo_op: self time in µs}`` over trace events: each op's duration less that of ops nested in it.

  ``events``: Chrome-trace ``"X"`` events with ``args.hlo_op``; nesting is by time on one thread.
  """
  out: dict[str, float] = collections.defaultdict(float)
  by_thread = collections.defaultdict(list)
  for e in events:
    by_thread[(e["pid"], e["tid"])].append(e)
  for evs in by_thread.values():
    evs.sort(key=lambda e: (e["ts"], -e["dur"]))
    stack: list[list] = []                        # [end, hlo_op]
    for e in evs:
      start, end, op = e["ts"], e["ts"] + e["dur"], e["args"]["hlo_op"]
      while stack and stack[-1][0] <= start:
        stack.pop()
      out[op] += e["dur"]
      if stack:
        out[stack[-1][1]] -= e["dur"]             # the parent's own time excludes its children
      stack.append([end, op])
  return dict(out)


def read_trace(folder: pathlib.Path, module: str) -> list[dict]:
  """The ``"X"`` events of ``module``'s ops from the newest ``*.trace.json.gz`` under ``folder``."""
  paths = sorted(folder.rglob("*.trace.json.gz"), key=lambda p: p.stat().st_mtime)
  if not paths:
    raise RuntimeError(f"jax.profiler.trace wrote no *.trace.json.gz under {folder}")
  data = json.loads(gzip.open(paths[-1]).read())
  return [e for e in data["traceEvents"] if e.get("ph") == "X" and "hlo_op" in e.get("args", {})
          and e["args"].get("hlo_module") == module]


def profile_variant(config: dict, variant: str, steps: int) -> dict:
  """Time and profile ``variant``'s train step: ``{"step_s", "op_s", "parts", "kinds", ...}`` (seconds per step)."""
  import jax
  import numpy as np

  from nlosjax import inference, plan
  from nlosjax import train as T
  typed = T.RunConfig.from_dict(config)
  mcfg = T.model_config_for(typed, inference.training_setup(typed), variant)
  mesh = T.mesh_for(typed)
  batch = int(config["train"]["batch_size"])
  t = time.perf_counter()
  step, _, batch_shapes = plan.compile_train_step(typed, mcfg, variant, mesh)   # the run's own step
  compile_s = time.perf_counter() - t
  text = step.as_text()
  names, model = hlo_op_names(text), type(T.network(mcfg)).__name__
  module = re.search(r"HloModule\s+([\w.\-]+)", text).group(1)
  optim, _ = T.training_recipe(typed, variant)
  state = T.create_train_state(T.network(mcfg), tuple(mcfg.input_shape(batch)),
                               T.make_optimizer(optim, int(config["train"]["steps"])), jax.random.key(0), mesh)
  rng = np.random.default_rng(0)
  data = T.shard_batch({k: (rng.poisson(RATE, s.shape) if k == "measurement" else rng.random(s.shape))
                        .astype(np.float32) for k, s in batch_shapes.items()}, mesh)
  key = jax.random.key(1)
  for _ in range(WARM):
    state, metrics = step(state, data, key)
    jax.block_until_ready(metrics)
  times = []
  for _ in range(steps):
    t = time.perf_counter()
    state, metrics = step(state, data, key)
    jax.block_until_ready(metrics)
    times.append(time.perf_counter() - t)
  with tempfile.TemporaryDirectory() as tmp:
    with jax.profiler.trace(tmp):
      for _ in range(steps):
        state, metrics = step(state, data, key)
        jax.block_until_ready(metrics)
    events = read_trace(pathlib.Path(tmp), module)
  own = self_times(events)
  parts: dict[tuple[str, str], float] = collections.defaultdict(float)
  kinds: dict[str, float] = collections.defaultdict(float)
  found = 0.0
  for op, us in own.items():
    s = us / 1e6 / steps
    if op in names:
      found += s
    parts[op_part(names.get(op), model)] += s
    kinds[op_kind(op)] += s
  total = sum(own.values()) / 1e6 / steps
  return {"variant": variant, "input": list(mcfg.input_shape(batch)), "compile_s": compile_s,
          "step_s": statistics.median(times), "op_s": total, "ops": len(own),
          "events_per_step": len(events) / steps, "with_metadata": found / total if total else 0.0,
          "parts": dict(parts), "kinds": dict(kinds)}


def _pct(x: float, total: float) -> str:
  return f"{100 * x / total:.1f} %" if total else "-"


def render(results: list[dict], command: str, config_name: str) -> str:
  """The Markdown report for the profiles of :func:`profile_variant`."""
  lines = [f"# Where a training step's time goes: the `{config_name}` preset's train step, profiled", ""]
  lines += _machine.provenance(command) + [""]
  lines += ["| variant | input [B, F, T, h, w] | compile (s) | step (s, median) | op time (s per step) "
            "| ops | op runs per step | op time with metadata |", "|---|---|---:|---:|---:|---:|---:|---:|"]
  for r in results:
    lines.append(f"| {r['variant']} | {' x '.join(map(str, r['input']))} | {r['compile_s']:.1f} | "
                 f"{r['step_s']:.3f} | {r['op_s']:.3f} | {r['ops']} | {r['events_per_step']:.0f} | "
                 f"{100 * r['with_metadata']:.0f} % |")
  for r in results:
    total = r["op_s"]
    lines += ["", f"## {r['variant']}: by part of the model", "",
              "| part | forward (s) | backward (s) | other (s) | share |", "|---|---:|---:|---:|---:|"]
    by_part: dict[str, dict[str, float]] = collections.defaultdict(lambda: collections.defaultdict(float))
    for (part, direction), s in r["parts"].items():
      by_part[part][direction] += s
    small = collections.defaultdict(float)
    for part, d in sorted(by_part.items(), key=lambda kv: -sum(kv[1].values())):
      if sum(d.values()) < SMALL * total:
        for direction, s in d.items():
          small[direction] += s
        small["parts"] += 1
        continue
      lines.append(f"| `{part}` | {d.get('forward', 0):.3f} | {d.get('backward', 0):.3f} | "
                   f"{d.get('-', 0):.3f} | {_pct(sum(d.values()), total)} |")
    if small:
      n = int(small.pop("parts"))
      lines.append(f"| {n} parts below {100 * SMALL:g} % each | {small.get('forward', 0):.3f} | "
                   f"{small.get('backward', 0):.3f} | {small.get('-', 0):.3f} | {_pct(sum(small.values()), total)} |")
    lines += ["", f"## {r['variant']}: by kind of op", "", "| kind | s per step | share |", "|---|---:|---:|"]
    for kind, s in sorted(r["kinds"].items(), key=lambda kv: -kv[1]):
      lines.append(f"| {kind} | {s:.3f} | {_pct(s, total)} |")
  lines += ["", "How to read it: op times are self times (a loop's own time; its body's ops are counted "
            "under the code they come from), summed over XLA:CPU's threads, per step; shares are of that "
            "sum. `forward`/`backward`: the network's forward pass and its transpose; `other`: ops of "
            "that part outside both (none for the network's parts). Parts are module paths of the "
            "parameter tree (`python -m benchmarks.step_profile --help`)."]
  return "\n".join(lines) + "\n"


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="cpu", help="preset name or .py file (default: %(default)s)")
  parser.add_argument("--variants", nargs="+", default=[OURS_S, OURS],
                      help="model variants to profile (default: %(default)s)")
  parser.add_argument("--steps", type=int, default=5, help="timed and profiled steps each (default: %(default)s)")
  parser.add_argument("--out", default=str(DEFAULT_OUT), help="Markdown output")
  args = parser.parse_args(argv)
  if args.steps < 1:
    parser.error("--steps must be at least 1")
  from experiments.cli import load_config
  config = load_config(args.config)
  results = []
  for variant in args.variants:
    print(f"profiling {variant} ...", flush=True)
    results.append(profile_variant(config, variant, args.steps))
  command = "python -m benchmarks.step_profile" + "".join(
      f" {flag} {value}" for flag, value, default in (
          ("--config", args.config, "cpu"), ("--variants", " ".join(args.variants), "ours_s ours"),
          ("--steps", args.steps, "5")) if str(value) != default)
  if pathlib.Path(args.out).resolve() != DEFAULT_OUT:
    command += f" --out {args.out}"
  text = render(results, command, args.config)
  print(text)
  pathlib.Path(args.out).write_text(text)
  print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

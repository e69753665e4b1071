"""Where a compiled step's time goes: per-HLO-op device time from one ``jax.profiler`` trace.

    from benchmarks.op_profile import op_profile
    compiled = jax.jit(f).lower(*args).compile()
    prof = op_profile(lambda: compiled(*args), compiled.as_text(), steps=2)
    prof["ops"][:5], prof["categories"]

The trace (read by :func:`benchmarks.step_profile.read_trace`) holds one complete event
(``"ph": "X"``) per executed op, with the HLO instruction's name in ``args.hlo_op``: on a
GPU one per kernel launch on the device's stream, on XLA:CPU one per thunk. Self times
(:func:`benchmarks.step_profile.self_times`) summed by ``hlo_op`` and divided by the steps
traced are each op's device time per step. Beside ``step_profile`` (a CPU training step by
model part), this module serves any compiled step on any backend, by HLO category.

Each op is put in a category from the compiled HLO text (:func:`hlo_ops`): the
instruction's opcode, or for a fusion the heaviest opcode inside it (convolution before
dot before FFT, ...), and a custom call by its target (cuDNN convolutions and cuBLAS GEMMs
are custom calls on a GPU). Ops inside a ``while`` body appear once per trip, so a serial
loop's cost is the sum of its body's rows.

Limits: time between ops (launch gaps, host syncs) is not in any row. ``busy_ms`` sums op
time over every thread (``lanes``) that ran ops: on a GPU one stream, so against the step's
wall time it says how much of it the device spent running ops at all; on XLA:CPU the
thunk executor runs independent ops on several threads at once, and ``busy_ms`` may
exceed the wall time, up to ``lanes`` times it.
"""

from __future__ import annotations

import collections
import pathlib
import re
import tempfile
import time

from benchmarks.step_profile import read_trace, self_times

#: The opcode that names a fusion's category, first match wins.
HEAVY = ("convolution", "dot", "fft", "custom-call", "scatter", "gather", "sort", "reduce-window",
         "select-and-scatter", "reduce", "dynamic-update-slice", "dynamic-slice", "transpose", "copy",
         "concatenate", "pad", "slice")
_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*.*?\s([a-z][\w\-]*)\((.*)$")
_COMP = re.compile(r"^\s*(?:ENTRY\s+)?%?([\w.\-]+)\s*\(.*\)\s*->.*\{\s*$")
_CALLS = re.compile(r"calls=%?([\w.\-]+)")
_TARGET = re.compile(r'custom_call_target="([^"]+)"')
_OPNAME = re.compile(r'op_name="([^"]+)"')


def hlo_ops(hlo_text: str) -> dict[str, dict]:
  """``instruction name -> {"opcode", "category", "op_name"}`` for every instruction of an HLO module's text.

  ``category``: the opcode; for a fusion the first of :data:`HEAVY` among the opcodes of the
  computation it calls (``"elementwise"`` when none), for a custom call ``"custom-call:<target>"``.
  ``op_name``: the JAX source op of the instruction (of a fusion: of its heaviest instruction).
  """
  comps: dict[str, list[tuple[str, str, str]]] = collections.defaultdict(list)
  current = None
  for line in hlo_text.splitlines():
    m = _COMP.match(line)
    if m and "=" not in line.split("(")[0]:
      current = m.group(1)
      continue
    m = _INSTR.match(line)
    if m and current is not None:
      comps[current].append((m.group(1), m.group(2), line))

  def describe(opcode: str, line: str, depth: int = 0) -> tuple[str, str]:
    name = (_OPNAME.search(line) or [None, ""])[1]
    if opcode == "custom-call":
      return f"custom-call:{(_TARGET.search(line) or [None, '?'])[1]}", name
    if opcode == "fusion" and depth < 4:
      called = _CALLS.search(line)
      inner = comps.get(called.group(1), []) if called else []
      for heavy in HEAVY:
        for _, op, text in inner:
          if op == heavy:
            return describe(op, text, depth + 1)
          if op == "fusion":                       # a fusion nested in a fusion
            cat, inner_name = describe(op, text, depth + 1)
            if cat.split(":")[0] == heavy:
              return cat, inner_name
      return "elementwise", name
    return opcode, name

  out = {}
  for instrs in comps.values():
    for name, opcode, line in instrs:
      category, op_name = describe(opcode, line)
      out[name] = {"opcode": opcode, "category": category, "op_name": op_name}
  return out


def summarize(events: list[dict], ops: dict[str, dict], steps: int, top: int = 15) -> dict:
  """Per-op and per-category milliseconds per step of ``events`` (as ``step_profile.read_trace`` returns).

  Each op counts its self time (:func:`benchmarks.step_profile.self_times`: a ``while`` op's
  event spans its body's ops on XLA:CPU; counted whole, the body would count twice).

  Returns ``{"ops": [{"op", "category", "op_name", "ms", "share", "count"}, ...] (the
  ``top`` largest), "categories": {category: {"ms", "share"}}, "busy_ms", "distinct_ops",
  "lanes"}``; ``share`` of ``busy_ms``, the op time per step summed over the ``lanes``
  (distinct ``(pid, tid)`` threads) that ran ops.
  """
  if steps < 1:
    raise ValueError(f"steps must be >= 1, got {steps}")
  us = collections.Counter({op: max(t, 0.0) for op, t in self_times(events).items()})
  count = collections.Counter(e["args"]["hlo_op"] for e in events)
  busy = sum(us.values()) / 1e3 / steps
  share = (lambda ms: ms / busy) if busy > 0 else (lambda ms: 0.0)
  unknown = {"opcode": "?", "category": "?", "op_name": ""}
  rows = []
  for op, t in us.most_common():
    info = ops.get(op, unknown)
    ms = t / 1e3 / steps
    rows.append({"op": op, "category": info["category"], "op_name": info["op_name"], "ms": ms,
                 "share": share(ms), "count": count[op] / steps})
  cats = collections.defaultdict(float)
  for r in rows:
    cats[r["category"]] += r["ms"]
  categories = {c: {"ms": ms, "share": share(ms)} for c, ms in sorted(cats.items(), key=lambda kv: -kv[1])}
  lanes = len({(e["pid"], e["tid"]) for e in events})
  return {"ops": rows[:top], "categories": categories, "busy_ms": busy, "distinct_ops": len(rows),
          "lanes": lanes}


def op_profile(run, hlo_text: str, *, steps: int = 2, top: int = 15) -> dict:
  """Trace ``steps`` calls of ``run()`` (one call of a compiled executable) and summarize them.

  ``run``: no arguments, returns what to wait for; a step that donates its state keeps
  the new state itself (e.g. in a closure). ``hlo_text``: the executable's
  ``compiled.as_text()``, for the categories. One untraced call runs first.
  Returns :func:`summarize`'s dict plus ``"wall_ms"`` (mean wall time per traced call,
  profiler overhead included) and ``"steps"``.
  """
  import jax
  ops = hlo_ops(hlo_text)
  module = re.match(r"\s*HloModule\s+([\w.\-]+)", hlo_text)
  if module is None:
    raise ValueError("hlo_text does not start with an HloModule line")
  # One call first, waited for: a call still running when the trace starts would add a partial step.
  jax.block_until_ready(run())
  with tempfile.TemporaryDirectory() as d:
    with jax.profiler.trace(d):
      t0 = time.perf_counter()
      for _ in range(steps):
        jax.block_until_ready(run())
      wall = (time.perf_counter() - t0) / steps
    events = read_trace(pathlib.Path(d), module.group(1))
  return {**summarize(events, ops, steps, top), "wall_ms": wall * 1e3, "steps": steps}


#: Vendor datasheet peaks, dense, in FLOP/s: (float32 on the CUDA cores, TF32 on the tensor
#: cores), by a substring of ``jax.Device.device_kind``. JAX's default float32 matmul and
#: convolution precision on these GPUs may use TF32.
PEAK_FLOPS = {"H200": (67e12, 495e12), "H100": (67e12, 495e12), "A100": (19.5e12, 156e12),
              "L40S": (91.6e12, 183e12), "V100": (15.7e12, None)}


def peak_flops(device_kind: str) -> tuple[float | None, float | None]:
  """``(float32, tf32)`` peak FLOP/s of a device kind from :data:`PEAK_FLOPS`, ``(None, None)`` if unknown."""
  for key, peaks in PEAK_FLOPS.items():
    if key.lower() in device_kind.lower():
      return peaks
  return None, None


def format_profile(prof: dict, flops: float | None = None, peak: tuple | None = None) -> list[str]:
  """Markdown lines: the achieved FLOP/s against ``peak`` (as :func:`peak_flops`), the categories, the top ops."""
  out = []
  wall = prof["wall_ms"]
  lanes = prof.get("lanes", 1)
  over = f", summed over {lanes} threads" if lanes > 1 else ""
  line = (f"Traced {prof['steps']} step(s): {wall:.1f} ms a step (profiler on), ops busy "
          f"{prof['busy_ms']:.1f} ms ({prof['busy_ms'] / wall:.0%} of the wall time{over}) over "
          f"{prof['distinct_ops']} distinct ops.")
  if flops:
    achieved = flops / (wall / 1e3)
    line += f" {flops / 1e9:.4g} GFLOP a step: {achieved / 1e12:.3g} TFLOP/s"
    f32, tf32 = peak or (None, None)
    parts = [f"{achieved / v:.1%} of the {v / 1e12:.0f} TFLOP/s {name} peak"
             for name, v in (("float32", f32), ("TF32", tf32)) if v]
    line += (", " + " and ".join(parts) + "." if parts else ".")
  out += [line, "", "| category | ms a step | share of busy |", "|---|---|---|"]
  out += [f"| {c} | {v['ms']:.2f} | {v['share']:.1%} |" for c, v in prof["categories"].items()]
  out += ["", "| op | category | ms a step | share | runs a step | JAX op |", "|---|---|---|---|---|---|"]
  for r in prof["ops"]:
    out.append(f"| `{r['op']}` | {r['category']} | {r['ms']:.2f} | {r['share']:.1%} | {r['count']:g} | "
               f"`{r['op_name'][-80:]}` |")
  return out + [""]

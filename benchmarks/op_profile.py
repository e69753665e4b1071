"""Where a compiled step's time goes: per-HLO-op device time from one ``jax.profiler`` trace.

    from benchmarks.op_profile import op_profile
    compiled = jax.jit(f).lower(*args).compile()
    prof = op_profile(lambda: compiled(*args), compiled.as_text(), steps=2)
    prof["ops"][:5], prof["categories"]

The trace's Perfetto JSON (``jax.profiler.trace(..., create_perfetto_trace=True)``) holds
one complete event (``"ph": "X"``) per executed op, with the HLO instruction's name in
``args.hlo_op``: on a GPU one per kernel launch on the device's stream, on XLA:CPU one per
thunk. Summed by ``hlo_op`` and divided by the steps traced, that is each op's device time
per step. Each op is put in a category from the compiled HLO text (:func:`hlo_ops`): the
instruction's opcode, or for a fusion the heaviest opcode inside it (convolution before
dot before FFT, ...), and a custom call by its target (cuDNN convolutions and cuBLAS GEMMs
are custom calls on a GPU). Ops inside a ``while`` body appear once per trip, so a serial
loop's cost is the sum of its body's rows.

Limits: time between ops (launch gaps, host syncs) is not in any row; ``busy_ms`` against
the step's wall time says how much of it the device spent running ops at all.
"""

from __future__ import annotations

import collections
import glob
import gzip
import json
import os
import re
import tempfile
import time

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


def trace_events(folder: str) -> list[dict]:
  """The complete events of the one Perfetto trace under ``folder`` that carry an ``hlo_op``."""
  paths = glob.glob(os.path.join(folder, "**", "perfetto_trace.json.gz"), recursive=True)
  if not paths:
    raise FileNotFoundError(f"{folder}: no perfetto_trace.json.gz (jax.profiler wrote no trace)")
  with gzip.open(max(paths, key=os.path.getmtime)) as f:
    data = json.load(f)
  events = data["traceEvents"] if isinstance(data, dict) else data
  return [e for e in events if e.get("ph") == "X" and "hlo_op" in (e.get("args") or {})]


def exclusive_us(events: list[dict]) -> list[float]:
  """Each event's duration less that of the events nested in it on the same thread (microseconds).

  XLA:CPU records a ``while`` (or ``conditional``, ``call``) op as one event spanning the
  events of its body's ops; counted whole, the body's time would count twice.
  """
  out = [float(e.get("dur", 0.0)) for e in events]
  by_thread = collections.defaultdict(list)
  for i, e in enumerate(events):
    if "ts" in e:                                          # an event without a start nests nothing
      by_thread[(e.get("pid"), e.get("tid"))].append(i)
  for idx in by_thread.values():
    idx.sort(key=lambda i: (float(events[i]["ts"]), -float(events[i].get("dur", 0.0))))
    stack: list[int] = []                                  # open events, outermost first
    for i in idx:
      start = float(events[i]["ts"])
      while stack and start >= float(events[stack[-1]]["ts"]) + float(events[stack[-1]].get("dur", 0.0)):
        stack.pop()
      if stack:
        out[stack[-1]] -= float(events[i].get("dur", 0.0))
      stack.append(i)
  return [max(v, 0.0) for v in out]


def summarize(events: list[dict], ops: dict[str, dict], steps: int, top: int = 15) -> dict:
  """Per-op and per-category milliseconds per step of ``events`` (as :func:`trace_events` returns).

  Each event counts its exclusive time (:func:`exclusive_us`).

  Returns ``{"ops": [{"op", "category", "op_name", "ms", "share", "count"}, ...] (the
  ``top`` largest), "categories": {category: {"ms", "share"}}, "busy_ms", "distinct_ops"}``;
  ``share`` of ``busy_ms``, the summed op time per step.
  """
  if steps < 1:
    raise ValueError(f"steps must be >= 1, got {steps}")
  us = collections.Counter()
  count = collections.Counter()
  for e, exclusive in zip(events, exclusive_us(events)):
    us[e["args"]["hlo_op"]] += exclusive
    count[e["args"]["hlo_op"]] += 1
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
  return {"ops": rows[:top], "categories": categories, "busy_ms": busy, "distinct_ops": len(rows)}


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
  # One call first, waited for: a call still running when the trace starts would add a partial step.
  jax.block_until_ready(run())
  with tempfile.TemporaryDirectory() as d:
    with jax.profiler.trace(d, create_perfetto_trace=True):
      t0 = time.perf_counter()
      for _ in range(steps):
        jax.block_until_ready(run())
      wall = (time.perf_counter() - t0) / steps
    events = trace_events(d)
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
  line = (f"Traced {prof['steps']} step(s): {wall:.1f} ms a step (profiler on), the device busy "
          f"{prof['busy_ms']:.1f} ms of it ({prof['busy_ms'] / wall:.0%}) over {prof['distinct_ops']} distinct ops.")
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

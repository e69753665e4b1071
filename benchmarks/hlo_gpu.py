"""The GPU step understood without a GPU: the paper-scale train step lowered for CUDA, its HLO counted.

    python -m benchmarks.hlo_gpu [--config paper] [--batch 4] [--variant ours]
                                 [--out benchmarks/results/hlo_gpu.md]
    JAX_PLATFORMS=cpu python -m benchmarks.hlo_gpu --compile [--configs cpu,paper]
                                 [--targets h100,h200] [--inference paper]   # needs jax[cuda12]

On a CPU-only machine, the run's own train step (``nlosjax.train.make_train_step``, with the
state, batch and key as ``nlosjax.plan.compile_train_step`` builds them, all abstract
``jax.ShapeDtypeStruct``: nothing of the paper's size is allocated but the physics operators
the step is bound to) is traced and lowered with ``lowering_platforms=("cuda",)``. Nothing is
compiled by default; ``--compile`` (below) has XLA:GPU compile it for a target description.
The census reads the lowered program's HLO text
(``Lowered.as_text(dialect="hlo", debug_info=True)``, the StableHLO converted, before any XLA
pass) and counts, per kind of op, the instructions in the text ("static") and how often each
runs in one step ("per step": the static count times the trip counts of the ``while`` loops
around it, read from each loop's condition and initial value where they are constants):

* ``while`` loops: trip counts and what each body holds (convolutions, matmuls, dynamic
  slices, nested loops), and the JAX code its ops come from;
* convolutions: shapes, ``dim_labels`` (layout), window, feature and batch group counts,
  grouped by shape; a convolution whose window is larger than its output in a spatial
  dimension is a weight (kernel) gradient (the window runs over the activations);
* custom calls, FFTs and their sizes, transposes (the largest by bytes), float64 and host-side
  ops, scatter/gather, dynamic slices in loops;
* the choices the code makes by backend: ``jax.default_backend()`` is this machine's ("cpu")
  whatever the lowering platform, so ``scan_method="auto"`` traces CPU's branch here. The
  census is taken twice: as a GPU process would trace the step (``scan_method`` pinned to
  ``nlosjax.ssm.resolve_method("auto", backend="gpu")``) and as it is traced here.

The closing list of what is likely slow on a GPU gives expectations to check on a device,
each with its evidence from the census; nothing here is a measurement of a GPU.

``--compile`` (with the CUDA plugin installed and ``JAX_PLATFORMS=cpu``) compiles the train steps,
and the batch-1 forward pass of the presets in ``--inference``, with XLA:GPU for the H100 and H200
descriptions in ``benchmarks/gpu_targets/`` (:func:`compile_for_target`), reads the optimised
program (:func:`compiled_census`: kernels, cuDNN calls, FFTs, loops, float atomics, bytes and
FLOPs) and writes ``results/hlo_gpu_compiled.md`` with a roofline per target and the GPU step's
structural goals.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import math
import pathlib
import re
import sys
import time

from experiments import provenance as _machine
from nlosjax.variants import OURS

ROOT = pathlib.Path(__file__).resolve().parents[1]
DEFAULT_OUT = pathlib.Path(__file__).resolve().parent / "results" / "hlo_gpu.md"
PLATFORM = "cuda"

DTYPE_BYTES = {"pred": 1, "s8": 1, "u8": 1, "s16": 2, "u16": 2, "f16": 2, "bf16": 2, "s32": 4, "u32": 4,
               "f32": 4, "s64": 8, "u64": 8, "f64": 8, "c64": 8, "c128": 16, "s4": 1, "u4": 1,
               "f8e4m3fn": 1, "f8e5m2": 1, "token": 0}
#: Opcodes that move data to or from the host.
HOST_OPCODES = ("send", "send-done", "recv", "recv-done", "infeed", "outfeed")
#: Custom-call targets that are annotations (Shardy's sharding marks), not kernels.
ANNOTATION_TARGETS = ("xla.sdy.", "Sharding", "SPMDFullToShardShape", "SPMDShardToFullShape")
#: Computations called as scalar reducers/comparators of these opcodes (``to_apply``), not run as code.
APPLIES = ("reduce", "reduce-window", "scatter", "select-and-scatter", "sort", "map", "all-reduce",
           "reduce-scatter")


# ------------------------------------------------------------------------ parsing
@dataclasses.dataclass
class Instr:
  """One HLO instruction: ``name = shape opcode(operands), attrs``."""
  name: str
  shape: str
  opcode: str
  operands: tuple[str, ...]
  attrs: str
  computation: str
  root: bool = False
  literal: str = ""          # a constant's value, a parameter's number
  op_name: str = ""          # metadata: the JAX code it came from
  frame: int = 0             # metadata: innermost stack frame id (0: none)

  def attr(self, key: str) -> str | None:
    """The value of ``key=...`` in the attributes (a ``{...}`` group whole; a name without its ``%``), or None."""
    m = re.search(rf"(?:^|[ ,]){re.escape(key)}=", self.attrs)
    if m is None:
      return None
    i = m.end()
    if i < len(self.attrs) and self.attrs[i] == "{":
      j = _close(self.attrs, i, "{", "}")
      return self.attrs[i + 1:j]
    return re.match(r'"[^"]*"|[^,\s]+', self.attrs[i:]).group(0).strip('"').lstrip("%")


@dataclasses.dataclass
class HloModule:
  """A parsed HLO module: its computations (instructions in order), entry and stack frames."""
  computations: dict[str, list[Instr]]
  entry: str
  by_name: dict[str, Instr]
  frames: dict[int, tuple[str, str, int, int]]   # id -> (file, function, line, parent id or 0)

  def source(self, instr: Instr) -> str:
    """``file:function`` of the innermost project frame (``nlosjax/``, ``experiments/``) of ``instr``."""
    seen, f = set(), instr.frame
    while f and f in self.frames and f not in seen:
      seen.add(f)
      file, fn, line, parent = self.frames[f]
      m = re.search(r"(nlosjax|experiments)/.*$", file)
      if m:
        return f"{m.group(0)}:{fn}"
      f = parent
    return ""


def _close(text: str, i: int, open_: str, close: str) -> int:
  """Index of the bracket closing the one at ``text[i]``."""
  depth = 0
  for j in range(i, len(text)):
    c = text[j]
    if c == open_:
      depth += 1
    elif c == close:
      depth -= 1
      if depth == 0:
        return j
  raise ValueError(f"unbalanced {open_!r} in {text[:200]!r}")


def _split_top(text: str) -> list[str]:
  """``text`` split at commas outside brackets and quotes."""
  out, depth, cur, quote = [], 0, [], False
  for c in text:
    if c == '"':
      quote = not quote
    elif not quote and c in "([{":
      depth += 1
    elif not quote and c in ")]}":
      depth -= 1
    if c == "," and depth == 0 and not quote:
      out.append("".join(cur).strip())
      cur = []
    else:
      cur.append(c)
  if "".join(cur).strip():
    out.append("".join(cur).strip())
  return out


_INSTR = re.compile(r"^\s*(ROOT\s+)?%?([\w.\-]+)\s*=\s*")
_COMP = re.compile(r"^(ENTRY\s+)?%?([\w.\-]+)\s*(\(.*\)\s*->\s*.*)?\{\s*$")


def _parse_instr(line: str, computation: str) -> Instr | None:
  m = _INSTR.match(line)
  if m is None:
    return None
  rest = line[m.end():]
  if rest.startswith("("):                                  # a tuple shape
    j = _close(rest, 0, "(", ")")
    shape, rest = rest[:j + 1], rest[j + 1:].lstrip()
  else:
    shape, _, rest = rest.partition(" ")
  op = re.match(r"([\w\-]+)\(", rest)
  if op is None:
    return None
  opcode = op.group(1)
  j = _close(rest, op.end() - 1, "(", ")")
  inner, attrs = rest[op.end():j], rest[j + 1:].lstrip(", ")
  literal = inner if opcode in ("constant", "parameter") else ""
  operands = () if opcode in ("constant", "parameter", "iota") else tuple(
      o.split()[-1].lstrip("%") for o in _split_top(inner) if o.split())
  meta = re.search(r"metadata=\{([^}]*)\}", attrs)
  op_name, frame = "", 0
  if meta:
    n = re.search(r'op_name="([^"]*)"', meta.group(1))
    f = re.search(r"stack_frame_id=(\d+)", meta.group(1))
    op_name, frame = (n.group(1) if n else ""), (int(f.group(1)) if f else 0)
  return Instr(m.group(2), shape, opcode, operands, attrs, computation, bool(m.group(1)), literal,
               op_name, frame)


def _parse_frames(text: str) -> dict[int, tuple[str, str, int, int]]:
  """The ``FileNames``/``FunctionNames``/``FileLocations``/``StackFrames`` tables of ``debug_info`` text.

  A frame's printed ``parent_frame_id`` is its parent's id plus one (1: no parent).
  """
  sections: dict[str, dict[int, str]] = {}
  current = None
  for line in text.splitlines():
    if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
      current = sections.setdefault(line, {})
      continue
    if current is not None:
      m = re.match(r"^(\d+) (.*)$", line)
      if m is None:
        current = None
        continue
      current[int(m.group(1))] = m.group(2)
  files = {k: v.strip('"') for k, v in sections.get("FileNames", {}).items()}
  funcs = {k: v.strip('"') for k, v in sections.get("FunctionNames", {}).items()}
  locs = {}
  for k, v in sections.get("FileLocations", {}).items():
    f = dict(re.findall(r"(\w+)=(\d+)", v))
    locs[k] = (files.get(int(f.get("file_name_id", 0)), ""), funcs.get(int(f.get("function_name_id", 0)), ""),
               int(f.get("line", 0)))
  out = {}
  for k, v in sections.get("StackFrames", {}).items():
    f = dict(re.findall(r"(\w+)=(\d+)", v))
    file, fn, line = locs.get(int(f.get("file_location_id", 0)), ("", "", 0))
    out[k] = (file, fn, line, max(int(f.get("parent_frame_id", 1)) - 1, 0))
  return out


def parse_hlo(text: str) -> HloModule:
  """Parse HLO text (``Lowered.as_text(dialect="hlo")``, with or without ``debug_info``)."""
  text = re.sub(r"/\*.*?\*/", "", text)                    # /*index=5*/ inside tuple shapes
  comps: dict[str, list[Instr]] = {}
  by_name: dict[str, Instr] = {}
  entry, current = "", None
  for line in text.splitlines():
    if current is None:
      m = _COMP.match(line)
      if m and not line.startswith((" ", "HloModule")):
        current = m.group(2)
        comps[current] = []
        if m.group(1):
          entry = current
      continue
    if line.strip() == "}":
      current = None
      continue
    ins = _parse_instr(line, current)
    if ins is not None:
      comps[current].append(ins)
      by_name[ins.name] = ins
  if not entry:
    raise ValueError("no ENTRY computation in the HLO text")
  return HloModule(comps, entry, by_name, _parse_frames(text))


# ------------------------------------------------------------------------- shapes
def arrays(shape: str) -> list[tuple[str, tuple[int, ...]]]:
  """``[(dtype, dims), ...]`` of every array in a (possibly tuple) HLO shape."""
  return [(d, tuple(int(x) for x in dims.split(",") if x))
          for d, dims in re.findall(r"\b([a-z]+\d*(?:e\d+m\d+\w*)?)\[([\d,]*)\]", shape)]


def nbytes(shape: str) -> int:
  return sum(DTYPE_BYTES.get(d, 4) * math.prod(dims) for d, dims in arrays(shape))


def dims_text(shape: str) -> str:
  """``"f32[4,16,16]"`` (layouts dropped); tuples joined by ``", "``."""
  return ", ".join(f"{d}[{','.join(map(str, s))}]" for d, s in arrays(shape))


def fmt_bytes(n: float) -> str:
  for unit, size in (("GiB", 2 ** 30), ("MiB", 2 ** 20), ("KiB", 2 ** 10)):
    if n >= size:
      return f"{n / size:.1f} {unit}"
  return f"{n:.0f} B"


# ------------------------------------------------------------------- call graph
def callees(ins: Instr) -> list[tuple[str, str]]:
  """``[(computation, role), ...]`` ``ins`` calls; role ``body``, ``condition``, ``call``, ``branch``, ``apply``."""
  out = []
  if ins.opcode == "while":
    out += [(ins.attr("body"), "body"), (ins.attr("condition"), "condition")]
  elif ins.opcode == "conditional":
    branches = ins.attr("branch_computations")
    names = _split_top(branches) if branches else [ins.attr("true_computation"), ins.attr("false_computation")]
    out += [(n.lstrip("%"), "branch") for n in names if n]
  else:
    for key in ("to_apply", "calls", "called_computations"):
      v = ins.attr(key)
      if v:
        role = "apply" if ins.opcode in APPLIES else "call"
        out += [(n.strip().lstrip("%"), role) for n in v.split(",") if n.strip()]
  return [(c, r) for c, r in out if c]


def _const_int(module: HloModule, name: str) -> int | None:
  ins = module.by_name.get(name)
  if ins is None or ins.opcode != "constant":
    return None
  try:
    return int(ins.literal)
  except ValueError:
    return None


def _tuple_index(ins: Instr | None) -> int | None:
  if ins is None or ins.opcode != "get-tuple-element":
    return None
  v = ins.attr("index")
  return int(v) if v is not None else None


def trip_count(module: HloModule, loop: Instr) -> int | None:
  """The trip count of a ``while`` whose condition compares a tuple element with a constant.

  The element's initial value (in the loop's operand tuple) must be a constant and the body must
  add a constant to it; ``LT``/``LE``/``GT``/``GE``/``NE`` comparisons. None where any of these is
  not static (a ``while_loop`` with a traced bound). A compiled program's loops state it
  (``backend_config={"known_trip_count":{"n":"16"}}``), which is read first.
  """
  known = re.search(r'"known_trip_count":\{"n":"(\d+)"', loop.attrs)
  if known:
    return int(known.group(1))
  cond = module.computations.get(loop.attr("condition"), [])
  root = next((i for i in cond if i.root), None)
  if root is None or root.opcode != "compare" or len(root.operands) != 2:
    return None
  a, b = (module.by_name.get(o) for o in root.operands)
  direction = root.attr("direction")
  flip = {"LT": "GT", "GT": "LT", "LE": "GE", "GE": "LE", "NE": "NE"}
  if _tuple_index(a) is None and _tuple_index(b) is not None:
    a, b, direction = b, a, flip.get(direction, direction)
  k = _tuple_index(a)
  bound = _const_int(module, b.name) if b is not None else None
  if k is None or bound is None or not loop.operands:
    return None
  init_tuple = module.by_name.get(loop.operands[0])
  if init_tuple is None or init_tuple.opcode != "tuple" or k >= len(init_tuple.operands):
    return None
  start = _const_int(module, init_tuple.operands[k])
  body = module.computations.get(loop.attr("body"), [])
  broot = next((i for i in body if i.root), None)
  if start is None or broot is None or broot.opcode != "tuple" or k >= len(broot.operands):
    return None
  upd = module.by_name.get(broot.operands[k])
  step = None
  if upd is not None and upd.opcode in ("add", "subtract") and len(upd.operands) == 2:
    x, y = (module.by_name.get(o) for o in upd.operands)
    if upd.opcode == "add" and _tuple_index(y) == k:
      x, y = y, x
    if _tuple_index(x) == k and y is not None:
      step = _const_int(module, y.name)
      if step is not None and upd.opcode == "subtract":
        step = -step
  if not step:
    return None
  if direction in ("LT", "LE") and step > 0:
    return max(0, -(-(bound - start + (direction == "LE")) // step))
  if direction in ("GT", "GE") and step < 0:
    return max(0, -(-(start - bound + (direction == "GE")) // -step))
  if direction == "NE" and (bound - start) % step == 0 and (bound - start) // step >= 0:
    return (bound - start) // step
  return None


@dataclasses.dataclass
class Graph:
  """Per computation: runs per step and whether it runs inside a loop; per ``while``: its trips."""
  runs: dict[str, int]
  in_loop: set[str]
  trips: dict[str, int | None]       # while instruction name -> trip count
  unknown_trips: int                 # loops whose trip count is not static (counted as 1 trip)


def call_graph(module: HloModule) -> Graph:
  """Runs of each computation per step: the sum over its callers of the caller's runs times trips."""
  edges: dict[str, list[tuple[str, int, bool]]] = collections.defaultdict(list)   # callee <- (caller, factor, loop)
  trips: dict[str, int | None] = {}
  for comp, instrs in module.computations.items():
    for ins in instrs:
      for callee, role in callees(ins):
        if role in ("apply", "condition"):
          continue
        factor = 1
        if role == "body":
          trips[ins.name] = t = trip_count(module, ins)
          factor = 1 if t is None else t
        edges[callee].append((comp, factor, role == "body"))
  runs: dict[str, int] = {}
  in_loop: set[str] = set()

  def visit(comp: str, stack=()) -> int:
    if comp in runs:
      return runs[comp]
    if comp == module.entry:
      runs[comp] = 1
      return 1
    if comp in stack:
      raise ValueError(f"recursive call graph at {comp}")
    total = 0
    for caller, factor, loop in edges.get(comp, ()):
      total += visit(caller, stack + (comp,)) * factor
      if loop or caller in in_loop:
        in_loop.add(comp)
    runs[comp] = total
    return total

  sys.setrecursionlimit(max(sys.getrecursionlimit(), 20000))
  for comp in module.computations:
    visit(comp)
  return Graph(runs, in_loop, trips, sum(t is None for t in trips.values()))


def contexts(module: HloModule) -> tuple[dict[str, str], dict[str, str]]:
  """Per computation, the full ``op_name`` and the source of the instruction that first calls it.

  JAX writes ``op_name`` relative to a loop body or called function (``while/body/...``); an
  instruction's full name is its caller's joined with its own (:func:`full_name`).
  """
  names, sources = {module.entry: ""}, {module.entry: ""}
  todo = [module.entry]
  while todo:
    comp = todo.pop()
    for ins in module.computations.get(comp, ()):
      for callee, role in callees(ins):
        if role == "apply" or callee in names:
          continue
        names[callee] = _call_context(module, ins, names[comp])
        sources[callee] = module.source(ins) or sources[comp]
        todo.append(callee)
  return names, sources


def _call_context(module: HloModule, ins: Instr, context: str) -> str:
  """The full ``op_name`` of a calling instruction; where JAX wrote it relative (a ``while``), the
  prefix its operands' (a loop's initial tuple's) full names share most often."""
  name = full_name(ins.op_name, context)
  if name.startswith("jit("):
    return name
  operands = [module.by_name[o] for o in ins.operands if o in module.by_name]
  operands += [module.by_name[o] for x in operands if x.opcode == "tuple" for o in x.operands if o in module.by_name]
  prefixes = collections.Counter(full_name(x.op_name, context).rpartition("/")[0] for x in operands)
  prefixes.pop("", None)
  best = next((p for p, _ in prefixes.most_common() if p.startswith("jit(")), "")
  return f"{best}/{ins.op_name}" if best else name


def full_name(op_name: str, context: str) -> str:
  """``op_name`` prefixed by its computation's context unless it is already whole (``jit(...)/...``)."""
  if not op_name or op_name.startswith("jit(") or not context:
    return op_name or context
  return f"{context}/{op_name}"


def closure(module: HloModule, comp: str, into_loops: bool = False) -> list[Instr]:
  """Instructions of ``comp`` and of what it calls (not scalar reducers; nested loop bodies if ``into_loops``)."""
  out, todo, seen = [], [comp], set()
  while todo:
    c = todo.pop()
    if c in seen:
      continue
    seen.add(c)
    for ins in module.computations.get(c, ()):
      out.append(ins)
      for callee, role in callees(ins):
        if role == "call" or role == "branch" or (role == "body" and into_loops):
          todo.append(callee)
  return out


# -------------------------------------------------------------------------- census
def part_of(op_name: str, model: str = "STMambaNet") -> str:
  """``"st_mamba0 (backward)"``: the network part and direction an op comes from (``step_profile.op_part``)."""
  from benchmarks.step_profile import op_part
  part, direction = op_part(re.sub(r"/(checkpoint|remat|rematted_computation)(?=/)", "", op_name), model)
  return part if direction == "-" else f"{part} ({direction})"


def _top(counter: collections.Counter, n: int = 3) -> str:
  items = counter.most_common(n)
  more = len(counter) - len(items)
  return "; ".join(f"{k} x{v}" if v > 1 else k for k, v in items) + (f"; +{more} more" if more > 0 else "")


#: What the ``dim_labels`` of this project's convolutions are (see ``nlosjax/models/conv.py``).
CONV_FORMS = {
    "b01f_01io->b01f": "NHWC x HWIO -> NHWC (a forward conv)",
    "b01f_01oi->b01f": "NHWC x HWOI -> NHWC (JAX's input gradient: the kernel flipped, i/o swapped)",
    "f01b_i01o->01bf": "CHWN x IHWO -> HWNC (JAX's own kernel gradient, conv2d_kernel_grad's default path)",
    "f01b_i01o->b01f": "CHWN x IHWO -> NHWC (conv2d_kernel_grad's swapped path: cotangent convolved with the "
                       "input as kernel; chosen by shape, F <= C and kernels <= 3x3, timed on XLA:CPU)",
}


#: ``dim_labels`` of ``conv2d_kernel_grad_cpu``'s swapped weight gradient (``CONV_FORMS``).
SWAPPED_LABELS = "f01b_i01o->b01f"
#: Ops that pass an array through unchanged in value (followed back from a convolution's input).
_PASS_THROUGH = ("convert", "copy", "bitcast")


def _pads(text: str | None) -> list[tuple[int, int]]:
  """``[(lo, hi), ...]`` per dimension of a ``padding=`` (``pad`` op) or ``pad=`` (window) value."""
  return [tuple(int(v) for v in d.split("_")[:2]) for d in text.split("x")] if text else []


def swapped_weight_grad(module: HloModule, ins: Instr) -> bool:
  """Whether convolution ``ins`` is a weight gradient in the swapped layout.

  A weight gradient (window larger than output) is in XLA's own layout when its window is the
  cotangent and it slides over the activations; swapped, the roles are exchanged: the window
  is the (padded) activations and it slides over the cotangent padded by ``output - 1`` on
  both sides of every spatial dimension (a full correlation, whose output then runs
  backwards). Read from the ``dim_labels`` of ``conv2d_kernel_grad``'s swapped form
  (:data:`SWAPPED_LABELS`) or, whatever the labels, from that padding: the ``pad`` op feeding
  the input (through converts, copies, transposes and calls) plus the window's own padding.
  """
  f = conv_facts(module, ins)
  if not f["weight_grad"]:
    return False
  labels = f["dim_labels"]
  if labels == SWAPPED_LABELS:
    return True
  lhs_labels, out_labels = labels.split("_")[0], labels.split("->")[-1]
  out_dims = arrays(ins.shape)[0][1]
  window = dict(enumerate(_pads(re.search(r"pad=([\d_x-]+)", f["window"]).group(1)
                                if "pad=" in f["window"] else "")))
  src = module.by_name.get(ins.operands[0])
  dims = list(range(len(lhs_labels)))           # the input's dimensions as dimensions of ``src``
  while src is not None and src.opcode in _PASS_THROUGH + ("transpose", "call") and src.operands:
    if src.opcode == "call":                     # its value is its computation's root (a jitted jnp.pad)
      src = next((i for i in module.computations.get(src.attr("to_apply") or "", []) if i.root), None)
      continue
    if src.opcode == "transpose":
      perm = [int(v) for v in src.attr("dimensions").split(",")]
      dims = [perm[d] for d in dims]
    src = module.by_name.get(src.operands[0])
  explicit = _pads(src.attr("padding")) if src is not None and src.opcode == "pad" else []
  full = []
  for d in range(len(f["window_size"])):
    out = out_dims[out_labels.index(str(d))]
    if out < 2:
      continue
    lo, hi = window.get(d, (0, 0))
    if explicit:
      e_lo, e_hi = explicit[dims[lhs_labels.index(str(d))]]
      lo, hi = lo + e_lo, hi + e_hi
    full.append(lo >= out - 1 and hi >= out - 1)
  return bool(full) and all(full)


def conv_facts(module: HloModule, ins: Instr) -> dict:
  """Shapes, layout, window, groups, FLOPs and whether a convolution is a weight gradient."""
  lhs, rhs = (module.by_name[o].shape if o in module.by_name else "" for o in ins.operands[:2])
  labels = ins.attr("dim_labels") or ""
  window = ins.attr("window") or ""
  size = re.search(r"size=([\dx]+)", window)
  win = tuple(int(x) for x in size.group(1).split("x")) if size else ()
  out_dims = arrays(ins.shape)[0][1] if arrays(ins.shape) else ()
  out_labels = labels.split("->")[-1] if "->" in labels else ""
  spatial_out = [out_dims[out_labels.index(str(d))] for d in range(len(win))
                 if str(d) in out_labels and out_labels.index(str(d)) < len(out_dims)]
  weight_grad = any(w > o for w, o in zip(win, spatial_out))
  rhs_labels = labels.split("_")[1].split("->")[0] if "_" in labels else ""
  rhs_dims = arrays(rhs)[0][1] if arrays(rhs) else ()
  cin = rhs_dims[rhs_labels.index("i")] if "i" in rhs_labels and len(rhs_dims) == len(rhs_labels) else 1
  flops = 2 * math.prod(out_dims) * math.prod(win or (1,)) * cin
  moved = nbytes(lhs) + nbytes(rhs) + nbytes(ins.shape)
  transposed_kernel = rhs_labels.find("o") < rhs_labels.find("i")
  kind = "weight gradient" if weight_grad else ("input gradient" if transposed_kernel else "forward")
  cout = rhs_dims[rhs_labels.index("o")] if "o" in rhs_labels and len(rhs_dims) == len(rhs_labels) else 1
  return {"kind": kind, "form": CONV_FORMS.get(labels, ""), "bytes": moved, "cin": cin, "cout": cout,
          "flop_per_byte": flops / max(moved, 1), "lhs": dims_text(lhs), "rhs": dims_text(rhs),
          "out": dims_text(ins.shape), "dim_labels": labels,
          "window": window, "feature_group_count": int(ins.attr("feature_group_count") or 1),
          "batch_group_count": int(ins.attr("batch_group_count") or 1), "weight_grad": weight_grad,
          "window_size": win, "gflop": flops / 1e9}


def census(hlo_text: str, stablehlo_text: str | None = None, model: str = "STMambaNet") -> dict:
  """Counts of the lowered program's ops by kind; see the module docstring. JSON-friendly."""
  module = parse_hlo(hlo_text)
  g = call_graph(module)
  code = [i for c, instrs in module.computations.items() if g.runs.get(c, 0) or c == module.entry
          for i in instrs]
  run = {i.name: g.runs.get(i.computation, 0) for i in code}
  names, sources = contexts(module)
  where = {i.name: (part_of(full_name(i.op_name, names.get(i.computation, "")), model),
                    module.source(i) or sources.get(i.computation, "")) for i in code}
  out: dict = {"instructions": len(code), "computations": len(module.computations),
               "executed_per_step": sum(run.values())}
  ops = collections.defaultdict(lambda: [0, 0])
  for i in code:
    ops[i.opcode][0] += 1
    ops[i.opcode][1] += run[i.name]
  out["opcodes"] = sorted(([k, s, r] for k, (s, r) in ops.items()), key=lambda x: -x[2])

  # while loops
  loops = []
  for i in code:
    if i.opcode != "while":
      continue
    body = i.attr("body")
    inside = [x for x in closure(module, body) if x.opcode not in ("parameter", "get-tuple-element", "tuple",
                                                                   "constant")]
    kinds = collections.Counter(x.opcode for x in inside)
    parts = collections.Counter(where[x.name][0] for x in inside)
    sources = collections.Counter(where[x.name][1] for x in inside if where[x.name][1])
    largest = max((nbytes(x.shape) for x in inside), default=0)
    written = sum(nbytes(x.shape) for x in closure(module, body) if x.opcode not in (
        "parameter", "get-tuple-element", "tuple", "constant", "bitcast", "reshape", "while", "call",
        "conditional"))
    loops.append({"name": i.name, "trips": g.trips.get(i.name), "runs": run[i.name],
                  "nested_in_loop": i.computation in g.in_loop, "body_ops": len(inside),
                  "convolution": kinds["convolution"], "dot": kinds["dot"], "fft": kinds["fft"],
                  "dynamic-slice": kinds["dynamic-slice"], "dynamic-update-slice": kinds["dynamic-update-slice"],
                  "while": kinds["while"], "largest_body_bytes": largest,
                  "body_bytes": written,
                  "part": parts.most_common(1)[0][0] if parts else "", "source": _top(sources, 2),
                  "carry": dims_text(i.shape)})
  out["loops"] = loops
  out["unknown_trips"] = g.unknown_trips

  # convolutions
  convs = []
  for i in code:
    if i.opcode == "convolution":
      f = conv_facts(module, i)
      f.update(runs=run[i.name], part=where[i.name][0], source=where[i.name][1], in_loop=i.computation in g.in_loop,
               swapped=swapped_weight_grad(module, i))
      convs.append(f)
  out["convolutions"] = convs

  # custom calls, FFTs, transposes, f64, host ops, gather/scatter, dynamic slices
  out["custom_calls"] = [{"target": i.attr("custom_call_target") or "", "shape": dims_text(i.shape),
                          "runs": run[i.name], "annotation": (i.attr("custom_call_target") or "").startswith(
                              ANNOTATION_TARGETS)} for i in code if i.opcode == "custom-call"]
  out["ffts"] = [{"type": i.attr("fft_type") or "", "length": i.attr("fft_length") or "",
                  "input": dims_text(module.by_name[i.operands[0]].shape) if i.operands and
                  i.operands[0] in module.by_name else "", "output": dims_text(i.shape), "runs": run[i.name],
                  "part": where[i.name][0], "source": where[i.name][1], "in_loop": i.computation in g.in_loop}
                 for i in code if i.opcode == "fft"]
  out["transposes"] = [{"shape": dims_text(i.shape), "dims": i.attr("dimensions") or "", "bytes": nbytes(i.shape),
                        "runs": run[i.name], "part": where[i.name][0], "source": where[i.name][1]}
                       for i in code if i.opcode == "transpose"]
  out["f64"] = [{"opcode": i.opcode, "shape": dims_text(i.shape), "runs": run[i.name], "part": where[i.name][0]}
                for i in code if "f64[" in i.shape or "c128[" in i.shape]
  callbacks = [c for c in out["custom_calls"] if re.search(r"callback|host", c["target"], re.I)]
  out["host"] = [{"opcode": i.opcode, "shape": dims_text(i.shape), "runs": run[i.name]}
                 for i in code if i.opcode in HOST_OPCODES] + [
                {"opcode": f"custom-call {c['target']}", "shape": c["shape"], "runs": c["runs"]} for c in callbacks]
  def indices(i):
    x = module.by_name.get(i.operands[1]) if len(i.operands) > 1 else None   # start/scatter indices
    return (dims_text(x.shape), x.opcode == "constant") if x is not None else ("", False)
  out["gather_scatter"] = [{"opcode": i.opcode, "shape": dims_text(i.shape), "bytes": nbytes(i.shape),
                            "indices": indices(i)[0], "constant_indices": indices(i)[1],
                            "index_rows": _index_rows(module, i),
                            "runs": run[i.name], "in_loop": i.computation in g.in_loop, "part": where[i.name][0],
                            "source": where[i.name][1]} for i in code if i.opcode in ("gather", "scatter")]
  dyn = []
  for i in code:
    if i.opcode in ("dynamic-slice", "dynamic-update-slice"):
      other = module.by_name.get(i.operands[0 if i.opcode == "dynamic-slice" else 1]) if len(i.operands) > 1 else None
      moved, buffer = (i.shape, other.shape if other else "") if i.opcode == "dynamic-slice" else (
          other.shape if other else "", i.shape)
      dyn.append({"opcode": i.opcode, "shape": dims_text(buffer), "moved": dims_text(moved),
                  "moved_bytes": nbytes(moved), "buffer_bytes": nbytes(buffer), "runs": run[i.name],
                  "in_loop": i.computation in g.in_loop, "source": where[i.name][1]})
  out["dynamic_slices"] = dyn
  out["conditionals"] = sum(1 for i in code if i.opcode == "conditional")
  if stablehlo_text is not None:
    out["stablehlo"] = stablehlo_counts(stablehlo_text)
  return out


def _index_rows(module: HloModule, ins: Instr) -> int:
  """How many index vectors a gather/scatter reads (1: one window, like a dynamic slice)."""
  x = module.by_name.get(ins.operands[1]) if len(ins.operands) > 1 else None
  dims = arrays(x.shape)[0][1] if x is not None and arrays(x.shape) else ()
  return math.prod(dims[:-1]) if len(dims) > 1 else 1


def stablehlo_counts(text: str) -> dict:
  """Static counts of a few StableHLO ops in the MLIR text (each function's body once)."""
  names = ("while", "convolution", "fft", "custom_call", "transpose", "dot_general", "gather", "scatter",
           "dynamic_slice", "dynamic_update_slice", "case", "if")
  return {n: len(re.findall(rf"(?<![#\w])stablehlo\.{n}\b(?![<\w])", text)) for n in names} | {
      "func.call": len(re.findall(r"\bfunc\.call\b|\bcall @", text)),
      "f64": len(re.findall(r"tensor<[\dx]*f64>", text))}


# --------------------------------------------------------------------- the step
def backend_choices(root: pathlib.Path = ROOT) -> list[str]:
  """``file:line: text`` of every ``default_backend()`` / ``platform_dependent`` use in ``nlosjax/``."""
  out = []
  for path in sorted((root / "nlosjax").rglob("*.py")):
    for n, line in enumerate(path.read_text().splitlines(), 1):
      code = line.split("#")[0]
      if re.search(r"default_backend\(|platform_dependent|devices\(\)\[0\]\.platform", code):
        out.append(f"{path.relative_to(root)}:{n}: `{line.strip()}`")
  return out


def lower_step(config: dict, variant: str, batch: int, scan_method: str | None = None,
               platform: str = PLATFORM) -> dict:
  """The run's train step for ``variant`` lowered for ``platform`` from shapes; its texts and facts.

  The same pieces as ``nlosjax.plan.compile_train_step`` (the preset's optimiser, loss weights,
  mesh, abstract state and batch), traced and lowered, not compiled. ``scan_method``: replaces the
  model config's (None: as configured, resolved by this process's backend).
  """
  import jax

  from nlosjax import inference, plan
  from nlosjax import train as T
  from nlosjax.ssm import resolve_method
  config = {**config, "train": {**config["train"], "batch_size": int(batch)}}
  typed = T.RunConfig.from_dict(config)
  mcfg = T.model_config_for(typed, inference.training_setup(typed), variant)
  if scan_method is not None:
    mcfg = dataclasses.replace(mcfg, scan_method=scan_method)
  mesh = T.mesh_for(typed)
  optim, weights = T.training_recipe(typed, variant)
  tx = T.make_optimizer(optim, int(config["train"]["steps"]))
  t = time.perf_counter()
  state = T.abstract_train_state(T.network(mcfg), tuple(mcfg.input_shape(batch)), tx, mesh)
  batch_shapes = plan._abstract_batch(mcfg, batch, mesh)
  key = jax.eval_shape(lambda: jax.random.key(0))
  step = T.make_train_step(mcfg, weights, mesh)                 # the run's own jitted step
  table = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=a.sharding), step.table)
  traced = step.jitted.trace(state, batch_shapes, key, table)
  trace_s = time.perf_counter() - t
  t = time.perf_counter()
  note = ""
  try:
    lowered = traced.lower(lowering_platforms=(platform,))
    lowered_for = platform
  except Exception as e:                              # noqa: BLE001 - reported, CPU lowering instead
    note = f"lowering for {platform} failed: {type(e).__name__}: {str(e).splitlines()[0]}; lowered for cpu instead"
    lowered = traced.lower(lowering_platforms=("cpu",))
    lowered_for = "cpu"
  lower_s = time.perf_counter() - t
  stablehlo = lowered.as_text()
  hlo = lowered.as_text(dialect="hlo", debug_info=True)
  return {"stablehlo": stablehlo, "hlo": hlo, "lowered_for": lowered_for, "note": note,
          "scan_method": mcfg.scan_method, "scan_resolved": resolve_method(mcfg.scan_method),
          "scan_chunk": mcfg.scan_chunk, "conv_impl": mcfg.conv_impl, "input": list(mcfg.input_shape(batch)),
          "remat": mcfg.remat, "physics_chunk": mcfg.physics_chunk, "trace_s": trace_s, "lower_s": lower_s,
          "operator_bytes": sum(int(a.size) * a.dtype.itemsize for a in jax.tree.leaves(step.table)),
          "model": type(T.network(mcfg)).__name__}


# ------------------------------------------------------------------------ report
def _group(rows: list[dict], keys: tuple[str, ...]) -> list[tuple[tuple, list[dict]]]:
  groups: dict[tuple, list[dict]] = {}
  for r in rows:
    groups.setdefault(tuple(r[k] for k in keys), []).append(r)
  return list(groups.items())


def _n(x) -> str:
  return "?" if x is None else f"{x:,}"


def loop_rows(c: dict) -> list[str]:
  keys = ("trips", "runs", "nested_in_loop", "body_ops", "convolution", "dot", "fft", "dynamic-slice",
          "dynamic-update-slice", "while", "source")
  lines = ["| loops | trips | runs of each per step | nested | body ops | conv | dot | fft | dyn-slice | "
           "dyn-update-slice | nested loops | largest body array | op outputs per trip | parts (most ops) | code |",
           "|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"]
  groups = sorted(_group(c["loops"], keys), key=lambda kv: -(len(kv[1]) * (kv[0][0] or 1) * kv[0][1]))
  for k, rows in groups:
    lines.append(f"| {len(rows)} | {_n(k[0])} | {_n(k[1])} | {'yes' if k[2] else 'no'} | {k[3]} | {k[4]} | {k[5]} | "
                 f"{k[6]} | {k[7]} | {k[8]} | {k[9]} | {fmt_bytes(max(r['largest_body_bytes'] for r in rows))} | "
                 f"{fmt_bytes(max(r['body_bytes'] for r in rows))} | "
                 f"{_top(collections.Counter(r['part'] for r in rows), 4)} | {k[10]} |")
  return lines


def conv_rows(c: dict) -> list[str]:
  keys = ("lhs", "rhs", "out", "dim_labels", "window", "feature_group_count", "batch_group_count", "kind")
  lines = ["| n | per step | lhs | rhs | out | dim_labels | window | fgc | bgc | kind | GFLOP per step | FLOP/B "
           "| parts | code |", "|---:|---:|---|---|---|---|---|---:|---:|---|---:|---:|---|---|"]
  groups = sorted(_group(c["convolutions"], keys), key=lambda kv: -sum(r["gflop"] * r["runs"] for r in kv[1]))
  for k, rows in groups:
    parts = collections.Counter(r["part"] for r in rows)
    srcs = collections.Counter(r["source"].split("/")[-1] for r in rows if r["source"])
    lines.append(f"| {len(rows)} | {sum(r['runs'] for r in rows)} | {k[0]} | {k[1]} | {k[2]} | `{k[3]}` | "
                 f"`{k[4]}` | {k[5]} | {k[6]} | {k[7]} | {sum(r['gflop'] * r['runs'] for r in rows):.1f} | "
                 f"{rows[0]['flop_per_byte']:.0f} | {_top(parts, 2)} | {_top(srcs, 2)} |")
  forms = collections.Counter(r["dim_labels"] for r in c["convolutions"])
  lines += ["", "The layouts (`dim_labels`):", ""]
  lines += [f"- `{k}` x{n}: {CONV_FORMS.get(k, 'not one of the forms this project writes')}"
            for k, n in forms.most_common()]
  return lines


def prime_factors(n: int) -> list[int]:
  out, p = [], 2
  while p * p <= n:
    while n % p == 0:
      out.append(p)
      n //= p
    p += 1
  return out + ([n] if n > 1 else [])


def summary(c: dict) -> dict:
  """The headline numbers of one census."""
  loops = c["loops"]
  convs = c["convolutions"]
  wg = [r for r in convs if r["weight_grad"]]
  kernels_cc = [r for r in c["custom_calls"] if not r["annotation"]]
  return {
      "loops": len(loops), "loop_runs": sum(r["runs"] for r in loops),
      "loop_trips": sum(r["runs"] * (r["trips"] or 1) for r in loops),
      "max_trips": max((r["trips"] or 0 for r in loops), default=0),
      "unknown_trips": c["unknown_trips"],
      "convs": len(convs), "conv_runs": sum(r["runs"] for r in convs),
      "weight_grads": len(wg), "weight_grad_runs": sum(r["runs"] for r in wg),
      "largest_wg_window": max((r["window_size"] for r in wg), key=math.prod, default=()),
      "grouped_convs": sum(1 for r in convs if r["feature_group_count"] > 1 or r["batch_group_count"] > 1),
      "conv_gflop": sum(r["gflop"] * r["runs"] for r in convs),
      "wg_gflop": sum(r["gflop"] * r["runs"] for r in wg),
      "custom_calls": len(c["custom_calls"]), "kernel_custom_calls": len(kernels_cc),
      "ffts": len(c["ffts"]), "fft_runs": sum(r["runs"] for r in c["ffts"]),
      "transposes": len(c["transposes"]), "transpose_runs": sum(r["runs"] for r in c["transposes"]),
      "transpose_bytes": sum(r["bytes"] * r["runs"] for r in c["transposes"]),
      "f64": len(c["f64"]), "host": len(c["host"]),
      "gather": sum(r["opcode"] == "gather" for r in c["gather_scatter"]),
      "scatter": sum(r["opcode"] == "scatter" for r in c["gather_scatter"]),
      "dyn_in_loop": sum(r["in_loop"] for r in c["dynamic_slices"]),
      "dyn_in_loop_runs": sum(r["runs"] for r in c["dynamic_slices"] if r["in_loop"]),
  }


#: Arithmetic intensity (FLOP per byte moved, before fusion) below which a convolution is
#: expected to be bound by memory bandwidth on a current GPU (an H100/H200 does ~50-70 TFLOP/s
#: float32 on tensor cores against ~3-5 TB/s: the crossover lies well above this).
LOW_INTENSITY = 20.0


def slow_list(c: dict, s: dict) -> list[str]:
  """Expectations of what runs slowly on a GPU, each with its evidence from census ``c``."""
  out = []
  loops = [r for r in c["loops"] if (r["trips"] or 0) * r["runs"] >= 8]
  if loops:
    common = collections.Counter((r["trips"], r["runs"]) for r in loops).most_common(6)
    scans = [r for r in loops if "ssm/scan.py" in r["source"]]
    per_trip = [r["body_bytes"] for r in loops]
    out.append(
        f"**Serial loops.** {len(loops)} `while` loops run 8 or more trips per step "
        f"({', '.join(f'{n} x {t} trips' + (f' (started {k} times)' if k > 1 else '') for (t, k), n in common)}), "
        f"{sum(r['runs'] * (r['trips'] or 1) for r in loops):,} trips per step in all, one after the other; "
        f"{len(scans)} of them are the selective scan's (`nlosjax/ssm/scan.py`), the rest "
        f"{_top(collections.Counter(r['part'] for r in loops if r not in scans), 2) or 'none'}. "
        f"Each trip is at least one kernel launch after fusion (bodies of {min(r['body_ops'] for r in loops)}-"
        f"{max(r['body_ops'] for r in loops)} ops before fusion, writing {fmt_bytes(min(per_trip))}-"
        f"{fmt_bytes(max(per_trip))} per trip). Expected: trips that small in bytes are launch-bound, "
        f"larger ones bandwidth-bound, and in both cases no two trips overlap.")
  wg = [r for r in c["convolutions"] if r["weight_grad"]]
  swapped = [r for r in wg if r["swapped"]]
  if wg and not swapped:
    out.append(
        f"**Weight-gradient convolutions.** {len(wg)} of {s['convs']} convolutions are weight gradients, all in "
        f"XLA's own layout (the window is the cotangent; `benchmarks.hlo_gpu.swapped_weight_grad`), the form "
        f"XLA:GPU rewrites into cuDNN backward-filter calls. Expected: no large-window forward convolutions.")
  if swapped:
    big = max(wg, key=lambda r: math.prod(r["window_size"]))
    out.append(
        f"**Weight-gradient convolutions with large windows.** {len(wg)} of {s['convs']} convolutions are "
        f"weight gradients, {s['wg_gflop']:.0f} of {s['conv_gflop']:.0f} conv GFLOP per step; windows up to "
        f"{'x'.join(map(str, big['window_size']))} ({big['lhs']} with {big['rhs']} -> {big['out']}, "
        f"`{big['dim_labels']}`, {big['part']}). {len(swapped)} of them are in `conv2d_kernel_grad`'s swapped form "
        f"(`f01b_i01o->b01f`: a forward-looking convolution whose filter is the activation, batch = the "
        f"cotangent's {sorted({arrays(r['out'])[0][1][0] for r in swapped})} channels), a choice timed on XLA:CPU. "
        f"Expected: cuDNN has no fast kernel for a 130x130 filter and a 3x3 output, whether XLA:GPU reads it as "
        f"a backward-filter convolution or not.")
  grouped = [r for r in c["convolutions"] if r["feature_group_count"] > 1 or r["batch_group_count"] > 1]
  if grouped:
    fg = collections.Counter((r["feature_group_count"], r["batch_group_count"]) for r in grouped)
    out.append(f"**Grouped convolutions.** {len(grouped)} with feature_group_count or batch_group_count > 1 "
               f"({', '.join(f'{n} x fgc {a} / bgc {b}' for (a, b), n in fg.most_common(4))}): depthwise and "
               f"batch-grouped convolutions are expected to get slower cuDNN kernels than dense ones.")
  low = [r for r in c["convolutions"] if r["kind"] != "weight gradient" and r["flop_per_byte"] < LOW_INTENSITY]
  if low:
    ex = max(low, key=lambda r: r["bytes"])
    out.append(f"**Few-channel convolutions.** {len(low)} forward/input-gradient convolutions do under "
               f"{LOW_INTENSITY:g} FLOP per byte they read and write "
               f"({fmt_bytes(sum(r['bytes'] * r['runs'] for r in low))} "
               f"per step before fusion; e.g. {ex['lhs']} with {ex['rhs']}: {ex['cin']} -> {ex['cout']} channels, "
               f"{ex['flop_per_byte']:.0f} FLOP/B, {ex['part']}). Expected bandwidth-bound: their time is their "
               f"bytes, not their FLOPs, and tensor cores do not help at {ex['cout']} output channels.")
  odd = collections.Counter(r["dim_labels"] for r in c["convolutions"]
                            if r["dim_labels"] not in ("b01f_01io->b01f", "b01f_01oi->b01f"))
  if odd:
    out.append(f"**Convolution layouts.** {sum(odd.values())} of {s['convs']} convolutions put the batch "
               f"elsewhere than first (`{'`, `'.join(k for k, _ in odd.most_common(4))}`, all weight gradients); "
               f"XLA:GPU's layout assignment is expected to add transposes of their operands (up to "
               f"{fmt_bytes(max(r['bytes'] for r in c['convolutions'] if r['dim_labels'] in odd))} per convolution) "
               f"around the ones cuDNN cannot take as they are.")
  if c["ffts"]:
    in_loop = [r for r in c["ffts"] if r["in_loop"]]
    lengths = sorted({int(x) for r in c["ffts"] for x in r["length"].split(",") if x.strip().isdigit()})
    awkward = [n for n in lengths if max(prime_factors(n), default=1) > 7]
    factored = ", ".join(f"{n} = " + " x ".join(map(str, prime_factors(n))) for n in awkward)
    out.append(f"**FFTs.** {s['ffts']} FFT ops, {s['fft_runs']} per step, lengths {lengths}"
               + (f"; {len(in_loop)} inside loops (the physics layer one feature channel at a time), run "
                  f"{sum(r['runs'] for r in in_loop)} times" if in_loop else "")
               + (f". Lengths with a prime factor above 7 ({factored}) "
                  "fall outside the radices cuFFT documents as its fastest (2, 3, 5, 7): expected slower per point "
                  "than the power-of-two ones" if awkward else "")
               + ". Batched FFTs run inside a loop cost a launch per trip.")
  if c["transposes"]:
    big = max(c["transposes"], key=lambda r: r["bytes"])
    out.append(f"**Transposes.** {s['transposes']} transposes ({s['transpose_runs']} per step) move "
               f"{fmt_bytes(s['transpose_bytes'])} per step before fusion; the largest {big['shape']} "
               f"({fmt_bytes(big['bytes'])}, dims {{{big['dims']}}}, {big['part']}). Expected bandwidth cost "
               f"where XLA cannot fold them into a neighbour's layout.")
  if s["dyn_in_loop"]:
    dyn = [r for r in c["dynamic_slices"] if r["in_loop"]]
    out.append(f"**Dynamic slices in loops.** {s['dyn_in_loop']} dynamic-slice/dynamic-update-slice ops inside "
               f"loops, {s['dyn_in_loop_runs']:,} runs per step, moving "
               f"{fmt_bytes(sum(r['moved_bytes'] * r['runs'] for r in dyn))} per step: each trip reads its slice "
               f"and writes its output; expected in place, one more small kernel per trip where not fused.")
  one = [r for r in c["gather_scatter"] if r["index_rows"] == 1]
  if one:
    out.append(f"**One-window scatters.** {len(one)} of {s['gather'] + s['scatter']} gather/scatter ops read a "
               f"single index vector ({_top(collections.Counter(r['source'].split('/')[-1] for r in one), 2)}; "
               f"a single-window update): expected to cost like a dynamic-update-slice, not like a scatter.")
  scat = [r for r in c["gather_scatter"] if r["index_rows"] > 1]
  if scat:
    kinds = collections.Counter((r["opcode"], r["shape"], r["indices"], r["source"].split("/")[-1]) for r in scat)
    out.append("**Gather/scatter with computed indices.** " + "; ".join(
        f"{n} x {op} {shape} at indices {idx} ({src})" for (op, shape, idx, src), n in kinds.most_common(4))
        + ". Expected: scatter-adds whose indices collide serialise on atomics.")
  if s["f64"]:
    out.append(f"**float64.** {s['f64']} ops with float64 values: GPUs run float64 at a fraction of float32's rate.")
  if s["host"]:
    out.append(f"**Host traffic.** {s['host']} host-side ops (callbacks, send/recv): each stalls the device.")
  return out


def render(gpu: dict, here: dict | None, info_gpu: dict, info_here: dict | None, command: str,
           config_name: str, variant: str, batch: int, choices: list[str]) -> str:
  """The Markdown report: census as a GPU process traces the step, beside the one traced here."""
  s = summary(gpu)
  lines = [f"# The `{config_name}` train step lowered for CUDA without a GPU: an HLO census", ""]
  lines += _machine.provenance(command) + [""]
  lowered = info_gpu["lowered_for"]
  lines += [f"Variant `{variant}` ({info_gpu['model']}), batch {batch}, input "
            f"{' x '.join(map(str, info_gpu['input']))}; lowered for `{lowered}` "
            f"(`jax.jit(step).trace(...).lower(lowering_platforms=(\"{PLATFORM}\",))`, abstract inputs; "
            f"trace {info_gpu['trace_s']:.1f} s, lower {info_gpu['lower_s']:.1f} s; nothing compiled). "
            f"The physics operators the step is bound to: {fmt_bytes(info_gpu['operator_bytes'])}.", ""]
  if info_gpu["note"]:
    lines += [f"**Note: {info_gpu['note']}.** The census below is of the CPU lowering.", ""]
  lines += ["## Backend-dependent choices", "",
            "`lowering_platforms` changes what the program is lowered for, not `jax.default_backend()`, which "
            "stays this machine's (`cpu`) while the step is traced. The code's backend checks "
            "(`default_backend()`, `platform_dependent`, `devices()[0].platform` in `nlosjax/`):", ""]
  lines += [f"- {c}" for c in choices] or ["- none"]
  lines += ["",
            f"- The model's `scan_method` is `{info_here['scan_method'] if info_here else 'auto'}`: "
            f"`nlosjax.ssm.resolve_method` takes it to **`{info_here['scan_resolved'] if info_here else '?'}`** "
            f"when traced here (the CPU branch) and to **`{info_gpu['scan_resolved']}`** in a GPU process. "
            f"The census below is of the step as a GPU process traces it (`scan_method=\"{info_gpu['scan_method']}\"` "
            "pinned); the one as traced here follows it for comparison.",
            f"- `conv_impl` is `{info_gpu['conv_impl']}`: `nlosjax.models.conv.resolve_conv_impl` picks each "
            "layer's implementation by its shape alone (no backend check), tuned on XLA:CPU.",
            "- `nlosjax.platforms.by_platform` (`lax.platform_dependent`) picks by the platform the program is "
            "lowered for, so the census holds the GPU paths (`docs/gpu.md`): `conv2d_kernel_grad` as JAX's own "
            "kernel gradient, `resample_depth` as a dense product, the physics layer's FFTs batched at 7-smooth "
            f"lengths. The lowered program holds {gpu['conditionals']} `conditional` ops: a program lowered for "
            "one platform keeps that platform's branch alone.", ""]

  lines += ["## Summary", "",
            "| | as a GPU process traces it | as traced on this machine |", "|---|---:|---:|"]
  h = summary(here) if here else None
  rows = [("HLO instructions (static)", gpu["instructions"], here and here["instructions"]),
          ("instructions run per step (loop trips counted)", gpu["executed_per_step"],
           here and here["executed_per_step"]),
          ("`while` loops (static)", s["loops"], h and h["loops"]),
          ("loop trips per step", s["loop_trips"], h and h["loop_trips"]),
          ("largest trip count", s["max_trips"], h and h["max_trips"]),
          ("loops with a trip count not static", s["unknown_trips"], h and h["unknown_trips"]),
          ("convolutions (static / per step)", f"{s['convs']} / {s['conv_runs']}",
           h and f"{h['convs']} / {h['conv_runs']}"),
          ("weight-gradient convolutions (static / per step)", f"{s['weight_grads']} / {s['weight_grad_runs']}",
           h and f"{h['weight_grads']} / {h['weight_grad_runs']}"),
          ("convolution GFLOP per step (weight gradients)", f"{s['conv_gflop']:.0f} ({s['wg_gflop']:.0f})",
           h and f"{h['conv_gflop']:.0f} ({h['wg_gflop']:.0f})"),
          ("convolutions with feature/batch groups > 1", s["grouped_convs"], h and h["grouped_convs"]),
          ("FFTs (static / per step)", f"{s['ffts']} / {s['fft_runs']}", h and f"{h['ffts']} / {h['fft_runs']}"),
          ("custom calls (of which kernels, not sharding marks)", f"{s['custom_calls']} ({s['kernel_custom_calls']})",
           h and f"{h['custom_calls']} ({h['kernel_custom_calls']})"),
          ("transposes (static / per step)", f"{s['transposes']} / {s['transpose_runs']}",
           h and f"{h['transposes']} / {h['transpose_runs']}"),
          ("transpose bytes per step (before fusion)", fmt_bytes(s["transpose_bytes"]),
           h and fmt_bytes(h["transpose_bytes"])),
          ("float64 ops", s["f64"], h and h["f64"]),
          ("host-side ops (callbacks, send/recv, in/outfeed)", s["host"], h and h["host"]),
          ("gather / scatter", f"{s['gather']} / {s['scatter']}", h and f"{h['gather']} / {h['scatter']}"),
          ("dynamic(-update)-slices in loops (static / per step)", f"{s['dyn_in_loop']} / {s['dyn_in_loop_runs']:,}",
           h and f"{h['dyn_in_loop']} / {h['dyn_in_loop_runs']:,}")]
  for name, a, b in rows:
    fa = f"{a:,}" if isinstance(a, int) else a
    fb = "-" if b is None else (f"{b:,}" if isinstance(b, int) else b)
    lines.append(f"| {name} | {fa} | {fb} |")
  sh = gpu.get("stablehlo")
  if sh:
    lines += ["", "StableHLO text, static counts (each function once; the HLO counts above agree where the "
              "conversion keeps one computation per function): " + ", ".join(f"`{k}` {v}" for k, v in sh.items()) + "."]

  lines += ["", "## Likely slow on a GPU (expectations to check on a device, not measurements)", ""]
  lines += [f"{n}. {item}" for n, item in enumerate(slow_list(gpu, s), 1)]
  if here:
    lh = summary(here)
    lines += [f"{len(slow_list(gpu, s)) + 1}. **The CPU branch, if the step is traced where the default backend is "
              f"CPU.** Traced here, the same step has {lh['loops']} loops and {lh['loop_trips']:,} loop trips per "
              f"step (against {s['loops']} and {s['loop_trips']:,}); a GPU process resolves `auto` itself, so "
              f"this matters only for programs exported from a CPU host."]

  for title, c in (("as a GPU process traces it", gpu), ("as traced on this machine", here)):
    if c is None:
      continue
    lines += ["", f"## While loops, {title}", "",
              "Grouped by trip count, runs and body; `runs` is how often the loop itself starts per step (its "
              "enclosing loops' trips); `body ops` counts the body's instructions and those of what it calls, "
              "not nested loop bodies. `part` is the network part most of the body's ops come from (`op_name` "
              "metadata), `code` the innermost project function that emitted them. `op outputs per trip`: the "
              "bytes every body op writes, before fusion (an upper bound on a trip's memory traffic).", ""]
    lines += loop_rows(c)
  lines += ["", "## Convolutions (as a GPU process traces it)", "",
            "Grouped by shapes, `dim_labels` (b/f: batch/feature of the input, i/o of the kernel, digits the "
            "spatial dims), window (`size`, `pad`, `stride`, `lhs_dilate`/`rhs_dilate` as XLA prints them), "
            "feature_group_count (fgc) and batch_group_count (bgc). A weight gradient: a window larger than the "
            "output in a spatial dim (the kernel slides over the activations and the output is the kernel's size). "
            "GFLOP: 2 x output x window x kernel input channels, padding included, per step.", ""]
  lines += conv_rows(gpu)
  lines += ["", "## Custom calls, FFTs, transposes (as a GPU process traces it)", ""]
  cc = collections.Counter((r["target"], r["annotation"]) for r in gpu["custom_calls"])
  lines += ["| custom-call target | static | per step | what |", "|---|---:|---:|---|"]
  for (target, ann), n in cc.most_common():
    runs = sum(r["runs"] for r in gpu["custom_calls"] if r["target"] == target)
    lines.append(f"| `{target}` | {n} | {runs} | {'sharding annotation (Shardy), no kernel' if ann else 'kernel'} |")
  if not cc:
    lines.append("| none | 0 | 0 | |")
  lines += ["", "No cuDNN or cuFFT custom calls appear before compilation: XLA:GPU turns `convolution` into "
            "`__cudnn$conv...` custom calls and `fft` into cuFFT calls while it compiles, which needs a GPU.", "",
            "| FFT | length | input | output | static | per step | in a loop | part | code |",
            "|---|---|---|---|---:|---:|---|---|---|"]
  for k, rows in sorted(_group(gpu["ffts"], ("type", "length", "input", "output", "in_loop")),
                        key=lambda kv: -sum(r["runs"] for r in kv[1])):
    parts = collections.Counter(r["part"] for r in rows)
    srcs = collections.Counter(r["source"].split("/")[-1] for r in rows if r["source"])
    lines.append(f"| {k[0]} | {{{k[1]}}} | {k[2]} | {k[3]} | {len(rows)} | {sum(r['runs'] for r in rows)} | "
                 f"{'yes' if k[4] else 'no'} | {_top(parts, 2)} | {_top(srcs, 2)} |")
  lines += ["", "Largest transposes by bytes (before fusion; XLA may fold many into layouts):", "",
            "| shape | dims | bytes | per step | part | code |", "|---|---|---:|---:|---|---|"]
  for r in sorted(gpu["transposes"], key=lambda r: -r["bytes"])[:10]:
    lines.append(f"| {r['shape']} | {{{r['dims']}}} | {fmt_bytes(r['bytes'])} | {r['runs']} | {r['part']} | "
                 f"{r['source'].split('/')[-1]} |")
  lines += ["", "## Gather, scatter, dynamic slices (as a GPU process traces it)", ""]
  gs = gpu["gather_scatter"]
  if gs:
    lines += ["| op | shape | indices | indices constant | in a loop | static | per step | code |",
              "|---|---|---|---|---|---:|---:|---|"]
    for k, rows in _group(gs, ("opcode", "shape", "indices", "constant_indices", "in_loop", "source")):
      lines.append(f"| {k[0]} | {k[1]} | {k[2]} | {'yes' if k[3] else 'no'} | {'yes' if k[4] else 'no'} | "
                   f"{len(rows)} | {sum(r['runs'] for r in rows)} | {k[5].split('/')[-1]} |")
  else:
    lines.append("No gather or scatter ops.")
  dyn = [r for r in gpu["dynamic_slices"] if r["in_loop"]]
  lines += ["", f"Dynamic slices inside loops: {len(dyn)} static, {sum(r['runs'] for r in dyn):,} per step "
            f"(slices moved per step: {fmt_bytes(sum(r['moved_bytes'] * r['runs'] for r in dyn))}); outside "
            f"loops {sum(not r['in_loop'] for r in gpu['dynamic_slices'])}. The most frequent:", "",
            "| op | slice moved | of buffer | static | per step | code |", "|---|---|---|---:|---:|---|"]
  for k, rows in sorted(_group(dyn, ("opcode", "moved", "shape", "source")),
                        key=lambda kv: -sum(r["runs"] for r in kv[1]))[:10]:
    lines.append(f"| {k[0]} | {k[1]} | {k[2]} | {len(rows)} | {sum(r['runs'] for r in rows):,} | "
                 f"{k[3].split('/')[-1]} |")
  lines += ["", "## Op counts (as a GPU process traces it)", "", "| opcode | static | per step |", "|---|---:|---:|"]
  for op, st, r in gpu["opcodes"][:25]:
    lines.append(f"| `{op}` | {st:,} | {r:,} |")
  lines += ["", "How to read it: every count is of the program JAX hands XLA, before XLA:GPU's passes "
            "(fusion, layout assignment, the cuDNN/cuFFT rewrites), which would merge many of these ops into "
            "fewer kernels; loops stay loops. `per step` multiplies static counts by the static trip counts of "
            "the loops around them (a loop whose trip count is not static counts once). Nothing here was run "
            "on a GPU: the list of what is likely slow gives expectations, to be checked with "
            "`python -m benchmarks.device` on one (`docs/gpu.md`)."]
  return "\n".join(lines) + "\n"


# ------------------------------------------------------------ the compiled program
TARGETS_DIR = pathlib.Path(__file__).resolve().parent / "gpu_targets"
#: The GPU targets ``--compile`` builds for: ``xla.GpuTargetConfigProto`` texts in :data:`TARGETS_DIR`.
TARGETS = {"h100": "h100.txtpb", "h200": "h200.txtpb"}
COMPILED_OUT = pathlib.Path(__file__).resolve().parent / "results" / "hlo_gpu_compiled.md"
#: Compiled-HLO opcodes that launch no kernel of their own (control flow, views, bookkeeping).
NOT_KERNELS = ("parameter", "constant", "get-tuple-element", "tuple", "bitcast", "while", "conditional", "call",
               "after-all", "partition-id", "replica-id", "opt-barrier", "add-dependency", "domain",
               "async-start", "async-update", "async-done", "copy-start", "copy-done")
CUDNN_PREFIX = "__cudnn$conv"
GEMM_TARGETS = ("__cublas$gemm", "__cublas$lt$matmul")
FLOAT_DTYPES = ("f16", "bf16", "f32", "f64", "c64", "c128")
#: The largest prime factor an FFT length may have (cuFFT's fast radices: 2, 3, 5, 7).
FFT_SMOOTH = 7


def target_facts(text: str) -> dict:
  """Peak float32 FLOP/s (SMs x FP32 lanes per SM x 2 x clock) and memory bandwidth from a target text."""
  def num(key):
    m = re.search(rf"\b{key}:\s*([\d.]+)", text)
    return float(m.group(1)) if m else 0.0
  name = re.search(r'device_description_str:\s*"([^"]*)"', text)
  return {"name": name.group(1) if name else "?", "peak_flops": num("core_count") * num("fpus_per_core") * 2 *
          num("clock_rate_ghz") * 1e9, "bandwidth": num("memory_bandwidth"),
          "memory": num("device_memory_size"), "sms": int(num("core_count"))}


def _control(module: HloModule) -> set[str]:
  """Computations run as code (entry, loop bodies, branches, calls, async wrappers), not fused computations or
  scalar reducers: their instructions are the program's kernels and control. Loop conditions are left out
  (a loop whose trip count is known runs its body that many times without them)."""
  out, todo = set(), [module.entry]
  while todo:
    c = todo.pop()
    if c in out:
      continue
    out.add(c)
    for ins in module.computations.get(c, ()):
      if ins.opcode == "fusion":
        continue
      todo += [callee for callee, role in callees(ins) if role not in ("apply", "condition")]
  return out


def _fused_root(module: HloModule, ins: Instr) -> Instr | None:
  return next((i for i in module.computations.get(ins.attr("calls") or "", []) if i.root), None)


def _kernel_bytes(module: HloModule, ins: Instr) -> int:
  """Bytes a kernel reads and writes: its operands and outputs, where a fusion reads an operand only
  through dynamic slices the slices alone, and an in-place dynamic-update-slice root its update alone."""
  ops = [module.by_name[o] for o in ins.operands if o in module.by_name]
  if ins.opcode != "fusion":
    return sum(nbytes(o.shape) for o in ops) + nbytes(ins.shape)
  body = module.computations.get(ins.attr("calls") or "", [])
  params = {int(i.literal): i.name for i in body if i.opcode == "parameter" and i.literal.strip().isdigit()}
  users = collections.defaultdict(list)
  for i in body:
    for o in i.operands:
      users[o].append(i)
  root = next((i for i in body if i.root), None)
  total = 0
  for k, o in enumerate(ops):
    p = params.get(k)
    us = users.get(p, [])
    if us and all(u.opcode == "dynamic-slice" and u.operands[0] == p for u in us):
      total += sum(nbytes(u.shape) for u in us)
    elif us and root is not None and all(u is root and root.opcode == "dynamic-update-slice" and
                                         root.operands[0] == p for u in us):
      total += 0                                   # updated in place: the update is counted as the output
    else:
      total += nbytes(o.shape)
  if root is not None and root.opcode == "dynamic-update-slice" and len(root.operands) > 1 and \
     root.operands[1] in module.by_name:
    return total + nbytes(module.by_name[root.operands[1]].shape)
  return total + nbytes(ins.shape)


def _gemm_flops(module: HloModule, ins: Instr) -> float:
  """2 x output elements x contracted length of a cuBLAS call or the ``dot`` inside a GEMM fusion."""
  dot = ins
  if ins.opcode == "fusion":
    dot = next((i for i in closure(module, ins.attr("calls") or "") if i.opcode == "dot"), None)
    if dot is None:
      return 0.0
    lhs_dims = [int(v) for v in (dot.attr("lhs_contracting_dims") or "").split(",") if v]
  else:
    m = re.search(r'"lhs_contracting_dimensions":\[([^\]]*)\]', ins.attrs)
    lhs_dims = [int(v.strip('" ')) for v in m.group(1).split(",") if v.strip('" ')] if m else []
  lhs = module.by_name.get(dot.operands[0]) if dot.operands else None
  shape = arrays(lhs.shape)[0][1] if lhs is not None and arrays(lhs.shape) else ()
  k = math.prod(shape[d] for d in lhs_dims if d < len(shape)) if lhs_dims else 1
  return 2.0 * math.prod(arrays(dot.shape)[0][1]) * k


def _fft_flops(ins: Instr) -> float:
  """5 N log2 N per complex transform of N points (half for a real one), times the batch."""
  lengths = [int(v) for v in (ins.attr("fft_length") or "").split(",") if v]
  n = math.prod(lengths) if lengths else 1
  out = arrays(ins.shape)[0][1] if arrays(ins.shape) else ()
  batch = math.prod(out[:len(out) - len(lengths)]) if out else 1
  real = (ins.attr("fft_type") or "FFT") in ("RFFT", "IRFFT")
  return batch * 5 * n * math.log2(max(n, 2)) * (0.5 if real else 1.0)


def cudnn_facts(module: HloModule, ins: Instr) -> dict:
  """A cuDNN convolution call's forward convolution: input, filter and output shapes, window and FLOPs.

  ``convForward(input, filter) -> output``, ``convBackwardInput(output grad, filter) -> input grad``,
  ``convBackwardFilter(input, output grad) -> filter grad``; the window and ``dim_labels`` are the
  forward convolution's. FLOPs: 2 x forward output elements x window x filter input channels.
  """
  target = ins.attr("custom_call_target") or ""
  shapes = [module.by_name[o].shape if o in module.by_name else "" for o in ins.operands[:2]]
  result = arrays(ins.shape)[0] if arrays(ins.shape) else ("f32", ())
  result_text = f"{result[0]}[{','.join(map(str, result[1]))}]"
  if target.endswith("BackwardFilter"):
    x, w, y = shapes[0], result_text, shapes[1]
  elif target.endswith("BackwardInput"):
    x, w, y = result_text, shapes[1], shapes[0]
  else:
    x, w, y = shapes[0], shapes[1], result_text
  labels = ins.attr("dim_labels") or ""
  size = re.search(r"size=([\dx]+)", ins.attr("window") or "")
  window = tuple(int(v) for v in size.group(1).split("x")) if size else ()
  w_labels = labels.split("_")[1].split("->")[0] if "_" in labels else ""
  w_dims = arrays(w)[0][1] if arrays(w) else ()
  cin = w_dims[w_labels.index("i")] if "i" in w_labels and len(w_dims) == len(w_labels) else 1
  y_dims = arrays(y)[0][1] if arrays(y) else ()
  out_labels = labels.split("->")[-1] if "->" in labels else ""
  spatial = [y_dims[out_labels.index(str(d))] for d in range(len(window))
             if str(d) in out_labels and out_labels.index(str(d)) < len(y_dims)]
  return {"target": target, "input": dims_text(x), "filter": dims_text(w), "output": dims_text(y),
          "window": window, "flops": 2.0 * math.prod(y_dims) * math.prod(window or (1,)) * cin,
          "weight_grad_as_forward": target.endswith("Forward") and any(a > b for a, b in zip(window, spatial))}


def kernel_kind(module: HloModule, ins: Instr) -> str:
  """``cudnn``, ``gemm``, ``fft``, ``scatter``, ``fusion`` or the opcode of one kernel."""
  target = ins.attr("custom_call_target") or ""
  if ins.opcode == "custom-call":
    return "cudnn" if target.startswith(CUDNN_PREFIX) else ("gemm" if target.startswith(GEMM_TARGETS) else
                                                             f"custom-call {target}")
  if ins.opcode == "fusion":
    if re.search(r'"kind":"__triton_gemm"|"kind":"__cublas', ins.attrs) or (
        ins.attr("kind") == "kCustom" and any(i.opcode == "dot" for i in closure(module, ins.attr("calls") or ""))):
      return "gemm"
    root = _fused_root(module, ins)
    if root is not None and root.opcode == "scatter":
      return "scatter"
    return "fusion"
  return ins.opcode


def compiled_census(text: str) -> dict:
  """What XLA:GPU's optimised program (``Compiled.as_text()``) runs per step; JSON-friendly.

  Kernels are the instructions of the computations run as code (:func:`_control`) that launch
  work (not :data:`NOT_KERNELS`); each is counted once per run (loop trips multiplied in). FLOPs
  are those of cuDNN convolutions, GEMMs and FFTs (elementwise work not counted); bytes are each
  kernel's operands and outputs (:func:`_kernel_bytes`). A float atomic: a scatter on floats
  whose indices are not declared unique (``unique_indices=true``), which XLA:GPU emits as atomic
  read-modify-writes.
  """
  module = parse_hlo(text)
  g = call_graph(module)
  control = _control(module)
  run = lambda i: g.runs.get(i.computation, 0)          # noqa: E731
  kernels = []
  for c in control:
    for i in module.computations.get(c, ()):
      if i.opcode in NOT_KERNELS:
        continue
      kind = kernel_kind(module, i)
      flops = 0.0
      if kind == "cudnn":
        flops = cudnn_facts(module, i)["flops"]
      elif kind == "gemm":
        flops = _gemm_flops(module, i)
      elif i.opcode == "fft":
        flops = _fft_flops(i)
      kernels.append({"name": i.name, "kind": kind, "opcode": i.opcode, "runs": run(i), "in_loop": c in g.in_loop,
                      "flops": flops, "bytes": _kernel_bytes(module, i)})
  cudnn = []
  for c in control:
    for i in module.computations.get(c, ()):
      if i.opcode == "custom-call" and (i.attr("custom_call_target") or "").startswith(CUDNN_PREFIX):
        f = cudnn_facts(module, i)
        cudnn.append({**f, "runs": run(i), "gflop": f.pop("flops") / 1e9})
  ffts = [{"type": i.attr("fft_type") or "FFT", "length": tuple(int(v) for v in (i.attr("fft_length") or "").split(",")
                                                                 if v),
           "shape": dims_text(i.shape), "runs": run(i), "in_loop": i.computation in g.in_loop}
          for c in control for i in module.computations.get(c, ()) if i.opcode == "fft"]
  loops = [{"name": i.name, "trips": g.trips.get(i.name), "runs": run(i), "nested": i.computation in g.in_loop,
            "kernels_per_trip": sum(1 for x in closure(module, i.attr("body")) if x.computation in control and
                                    x.opcode not in NOT_KERNELS)}
           for c in control for i in module.computations.get(c, ()) if i.opcode == "while"]
  scatters = []
  for comp, instrs in module.computations.items():
    for i in instrs:
      if i.opcode != "scatter":
        continue
      dtype = arrays(i.shape)[0][0] if arrays(i.shape) else ""
      unique = (i.attr("unique_indices") or "false") == "true"
      scatters.append({"shape": dims_text(i.shape), "runs": g.runs.get(comp, 0), "unique_indices": unique,
                       "float_atomic": dtype in FLOAT_DTYPES and not unique,
                       "indices": dims_text(module.by_name[i.operands[1]].shape)
                       if len(i.operands) > 1 and i.operands[1] in module.by_name else ""})
  return {"kernels": kernels, "cudnn": cudnn, "ffts": ffts, "loops": loops, "scatters": scatters,
          "unknown_trips": g.unknown_trips}


def compiled_summary(c: dict, target: dict | None = None) -> dict:
  """Per-step totals of :func:`compiled_census` and, given :func:`target_facts`, the roofline (seconds):
  the sum over kernels of the larger of FLOPs / peak and bytes / bandwidth."""
  k = c["kernels"]
  s = {"kernels_static": len(k), "kernels_per_step": sum(r["runs"] for r in k),
       "by_kind": dict(collections.Counter({r["kind"]: 0 for r in k}) + collections.Counter(
           {kind: sum(r["runs"] for r in k if r["kind"] == kind) for kind in {r["kind"] for r in k}})),
       "flops": sum(r["flops"] * r["runs"] for r in k), "bytes": sum(r["bytes"] * r["runs"] for r in k),
       "cudnn_by_target": dict(collections.Counter({r["target"]: 0 for r in c["cudnn"]}) + collections.Counter(
           {t: sum(r["runs"] for r in c["cudnn"] if r["target"] == t) for t in {r["target"] for r in c["cudnn"]}})),
       "cudnn_over_3x3": sum(r["runs"] for r in c["cudnn"] if any(w > 3 for w in r["window"])),
       "largest_window": max((r["window"] for r in c["cudnn"]), key=math.prod, default=[]),
       "weight_grad_as_forward": sum(r["runs"] for r in c["cudnn"] if r["weight_grad_as_forward"]),
       "ffts_per_step": sum(r["runs"] for r in c["ffts"]),
       "fft_lengths": sorted({n for r in c["ffts"] for n in r["length"]}),
       "fft_rough": sorted({n for r in c["ffts"] for n in r["length"] if max(prime_factors(n) or [1]) > FFT_SMOOTH}),
       "ffts_in_loops": sum(r["runs"] for r in c["ffts"] if r["in_loop"]),
       "loops": len(c["loops"]), "loop_trips": sum(r["runs"] * (r["trips"] or 1) for r in c["loops"]),
       "float_atomics": sum(r["runs"] for r in c["scatters"] if r["float_atomic"]),
       "scatters": sum(r["runs"] for r in c["scatters"]), "unknown_trips": c["unknown_trips"]}
  if target is not None:
    s["roofline_s"] = sum(max(r["flops"] / target["peak_flops"], r["bytes"] / target["bandwidth"]) * r["runs"]
                          for r in k)
    s["compute_s"] = s["flops"] / target["peak_flops"]
    s["memory_s"] = s["bytes"] / target["bandwidth"]
  return s


def compile_for_target(config: dict, variant: str, batch: int, target: str, what: str = "train") -> dict:
  """The run's train step (``what="train"``) or the network's forward pass (``"inference"``) compiled by
  XLA:GPU for ``target`` (a :data:`TARGETS` key)
  on this machine, without a GPU: the optimised HLO text, cost analysis and times.

  Needs the CUDA plugin (``jax[cuda12]``) and ``JAX_PLATFORMS=cpu``; the step is built as
  :func:`lower_step` builds it, its shardings on a one-device mesh of the target's topology
  (``jax.experimental.topologies.get_topology_desc``), the physics operators as shapes.
  """
  import jax
  import jax.numpy as jnp
  import numpy as np
  from jax.experimental import topologies
  from jax.sharding import Mesh, NamedSharding
  from jax.sharding import PartitionSpec as P

  from nlosjax import inference, plan
  from nlosjax import train as T
  from nlosjax.physics import operator_args
  from nlosjax.ssm import resolve_method
  text = (TARGETS_DIR / TARGETS[target]).read_text()
  topo = topologies.get_topology_desc(target, "cuda", target_config=text, topology="1x1x1")
  mesh = Mesh(np.asarray(topo.devices).reshape(-1), ("data",))
  rep = NamedSharding(mesh, P())
  config = {**config, "train": {**config["train"], "batch_size": int(batch)}}
  typed = T.RunConfig.from_dict(config)
  mcfg = T.model_config_for(typed, inference.training_setup(typed), variant)
  mcfg = dataclasses.replace(mcfg, scan_method=resolve_method("auto", backend="gpu"))
  optim, weights = T.training_recipe(typed, variant)
  tx = T.make_optimizer(optim, int(config["train"]["steps"]))
  t = time.perf_counter()
  state = T.abstract_train_state(T.network(mcfg), tuple(mcfg.input_shape(batch)), tx, mesh)
  batch_shapes = plan._abstract_batch(mcfg, batch, mesh)
  k = jax.eval_shape(lambda: jax.random.key(0))
  key = jax.ShapeDtypeStruct(k.shape, k.dtype, sharding=rep)
  step = T.make_train_step(mcfg, weights, T.mesh_for(typed))        # the operators, built on this machine
  table = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=rep), step.table)
  if what == "train":
    bound = operator_args.Bound(step.__wrapped__, table, donate_argnums=0, out_shardings=(rep, rep))
    lowered = bound.jitted.trace(state, batch_shapes, key, table).lower()
  else:                                                              # the network's forward pass alone
    model = T.network(mcfg)
    bound = operator_args.Bound(lambda p, x: model.apply({"params": p}, x), table)
    x = jax.ShapeDtypeStruct(tuple(mcfg.input_shape(batch)), jnp.float32, sharding=rep)
    lowered = bound.jitted.trace(state.params, x, table).lower()
  lower_s = time.perf_counter() - t
  t = time.perf_counter()
  compiled = lowered.compile()
  compile_s = time.perf_counter() - t
  try:
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    cost = {k: float(v) for k, v in (cost or {}).items() if k in ("flops", "bytes accessed", "transcendentals")}
  except Exception as e:                                        # noqa: BLE001 - reported
    cost = {"error": f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"}
  return {"hlo": compiled.as_text(), "cost": cost, "lower_s": lower_s, "compile_s": compile_s,
          "target": target_facts(text), "input": list(mcfg.input_shape(batch)),
          "scan_method": mcfg.scan_method, "model": type(T.network(mcfg)).__name__}


def _verdict(ok: bool) -> str:
  return "**met**" if ok else "**not met**"


def render_compiled(runs: list[dict], command: str, variant: str, batch: int, failed: list[str] = ()) -> str:
  """The Markdown report of ``--compile``: one section per (preset, target), the goals on the paper step."""
  lines = ["# The train step compiled by XLA:GPU for an H100 and an H200 on a CPU-only machine", ""]
  lines += _machine.provenance(command) + [""]
  lines += [f"**Failed to compile: {f}.**" for f in failed] + ([""] if failed else [])
  lines += [f"Variant `{variant}`, train steps at batch {batch}, inference (the network's forward pass) at "
            "batch 1. Each step is built as the run builds it (the preset's model, "
            "optimiser and loss), its state, batch, key and physics operators as `jax.ShapeDtypeStruct`s on a "
            "one-device mesh of the target's topology (`jax.experimental.topologies.get_topology_desc(target, "
            "\"cuda\", target_config=benchmarks/gpu_targets/<target>.txtpb, topology=\"1x1x1\")`), then "
            "`.trace(...).lower().compile()` with the CUDA plugin installed and `JAX_PLATFORMS=cpu`. Nothing runs "
            "on a GPU: no autotuning happens, so cuDNN and GEMM algorithms are XLA's defaults. The optimised "
            "program (`compiled.as_text()`) is read by `benchmarks.hlo_gpu.compiled_census`.", "",
            "Kernels: the launching instructions (fusions, custom calls, FFTs, copies) of the computations "
            "run as code, counted per step with loop trips multiplied in. FLOPs: cuDNN convolutions, GEMMs and "
            "FFTs (5 N log2 N per complex transform); elementwise work is not counted. Bytes: each kernel's "
            "operands and outputs (a fusion reading an operand through dynamic slices counts the slices; an "
            "in-place update counts the update). Roofline: the sum over kernels of the larger of FLOPs / peak "
            "and bytes / bandwidth; launch overhead is not in it. Peak float32 FLOP/s is SMs x FP32 lanes per "
            "SM x 2 x clock from the target file (132 x 128 x 2 x 1.98 GHz = 66.9 TFLOP/s, NVIDIA's 67 TFLOP/s "
            "for H100 SXM and H200, without tensor cores); bandwidth is the target file's (NVIDIA's data "
            "sheets: H100 SXM 3.35 TB/s, H200 4.8 TB/s). `cost_analysis` is XLA's own count (loop bodies "
            "counted once, not per trip).", ""]
  paper = [r for r in runs if r["config"] == "paper" and r["what"] == "train"]
  if paper:
    lines += ["## Goals (the `paper` train step)", "",
              "| goal | " + " | ".join(r["target"]["name"] for r in paper) + " |",
              "|---|" + "---|" * len(paper)]
    def row(name, fn):
      lines.append(f"| {name} | " + " | ".join(fn(r["summary"]) for r in paper) + " |")
    row("no cuDNN convolution with a window larger than 3 x 3; every weight gradient backward-filter",
        lambda s: f"{_verdict(s['cudnn_over_3x3'] == 0 and s['weight_grad_as_forward'] == 0)}: "
                  f"{s['cudnn_over_3x3']} over 3 x 3, {s['weight_grad_as_forward']} weight gradients as forward "
                  f"convolutions; {s['cudnn_by_target'].get('__cudnn$convBackwardFilter', 0)} backward-filter")
    row("no float atomics", lambda s: f"{_verdict(s['float_atomics'] == 0)}: {s['float_atomics']} float scatters "
                                      f"without unique indices a step ({s['scatters']} scatters)")
    row(f"no FFT length with a prime factor above {FFT_SMOOTH}",
        lambda s: f"{_verdict(not s['fft_rough'])}: lengths {', '.join(map(str, s['fft_lengths'])) or 'none'}")
    row("no FFT inside a loop", lambda s: f"{_verdict(s['ffts_in_loops'] == 0)}: {s['ffts_in_loops']} of "
                                          f"{s['ffts_per_step']} FFTs a step in loops")
    row("roofline under 0.5 s a step", lambda s: f"{_verdict(s['roofline_s'] < 0.5)}: {s['roofline_s']:.3f} s")
    lines.append("")
  lines += ["## Summary", "",
            "| preset | program | target | compile s | kernels a step (static) | cuDNN a step | GEMMs | FFTs | "
            "loops / trips | float atomics | GFLOP | GB moved | FLOP/B | compute ms | memory ms | roofline ms | "
            "XLA cost_analysis GFLOP / GB |",
            "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
  for r in runs:
    s, cost = r["summary"], r["cost"]
    xla = (f"{cost['flops'] / 1e9:.0f} / {cost.get('bytes accessed', 0) / 1e9:.1f}" if "flops" in cost
           else cost.get("error", "none returned"))
    lines.append(f"| {r['config']} | {r['what']} (batch {r['batch']}) | {r['target']['name']} | {r['compile_s']:.0f} | "
                 f"{s['kernels_per_step']:,} ({s['kernels_static']:,}) | {sum(s['cudnn_by_target'].values())} | "
                 f"{s['by_kind'].get('gemm', 0)} | {s['ffts_per_step']} | {s['loops']} / {s['loop_trips']:,} | "
                 f"{s['float_atomics']} | {s['flops'] / 1e9:.0f} | {s['bytes'] / 1e9:.2f} | "
                 f"{s['flops'] / max(s['bytes'], 1):.1f} | {s['compute_s'] * 1e3:.2f} | {s['memory_s'] * 1e3:.2f} | "
                 f"{s['roofline_s'] * 1e3:.2f} | {xla} |")
  for r in runs:
    s, c = r["summary"], r["census"]
    lines += ["", f"## `{r['config']}` {r['what']} (batch {r['batch']}), {r['target']['name']}", "",
              f"Input {' x '.join(map(str, r['input']))}, model {r['model']}, scan `{r['scan_method']}`; lowered in "
              f"{r['lower_s']:.0f} s, compiled in {r['compile_s']:.0f} s.", "",
              "Kernels a step by kind: " + ", ".join(f"{k} {v:,}" for k, v in sorted(
                  s["by_kind"].items(), key=lambda kv: -kv[1])) + ".", "",
              "| cuDNN call | input | filter | output (of the forward convolution) | window | static | a step | "
              "GFLOP a step |",
              "|---|---|---|---|---|---:|---:|---:|"]
    for k, rows in sorted(_group(c["cudnn"], ("target", "input", "filter", "output")),
                          key=lambda kv: -sum(x["gflop"] * x["runs"] for x in kv[1])):
      lines.append(f"| `{k[0]}` | {k[1]} | {k[2]} | {k[3]} | {'x'.join(map(str, rows[0]['window']))} | {len(rows)} | "
                   f"{sum(x['runs'] for x in rows)} | {sum(x['gflop'] * x['runs'] for x in rows):.1f} |")
    lines += ["", "| FFT | length | prime factors | output | in a loop | static | a step |",
              "|---|---|---|---|---|---:|---:|"]
    for k, rows in _group(c["ffts"], ("type", "length", "shape", "in_loop")):
      lines.append(f"| {k[0]} | {' x '.join(map(str, k[1]))} | "
                   f"{' x '.join(str(p) for n in k[1] for p in prime_factors(n))} | {k[2]} | "
                   f"{'yes' if k[3] else 'no'} | {len(rows)} | {sum(x['runs'] for x in rows)} |")
    lines += ["", "| while loops | trips | runs a step | nested | kernels a trip |", "|---:|---:|---:|---|---:|"]
    for k, rows in sorted(_group(c["loops"], ("trips", "runs", "nested", "kernels_per_trip")),
                          key=lambda kv: -len(kv[1]) * (kv[0][0] or 1) * kv[0][1]):
      lines.append(f"| {len(rows)} | {_n(k[0])} | {k[1]} | {'yes' if k[2] else 'no'} | {k[3]} |")
    if c["scatters"]:
      lines += ["", "| scatter | indices | unique indices | float atomic | static | a step |",
                "|---|---|---|---|---:|---:|"]
      for k, rows in _group(c["scatters"], ("shape", "indices", "unique_indices", "float_atomic")):
        lines.append(f"| {k[0]} | {k[1]} | {'yes' if k[2] else 'no'} | {'yes' if k[3] else 'no'} | {len(rows)} | "
                     f"{sum(x['runs'] for x in rows)} |")
    else:
      lines += ["", "No scatters."]
  lines += ["", "How to read it: counts are of XLA:GPU's optimised program for the target, compiled without a "
            "GPU; the roofline is a lower bound from bytes and FLOPs, not a time measured on a device "
            "(`python -m benchmarks.device` measures one)."]
  return "\n".join(lines) + "\n"


def main_compile(args) -> int:
  """``--compile``: every (preset, target) compiled and read; the report written whole."""
  import os
  if os.environ.get("JAX_PLATFORMS", "") != "cpu":
    print("--compile needs JAX_PLATFORMS=cpu (and jax[cuda12] installed)", file=sys.stderr)
    return 2
  from experiments.cli import load_config
  runs, failed = [], []
  for name in args.configs.split(","):
    config = load_config(name)
    for target in args.targets.split(","):
      jobs = [("train", args.batch)] + ([("inference", 1)] if name in args.inference.split(",") else [])
      for what, batch in jobs:
        print(f"compiling the {name} {what} step (batch {batch}) for {target} ...", flush=True)
        try:
          r = compile_for_target(config, args.variant, batch, target, what)
        except Exception as e:                                   # noqa: BLE001 - reported in the file
          failed.append(f"`{name}` {what}, {target}: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}")
          print(f"  failed: {failed[-1]}", flush=True)
          continue
        census = compiled_census(r.pop("hlo"))
        runs.append({**r, "config": name, "what": what, "batch": batch, "census": census,
                     "summary": compiled_summary(census, r["target"])})
        print(f"  compiled in {r['compile_s']:.0f} s; {runs[-1]['summary']['kernels_per_step']:,} kernels, "
              f"roofline {runs[-1]['summary']['roofline_s']:.4f} s", flush=True)
  command = "python -m benchmarks.hlo_gpu --compile" + "".join(
      f" {flag} {value}" for flag, value, default in (
          ("--configs", args.configs, "cpu,paper"), ("--targets", args.targets, "h100,h200"),
          ("--batch", args.batch, "4"), ("--variant", args.variant, OURS), ("--inference", args.inference, "paper"))
      if str(value) != default)
  out = pathlib.Path(args.out) if args.out else COMPILED_OUT
  if out.resolve() != COMPILED_OUT:
    command += f" --out {args.out}"
  text = render_compiled(runs, command, args.variant, args.batch, failed)
  print(text)
  out.write_text(text)
  print(f"wrote {out}")
  return 0


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="paper", help="preset name or .py file (default: %(default)s)")
  parser.add_argument("--batch", type=int, default=4, help="global batch (default: %(default)s)")
  parser.add_argument("--variant", default=OURS, help="model variant (default: %(default)s)")
  parser.add_argument("--out", default=None, help="Markdown output (default: results/hlo_gpu.md, with --compile "
                      "results/hlo_gpu_compiled.md)")
  parser.add_argument("--compile", action="store_true",
                      help="compile the train steps with XLA:GPU for --targets without a GPU (needs jax[cuda12] and "
                           "JAX_PLATFORMS=cpu) and read the optimised program")
  parser.add_argument("--configs", default="cpu,paper", help="with --compile: presets (default: %(default)s)")
  parser.add_argument("--inference", default="paper", help="with --compile: presets whose batch-1 inference is "
                      "compiled too ('' for none; default: %(default)s)")
  parser.add_argument("--targets", default="h100,h200", help=f"with --compile: of {', '.join(TARGETS)} "
                      "(default: %(default)s)")
  args = parser.parse_args(argv)
  if args.batch < 1:
    parser.error("--batch must be at least 1")
  if args.compile:
    return main_compile(args)
  args.out = args.out or str(DEFAULT_OUT)
  from experiments.cli import load_config
  from nlosjax.ssm import resolve_method
  config = load_config(args.config)
  print("lowering as a GPU process traces it ...", flush=True)
  info_gpu = lower_step(config, args.variant, args.batch, scan_method=resolve_method("auto", backend="gpu"))
  gpu = census(info_gpu.pop("hlo"), info_gpu.pop("stablehlo"), info_gpu["model"])
  print("lowering as traced on this machine ...", flush=True)
  info_here = lower_step(config, args.variant, args.batch)
  here = census(info_here.pop("hlo"), info_here.pop("stablehlo"), info_here["model"])
  command = "python -m benchmarks.hlo_gpu" + "".join(
      f" {flag} {value}" for flag, value, default in (
          ("--config", args.config, "paper"), ("--batch", args.batch, "4"), ("--variant", args.variant, OURS))
      if str(value) != default)
  if pathlib.Path(args.out).resolve() != DEFAULT_OUT:
    command += f" --out {args.out}"
  text = render(gpu, here, info_gpu, info_here, command, args.config, args.variant, args.batch,
                backend_choices())
  print(text)
  pathlib.Path(args.out).write_text(text)
  print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())

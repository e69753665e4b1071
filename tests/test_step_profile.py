"""benchmarks.step_profile: self times against a brute-force nesting, op kinds and parts, a real trace."""

import pathlib
import random
import re
import tempfile

import jax
import jax.numpy as jnp

from benchmarks import step_profile as S


def _event(op, ts, dur, tid=0):
  return {"ph": "X", "pid": 1, "tid": tid, "ts": ts, "dur": dur, "args": {"hlo_op": op}}


def _brute_self_times(events):
  """Each event's duration less those of its direct children (contained, with nothing in between)."""
  def inside(c, e):
    return (c is not e and c["tid"] == e["tid"] and e["ts"] <= c["ts"]
            and c["ts"] + c["dur"] <= e["ts"] + e["dur"])
  out = {}
  for e in events:
    children = [c for c in events if inside(c, e)
                and not any(inside(c, d) and inside(d, e) for d in events)]
    out[e["args"]["hlo_op"]] = out.get(e["args"]["hlo_op"], 0) + e["dur"] - sum(c["dur"] for c in children)
  return out


def _nested_trace(rng):
  """Loops holding ops holding ops, on two threads, every op name unique."""
  events = []

  def add(kind, ts, dur, tid):
    events.append(_event(f"{kind}.{len(events)}", ts, dur, tid))

  for tid in (0, 1):
    t = 0
    for _ in range(5):
      outer = rng.randint(50, 100)
      add("while", t, outer, tid)
      inner_t = t + 1
      while inner_t + 12 < t + outer:
        d = rng.randint(3, 10)
        add("fusion", inner_t, d, tid)
        if d > 5:
          add("copy", inner_t + 1, d - 3, tid)
        inner_t += d + rng.randint(0, 2)
      t += outer + rng.randint(0, 5)
  rng.shuffle(events)
  return events


def test_self_times_equal_the_brute_force_nesting_and_sum_to_the_busy_time():
  rng = random.Random(0)
  for _ in range(5):
    events = _nested_trace(rng)
    own = S.self_times(events)
    assert own == _brute_self_times(events)
    top = [e for e in events if e["args"]["hlo_op"].startswith("while")]
    assert sum(own.values()) == sum(e["dur"] for e in top)       # the time some op was running
    assert all(v >= 0 for v in own.values())


def test_op_kinds_by_thunk_name():
  assert S.op_kind("fft.86") == "FFT"
  assert S.op_kind("ynn_fusion.42") == S.op_kind("dot.3") == "convolution and matmul"
  assert S.op_kind("while.609") == "loop control (while, call)"
  for name in ("copy.3072", "transpose_copy_fusion", "wrapped_broadcast.14", "broadcast_pad_fusion.3",
               "bitcast_dynamic-update-slice_fusion.2"):
    assert S.op_kind(name).startswith("data movement"), name
  for name in ("multiply_add_fusion.617", "exponential_log-plus-one_fusion", "wrapped_reduce-window"):
    assert S.op_kind(name) == "elementwise and reductions", name


def test_op_parts_from_op_name_metadata():
  back = "jit(with_table)/transpose(jvp(STMambaNet))/volume/refine/conv2/conv_general_dilated"
  assert S.op_part(back) == ("volume/refine", "backward")
  scan = ("jit(with_table)/jvp(STMambaNet)/st_mamba0/ssm/spatial1/spatial1._branch/while/body/"
          "closed_call/broadcast_in_dim")
  assert S.op_part(scan) == ("st_mamba0/ssm", "forward")
  assert S.op_part("jit(with_table)/jvp(STMambaNet)/extract/interlaced0/fuse/nthwc,cf->nthwf/dot_general") \
      == ("extract", "forward")
  assert S.op_part("jit(with_table)/jvp(STMambaNet)/cross_prev1_0/in_proj_ref/dot_general") \
      == ("cross_prev1_0/in_proj_ref", "forward")
  assert S.op_part("jit(with_table)/mul") == ("loss and optimiser", "-")
  usm = "jit(with_table)/transpose(jvp(USMNet))/Conv_0/conv_general_dilated"
  assert S.op_part(usm, "USMNet") == ("Conv_0", "backward")
  assert S.op_part(usm) == ("loss and optimiser", "-")             # another network's ops
  assert S.op_part(None) == ("XLA-inserted (no metadata)", "-")


def test_a_real_trace_maps_to_the_compiled_programs_ops():
  @jax.jit
  def f(x):
    return jnp.sum(jnp.sin(x) @ x.T) + jnp.fft.fft(x).real.sum()

  x = jnp.ones((64, 64))
  compiled = f.lower(x).compile()
  names = S.hlo_op_names(compiled.as_text())
  module = re.search(r"HloModule\s+([\w.\-]+)", compiled.as_text()).group(1)
  assert names and all("/" in v or v for v in names.values())
  jax.block_until_ready(f(x))
  with tempfile.TemporaryDirectory() as tmp:
    with jax.profiler.trace(tmp):
      jax.block_until_ready(f(x))
    events = S.read_trace(pathlib.Path(tmp), module)
  ops = {e["args"]["hlo_op"] for e in events}
  assert ops and any(op in names for op in ops), (ops, sorted(names)[:10])
  assert "FFT" in {S.op_kind(op) for op in ops}

"""benchmarks.op_profile: per-op device time from a profiler trace, each op in its HLO category.

Independent references: a hand-written HLO module (what each instruction is, by construction),
hand-made trace events (the sums by hand), and a real trace of a function whose one large
matmul outweighs its other ops by orders of magnitude in FLOPs.
"""

import jax
import jax.numpy as jnp
import pytest

from benchmarks import op_profile as P

HLO = """HloModule m

%inner_conv (p0: f32[1,8,8,2], p1: f32[3,3,2,2]) -> f32[1,8,8,2] {
  %p0 = f32[1,8,8,2]{3,2,1,0} parameter(0)
  %p1 = f32[3,3,2,2]{3,2,1,0} parameter(1)
  %convolution.3 = f32[1,8,8,2]{3,2,1,0} convolution(%p0, %p1), window={size=3x3}, metadata={op_name="f/conv_dil"}
  ROOT %tanh.1 = f32[1,8,8,2]{3,2,1,0} tanh(%convolution.3)
}

%outer (q0: f32[1,8,8,2], q1: f32[3,3,2,2]) -> f32[1,8,8,2] {
  %q0 = f32[1,8,8,2]{3,2,1,0} parameter(0)
  %q1 = f32[3,3,2,2]{3,2,1,0} parameter(1)
  ROOT %nested = f32[1,8,8,2]{3,2,1,0} fusion(%q0, %q1), kind=kOutput, calls=%inner_conv
}

%pointwise (r0: f32[4]) -> f32[4] {
  %r0 = f32[4]{0} parameter(0)
  ROOT %exponential.2 = f32[4]{0} exponential(%r0), metadata={op_name="jit(f)/exp"}
}

ENTRY %main (a: f32[1,8,8,2], b: f32[3,3,2,2], c: f32[4]) -> f32[4] {
  %a = f32[1,8,8,2]{3,2,1,0} parameter(0)
  %b = f32[3,3,2,2]{3,2,1,0} parameter(1)
  %c = f32[4]{0} parameter(2)
  %conv_fusion = f32[1,8,8,2]{3,2,1,0} fusion(%a, %b), kind=kOutput, calls=%outer
  %cudnn = (f32[1,8,8,2], u8[0]) custom-call(%a, %b), custom_call_target="__cudnn$convForward", metadata={op_name="f/c"}
  %loop_fusion = f32[4]{0} fusion(%c), kind=kLoop, calls=%pointwise
  ROOT %transpose.7 = f32[4]{0} transpose(%loop_fusion), dimensions={0}
}
"""


def test_each_instruction_gets_its_opcode_or_its_fusions_heaviest_op():
  ops = P.hlo_ops(HLO)
  assert ops["conv_fusion"]["category"] == "convolution"                 # through a nested fusion
  assert ops["conv_fusion"]["op_name"] == "f/conv_dil"
  assert ops["cudnn"]["category"] == "custom-call:__cudnn$convForward"
  assert ops["loop_fusion"] == {"opcode": "fusion", "category": "elementwise", "op_name": ""}
  assert ops["transpose.7"]["category"] == "transpose"
  assert ops["convolution.3"]["opcode"] == "convolution"


def test_the_summary_is_the_sum_by_op_per_step_and_shares_add_to_one():
  ops = P.hlo_ops(HLO)
  ev = [{"ts": 10000.0 * k, "dur": d, "pid": 0, "tid": 0, "args": {"hlo_op": op}}
        for k, (op, d) in enumerate([("conv_fusion", 3000.0), ("conv_fusion", 1000.0), ("cudnn", 2000.0),
                                     ("transpose.7", 2000.0), ("mystery", 0.0)])]
  s = P.summarize(ev, ops, steps=2, top=2)
  assert s["busy_ms"] == pytest.approx(4.0)                             # 8000 us over 2 steps
  assert [(r["op"], r["ms"], r["count"]) for r in s["ops"]] == [("conv_fusion", 2.0, 1.0), ("cudnn", 1.0, 0.5)]
  assert s["categories"]["convolution"] == {"ms": 2.0, "share": 0.5}
  assert s["categories"]["?"]["ms"] == 0.0 and s["distinct_ops"] == 4 and s["lanes"] == 1
  assert sum(c["share"] for c in s["categories"].values()) == pytest.approx(1.0)
  with pytest.raises(ValueError, match="steps"):
    P.summarize(ev, ops, steps=0)


def test_a_loop_event_counts_only_the_time_its_body_ops_do_not():
  """A while op spanning its body's two ops on one thread, and an op on another thread inside its span."""
  def ev(op, ts, dur, tid=1):
    return {"ts": ts, "dur": dur, "tid": tid, "pid": 0, "args": {"hlo_op": op}}
  events = [ev("while.1", 0, 100), ev("body.a", 10, 30), ev("body.b", 50, 40), ev("other", 20, 50, tid=2),
            ev("after", 100, 5)]
  s = P.summarize(events, {}, steps=1, top=10)
  assert {r["op"]: r["ms"] * 1e3 for r in s["ops"]} == pytest.approx(
      {"while.1": 30.0, "body.a": 30.0, "body.b": 40.0, "other": 50.0, "after": 5.0})
  assert s["busy_ms"] == pytest.approx(0.155)                            # 30 + 30 + 40 + 50 + 5 us, no overlap
  assert s["lanes"] == 2                                                  # "other" ran beside the loop: 155 us in 105


def test_a_real_trace_puts_the_large_matmul_first_and_counts_each_op_once_a_step():
  f = jax.jit(lambda x, y: (x @ x).sum() + jnp.exp(y).sum())            # 2*384^3 FLOPs against 64 exps
  args = (jnp.ones((384, 384)), jnp.ones((64,)))
  compiled = f.lower(*args).compile()
  prof = P.op_profile(lambda: compiled(*args), compiled.as_text(), steps=3)
  assert prof["steps"] == 3 and prof["ops"][0]["category"] == "dot"
  assert prof["categories"]["dot"]["share"] > 0.5
  assert all(r["count"] == 1 for r in prof["ops"])                       # no call outside the trace leaks in
  assert 0 < prof["busy_ms"] <= prof["wall_ms"] * prof["lanes"]
  lines = P.format_profile(prof, flops=2 * 384 ** 3, peak=(1e12, None))
  assert "of the 1 TFLOP/s float32 peak." in lines[0] and any(line.startswith("| dot |") for line in lines)
  assert P.peak_flops("NVIDIA H200") == (67e12, 495e12) and P.peak_flops("cpu") == (None, None)

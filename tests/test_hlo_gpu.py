"""benchmarks.hlo_gpu's census against programs whose loops, convolutions and FFTs are known by construction."""

import math

import jax
import jax.numpy as jnp
import pytest
from jax import lax

from benchmarks import hlo_gpu as H


def _tiny(x, w, wg, v):
  """One scan of 7 trips holding a convolution, a fori_loop of 3 around a scan of 5, an RFFT of 12,
  a grouped convolution and a kernel gradient over an 8 x 8 image."""
  conv = lambda a, k, groups=1: lax.conv_general_dilated(          # noqa: E731
      a, k, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"), feature_group_count=groups)

  def body(c, _):
    return conv(c, w), None
  y, _ = lax.scan(body, x, None, length=7)

  def outer(i, acc):
    inner, _ = lax.scan(lambda c, t: (c * 0.5 + t, None), acc, jnp.ones((5, 3)))
    return inner
  z = lax.fori_loop(0, 3, outer, jnp.zeros(3))
  f = jnp.fft.rfft(v, n=12)
  g = conv(x, wg, groups=2)
  dk = jax.grad(lambda k: conv(x, k).sum())(w)
  return y.sum() + z.sum() + jnp.abs(f).sum() + g.sum() + dk.sum()


@pytest.fixture(scope="module")
def tiny_census():
  args = (jax.ShapeDtypeStruct((2, 8, 8, 4), jnp.float32), jax.ShapeDtypeStruct((3, 3, 4, 4), jnp.float32),
          jax.ShapeDtypeStruct((3, 3, 2, 6), jnp.float32), jax.ShapeDtypeStruct((2, 12), jnp.float32))
  lowered = jax.jit(_tiny).trace(*args).lower(lowering_platforms=("cuda",))
  return H.census(lowered.as_text(dialect="hlo", debug_info=True), lowered.as_text(), model="none")


def test_loops_and_trip_counts(tiny_census):
  loops = sorted((r["trips"], r["runs"], r["nested_in_loop"]) for r in tiny_census["loops"])
  assert loops == [(3, 1, False), (5, 3, True), (7, 1, False)]
  assert tiny_census["unknown_trips"] == 0
  assert tiny_census["stablehlo"]["while"] == 3
  scan7 = next(r for r in tiny_census["loops"] if r["trips"] == 7)
  assert scan7["convolution"] == 1


def test_convolutions(tiny_census):
  convs = tiny_census["convolutions"]
  assert len(convs) == tiny_census["stablehlo"]["convolution"]
  in_scan = [r for r in convs if r["runs"] == 7]
  assert len(in_scan) == 1 and in_scan[0]["dim_labels"] == "b01f_01io->b01f"
  grouped = [r for r in convs if r["feature_group_count"] == 2]
  assert len(grouped) == 1 and grouped[0]["out"] == "f32[2,8,8,6]"
  wg = [r for r in convs if r["weight_grad"]]
  assert len(wg) == 1 and wg[0]["window_size"] == (8, 8) and wg[0]["out"] == "f32[3,3,4,4]"
  assert wg[0]["kind"] == "weight gradient"
  # 2 x output x window x input channels: the forward conv in the scan, 2*8*8*4 outputs, 3x3 taps, 4 in
  assert in_scan[0]["gflop"] == pytest.approx(2 * (2 * 8 * 8 * 4) * 9 * 4 / 1e9)


def test_fft_and_the_rest(tiny_census):
  (fft,) = tiny_census["ffts"]
  assert (fft["type"], fft["length"], fft["input"], fft["output"]) == ("RFFT", "12", "f32[2,12]", "c64[2,7]")
  assert tiny_census["f64"] == [] and tiny_census["host"] == []
  s = H.summary(tiny_census)
  assert s["loop_trips"] == 7 + 3 + 3 * 5
  assert s["conv_runs"] == 7 + (len(tiny_census["convolutions"]) - 1)


FIXTURE = """HloModule fixture, entry_computation_layout={()->s32[]}

cond {
  p = (s32[], f32[4]{0}) parameter(0)
  i = s32[] get-tuple-element(p), index=0
  lim = s32[] constant(10)
  ROOT lt = pred[] compare(i, lim), direction=LT
}

body {
  p = (s32[], f32[4]{0}) parameter(0)
  i = s32[] get-tuple-element(p), index=0
  three = s32[] constant(3)
  next = s32[] add(i, three)
  x = f32[4]{0} get-tuple-element(p), index=1
  t = f32[4]{0} transpose(x), dimensions={0}
  ROOT out = (s32[], f32[4]{0}) tuple(next, t)
}

ENTRY main {
  two = s32[] constant(2)
  z = f32[4]{0} constant({0, 0, 0, 0})
  init = (s32[], f32[4]{0}) tuple(two, z)
  w = (s32[], f32[4]{0}) while(init), condition=cond, body=body
  ROOT r = s32[] get-tuple-element(w), index=0
}
"""


def test_hand_written_trip_count():
  """From 2 while < 10 by 3: 2, 5, 8, three trips; the transpose in the body runs three times."""
  c = H.census(FIXTURE)
  assert [(r["trips"], r["runs"]) for r in c["loops"]] == [(3, 1)]
  assert [(r["runs"], r["bytes"]) for r in c["transposes"]] == [(3, 16)]


# An optimised XLA:GPU program written by hand, in the form ``Compiled.as_text()`` prints: a loop of 4
# trips (the count only in its backend_config; its counter starts at a parameter) holding the counter's
# fusion, a fusion reading one row of a buffer, a 3 x 3 cuDNN forward convolution and an RFFT of 11 points; outside
# it, a weight gradient as a forward convolution with an 8 x 8 window, a 3 x 3 backward-filter call, a
# cuBLAS GEMM, an FFT of 16 points and two scatter fusions, one with indices declared unique.
COMPILED = """HloModule jit_step, is_scheduled=true, entry_computation_layout={()->f32[8,16]{1,0}}

%fused_row (param_0: f32[16,8], param_1: s32[]) -> f32[8] {
  %param_0 = f32[16,8]{1,0} parameter(0)
  %param_1 = s32[] parameter(1)
  %zero = s32[] constant(0)
  %ds = f32[1,8]{1,0} dynamic-slice(%param_0, %param_1, %zero), dynamic_slice_sizes={1,8}
  %bc = f32[8]{0} bitcast(%ds)
  ROOT %neg = f32[8]{0} negate(%bc)
}

%wrapped_add (param_0.4: s32[]) -> s32[] {
  %param_0.4 = s32[] parameter(0)
  %one = s32[] constant(1)
  ROOT %add.4 = s32[] add(%param_0.4, %one)
}

%add_f32 (a: f32[], b: f32[]) -> f32[] {
  %a = f32[] parameter(0)
  %b = f32[] parameter(1)
  ROOT %s = f32[] add(%a, %b)
}

%fused_scatter (param_0.2: f32[4,8], param_1.2: s32[6,1], param_2.2: f32[6,8]) -> f32[4,8] {
  %param_0.2 = f32[4,8]{1,0} parameter(0)
  %param_1.2 = s32[6,1]{1,0} parameter(1)
  %param_2.2 = f32[6,8]{1,0} parameter(2)
  ROOT %scatter.1 = f32[4,8]{1,0} scatter(%param_0.2, %param_1.2, %param_2.2), update_window_dims={1}, \
inserted_window_dims={0}, scatter_dims_to_operand_dims={0}, index_vector_dim=1, to_apply=%add_f32
}

%fused_scatter_unique (param_0.3: f32[4,8], param_1.3: s32[6,1], param_2.3: f32[6,8]) -> f32[4,8] {
  %param_0.3 = f32[4,8]{1,0} parameter(0)
  %param_1.3 = s32[6,1]{1,0} parameter(1)
  %param_2.3 = f32[6,8]{1,0} parameter(2)
  ROOT %scatter.2 = f32[4,8]{1,0} scatter(%param_0.3, %param_1.3, %param_2.3), update_window_dims={1}, \
inserted_window_dims={0}, scatter_dims_to_operand_dims={0}, index_vector_dim=1, unique_indices=true, \
to_apply=%add_f32
}

%cond (p.1: (s32[], f32[16,8], f32[1,8,8,2], f32[3,3,2,2], f32[2,11])) -> pred[] {
  %p.1 = (s32[], f32[16,8]{1,0}, f32[1,8,8,2]{3,2,1,0}, f32[3,3,2,2]{3,2,1,0}, f32[2,11]{1,0}) parameter(0)
  %i.1 = s32[] get-tuple-element(%p.1), index=0
  %limit = s32[] constant(4)
  ROOT %lt = pred[] compare(%i.1, %limit), direction=LT
}

%body (p: (s32[], f32[16,8], f32[1,8,8,2], f32[3,3,2,2], f32[2,11])) -> (s32[], f32[16,8], f32[1,8,8,2], \
f32[3,3,2,2], f32[2,11]) {
  %p = (s32[], f32[16,8]{1,0}, f32[1,8,8,2]{3,2,1,0}, f32[3,3,2,2]{3,2,1,0}, f32[2,11]{1,0}) parameter(0)
  %i = s32[] get-tuple-element(%p), index=0
  %next = s32[] fusion(%i), kind=kLoop, calls=%wrapped_add
  %buf = f32[16,8]{1,0} get-tuple-element(%p), index=1
  %row = f32[8]{0} fusion(%buf, %i), kind=kLoop, calls=%fused_row
  %x = f32[1,8,8,2]{3,2,1,0} get-tuple-element(%p), index=2
  %w = f32[3,3,2,2]{3,2,1,0} get-tuple-element(%p), index=3
  %conv = (f32[1,8,8,2]{3,2,1,0}, u8[0]{0}) custom-call(%x, %w), window={size=3x3 pad=1_1x1_1}, \
dim_labels=b01f_01io->b01f, custom_call_target="__cudnn$convForward", \
backend_config={"cudnn_conv_backend_config":{"conv_result_scale":1}}
  %y = f32[1,8,8,2]{3,2,1,0} get-tuple-element(%conv), index=0
  %v = f32[2,11]{1,0} get-tuple-element(%p), index=4
  %f = c64[2,6]{1,0} fft(%v), fft_type=RFFT, fft_length={11}
  ROOT %t = (s32[], f32[16,8]{1,0}, f32[1,8,8,2]{3,2,1,0}, f32[3,3,2,2]{3,2,1,0}, f32[2,11]{1,0}) \
tuple(%next, %buf, %y, %w, %v)
}

ENTRY %main (Arg_0: f32[16,8], Arg_1: f32[1,8,8,2], Arg_2: f32[3,3,2,2], Arg_3: f32[2,11], Arg_4: s32[], \
Arg_5: s32[6,1], Arg_6: f32[6,8], Arg_7: f32[1,10,10,3], Arg_8: f32[8,4], Arg_9: f32[4,16], Arg_10: f32[8,8,3,2], \
Arg_11: c64[2,16], Arg_12: f32[4,8]) -> f32[8,16] {
  %Arg_0 = f32[16,8]{1,0} parameter(0)
  %Arg_1 = f32[1,8,8,2]{3,2,1,0} parameter(1)
  %Arg_2 = f32[3,3,2,2]{3,2,1,0} parameter(2)
  %Arg_3 = f32[2,11]{1,0} parameter(3)
  %Arg_4 = s32[] parameter(4)
  %Arg_5 = s32[6,1]{1,0} parameter(5)
  %Arg_6 = f32[6,8]{1,0} parameter(6)
  %Arg_7 = f32[1,10,10,3]{3,2,1,0} parameter(7)
  %Arg_8 = f32[8,4]{1,0} parameter(8)
  %Arg_9 = f32[4,16]{1,0} parameter(9)
  %Arg_10 = f32[8,8,3,2]{3,2,1,0} parameter(10)
  %Arg_11 = c64[2,16]{1,0} parameter(11)
  %Arg_12 = f32[4,8]{1,0} parameter(12)
  %init = (s32[], f32[16,8]{1,0}, f32[1,8,8,2]{3,2,1,0}, f32[3,3,2,2]{3,2,1,0}, f32[2,11]{1,0}) \
tuple(%Arg_4, %Arg_0, %Arg_1, %Arg_2, %Arg_3)
  %loop = (s32[], f32[16,8]{1,0}, f32[1,8,8,2]{3,2,1,0}, f32[3,3,2,2]{3,2,1,0}, f32[2,11]{1,0}) while(%init), \
condition=%cond, body=%body, backend_config={"known_trip_count":{"n":"4"}}
  %wg = (f32[1,3,3,2]{3,2,1,0}, u8[0]{0}) custom-call(%Arg_7, %Arg_10), window={size=8x8}, \
dim_labels=b01f_01io->b01f, custom_call_target="__cudnn$convForward"
  %bf = (f32[3,3,2,2]{3,2,1,0}, u8[0]{0}) custom-call(%Arg_1, %Arg_1), window={size=3x3 pad=1_1x1_1}, \
dim_labels=b01f_01io->b01f, custom_call_target="__cudnn$convBackwardFilter"
  %sc = f32[4,8]{1,0} fusion(%Arg_12, %Arg_5, %Arg_6), kind=kInput, calls=%fused_scatter
  %scu = f32[4,8]{1,0} fusion(%Arg_12, %Arg_5, %Arg_6), kind=kInput, calls=%fused_scatter_unique
  %fft16 = c64[2,16]{1,0} fft(%Arg_11), fft_type=FFT, fft_length={16}
  %gemm = (f32[8,16]{1,0}, s8[0]{0}) custom-call(%Arg_8, %Arg_9), custom_call_target="__cublas$gemm", \
backend_config={"gemm_backend_config":{"alpha_real":1,"dot_dimension_numbers":{"lhs_contracting_dimensions":["1"],\
"rhs_contracting_dimensions":["0"],"lhs_batch_dimensions":[],"rhs_batch_dimensions":[]}}}
  ROOT %out = f32[8,16]{1,0} get-tuple-element(%gemm), index=0
}
""".replace("\\\n", "")


def test_compiled_census_of_a_hand_written_program():
  """Every count of the hand-written program, by hand: 4 kernels a trip x 4 trips + 6 outside."""
  c = H.compiled_census(COMPILED)
  assert [(r["trips"], r["runs"], r["kernels_per_trip"]) for r in c["loops"]] == [(4, 1, 4)]
  s = H.compiled_summary(c)
  assert (s["kernels_static"], s["kernels_per_step"]) == (10, 22)
  assert s["by_kind"] == {"fusion": 8, "cudnn": 6, "fft": 5, "gemm": 1, "scatter": 2}
  assert s["cudnn_by_target"] == {"__cudnn$convForward": 5, "__cudnn$convBackwardFilter": 1}
  assert (s["cudnn_over_3x3"], s["weight_grad_as_forward"], s["largest_window"]) == (1, 1, (8, 8))
  assert (s["ffts_per_step"], s["fft_lengths"], s["fft_rough"], s["ffts_in_loops"]) == (5, [11, 16], [11], 4)
  assert (s["loops"], s["loop_trips"], s["unknown_trips"]) == (1, 4, 0)
  assert (s["float_atomics"], s["scatters"]) == (1, 2)
  bf = next(r for r in c["cudnn"] if r["target"].endswith("BackwardFilter"))
  assert (bf["input"], bf["filter"], bf["output"]) == ("f32[1,8,8,2]", "f32[3,3,2,2]", "f32[1,8,8,2]")


def test_compiled_flops_bytes_and_roofline():
  """FLOPs: 2 x forward output x window x input channels per convolution, 2MNK per GEMM, 5 N log2 N per
  complex FFT (half for a real one); the row fusion reads one 8-float row of its 16 x 8 buffer."""
  c = H.compiled_census(COMPILED)
  conv3 = 2 * (8 * 8 * 2) * 9 * 2
  flops = 4 * (conv3 + 2 * 5 * 11 * math.log2(11) / 2) + 2 * (3 * 3 * 2) * 64 * 3 + conv3 + 2 * 8 * 16 * 4 \
      + 2 * 5 * 16 * 4
  s = H.compiled_summary(c, {"peak_flops": 1.0, "bandwidth": 1e30})
  assert s["flops"] == pytest.approx(flops) and s["roofline_s"] == pytest.approx(flops)
  row = next(r for r in c["kernels"] if r["name"] == "row")
  assert (row["bytes"], row["runs"], row["in_loop"]) == (8 * 4 + 4 + 8 * 4, 4, True)
  gemm = next(r for r in c["kernels"] if r["name"] == "gemm")
  assert gemm["bytes"] == (8 * 4 + 4 * 16 + 8 * 16) * 4
  s = H.compiled_summary(c, {"peak_flops": 1e30, "bandwidth": 1.0})
  assert s["roofline_s"] == pytest.approx(s["bytes"])
  assert s["bytes"] == sum(r["bytes"] * r["runs"] for r in c["kernels"])


def test_target_facts_read_the_shipped_targets():
  """Peak float32: SMs x FP32 lanes x 2 x clock; bandwidth as the file states it."""
  h100, h200 = (H.target_facts((H.TARGETS_DIR / H.TARGETS[t]).read_text()) for t in ("h100", "h200"))
  assert h100["peak_flops"] == pytest.approx(132 * 128 * 2 * 1.98e9) == h200["peak_flops"]
  assert (h100["bandwidth"], h200["bandwidth"]) == (3.35e12, 4.8e12)
  assert "H100" in h100["name"] and "H200" in h200["name"]


def test_compile_for_a_gpu_target_without_a_gpu():
  """The recipe itself, where the CUDA plugin is installed (never in CI): a tiny jitted function compiled
  for the H200 target holds a cuDNN convolution and no ``convolution`` op."""
  pytest.importorskip("jax_plugins.xla_cuda12")
  if jax.default_backend() != "cpu":
    pytest.skip("needs JAX_PLATFORMS=cpu")
  from jax.experimental import topologies
  from jax.sharding import Mesh, NamedSharding, PartitionSpec
  topo = topologies.get_topology_desc("h200", "cuda", target_config=(H.TARGETS_DIR / "h200.txtpb").read_text(),
                                      topology="1x1x1")
  rep = NamedSharding(Mesh(topo.devices[:1], ("data",)), PartitionSpec())
  conv = lambda a, k: lax.conv_general_dilated(a, k, (1, 1), "SAME",           # noqa: E731
                                               dimension_numbers=("NHWC", "HWIO", "NHWC"))
  args = (jax.ShapeDtypeStruct((2, 16, 16, 8), jnp.float32, sharding=rep),
          jax.ShapeDtypeStruct((3, 3, 8, 8), jnp.float32, sharding=rep))
  text = jax.jit(conv).trace(*args).lower().compile().as_text()
  s = H.compiled_summary(H.compiled_census(text))
  assert s["cudnn_by_target"].get("__cudnn$convForward", 0) == 1 and s["cudnn_over_3x3"] == 0

"""benchmarks.hlo_gpu's census against programs whose loops, convolutions and FFTs are known by construction."""

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

"""experiments.independent_set's stroke-font letters and resolution charts.

Independent references: closed-form areas (unions of capsules for stroked
glyphs, rectangles for the bars chart, discs for the dots chart) against
counts on a fine grid of sample points, mirror symmetries of symmetric
glyphs, rotation invariance of area, and the object parameters a written
file records.
"""

import json
import math
import subprocess
import sys

import h5py
import numpy as np
import pytest

from experiments import configs
from experiments import independent_set as I

N = 1213                      # fine grid: N x N sample points over [-L, L]^2 (a pitch no edge falls on)
L = 0.4                       # m
PITCH = 2 * L / N
G = (np.arange(N) + 0.5) * PITCH - L
V, U = np.meshgrid(G, G, indexing="ij")     # v along rows, u along columns


def area(mask):
  """Area (m^2) of a mask sampled on the fine grid."""
  return float(mask.sum()) * PITCH ** 2


def outline(glyph, height, stroke):
  """Upper bound (m) on a stroked glyph's boundary length: its capsules' perimeters summed.

  The grid count of a region misses its area by at most about a pitch times half its
  boundary length: the sub-pixel bound the area tests use.
  """
  h = stroke * height / 2
  total = 0.0
  for line in I.GLYPHS[glyph]:
    v = np.asarray(line) * height
    total += float(np.sum(2 * np.hypot(*np.diff(v, axis=0).T) + 2 * math.pi * h))
  return total


def test_mix_is_a_distribution_with_letters_a_third_and_every_glyph_drawn():
  assert set(I.KIND_MIX) == set(I.SHAPES) == set(I.SIZE_RANGES)
  assert sum(I.KIND_MIX.values()) == pytest.approx(1.0, abs=1e-12)
  assert {"ring", "cross", "ellipse", "triangle", "ell", "letter", "bars", "dots"} <= set(I.SHAPES)
  assert 0.3 <= I.KIND_MIX["letter"] <= 0.4 and len(I.GLYPHS) >= 10
  rng = np.random.default_rng(0)
  objs = [I.draw_object(rng) for _ in range(3000)]
  kinds = [o["kind"] for o in objs]
  for k, share in I.KIND_MIX.items():           # binomial sd <= 0.009 at n = 3000
    assert kinds.count(k) / len(objs) == pytest.approx(share, abs=0.03), k
  letters = [o for o in objs if o["kind"] == "letter"]
  assert {o["glyph"] for o in letters} == set(I.GLYPHS)
  strokes = np.array([o["stroke"] for o in letters])
  assert strokes.min() >= I.STROKE_RANGE[0] and strokes.max() <= I.STROKE_RANGE[1]
  for kind, (lo, hi) in (("bars", I.BARS_RANGE), ("dots", I.DOTS_RANGE)):
    assert {o["count"] for o in objs if o["kind"] == kind} == set(range(lo, hi + 1))


@pytest.mark.parametrize("stroke", [0.08, 0.18])
def test_letter_l_area_is_two_capsules_less_their_overlap(stroke):
  """L: a stem (length s) and a foot (0.6 s) meeting at a corner, half-width h.

  Capsule areas 2 h len + pi h^2 each; they overlap in 3/4 of the corner disc
  plus the h x h square inside the corner: 2 h (1.6 s) + 5/4 pi h^2 - h^2.
  """
  s = 0.6
  h = stroke * s / 2
  want = 2 * h * 1.6 * s + 1.25 * math.pi * h ** 2 - h ** 2
  got = area(I.shape_mask("letter", U, V, s, 0.0, glyph="L", stroke=stroke))
  assert abs(got - want) <= outline("L", s, stroke) * PITCH / 2
  # The bound is tight enough to tell: forgetting the overlap would miss by more.
  assert outline("L", s, stroke) * PITCH / 2 < (0.75 * math.pi + 1) * h ** 2 / 2


def test_letter_h_area_and_its_mirror_symmetries():
  """H: two stems (length s) and a bar (0.6 s) between their midpoints.

  Area: two capsules 2 (2 h s + pi h^2) plus the bar outside the stems, 2 h (0.6 s - 2 h).
  """
  s, stroke = 0.6, 0.12
  h = stroke * s / 2
  m = I.shape_mask("letter", U, V, s, 0.0, glyph="H", stroke=stroke)
  want = 2 * (2 * h * s + math.pi * h ** 2) + 2 * h * (0.6 * s - 2 * h)
  assert abs(area(m) - want) <= outline("H", s, stroke) * PITCH / 2
  # The grid is symmetric about 0 in u and v, so mirroring is reversing an axis.
  np.testing.assert_array_equal(m, m[:, ::-1])
  np.testing.assert_array_equal(m, m[::-1, :])


def test_letter_t_is_left_right_symmetric_but_not_up_down():
  m = I.shape_mask("letter", U, V, 0.6, 0.0, glyph="T", stroke=0.1)
  np.testing.assert_array_equal(m, m[:, ::-1])
  assert np.mean(m != m[::-1, :]) > 0.02
  # The bar lies at the top (v > 0: q is up in the glyph's frame).
  assert m[V > 0.25].sum() > 3 * m[V < -0.25].sum()


@pytest.mark.parametrize("glyph", ["L", "K", "4", "M"])
def test_rotated_glyph_has_the_unrotated_area(glyph):
  want = area(I.shape_mask("letter", U, V, 0.5, 0.0, glyph=glyph, stroke=0.14))
  for angle in (0.3, 1.0, 2.5):
    got = area(I.shape_mask("letter", U, V, 0.5, angle, glyph=glyph, stroke=0.14))
    assert abs(got - want) <= outline(glyph, 0.5, 0.14) * PITCH, angle


@pytest.mark.parametrize("n", [3, 4, 5])
def test_bars_chart_fills_n_bars_of_equal_bar_and_gap_width(n):
  s = 0.6
  w = s / (2 * n - 1)
  m = I.shape_mask("bars", U, V, s, 0.0, count=n)
  box = (np.abs(U) <= s / 2) & (np.abs(V) <= s / 2)
  assert not np.any(m & ~box)
  # Filled fraction of the s x s box: n w / s, to within a grid pitch on each bar edge.
  frac = m.sum() / box.sum()
  assert abs(frac - n * w / s) <= (2 * n * s + 2 * n * w) * PITCH / s ** 2
  # Crossing the chart along u: n runs of width w separated by gaps of width w.
  row = m[N // 2]
  edges = np.flatnonzero(np.diff(row.astype(int)))
  assert len(edges) == 2 * n
  runs = np.diff(G[edges])                                  # bar, gap, bar, ..., bar
  np.testing.assert_allclose(runs, w, atol=1.5 * PITCH)


@pytest.mark.parametrize("k", [2, 3, 4])
def test_dots_chart_area_is_k_squared_discs(k):
  s = 0.6
  r = I.DOT_RADIUS * s / k
  m = I.shape_mask("dots", U, V, s, 0.7, count=k)
  assert area(m) == pytest.approx(k * k * math.pi * r ** 2, rel=2e-3)
  # k^2 separate discs: count 4-connected components by a flood fill on a coarse copy.
  coarse = m[::4, ::4]
  seen = np.zeros_like(coarse)
  blobs = 0
  for start in zip(*np.nonzero(coarse)):
    if seen[start]:
      continue
    blobs += 1
    stack = [start]
    while stack:
      i, j = stack.pop()
      if 0 <= i < coarse.shape[0] and 0 <= j < coarse.shape[1] and coarse[i, j] and not seen[i, j]:
        seen[i, j] = True
        stack += [(i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)]
  assert blobs == k * k


def test_bad_glyph_and_kind_are_refused():
  with pytest.raises(ValueError, match="glyph"):
    I.shape_mask("letter", U[:2, :2], V[:2, :2], 0.5, 0.0, glyph="?")
  with pytest.raises(ValueError, match="kind"):
    I.shape_mask("star", U[:2, :2], V[:2, :2], 0.5, 0.0)


def test_written_set_holds_every_kind_with_non_empty_masks(tmp_path):
  data = {**configs.get_config("cpu")["data"], "grid": 16, "num_bins": 32, "bin_width": 528e-12}
  path = I.write_independent_set(tmp_path / "ind.h5", data, sequences=12, frames=2, seed=3,
                                 progress=False)
  seen = set()
  with h5py.File(path, "r") as f:
    assert f.attrs["generator_version"] == I.GENERATOR_VERSION
    for g in f["sequences"].values():
      objects = json.loads(g.attrs["objects"])
      assert sum(o["dynamic"] for o in objects) == 1 and objects[-1]["dynamic"]
      for o in objects:
        seen.add(o["kind"])
        assert len(o["rays"]) == 2 and min(o["rays"]) > 0, o
      assert g["intensity"][...].max() > 0
  assert seen == set(I.SHAPES)


def test_scenes_are_drawn_without_the_training_generator_or_matplotlib():
  """Drawing and rendering scenes imports neither nlosjax.data.scenes/surfaces nor matplotlib."""
  code = ("import sys, numpy as np\n"
          "from experiments import independent_set as I\n"
          "from nlosjax.physics import Setup\n"
          "setup = Setup(wall_size=2.0, grid=(8, 8), bin_width=528e-12, num_bins=32)\n"
          "rng = np.random.default_rng(0)\n"
          "kinds = set()\n"
          "for _ in range(12):\n"
          "  kinds |= {o['kind'] for o in I.make_sequence(rng, setup, 1)['objects']}\n"
          "assert 'letter' in kinds, kinds\n"
          "print(sorted(m for m in sys.modules if m.startswith(('matplotlib', 'nlosjax.data'))))\n")
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
  assert out.stdout.strip() == "[]", out.stdout

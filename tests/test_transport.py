"""nlosjax.physics.transport and nlosjax.data.surfaces: the renderer that is not the LCT operator.

Independent references: an explicit loop over scan points and patches written
here from the radiometry (out-leg and back-leg factors multiplied, not the
module's combined formula), exact visibility by ray-segment intersection with
a rectangle, closed-form surface areas (shoelace for outlines, 4 pi r^2, 4 pi^2
R r), and invariants (a convex solid hides nothing from itself but its back).
"""

import math

import numpy as np
import pytest

from nlosjax.data import scenes, surfaces
from nlosjax.physics import Setup
from nlosjax.physics.transport import SurfaceSamples, default_spacing, render_surfaces
from tests.xla_options import xla_optimizations


@pytest.fixture(scope="module", autouse=True)
def _optimised_xla():
  # Programs here run long (full captures, samplers, renderers): XLA's optimisations pay for
  # their compile time. The suite turns them off by default (conftest.py).
  with xla_optimizations(True):
    yield


SETUP = Setup(wall_size=0.8, grid=(6, 6), bin_width=32e-12, num_bins=200)


def loop_transient(samples: SurfaceSamples, setup: Setup, visible=None) -> np.ndarray:
  """Brute force: for each scan point and patch, the two legs of the confocal path."""
  H, W = setup.grid
  out = np.zeros((setup.num_bins, H, W))
  dy, dx = setup.spacing
  for i in range(H):
    for j in range(W):
      s = np.array([setup.scan_x[j], setup.scan_y[i], 0.0])
      for n, p in enumerate(samples.points):
        d = p - s
        r = np.linalg.norm(d)
        toward_s = -d / r
        cos_p = float(toward_s @ samples.normals[n])
        if samples.two_sided[n]:
          cos_p = abs(cos_p)
        if cos_p <= 1e-3 or (visible is not None and not visible(s, p)):
          continue
        cos_w = d[2] / r
        # Out: the laser spot (Lambertian wall) irradiates the patch: cos_w cos_p / r^2.
        irradiance = cos_w * cos_p / r ** 2
        if samples.retroreflective[n]:
          back = 1.0                    # sent straight back: no second spread or cosine
        else:
          back = cos_p * cos_w / r ** 2  # a Lambertian patch seen from the wall spot
        k = int(2 * r // setup.bin_length)
        if k < setup.num_bins:
          out[k, i, j] += samples.albedo[n] * samples.area[n] * irradiance * back / (dy * dx)
  return out


def random_patches(rng, n=60):
  pts = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(0.3, 1.2, n)], 1)
  nrm = rng.normal(size=(n, 3))
  nrm[:, 2] = -np.abs(nrm[:, 2]) * rng.choice([1, 1, 1, -1], n)  # mostly facing the wall
  nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
  return SurfaceSamples(pts, nrm, rng.uniform(1e-4, 4e-4, n), rng.uniform(0.1, 1, n),
                        rng.uniform(size=n) < 0.3, rng.uniform(size=n) < 0.3, 0)


def test_render_surfaces_matches_the_loop_without_occlusion():
  s = random_patches(np.random.default_rng(0))
  got = render_surfaces(s, SETUP, occlusion=False)
  want = loop_transient(s, SETUP)
  assert want.sum() > 0
  np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-6 * want.max())


def test_wall_cosine_off_and_retroreflective_falloff():
  """One patch straight in front of a scan point: r^-4 diffuse and r^-2 retroreflective, exactly."""
  setup = Setup(wall_size=0.8, grid=(5, 5), bin_width=32e-12, num_bins=200)
  z = 0.7
  for retro, power in ((False, 4), (True, 2)):
    s = SurfaceSamples([[0.0, 0.0, z]], [[0, 0, -1.0]], 1e-4, 0.5, retro, False, 0)
    y = render_surfaces(s, setup, occlusion=False, wall_cosine=False)
    dy, dx = setup.spacing
    k = int(2 * z // setup.bin_length)
    assert y[k, 2, 2] == pytest.approx(0.5 * 1e-4 / z ** power / (dy * dx), rel=1e-5)


def plates():
  """A large back plate at 0.6 m and a small front plate at 0.35 m hiding part of it."""
  a = 0.01
  parts = []
  for z, half, cx in ((0.6, 0.25, 0.0), (0.35, 0.08, 0.05)):
    u = np.arange(-half + a / 2, half, a)
    X, Y = np.meshgrid(u + cx, u, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], 1)
    parts.append(SurfaceSamples(pts, np.tile([0, 0, -1.0], (X.size, 1)), a * a, 0.7, False, True,
                                len(parts)))
  return SurfaceSamples.concatenate(parts)


def hidden_by_front_plate(s, p):
  """Exact: does the open segment s -> p cross the front plate (z 0.35, |x - 0.05|, |y| <= 0.08)?"""
  if p[2] <= 0.35 + 1e-9:
    return False
  t = 0.35 / p[2]
  q = s + t * (p - s)
  return abs(q[0] - 0.05) <= 0.08 and abs(q[1]) <= 0.08


def test_occlusion_matches_exact_visibility():
  s = plates()
  exact = loop_transient(s, SETUP, visible=lambda sp, p: not hidden_by_front_plate(sp, p))
  seen_all = loop_transient(s, SETUP)
  got = render_surfaces(s, SETUP)
  err = np.abs(got - exact).sum() / exact.sum()
  ignored = np.abs(seen_all - exact).sum() / exact.sum()
  # The hidden part of the back plate is a real share of the signal; the z-buffer removes it,
  # leaving an error confined to the front plate's silhouette.
  assert ignored > 0.08
  assert err < 0.1 * ignored, (err, ignored)


def test_padding_buckets_change_nothing_and_compile_few_programs(monkeypatch):
  from nlosjax.physics import transport
  # Few buckets: 2048 * 2^k or 3072 * 2^k patches, cells a multiple of 128.
  assert [transport._padded_patches(n) for n in (1, 2048, 2049, 3073, 5000, 22528)] == \
      [2048, 2048, 3072, 4096, 6144, 24576]
  assert [transport._padded_cells(n) for n in (1, 128, 129, 320, 510)] == [128, 128, 256, 384, 512]
  s = plates()
  got = render_surfaces(s, SETUP)
  # Other paddings (more patches that carry nothing, more empty z-buffer cells): the same sums.
  monkeypatch.setattr(transport, "_PATCH_BUCKET", 4096 + 1024)
  monkeypatch.setattr(transport, "_CELL_BUCKET", 32 * 7)
  np.testing.assert_array_equal(render_surfaces(s, SETUP), got)


@pytest.mark.parametrize("kind", ["sphere", "box", "plate"])
def test_convex_objects_hide_nothing_but_their_back(kind):
  """Occlusion on or off gives the same transient for one convex object (or a plate)."""
  params = scenes.SceneParams(num_static=(0, 0), kinds=(kind,), dynamic_kinds=(kind,),
                              size_range=(0.3, 0.4), depth_range=(0.5, 1.0))
  setup = Setup(wall_size=1.0, grid=(6, 6), bin_width=48e-12, num_bins=160)
  scene = scenes.make_scene(3, params, 1, setup=setup)
  y_occ = surfaces.render_scene(scene, setup, spacing=0.012)
  y_all = surfaces.render_scene(scene, setup, spacing=0.012, occlusion=False)
  assert y_all.sum() > 0
  assert np.abs(y_occ - y_all).sum() / y_all.sum() < 1e-3


def _shoelace(poly):
  x, y = poly[:, 0], poly[:, 1]
  return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def test_sampled_areas_match_closed_forms():
  ident = np.eye(3)
  tex = {"name": "uniform", "albedo": 0.5}

  def obj(kind, shape, radius=0.3):
    return scenes.SceneObject(kind=kind, anchor=np.array([0.0, 0.0, 1.0]), rotation=ident,
                              size=0.4, radius=radius, shape=shape, texture=tex)

  sphere = surfaces.object_samples(obj("sphere", {"radius": 0.2}), 0.01)
  assert sphere.area.sum() == pytest.approx(4 * math.pi * 0.2 ** 2, rel=1e-9)
  np.testing.assert_allclose(sphere.normals, (sphere.points - [0, 0, 1]) / 0.2, atol=1e-12)
  torus = surfaces.object_samples(obj("torus", {"major": 0.15, "minor": 0.05}), 0.01)
  assert torus.area.sum() == pytest.approx(4 * math.pi ** 2 * 0.15 * 0.05, rel=1e-9)
  half = np.array([0.1, 0.05, 0.02])
  box = surfaces.object_samples(obj("box", {"half_extents": half}), 0.01)
  assert box.area.sum() == pytest.approx(8 * (half[0] * half[1] + half[1] * half[2]
                                              + half[0] * half[2]), rel=1e-9)
  for char in "AO8":
    polys = tuple(p * 0.4 for p in scenes.glyph_polygons(char))
    # Even-odd rule: holes subtract (outlines nest at most one deep in these glyphs).
    areas = sorted((_shoelace(p) for p in polys), reverse=True)
    want = areas[0] - sum(areas[1:])
    got = surfaces.object_samples(obj("letter", {"char": char, "polygons": polys}), 0.004)
    assert got.area.sum() == pytest.approx(want, rel=0.03), char
    assert np.all(got.two_sided) and np.all(got.normals[:, 2] < 0)


def test_materials_are_drawn_apart_from_the_scene():
  params = scenes.SceneParams(num_static=(2, 2))
  scene = scenes.make_scene(5, params, 2)
  assert not surfaces.object_materials(scene, 0.0).any()
  assert surfaces.object_materials(scene, 1.0).all()
  again = scenes.make_scene(5, params, 2)
  assert again.describe() == scene.describe()
  with pytest.raises(ValueError, match="probability"):
    surfaces.object_materials(scene, 1.5)


def test_transport_differs_from_the_lct_renderer_but_sees_the_same_scene():
  """Not the LCT operator: cosines and visibility change the transient; same scene, so the
  returns arrive at the same times (high correlation, not equality)."""
  from nlosjax.physics import render
  setup = Setup(wall_size=1.0, grid=(8, 8), bin_width=64e-12, num_bins=96)
  params = scenes.SceneParams(num_static=(1, 1), depth_range=(0.4, 0.9), size_range=(0.2, 0.3))
  scene = scenes.make_scene(2, params, 1, setup=setup)
  y = surfaces.render_scene(scene, setup)[0]
  vol = scenes.rasterize(scene, setup, supersample=4).volume(setup)
  x = np.asarray(render(vol[0], setup))
  c = np.corrcoef(y.ravel(), x.ravel())[0, 1]
  assert 0.6 < c < 0.999, c


def test_bad_input():
  with pytest.raises(ValueError, match="front of the wall"):
    SurfaceSamples([[0, 0, -1.0]], [[0, 0, 1.0]], 1e-4, 0.5, False, False, 0)
  with pytest.raises(ValueError, match="unit"):
    SurfaceSamples([[0, 0, 1.0]], [[0, 0, 2.0]], 1e-4, 0.5, False, False, 0)
  with pytest.raises(ValueError, match="finite"):
    SurfaceSamples([[0, 0, np.nan]], [[0, 0, 1.0]], 1e-4, 0.5, False, False, 0)
  with pytest.raises(ValueError, match="spacing"):
    surfaces.object_samples(scenes.make_scene(0, None, 1).objects[0], 0.0)
  empty = SurfaceSamples.concatenate([])
  assert render_surfaces(empty, SETUP).shape == (SETUP.num_bins, 6, 6)
  assert 0 < default_spacing(SETUP) <= SETUP.depth_bin_length / 2


@pytest.mark.parametrize("deform", [(0.0, 0.0), (0.3, 0.4)])
def test_moving_sampled_patches_equals_sampling_the_posed_scene(deform):
  """render_scene samples each object once and moves the patches per frame; sampling the
  object at its pose of that frame (line motion and spin) gives the same transient. A
  deforming planar object (non-rigid motion) is sampled at each frame's shape instead."""
  params = scenes.SceneParams(num_static=(1, 1), motions=("line",), spin_speed=(1.0, 2.0),
                              depth_range=(0.5, 1.0), size_range=(0.2, 0.3), deform=deform,
                              dynamic_kinds=("letter", "bars", "dots"))
  setup = Setup(wall_size=1.0, grid=(6, 6), bin_width=48e-12, num_bins=160)
  scene = scenes.make_scene(4, params, 4, setup=setup)
  got = surfaces.render_scene(scene, setup, frames=[3], spacing=0.015, retroreflective=0.5)[0]
  want = render_surfaces(surfaces.scene_samples(scene, 3, 0.015, retroreflective=0.5), setup,
                         spacing=0.015)
  np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6 * want.max())

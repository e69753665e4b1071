"""Procedural scenes (nlosjax.data.scenes): geometry of the ray cast, the helix, bounds, seeds.

Independent references: closed forms of the projected shapes (sphere, box,
torus, planar glyph), the helix equation written out here, and bounding
geometry of the drawn scenes.
"""

import math

import numpy as np
import pytest

from nlosjax.data import scenes
from nlosjax.data.scenes import Helix, Scene, SceneObject, SceneParams
from nlosjax.data.scenes import raster as scene_raster
from nlosjax.physics import Setup

# 2 m wall, 41 x 41 scan points (5 cm apart, a point at the wall centre), 2.53 m of depth.
SETUP = Setup(wall_size=2.0, grid=(41, 41), bin_width=132e-12, num_bins=128)
DZ = SETUP.depth_bin_length


def still_scene(*objects):
  """A scene of the given objects plus a far-away, motionless dynamic sphere (not drawn)."""
  helix = Helix(np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]),
                0.0, 0.0, 0.0, 0.0)
  dyn = SceneObject("sphere", helix.center, np.eye(3), 0.1, 0.05, {"radius": 0.05},
                    {"name": "uniform", "albedo": 1.0}, dynamic=True)
  return Scene(objects=tuple(objects) + (dyn,), helix=helix, num_frames=1, frame_rate=1.0, seed=0)


def obj(kind, anchor, shape, radius, rotation=None, albedo=0.8):
  rotation = np.eye(3) if rotation is None else rotation
  return SceneObject(kind, np.asarray(anchor, float), rotation, 2 * radius, radius, shape,
                     {"name": "uniform", "albedo": albedo})


def draw(scene, objects=(0,), supersample=1):
  return scenes.rasterize(scene, SETUP, objects=list(objects), supersample=supersample)


# ------------------------------------------------------------- ray casting
def test_sphere_depth_and_shading_match_the_closed_form():
  r, c = 0.3, np.array([0.1, -0.05, 1.0])
  out = draw(still_scene(obj("sphere", c, {"radius": r}, r)))
  X, Y = np.meshgrid(SETUP.scan_x, SETUP.scan_y)
  rho2 = (X - c[0]) ** 2 + (Y - c[1]) ** 2
  inside = rho2 < r * r
  expected_depth = c[2] - np.sqrt(np.where(inside, r * r - rho2, 0.0))
  ray = out.ray_depth[0, 0]
  np.testing.assert_array_equal(np.isfinite(ray), inside)
  np.testing.assert_allclose(ray[inside], expected_depth[inside], atol=1e-6)
  np.testing.assert_allclose(out.depth[0][inside], expected_depth[inside], atol=1e-6)
  assert np.all(out.depth[0][~inside] == scenes.BACKGROUND_DEPTH)
  # Lambertian |n_z| = sqrt(r^2 - rho^2) / r, times albedo 0.8.
  np.testing.assert_allclose(out.ray_albedo[0, 0][inside],
                             0.8 * np.sqrt(r * r - rho2[inside]) / r, atol=1e-6)
  assert out.intensity.max() == pytest.approx(1.0)


def test_box_facing_the_wall_is_a_flat_rectangle():
  half = np.array([0.2, 0.1, 0.15])
  c = np.array([0.0, 0.0, 0.9])
  out = draw(still_scene(obj("box", c, {"half_extents": half}, float(np.linalg.norm(half)))),
             supersample=4)
  X, Y = np.meshgrid(SETUP.scan_x, SETUP.scan_y)
  covered = np.isfinite(out.ray_depth[0]).mean(0)
  # Supersampled coverage integrates the 0.4 m x 0.2 m face: area / pixel area.
  dy, dx = SETUP.spacing
  assert covered.sum() == pytest.approx((4 * half[0] * half[1]) / (dx * dy), rel=0.02)
  hit = covered > 0
  np.testing.assert_allclose(out.depth[0][hit], c[2] - half[2], atol=1e-9)
  fully = (np.abs(X - c[0]) < half[0] - dx) & (np.abs(Y - c[1]) < half[1] - dy)
  assert np.all(covered[fully] == 1.0)


def test_torus_has_a_hole_and_its_ring_is_nearest_at_the_major_radius():
  major, minor = 0.25, 0.08
  c = np.array([0.0, 0.0, 1.2])
  out = draw(still_scene(obj("torus", c, {"major": major, "minor": minor}, major + minor)))
  ray = out.ray_depth[0, 0]
  X, Y = np.meshgrid(SETUP.scan_x, SETUP.scan_y)
  rho = np.hypot(X - c[0], Y - c[1])
  ring = np.abs(rho - major) < minor
  np.testing.assert_array_equal(np.isfinite(ray), ring)
  expected = c[2] - np.sqrt(np.maximum(minor ** 2 - (rho - major) ** 2, 0.0))
  np.testing.assert_allclose(ray[ring], expected[ring], atol=1e-5)
  assert not np.isfinite(ray[20, 20])  # the wall centre looks through the hole


def test_glyphs_follow_the_even_odd_rule():
  o, i = scenes.glyph_polygons("O"), scenes.glyph_polygons("I")
  assert len(o) == 2 and len(i) == 1
  inside = scenes.inside_polygons
  assert not inside(np.zeros(1), np.zeros(1), o)[0]   # the hole of the O
  assert inside(np.zeros(1), np.zeros(1), i)[0]
  pts = np.concatenate(o)
  assert np.max(pts.max(0) - pts.min(0)) == pytest.approx(1.0)
  with pytest.raises(ValueError, match="char"):
    scenes.glyph_polygons("é")


def test_planar_letter_is_flat_at_its_depth_and_has_its_hole():
  size, z = 0.8, 1.1
  polys = tuple(p * size for p in scenes.glyph_polygons("O"))
  letter = SceneObject("letter", np.array([0.0, 0.0, z]), np.eye(3), size, size / math.sqrt(2),
                       {"char": "O", "polygons": polys}, {"name": "uniform", "albedo": 1.0})
  out = draw(still_scene(letter))
  hit = np.isfinite(out.ray_depth[0, 0])
  assert hit.sum() > 20
  np.testing.assert_allclose(out.ray_depth[0, 0][hit], z, atol=1e-9)
  assert not hit[20, 20]
  # Facing the wall: shading is the albedo.
  np.testing.assert_allclose(out.ray_albedo[0, 0][hit], 1.0)


def test_nearer_objects_occlude_farther_ones():
  near = obj("sphere", [0.0, 0.0, 0.8], {"radius": 0.1}, 0.1, albedo=0.5)
  far = obj("box", [0.0, 0.0, 1.3], {"half_extents": np.array([0.3, 0.3, 0.1])}, 0.45, albedo=1.0)
  out = draw(still_scene(near, far), objects=(0, 1))
  assert out.depth[0][20, 20] == pytest.approx(0.7, abs=1e-6)
  assert out.depth[0][20, 25] == pytest.approx(1.2, abs=1e-6)  # x = 0.25 m


def test_volume_puts_each_ray_in_its_depth_bin_and_sums_to_the_intensity():
  scene = scenes.make_scene(3, num_frames=2, setup=SETUP)
  out = scenes.rasterize(scene, SETUP, supersample=2)
  vol = out.volume(SETUP)
  assert vol.shape == (2, SETUP.num_bins) + SETUP.grid and vol.dtype == np.float32
  col = vol.sum(1)
  np.testing.assert_allclose(col / col.max(axis=(1, 2), keepdims=True), out.intensity, atol=1e-5)
  # Independent binning of every ray: floor(z / (c dt / 2)).
  z, a = out.ray_depth[0], out.ray_albedo[0]
  ok = np.isfinite(z)
  k = np.floor(z[ok] / DZ).astype(int)
  ii, jj = np.nonzero(ok)[1:]
  ref = np.zeros(vol.shape[1:])
  np.add.at(ref, (k, ii, jj), a[ok] / 4)
  np.testing.assert_allclose(vol[0], ref, atol=1e-6)


# -------------------------------------------------------------------- helix
def helix_reference(h, t):
  """p(t) = c + r (cos th u + sin th (a x u)) + pitch (th - phase) / 2 pi a."""
  th = h.phase + h.angular_speed * np.asarray(t)
  v = np.cross(h.axis, h.ref)
  return np.array([h.center + h.radius * (math.cos(x) * h.ref + math.sin(x) * v)
                   + h.pitch * (x - h.phase) / (2 * math.pi) * h.axis for x in th])


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_trajectory_is_the_drawn_helix(seed):
  scene = scenes.make_scene(seed, num_frames=32)
  h = scene.helix
  traj = scene.trajectory
  np.testing.assert_allclose(traj, helix_reference(h, scene.times), atol=1e-12)
  assert abs(np.linalg.norm(h.axis) - 1) < 1e-12 and abs(h.axis @ h.ref) < 1e-12
  # Constant distance r from the axis; axial position linear in time.
  rel = traj - h.center
  axial = rel @ h.axis
  radial = np.linalg.norm(rel - axial[:, None] * h.axis, axis=1)
  np.testing.assert_allclose(radial, h.radius, atol=1e-12)
  slope = np.polyfit(scene.times, axial, 1)[0]
  assert slope == pytest.approx(h.pitch * h.angular_speed / (2 * math.pi), abs=1e-12)
  p = SceneParams()
  assert p.helix_speed[0] <= abs(h.angular_speed) <= p.helix_speed[1]


def test_dynamic_object_footprint_moves_with_the_trajectory_and_statics_stay_put():
  params = SceneParams(dynamic_kinds=("sphere", "box", "letter"), helix_radius=(0.2, 0.25),
                       helix_speed=(1.0, 1.5))
  for seed in range(3):
    scene = scenes.make_scene(seed, params, num_frames=12, setup=SETUP)
    dyn = scene.dynamic_index
    moving = scenes.rasterize(scene, SETUP, objects=[dyn], supersample=4)
    cover = np.isfinite(moving.ray_depth).mean(1)                 # [F, H, W]
    X, Y = np.meshgrid(SETUP.scan_x, SETUP.scan_y)
    area = cover.sum((1, 2))
    cx = (cover * X).sum((1, 2)) / area
    cy = (cover * Y).sum((1, 2)) / area
    offset = np.stack([cx, cy], 1) - scene.trajectory[:, :2]
    # Rigid translation: the footprint centroid keeps a fixed offset from the anchor.
    assert np.abs(offset - offset.mean(0)).max() < 0.25 * SETUP.spacing[0], offset
    assert np.ptp(scene.trajectory[:, 0]) + np.ptp(scene.trajectory[:, 1]) > 0.1
    zmean = np.nanmean(np.where(np.isfinite(moving.ray_depth), moving.ray_depth, np.nan), axis=(1, 2, 3))
    dz = zmean - scene.trajectory[:, 2]
    assert np.abs(dz - dz.mean()).max() < 0.03
    statics = [i for i in range(len(scene.objects)) if i != dyn]
    still = scenes.rasterize(scene, SETUP, objects=statics)
    assert np.all(still.depth == still.depth[:1]) and np.all(still.intensity == still.intensity[:1])


# ------------------------------------------------------------- draws, bounds
def test_same_seed_same_scene_other_seed_other_scene():
  a = scenes.make_scene(11, num_frames=4).describe()
  b = scenes.make_scene(11, num_frames=4).describe()
  c = scenes.make_scene(12, num_frames=4).describe()
  assert a == b and a != c
  assert a["generator_version"] == scenes.GENERATOR_VERSION


def test_drawn_scenes_stay_in_their_box():
  p = SceneParams()
  seen = set()
  for seed in range(60):
    scene = scenes.make_scene(seed, p, num_frames=16, setup=SETUP)
    statics = [o for o in scene.objects if not o.dynamic]
    assert p.num_static[0] <= len(statics) <= p.num_static[1]
    assert scene.objects[-1].dynamic and scene.dynamic_index == len(scene.objects) - 1
    for o in statics:
      assert p.depth_range[0] - 1e-9 <= o.anchor[2] - o.radius
      assert o.anchor[2] + o.radius <= p.depth_range[1] + 1e-9
      assert np.all(np.abs(o.anchor[:2]) <= p.lateral_extent + 1e-9)
    r = scene.objects[-1].radius
    traj = scene.trajectory
    assert np.all(traj[:, 2] - r >= p.depth_range[0] - 1e-9)
    assert np.all(traj[:, 2] + r <= p.depth_range[1] + 1e-9)
    assert np.all(np.abs(traj[:, :2]) <= p.lateral_extent + 1e-9)
    seen.update(o.kind for o in scene.objects)
    seen.update(o.texture["name"] for o in scene.objects)
  assert set(scenes.DEFAULT_KINDS) <= seen and set(scenes.TEXTURES) <= seen
  assert not set(scenes.CHART_KINDS) & seen          # charts only when a scene's kinds name them


def test_rasterized_maps_have_documented_ranges_and_dtypes():
  scene = scenes.make_scene(5, num_frames=3, setup=SETUP)
  out = scenes.rasterize(scene, SETUP, supersample=2)
  assert out.intensity.shape == (3, 41, 41) and out.intensity.dtype == np.float32
  assert out.intensity.min() >= 0 and np.allclose(out.intensity.max((1, 2)), 1.0)
  fg = out.depth != scenes.BACKGROUND_DEPTH
  assert np.all(out.intensity[~fg] == 0)
  assert out.depth[fg].min() >= 0.5 - 1e-6 and out.depth[fg].max() <= 1.5 + 1e-6


def test_bad_parameters_name_the_argument():
  with pytest.raises(ValueError, match="kinds"):
    SceneParams(kinds=("cube",))
  with pytest.raises(ValueError, match="size_range"):
    SceneParams(size_range=(0.5, 2.0))
  with pytest.raises(ValueError, match="depth_range"):
    SceneParams(depth_range=(1.0, 0.5))
  with pytest.raises(ValueError, match="unknown scene parameter"):
    SceneParams.from_dict({"colour": 1})
  with pytest.raises(ValueError, match="maximum depth"):
    scenes.make_scene(0, SceneParams(depth_range=(0.5, 3.0), size_range=(0.2, 0.4)), 2, setup=SETUP)
  with pytest.raises(ValueError, match="num_frames"):
    scenes.make_scene(0, num_frames=0)
  with pytest.raises(ValueError, match="frames"):
    scenes.rasterize(scenes.make_scene(0, num_frames=2), SETUP, frames=[2])
  assert SceneParams.from_dict(SceneParams().to_dict()) == SceneParams()


# ------------------------------------------------------- later options
def test_default_scenes_do_not_depend_on_the_later_options_and_to_dict_omits_them():
  """Adding albedo_range / motions / spin_speed changed no default scene (files stay valid)."""
  d = SceneParams().to_dict()
  assert not {"albedo_range", "motions", "spin_speed"} & set(d)
  assert SceneParams.from_dict(d) == SceneParams()
  a = scenes.make_scene(7, SceneParams(), 4)
  b = scenes.make_scene(7, SceneParams(motions=("helix",), albedo_range=(0.5, 1.0)), 4)
  assert a.describe() == b.describe() and a.motion == "helix"
  wide = SceneParams(albedo_range=(0.05, 1.0), motions=("helix", "line"), spin_speed=(0.5, 1.0))
  assert SceneParams.from_dict(wide.to_dict()) == wide
  # Charts, font weights and non-rigid motion (added later still) change no default scene either.
  assert not {"glyph_weights", "deform"} & set(d) and SceneParams().kinds == scenes.DEFAULT_KINDS
  c = scenes.make_scene(7, SceneParams(glyph_weights=("bold",), deform=(0.0, 0.0)), 4)
  assert a.describe() == c.describe() and not c.deforms
  new = SceneParams(kinds=scenes.KINDS, glyph_weights=scenes.GLYPH_WEIGHTS, deform=(0.1, 0.3))
  assert SceneParams.from_dict(new.to_dict()) == new


def test_line_motion_is_a_straight_constant_velocity_path_inside_the_box():
  params = SceneParams(motions=("line",))
  for seed in range(4):
    scene = scenes.make_scene(seed, params, 9, setup=SETUP)
    assert scene.motion == "line"
    traj = scene.trajectory
    step = np.diff(traj, axis=0)
    np.testing.assert_allclose(step, np.broadcast_to(step[0], step.shape), atol=1e-12)
    r = scene.objects[scene.dynamic_index].radius
    assert np.all(traj[:, 2] - r >= params.depth_range[0] - 1e-12)
    assert np.all(traj[:, 2] + r <= params.depth_range[1] + 1e-12)
    assert np.all(np.abs(traj[:, :2]) <= params.lateral_extent + 1e-12)
  mixed = [scenes.make_scene(s, SceneParams(motions=("helix", "line")), 2).motion for s in range(20)]
  assert set(mixed) == {"helix", "line"}


def test_spin_turns_the_dynamic_object_about_its_anchor():
  """A spinning plate's footprint changes shape between frames while its anchor's does not
  move (zero path); statics do not turn; rotation(f) is the axis-angle turn of speed * t."""
  params = SceneParams(num_static=(1, 1), dynamic_kinds=("plate",), helix_radius=(0.0, 0.0),
                       helix_pitch=(0.0, 0.0), spin_speed=(1.0, 1.0))
  scene = scenes.make_scene(3, params, 5, setup=SETUP)
  i = scene.dynamic_index
  np.testing.assert_allclose(scene.trajectory, np.broadcast_to(scene.trajectory[0], (5, 3)), atol=1e-12)
  R0, R4 = scene.rotation(i, 0), scene.rotation(i, 4)
  angle = math.acos(np.clip((np.trace(R4 @ R0.T) - 1) / 2, -1, 1))
  assert angle == pytest.approx(4 / scene.frame_rate * abs(scene.spin_speed), abs=1e-9)
  np.testing.assert_allclose((R4 @ R0.T) @ scene.spin_axis, scene.spin_axis, atol=1e-12)
  static = 1 - i
  np.testing.assert_array_equal(scene.rotation(static, 4), scene.objects[static].rotation)
  cover = np.isfinite(scenes.rasterize(scene, SETUP, objects=[i], supersample=2).ray_depth).mean(1)
  assert np.abs(cover[0] - cover[4]).sum() > 1.0


def test_albedo_range_sets_the_base_albedo():
  params = SceneParams(albedo_range=(0.05, 0.1), num_static=(3, 3), texture_probability=0.0,
                       kinds=("sphere",), dynamic_kinds=("sphere",), size_range=(0.2, 0.25))
  scene = scenes.make_scene(0, params, 1)
  assert all(0.05 <= o.texture["albedo"] <= 0.1 for o in scene.objects)
  with pytest.raises(ValueError, match="albedo_range"):
    SceneParams(albedo_range=(0.0, 1.0))
  with pytest.raises(ValueError, match="motions"):
    SceneParams(motions=("zigzag",))


# ------------------------------------------- charts, thin glyphs, non-rigid motion
def shoelace(poly):
  x, y = poly[:, 0], poly[:, 1]
  return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def covered_area(polygons, step=2e-3):
  """Brute force: the even-odd area of outlines counted on a fine grid (m^2)."""
  pts = np.concatenate(polygons)
  u = np.arange(pts[:, 0].min(), pts[:, 0].max(), step) + step / 2
  v = np.arange(pts[:, 1].min(), pts[:, 1].max(), step) + step / 2
  U, V = np.meshgrid(u, v)
  return scenes.inside_polygons(U.ravel(), V.ravel(), polygons).sum() * step * step


def test_bar_chart_has_equal_bars_and_gaps_of_the_closed_form_area():
  size, fill = 0.5, 0.8
  for count in (3, 4, 6):
    polys = scenes.chart_polygons("bars", count, size, fill)
    width = size / (2 * count - 1)
    assert len(polys) == count
    assert covered_area(polys) == pytest.approx(count * width * fill * size, rel=0.02)
    # Across the middle: count runs of width w, separated by gaps of width w, spanning `size`.
    u = np.linspace(-size / 2 + 1e-4, size / 2 - 1e-4, 4001)
    inside = scenes.inside_polygons(u, np.zeros_like(u), polys)
    edges = np.flatnonzero(np.diff(inside.astype(int)))
    assert inside[0] and inside[-1] and len(edges) == 2 * (count - 1)
    np.testing.assert_allclose(np.diff(u[edges]), width, atol=2 * (u[1] - u[0]))


def test_dot_chart_is_a_grid_of_discs_of_the_circles_area():
  size, fill, count = 0.4, 0.6, 3
  polys = scenes.chart_polygons("dots", count, size, fill)
  r = fill * size / count / 2
  assert len(polys) == count * count
  np.testing.assert_allclose([shoelace(p) for p in polys], math.pi * r * r, rtol=1e-12)
  assert covered_area(polys, 1e-3) == pytest.approx(count * count * math.pi * r * r, rel=0.02)
  centres = np.array([p.mean(0) for p in polys])
  pitch = size / count
  assert sorted(set(np.round(centres[:, 0] / pitch, 6))) == [-1.0, 0.0, 1.0]


def test_chart_facing_the_wall_covers_its_area_on_the_scan_grid():
  """A fronto-parallel bar chart at 1 m: ray-cast coverage x pixel area = its closed-form area."""
  size, fill, count = 0.9, 0.9, 3
  polys = scenes.chart_polygons("bars", count, size, fill)
  chart = SceneObject("bars", np.array([0.0, 0.0, 1.0]), np.eye(3), size, 0.64,
                      {"count": count, "fill": fill, "polygons": polys}, {"name": "uniform", "albedo": 1.0})
  out = draw(still_scene(chart), supersample=8)
  dy, dx = SETUP.spacing
  area = np.isfinite(out.ray_depth[0]).mean(0).sum() * dx * dy
  assert area == pytest.approx(count * size / (2 * count - 1) * fill * size, rel=0.03)


def test_regular_glyphs_have_thinner_strokes_than_bold():
  for char in "EHL7":
    bold = covered_area(scenes.glyph_polygons(char, "bold"), 2e-3)
    regular = covered_area(scenes.glyph_polygons(char, "regular"), 2e-3)
    assert regular < 0.8 * bold, char
  with pytest.raises(ValueError, match="weight"):
    scenes.glyph_polygons("E", "light")


def deforming_scene(kind="letter", seed=3, frames=6):
  params = SceneParams(num_static=(1, 1), dynamic_kinds=(kind,), deform=(0.3, 0.4),
                       helix_speed=(1.0, 1.5), texture_probability=1.0)
  return scenes.make_scene(seed, params, frames, setup=SETUP)


def test_deformation_is_an_area_keeping_stretch_of_the_drawn_amplitude():
  scene = deforming_scene()
  i = scene.dynamic_index
  assert scene.deforms and 0.3 <= scene.deform_amplitude <= 0.4
  for f in range(scene.num_frames):
    M = scene.deformation(i, f)
    s = scene.deform_amplitude * math.sin(scene.deform_speed * f / scene.frame_rate + scene.deform_phase)
    np.testing.assert_allclose(M, M.T, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(M), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.eigvalsh(M), sorted([math.exp(s), math.exp(-s)]), atol=1e-12)
    direction = np.array([math.cos(scene.deform_angle), math.sin(scene.deform_angle)])
    np.testing.assert_allclose(M @ direction, math.exp(s) * direction, atol=1e-12)
  static = 1 - i
  np.testing.assert_array_equal(scene.deformation(static, 2), np.eye(2))
  assert "warp" not in scene.posed(static, 2).shape
  assert scene.describe()["deform"]["amplitude"] == scene.deform_amplitude
  # The stretched object stays in the scene box: its bounding radius covers the largest stretch.
  r = scene.objects[i].radius
  outline = np.concatenate(scene.objects[i].shape["polygons"])
  assert np.max(np.linalg.norm(outline, axis=1)) * math.exp(scene.deform_amplitude) <= r + 1e-9
  assert np.all(scene.trajectory[:, 2] - r >= 0.5 - 1e-9)
  assert np.all(scene.trajectory[:, 2] + r <= 1.5 + 1e-9)
  with pytest.raises(ValueError, match="deform"):
    SceneParams(deform=(0.2, 0.8))
  with pytest.raises(ValueError, match="glyph_weights"):
    SceneParams(glyph_weights=("light",))


def test_deformed_object_casts_the_footprint_of_its_explicitly_mapped_outline():
  """Twin: the ray cast of a posed (warped) object equals that of an object whose outline was
  mapped by hand and which carries no warp (a uniform texture, so albedo compares too)."""
  scene = deforming_scene("dots", seed=5)
  i = scene.dynamic_index
  for f in (0, 3, 5):
    posed = scene.posed(i, f)
    M = posed.shape["warp"]
    mapped = SceneObject(posed.kind, posed.anchor, posed.rotation, posed.size, posed.radius,
                         {"polygons": tuple(p @ M.T for p in posed.shape["polygons"])},
                         {"name": "uniform", "albedo": 0.7})
    warped = SceneObject(posed.kind, posed.anchor, posed.rotation, posed.size, posed.radius,
                         posed.shape, {"name": "uniform", "albedo": 0.7})
    ox, oy = scene_raster._ray_origins(SETUP, 3)
    t_a, a_a = scene_raster._cast(warped, warped.anchor, ox, oy)
    t_b, a_b = scene_raster._cast(mapped, mapped.anchor, ox, oy)
    hit_a, hit_b = np.isfinite(t_a), np.isfinite(t_b)
    assert hit_a.sum() > 50
    assert np.sum(hit_a != hit_b) <= 2          # rays exactly on an edge may round either way
    both = hit_a & hit_b
    np.testing.assert_allclose(t_a[both], t_b[both], rtol=1e-12)
    np.testing.assert_allclose(a_a[both], a_b[both], rtol=1e-12)
  cover = np.isfinite(scenes.rasterize(scene, SETUP, objects=[i], supersample=3).ray_depth).mean(1)
  assert np.abs(cover[0] - cover[3]).sum() > 1.0     # its footprint changes shape over the sequence


def test_transport_patches_of_a_deformed_object_follow_its_mapped_outline():
  """Patches sampled on a deformed planar object: their area is the outline's (det M = 1), and
  every patch, mapped back by M^-1 in the object's plane, lies inside the reference outline,
  with the albedo of its reference point."""
  from nlosjax.data import surfaces
  scene = deforming_scene("letter", seed=3)
  i = scene.dynamic_index
  ref_area = covered_area(scene.objects[i].shape["polygons"], 1e-3)
  for f in (0, 4):
    posed = scene.posed(i, f)
    M = posed.shape["warp"]
    samples = surfaces.object_samples(posed, 0.01)
    assert float(np.sum(samples.area)) == pytest.approx(ref_area, rel=0.03)
    local = (np.asarray(samples.points) - posed.anchor) @ posed.rotation
    np.testing.assert_allclose(local[:, 2], 0.0, atol=1e-12)
    back = local[:, :2] @ np.linalg.inv(M).T
    assert scenes.inside_polygons(back[:, 0], back[:, 1], posed.shape["polygons"]).all()
    q = np.concatenate([back, np.zeros((len(back), 1))], axis=1)
    np.testing.assert_allclose(samples.albedo, scenes.texture_albedo(posed.texture, q), rtol=1e-12)

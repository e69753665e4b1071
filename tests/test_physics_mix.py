"""The forward model as a random variable (nlosjax.data.dataset.physics, renderer="mix").

Independent references: the confocal path written as two legs in an explicit
loop over scan points and patches; the default diffuse and retroreflective
materials (a general material at ``kappa = 1, p = 4 / 2`` must equal them);
the expected counts written out per scan point with ``np.convolve``, slicing
and sums; moments of the measured jitter curve read from its file; the
closed-form mean of a discrete exponential; Poisson z-scores of the stored
counts around that rate.
"""

import json
import math

import numpy as np
import pytest

from nlosjax.data import dataset as D
from nlosjax.data.dataset import physics as P
from nlosjax.data.dataset.simulate import mixed_rate
from nlosjax.physics import Setup
from nlosjax.physics.noise import jitter_kernel, load_measured_jitter
from nlosjax.physics.transport import SurfaceSamples, render_surfaces
from tests.test_dataset import SCENE, tiny_spec
from tests.xla_options import xla_optimizations


@pytest.fixture(scope="module", autouse=True)
def _optimised_xla():
  with xla_optimizations(True):
    yield


SETUP = Setup(wall_size=0.8, grid=(5, 5), bin_width=32e-12, num_bins=160)


def random_patches(rng, n=40):
  pts = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(0.3, 1.0, n)], 1)
  nrm = rng.normal(size=(n, 3))
  nrm[:, 2] = -np.abs(nrm[:, 2])
  nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
  return SurfaceSamples(pts, nrm, rng.uniform(1e-4, 4e-4, n), rng.uniform(0.1, 1, n),
                        rng.uniform(size=n) < 0.3, rng.uniform(size=n) < 0.3, 0)


def loop_general(s: SurfaceSamples, setup: Setup, power, kappa) -> np.ndarray:
  """Out leg ``(cos_w cos_p)^kappa / r^2`` times back leg ``(cos_w cos_p)^(kappa (p - 2) / 2) / r^(p - 2)``."""
  H, W = setup.grid
  out = np.zeros((setup.num_bins, H, W))
  dy, dx = setup.spacing
  for i in range(H):
    for j in range(W):
      sp = np.array([setup.scan_x[j], setup.scan_y[i], 0.0])
      for n, p in enumerate(s.points):
        d = p - sp
        r = np.linalg.norm(d)
        cos_p = float(-d / r @ s.normals[n])
        cos_p = abs(cos_p) if s.two_sided[n] else cos_p
        if cos_p <= 1e-3:
          continue
        c = (d[2] / r) * cos_p
        out_leg = c ** kappa / r ** 2
        back_leg = c ** (kappa * (power[n] - 2) / 2) / r ** (power[n] - 2)
        k = int(2 * r // setup.bin_length)
        if k < setup.num_bins:
          out[k, i, j] += s.albedo[n] * s.area[n] * out_leg * back_leg / (dy * dx)
  return out


def test_general_material_matches_the_two_leg_loop():
  rng = np.random.default_rng(1)
  s = random_patches(rng)
  power = rng.uniform(2, 4, len(s))
  for kappa in (0.0, 0.6, 1.7):
    got = render_surfaces(s, SETUP, occlusion=False, falloff_power=power, cosine_power=kappa)
    want = loop_general(s, SETUP, power, kappa)
    assert want.sum() > 0
    np.testing.assert_allclose(got, want, rtol=5e-4, atol=1e-6 * want.max())


def test_general_material_at_kappa_1_is_the_diffuse_and_retroreflective_model():
  s = random_patches(np.random.default_rng(2))
  default = render_surfaces(s, SETUP)                       # occlusion on: the same visibility
  general = render_surfaces(s, SETUP, falloff_power=np.where(s.retroreflective, 2.0, 4.0),
                            cosine_power=1.0)
  np.testing.assert_allclose(general, default, rtol=1e-4, atol=1e-6 * default.max())


def test_general_material_rejects_bad_exponents():
  s = random_patches(np.random.default_rng(3), n=4)
  with pytest.raises(ValueError, match="falloff_power"):
    render_surfaces(s, SETUP, falloff_power=1.5)
  with pytest.raises(ValueError, match="cosine_power"):
    render_surfaces(s, SETUP, cosine_power=-1.0)


# ------------------------------------------------------------------- the draws
def test_draws_are_deterministic_cover_the_families_and_respect_the_ranges():
  mix = P.PhysicsMix(time_shift=3)
  setup = Setup(wall_size=2.0, grid=(8, 8), bin_width=132e-12, num_bins=64)
  draws = [mix.draw(s, setup) for s in range(300)]
  assert draws[7] == mix.draw(7, setup)
  assert {d.family for d in draws} == set(P.FAMILIES)
  for d in draws:
    assert all(p == 2.0 or 2.0 <= p <= 4.0 for p in d.falloff_power)
    assert abs(d.time_shift) <= 3
    assert (d.cosine_power == 0.0) == (d.family != "transport")
    assert (d.jitter_fwhm is None) != (d.jitter_stretch is None)
    json.loads(d.describe())
  share_retro = np.mean([p == 2.0 for d in draws for p in d.falloff_power])
  assert share_retro == pytest.approx(0.2, abs=0.03)
  assert {d.family for d in (mix.restricted(("lct",)).draw(s, setup) for s in range(20))} == {"lct"}
  assert all(p == 2.0 for p in P.PhysicsMix(retroreflective=1.0).draw(0, setup).falloff_power)


@pytest.mark.parametrize("bad", [dict(families=("lct", "ray")), dict(families=()),
                                 dict(falloff_power=(1.0, 4.0)), dict(retroreflective=1.5),
                                 dict(time_shift=-1), dict(dark_counts=(0.0, 3.0)),
                                 dict(jitter_stretch=(2.0, 1.0))])
def test_bad_mixes_are_refused(bad):
  with pytest.raises(ValueError, match="PhysicsMix"):
    P.PhysicsMix(**bad)
  with pytest.raises(ValueError, match="unknown data.physics key"):
    P.PhysicsMix.from_dict({"familes": ("lct",)})


def _draw(**changes):
  setup = Setup(wall_size=2.0, grid=(8, 8), bin_width=32e-12, num_bins=64)
  base = dict(family="lct", cosine_power=0.0, scene_falloff=4.0, falloff_power=(4.0,),
              jitter_fwhm=None, jitter_stretch=1.0, tail_weight=0.0, tail_decay=1e-10,
              decay_fraction=0.0, decay_time=1e-9, dark_counts=None, gain_sigma=0.0,
              vignetting=0.0, vignetting_centre=(0.0, 0.0), gain_seed=0, time_shift=0)
  return setup, P.ForwardModel(**{**base, **changes})


def _moments(kernel):
  k = np.arange(kernel.size) - kernel.size // 2
  mean = float(np.sum(kernel * k))
  return mean, float(np.sum(kernel * (k - mean) ** 2))


def test_impulse_kernels_against_the_curve_and_closed_forms():
  setup, fm = _draw()
  np.testing.assert_allclose(P.impulse_kernel(setup, fm), jitter_kernel(setup, "measured"), rtol=1e-6)
  # A stretch s multiplies the curve's spread by s: its variance in bins, from the file.
  t, counts = load_measured_jitter()
  w = counts / counts.sum()
  sd = math.sqrt(np.sum(w * (t - np.sum(w * t)) ** 2)) / setup.bin_width
  for s in (0.7, 2.0):
    _, var = _moments(P.impulse_kernel(setup, _draw(jitter_stretch=s)[1]))
    assert math.sqrt(var) == pytest.approx(s * sd, rel=0.1), (s, var, sd)
  gauss = P.impulse_kernel(setup, _draw(jitter_fwhm=100e-12, jitter_stretch=None)[1])
  np.testing.assert_allclose(gauss, jitter_kernel(setup, 100e-12), rtol=1e-6)
  # A tail of weight w and time constant tau delays the mean by w * E[k] of the discrete exponential.
  tau, wt = 150e-12, 0.3
  plain = P.impulse_kernel(setup, _draw(jitter_fwhm=50e-12, jitter_stretch=None)[1])
  tailed = P.impulse_kernel(setup, _draw(jitter_fwhm=50e-12, jitter_stretch=None,
                                         tail_weight=wt, tail_decay=tau)[1])
  n = math.ceil(6 * tau / setup.bin_width) + 1
  e = np.exp(-np.arange(n) * setup.bin_width / tau)
  mean_tail = float(np.sum(np.arange(n) * e) / e.sum())
  assert tailed.size % 2 == 1 and tailed.sum() == pytest.approx(1.0) and tailed.min() >= 0
  assert _moments(tailed)[0] - _moments(plain)[0] == pytest.approx(wt * mean_tail, rel=1e-6)
  assert int(np.argmax(tailed)) == tailed.size // 2


def test_background_profile_and_gain_map():
  setup, fm = _draw()
  flat = P.background_profile(setup, fm, 64.0)
  np.testing.assert_allclose(flat, 1.0)
  _, fm = _draw(decay_fraction=0.5, decay_time=0.5e-9)
  b = P.background_profile(setup, fm, 64.0)
  assert b.sum() == pytest.approx(64.0) and np.all(np.diff(b) < 0)
  t = (np.arange(64) + 0.5) * 32e-12
  e = np.exp(-t / 0.5e-9)
  assert b[-1] == pytest.approx(64.0 * (0.5 / 64 + 0.5 * e[-1] / e.sum()), rel=1e-9)
  _, fm = _draw(vignetting=0.4, vignetting_centre=(0.0, 0.0))
  g = P.gain_map(setup, fm)
  assert g.mean() == pytest.approx(1.0) and g[0, 0] < g[3, 3] and g[0, 0] / g.max() == pytest.approx(
      0.6 / (1 - 0.4 * (0.125 ** 2 * 2) / (0.875 ** 2 * 2)), rel=1e-6)
  _, fm = _draw(gain_sigma=0.3, gain_seed=5)
  g = P.gain_map(setup, fm)
  assert g.mean() == pytest.approx(1.0) and np.std(np.log(g)) == pytest.approx(0.3, rel=0.25)


def test_mixed_rate_against_a_per_scan_point_loop():
  setup, fm = _draw(jitter_fwhm=80e-12, jitter_stretch=None, tail_weight=0.2, tail_decay=100e-12,
                    decay_fraction=0.6, decay_time=0.4e-9, gain_sigma=0.2, vignetting=0.3,
                    vignetting_centre=(0.1, -0.2), gain_seed=3, gate_time=0.2e-9)
  rng = np.random.default_rng(0)
  clean = np.zeros((2, setup.num_bins) + setup.grid, np.float32)
  clean[:, 20:40] = rng.uniform(0, 5, (2, 20) + setup.grid)
  g = P.impulse_kernel(setup, fm)
  c = g.size // 2
  gain = P.gain_map(setup, fm)
  b = P.background_profile(setup, fm, 40.0)
  T = setup.num_bins
  for shift in (0, 2, -3):
    fm_s = P.ForwardModel(**{**fm.__dict__, "time_shift": shift})
    got = mixed_rate(clean, setup, fm_s, efficiency=0.3, ambient_total=40.0, dark_counts=6.4)
    want = np.zeros_like(got, np.float64)
    for f in range(2):
      for i in range(setup.grid[0]):
        for j in range(setup.grid[1]):
          h = np.convolve(clean[f, :, i, j].astype(np.float64), g)[c:c + T]
          s = np.zeros(T)
          for t in range(T):
            if 0 <= t - shift < T:
              s[t] = h[t - shift]
          want[f, :, i, j] = 0.3 * gain[i, j] * (s + b) + 6.4 / T
          for t in range(T):
            if t * setup.bin_width < 0.2e-9:       # bins that start before the gate: no counts
              want[f, t, i, j] = 0.0
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-6)


# ------------------------------------------------------------------- the scanner sweep
def sweep_by_path_samples(x, length, serpentine, samples=4000):
  """Mean over ``samples`` positions (midpoint rule) along the last ``length`` steps of the path
  arriving at each scan point, each position's histogram interpolated from its two neighbours."""
  H, W = x.shape[-2:]
  out = np.zeros_like(x, np.float64)
  s = (np.arange(samples) + 0.5) / samples * length
  for i in range(H):
    direction = -1 if serpentine and i % 2 else 1
    for j in range(W):
      pos = np.clip(j - direction * s, 0, W - 1)                   # off the grid: the edge point
      lo = np.floor(pos).astype(int)
      hi = np.minimum(lo + 1, W - 1)
      a = pos - lo
      hist = (1 - a) * x[..., i, lo] + a * x[..., i, hi]          # [..., samples]
      out[..., i, j] = hist.mean(-1)
  return out


@pytest.mark.parametrize("length,serpentine", [(0.3, False), (1.0, True), (2.6, True), (4.0, False)])
def test_sweep_smear_is_the_mean_along_the_raster_path(length, serpentine):
  x = np.random.default_rng(4).uniform(0, 5, (3, 6, 7))
  got = P.sweep_smear(x, length, serpentine)
  np.testing.assert_allclose(got, sweep_by_path_samples(x, length, serpentine), rtol=1e-5, atol=1e-6)
  np.testing.assert_array_equal(P.sweep_smear(x, 0.0), x)
  w = P.sweep_weights(1.0)                                         # closed form: 1 - L/2, L/2
  np.testing.assert_allclose(w, [0.5, 0.5])
  np.testing.assert_allclose(P.sweep_weights(0.5), [0.75, 0.25])


def test_sweep_is_validated_and_drawn_last():
  for bad in (dict(sweep=1.5), dict(sweep_length=(0.0, 5.0)), dict(sweep_length=(1.0, 0.5)),
              dict(sweep_serpentine=-0.1)):
    with pytest.raises(ValueError, match="PhysicsMix.sweep"):
      P.PhysicsMix(**bad)
  with pytest.raises(ValueError, match="sweep length"):
    P.sweep_weights(-1.0)
  with pytest.raises(ValueError, match=r"\[\.\.\., H, W\]"):
    P.sweep_smear(np.ones(3), 1.0)
  setup = Setup(wall_size=2.0, grid=(8, 8), bin_width=132e-12, num_bins=64)
  plain, swept = P.PhysicsMix(), P.PhysicsMix(sweep=1.0, sweep_length=(0.5, 1.5))
  assert "sweep" not in plain.to_dict() and P.PhysicsMix.from_dict(swept.to_dict()) == swept
  for seed in range(20):                 # every earlier draw unchanged: a mix without it draws as before
    a, b = plain.draw(seed, setup), swept.draw(seed, setup)
    assert a.sweep_length == 0.0 and 0.5 <= b.sweep_length <= 1.5
    assert {**a.__dict__, "sweep_length": 0, "sweep_serpentine": 0} == {
        **b.__dict__, "sweep_length": 0, "sweep_serpentine": 0}


def test_mixed_rate_sweeps_the_signal_only():
  setup, fm = _draw(jitter_fwhm=80e-12, jitter_stretch=None, gain_sigma=0.2, gain_seed=3)
  swept = P.ForwardModel(**{**fm.__dict__, "sweep_length": 1.7, "sweep_serpentine": True})
  clean = np.zeros((1, setup.num_bins) + setup.grid, np.float32)
  clean[:, 20:40] = np.random.default_rng(1).uniform(0, 5, (1, 20) + setup.grid)
  plain = mixed_rate(clean, setup, fm, efficiency=0.3, ambient_total=40.0, dark_counts=6.4)
  got = mixed_rate(clean, setup, swept, efficiency=0.3, ambient_total=40.0, dark_counts=6.4)
  gain = P.gain_map(setup, fm)
  signal = (plain - 6.4 / setup.num_bins) / (0.3 * gain) - 40.0 / setup.num_bins
  want = 0.3 * gain * (sweep_by_path_samples(signal, 1.7, True) + 40.0 / setup.num_bins) + 6.4 / setup.num_bins
  np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)


# ------------------------------------------------------------------- datasets
def mix_spec(**physics):
  return tiny_spec(renderer="mix", retroreflective=0.0, physics={"time_shift": 1, **physics},
                   store_albedo=False)


def test_spec_round_trips_and_refuses_a_mix_without_physics():
  spec = mix_spec(families=("lct", "points"))
  again = D.DatasetSpec.from_config({**spec.to_dict(), "scene": spec.scene.to_dict()})
  assert again == spec and again.physics.families == ("lct", "points")
  with pytest.raises(ValueError, match="renderer='mix' and physics go together"):
    tiny_spec(renderer="mix")
  with pytest.raises(ValueError, match="renderer='mix' and physics go together"):
    tiny_spec(physics={})
  assert "physics" not in tiny_spec().to_dict()       # files without it keep their spec


@pytest.mark.parametrize("family", P.FAMILIES)
def test_each_family_renders_and_stores_its_draw(family):
  spec = mix_spec(families=(family,), retroreflective=1.0)
  seq = D.simulate_sequence(spec, "train", 0)
  a, attrs = seq["arrays"], seq["attrs"]
  drawn = json.loads(attrs["physics"])
  assert attrs["family"] == family == drawn["family"]
  assert a["clean"].sum(axis=1).mean() == pytest.approx(attrs["photons"], rel=1e-3)
  assert a["measurement"].shape == a["clean"].shape and np.all(np.isfinite(a["clean"]))


def test_lct_family_falloff_moves_energy_as_the_distance_power():
  """r^-2 against r^-4 of the same scene: per scan point, the energy ratio is ~r^2 of its return."""
  scene = {**SCENE, "num_static": (0, 0)}
  near = tiny_spec(renderer="mix", retroreflective=0.0, store_albedo=False, scene=scene,
                   physics={"families": ("lct",), "retroreflective": 1.0})
  far = tiny_spec(renderer="mix", retroreflective=0.0, store_albedo=False, scene=scene,
                  physics={"families": ("lct",), "retroreflective": 0.0, "falloff_power": (4.0, 4.0)})
  c2 = D.simulate_sequence(near, "train", 1)["arrays"]["clean"][0].astype(np.float64)
  c4 = D.simulate_sequence(far, "train", 1)["arrays"]["clean"][0].astype(np.float64)
  setup = near.setup
  r = (np.arange(setup.num_bins) + 0.5) * setup.bin_length / 2
  lit = c4.sum(0) > 0.2 * c4.sum(0).max()
  ratio = c2.sum(0)[lit] / c4.sum(0)[lit]
  mean_r2 = (c4 * r[:, None, None] ** 2).sum(0)[lit] / c4.sum(0)[lit]
  np.testing.assert_allclose(ratio / ratio.mean(), mean_r2 / mean_r2.mean(), rtol=1e-3)


def test_stored_counts_are_poisson_around_the_mixed_rate():
  spec = mix_spec(families=("points",), gain_sigma=(0.2, 0.2), decay=1.0, time_shift=1)
  spec = D.DatasetSpec.from_config({**spec.to_dict(), "scene": {**SCENE, "helix_speed": (0.0, 0.0)}},
                                   frames=32, photons=(3000.0, 3000.0), efficiency=(0.2, 0.2))
  seq = D.simulate_sequence(spec, "train", 0)
  a, attrs = seq["arrays"], seq["attrs"]
  fm = P.ForwardModel(**{k: tuple(v) if isinstance(v, list) else v
                         for k, v in json.loads(attrs["physics"]).items()})
  ambient_total = attrs["ambient"] * spec.setup.num_bins
  dark = spec.dark_counts if fm.dark_counts is None else fm.dark_counts
  lam = mixed_rate(a["clean"][:1], spec.setup, fm, efficiency=0.2, ambient_total=ambient_total,
                   dark_counts=dark)[0].astype(np.float64)
  mean = a["measurement"].astype(np.float64).mean(0)
  F = a["measurement"].shape[0]
  z = (mean.sum(0) - lam.sum(0)) / np.sqrt(lam.sum(0) / F)
  assert np.abs(z).max() < 5.0 and abs(z.mean()) < 5.0 / math.sqrt(z.size)

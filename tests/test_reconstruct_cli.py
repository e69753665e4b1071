"""Tests for ``python -m experiments.reconstruct`` and ``nlosjax.inference``.

Tiny captures written here (a rendered patch, 16 x 16 scan points); the
library calls they must reproduce are made independently in the tests; the
network path is checked against a hand-built forward pass of a tiny trained
checkpoint: the input the network receives (binning, under-scanning, the
rescaled wavelet) is rebuilt by hand, and one end-to-end run checks the rest.
"""

from __future__ import annotations

import json
import math
import re

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from experiments import reconstruct as cli
from nlosjax import inference as cio
from nlosjax import physics
from nlosjax.data import io
from nlosjax.physics.setup import SPEED_OF_LIGHT, Setup
from nlosjax.train import RunConfig

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
PATCH_BIN = 70


def names(path):
  return re.escape(str(path))


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
  """A 16 x 16 x 128 capture (1 m wall, 32 ps) of a bright patch at depth bin 70, with noise."""
  setup = Setup(wall_size=1.0, grid=(16, 16), bin_width=32e-12, num_bins=128)
  albedo = np.zeros((128, 16, 16), np.float32)
  albedo[PATCH_BIN, 5:11, 6:10] = 1.0
  clean = np.asarray(physics.render(albedo, setup))
  counts = np.random.default_rng(0).poisson(clean / clean.max() * 50 + 0.05).astype(np.float32)
  path = io.save_capture(tmp_path_factory.mktemp("cap") / "patch.h5", counts, setup)
  return path, counts, setup


def run_cli(args, capsys=None):
  out = cli.main([*map(str, args), "--no-cache", "--quiet"])
  return out


@pytest.mark.full
def test_classic_writes_every_output_and_matches_the_library(capture, tmp_path):
  path, counts, setup = capture
  out = tmp_path / "lct"
  # Our refined operators: within 3 bins at this patch's depth (bin 70 of 128), where the
  # public one-voxel cone on the coarse u-grid is off by up to 4.
  res = run_cli([path, "--method", "lct", "--snr", "0.5", "--operators", "refined", "--out", out])
  expected = np.asarray(physics.reconstruct(counts, setup, "lct", snr=0.5, variant="refined"))
  with h5py.File(out / "volume.h5", "r") as f:
    np.testing.assert_allclose(f["volume"][...], expected, rtol=1e-5, atol=1e-6 * expected.max())
    assert f.attrs["format"] == io.CAPTURE_FORMAT and f.attrs["method"] == "lct"
    assert json.loads(f.attrs["options"]) == {"snr": 0.5, "variant": "refined"}
    assert tuple(f.attrs["grid"]) == (16, 16) and math.isclose(f.attrs["bin_width"], 32e-12)
    intensity, depth = f["intensity"][...], f["depth"][...]
  # Images: the last 11 depth bins (the public code's boundary clip) left out.
  masked = expected.copy()
  masked[128 - cli.EDGE_BINS:] = 0
  ref_i, ref_d = physics.intensity_depth(masked, setup)
  np.testing.assert_allclose(intensity, ref_i, atol=1e-5)
  np.testing.assert_allclose(depth, ref_d, atol=1e-6)
  # Physics: the patch is found at its depth (within 3 bins) and is the brightest region.
  patch = (slice(5, 11), slice(6, 10))
  assert np.all(np.abs(depth[patch] - PATCH_BIN * setup.depth_bin_length) <= 3 * setup.depth_bin_length)
  assert intensity[patch].mean() > 3 * np.delete(intensity.ravel(), np.ravel_multi_index(
      np.mgrid[5:11, 6:10].reshape(2, -1), (16, 16))).mean()
  for name in ("intensity.png", "depth.png", "views.png"):
    assert (out / name).read_bytes()[:8] == PNG_MAGIC
  timings = json.loads((out / "timings.json").read_text())
  assert set(timings) >= {"load_s", "reconstruct_s", "write_s", "total_s"}
  assert res["volume"].shape == (1, 128, 16, 16)


def test_fk_images_use_the_square_root(capture, tmp_path):
  path, counts, setup = capture
  res = run_cli([path, "--method", "fk", "--out", tmp_path / "fk", "--edge-bins", "0"])
  vol = np.asarray(physics.reconstruct(counts, setup, "fk"))
  ref_i, _ = physics.intensity_depth(np.sqrt(vol), setup)
  np.testing.assert_allclose(res["intensity"][0], ref_i, atol=1e-5)


@pytest.mark.full
def test_scan_stride_and_depth_range(capture, tmp_path):
  path, counts, setup = capture
  res = run_cli([path, "--method", "phasor", "--scan-stride", "4", "--depth-range", "0.2", "0.5",
                 "--out", tmp_path / "ph"])
  gated = setup.with_depth_range(0.2, 0.5)
  # Independent interpolation: samples at 2 + 4 i, linear in between, held at the ends.
  pos = np.clip((np.arange(16) - 2) / 4.0, 0, 3)
  lo = np.minimum(np.floor(pos).astype(int), 2)
  m = np.zeros((16, 4))
  m[np.arange(16), lo] = 1 - (pos - lo)
  m[np.arange(16), lo + 1] += pos - lo
  dense = np.einsum("Hh,thw,Ww->tHW", m, counts[:, 2::4, 2::4], m)
  expected = np.asarray(physics.reconstruct(dense.astype(np.float32), gated, "phasor"))
  assert res["volume"].shape == (1, gated.num_depth_bins, 16, 16)
  np.testing.assert_allclose(res["volume"][0], expected, rtol=1e-4, atol=1e-5 * expected.max())
  with h5py.File(tmp_path / "ph" / "volume.h5", "r") as f:
    assert tuple(f.attrs["depth_range"]) == (0.2, 0.5) and f.attrs["scan_stride"] == 4


def test_csa_reads_the_sparse_scan_as_a_masked_grid_and_matches_the_library(capture, tmp_path):
  path, counts, setup = capture
  res = run_cli([path, "--method", "csa", "--scan-stride", "4", "--tau-rel", "0.1", "--iterations", "20",
                 "--out", tmp_path / "csa"])
  # Independent mask: the scan points 2 + 4 i, nothing interpolated.
  mask = np.zeros((16, 16), np.float32)
  mask[2::4, 2::4] = 1.0
  expected = np.asarray(physics.reconstruct(counts * mask, setup, "csa", mask=mask, tau_rel=0.1, iterations=20))
  np.testing.assert_allclose(res["volume"][0], expected, rtol=1e-5, atol=1e-6 * expected.max())
  # The unscanned points are read as absent: any counts there change nothing.
  noisy = counts + (1 - mask) * 1e3
  again = np.asarray(physics.reconstruct(noisy * mask, setup, "csa", mask=mask, tau_rel=0.1, iterations=20))
  np.testing.assert_array_equal(again, expected)
  with h5py.File(tmp_path / "csa" / "volume.h5", "r") as f:
    assert f.attrs["method"] == "csa" and f.attrs["scan_stride"] == 4
    assert json.loads(f.attrs["options"])["tau_rel"] == 0.1
  with pytest.raises(SystemExit):
    run_cli([path, "--method", "lct", "--tau-rel", "0.1", "--out", tmp_path / "x"])


@pytest.mark.parametrize("case", ["corrupt", "unknown", "override", "option", "method_option"])
def test_errors_name_the_file_and_the_problem(case, capture, tmp_path, capsys):
  path, _, _ = capture
  args = ["--method", "lct", "--out", tmp_path / "o"]
  if case == "corrupt":
    bad = tmp_path / "bad.h5"
    bad.write_bytes(path.read_bytes()[:2000])
    target, words = bad, ["corrupt"]
  elif case == "unknown":
    target = tmp_path / "noise.bin"
    target.write_bytes(np.random.default_rng(1).bytes(4096))
    words = ["unrecognised", "lct_mat"]
  elif case == "override":
    target, words = path, ["wall_size", "contradicts"]
    args += ["--setup", "wall_size=3.0"]
  elif case == "option":
    target, words = path, ["--tofgrid", "nlosjax_capture"]
    args += ["--tofgrid", "none"]
  else:
    target, words = path, ["--snr"]
    args = ["--method", "fk", "--snr", "0.3", "--out", tmp_path / "o"]
  with pytest.raises(SystemExit) as info:
    run_cli([target, *args])
  assert info.value.code == 2
  err = capsys.readouterr().err
  if case != "method_option":
    assert str(target) in err
  for w in words:
    assert w in err
  assert not (tmp_path / "o" / "volume.h5").exists()


# ------------------------------------------------------------------ network
TRAINED = Setup(wall_size=2.0, grid=(16, 16), bin_width=132e-12, num_bins=32)
TINY = dict(width=4, d_state=2, extract_time_stride=2, extract_blocks=1, st_depth=1, cross_depth=1,
            spread_min_width=1, volume_features=1, refine_width=2, dilations=[1, 2])
TINY_USM = dict(trn_width=2, trn_kernels=[3, 9], fusion_widths=[], extract_width=1,
                refine=[[2, 3], [2, 3]], render_widths=[2, 2])


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
  """A main-job workdir with tiny "ours" and "usm" checkpoints (random parameters, the real layout).

  Returns ``(workdir, ours config, ours params, (usm config, usm params))``.
  """
  from nlosjax import train
  workdir = tmp_path_factory.mktemp("run")
  config = {"data": {"wall_size": 2.0, "grid": 16, "bin_width": 132e-12, "num_bins": 32,
                     "input_stride": 4}, "model": TINY, "usm": {"model": TINY_USM}}
  (workdir / "config.json").write_text(json.dumps(config))
  rng = np.random.default_rng(3)
  out = {}
  for variant in ("ours", "usm"):
    mcfg = train.model_config_for(RunConfig.from_dict(config), TRAINED, variant)
    # Random parameters of the right shapes (no init compilation).
    shapes = jax.eval_shape(mcfg.module().init, jax.random.key(0),
                            jax.ShapeDtypeStruct(mcfg.input_shape(), jnp.float32))["params"]
    params = jax.tree.map(lambda a: jnp.asarray(rng.normal(0.0, 0.3, a.shape), a.dtype), shapes)
    state = train.TrainState.create(apply_fn=None, params=params, tx=optax.sgd(0.1))
    ckpt = train.Checkpointer(workdir / variant / "checkpoints", json.dumps({"model": repr(mcfg)}),
                              every=1)
    ckpt.save(state, 0, force=True)
    ckpt.close()
    out[variant] = (mcfg, params)
  return (workdir,) + out["ours"] + (out["usm"],)


@pytest.mark.full
def test_load_trained_restores_the_parameters(trained_run):
  workdir, mcfg, params, _ = trained_run
  for where in (workdir, workdir / "ours" / "checkpoints"):
    got_cfg, got, info = cio.load_trained(where)
    assert got_cfg == mcfg and info["variant"] == "ours" and info["step"] == 0
    jax.tree.map(np.testing.assert_array_equal, got, params)
  with pytest.raises(ValueError, match="ours_s"):
    cio.load_trained(workdir, "ours_s")


@pytest.mark.full
def test_load_trained_defaults_to_the_step_chosen_on_validation(trained_run, tmp_path):
  """selection.json's step, not the latest, and from best_checkpoint when checkpoints/ pruned it."""
  from nlosjax import train
  workdir, mcfg, params, _ = trained_run
  run = tmp_path / "run"
  (run / "ours").mkdir(parents=True)
  (run / "config.json").write_text((workdir / "config.json").read_text())
  later = jax.tree.map(lambda a: a + 1.0, params)
  signature = json.dumps({"model": repr(mcfg)})
  for folder, steps in (("checkpoints", ((3, later), (9, later))), ("best_checkpoint", ((2, params),))):
    ckpt = train.Checkpointer(run / "ours" / folder, signature, every=1)
    for step, p in steps:
      ckpt.save(train.TrainState.create(apply_fn=None, params=p, tx=optax.sgd(0.1)).replace(step=step),
                0, force=True)
    ckpt.close()
  _, got, info = cio.load_trained(run)                   # no selection: the latest
  assert info["step"] == 9 and not info["selected_on_validation"]
  (run / "ours" / "selection.json").write_text(json.dumps({"select": "plateau", "step": 2}))
  _, got, info = cio.load_trained(run)                   # pruned from checkpoints/: best_checkpoint
  assert info["step"] == 2 and info["selected_on_validation"] and info["checkpoint"].parent.name == "best_checkpoint"
  jax.tree.map(np.testing.assert_array_equal, got, params)
  (run / "ours" / "selection.json").write_text(json.dumps({"select": "val", "step": 3}))
  _, got, info = cio.load_trained(run)
  assert info["step"] == 3 and info["checkpoint"].parent.name == "checkpoints"
  _, got, info = cio.load_trained(run, step=9)           # an explicit step wins
  assert info["step"] == 9 and not info["selected_on_validation"]


def test_load_trained_refuses_another_config(trained_run, tmp_path):
  workdir, _, _, _ = trained_run
  other = tmp_path / "other"
  other.mkdir()
  (other / "ours").symlink_to(workdir / "ours", target_is_directory=True)
  config = json.loads((workdir / "config.json").read_text())
  config["model"]["width"] = 8
  (other / "config.json").write_text(json.dumps(config))
  with pytest.raises(ValueError, match="another model config"):
    cio.load_trained(other)


@pytest.mark.full
def test_model_cli_feeds_the_network_a_hand_built_input(trained_run, tmp_path, monkeypatch):
  workdir, mcfg, params, _ = trained_run
  rng = np.random.default_rng(4)
  capture = Setup(wall_size=1.0, grid=(16, 16), bin_width=16e-12, num_bins=260)
  video = rng.poisson(1.0, (3, 260, 16, 16)).astype(np.float32)
  path = io.save_capture(tmp_path / "video.h5", video, capture)
  seen = {}

  def fake_run_model(model_config, got_params, frames, **kw):
    seen.update(config=model_config, params=got_params, frames=np.asarray(frames))
    f, t = frames.shape[:2]
    z = model_config.setup.num_depth_bins
    return {"intensity": np.zeros((f, 16, 16)), "depth": np.zeros((f, 16, 16)),
            "volume": np.zeros((f, z, 16, 16)), "transient": np.zeros((f, t, 16, 16))}

  monkeypatch.setattr(cio, "run_model", fake_run_model)
  run_cli([path, "--method", "model", "--checkpoint", workdir, "--frame", "all", "--out", tmp_path / "m"])

  # By hand: 8 x 16 ps = 128 ps bins (nearest to the trained 132 ps), 260 // 8 = 32 of them,
  # the trailing 4 raw bins dropped; scan points 2 + 4 i; the wavelength kept at the
  # trained number of coarse (2 x) bins: 2 * 2 * (2 m / 15) / (c 264 ps) bins, so
  # sampling = that * (c 256 ps) / (2 * 1 m / 15).
  binned = video[:, :256].reshape(3, 32, 8, 16, 16).sum(axis=2)[:, :, 2::4, 2::4]
  np.testing.assert_array_equal(seen["frames"], binned)
  sampling = (4 * 2.0 / 15) / (SPEED_OF_LIGHT * 264e-12) * (SPEED_OF_LIGHT * 256e-12) / (2 * 1.0 / 15)
  expected = mcfg.replace(setup=Setup(wall_size=1.0, grid=(16, 16), bin_width=128e-12, num_bins=32),
                          wavelet_sampling=sampling)
  assert math.isclose(seen["config"].wavelet_sampling, sampling, rel_tol=1e-9)
  assert seen["config"] == expected.replace(wavelet_sampling=seen["config"].wavelet_sampling)
  jax.tree.map(np.testing.assert_array_equal, seen["params"], params)
  with h5py.File(tmp_path / "m" / "volume.h5", "r") as f:
    info = json.loads(f.attrs["model"])
    assert info["bin_factor"] == 8 and info["variant"] == "ours"
    assert math.isclose(f.attrs["bin_width"], 128e-12) and int(f.attrs["num_bins"]) == 32
    assert f["volume"].shape == (3, 32, 16, 16)


@pytest.mark.full
def test_model_cli_end_to_end(trained_run, tmp_path):
  workdir, mcfg, params, _ = trained_run
  rng = np.random.default_rng(5)
  capture = Setup(wall_size=1.0, grid=(16, 16), bin_width=16e-12, num_bins=256)
  video = rng.poisson(1.0, (2, 256, 16, 16)).astype(np.float32)
  path = io.save_capture(tmp_path / "video.h5", video, capture)
  res = run_cli([path, "--method", "model", "--checkpoint", workdir, "--frame", "all",
                 "--out", tmp_path / "m"])
  assert res["volume"].shape == (2, 32, 16, 16) and res["intensity"].shape == (2, 16, 16)
  assert np.isfinite(res["volume"]).all()
  assert res["intensity"].min() >= 0 and math.isclose(float(res["intensity"].max()), 1.0, rel_tol=1e-5)
  assert not np.allclose(res["volume"][0], res["volume"][1])     # each frame is its own output
  for name in ("intensity.png", "depth.png", "views.png"):
    assert (tmp_path / "m" / name).read_bytes()[:8] == PNG_MAGIC


@pytest.mark.full
def test_model_cli_adapt_records_what_it_did_and_refuses_classic_methods(trained_run, capture, tmp_path, capsys):
  workdir, *_ = trained_run
  rng = np.random.default_rng(7)
  setup = Setup(wall_size=1.0, grid=(16, 16), bin_width=16e-12, num_bins=256)
  x = rng.poisson(1.0, (256, 16, 16)).astype(np.float32)
  x[100:110, 4:12, 4:12] += 30.0
  path = io.save_capture(tmp_path / "still.h5", x, setup)
  res = run_cli([path, "--method", "model", "--checkpoint", workdir, "--adapt", "--adapt-steps", "3",
                 "--out", tmp_path / "a"])
  assert np.isfinite(res["volume"]).all()
  with h5py.File(tmp_path / "a" / "volume.h5", "r") as f:
    adapted = json.loads(f.attrs["model"])["adapted"]
  assert adapted["steps"] <= 3 and adapted["holdout"] == 0.25 and adapted["seconds"] > 0
  assert adapted["holdout_nll"][1] <= adapted["holdout_nll"][0]
  assert "of which adapting" in capsys.readouterr().out
  with pytest.raises(SystemExit):
    run_cli([capture, "--method", "lct", "--adapt", "--out", tmp_path / "c"])
  assert "--adapt fits a network" in capsys.readouterr().err


@pytest.mark.full
def test_usm_cli_end_to_end(trained_run, tmp_path):
  """``--method usm`` restores the run's USM (not Ours) and reconstructs every frame."""
  workdir, _, _, (ucfg, uparams) = trained_run
  got_cfg, got, info = cio.load_trained(workdir, "usm")
  assert got_cfg == ucfg and info["variant"] == "usm"
  jax.tree.map(np.testing.assert_array_equal, got, uparams)
  rng = np.random.default_rng(6)
  capture = Setup(wall_size=1.0, grid=(16, 16), bin_width=16e-12, num_bins=256)
  video = rng.poisson(1.0, (2, 256, 16, 16)).astype(np.float32)
  path = io.save_capture(tmp_path / "video.h5", video, capture)
  res = run_cli([path, "--method", "usm", "--checkpoint", workdir, "--frame", "all",
                 "--out", tmp_path / "u"])
  assert res["volume"].shape == (2, 32, 16, 16) and res["intensity"].shape == (2, 16, 16)
  assert np.isfinite(res["volume"]).all() and np.isfinite(res["depth"]).all()
  assert 0.0 <= res["intensity"].min() and res["intensity"].max() <= 1.0
  with h5py.File(tmp_path / "u" / "volume.h5", "r") as f:
    assert json.loads(f.attrs["model"])["variant"] == "usm"
  with pytest.raises(SystemExit):
    run_cli([path, "--method", "usm", "--variant", "ours", "--checkpoint", workdir,
             "--out", tmp_path / "x"])


def test_model_cli_refuses_another_stride(trained_run, capture, tmp_path, capsys):
  workdir, _, _, _ = trained_run
  path, _, _ = capture
  with pytest.raises(SystemExit):
    run_cli([path, "--method", "model", "--checkpoint", workdir, "--scan-stride", "2",
             "--out", tmp_path / "x"])
  assert "stride 4" in capsys.readouterr().err


def test_triplets_replicate_the_ends():
  frames = np.arange(4)[:, None, None, None] * np.ones((4, 1, 1, 1))
  got = cio.triplets(frames, 3)[:, :, 0, 0, 0]
  np.testing.assert_array_equal(got, [[0, 0, 1], [0, 1, 2], [1, 2, 3], [2, 3, 3]])
  np.testing.assert_array_equal(cio.triplets(frames[:1], 3)[:, :, 0, 0, 0], [[0, 0, 0]])


def test_every_registered_variant_is_a_method_and_adapt_refuses_a_baseline(tmp_path, capsys):
  """``--method lfe`` / ``ik`` name the shipped baselines (the registry's names, not a list of
  three): LFE moves to the capture; I-K, whose kernel is sized by its training setup, is refused
  with the reason; ``--adapt`` fits ST-Mamba networks only."""
  rng = np.random.default_rng(8)
  setup = Setup(wall_size=1.0, grid=(16, 16), bin_width=16e-12, num_bins=256)
  x = rng.poisson(1.0, (256, 16, 16)).astype(np.float32)
  x[100:110, 4:12, 4:12] += 30.0
  path = io.save_capture(tmp_path / "still.h5", x, setup)
  res = run_cli([path, "--method", "lfe", "--pretrained", "cpu", "--out", tmp_path / "lfe"])
  assert np.isfinite(res["volume"]).all() and 0.0 <= res["intensity"].min() <= res["intensity"].max() <= 1.0
  with h5py.File(tmp_path / "lfe" / "volume.h5", "r") as f:
    assert json.loads(f.attrs["model"])["variant"] == "lfe"
  with pytest.raises(SystemExit):
    run_cli([path, "--method", "lfe", "--pretrained", "cpu", "--adapt", "--out", tmp_path / "a"])
  assert "fits an ST-Mamba network, not LFE" in capsys.readouterr().err
  with pytest.raises(SystemExit):
    run_cli([path, "--method", "ik", "--pretrained", "cpu", "--out", tmp_path / "ik"])
  assert "cannot move to a capture" in capsys.readouterr().err

"""The golden probes: fixed tiny computations whose every number the suite pins.

Each probe family is a function returning ``{key: array}``; :data:`FAMILIES` lists them with
their tier. Inputs are made by NumPy alone from fixed seeds and closed forms (a point
scatterer's transient, Poisson counts, random weights), never by the library code under test,
so a change to a renderer moves the data probe, not every probe downstream of it.

Tolerances (:func:`tolerance`) are relative to the largest magnitude of the golden array:
``max |new - golden| <= rtol * max |golden|``. The default, :data:`RTOL`, is ten times below
the 1e-4 relative change every golden must catch and ten times above what XLA's and NumPy's
instruction sets move (``python -m tests.golden --isa-check`` regenerates under narrower
vector units and prints the largest difference per family). Noisy counts and data stored
at reduced precision are compared by what survives rounding (:data:`COUNTS`, :data:`COMPACT`).
"""

from __future__ import annotations

import contextlib
import io
import json
import pathlib
import tempfile

import numpy as np

#: Relative-to-maximum tolerance of every float probe unless :func:`tolerance` says otherwise.
RTOL = 2e-5
#: Poisson counts: at most this fraction of elements may differ, and the sum by this relative
#: amount (a rate moved by float rounding flips a draw now and then). The rates themselves are
#: pinned at :data:`RTOL` (the ``rate/`` keys of :func:`data`).
COUNTS = ("counts", 2e-3, 1e-3)
#: ``clean`` as the dataset stores it: rounded to 12 mantissa bits, so one rounding may flip
#: (2**-12 relative to that element).
COMPACT = ("rel", 3e-4)

C = 299_792_458.0


def tiny_setup(**kw):
  from nlosjax.physics import Setup
  return Setup(**{"wall_size": 2.0, "grid": 16, "bin_width": 264e-12, "num_bins": 64, **kw})


def point_transient(setup, points, *, power: int = 4) -> np.ndarray:
  """``[T, H, W]`` float32: the confocal returns of point scatterers, by closed form (NumPy).

  ``points``: ``[(x, y, z, albedo)]`` metres; each scan point gets ``albedo / r**power`` in
  the bin of its round trip ``2 r / c``, spread linearly over the two nearest bins.
  """
  H, W = setup.grid
  T = setup.num_bins
  xs = np.linspace(-setup.wall_size / 2, setup.wall_size / 2, W)
  ys = np.linspace(-setup.wall_size / 2, setup.wall_size / 2, H)
  out = np.zeros((T, H, W), np.float64)
  for x, y, z, a in points:
    r = np.sqrt((xs[None, :] - x) ** 2 + (ys[:, None] - y) ** 2 + z ** 2)
    pos = 2 * r / C / setup.bin_width
    k = np.floor(pos).astype(int)
    frac = pos - k
    for kk, w in ((k, 1 - frac), (k + 1, frac)):
      ok = kk < T
      ii, jj = np.nonzero(ok)
      out[kk[ok], ii, jj] += a * w[ok] / r[ok] ** power
  return (out / out.max()).astype(np.float32)


def tiny_scene(seed: int = 3, frames: int = 3):
  """``(clean [F, T, H, W], intensity [F, H, W], depth [F, H, W])``: a few moving points, NumPy only."""
  setup = tiny_setup()
  rng = np.random.default_rng(seed)
  H, W = setup.grid
  clean, intensity, depth = [], [], []
  base = [(rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(0.6, 1.6), rng.uniform(0.4, 1.0))
          for _ in range(3)]
  for f in range(frames):
    pts = [(x + 0.05 * f, y - 0.03 * f, z, a) for x, y, z, a in base]
    clean.append(point_transient(setup, pts))
    img, dep = np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)
    for x, y, z, a in pts:
      j = int(np.clip(round((x / setup.wall_size + 0.5) * (W - 1)), 0, W - 1))
      i = int(np.clip(round((y / setup.wall_size + 0.5) * (H - 1)), 0, H - 1))
      img[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2] = a
      dep[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2] = z
    intensity.append(img)
    depth.append(dep)
  return np.stack(clean), np.stack(intensity), np.stack(depth)


def noisy(clean: np.ndarray, seed: int, photons: float = 300.0, background: float = 0.02) -> np.ndarray:
  """Poisson counts of ``clean`` scaled to ``photons`` per scan point, plus a flat background (NumPy)."""
  rng = np.random.default_rng(seed)
  per_point = clean.sum(axis=-3, keepdims=True).mean()
  rate = clean * (photons / max(per_point, 1e-12)) + background
  return rng.poisson(rate).astype(np.float32)


# --------------------------------------------------------------------------- classic methods

def classic() -> dict:
  """Every classic method and CSA on one point-scatterer capture (Poisson counts)."""
  from nlosjax import physics
  setup = tiny_setup()
  clean, _, _ = tiny_scene(frames=1)
  transient = noisy(clean, seed=11)[0]
  out = {}
  for method in physics.METHODS:
    out[f"{method}"] = physics.reconstruct(transient, setup, method)
  for method in ("fbp", "lct", "fk", "phasor"):
    out[f"{method}/refined"] = physics.reconstruct(transient, setup, method, variant="refined")
  out["lct/retroreflective"] = physics.reconstruct(transient, setup, "lct", falloff="retroreflective", snr=0.5)
  gated = setup.with_depth_range(0.5, 1.7)
  out["lct/gated"] = physics.reconstruct(transient, gated, "lct")
  out["phasor/gated"] = physics.reconstruct(transient, gated, "phasor")
  mask = np.zeros(setup.grid, bool)
  mask[2::4, 2::4] = True
  out["csa/under-scanned"] = physics.reconstruct(transient * mask, setup, "csa", mask=mask, iterations=40)
  intensity, depth = physics.intensity_depth(out["lct"], setup)
  out["lct/intensity"], out["lct/depth"] = intensity, depth
  out["render/diffuse"] = physics.render(_albedo(setup), setup)
  out["render/retroreflective"] = physics.render(_albedo(setup), setup, falloff="retroreflective")
  return {k: np.asarray(v) for k, v in out.items()}


def _albedo(setup) -> np.ndarray:
  rng = np.random.default_rng(5)
  a = np.zeros((setup.num_depth_bins,) + setup.grid, np.float32)
  for _ in range(4):
    k, i, j = rng.integers(10, setup.num_depth_bins - 10), rng.integers(2, 14), rng.integers(2, 14)
    a[k, i:i + 3, j:j + 2] = rng.uniform(0.3, 1.0)
  return a


# --------------------------------------------------------------------------- scan kernels

def scan() -> dict:
  """Every selective-scan method, forward and gradients, causal and reverse; the bidirectional scan and a mixer."""
  import jax
  import jax.numpy as jnp

  from nlosjax.ssm import METHODS, MambaMixer, bidirectional_scan, selective_scan
  rng = np.random.default_rng(21)
  Bn, L, D, N = 2, 24, 6, 4
  x = rng.normal(size=(Bn, L, D)).astype(np.float32)
  dt = np.log1p(np.exp(rng.normal(size=(Bn, L, D)))).astype(np.float32)
  A = -np.exp(rng.normal(size=(D, N))).astype(np.float32)
  Bm = rng.normal(size=(Bn, L, N)).astype(np.float32)
  Cm = rng.normal(size=(Bn, L, N)).astype(np.float32)
  Dv = rng.normal(size=(D,)).astype(np.float32)
  gy = rng.normal(size=(Bn, L, D)).astype(np.float32)
  out = {}
  for method in METHODS:
    for reverse in (False, True):
      def loss(x, dt, A, B, C, D, method=method, reverse=reverse):
        y = selective_scan(x, dt, A, B, C, D, method=method, reverse=reverse, chunk_size=8)
        return jnp.sum(y * gy), y
      (_, y), grads = jax.jit(jax.value_and_grad(loss, argnums=range(6), has_aux=True))(x, dt, A, Bm, Cm, Dv)
      tag = f"{method}/{'reverse' if reverse else 'causal'}"
      out[f"{tag}/y"] = y
      for name, g in zip(("x", "dt", "A", "B", "C", "D"), grads):
        out[f"{tag}/grad_{name}"] = g
  out["bidirectional/y"] = jax.jit(lambda *a: bidirectional_scan(*a, method="sequential"))(x, dt, A, Bm, Cm, Dv)
  mixer = MambaMixer(d_model=D, d_state=N, direction="bidirectional", scan_method="sequential")
  params = mixer.init(jax.random.key(0), x)
  for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
    out[f"mixer/param{jax.tree_util.keystr(path)}"] = leaf      # init is part of what a run reproduces
  out["mixer/y"] = jax.jit(mixer.apply)(params, x)
  return {k: np.asarray(v) for k, v in out.items()}


# --------------------------------------------------------------------------- networks

TINY_MODEL = dict(width=4, d_state=2, extract_time_stride=2, extract_blocks=1, st_depth=1, cross_depth=1,
                  spread_min_width=1, volume_features=1, refine_width=2, conv_impl="fold")
TINY_USM = dict(trn_width=2, trn_kernels=(3, 9), fusion_widths=(), extract_width=1,
                refine=((2, 3), (2, 3)), render_widths=(2, 2))


def model_configs() -> dict:
  """Every variant at a tiny size on :func:`tiny_setup`, stride 4 (built from the typed configs)."""
  from nlosjax.models.ik import IKConfig
  from nlosjax.models.lfe import LFEConfig
  from nlosjax.models.network import ModelConfig
  from nlosjax.models.usm import USMConfig
  from nlosjax.variants import IK, LFE, OURS, OURS_S, USM
  s = tiny_setup()
  return {OURS: ModelConfig(setup=s, stride=4, frames=3, **TINY_MODEL),
          OURS_S: ModelConfig(setup=s, stride=4, frames=1, **TINY_MODEL),
          USM: USMConfig(setup=s, stride=4, **TINY_USM),
          LFE: LFEConfig(setup=s, stride=4, extract_width=1),
          IK: IKConfig(setup=s, stride=4, extract_width=1)}


def network_input(mcfg, batch: int = 2, seed: int = 31) -> np.ndarray:
  """``[B, F, T, h, w]`` Poisson counts of the point scene at the model's under-scanned grid."""
  clean, _, _ = tiny_scene(frames=max(mcfg.frames, 1) + batch - 1)
  counts = noisy(clean, seed=seed)[:, :, mcfg.stride // 2::mcfg.stride, mcfg.stride // 2::mcfg.stride]
  return np.stack([counts[b:b + mcfg.frames] for b in range(batch)])


def forward() -> dict:
  """Each variant's parameters at initialisation (fixed key) and its outputs on a fixed input."""
  import jax

  from nlosjax.train.state import network
  out = {}
  for variant, mcfg in model_configs().items():
    model = network(mcfg)
    x = network_input(mcfg)
    params = jax.jit(model.init)(jax.random.key(1), x)
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
      out[f"{variant}/param{jax.tree_util.keystr(path)}"] = leaf
    y = jax.jit(model.apply)(params, x)
    for k in sorted(y):
      out[f"{variant}/out/{k}"] = y[k]
  return {k: np.asarray(v) for k, v in out.items()}


def train() -> dict:
  """Two jitted train steps of each variant (AdamW, the ``cpu`` preset's loss): metrics per step and
  the gradient at initialisation, leaf by leaf."""
  import jax

  from nlosjax import losses
  from nlosjax.physics import illumination_wavelet
  from nlosjax.train import OptimConfig, make_optimizer
  from nlosjax.train.sharding import make_mesh
  from nlosjax.train.state import create_train_state, network
  from nlosjax.train.step import make_targets, make_train_step
  from nlosjax.variants import OURS
  weights = losses.LossWeights(object_intensity=3.0)
  optim = OptimConfig(learning_rate=3e-3, weight_decay=0.95, warmup_steps=1, cosine=True, clip_norm=1.0)
  mesh = make_mesh(jax.devices()[:1])
  out = {}
  for variant, mcfg in model_configs().items():
    model = network(mcfg)
    batch = train_batch(mcfg)
    state = create_train_state(model, batch["measurement"].shape, make_optimizer(optim, 10), jax.random.key(2), mesh)
    wavelet = illumination_wavelet(mcfg.setup, cycles=mcfg.wavelet_cycles, sampling_coeff=mcfg.wavelet_sampling)

    def loss_fn(params, state=state, batch=batch, mcfg=mcfg, wavelet=wavelet):
      y = state.apply_fn({"params": params}, batch["measurement"])
      return losses.total_loss(y, make_targets(batch, mcfg.time_window), weights, wavelet)[0]

    if variant == OURS:     # every leaf of the paper's network; the others by the step's l2_grads
      grads = jax.jit(jax.grad(loss_fn))(state.params)
      for path, leaf in jax.tree_util.tree_flatten_with_path(grads)[0]:
        out[f"{variant}/grad{jax.tree_util.keystr(path)}"] = leaf
    step = make_train_step(mcfg, weights, mesh)
    for i in range(2):
      state, metrics = step(state, batch, jax.random.key(i))
      for k, v in metrics.items():
        out[f"{variant}/step{i}/{k}"] = v
  return {k: np.asarray(v) for k, v in out.items()}


def train_batch(mcfg, batch: int = 2) -> dict:
  """A training batch of the point scene: counts, clean transient, intensity and depth (NumPy)."""
  clean, intensity, depth = tiny_scene(frames=max(mcfg.frames, 1) + batch - 1)
  mid = mcfg.frames // 2
  return {"measurement": network_input(mcfg, batch),
          "transient": np.stack([clean[b + mid] for b in range(batch)]),
          "intensity": np.stack([intensity[b + mid] for b in range(batch)]),
          "depth": np.stack([depth[b + mid] for b in range(batch)])}


# --------------------------------------------------------------------------- metrics and losses

def scores() -> dict:
  """Every per-frame and temporal score, and every loss term, on fixed images and outputs."""
  import jax.numpy as jnp

  from nlosjax import losses
  from nlosjax.evaluation import scores as sc
  from nlosjax.physics import illumination_wavelet
  rng = np.random.default_rng(41)
  _, gt_i, gt_d = tiny_scene(frames=4)
  pred_i = np.clip(gt_i + rng.normal(0, 0.1, gt_i.shape), 0, 1).astype(np.float32)
  pred_d = np.where(rng.uniform(size=gt_d.shape) < 0.9, gt_d + rng.normal(0, 0.05, gt_d.shape),
                    rng.uniform(0.5, 1.5, gt_d.shape)).astype(np.float32)
  pred_d[:, :2] = 0.0
  out = {f"frame/{k}": v for k, v in sc.frame_scores(pred_i, pred_d, gt_i, gt_d, sequence=np.array([0, 0, 1, 1]),
                                                      frame=np.array([0, 1, 0, 1])).items()}
  setup = tiny_setup()
  clean, _, _ = tiny_scene(frames=2)
  vol = rng.uniform(0, 1, (2, setup.num_depth_bins) + setup.grid).astype(np.float32)
  outputs = {"transient": jnp.asarray(clean * 1.1 + 0.01), "volume": jnp.asarray(vol),
             "intensity": jnp.asarray(pred_i[:2]), "depth": jnp.asarray(pred_d[:2])}
  targets = {"transient": jnp.asarray(clean), "intensity": jnp.asarray(gt_i[:2]), "depth": jnp.asarray(gt_d[:2])}
  wavelet = illumination_wavelet(setup, cycles=4.0, sampling_coeff=2.0)
  loss, terms = losses.total_loss(outputs, targets, losses.LossWeights(object_intensity=3.0), wavelet)
  out["loss/total"] = loss
  for k, v in terms.items():
    out[f"loss/{k}"] = v
  return {k: np.asarray(v) for k, v in out.items()}


# --------------------------------------------------------------------------- data

DATA = dict(wall_size=2.0, grid=16, num_bins=64, bin_width=264e-12, frames=3, input_stride=4, input_offset=2,
            num_sequences={"train": 1, "val": 1, "test": 1}, render_batch=4, seed=7,
            efficiency=(0.05, 0.3), photons=(2e2, 2e3), ambient=(50.0, 500.0), dark_counts=0.5,
            jitter="measured", store_clean=True, store_albedo=False)
SCENE = dict(num_static=(1, 2), depth_range=(0.5, 1.5), lateral_extent=0.5, size_range=(0.25, 0.6),
             texture_probability=0.5, supersample=2, albedo_range=(0.2, 1.0), motions=("helix", "line"),
             spin_speed=(0.0, 0.8))
RENDERERS = {"lct": dict(renderer="lct", retroreflective=0.0),
             "transport": dict(renderer="transport", retroreflective=0.5),
             # Every PhysicsMix option drawn often (real_v4's choices), ambient light on.
             "mix": dict(renderer="mix", retroreflective=0.0,
                         physics={"retroreflective": 0.8, "tail": 0.8, "tail_weight": (0.1, 0.5),
                                  "tail_decay": (1e-10, 1e-9), "dark_counts": (0.5, 50.0),
                                  "gain_sigma": (0.05, 0.4), "time_shift": 1, "gate": 0.5,
                                  "gate_time": (2.0e-9, 2.6e-9)})}


def data_spec(renderer: str):
  from nlosjax.data.dataset import DatasetSpec
  return DatasetSpec.from_config({**DATA, **RENDERERS[renderer], "scene": dict(SCENE)})


def data() -> dict:
  """One simulated sequence of each renderer family: every array the dataset stores; and the detector's
  expected counts (the rate the Poisson draws sample) of a fixed transient, with and without jitter."""
  from nlosjax.data.dataset.simulate import measurement_rate, simulate_sequence
  from nlosjax.physics.noise import expected_counts
  out = {}
  clean, _, _ = tiny_scene(frames=2)
  setup = tiny_setup()
  for jitter in ("measured", 100e-12, None):
    out[f"rate/jitter={jitter}"] = measurement_rate(clean * 50.0, setup, efficiency=0.2, ambient=2.0,
                                                    dark_counts=0.01, jitter=jitter)
  out["rate/pulses"] = np.asarray(expected_counts(clean[0] * 0.01, setup, pulses=1e4, efficiency=0.3, ambient=1e-4,
                                                  dark_counts=1e-5, jitter="measured"))
  from nlosjax.data import scenes
  from nlosjax.data.dataset import simulate as sim
  from nlosjax.data.dataset.spec import sequence_seed
  for renderer in RENDERERS:          # each renderer's clean transient before the dataset rounds it
    spec = data_spec(renderer)
    seed = sequence_seed(spec.seed, "train", 0)
    scene = scenes.make_scene(seed, spec.scene, spec.frames, setup=spec.setup)
    maps = scenes.rasterize(scene, spec.setup, supersample=spec.scene.supersample)
    fm = None if spec.physics is None else spec.physics.draw(seed, spec.setup)
    render = sim._render_clean(spec, scene, maps, sim.render_setup(spec), fm)
    out[f"render/{renderer}"] = render
    if fm is not None:
      out[f"rate/{renderer}"] = sim.mixed_rate(render / render.max() * 20.0, spec.setup, fm, efficiency=0.2,
                                               ambient_total=200.0, dark_counts=1.0)
  for renderer in RENDERERS:
    seq = simulate_sequence(data_spec(renderer), "train", 0)
    for k, v in seq["arrays"].items():
      out[f"{renderer}/{k}"] = np.asarray(v)
    for k in ("efficiency", "photons", "signal_scale", "ambient", "dark_counts"):
      out[f"{renderer}/attr/{k}"] = np.asarray(seq["attrs"][k], np.float64)
  return out


# --------------------------------------------------------------------------- shipped networks

def pretrained() -> dict:
  """Every shipped network's outputs on a fixed input of its shape."""
  from nlosjax import inference
  out = {}
  for name, variant in inference.pretrained_names():
    rng = np.random.default_rng([20261201, *f"{name}-{variant}".encode()])
    mcfg, params, _ = inference.load_pretrained(name, variant)
    s = mcfg.setup
    h, w = (-(-n // mcfg.stride) for n in s.grid)
    frames = rng.poisson(rng.gamma(2.0, 0.5, size=(mcfg.frames + 1, s.num_bins, h, w))).astype(np.float32)
    o = inference.run_model(mcfg, params, frames, batch_size=2)
    for k in ("intensity", "depth", "volume"):
      out[f"{name}-{variant}/{k}"] = np.asarray(o[k])
  return out


# --------------------------------------------------------------------------- the evaluation protocol and CLIs

def protocol() -> dict:
  """The evaluation protocol on a tiny dataset: untrained Ours-S (fixed init) and every classic method at
  fixed settings, every per-frame score of the test split."""
  import jax

  from nlosjax.evaluation import protocol as P
  from nlosjax.train import RunConfig
  from nlosjax.train.state import network
  from nlosjax.variants import OURS_S
  out = {}
  with tempfile.TemporaryDirectory() as d:
    path = pathlib.Path(d) / "tiny.h5"
    from nlosjax.data.dataset import write_dataset
    write_dataset(path, data_spec("lct"), progress=False)
    config = RunConfig.from_dict({"data": {**DATA, **RENDERERS["lct"], "scene": dict(SCENE), "path": str(path)},
                                  "model": dict(TINY_MODEL), "train": {"eval_batch_size": 2, "batch_size": 2}})
    mcfg = model_configs()[OURS_S]
    x = network_input(mcfg)
    params = network(mcfg).init(jax.random.key(1), x)["params"]
    settings = {m: {} for m in ("fbp", "lct", "fk", "phasor", "rsd")}
    ev = P.evaluate(config, path, {OURS_S: (mcfg, params)}, split="test", classic_settings=settings,
                    log=lambda s: None)
    for method, sc in ev["scores"].items():
      for metric, v in sc.items():
        out[f"{method}/{metric}"] = np.asarray(v, np.float64)
  return out


def cli() -> dict:
  """The command lines end to end: ``experiments.reconstruct`` on a capture file (LCT and the shipped Ours),
  and the main job (``experiments.train``) on a tiny config, read back from what they write."""
  import h5py

  from experiments import reconstruct
  from experiments import train as main_job
  out = {}
  with tempfile.TemporaryDirectory() as d:
    tmp = pathlib.Path(d)
    from nlosjax.data import io
    for method in ("lct", "ours"):
      with contextlib.redirect_stdout(io_sink()), contextlib.redirect_stderr(io_sink()):
        reconstruct.main([str(io.shipped_scan_path()), "--method", method, "--out", str(tmp / method)])
      with h5py.File(tmp / method / "volume.h5", "r") as f:
        out[f"reconstruct/{method}/volume"] = np.asarray(f["volume"][()])
    args = ["--workdir", str(tmp / "job"), *main_job_overrides(tmp / "data.h5")]
    with contextlib.redirect_stdout(io_sink()), contextlib.redirect_stderr(io_sink()):
      main_job.main(args)
    table = json.loads((tmp / "job" / "results" / "table.json").read_text())
    for method, metrics in table.items():
      for metric, summary in metrics.items():
        out[f"main_job/{method}/{metric}"] = np.array([summary["mean"], *summary["ci95"]], np.float64)
  return out


def io_sink():
  return io.StringIO()


def main_job_overrides(data_path) -> list[str]:
  """The ``cpu`` preset shrunk to seconds by command-line overrides (the syntax users type)."""
  flat = {"data.path": str(data_path), "independent.path": str(pathlib.Path(data_path).with_name("independent.h5")),
          "data.grid": 16, "data.num_bins": 64, "data.bin_width": 264e-12,
          "data.frames": 4, "data.num_sequences.train": 2, "data.num_sequences.val": 1,
          "data.num_sequences.test": 1, "data.render_batch": 4, "data.renderer": "lct",
          "data.retroreflective": 0.0, "data.photons": (1e3, 1e4),
          "train.steps": 3, "train.batch_size": 2, "train.eval_batch_size": 2, "train.log_every": 1,
          "train.checkpoint_every": 3, "train.keep_checkpoints": 1,
          "independent.sequences": 1, "independent.frames": 3,
          **{f"model.{k}": v for k, v in TINY_MODEL.items()}}
  return [f"--config.{k}={v!r}" if not isinstance(v, str) else f"--config.{k}={v}" for k, v in flat.items()]


# --------------------------------------------------------------------------- registry

#: family -> (probe, tier): "default" runs in the README's test command, "full" in ``--tier full``.
FAMILIES = {
    "classic": (classic, "default"),
    "scan": (scan, "default"),
    "forward": (forward, "default"),
    "train": (train, "default"),
    "scores": (scores, "default"),
    "data": (data, "default"),
    "pretrained": (pretrained, "full"),
    "protocol": (protocol, "full"),
    "cli": (cli, "full"),
}


def tolerance(family: str, key: str, golden: np.ndarray) -> tuple:
  """How ``family/key`` is compared: ``("rel", rtol)``, ``("counts", frac, sum_rtol)`` or ``("exact",)``."""
  if golden.dtype.kind in "iub":
    if family == "data" and key.endswith("/measurement"):
      return COUNTS
    return ("exact",)
  if family == "data" and key.endswith("/clean"):
    return COMPACT
  return ("rel", RTOL)

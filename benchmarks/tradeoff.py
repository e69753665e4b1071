"""Speed-accuracy trade-offs of every reconstruction knob, on the test split of the CPU-preset data.

    python -m benchmarks.tradeoff [--quick] [--steps N] [--repeats N] [--batch 8] [--knobs ...]
                                  [--workdir runs/tradeoff] [--out-dir benchmarks/results]

For each configuration, on the test split of the CPU preset's dataset
(``runs/data/cpu.h5``, made if absent; 8 sequences x 6 middle frames = 48
frames, 32 x 32 x 128 bins of 132 ps, 2 m wall):

* time per reconstructed frame: the pipeline ``input -> (intensity, depth)``
  under one ``jax.jit``; compile time is ``.lower(x).compile()`` (tracing,
  operator construction -- cached per Setup across configurations -- and XLA
  compilation); the warm time of one batch of ``--batch`` frames, divided by
  the batch, is the median over ``--repeats`` rounds in which *every*
  executable of the run is called once in turn (each call ended by
  ``block_until_ready``, after a warm-up round), so that the load of a shared
  machine weighs on all configurations alike;
* memory: XLA's planned buffers of the compiled pipeline,
  ``memory_analysis()`` temp + argument + output bytes (constants such as the
  physics operators not counted; not the process RSS);
* accuracy against the ground truth of all 48 frames: intensity PSNR and SSIM
  (data range 1), depth RMSE and MAD (metres; background 0 m), as in Table 1.

Knobs, each varied with the others at the default (8 x 8 input = every 4th
scan point, the stored exposure, 3 frames, the CPU preset's model, the
``auto`` scan kernel, float32, no depth range):

* method: FBP, LCT, f-k, phasor, RSD (input interpolated bilinearly to the
  full grid, the paper's protocol), USM (the learned baseline, the preset's
  ``usm`` section and recipe), Ours-S, Ours;
* scan density: every 8th / 4th / 2nd / every scan point (4 x 4 ... 32 x 32)
  of the same scenes, classic methods (the networks are trained for 8 x 8);
* exposure: the stored noise-free transients re-noised with
  ``nlosjax.physics.add_spad_noise`` at 0.1, 0.3, 1 and 3 times the stored
  exposure (signal, ambient and dark counts scale together; each sequence
  keeps its efficiency);
* frames: 1 (Ours-S), 3 (Ours), 5 (windows of 5, clipped at sequence ends);
* model: width ``C``, ST-Mamba depth and SSM state size ``N``;
* scan kernel (associative, sequential, chunked) and bfloat16 activations on
  the default model's weights (same parameter tree);
* time gating: a Setup depth range (none, the first half of the full range,
  the scenes' 0.5-1.5 m, its middle half and quarter) for the classic
  methods and Ours (Ours-S at 0.5-1.5 m only), with the depth accuracy
  inside each range and a per-stage profile of LCT and the network.

``--knobs`` runs a subset (``method`` always runs). The quick mode (about 7
minutes on 2 shared cores once the checkpoints exist) is what
``benchmarks/results/tradeoff.md`` was produced with.

Every learned configuration is trained by this benchmark with one shared
budget (``--steps``; 150 with ``--quick``) and the CPU preset's optimiser
and seed, into ``WORKDIR/s<steps>/<name>``; a rerun restores the
checkpoints (an interrupted training resumes). Writes ``OUT/tradeoff.md``,
``OUT/tradeoff.json`` and ``OUT/tradeoff.png`` (time per frame against
intensity PSNR, every configuration a point, the Pareto front of the
configurations that read the default capture drawn).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import pathlib
import statistics
import sys
import time
from typing import Any, Callable, Sequence

import numpy as np

from experiments import provenance as _machine_facts

DEFAULT_OUT_DIR = pathlib.Path(__file__).resolve().parent / "results"
DEFAULT_WORKDIR = pathlib.Path("runs/tradeoff")
QUICK_STEPS, FULL_STEPS = 150, 300
QUICK_REPEATS, FULL_REPEATS = 9, 15
MIB = 1024.0 ** 2

CLASSIC = ("fbp", "lct", "fk", "phasor", "rsd")
LABELS = {"fbp": "FBP", "lct": "LCT", "fk": "f-k", "phasor": "Phasor", "rsd": "RSD"}
DENSITY_STRIDES = (8, 4, 2, 1)
EXPOSURES = (0.1, 0.3, 1.0, 3.0)
KNOBS = ("method", "density", "exposure", "frames", "model", "kernel", "gating")
GOAL_HALVING = 1.6     # the goal: halving the depth range cuts the time by this much
APERTURE = 0.7         # m: lateral reach of the aperture gating rows (35 degrees off axis at 1 m)


# ------------------------------------------------------------------ Pareto
def pareto_front(times, scores) -> np.ndarray:
  """Boolean mask ``[n]`` of the points no other point dominates.

  Point ``j`` dominates ``i`` when ``times[j] <= times[i]``, ``scores[j] >=
  scores[i]`` and one of the two is strict (less time is better, more score
  is better). Identical points do not dominate each other, so both stay on
  the front. Points with a non-finite time or score are never on it (and
  dominate nothing). A sweep in order of time: ``O(n log n)``.

  Args:
    times: ``[n]`` seconds (or any cost).
    scores: ``[n]`` e.g. PSNR in dB.
  """
  t = np.asarray(times, np.float64)
  s = np.asarray(scores, np.float64)
  if t.shape != s.shape or t.ndim != 1:
    raise ValueError(f"times and scores must be 1-D of one length, got {t.shape} and {s.shape}")
  mask = np.zeros(t.shape, bool)
  ok = np.flatnonzero(np.isfinite(t) & np.isfinite(s))
  order = ok[np.lexsort((-s[ok], t[ok]))]        # time ascending, score descending
  best, last = -np.inf, None
  for i in order:
    if s[i] > best:
      mask[i], best, last = True, s[i], (t[i], s[i])
    elif last is not None and (t[i], s[i]) == last:
      mask[i] = True
  return mask


def recommend(points: Sequence[dict], *, tolerance_db: float = 1.0) -> dict:
  """``{"fastest", "balanced", "best"}``: names of Pareto-front points.

  ``best`` has the highest PSNR, ``fastest`` the least time per frame, and
  ``balanced`` is the fastest point within ``tolerance_db`` of the best PSNR.

  Args:
    points: dicts with ``name``, ``time`` (s per frame) and ``psnr`` (dB).
  """
  if not points:
    raise ValueError("recommend needs at least one point")
  t = np.array([p["time"] for p in points], np.float64)
  s = np.array([p["psnr"] for p in points], np.float64)
  front = np.flatnonzero(pareto_front(t, s))
  if front.size == 0:
    raise ValueError("no point has a finite time and PSNR")
  best = front[np.argmax(s[front])]
  fastest = front[np.argmin(t[front])]
  near = front[s[front] >= s[best] - tolerance_db]
  balanced = near[np.argmin(t[near])]
  return {"fastest": points[fastest]["name"], "balanced": points[balanced]["name"],
          "best": points[best]["name"]}


def learned_beats_classic(points: Sequence[dict]) -> list[str]:
  """Learned front points faster than every classic point at least as accurate, and more
  accurate than every faster classic point (both vacuous when there is none).

  Args:
    points: dicts with ``name``, ``time``, ``psnr``, ``kind`` ("classic" | "learned").
  Returns:
    the names of such learned points on the Pareto front of ``points``.
  """
  t = np.array([p["time"] for p in points], np.float64)
  s = np.array([p["psnr"] for p in points], np.float64)
  front = pareto_front(t, s)
  classic = [i for i, p in enumerate(points) if p["kind"] == "classic"]
  out = []
  for i, p in enumerate(points):
    if p["kind"] != "learned" or not front[i]:
      continue
    if all(t[i] < t[j] for j in classic if s[j] >= s[i]) and all(
        s[i] > s[j] for j in classic if t[j] <= t[i]):
      out.append(p["name"])
  return out


# ------------------------------------------------------------------ timing
def _padded(inputs: np.ndarray, batch: int) -> np.ndarray:
  """``inputs [N, ...]`` padded to a multiple of ``batch`` by repeating the last example."""
  if len(inputs) == 0:
    raise ValueError("inputs is empty")
  pad = (-len(inputs)) % batch
  return np.concatenate([inputs, np.repeat(inputs[-1:], pad, axis=0)]) if pad else inputs


def evaluate(fn: Callable, inputs: np.ndarray, *, batch: int, cache: dict, key,
             params=None) -> dict:
  """Compile ``fn`` once per ``key`` and run it over ``inputs`` in batches.

  Args:
    fn: ``fn(x) -> dict`` (or ``fn(params, x)`` when ``params`` is given)
      with ``"intensity"`` and ``"depth"`` ``[B, H, W]``; jitted here.
    inputs: ``[N, ...]`` examples; the last batch is padded by repeating the
      last example and its extra outputs dropped.
    batch: examples per call.
    cache: ``key -> {"executable", "args", "compile_s", "mem_mib"}``. When
      ``key`` is there its executable is reused (the same computation on
      other data, e.g. another exposure); otherwise ``fn`` is compiled
      (``.lower(first batch).compile()``, timed) and stored with its
      first-batch arguments, for :func:`interleaved_times`.
    key: hashable name of the computation.
    params: an optional first argument (a pytree, e.g. network parameters).
  Returns:
    ``{"outputs": {"intensity", "depth": [N, H, W]}, "compile_s", "mem_mib"
    (XLA temp + argument + output bytes), "key"}``.
  """
  import jax
  if batch < 1:
    raise ValueError(f"batch must be >= 1, got {batch}")
  n = len(inputs)
  x = _padded(inputs, batch)
  wrap = (lambda xb: (params, xb)) if params is not None else (lambda xb: (xb,))
  if key not in cache:
    args0 = wrap(jax.device_put(x[:batch]))
    t = time.perf_counter()
    compiled = jax.jit(fn).lower(*args0).compile()
    compile_s = time.perf_counter() - t
    mem = compiled.memory_analysis()
    mem_mib = (float("nan") if mem is None else
               (mem.temp_size_in_bytes + mem.argument_size_in_bytes + mem.output_size_in_bytes) / MIB)
    cache[key] = {"executable": compiled, "args": args0, "compile_s": compile_s,
                  "mem_mib": mem_mib}
  entry = cache[key]
  outs = {"intensity": [], "depth": []}
  for i in range(0, len(x), batch):
    o = entry["executable"](*wrap(jax.device_put(x[i:i + batch])))
    for k in outs:
      outs[k].append(np.asarray(o[k]))
  return {"outputs": {k: np.concatenate(v)[:n] for k, v in outs.items()},
          "compile_s": entry["compile_s"], "mem_mib": entry["mem_mib"], "key": key}


def interleaved_times(fns: dict, inputs: dict, *, rounds: int) -> dict:
  """Seconds per call of already-compiled ``fns[k](*inputs[k])``, timed round-robin.

  One untimed warm-up round, then ``rounds`` rounds of one call of every
  function each (ended by ``block_until_ready``), so a change in the
  machine's load hits every function alike and their ratios stay
  meaningful on a shared machine.

  Returns:
    ``{k: [seconds of each round]}``; take the median.
  """
  import jax
  if rounds < 1:
    raise ValueError(f"rounds must be >= 1, got {rounds}")
  for k, f in fns.items():
    jax.block_until_ready(f(*inputs[k]))
  times = {k: [] for k in fns}
  for _ in range(rounds):
    for k, f in fns.items():
      t = time.perf_counter()
      jax.block_until_ready(f(*inputs[k]))
      times[k].append(time.perf_counter() - t)
  return times


# ---------------------------------------------------------------- pipelines
def classic_pipeline(method: str, setup, stride: int, *, volume: bool = False) -> Callable:
  """``x [B, T, h, w] -> {"intensity", "depth" [B, H, W] (, "volume" [B, Z, H, W])}``.

  The evaluation protocol of :func:`nlosjax.evaluation.baselines.classic_images`: the
  under-scanned counts interpolated bilinearly onto ``setup``'s grid, the
  method's volume (``sqrt`` of f-k's albedo squared), then
  :func:`nlosjax.physics.intensity_depth`. Jittable.
  """
  import jax
  import jax.numpy as jnp

  from nlosjax.evaluation.baselines import TABLE_VARIANT, upsample_scan
  from nlosjax.physics import intensity_depth, reconstruct
  if method not in CLASSIC:
    raise ValueError(f"method must be one of {CLASSIC}, got {method!r}")

  def fn(x):
    # The methods cache their operators per Setup; built under this trace they would be
    # cached as tracers and leak into later calls. Concrete values are computed eagerly here.
    with jax.ensure_compile_time_eval():
      vol = reconstruct(upsample_scan(x, setup.grid, stride), setup, method,
                        **({"variant": TABLE_VARIANT[method]} if method in TABLE_VARIANT else {}))
    if method == "fk":
      vol = jnp.sqrt(vol)
    inten, depth = intensity_depth(vol, setup)
    out = {"intensity": inten, "depth": depth}
    if volume:
      out["volume"] = vol
    return out

  return fn


def learned_pipeline(mcfg, *, volume: bool = False) -> Callable:
  """``(params, x [B, F, T, h, w]) -> {"intensity", "depth" (, "volume")}`` of ``mcfg.module()``.

  The intensity is clamped to [0, 1] as in the main job's evaluation (USM's head is not).
  """
  import jax.numpy as jnp
  model = mcfg.module()

  def fn(params, x):
    out = model.apply({"params": params}, x)
    keys = ("intensity", "depth", "volume") if volume else ("intensity", "depth")
    return {k: jnp.clip(out[k], 0.0, 1.0) if k == "intensity" else out[k] for k in keys}

  return fn


# --------------------------------------------------------------------- data
@dataclasses.dataclass
class TestSplit:
  """The test split in memory, full scan grid.

  Attributes:
    setup: the file's Setup (no depth range).
    measurement: per sequence ``[F, T, H, W]`` float32 SPAD counts.
    clean: per sequence ``[F, T, H, W]`` float32 noise-free photons per bin (or None).
    intensity, depth: per sequence ``[F, H, W]``.
    attrs: per sequence ``efficiency``, ``ambient``, ``dark_counts`` (per bin).
    examples: ``[N, 2]`` (sequence, middle frame), middles ``1 .. F - 2``.
  """

  setup: Any
  measurement: list
  clean: list | None
  intensity: list
  depth: list
  attrs: list
  examples: np.ndarray

  @classmethod
  def load(cls, path, split: str = "test") -> "TestSplit":
    from nlosjax.data.dataset import open_dataset
    with open_dataset(path) as ds:
      names = ds.names(split)
      if not names:
        raise ValueError(f"{path}: no {split!r} sequences")
      has_clean = all(ds.has(n, "clean") for n in names)
      meas, clean, inten, depth, attrs, examples = [], [] if has_clean else None, [], [], [], []
      for s, name in enumerate(names):
        meas.append(ds.read(name, "measurement", dtype=np.float32))
        if has_clean:
          clean.append(ds.read(name, "clean", dtype=np.float32))
        inten.append(ds.read(name, "intensity", dtype=np.float32))
        depth.append(ds.read(name, "depth", dtype=np.float32))
        a = ds.sequence_attrs(name)
        attrs.append({k: float(a[k]) for k in ("efficiency", "ambient", "dark_counts")})
        F = meas[-1].shape[0]
        if F < 3:
          raise ValueError(f"{path}: sequence {name} has {F} frames; need >= 3")
        examples += [(s, m) for m in range(1, F - 1)]
      setup = ds.setup
    return cls(setup, meas, clean, inten, depth, attrs, np.asarray(examples, np.int64))

  def __len__(self):
    return len(self.examples)

  def gt(self) -> tuple[np.ndarray, np.ndarray]:
    """``(intensity [N, H, W], depth [N, H, W])`` of the middle frames."""
    return (np.stack([self.intensity[s][m] for s, m in self.examples]),
            np.stack([self.depth[s][m] for s, m in self.examples]))

  def windows(self, stride: int, frames: int, measurement: list | None = None) -> np.ndarray:
    """``[N, frames, T, h, w]`` under-scanned inputs (frame indices clipped at sequence ends).

    Scan points ``stride // 2 + stride * i`` (the model's convention).
    """
    meas = self.measurement if measurement is None else measurement
    half = frames // 2
    out = []
    for s, m in self.examples:
      idx = np.clip(np.arange(m - half, m + half + 1), 0, meas[s].shape[0] - 1)
      out.append(meas[s][idx][..., stride // 2::stride, stride // 2::stride])
    return np.stack(out).astype(np.float32)

  def renoised(self, exposure: float, seed: int = 0) -> list:
    """Per sequence ``[F, T, H, W]`` counts at ``exposure`` times the stored exposure.

    ``add_spad_noise`` of the stored noise-free transient with ``pulses =
    exposure`` (signal), ambient and dark counts times ``exposure``, the
    sequence's efficiency and the measured jitter; seeded by ``(seed, sequence)``.
    """
    import jax

    from nlosjax.physics import add_spad_noise
    if self.clean is None:
      raise ValueError("the dataset stores no clean transients; cannot vary the exposure")
    if not exposure > 0:
      raise ValueError(f"exposure must be > 0, got {exposure!r}")
    key = jax.random.key(seed)
    out = []
    for s, (clean, a) in enumerate(zip(self.clean, self.attrs)):
      out.append(np.asarray(add_spad_noise(
          jax.random.fold_in(key, s), clean, self.setup, pulses=float(exposure),
          efficiency=a["efficiency"], ambient=a["ambient"] * exposure,
          dark_counts=a["dark_counts"] * exposure, jitter="measured"), np.float32))
    return out


def scores(intensity, depth, gt_i, gt_d) -> dict:
  """``metric -> [mean, std]`` over frames: ``psnr``, ``ssim``, ``rmse``, ``mad``."""
  from nlosjax.evaluation.scores import frame_scores
  per_frame = frame_scores(intensity, depth, gt_i, gt_d)
  return {k: [float(np.mean(per_frame[k])), float(np.std(per_frame[k]))]
          for k in ("psnr", "ssim", "rmse", "mad")}


# ----------------------------------------------------------------- learned
@dataclasses.dataclass(frozen=True)
class Learned:
  """A network configuration trained by this benchmark.

  Attributes:
    name: folder name under ``WORKDIR/s<steps>``.
    label: table label.
    frames: input frames (odd).
    model: ``ModelConfig`` overrides on top of the preset's ``model`` section.
    variant: the main job's variant it is built as (``"usm"``: the preset's
      ``usm`` section and recipe, :func:`nlosjax.train.model_config_for`).
  """

  name: str
  label: str
  frames: int
  model: tuple = ()
  variant: str = "ours"


LEARNED = (
    Learned("usm", "USM", 1, variant="usm"),
    Learned("ours_s", "Ours-S", 1),
    Learned("ours", "Ours", 3),
    Learned("ours_f5", "Ours, 5 frames", 5),
    Learned("ours_w4", "Ours, width 4", 3, (("width", 4),)),
    Learned("ours_w16", "Ours, width 16", 3, (("width", 16),)),
    Learned("ours_d2", "Ours, 2 ST-Mamba blocks", 3, (("st_depth", 2),)),
    Learned("ours_n1", "Ours, N = 1", 3, (("d_state", 1),)),
    Learned("ours_n16", "Ours, N = 16", 3, (("d_state", 16),)),
)


def learned_config(config: dict, setup, spec: Learned):
  """The model config of ``spec`` on ``setup`` (the preset's model section + overrides; USM's own)."""
  from nlosjax.models.network import ModelConfig
  if spec.variant == "usm":
    from nlosjax.train import model_config_for
    return model_config_for(config, setup, "usm")
  kw = {**config.get("model", {}), **dict(spec.model), "frames": spec.frames}
  return ModelConfig(setup=setup, stride=int(config["data"]["input_stride"]), **kw)


def window_loader(config: dict, path, window: int, *, batch_size: int, seed: int):
  """The training loader of :mod:`nlosjax.train` with ``window`` adjacent input frames.

  ``window = 3`` gives exactly :class:`~nlosjax.data.dataset.TripletLoader`'s
  batches; wider windows clip frame indices at the sequence ends.
  """
  from nlosjax.data.dataset import TripletLoader

  class WindowLoader(TripletLoader):
    def triplet_frames(self, middle: int, num_frames: int) -> np.ndarray:
      return window_frames(middle, num_frames, window)

  data = config["data"]
  opts = data.get("loader", {})
  stride = int(data["input_stride"])
  return WindowLoader(path, split="train", batch_size=batch_size, stride=stride,
                      offset=stride // 2, seed=seed, shuffle=True, drop_remainder=True,
                      ends=opts.get("ends", "valid"), target=opts.get("target", "clean"),
                      in_memory=True)


def window_frames(middle: int, num_frames: int, window: int) -> np.ndarray:
  """``[window]`` frame indices centred on ``middle``, clipped to ``[0, num_frames)``."""
  if window < 1 or window % 2 == 0:
    raise ValueError(f"window must be a positive odd integer, got {window!r}")
  half = window // 2
  return np.clip(np.arange(middle - half, middle + half + 1), 0, num_frames - 1)


def train_learned(spec: Learned, config: dict, setup, root: pathlib.Path, steps: int,
                  get_loader: Callable[[], Any], log: Callable[[str], None] = print):
  """Train ``spec`` for ``steps`` AdamW steps, or restore it; returns ``(model_config, params)``.

  The main job's recipe (:func:`nlosjax.train.train_model`): the preset's
  optimiser (schedule over ``steps``), loss, batch size and seed, the same
  batches; checkpoints every 50 steps in ``root/<name>/checkpoints``, resumed
  after an interruption, refused if written by another recipe.

  Args:
    spec: the configuration.
    config: the preset (``data``, ``model``, ``train`` sections).
    setup: the dataset's full-grid Setup.
    root: checkpoint root.
    steps: the training budget.
    get_loader: returns the training loader (:func:`window_loader`, wide
      enough for ``spec.frames``); called only when training is needed.
  """
  import jax
  from jax.sharding import NamedSharding
  from jax.sharding import PartitionSpec as P
  from tqdm import tqdm

  from nlosjax.train import (
    BATCH_KEYS,
    Checkpointer,
    create_train_state,
    make_mesh,
    make_optimizer,
    make_train_step,
    select_frames,
    shard_batch,
    training_recipe,
  )
  tr = config["train"]
  batch_size, seed = int(tr["batch_size"]), int(tr.get("seed", 0))
  mcfg = learned_config(config, setup, spec)
  optim, weights = training_recipe(config, "usm" if spec.variant == "usm" else "ours")
  mesh = make_mesh()
  init_key, loop_key = jax.random.split(jax.random.key(seed))

  def init():
    return create_train_state(mcfg.module(), (batch_size,) + mcfg.input_shape()[1:],
                              make_optimizer(optim, steps), init_key, mesh)

  signature = json.dumps({"benchmark": "tradeoff", "model": repr(mcfg),
                          "optim": dataclasses.asdict(optim), "loss": dataclasses.asdict(weights),
                          "batch_size": batch_size, "seed": seed, "steps": steps}, sort_keys=True)
  vdir = root / spec.name
  ckpt = Checkpointer(vdir / "checkpoints", signature, every=50, keep=1)
  latest = ckpt.latest_step()
  if latest is not None and latest >= steps:
    # Finished: restore into shapes only (no compiled initialisation).
    replicated = NamedSharding(mesh, P())
    state = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=replicated),
                         jax.eval_shape(init))
  else:
    state = init()
  start = 0
  restored = ckpt.restore_latest(state)
  if restored is not None:
    state, start = restored
  if start < steps:
    log(f"[{spec.name}] training steps {start}..{steps} into {vdir}")
    loader = get_loader()
    step_fn = make_train_step(mcfg, weights, mesh)
    t0 = time.perf_counter()
    with tqdm(total=steps, initial=start, desc=f"train {spec.name}", unit="step",
              dynamic_ncols=True, mininterval=2.0) as bar:
      for step in range(start, steps):
        host = loader.batch(step)
        batch = {k: host[k] for k in BATCH_KEYS}
        batch["measurement"] = select_frames(batch["measurement"], mcfg.frames)
        state, metrics = step_fn(state, shard_batch(batch, mesh), jax.random.fold_in(loop_key, step))
        ckpt.save(state, step + 1, force=(step + 1 == steps))
        bar.update(1)
    loss = float(metrics["loss"])
    if not math.isfinite(loss):
      raise FloatingPointError(f"[{spec.name}] non-finite loss {loss} after {steps} steps")
    (vdir / "train.json").write_text(json.dumps(
        {"steps": steps, "final_loss": loss, "resumed_from": start,
         "train_s": round(time.perf_counter() - t0, 1)}) + "\n")
  else:
    log(f"[{spec.name}] restored step {int(state.step)} from {vdir / 'checkpoints'}")
  ckpt.close()
  return mcfg, state.params


# ------------------------------------------------------------------ gating
def depth_ranges(scene_range: tuple[float, float], max_depth: float,
                 aperture: float | None = None) -> list[tuple[str, tuple | None, float | None]]:
  """``[(label, range, aperture)]``: no range (``full``), its first half (``full/2``), the
  scenes' range ``R``, and the middle half and quarter of ``R``; with ``aperture``, also
  ``R|a`` and ``R/2|a`` (the same ranges with ``Setup.aperture``)."""
  z0, z1 = scene_range
  mid, half = 0.5 * (z0 + z1), 0.5 * (z1 - z0)
  out = [("full", None, None), ("full/2", (0.0, 0.5 * max_depth), None), ("R", (z0, z1), None),
         ("R/2", (mid - half / 2, mid + half / 2), None),
         ("R/4", (mid - half / 4, mid + half / 4), None)]
  if aperture is not None:
    out += [("R|a", (z0, z1), aperture), ("R/2|a", (mid - half / 2, mid + half / 2), aperture)]
  return out


def gated_setup(setup, rng, aperture=None):
  """``setup`` with a depth range (``None``: ungated) and an aperture."""
  su = setup if rng is None else setup.with_depth_range(*rng)
  return su if aperture is None else su.with_aperture(aperture)


def in_range_accuracy(gated: dict, ungated: dict, gt_d: np.ndarray, gated_setup, *,
                      near: float = 0.1) -> dict:
  """Depth accuracy inside a depth range, gated against ungated, on the same pixels.

  Args:
    gated, ungated: ``{"depth": [N, H, W]}`` metres, reconstructions with and
      without the depth range.
    gt_d: ``[N, H, W]`` true depth (0 = background).
    gated_setup: the Setup with the range (none: every foreground pixel).
    near: depths below this (metres) count as background (the networks'
      soft depth fades to 0 m rather than reaching it).
  Returns:
    ``pixels`` (true depth in the range, pooled over frames), ``rmse_gated``,
    ``rmse_ungated``, ``mad_gated``, ``mad_ungated`` (metres, against the
    truth over those pixels), ``missed_gated``, ``missed_ungated`` (the
    fraction of them reconstructed as background, depth below ``near``) and
    ``agreement`` (mean ``|gated - ungated|`` over them, metres); NaN when
    no pixel is in the range.
  """
  if gated_setup.depth_range is None:
    mask = gt_d > 0
  else:
    lo, hi = gated_setup.depth_range
    mask = (gt_d >= lo) & (gt_d <= hi) & (gt_d > 0)
  out = {"pixels": int(mask.sum())}
  nan = float("nan")
  for tag, r in (("gated", gated), ("ungated", ungated)):
    err = (np.asarray(r["depth"], np.float64) - gt_d)[mask]
    out[f"rmse_{tag}"] = float(np.sqrt(np.mean(err ** 2))) if err.size else nan
    out[f"mad_{tag}"] = float(np.mean(np.abs(err))) if err.size else nan
    out[f"missed_{tag}"] = float(np.mean(np.asarray(r["depth"])[mask] < near)) if err.size else nan
  diff = np.abs(np.asarray(gated["depth"], np.float64) - ungated["depth"])[mask]
  out["agreement"] = float(np.mean(diff)) if diff.size else nan
  return out


def lct_stages(setup, *, snr: float = 0.1) -> tuple[dict, Any]:
  """LCT (diffuse, Wiener ``snr``) split in three jittable stages; ``(stages, domain)``.

  ``input``: ``x [B, T, H, W]`` -> time window -> v-resampling -> lateral
  FFTs of the ``Nv`` rows; ``v-axis``: FFT of length ``Lv`` along v, Wiener
  filter, inverse FFT kept to ``Nu`` rows; ``output``: inverse lateral FFTs,
  u -> depth, clamp at 0 -> ``[B, Z, H, W]``. Composed, the same operations
  as :func:`nlosjax.physics.lct` (:func:`~nlosjax.physics.operators.lct_apply`),
  split so each can be timed.
  """
  import jax.numpy as jnp

  from nlosjax.physics.operators import lct_filter, lct_operators
  ops = lct_operators(setup, 3.0, oversample=1)
  filt = lct_filter(ops, snr)
  dom = ops.domain
  lv, h2, w2 = dom.fft_shape
  H, W = setup.grid
  t0, t1 = dom.t

  def stage_in(x):
    v = jnp.einsum("vt,bthw->bvhw", ops.to_v, x[:, t0:t1], precision="highest")
    return jnp.fft.fft(jnp.fft.rfft(v, n=w2, axis=3), n=h2, axis=2)

  def stage_v(spec):
    return jnp.fft.ifft(jnp.fft.fft(spec, n=lv, axis=1) * filt, axis=1)[:, :dom.num_u]

  def stage_out(spec):
    vol = jnp.fft.irfft(jnp.fft.ifft(spec, axis=2)[:, :, :H], n=w2, axis=3)[..., :W]
    return jnp.maximum(jnp.einsum("zu,buhw->bzhw", ops.to_z, vol, precision="highest"), 0.0)

  return {"input": stage_in, "v-axis": stage_v, "output": stage_out}, dom


def lct_stage_executables(setup, x_full: np.ndarray) -> tuple[dict, dict]:
  """Jitted :func:`lct_stages` with their inputs for ``x_full [B, T, H, W]``.

  Returns ``({stage: (fn, args)}, {"nt", "nv", "lv", "nu"})`` (the domain's bin counts).
  """
  import jax
  stages, dom = lct_stages(setup)
  fns = {k: jax.jit(f) for k, f in stages.items()}
  x = jax.device_put(x_full)
  a = fns["input"](x)
  b = fns["v-axis"](a)
  args = {"input": (x,), "v-axis": (a,), "output": (b,)}
  sizes = {"nt": dom.t[1] - dom.t[0], "nv": dom.num_v, "lv": dom.fft_shape[0], "nu": dom.num_u}
  return {k: (fns[k], args[k]) for k in fns}, sizes


def network_volume_executable(mcfg, params, batch: int) -> tuple[Callable, tuple, int]:
  """The network's volume stage alone, jitted, with a ``[batch, Tw, H, W]`` input.

  :class:`~nlosjax.models.blocks.VolumeReconstruction` (feature extraction,
  physics layer, refinement) with the trained ``params["volume"]``. Returns
  ``(fn, args, Tw)``.
  """
  import jax
  import jax.numpy as jnp

  from nlosjax.models import blocks
  vol = blocks.VolumeReconstruction(**mcfg.volume_kwargs())
  a, b = mcfg.time_window
  H, W = mcfg.setup.grid
  xt = jax.random.uniform(jax.random.key(0), (batch, b - a, H, W), jnp.float32)
  fn = jax.jit(lambda p, t: vol.apply({"params": p}, t)["intensity"])
  return fn, (params["volume"], xt), b - a


# ------------------------------------------------------------------ machine
def machine_line() -> str:
  from benchmarks.model import machine
  m = machine()
  return (f"{m['cpu']}; {m['cores']} usable cores; {m['mem_gib']:.1f} GiB; JAX backend"
          f" {m['backend']} ({m['device']}); {m['versions']}")


def load_average() -> str:
  return _machine_facts.load_average(", ")


# --------------------------------------------------------------------- run
def run(args) -> dict:
  """Every measurement; returns the JSON-able results (see the module docstring)."""
  from tqdm import tqdm

  from experiments.configs import get_config
  from nlosjax.evaluation.baselines import upsample_scan
  from nlosjax.evaluation.report import METHOD_LABELS
  from nlosjax.train import ensure_dataset, with_defaults
  t_start = time.perf_counter()
  config = with_defaults(get_config("cpu"))
  config["train"]["steps"] = args.steps
  data_path = pathlib.Path(config["data"]["path"])
  ensure_dataset(config, data_path)
  test = TestSplit.load(data_path)
  setup = test.setup
  stride = int(config["data"]["input_stride"])
  gt_i, gt_d = test.gt()
  B = args.batch
  res: dict = {"configs": [], "gating": {}, "stages": {}, "steps": args.steps, "batch": B,
               "max_depth": setup.max_depth, "wall_size": setup.wall_size, "rounds": args.repeats, "frames": len(test),
               "data": str(data_path), "knobs": sorted(args.knobs)}
  labels = {**LABELS, **METHOD_LABELS}

  def add(knob: str, name: str, label: str, kind: str, m: dict, *, capture: str = "default",
          setting: str = "") -> None:
    o = m["outputs"]
    res["configs"].append({
        "knob": knob, "name": name, "label": label, "kind": kind, "capture": capture,
        "setting": setting, "key": m["key"], "compile_s": m["compile_s"], "mem_mib": m["mem_mib"],
        **scores(o["intensity"], o["depth"], gt_i, gt_d)})

  # ---- learned configurations: trained or restored on first use
  root = pathlib.Path(args.workdir) / f"s{args.steps}"
  window = max(s.frames for s in LEARNED)
  loader_box: list = []

  def get_loader():
    if not loader_box:
      tr = config["train"]
      loader_box.append(window_loader(config, data_path, window, batch_size=int(tr["batch_size"]),
                                      seed=int(tr.get("seed", 0))))
    return loader_box[0]

  specs = {spec.name: spec for spec in LEARNED}
  models: dict = {}

  def trained(name: str):
    """``(model_config, params)`` of a learned configuration, trained or restored on first use."""
    if name not in models:
      models[name] = train_learned(specs[name], config, setup, root, args.steps, get_loader)
    return models[name]

  inputs = {f: test.windows(stride, f) for f in (1, 3, 5)}
  cache: dict = {}       # computation -> executable; every one is timed at the end

  def classic(method, s=stride, meas=None, su=setup):
    x = inputs[1][:, 0] if (s == stride and meas is None) else test.windows(s, 1, meas)[:, 0]
    return evaluate(classic_pipeline(method, su, s), x, batch=B, cache=cache,
                    key=("classic", method, s, su))

  def learned(name, mcfg=None, meas=None):
    base, params = trained(name)
    mcfg = mcfg or base
    x = inputs[mcfg.frames] if meas is None else test.windows(stride, mcfg.frames, meas)
    return evaluate(learned_pipeline(mcfg), x, batch=B, params=params, cache=cache,
                    key=("learned", name, mcfg))

  jobs: list = []        # (knob, description, callable) run in order under one progress bar
  default: dict = {}     # method -> its default-capture evaluation

  def job_method(method):
    m = classic(method) if method in CLASSIC else learned(method)
    default[method] = m
    add("method", method, labels[method], "classic" if method in CLASSIC else "learned", m,
        setting=labels[method])

  for method in CLASSIC + ("usm", "ours_s", "ours"):
    jobs.append(("method", f"method {method}", lambda method=method: job_method(method)))

  def job_density(method, s):
    n = len(range(s // 2, setup.grid[0], s))
    add("density", f"{method}@{n}x{n}", f"{LABELS[method]}, {n}x{n}", "classic",
        classic(method, s), capture=f"{n}x{n}", setting=f"{n}x{n}")

  for method in CLASSIC:
    for s in DENSITY_STRIDES:
      if s != stride:
        jobs.append(("density", f"density {method} {s}",
                     lambda method=method, s=s: job_density(method, s)))

  noisy: dict = {}

  def job_exposure(method, e):
    if e not in noisy:
      noisy.clear()
      noisy[e] = test.renoised(e, seed=1)
    m = classic(method, meas=noisy[e]) if method in CLASSIC else learned(method, meas=noisy[e])
    add("exposure", f"{method}@x{e:g}", f"{labels[method]}, exposure x{e:g}",
        "classic" if method in CLASSIC else "learned", m, capture=f"x{e:g}", setting=f"x{e:g}")

  for e in EXPOSURES:
    for method in CLASSIC + ("usm", "ours_s", "ours"):
      jobs.append(("exposure", f"exposure {method} x{e:g}",
                   lambda method=method, e=e: job_exposure(method, e)))

  for spec in LEARNED:
    if spec.name not in ("usm", "ours_s", "ours"):
      knob = "frames" if spec.model == () else "model"
      jobs.append((knob, f"{knob} {spec.name}", lambda spec=spec, knob=knob: add(
          knob, spec.name, spec.label, "learned", learned(spec.name), setting=spec.label)))

  for method in ("associative", "chunked"):
    jobs.append(("kernel", f"kernel {method}", lambda method=method: add(
        "kernel", f"ours@{method}", f"Ours, {method} scan", "learned",
        learned("ours", trained("ours")[0].replace(scan_method=method)), setting=method)))
  jobs.append(("kernel", "precision bfloat16", lambda: add(
      "kernel", "ours@bf16", "Ours, bfloat16 activations", "learned",
      learned("ours", trained("ours")[0].replace(dtype="bfloat16")), setting="bfloat16")))

  # ---- time gating: accuracy inside each range; the stage profile's executables
  ranges = depth_ranges(tuple(config["data"]["scene"]["depth_range"]), setup.max_depth,
                        args.aperture)
  res["aperture"] = args.aperture
  gating: dict = {}
  extra: dict = {}       # (name, range label) -> (fn, args): stage executables, timed with the rest

  def job_gating(method):
    gating[method] = {}
    for label, rng, ap in ranges:
      su = gated_setup(setup, rng, ap)
      if rng is None:
        m = default[method]
      elif method in CLASSIC:
        m = classic(method, su=su)
      else:
        m = learned(method, trained(method)[0].with_setup(su))
      acc = in_range_accuracy(m["outputs"], default[method]["outputs"], gt_d, su)
      sc = scores(m["outputs"]["intensity"], m["outputs"]["depth"], gt_i, gt_d)
      gating[method][label] = {"range": rng, "aperture": ap, "depth_bins": list(su.depth_bins),
                               "time_bins": list(su.time_bins), "key": m["key"],
                               "compile_s": m["compile_s"], "mem_mib": m["mem_mib"], **acc,
                               "psnr": sc["psnr"], "rmse": sc["rmse"]}
      if label == "R":
        add("gating", f"{method}@R", f"{labels[method]}, gated {rng[0]:g}-{rng[1]:g} m",
            "classic" if method in CLASSIC else "learned", m, setting=f"{rng[0]:g}-{rng[1]:g} m")

  for method in CLASSIC + ("ours",):
    jobs.append(("gating", f"gating {method}", lambda method=method: job_gating(method)))

  def job_gated_ours_s():
    z = tuple(config["data"]["scene"]["depth_range"])
    m = learned("ours_s", trained("ours_s")[0].with_setup(setup.with_depth_range(*z)))
    add("gating", "ours_s@R", f"{labels['ours_s']}, gated {z[0]:g}-{z[1]:g} m", "learned", m,
        setting=f"{z[0]:g}-{z[1]:g} m")

  jobs.append(("gating", "gating ours_s (R only)", job_gated_ours_s))

  def job_stages():
    x_full = np.asarray(upsample_scan(inputs[1][:B, 0], setup.grid, stride))
    stages: dict = {"lct": {}, "ours": {}}
    for label, rng, ap in ranges:
      su = gated_setup(setup, rng, ap)
      ex, stages["lct"][label] = lct_stage_executables(su, x_full)
      for k, v in ex.items():
        extra[(f"lct:{k}", label)] = v
      fn, fargs, tw = network_volume_executable(trained("ours")[0].with_setup(su),
                                                trained("ours")[1], B)
      extra[("ours:volume", label)] = (fn, fargs)
      stages["ours"][label] = {"tw": tw}
    res["stages"] = stages

  jobs.append(("gating", "stage profile", job_stages))

  jobs = [j for j in jobs if j[0] in args.knobs]
  with tqdm(total=len(jobs), desc="configurations", unit="job", dynamic_ncols=True) as bar:
    for _, desc, job in jobs:
      bar.set_postfix_str(desc)
      job()
      bar.update(1)
  for loader in loader_box:
    loader.close()

  # ---- every executable timed side by side
  fns = {("x",) + k: v["executable"] for k, v in cache.items()}
  fargs = {("x",) + k: v["args"] for k, v in cache.items()}
  fns.update({("s",) + k: v[0] for k, v in extra.items()})
  fargs.update({("s",) + k: v[1] for k, v in extra.items()})
  print(f"timing {len(fns)} executables in {args.repeats} interleaved rounds ...", flush=True)
  t = time.perf_counter()
  rounds = interleaved_times(fns, fargs, rounds=args.repeats)
  res["timing_s"] = time.perf_counter() - t
  res["executables"] = len(fns)
  per_call = {k[1:]: statistics.median(v) for k, v in rounds.items()}
  spread = {k[1:]: (min(v), max(v)) for k, v in rounds.items()}
  for r in res["configs"]:
    r["time"] = per_call[r["key"]] / B
    r["time_range"] = [spread[r["key"]][0] / B, spread[r["key"]][1] / B]
  for rr in gating.values():
    for g in rr.values():
      g["time"] = per_call[g["key"]] / B
  for label, _, _ in (ranges if res["stages"] else []):
    st = res["stages"]["lct"][label]
    for k in ("input", "v-axis", "output"):
      st[k] = per_call[(f"lct:{k}", label)]
    net = res["stages"]["ours"][label]
    net["volume"] = per_call[("ours:volume", label)]
    net["whole"] = gating["ours"][label]["time"] * B
    net["front"] = max(net["whole"] - net["volume"], 0.0)
  for d in [*res["configs"], *(g for rr in gating.values() for g in rr.values())]:
    d["key"] = repr(d["key"])
  res["gating"] = gating
  cache.clear()
  extra.clear()
  res["wall_s"] = time.perf_counter() - t_start
  return res


# ------------------------------------------------------------------ output
def _ms(s: float) -> str:
  return f"{1e3 * s:.1f}" if s * 1e3 < 100 else f"{1e3 * s:.0f}"


def knob_table(rows: list[dict]) -> list[str]:
  lines = ["| configuration | ms / frame | range | compile s | XLA MiB | PSNR (dB) ↑ | SSIM ↑ |"
           " depth RMSE (m) ↓ | depth MAD (m) ↓ |",
           "|---|---|---|---|---|---|---|---|---|"]
  for r in rows:
    lo, hi = r.get("time_range", (r["time"], r["time"]))
    lines.append(f"| {r['label']} | {_ms(r['time'])} | {_ms(lo)}-{_ms(hi)} | {r['compile_s']:.1f} |"
                 f" {r['mem_mib']:.1f} |"
                 f" {r['psnr'][0]:.2f} ± {r['psnr'][1]:.2f} | {r['ssim'][0]:.3f} |"
                 f" {r['rmse'][0]:.3f} | {r['mad'][0]:.3f} |")
  return lines


def pareto_points(res: dict) -> list[dict]:
  """Every configuration as a point; ``default`` capture ones are the front's candidates."""
  return [{"name": r["name"], "label": r["label"], "time": r["time"], "psnr": r["psnr"][0],
           "kind": r["kind"], "capture": r["capture"], "knob": r["knob"]} for r in res["configs"]]


def to_markdown(res: dict, cmd: str, machine: str, loads: tuple[str, str], *,
                gating: bool = True) -> str:
  """The Markdown report of :func:`run`'s results (``gating``: include the gating section)."""
  rows = res["configs"]
  pts = pareto_points(res)
  default = [p for p in pts if p["capture"] == "default"]
  front = pareto_front([p["time"] for p in default], [p["psnr"] for p in default])
  front_names = [p["name"] for p, f in zip(default, front) if f]
  rec = recommend(default)
  beats = learned_beats_classic(default)
  from experiments.provenance import git_commit
  by_name = {r["name"]: r for r in rows}
  out = [
      "# Speed and accuracy of every reconstruction knob",
      "",
      f"Produced by `{cmd}` on {datetime.date.today().isoformat()} ({res['wall_s']:.0f} s).",
      "",
      f"- Commit: {git_commit()}",
      f"- Machine: {machine}. Load average (1, 5, 15 min) before: {loads[0]}; after: {loads[1]}."
      + _load_remark(loads[0]) +
      f" Every time in this file comes from one phase in which all"
      f" {res['executables']} executables were called in turn, {res['rounds']} rounds after a"
      f" warm-up round ({res['timing_s']:.0f} s): the median is reported, and the `range` column"
      " gives the fastest and slowest round, the noise within this run. Between runs the load"
      " of the shared machine moves absolute times much more than that; ratios between rows of"
      " this file are the stable quantity.",
      f"- Data: test split of `{res['data']}`, {res['frames']} frames (8 sequences x middle frames"
      " 1-6), 32 x 32 scan grid, 128 bins of 132 ps, 2 m wall; objects at 0.5-1.5 m.",
      f"- Learned configurations: trained by this benchmark, {res['steps']} AdamW steps of batch 4"
      " each (the CPU preset's optimiser with the cosine schedule over those steps, seed 0, the"
      " main job's batches; the main job trains 300 steps, so `Ours` here is not Table 1's"
      " unless the budgets match).",
      f"- Time: jitted pipeline `input -> (intensity, depth)`, batch {res['batch']}, per frame ="
      " median call / batch; compile = `.lower().compile()` (tracing, operator construction"
      " cached per Setup, XLA). XLA MiB = `memory_analysis()` temp + argument + output bytes"
      " (constants not counted; not the process RSS).",
      "- Accuracy: mean ± std over frames of intensity PSNR; means of SSIM, depth RMSE and MAD"
      " (background 0 m), against the ground truth, as Table 1. Classic methods read the"
      " under-scanned input interpolated bilinearly to 32 x 32 (the paper's protocol).",
      "",
      "## Pareto front and recommended settings",
      "",
      "![time per frame vs PSNR](tradeoff.png)",
      "",
      "The front is taken over the configurations that read the same capture (8 x 8 scan"
      " points, the stored exposure): different reconstructions of the same data. Scan-density"
      " and exposure points (hollow in the plot) change the capture, not the reconstruction,"
      " and are shown for reference.",
      "",
      "Pareto front (fastest first): " + ", ".join(
          f"{by_name[n]['label']} ({_ms(by_name[n]['time'])} ms, {by_name[n]['psnr'][0]:.2f} dB)"
          for n in sorted(front_names, key=lambda n: by_name[n]["time"])) + ".",
      "",
      "| goal | configuration | ms / frame | PSNR (dB) | depth RMSE (m) |",
      "|---|---|---|---|---|",
  ]
  for goal in ("fastest", "balanced", "best"):
    r = by_name[rec[goal]]
    out.append(f"| {goal} | {r['label']} | {_ms(r['time'])} | {r['psnr'][0]:.2f} |"
               f" {r['rmse'][0]:.3f} |")
  out += ["", "(fastest: least time on the front; balanced: the fastest front point within 1 dB"
          " of the best PSNR; best: highest PSNR.)", ""]
  best_classic = max((p for p in default if p["kind"] == "classic"), key=lambda p: p["psnr"])
  out.append("Learned configurations on the front that are faster than every classic"
             " configuration reaching their PSNR and more accurate than every faster classic one: "
             + (", ".join(by_name[n]["label"] for n in beats) if beats else "none")
             + f". Best classic configuration: {by_name[best_classic['name']]['label']}"
             f" ({best_classic['psnr']:.2f} dB, {_ms(best_classic['time'])} ms).")
  learned_pts = [p for p in default if p["kind"] == "learned"]
  if learned_pts:
    top = max(p["psnr"] for p in learned_pts)
    denser = sorted((p for p in pts if p["kind"] == "classic" and p["psnr"] >= top),
                    key=lambda p: p["time"])
    out.append("")
    out.append(f"Across captures, the classic configurations at or above the best learned PSNR"
               f" ({top:.2f} dB, 8 x 8 scan points) are: "
               + (", ".join(f"{p['label']} ({p['psnr']:.2f} dB, {_ms(p['time'])} ms)" for p in denser)
                  if denser else "none")
               + (" -- they read 4-16x more scan points than the networks." if denser else "."))
  out.append("")

  sections = [
      ("method", "Method (default capture)", None),
      ("density", "Scan density (classic methods; the networks are trained for 8 x 8)",
       "The 8 x 8 rows are those of the method table."),
      ("exposure", "Exposure (stored noise-free transients re-noised with `add_spad_noise`;"
       " x1 is a fresh draw at the stored exposure)", "Each exposure runs the default capture's"
       " executable on other data, so its time and compile columns are that executable's."),
      ("frames", "Frames (same budget)", None),
      ("model", "Model size (same budget; default: width 8, 1 ST-Mamba block, N = 4)", None),
      ("kernel", "Scan kernel and precision (default weights; `auto` = sequential on CPU)", None),
      ("gating", "Time gating on: a Setup depth range = the scenes' 0.5-1.5 m (off: the method"
       " table)", None),
  ]
  extra_rows = {"frames": ["ours_s", "ours"], "model": ["ours"], "kernel": ["ours"]}
  for knob, title, note in sections:
    rs = [r for r in rows if r["knob"] == knob]
    if not rs:
      continue
    rs = [by_name[n] for n in extra_rows.get(knob, []) if n in by_name] + rs
    if knob == "density":
      rs = sorted(rs, key=lambda r: (CLASSIC.index(r["name"].split("@")[0]),
                                     int(r["setting"].split("x")[0])))
    out += [f"## {title}", ""] + knob_table(rs) + ([""] + [note] if note else []) + [""]
    if knob == "kernel":
      out += ["The default row (`Ours`) uses `auto`, which is `sequential` on CPU.", ""]
  if gating and res.get("gating"):
    out += gating_markdown(res)
  return "\n".join(out) + "\n"


def gating_markdown(res: dict) -> list[str]:
  """The time-gating section: times and ratios, accuracy inside the range, the stage profile."""
  from nlosjax.evaluation.report import METHOD_LABELS
  g, st = res["gating"], res["stages"]
  labels = list(next(iter(g.values())))
  halvings = [("full", "full/2"), ("R", "R/2"), ("R/2", "R/4")]
  if "R|a" in labels:
    halvings.append(("R|a", "R/2|a"))
  out = ["## Time gating by depth range", "",
         "A Setup depth range gates the time bins each method reads and crops the volume"
         " (`Setup.with_depth_range`); the networks keep their weights (`ModelConfig.with_setup`)."
         " Times are ms per frame (interleaved with every other executable, see the top).", ""]
  first = next(iter(g.values()))
  desc = []
  for lab in labels:
    r = first[lab]
    rng = _rng(r["range"]) + (f", aperture {r['aperture']:g} m" if r.get("aperture") else "")
    desc.append(f"`{lab}` = {rng} (depth bins {r['depth_bins'][0]}-{r['depth_bins'][1] - 1},"
                f" time bins {r['time_bins'][0]}-{r['time_bins'][1] - 1})")
  out += ["Ranges: " + "; ".join(desc) + ".", ""]
  out += ["| method | " + " | ".join(labels) + " | " +
          " | ".join(f"{a} / {b}" for a, b in halvings) + " |",
          "|---|" + "---|" * (len(labels) + len(halvings))]
  for method, rr in g.items():
    lab = LABELS.get(method) or METHOD_LABELS[method]
    out.append(f"| {lab} | " + " | ".join(_ms(rr[k]["time"]) for k in labels) + " | " +
               " | ".join(f"{rr[a]['time'] / rr[b]['time']:.2f}x" for a, b in halvings) + " |")
  lct, ours = g["lct"], g["ours"]
  r_lct, r_ours = lct["R"]["time"] / lct["R/2"]["time"], ours["R"]["time"] / ours["R/2"]["time"]
  f_lct = lct["full"]["time"] / lct["full/2"]["time"]
  f_ours = ours["full"]["time"] / ours["full/2"]["time"]
  with_ap = "R|a" in lct
  if with_ap:
    a_lct = lct["R|a"]["time"] / lct["R/2|a"]["time"]
    a_ours = ours["R|a"]["time"] / ours["R/2|a"]["time"]
  met = min(a_lct, a_ours) >= GOAL_HALVING if with_ap else min(r_lct, r_ours) >= GOAL_HALVING
  out += ["", f"**Goal: halving the depth range cuts the time of LCT and of the network by >="
          f" {GOAL_HALVING}x -- {'met' if met else 'not met'}"
          + (f" with an aperture of {lct['R|a']['aperture']:g} m" if with_ap else "") + ".**"
          + (f" With the aperture, R|a -> R/2|a: LCT {a_lct:.2f}x, Ours {a_ours:.2f}x." if with_ap
             else "")
          + f" Without it, halving the scenes' range R ="
          f" {_rng(lct['R']['range'])} to R/2 = {_rng(lct['R/2']['range'])}: LCT {r_lct:.2f}x,"
          f" Ours {r_ours:.2f}x. Halving the full range (0-{res['max_depth']:.3g} m ->"
          f" {_rng(lct['full/2']['range'])}): LCT {f_lct:.2f}x, Ours {f_ours:.2f}x.", ""]

  out += ["Accuracy inside the range, over the pixels whose true depth lies in it (object pixels"
          " only): depth RMSE (m) against the truth, gated / ungated reconstruction of the same"
          " pixels; missed = the share of those pixels reconstructed as background (depth < 0.1 m),"
          " gated / ungated; agree = mean |gated - ungated| depth over them (m). PSNR ="
          " whole-frame intensity PSNR (dB), ungated / gated to R (R holds every object).", "",
          "| method | " + " | ".join(f"depth RMSE {k}" for k in labels[1:]) + " | " +
          " | ".join(f"missed {k}" for k in labels[1:]) + " | " +
          " | ".join(f"agree {k}" for k in labels[1:]) + " | PSNR full / R |",
          "|---|" + "---|" * (3 * (len(labels) - 1) + 1)]
  for method, rr in g.items():
    lab = LABELS.get(method) or METHOD_LABELS[method]
    out.append(f"| {lab} | " + " | ".join(
        f"{rr[k]['rmse_gated']:.3f} / {rr[k]['rmse_ungated']:.3f}" for k in labels[1:]) + " | " +
        " | ".join(f"{rr[k]['missed_gated']:.2f} / {rr[k]['missed_ungated']:.2f}"
                   for k in labels[1:]) + " | " +
        " | ".join(f"{rr[k]['agreement']:.3f}" for k in labels[1:]) +
        f" | {rr['full']['psnr'][0]:.2f} / {rr['R']['psnr'][0]:.2f} |")

  B = res["batch"]
  out += ["", "### Where the time goes", "",
          "LCT split in three stages (`lct_stages`; ms per frame, timed side by side): `input` ="
          " time window -> v-resampling -> lateral FFTs of the Nv v-rows; `v-axis` = FFT of length"
          " Lv along v, Wiener filter, inverse FFT kept to Nu rows; `output` = inverse lateral FFTs"
          " of the Nu rows, u -> depth. Ours: the `volume` stage (feature extraction, physics layer,"
          " refinement) alone, and the `front` (extraction, ST-Mamba, cross ST-Mamba, spreading on"
          " the Tw-bin time window) = whole - volume.", "",
          "| range | LCT Nt / Nv / Lv / Nu | LCT input | v-axis | output | Ours Tw | Ours front |"
          " Ours volume |", "|---|---|---|---|---|---|---|---|"]
  for lab in labels:
    a, b = st["lct"][lab], st["ours"][lab]
    out.append(f"| {lab} | {a['nt']} / {a['nv']} / {a['lv']} / {a['nu']} | {_ms(a['input'] / B)} |"
               f" {_ms(a['v-axis'] / B)} | {_ms(a['output'] / B)} | {b['tw']} |"
               f" {_ms(b['front'] / B)} | {_ms(b['volume'] / B)} |")
  a, b = st["lct"]["R"], st["lct"]["R/2"]
  c, d = st["ours"]["R"], st["ours"]["R/2"]
  out += ["", f"From R to R/2 the LCT stages get {a['input'] / b['input']:.2f}x (input),"
          f" {a['v-axis'] / b['v-axis']:.2f}x (v-axis) and {a['output'] / b['output']:.2f}x (output)"
          f" faster; the network's front {c['front'] / max(d['front'], 1e-12):.2f}x and its volume"
          f" stage {c['volume'] / d['volume']:.2f}x.", ""]
  wall, zmax = res["wall_size"], res["max_depth"]
  rb = first["R"]
  z_far = first["R"]["range"][1]
  diag = math.sqrt(2.0) * wall
  out += ["**Why the time does not halve with the range.** A gated method must read every time"
          " bin that can hold a return from the range: from `z_min` straight ahead up to the far"
          f" edge seen from a scan point one wall diagonal ({diag:.2f} m) away, at a distance of"
          f" hypot({z_far:g}, {diag:.2f}) = {math.hypot(z_far, diag):.2f} m, beyond the histogram's"
          f" reach of {zmax:.2f} m (T c dt / 2). So every window here ends at the last bin (R: time bins"
          f" {rb['time_bins'][0]}-{rb['time_bins'][1] - 1}); halving the range only moves its"
          " start. What scales with the range is the depth side: LCT's output stage (Nu u-rows)"
          " and half of its v-axis FFT (Lv >= Nv + Nu - 1), the network's volume stage (physics"
          " layer and refinement on the depth bins). What does not: LCT's v-resampling and lateral"
          " FFTs of Nv ~ T - t0^2 / T rows, and the network's front on the Tw-bin window. Time ~"
          " a + b Z with a large a. A range makes a real difference against no range at all (the"
          " `full` column; f-k excepted) but not between two ranges of this geometry. What"
          " changes it: `Setup.aperture` bounds the lateral reach (voxel-to-scan-point offsets"
          " up to rho; cone paths beyond it are not modelled), so the window ends at"
          " hypot(z_max, rho) and Nv falls with the range (the `R|a` columns); its price is the"
          " oblique returns it ignores, measured in the accuracy table above.", ""]
  return out


def _load_remark(load_before) -> str:
  """A sentence on what the load average before the run means for the times."""
  try:
    one_minute = float(str(load_before).split(",")[0])
  except ValueError:
    return ""
  if one_minute < 1.5:
    return " The machine was otherwise quiet (1-minute load below 1.5 on 2 cores)."
  return (" Other jobs shared the cores while this ran, so times are upper bounds for an idle"
          " machine.")


def _rng(r) -> str:
  return "no range" if r is None else f"{r[0]:.3g}-{r[1]:.3g} m"


def plot(res: dict, path) -> None:
  """Time per frame (log) against intensity PSNR; front of the default-capture points drawn."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  pts = pareto_points(res)
  default = [p for p in pts if p["capture"] == "default"]
  front = pareto_front([p["time"] for p in default], [p["psnr"] for p in default])
  fig, ax = plt.subplots(figsize=(8.5, 5.5))
  colours = {"classic": "tab:blue", "learned": "tab:red"}
  for kind, marker in (("classic", "o"), ("learned", "*")):
    d = [p for p in default if p["kind"] == kind]
    ax.scatter([1e3 * p["time"] for p in d], [p["psnr"] for p in d], marker=marker,
               s=90 if kind == "learned" else 40, c=colours[kind], label=f"{kind} (default capture)",
               zorder=3)
    c = [p for p in pts if p["kind"] == kind and p["capture"] != "default"]
    ax.scatter([1e3 * p["time"] for p in c], [p["psnr"] for p in c], marker=marker,
               s=70 if kind == "learned" else 30, facecolors="none", edgecolors=colours[kind],
               alpha=0.6, label=f"{kind}, other capture (density, exposure)", zorder=2)
  fp = sorted([p for p, f in zip(default, front) if f], key=lambda p: p["time"])
  xs, ys = [], []
  for p in fp:
    if xs:
      xs.append(1e3 * p["time"])
      ys.append(ys[-1])
    xs.append(1e3 * p["time"])
    ys.append(p["psnr"])
  ax.plot(xs, ys, "k--", lw=1, label="Pareto front (default capture)", zorder=1)
  for p in fp:
    ax.annotate(p["label"], (1e3 * p["time"], p["psnr"]), textcoords="offset points",
                xytext=(4, 4), fontsize=7)
  others = [p for p in default if p not in fp and p["knob"] == "method"]
  for p in others:
    ax.annotate(p["label"], (1e3 * p["time"], p["psnr"]), textcoords="offset points",
                xytext=(4, -9), fontsize=7, color="gray")
  top = max((p["psnr"] for p in default if p["kind"] == "learned"), default=np.inf)
  for p in pts:
    if p["capture"] != "default" and p["kind"] == "classic" and p["psnr"] >= top:
      ax.annotate(p["label"], (1e3 * p["time"], p["psnr"]), textcoords="offset points",
                  xytext=(4, -3), fontsize=6, color="gray")
  ax.set_xscale("log")
  from matplotlib.ticker import FormatStrFormatter
  ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
  ax.xaxis.set_minor_formatter(FormatStrFormatter("%g"))
  ax.tick_params(axis="x", which="minor", labelsize=7)
  ax.set_xlabel("time per reconstructed frame (ms, jitted, warm; log scale)")
  ax.set_ylabel("intensity PSNR (dB)")
  ax.set_title(f"Speed vs accuracy, test split ({res['frames']} frames), 2 shared CPU cores",
               fontsize=10)
  ax.grid(True, which="both", alpha=0.3)
  ax.legend(fontsize=7, loc="lower right")
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def main(argv=None) -> dict:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--quick", action="store_true",
                      help=f"CI-sized: {QUICK_STEPS} training steps, {QUICK_REPEATS} timed calls")
  parser.add_argument("--steps", type=int, default=None,
                      help=f"training steps of every learned configuration (default {FULL_STEPS};"
                      f" --quick {QUICK_STEPS})")
  parser.add_argument("--repeats", type=int, default=None,
                      help=f"interleaved timing rounds (default {FULL_REPEATS}; --quick {QUICK_REPEATS})")
  parser.add_argument("--batch", type=int, default=8, help="frames per call (default 8)")
  parser.add_argument("--aperture", type=float, default=APERTURE,
                      help=f"Setup.aperture (m) of the R|a and R/2|a gating rows (default {APERTURE})")
  parser.add_argument("--knobs", default=",".join(KNOBS),
                      help=f"comma-separated subset of {','.join(KNOBS)} (method is always run)")
  parser.add_argument("--workdir", default=str(DEFAULT_WORKDIR),
                      help="checkpoints of the learned configurations (default runs/tradeoff)")
  parser.add_argument("--out-dir", default=str(DEFAULT_OUT_DIR),
                      help="where tradeoff.md, .json and .png go (default benchmarks/results)")
  args = parser.parse_args(argv)
  args.steps = args.steps or (QUICK_STEPS if args.quick else FULL_STEPS)
  args.repeats = args.repeats or (QUICK_REPEATS if args.quick else FULL_REPEATS)
  args.knobs = {"method"} | {k for k in args.knobs.split(",") if k}
  if not args.knobs <= set(KNOBS):
    parser.error(f"--knobs: unknown {sorted(args.knobs - set(KNOBS))}; choose from {KNOBS}")
  if args.steps < 1 or args.repeats < 1 or args.batch < 1:
    parser.error("--steps, --repeats and --batch must be >= 1")
  cmd = "python -m benchmarks.tradeoff " + " ".join(argv if argv is not None else sys.argv[1:])
  before = load_average()
  res = run(args)
  after = load_average()
  machine = machine_line()
  res.update(command=cmd.strip(), machine=machine, load_before=before, load_after=after)
  out = pathlib.Path(args.out_dir)
  out.mkdir(parents=True, exist_ok=True)
  (out / "tradeoff.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
  plot(res, out / "tradeoff.png")
  md = to_markdown(res, cmd.strip(), machine, (before, after))
  (out / "tradeoff.md").write_text(md)
  print(md)
  return res


if __name__ == "__main__":
  main()

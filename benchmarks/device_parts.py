"""The parts of ``python -m benchmarks.device`` (see its docstring): what each measures, and how.

Every part is a function ``part(ctx)`` that fills ``ctx.data`` (saved with ``ctx.save()`` after
each row, so a run cut off mid-part keeps the rows it finished) and asks ``ctx.fits(seconds,
what)`` before each costly step: a step whose estimate exceeds the time left to the part is
skipped with a note. ``--tiny`` runs the same functions on the shapes of :data:`TINY`.
"""

from __future__ import annotations

import contextlib
import gc
import importlib
import importlib.metadata
import os
import platform
import statistics
import subprocess
import time
import zlib

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import op_profile
from benchmarks import physics as physics_bench
from benchmarks import scan as scan_bench
from experiments import configs, provenance
from experiments.demo import OPTIONS as CLASSIC_OPTIONS
from nlosjax import physics, plan, platforms, train
from nlosjax.data import io
from nlosjax.physics import Setup
from nlosjax.ssm import resolve_method, selective_scan
from nlosjax.variants import OURS, OURS_S

GIB = 2.0 ** 30
#: Correctness limits. The scans run in float32 against a float64 loop: relative error (max
#: |difference| / max |reference|) of y, the final state and the seven gradients. Classic methods:
#: NCC of the max-projection with the CPU reference. The train step runs at float32 matmul
#: precision ("highest": no TF32 on GPUs) against the CPU values: relative difference of the
#: loss and of the gradients' global norm (float32 through ~100 layers, other FFT and reduction
#: orders: ~1e-5 expected, 1e-3 allowed).
SCAN_RTOL, CLASSIC_NCC, TRAIN_RTOL = 1e-4, 0.99, 1e-3
SCAN_METHODS = ("sequential", "chunked", "blockwise", "associative")
CLASSIC_METHODS = tuple(CLASSIC_OPTIONS)
DEPTH_RANGE = (0.2, 1.5)              # m, as experiments.demo
SEED = 0
#: Sizes of a full run and of ``--tiny`` (the same functions; tiny fits 2 CPU cores).
#: ``train``: the correctness train step (preset, variant, batch, Setup overrides, model
#: overrides); ``paper``: the paper-scale part's model; ``classic``: scan size and bins of
#: the classic methods' timing; ``scan_shapes``: benchmarks.scan's shapes (the paper's own are
#: added from the paper part's model; tiny: those alone, one shape); ``spatial_factor``: of the
#: shipped scan; ``cpu_tuned_prior``: the least seconds assumed for compiling the paper step's
#: CPU-tuned program and for running one step of it on the device, before its estimate is
#: scaled from the GPU path's own (conservative: the first H200 run, docs/gpu.md).
FULL = {"train": ("cpu", OURS, 2, {}, {}), "paper": ("paper", OURS, None, {}, {}),
        "classic": (128, 512), "scan_shapes": scan_bench.DEFAULT_SHAPES, "scan_repeats": 5,
        "spatial_factor": 1, "max_batch": 1024, "repeats": 5, "cpu_tuned_prior": (120.0, 20.0)}
_TINY_DATA = {"grid": 16, "num_bins": 64, "bin_width": 264e-12}
_TINY_MODEL = {"dilations": (1,), "volume_features": 1, "refine_width": 1}
TINY = {"train": ("cpu", OURS_S, 2, _TINY_DATA, _TINY_MODEL),
        "paper": ("cpu", OURS_S, 2, _TINY_DATA, _TINY_MODEL),
        "classic": (32, 128), "scan_shapes": (), "scan_repeats": 2,
        "spatial_factor": 2, "max_batch": 2, "repeats": 2, "cpu_tuned_prior": (0.0, 0.0)}
#: The paper-scale train step's two programs, in the order they are measured:
#: (key in ``paper_scale.json``, the path every ``nlosjax.platforms`` switch takes, label).
TRAIN_PATHS = (("train", platforms.ACCELERATOR, "GPU path"), ("train_cpu_tuned", platforms.CPU, "CPU-tuned path"))


def sizes(tiny: bool) -> dict:
  return TINY if tiny else FULL


def _oom(e: BaseException) -> bool:
  text = f"{type(e).__name__}: {e}"
  return "RESOURCE_EXHAUSTED" in text or "out of memory" in text.lower() or isinstance(e, MemoryError)


def _error(e: BaseException) -> str:
  first = str(e).splitlines()[0][:300] if str(e) else ""
  return ("out of memory: " if _oom(e) else "") + f"{type(e).__name__}: {first}"


def _median_time(fn, repeats: int) -> float:
  times = []
  for _ in range(repeats):
    t = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - t)
  return statistics.median(times)


def memory_stats(device=None) -> dict | None:
  try:
    return dict((device or jax.devices()[0]).memory_stats() or {}) or None
  except Exception:                                # some backends do not implement it
    return None


# ------------------------------------------------------------------- environment
def _version(dist: str) -> str | None:
  """The installed distribution's version, else the module's ``__version__``, else None."""
  try:
    return importlib.metadata.version(dist)
  except importlib.metadata.PackageNotFoundError:
    pass
  try:
    return str(importlib.import_module(dist.replace("-", "_").replace("orbax_", "orbax.")).__version__)
  except (ImportError, AttributeError):
    return None


def _driver() -> dict:
  """``nvidia-smi``'s name, driver and memory per GPU, else ``/proc/driver/nvidia/version``; {} where neither."""
  try:
    out = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total",
                          "--format=csv,noheader"], capture_output=True, text=True, timeout=20)
    if out.returncode == 0 and out.stdout.strip():
      return {"nvidia_smi": out.stdout.strip().splitlines()}
  except (OSError, subprocess.SubprocessError):
    pass
  try:
    with open("/proc/driver/nvidia/version") as f:
      return {"proc_driver": f.readline().strip()}
  except OSError:
    return {}


def environment(ctx) -> None:
  """Device kind and memory, driver, versions, host; the provenance lines the results file will carry."""
  dev = jax.devices()[0]
  d = ctx.data
  d.update(platform=dev.platform, device_kind=dev.device_kind, device_count=jax.device_count(),
           devices=[str(x) for x in jax.devices()], backend=jax.default_backend(),
           memory_stats=memory_stats(dev), driver=_driver(), tiny=ctx.tiny)
  d["plan_memory"] = dict(zip(("bytes", "source"), plan.device_memory(dev)))
  d["versions"] = {k: _version(k) for k in ("jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "chex",
                                            "numpy", "scipy", "h5py", "jax-cuda12-plugin",
                                            "jax-cuda13-plugin", "jax-cuda12-pjrt", "jax-cuda13-pjrt")}
  d["versions"]["python"] = platform.python_version()
  d["host"] = {"cpu": provenance.cpu_model(), "usable_cores": provenance.usable_cores(),
               "memory": provenance.memory_text(), "load_average": provenance.load_average(", ")}
  d["env"] = {k: v for k, v in os.environ.items() if k.startswith(("XLA_", "JAX_", "TF_", "CUDA_VISIBLE"))}
  d["provenance"] = provenance.provenance(ctx.command)
  ctx.save()
  mem = (d["memory_stats"] or {}).get("bytes_limit")
  ctx.log(f"device {d['device_kind']} ({d['platform']}, {d['device_count']} device(s)); allocator limit "
          f"{'n/a' if mem is None else f'{mem / GIB:.1f} GiB'}; jax {d['versions']['jax']}; "
          f"driver {d['driver'] or 'n/a'}; host {d['host']['cpu']}")


# ------------------------------------------------------------------- correctness
def scan_inputs(seed: int = SEED, Bt: int = 3, L: int = 37, Dch: int = 8, N: int = 4):
  """float32 ``(x, dt, A, B, C, D, h0, w)``: dt log-uniform in [0.01, 2], A in [-4, -0.1], w the loss weights."""
  rng = np.random.default_rng(seed)
  x = rng.normal(size=(Bt, L, Dch))
  dt = np.exp(rng.uniform(np.log(1e-2), np.log(2.0), (Bt, L, Dch)))
  A = -np.exp(rng.uniform(np.log(0.1), np.log(4.0), (Dch, N)))
  B, C = rng.normal(size=(Bt, L, N)), rng.normal(size=(Bt, L, N))
  D, h0, w = rng.normal(size=Dch), rng.normal(size=(Bt, Dch, N)), rng.normal(size=(Bt, L, Dch))
  return tuple(v.astype(np.float32) for v in (x, dt, A, B, C, D, h0, w))


def scan_loop(x, dt, A, B, C, D, h0, w, reverse: bool):
  """float64 NumPy loop over time of the selective scan and its adjoint, for ``loss = sum(y * w)``.

  ``h_t = exp(dt_t A) h_{t-1} + dt_t x_t B_t``, ``y_t = h_t C_t + D x_t`` (``reverse``: from the last
  step). Adjoint: ``g_t = w_t C_t + a_{t+1} g_{t+1}``; the cotangents follow in closed form.
  Returns ``(y, h_last, (gx, gdt, gA, gB, gC, gD, gh0))``.
  """
  x, dt, A, B, C, D, h0, w = (np.asarray(v, np.float64) for v in (x, dt, A, B, C, D, h0, w))
  L = x.shape[1]
  order = list(range(L - 1, -1, -1) if reverse else range(L))
  h, y = h0.copy(), D * x
  prev, decay, state = {}, {}, {}
  for t in order:
    a = np.exp(dt[:, t, :, None] * A)                                   # [Bt, Dch, N]
    prev[t] = h
    h = a * h + (dt[:, t] * x[:, t])[:, :, None] * B[:, t, None, :]
    decay[t], state[t] = a, h
    y[:, t] += np.einsum("bdn,bn->bd", h, C[:, t])
  G = np.zeros_like(h0)
  gx, gdt, gB, gC, gA = (np.zeros_like(v) for v in (x, dt, B, C, A))
  for t in reversed(order):
    g = w[:, t, :, None] * C[:, t, None, :] + G
    s = np.einsum("bdn,bn->bd", g, B[:, t])
    gla = g * prev[t] * decay[t]
    gx[:, t] = dt[:, t] * s + D * w[:, t]
    gdt[:, t] = x[:, t] * s + np.einsum("bdn,dn->bd", gla, A)
    gA += np.einsum("bdn,bd->dn", gla, dt[:, t])
    gB[:, t] = np.einsum("bdn,bd->bn", g, dt[:, t] * x[:, t])
    gC[:, t] = np.einsum("bd,bdn->bn", w[:, t], state[t])
    G = decay[t] * g
  return y, h, (gx, gdt, gA, gB, gC, np.sum(w * x, axis=(0, 1)), G)


def _rel(a, b) -> float:
  a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
  return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300))


def _scan_fn(method: str, chunk: int):
  """jit of ``(x..., w) -> ((y, h, grads) causal, (y, h, grads) reverse)`` of ``sum(y * w)``."""
  def one(reverse, x, dt, A, B, C, D, h0, w):
    def loss(*a):
      y, h = selective_scan(*a[:6], reverse=reverse, method=method, initial_state=a[6], return_state=True,
                            chunk_size=chunk)
      return jnp.sum(y * w), (y, h)
    (_, (y, h)), g = jax.value_and_grad(loss, argnums=tuple(range(7)), has_aux=True)(x, dt, A, B, C, D, h0)
    return y, h, g
  return jax.jit(lambda *a: (one(False, *a), one(True, *a)))


def shipped_scan(tiny: bool):
  """The shipped exit-sign scan (``experiments.demo``'s), depths 0.2-1.5 m; summed 2 x 2 for ``--tiny``."""
  x, setup = io.load_measurement(io.shipped_scan_path(), spatial_factor=sizes(tiny)["spatial_factor"])
  return x, setup.with_depth_range(*DEPTH_RANGE)


def classic_mip(method: str, x, setup) -> np.ndarray:
  """Max-projection along depth of ``method``'s volume (demo options; f-k square-rooted), max 1, as uint8.

  Quantised to 255 levels for a reference file of a few KB: the rounding moves the NCC by ~1e-4.
  """
  vol = np.asarray(jax.jit(lambda v: physics.reconstruct(v, setup, method, **CLASSIC_OPTIONS[method]))(x),
                   np.float64)
  if method == "fk":
    vol = np.sqrt(np.maximum(vol, 0.0))
  mip = vol.max(axis=0)
  return np.rint(255 * np.clip(mip / max(float(np.abs(mip).max()), 1e-30), 0, 1)).astype(np.uint8)


def config_for(case) -> dict:
  """A preset with ``case``'s batch, Setup and model overrides, train defaults filled in."""
  preset, _, batch, data, model = case
  cfg = configs.get_config(preset)
  cfg["data"].update(data)
  cfg["model"].update(model)
  if batch is not None:
    cfg["train"]["batch_size"] = batch
  return cfg


def setup_of(config: dict) -> Setup:
  d = config["data"]
  grid = d["grid"] if isinstance(d["grid"], (tuple, list)) else (d["grid"], d["grid"])
  return Setup(wall_size=d["wall_size"], grid=tuple(grid), bin_width=d["bin_width"], num_bins=d["num_bins"])


def synthetic_params(abstract, seed: int = SEED):
  """Deterministic parameters of the shapes in ``abstract`` (no init compiled: ~20 s of CPU saved).

  Per leaf, from a NumPy generator seeded by its path, uniform draws only (the most stable stream
  across NumPy versions, so the device and the reference see the same numbers): kernels of
  variance 1 / fan-in; Mamba's ``A_log`` S4D-real, ``D`` ones, ``dt`` biases for dt in [1e-3, 0.1];
  scales and gains ones, other leaves of standard deviation 0.02.
  """
  def leaf(path, a):
    name = str(getattr(path[-1], "key", path[-1]))
    rng = np.random.default_rng([seed, zlib.crc32(jax.tree_util.keystr(path).encode())])
    shape = tuple(a.shape)
    if name.startswith("A_log"):
      v = np.broadcast_to(np.log(np.arange(1.0, shape[-1] + 1.0)), shape)
    elif name == "D" or name.startswith("D_") or name == "scale" or name.endswith("gain"):
      v = np.ones(shape)
    elif name.startswith("dt_proj") and name.endswith("bias"):
      v = np.log(np.expm1(np.exp(np.log(1e-3) + np.log(100.0) * rng.random(shape))))
    elif "kernel" in name and len(shape) >= 2:
      v = np.sqrt(3.0 / max(int(np.prod(shape[:-1])), 1)) * (2 * rng.random(shape) - 1)
    else:
      v = 0.02 * np.sqrt(3.0) * (2 * rng.random(shape) - 1)
    return np.asarray(v, a.dtype)
  return jax.tree_util.tree_map_with_path(leaf, abstract)


def synthetic_batch(mcfg, batch: int, seed: int = SEED) -> dict:
  """A fixed batch: counts 0-3, uniform transient and intensity, depths 0.5-1.5 m (uniform draws only)."""
  rng = np.random.default_rng(seed)
  T, (H, W) = mcfg.setup.num_bins, mcfg.setup.grid
  return {"measurement": np.floor(4 * rng.random(mcfg.input_shape(batch))).astype(np.float32),
          "transient": rng.random((batch, T, H, W)).astype(np.float32),
          "intensity": rng.random((batch, H, W)).astype(np.float32),
          "depth": (0.5 + rng.random((batch, H, W))).astype(np.float32)}


@contextlib.contextmanager
def matmul_precision(precision: str | None):
  """``jax.default_matmul_precision(precision)`` while tracing (nothing for None); the config where it is absent."""
  if precision is None:
    yield
    return
  if hasattr(jax, "default_matmul_precision"):
    with jax.default_matmul_precision(precision):
      yield
    return
  old = jax.config.jax_default_matmul_precision
  jax.config.update("jax_default_matmul_precision", precision)
  try:
    yield
  finally:
    jax.config.update("jax_default_matmul_precision", old)


_COMPILED: dict = {}
#: How many compiled train steps :func:`compiled_train_step` keeps (the paper part alternates two).
KEEP_COMPILED = 2


def native_path() -> str:
  """The path ``nlosjax.platforms.by_platform`` takes without an override on this process's default device."""
  return platforms.CPU if jax.default_backend() == "cpu" else platforms.ACCELERATOR


@contextlib.contextmanager
def forced_path(path: str | None):
  """Trace under ``path``'s override (``nlosjax.platforms``) where it is not the device's own; else nothing.

  So each program is traced as the library traces it where its path is the device's own
  (the GPU path on a GPU, the CPU-tuned path on a CPU), and forced only where it is not.
  """
  if path is None or path == native_path():
    yield
    return
  with platforms.cpu_paths() if path == platforms.CPU else platforms.accelerator_paths():
    yield


def _step_key(config: dict, variant: str, precision: str | None, path: str | None) -> tuple:
  return repr(sorted(config.items())), variant, precision, path or native_path()


def is_compiled(config: dict, variant: str, precision: str | None = None, path: str | None = None) -> bool:
  """Whether :func:`compiled_train_step` holds this step already (a call costs no compile)."""
  return _step_key(config, variant, precision, path) in _COMPILED


def compiled_train_step(config: dict, variant: str, precision: str | None, path: str | None = None) -> dict:
  """The run's real train step (``plan.compile_train_step``) and the dry run's plan of it for this device.

  ``path``: :data:`nlosjax.platforms.CPU` or ``ACCELERATOR`` to trace every platform switch on
  that branch (:func:`forced_path`); None for the device's own. The last :data:`KEEP_COMPILED`
  steps are kept for the next call with the same arguments (``--tiny``'s paper part reuses the
  correctness step, the same program on a CPU).
  """
  key = _step_key(config, variant, precision, path)
  if key in _COMPILED:
    return _COMPILED[key]
  typed = train.RunConfig.from_dict(config)
  setup, mesh = setup_of(config), train.mesh_for(typed)
  mcfg = train.model_config_for(typed, setup, variant)
  t = time.perf_counter()
  with matmul_precision(precision), forced_path(path):
    compiled, abstract_state, abstract_batch = plan.compile_train_step(typed, mcfg, variant, mesh)
  compile_s = time.perf_counter() - t
  batch = int(config["train"]["batch_size"])
  # The dry run's own numbers (nlosjax.plan.dry_run builds them with this function).
  step_plan = plan._step_plan("train", compiled, mcfg, batch, mesh.devices.size, compile_s, backward=True)
  while len(_COMPILED) >= KEEP_COMPILED:
    _COMPILED.pop(next(iter(_COMPILED)))
  _COMPILED[key] = out = dict(compiled=compiled, state=abstract_state, mcfg=mcfg, mesh=mesh, batch=batch,
                              plan=step_plan, compile_s=compile_s, path=key[-1],
                              forced=key[-1] != native_path())
  return out


def train_state_for(step: dict, seed: int = SEED):
  """A train state of synthetic parameters, placed as the compiled step expects."""
  abstract = step["state"]
  params = synthetic_params(abstract.params, seed)
  state = train.TrainState.create(apply_fn=abstract.apply_fn, params=params, tx=abstract.tx)
  return jax.tree.map(lambda v, a: jax.device_put(jnp.asarray(v, a.dtype), a.sharding), state, abstract)


def train_values(tiny: bool, precision: str | None) -> dict:
  """Loss and gradient global norm of one train step on the fixed batch (``sizes(tiny)["train"]``)."""
  case = sizes(tiny)["train"]
  step = compiled_train_step(config_for(case), case[1], precision)
  data = train.shard_batch(synthetic_batch(step["mcfg"], step["batch"]), step["mesh"])
  _, m = step["compiled"](train_state_for(step), data, jax.random.key(1))
  return {"loss": float(m["loss"]), "grad_norm": float(m["l2_grads"]), "compile_s": step["compile_s"]}


def correctness_precision() -> str | None:
  """float32 matmuls: "highest" off CPU (TF32 is a GPU default); XLA:CPU computes them in float32 anyway."""
  return None if jax.default_backend() == "cpu" else "highest"


def make_reference(tiny: bool) -> dict:
  """The CPU values the correctness part compares with (``--make-reference``)."""
  x, setup = shipped_scan(tiny)
  out = {f"mip_{m}": classic_mip(m, x, setup) for m in CLASSIC_METHODS}
  v = train_values(tiny, None)
  out.update(loss=np.float64(v["loss"]), grad_norm=np.float64(v["grad_norm"]))
  return out


def _check(ctx, name: str, value: float, limit: float, ok: bool, **detail) -> None:
  ctx.data["checks"].append({"name": name, "value": value, "limit": limit, "ok": bool(ok), **detail})
  ctx.save()
  ctx.log(f"  {'ok  ' if ok else 'FAIL'} {name}: {value:.3g} (limit {limit:g})")


def _failed(ctx, name: str, limit: float, e: BaseException) -> None:
  """A check that raised: recorded as failed with the error, and the part goes on."""
  ctx.data["checks"].append({"name": name, "value": None, "limit": limit, "ok": False, "error": _error(e)})
  ctx.save()
  ctx.log(f"  FAIL {name}: {_error(e)}")


def correctness(ctx) -> None:
  """Scans vs a float64 loop; classic methods and one train step vs the CPU reference file."""
  ctx.data["checks"] = []
  ctx.data["limits"] = {"scan_rel": SCAN_RTOL, "classic_ncc": CLASSIC_NCC, "train_rel": TRAIN_RTOL}
  args = scan_inputs()
  chunk = 5                                          # divides no length: padding exercised
  ref = {rev: scan_loop(*args, reverse=rev) for rev in (False, True)}
  Bt, L, Dch = args[0].shape
  ctx.data["auto"] = resolve_method("auto", size=Bt * L * Dch * args[2].shape[-1])
  for method in SCAN_METHODS:
    try:
      out = _scan_fn(method, chunk)(*args)
    except Exception as e:                           # noqa: BLE001 - a failed check, not a failed run
      _failed(ctx, f"scan {method} vs float64 loop", SCAN_RTOL, e)
      continue
    for rev, (y, h, g) in zip((False, True), out):
      y_ref, h_ref, g_ref = ref[rev]
      errs = {"y": _rel(y, y_ref), "h_last": _rel(h, h_ref)}
      errs.update({f"d{n}": _rel(a, b) for n, a, b in zip(("x", "dt", "A", "B", "C", "D", "h0"), g, g_ref)})
      worst = max(errs.values())
      _check(ctx, f"scan {method} {'reverse' if rev else 'causal'} vs float64 loop", worst, SCAN_RTOL,
             np.isfinite(worst) and worst <= SCAN_RTOL, errors=errs)
  reference = ctx.reference()
  x, setup = shipped_scan(ctx.tiny)
  for method in CLASSIC_METHODS:
    name = f"classic {method} on the shipped scan vs CPU (max-projection NCC)"
    try:
      mip = classic_mip(method, x, setup)
    except Exception as e:                           # noqa: BLE001 - a failed check
      _failed(ctx, name, CLASSIC_NCC, e)
      continue
    r = physics_bench.ncc(mip, reference[f"mip_{method}"])
    _check(ctx, name, r, CLASSIC_NCC, np.isfinite(r) and r >= CLASSIC_NCC)
  precision = correctness_precision()
  try:
    v = train_values(ctx.tiny, precision)
  except Exception as e:                             # noqa: BLE001 - a failed check
    _failed(ctx, "train step loss and gradient norm vs CPU", TRAIN_RTOL, e)
    return
  ctx.data["train"] = {**v, "precision": precision or "default", "case": list(sizes(ctx.tiny)["train"][:3])}
  for k in ("loss", "grad_norm"):
    want = float(reference[k])
    rel = abs(v[k] - want) / max(abs(want), 1e-30)
    _check(ctx, f"train step {k} vs CPU", rel, TRAIN_RTOL, np.isfinite(v[k]) and rel <= TRAIN_RTOL,
           device=v[k], cpu=want)


# ------------------------------------------------------------------ scan kernels
def paper_scan_shapes(mcfg, batch: int) -> dict:
  """The model's SSM shapes ``Bt x L x D x N``: temporal ``(B F h w, T', D, N)``, spatial ``(B F T', h w, D, N)``."""
  a, b = mcfg.time_window
  tp = (b - a) // mcfg.extract_time_stride
  h, w = mcfg.input_grid
  n, D, N = batch * mcfg.frames, mcfg.expand * mcfg.width, mcfg.d_state
  return {"temporal": (n * h * w, tp, D, N), "spatial": (n * tp, h * w, D, N)}


def scan_kernels(ctx) -> None:
  """``benchmarks.scan``'s timing (imported) at its default shapes and the paper model's own."""
  sz = sizes(ctx.tiny)
  case = sz["paper"]
  cfg = config_for(case)
  mcfg = train.model_config_for(train.RunConfig.from_dict(cfg), setup_of(cfg), case[1])
  shapes = {"x".join(map(str, scan_bench.parse_shape(s))): "benchmarks.scan default" for s in sz["scan_shapes"]}
  for kind, s in paper_scan_shapes(mcfg, int(cfg["train"]["batch_size"])).items():
    shapes.setdefault("x".join(map(str, s)), f"paper model {kind} SSM, batch {cfg['train']['batch_size']}")
  ctx.data.update(shapes=[], repeats=sz["scan_repeats"], methods=list(scan_bench.METHODS))
  estimate = 5.0 if ctx.tiny else 30.0
  for name, origin in shapes.items():
    shape = scan_bench.parse_shape(name)
    if not ctx.fits(estimate, f"scan shape {name}"):
      continue
    t = time.perf_counter()
    Bt, L, D, N = shape
    auto = resolve_method("auto", size=Bt * L * D * N)
    ctx.log(f"scan shape {name} ({origin}), auto -> {auto}")
    try:
      rows = scan_bench.bench_shape(shape, scan_bench.METHODS, sz["scan_repeats"], None, log=ctx.log)
    except Exception as e:                           # noqa: BLE001 - an OOM at one shape is a result
      ctx.data["shapes"].append({"shape": name, "origin": origin, "auto": auto, "error": _error(e)})
      ctx.save()
      ctx.log(f"  failed: {_error(e)}")
      continue
    floor = rows[("exp floor", "fwd")]["run_s"]
    table = [{"method": m, "pass": p, "ms": r["run_s"] * 1e3, "x_floor": r["run_s"] / floor,
              "compile_s": r["compile_s"], "peak_mb": r["peak_mb"]} for (m, p), r in rows.items()]
    ctx.data["shapes"].append({"shape": name, "origin": origin, "auto": auto, "io_mb": scan_bench.io_mb(shape),
                               "rows": table})
    ctx.save()
    estimate = 1.5 * (time.perf_counter() - t)


# ------------------------------------------------------------------- paper scale
def _peak_bytes() -> int | None:
  return (memory_stats() or {}).get("peak_bytes_in_use")


def fitting_batch(p, memory: int | None) -> int | None:
  """The largest batch below ``p.batch`` whose linear estimate fits the plan's share of ``memory``, else None.

  ``nlosjax.plan``'s first fix: arguments and outputs stay, temporaries scale with the batch.
  """
  if memory is None or p.batch <= 1 or p.temp_bytes <= 0:
    return None
  fixed, per = p.peak_bytes - p.temp_bytes, p.temp_bytes / p.batch
  fits = int((plan.MEMORY_FRACTION * memory - fixed) // per)
  return fits if 1 <= fits < p.batch else None


def step_peak(before: dict, after: dict, argument_bytes: int) -> dict:
  """A step's measured peak from ``memory_stats()`` before and after it.

  Device memory held before the step by anything but its arguments (earlier parts' leftovers,
  executables' constants) is not the step's: measured = peak after - (in use before - arguments).
  ``attributable`` is False where the peak did not rise during the step (an earlier peak was higher,
  so the step's own is hidden).
  """
  if "peak_bytes_in_use" not in after:
    return {"measured_peak_bytes": None,
            "memory_note": f"{jax.devices()[0].platform}: memory_stats() gives no peak_bytes_in_use"}
  other = max(before.get("bytes_in_use", 0) - argument_bytes, 0)
  return {"peak_before": before.get("peak_bytes_in_use"), "in_use_before": before.get("bytes_in_use"),
          "peak_after": after["peak_bytes_in_use"], "measured_peak_bytes": after["peak_bytes_in_use"] - other,
          "attributable": after["peak_bytes_in_use"] > before.get("peak_bytes_in_use", 0)}


def _run_step(run: dict) -> float:
  """One call of ``run``'s compiled step, waited for; its new state kept (the step donates it). Seconds."""
  t = time.perf_counter()
  run["state"], m = run["step"]["compiled"](run["state"], run["data"], run["key"])
  jax.block_until_ready(m)
  run["loss"] = m["loss"]
  return time.perf_counter() - t


def _step_row(ctx, key: str, cfg: dict, variant: str, path: str, reduce: bool) -> tuple[dict, dict]:
  """Compile ``path``'s train step (planned peak), run one step (device peak): ``(row, run)``.

  ``row`` is ``ctx.data[key]``, saved as it fills; ``run`` holds the compiled step, its state
  and batch for :func:`_run_step`. With ``reduce``, where the dry run says the preset's batch
  does not fit, the largest batch its linear estimate fits (``plan``'s first fix) is compiled
  instead, once.
  """
  label = dict((k, lab) for k, _, lab in TRAIN_PATHS)[key]
  reused = is_compiled(cfg, variant, None, path)
  step = compiled_train_step(cfg, variant, None, path)
  p = step["plan"]
  memory, source = plan.device_memory()
  reduced_from = None
  typed = train.RunConfig.from_dict(cfg)          # the config as the dry run reads it; rebuilt below
  if reduce and plan.verdict(typed, p, memory, variant) is not None:
    fits = fitting_batch(p, memory)
    if fits is not None and ctx.fits(1.2 * step["compile_s"], f"a train step at batch {fits}"):
      reduced_from = step["batch"]
      ctx.log(f"train step: batch {reduced_from} plans {p.peak_bytes / GIB:.1f} GiB, over "
              f"{plan.MEMORY_FRACTION:.0%} of {memory / GIB:.1f} GiB: batch {fits} instead")
      cfg = {**cfg, "train": {**cfg["train"], "batch_size": fits}}
      typed = train.RunConfig.from_dict(cfg)
      reused = is_compiled(cfg, variant, None, path)
      step = compiled_train_step(cfg, variant, None, path)
      p = step["plan"]
  row = {"path": step["path"], "label": label, "forced": step["forced"], "compile_reused": reused,
         "batch": step["batch"], "batch_reduced_from": reduced_from, "compile_s": step["compile_s"],
         "planned_peak_bytes": p.peak_bytes,
         "planned": {"argument": p.argument_bytes, "output": p.output_bytes, "temp": p.temp_bytes,
                     "alias": p.alias_bytes}, "flops": p.flops, "device_memory": memory,
         "device_memory_source": source, "peak_flops": op_profile.peak_flops(jax.devices()[0].device_kind),
         "fits": plan.verdict(typed, p, memory, variant) is None, "times_s": []}
  ctx.data[key] = row
  ctx.save()
  run = {"step": step, "state": train_state_for(step), "key": jax.random.key(1),
         "data": train.shard_batch(synthetic_batch(step["mcfg"], step["batch"]), step["mesh"]), "cfg": cfg}
  jax.block_until_ready((run["state"], run["data"]))
  before = memory_stats() or {}
  row["first_step_s"] = _run_step(run)
  after = memory_stats() or {}
  row["loss"] = float(run["loss"])
  row.update(step_peak(before, after, p.argument_bytes))
  _step_time(row)
  ctx.save()
  return row, run


def _step_time(row: dict) -> None:
  """``step_s`` (median of the timed steps, else the first step) and the FLOP/s it achieves."""
  row["step_s"] = statistics.median(row["times_s"]) if row["times_s"] else row["first_step_s"]
  row["steps_timed"] = len(row["times_s"])
  row["flop_per_s"] = row["flops"] / row["step_s"] if row["flops"] and row["step_s"] > 0 else None


def _step_profile(ctx, row: dict, run: dict) -> None:
  """One more step of ``run`` under ``jax.profiler``: each HLO op's device time (``benchmarks/op_profile.py``)."""
  if not ctx.fits(3.0 * row["step_s"] + 10.0, f"the {row['label']}'s per-op profile"):
    return
  try:
    row["profile"] = op_profile.op_profile(lambda: (_run_step(run), run["loss"])[1],
                                           run["step"]["compiled"].as_text(), steps=1, top=15)
  except Exception as e:                             # noqa: BLE001 - recorded, the step's numbers stand
    row["profile"] = {"error": _error(e)}
  ctx.save()


def _log_row(ctx, row: dict) -> None:
  measured = row.get("measured_peak_bytes")
  ctx.log(f"train step, {row['label']}, batch {row['batch']}: {row['step_s']:.3f} s ({row['steps_timed']} timed); "
          f"planned {row['planned_peak_bytes'] / GIB:.2f} GiB, measured "
          f"{'n/a' if measured is None else f'{measured / GIB:.2f} GiB'}")


def cpu_tuned_estimate(ctx, gpu: dict | None, cfg: dict, variant: str) -> float:
  """Seconds to compile the CPU-tuned step and run its first step, from the GPU path's row and the priors.

  A compile not already held costs at least ``cpu_tuned_prior[0]`` and 1.2x the GPU path's; a
  step at least ``cpu_tuned_prior[1]`` and 3x the GPU path's step (its time on the device is not
  known before it runs).
  """
  prior_compile, prior_step = sizes(ctx.tiny)["cpu_tuned_prior"]
  compile_s = 0.0 if is_compiled(cfg, variant, None, platforms.CPU) else \
      max(prior_compile, 1.2 * (gpu or {}).get("compile_s", prior_compile))
  step_s = max(prior_step, 3.0 * (gpu or {}).get("step_s", prior_step))
  return compile_s + step_s + (2.0 if ctx.tiny else 10.0)


def train_paths(ctx, cfg: dict, variant: str) -> None:
  """The train step's two programs on this device, side by side (``paper_scale.json``'s ``train`` rows).

  The GPU path first (every ``nlosjax.platforms`` switch on its accelerator branch, the program
  the library runs on a GPU): compile, one step for the peak memory, timed steps, its per-op
  profile. Then, where :func:`cpu_tuned_estimate` fits the time left, the CPU-tuned path at the
  same batch (every switch on its CPU branch, forced with ``nlosjax.platforms.cpu_paths`` off a
  CPU): compile, one step, then steps of the two programs alternated, and its per-op profile
  where the time allows. ``train_paths`` in the part's data: the pairs timed alternately and the
  CPU-tuned path's median time over the GPU path's from them.
  """
  repeats = 3 if not ctx.tiny else 2
  (gpu_key, gpu_path, _), (cpu_key, cpu_path, cpu_label) = TRAIN_PATHS
  gpu = run_gpu = None
  try:
    gpu, run_gpu = _step_row(ctx, gpu_key, cfg, variant, gpu_path, reduce=True)
    for _ in range(repeats):
      if not ctx.fits(1.5 * gpu["first_step_s"], "another timed train step (GPU path)"):
        break
      gpu["times_s"].append(_run_step(run_gpu))
    _step_time(gpu)
    ctx.save()
    _step_profile(ctx, gpu, run_gpu)
    _log_row(ctx, gpu)
  except Exception as e:                             # noqa: BLE001 - recorded; the CPU-tuned path still runs
    ctx.data[gpu_key] = {**ctx.data.get(gpu_key, {}), "error": _error(e)}
    ctx.save()
    ctx.log(f"train step (GPU path) failed: {_error(e)}")
  if run_gpu is not None:                            # the same batch for both programs
    cfg = run_gpu["cfg"]
  if not ctx.fits(cpu_tuned_estimate(ctx, gpu, cfg, variant), f"the {cpu_label}'s train step"):
    return
  try:
    cpu, run_cpu = _step_row(ctx, cpu_key, cfg, variant, cpu_path, reduce=False)
    pairs = {gpu_key: [], cpu_key: []}
    if gpu is not None and "error" not in gpu:
      for _ in range(repeats):
        if not ctx.fits(1.5 * (gpu["step_s"] + cpu["first_step_s"]), "another alternated pair of train steps"):
          break
        for key, row, run in ((gpu_key, gpu, run_gpu), (cpu_key, cpu, run_cpu)):
          t = _run_step(run)
          row["times_s"].append(t)
          pairs[key].append(t)
          _step_time(row)
        ctx.data["train_paths"] = {"pairs": len(pairs[cpu_key]), "gpu_s": statistics.median(pairs[gpu_key]),
                                   "cpu_tuned_s": statistics.median(pairs[cpu_key])}
        ctx.data["train_paths"]["ratio"] = ctx.data["train_paths"]["cpu_tuned_s"] / ctx.data["train_paths"]["gpu_s"]
        ctx.save()
    _step_time(cpu)
    ctx.save()
    _step_profile(ctx, cpu, run_cpu)
    _log_row(ctx, cpu)
  except Exception as e:                             # noqa: BLE001 - recorded
    ctx.data[cpu_key] = {**ctx.data.get(cpu_key, {}), "error": _error(e)}
    ctx.save()
    ctx.log(f"train step ({cpu_label}) failed: {_error(e)}")


def _inference(ctx, mcfg, batch: int, params) -> dict:
  model = train.network(mcfg)
  x_abs = jax.ShapeDtypeStruct(tuple(mcfg.input_shape(batch)), jnp.float32)
  t = time.perf_counter()
  compiled = jax.jit(lambda p, xx: model.apply({"params": p}, xx)).lower(params, x_abs).compile()
  compile_s = time.perf_counter() - t
  p = plan._step_plan("inference", compiled, mcfg, batch, 1, compile_s, backward=False)
  x = jax.device_put(np.random.default_rng(SEED).poisson(2.0, x_abs.shape).astype(np.float32))
  t = time.perf_counter()
  jax.block_until_ready(compiled(params, x))
  first = time.perf_counter() - t
  run_s = _median_time(lambda: compiled(params, x), sizes(ctx.tiny)["repeats"])
  return {"batch": batch, "compile_s": compile_s, "first_s": first, "step_s": run_s, "fps": batch / run_s,
          "ms_per_frame": run_s * 1e3 / batch, "planned_peak_bytes": p.peak_bytes, "peak_after": _peak_bytes()}


def _inference_search(ctx, mcfg, params, batch: int, estimate: float, last: int) -> tuple[int | None, float]:
  """Inference at ``batch``, doubling up to ``last``, while each fits the budget.

  ``estimate`` is the seconds the first batch is expected to take. Returns the next batch to
  try and its estimate, so a later call continues the search; the batch is None once a
  batch failed or did not fit the budget (the search is over).
  """
  while batch <= min(last, sizes(ctx.tiny)["max_batch"]):
    if not ctx.fits(estimate, f"inference at batch {batch}"):
      return None, estimate
    t = time.perf_counter()
    try:
      row = _inference(ctx, mcfg, batch, params)
    except Exception as e:                           # noqa: BLE001 - the first failure ends the search
      ctx.data["inference"].append({"batch": batch, "error": _error(e)})
      ctx.save()
      ctx.log(f"inference batch {batch}: {_error(e)} (search stops)")
      return None, estimate
    ctx.data["inference"].append(row)
    ctx.save()
    ctx.log(f"inference batch {batch}: {row['ms_per_frame']:.2f} ms/frame, {row['fps']:.1f} frames/s")
    estimate = 2.5 * (time.perf_counter() - t)
    batch *= 2
  return batch, estimate


def paper_scale(ctx) -> None:
  """The paper preset's Ours at 128 x 128 x 512: inference at batch 1, the train step's two paths, larger batches.

  Inference at batch 1 (the frames/s goal) runs first, so the train step's compile cannot
  take its share of the budget; then the train step on the GPU path and, where the time
  allows, on the CPU-tuned path (:func:`train_paths`); the batch search continues after them.
  """
  case = sizes(ctx.tiny)["paper"]
  cfg = config_for(case)
  variant = case[1]
  mcfg = train.model_config_for(train.RunConfig.from_dict(cfg), setup_of(cfg), variant)
  s = mcfg.setup
  ctx.data.update(preset=case[0], variant=variant, setup=[*s.grid, s.num_bins], input=list(mcfg.input_shape(1)),
                  inference=[])
  jax.clear_caches()
  model = train.network(mcfg)
  abstract = jax.eval_shape(model.init, jax.random.key(0), jax.ShapeDtypeStruct(mcfg.input_shape(1), jnp.float32))
  params = jax.device_put(synthetic_params(abstract["params"]))
  batch, estimate = _inference_search(ctx, mcfg, params, 1, 15.0 if ctx.tiny else 60.0, last=1)
  if ctx.fits(20.0 if ctx.tiny else 120.0, "the train step"):
    train_paths(ctx, cfg, variant)
  _COMPILED.clear()
  gc.collect()
  if batch is not None:
    _inference_search(ctx, mcfg, params, batch, estimate, last=sizes(ctx.tiny)["max_batch"])
  ok = [r for r in ctx.data["inference"] if "fps" in r]
  ctx.data["largest_batch"] = max((r["batch"] for r in ok), default=None)
  ctx.save()


# ---------------------------------------------------------------- classic methods
def classic(ctx) -> None:
  """ms per frame of each classic method at paper scale against its FFT floor (``benchmarks.physics``)."""
  n, bins = sizes(ctx.tiny)["classic"]
  setup = physics_bench.make_setup(n, bins)
  x = jax.device_put(physics_bench.synthetic_transient(setup, SEED))
  ctx.data.update(grid=n, bins=bins, rows=[])
  estimate = 5.0 if ctx.tiny else 20.0
  for method in CLASSIC_METHODS:
    if not ctx.fits(estimate, f"classic {method}"):
      continue
    t0 = time.perf_counter()
    try:
      t = time.perf_counter()
      fn = jax.jit(lambda v, m=method: physics.reconstruct(v, setup, m)).lower(x).compile()
      compile_s = time.perf_counter() - t
      floor = jax.jit(physics_bench.fft_floor(method, setup)).lower(x).compile()
      jax.block_until_ready((fn(x), floor(x)))
      reps = sizes(ctx.tiny)["repeats"]
      run, fl = [], []
      for _ in range(reps):                          # alternate, as benchmarks.physics does
        run.append(_median_time(lambda: fn(x), 1))
        fl.append(_median_time(lambda: floor(x), 1))
      row = {"method": method, "compile_s": compile_s, "ms": statistics.median(run) * 1e3,
             "floor_ms": statistics.median(fl) * 1e3}
      row["x_floor"] = row["ms"] / row["floor_ms"]
    except Exception as e:                           # noqa: BLE001 - recorded
      row = {"method": method, "error": _error(e)}
    ctx.data["rows"].append(row)
    ctx.save()
    ctx.log(f"classic {method}: " + (row.get("error") or f"{row['ms']:.2f} ms/frame, {row['x_floor']:.2f}x floor"))
    estimate = max(estimate, 1.5 * (time.perf_counter() - t0))


def future_mechanism_study(ctx) -> None:
  """Hook for the rows of a future mechanism study: only a note in the log for now."""
  ctx.log(f"future mechanism study: not implemented (hook benchmarks.device_parts.future_mechanism_study); "
          f"{ctx.total_left():.0f} s of the budget were left")

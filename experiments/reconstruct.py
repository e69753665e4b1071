"""Reconstruct a measured capture: any classic method or the trained network, from one command.

    python -m experiments.reconstruct FILE --method lct --out runs/recon/exit_lct
    python -m experiments.reconstruct FILE --method lct --snr 0.8 --falloff retroreflective --out DIR
    python -m experiments.reconstruct meas_10min.mat --method fk --spatial-factor 4 --out DIR
    python -m experiments.reconstruct FILE --method ours --pretrained cpu --out DIR
    python -m experiments.reconstruct FILE --method model --checkpoint runs/default --out DIR
    python -m experiments.reconstruct FILE --method usm --checkpoint runs/table1 --out DIR
    python -m experiments.reconstruct FILE --method phasor --scan-stride 4 --depth-range 0.3 1.2 --out DIR

FILE is any format ``nlosjax.data.io.load_measurement`` reads, detected from its
content: O'Toole LCT ``rect_data``/``width`` (.mat v5), Stanford f-k ``meas``
(.mat v7.3, aligned with its ``tofgrid`` found next to it or given by
``--tofgrid``), NLOST ``data``, nlosjax HDF5 captures and datasets, y-tal's TAL HDF5
captures (confocal, regular planar grid).

Methods: ``fbp``, ``lct``, ``fk``, ``phasor``, ``rsd`` (``nlosjax.physics``) and
``model`` (a network trained by ``python -m experiments.train``, ST-Mamba or a
baseline, moved to the capture: the same parameters, the physics layer rebuilt for the capture's
wall, grid and bins, time summed to about the trained bin width; a video is
reconstructed frame by frame, "Ours" reading each frame with its neighbours);
each variant's name (``ours``, ``ours_s``, ``usm``, ...; :data:`nlosjax.variants.VARIANTS`)
is ``model`` with that ``--variant`` (a baseline is in a run when its ``train.variants``
holds it).

The network's weights: ``--checkpoint`` (a training run of ``python -m
experiments.train``: workdir, variant folder or checkpoints folder), else the
weights shipped inside the package, ``--pretrained NAME`` (default ``real``;
``nlosjax.inference.pretrained_names()`` lists them; ``cpu`` is trained on
the cpu preset's 32 x 32 synthetic scans). Either way the model moves to the
capture as described above (``nlosjax.inference.for_capture``).

``--scan-stride K`` under-scans the capture (interval sampling: scan points
``K // 2 + K i``, the network's convention): classic methods then run on the
sparse scan interpolated back to the full grid (the paper's protocol), ``csa``
on the sparse scan as a masked full grid (what it is made for), the
network on the sparse scan itself (its trained stride; the default for
``model``). ``--depth-range A B`` (metres) reconstructs only those depths;
``--depth-range auto`` estimates them from the capture.

Writes into ``--out``: ``volume.h5`` (``volume [Z, H, W]`` or ``[F, Z, H, W]``,
``intensity``, ``depth`` and the Setup, method, options and timings as
attributes; nlosjax's capture layout), ``intensity.png``, ``depth.png`` and
``views.png`` (front, top and side maximum projections), and prints the
time taken (load, reconstruction including operator build and compilation,
writing).
"""

from __future__ import annotations

import argparse
import ast
import json
import pathlib
import sys
import time

import numpy as np

from nlosjax.variants import FAMILY_STMAMBA, OURS, VARIANTS

#: The learned methods: ``model`` (the variant named by ``--variant``) and each variant by name.
LEARNED = ("model", *VARIANTS)
METHODS = ("fbp", "lct", "fk", "phasor", "rsd", "csa", *LEARNED)
#: Shipped weights used when neither --checkpoint nor --pretrained is given.
DEFAULT_PRETRAINED = "real"
#: Options each classic method takes (the CLI passes only those given).
METHOD_OPTIONS = {"fbp": ("falloff", "operators", "oversample"),
                  "lct": ("snr", "falloff", "operators", "oversample"),
                  "fk": ("operators",), "phasor": ("cycles", "sampling_coeff", "operators", "oversample"),
                  "rsd": ("cycles", "sampling_coeff", "ratio"),
                  "csa": ("tau_rel", "iterations", "falloff", "oversample")}


def add_weight_arguments(parser, checkpoint_help: str = "training workdir, variant folder or checkpoints"
                         " folder (default: the shipped weights of --pretrained)") -> None:
  """``--checkpoint`` and ``--pretrained NAME`` (default :data:`DEFAULT_PRETRAINED`) on
  ``parser`` (a parser or an argument group): where a command's network comes from."""
  parser.add_argument("--checkpoint", default=None, help=checkpoint_help)
  parser.add_argument("--pretrained", default=None, metavar="NAME",
                      help=f"weights shipped in the package when no --checkpoint is given (default"
                           f" {DEFAULT_PRETRAINED!r}; nlosjax.inference.pretrained_names() lists them)")


def build_parser() -> argparse.ArgumentParser:
  p = argparse.ArgumentParser(prog="python -m experiments.reconstruct", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("file", help="measured capture (see nlosjax.data.io.load_measurement)")
  p.add_argument("--method", required=True, choices=METHODS)
  p.add_argument("--out", required=True, help="output folder (created)")
  g = p.add_argument_group("reading the file")
  g.add_argument("--format", default=None, help="format name (default: detected)")
  g.add_argument("--tofgrid", default=None,
                 help="Stanford f-k: time-of-flight file (default: found next to FILE); 'none' for aligned data")
  g.add_argument("--wall-size", type=float, default=None,
                 help="wall side, metres, for formats that do not record it (f-k, NLOST: 2)")
  g.add_argument("--zero-bins", type=int, default=None, help="zero the first raw bins")
  g.add_argument("--bin-factor", type=int, default=None, help="sum this many raw bins per bin")
  g.add_argument("--num-bins", type=int, default=None, help="keep this many bins")
  g.add_argument("--spatial-factor", type=int, default=1, help="downsample the scan grid by k")
  g.add_argument("--spatial-mode", choices=("sum", "stride"), default="sum",
                 help="k x k block sums (default) or interval sampling")
  g.add_argument("--frame", default="0", help="frame index of a video / dataset sequence, or 'all'")
  g.add_argument("--setup", action="append", default=[], metavar="FIELD=VALUE",
                 help="Setup override (repeatable), e.g. depth_range=(0.3,1.2); fields the file"
                      " records may only repeat its values")
  g.add_argument("--split", default=None, help="nlosjax dataset: split")
  g.add_argument("--sequence", default=None, help="nlosjax dataset: sequence name or index")
  g = p.add_argument_group("geometry")
  g.add_argument("--scan-stride", type=int, default=None,
                 help="under-scan by K (scan points K//2 + K i); model: must be its trained stride")
  g.add_argument("--depth-range", nargs="+", default=None, metavar="A B | auto",
                 help="reconstruct depths A..B metres only; 'auto': the range estimated from the"
                      " capture (nlosjax.physics.estimate_depth_range)")
  g.add_argument("--edge-bins", type=int, default=11,
                 help="classic methods: leave the histogram's last N depth bins out of the images"
                      " (the public nlos-fk code zeroes 11; 0 keeps all)")
  g = p.add_argument_group("classic method options")
  g.add_argument("--snr", type=float, default=None, help="lct: Wiener SNR (0.1; 0.8 retroreflective)")
  g.add_argument("--falloff", choices=("diffuse", "retroreflective"), default=None,
                 help="lct, fbp: radiometric falloff; with --adapt, the forward model's (default diffuse)")
  g.add_argument("--cycles", type=float, default=None, help="phasor, rsd: wavelet cycles")
  g.add_argument("--sampling-coeff", type=float, default=None, help="phasor, rsd: wavelength / (2 spacing)")
  g.add_argument("--ratio", type=float, default=None, help="rsd: spectrum threshold")
  g.add_argument("--operators", choices=("public", "refined"), default=None,
                 help="fbp, lct, fk, phasor: the public code's operators (default: its snr gives"
                      " its image) or our refined ones (see nlosjax.physics.reconstruct)")
  g.add_argument("--oversample", type=int, default=None,
                 help="lct, fbp, phasor with --operators refined: v-bins per time bin")
  g.add_argument("--tau-rel", type=float, default=None,
                 help="csa: l1 weight as a share of max(A^T b) (the library's 0.05; the measured"
                      " protocol takes 0.1 at stride 4, 0.03 at stride 8)")
  g.add_argument("--iterations", type=int, default=None, help="csa: the most FISTA steps (200)")
  g = p.add_argument_group("model options")
  add_weight_arguments(g)
  g.add_argument("--variant", choices=tuple(VARIANTS), default=None,
                 help="--method model: which trained variant (default: with --checkpoint the first"
                      f" trained of {', '.join(VARIANTS)}; shipped weights: ours)")
  g.add_argument("--adapt", action="store_true",
                 help="fit a small part of the network (nlosjax.adaptation.DEFAULT_TRAINABLE) to this"
                      " capture before reconstructing: the forward model of its volume is made to"
                      " reproduce the counts it read, stopping on scan points held out of the fit"
                      " (default: the network as trained)")
  g.add_argument("--adapt-steps", type=int, default=40, help="--adapt: at most this many steps (40)")
  g.add_argument("--adapt-holdout", type=float, default=0.25,
                 help="--adapt: share of the read scan points held out for stopping (0.25)")
  g.add_argument("--model-bin-factor", type=int, default=None,
                 help="capture bins per network bin (default: nearest to the trained bin width)")
  from experiments import xla_cache
  xla_cache.add_argument(p)
  p.add_argument("--quiet", action="store_true", help="print only the timing line")
  return p


def _frame_arg(value: str):
  if value == "all":
    return "all"
  try:
    return int(value)
  except ValueError:
    raise SystemExit(f"--frame must be an integer or 'all', got {value!r}") from None


def enable_compilation_cache() -> str | None:
  """Persist XLA executables across runs (a repeated reconstruction skips compilation).

  The folder is :func:`experiments.xla_cache.cache_dir`'s (``NLOSJAX_CACHE_DIR``, else
  ``.cache/xla`` in a clone, else ``~/.cache/nlosjax/xla``); returns it, or None where the
  cache is off. Caching is an optimisation only: a folder that cannot be made leaves it off.
  """
  from experiments import xla_cache
  return xla_cache.enable()


def load(args):
  """``(transient [F, T, H, W] float32, Setup, single)`` as the arguments ask."""
  from nlosjax.data import io
  frame = _frame_arg(args.frame)
  options = {}
  fmt = args.format or io.detect_format(args.file)
  spec = io.FORMATS[fmt]
  if args.tofgrid is not None:
    options["tofgrid"] = False if args.tofgrid.lower() == "none" else args.tofgrid
  if args.wall_size is not None:
    options["wall_size"] = args.wall_size
  if args.split is not None:
    options["split"] = args.split
  if args.sequence is not None:
    options["sequence"] = int(args.sequence) if args.sequence.lstrip("-").isdigit() else args.sequence
  for name in options:
    if name not in spec.options:
      flag = "--" + name.replace("_", "-")
      raise ValueError(f"{args.file}: {flag} does not apply to format {fmt!r}"
                       f" (its options: {sorted(spec.options) or 'none'})")
  overrides = {}
  for item in args.setup:
    key, sep, value = item.partition("=")
    if not sep:
      raise ValueError(f"--setup {item!r}: expected FIELD=VALUE, e.g. wall_size=0.8")
    try:
      overrides[key.strip()] = ast.literal_eval(value.strip())
    except (ValueError, SyntaxError):
      raise ValueError(f"--setup {item!r}: {value!r} is not a number or tuple") from None
  transient, setup = io.load_measurement(
      args.file, format=fmt, zero_bins=args.zero_bins, bin_factor=args.bin_factor,
      num_bins=args.num_bins, spatial_factor=args.spatial_factor, spatial_mode=args.spatial_mode,
      frame=frame, setup_overrides=overrides or None, **options)
  single = transient.ndim == 3
  if single:
    transient = transient[None]
  if args.depth_range is not None:
    z0, z1 = parse_depth_range(args.depth_range, transient, setup)
    try:
      setup = setup.with_depth_range(z0, min(z1, setup.max_depth))
    except ValueError as e:
      raise ValueError(f"--depth-range {z0} {z1}: {e}") from None
  return transient, setup, single, fmt


def parse_depth_range(values: list[str], transient, setup) -> tuple[float, float]:
  """``--depth-range A B`` (metres) or ``--depth-range auto`` (estimated from ``transient``)."""
  if len(values) == 1 and values[0] == "auto":
    from nlosjax.physics import estimate_depth_range
    return estimate_depth_range(transient, setup)
  try:
    z0, z1 = (float(v) for v in values)
  except ValueError:
    raise ValueError(f"--depth-range takes two depths in metres or 'auto', got {' '.join(values)}") from None
  return z0, z1


def classic_options(args) -> dict:
  allowed = METHOD_OPTIONS[args.method]
  given = {k: getattr(args, k) for k in ("snr", "falloff", "cycles", "sampling_coeff", "ratio",
                                         "operators", "oversample", "tau_rel", "iterations")
           if getattr(args, k) is not None}
  bad = sorted(set(given) - set(allowed))
  if bad:
    flags = ", ".join("--" + b.replace("_", "-") for b in bad)
    raise ValueError(f"--method {args.method} takes no {flags} (its options: "
                     f"{', '.join('--' + a.replace('_', '-') for a in allowed) or 'none'})")
  if "operators" in given:                       # the library's name for it
    given["variant"] = given.pop("operators")
  return given


#: Depth bins at the far end of the histogram left out of the images, as the public
#: nlos-fk ``cnlos_reconstruction.m`` does (``vol(end-10:end, :, :) = 0``, "clip
#: artifacts at boundary"): there the t^4 / t^2 weighting amplifies noise.
EDGE_BINS = 11


def edge_masked(volume, setup, edge_bins: int = EDGE_BINS) -> np.ndarray:
  """``volume [..., Z, H, W]`` with the depth bins of the histogram's last ``edge_bins`` set to 0."""
  volume = np.array(volume, np.float32, copy=True)
  k0, _ = setup.depth_bins
  first = max(0, setup.num_bins - edge_bins - k0)
  if edge_bins > 0 and first < volume.shape[-3]:
    volume[..., first:, :, :] = 0.0
  return volume


def reconstruct_classic(transient, setup, method: str, options: dict, stride: int | None, *,
                        edge_bins: int = EDGE_BINS):
  """``(volume [F, Z, H, W], intensity [F, H, W], depth [F, H, W])`` of a classic method.

  With ``stride``, the capture is under-scanned (points ``stride // 2 + stride i``)
  and interpolated back to the full grid before reconstructing; ``"csa"`` instead
  takes the sparse scan as a masked full grid (``mask=``). The intensity
  and depth images leave out the histogram's last ``edge_bins`` depth bins
  (:data:`EDGE_BINS`, as the public code); f-k's volume (albedo squared) is
  square-rooted for them. The returned volume is the method's output, unmasked.
  """
  import jax

  from nlosjax import physics
  x = transient
  if method == "csa" and stride is not None and stride > 1:
    from nlosjax.physics.methods.csa import interval_mask  # CSA reads the sparse scan itself
    mask = interval_mask(setup.height, setup.width, stride)
    x, options = x * mask, {**options, "mask": mask}
  elif stride is not None and stride > 1:
    from nlosjax.evaluation.baselines import upsample_scan
    from nlosjax.models.network import underscan
    x = upsample_scan(underscan(x, stride), setup.grid, stride)
  volume = np.asarray(jax.block_until_ready(physics.reconstruct(x, setup, method, **options)))
  linear = edge_masked(np.sqrt(np.maximum(volume, 0)) if method == "fk" else volume, setup,
                       edge_bins)                              # f-k gives albedo^2
  intensity, depth = project(linear, setup)
  return volume, intensity, depth


def project(volume, setup, *, threshold: float = 0.1, background_depth: float = 0.0):
  """NumPy twin of :func:`nlosjax.physics.intensity_depth` (same recipe and threshold).

  ``volume [..., Z, H, W]`` -> ``(intensity [..., H, W] in [0, 1], depth [..., H, W] m)``.
  In NumPy because on a fresh process the JAX version's first call compiles each
  operation (over a second on 2 cores), more than the projection itself.
  """
  vol = np.asarray(volume, np.float32)
  vol = np.where(np.isfinite(vol), np.maximum(vol, 0.0), 0.0)
  mip = vol.max(axis=-3)
  peak = mip.max(axis=(-2, -1), keepdims=True)
  intensity = np.where(peak > 0, mip / np.where(peak > 0, peak, 1.0), 0.0).astype(np.float32)
  depth = setup.depths.astype(np.float32)[vol.argmax(axis=-3)]
  depth = np.where(intensity >= max(threshold, 1e-30), depth, np.float32(background_depth))
  return np.clip(intensity, 0.0, 1.0), depth.astype(np.float32)


def trained_model(args, *, check_tree: bool = True):
  """``(model_config, params, info)`` of ``--checkpoint``, else of the shipped ``--pretrained`` weights.

  ``info`` holds ``variant``, ``checkpoint`` (where the parameters came from)
  and ``step``, and for shipped weights ``pretrained`` and ``params_sha256``.
  ``check_tree=False``: shipped weights' parameter tree is left for the caller to check
  (:func:`nlosjax.inference.check_params`) on the config it runs.

  Raises:
    ValueError: both options given, or shipped weights that do not exist
      (the message lists the shipped ones).
  """
  from nlosjax import inference as cio
  if args.checkpoint is not None:
    if args.pretrained is not None:
      raise ValueError(f"--checkpoint {args.checkpoint} and --pretrained {args.pretrained}: give one")
    return cio.load_trained(args.checkpoint, args.variant)
  name, variant = args.pretrained or DEFAULT_PRETRAINED, args.variant or OURS
  shipped = cio.pretrained_names()
  if (name, variant) not in shipped:
    have = ", ".join(f"{n} ({v})" for n, v in shipped) or "none"
    raise ValueError(f"no shipped weights {name!r} of variant {variant!r} (shipped: {have}); pass"
                     " --checkpoint WORKDIR (a run of python -m experiments.train) or --pretrained cpu")
  mcfg, params, prov = cio.load_pretrained(name, variant, check_tree=check_tree)
  return mcfg, params, {"variant": variant, "checkpoint": f"nlosjax/weights/{name}-{variant}",
                        "step": prov.get("best_step"), "pretrained": name,
                        "params_sha256": prov["params_sha256"]}


def reconstruct_model(transient, setup, args, log):
  """``(volume, intensity, depth, model Setup, info)`` of the trained network on the capture."""
  from nlosjax import inference as cio
  from nlosjax.models.network import underscan
  mcfg, params, info = trained_model(args, check_tree=False)
  if args.scan_stride is not None and args.scan_stride != mcfg.stride:
    raise ValueError(f"--scan-stride {args.scan_stride}: the network at {info['checkpoint']} was"
                     f" trained on stride {mcfg.stride}")
  adapted = cio.for_capture(mcfg, setup, bin_factor=args.model_bin_factor)
  # The tree is checked on the moved config: one trace of the network's init, shared with its
  # physics operators (a model that moves has the same tree at every Setup).
  cio.check_params(adapted.model_config, params, info["checkpoint"])
  log(f"model: {info['variant']} step {info['step']} from {info['checkpoint']}; capture bins x"
      f" {adapted.bin_factor} -> {adapted.setup.num_bins} bins of"
      f" {adapted.setup.bin_width * 1e12:.0f} ps; input {adapted.model_config.input_grid} ->"
      f" output {adapted.setup.grid}; wavelet sampling_coeff"
      f" {adapted.model_config.wavelet_sampling:.3g}")
  frames = np.asarray(underscan(adapted.prepare(transient), mcfg.stride))
  fitted = None
  if args.adapt:
    if VARIANTS[info["variant"]].family != FAMILY_STMAMBA:
      raise ValueError(f"--adapt fits an ST-Mamba network, not {VARIANTS[info['variant']].label}")
    from nlosjax.adaptation import adapt
    fitted = adapt(adapted.model_config, params, frames, steps=args.adapt_steps,
                   holdout=args.adapt_holdout, falloff=args.falloff or "diffuse")
    params = fitted.params
    log(fitted.summary())
  out = cio.run_model(adapted.model_config, params, frames)
  info = {k: str(v) for k, v in info.items() if k != "config"}
  if fitted is not None:
    info["adapted"] = {"steps": fitted.steps, "best_step": fitted.best_step, "seconds": fitted.seconds,
                       "trainable": list(fitted.trainable), "holdout": args.adapt_holdout,
                       "holdout_nll": [float(fitted.holdout_nll[0]), float(fitted.holdout_nll[fitted.best_step])]}
  info["bin_factor"] = adapted.bin_factor
  info["wavelet_sampling"] = adapted.model_config.wavelet_sampling
  return out["volume"], out["intensity"], out["depth"], adapted.setup, info


# ------------------------------------------------------------------ figures
def _extent(setup):
  return [setup.scan_x[0], setup.scan_x[-1], setup.scan_y[-1], setup.scan_y[0]]


def write_figures(out: pathlib.Path, volume, intensity, depth, setup, title: str) -> None:
  """``intensity.png``, ``depth.png`` (a montage for several frames) and ``views.png`` (frame 0)."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  n = intensity.shape[0]
  cols = min(n, 4)
  rows = -(-min(n, 16) // cols)
  z0, z1 = setup.depths[0], setup.depths[-1]
  ext = _extent(setup)
  for name, images, kw, label in (
      ("intensity", intensity, dict(cmap="gray", vmin=0, vmax=1), "intensity"),
      ("depth", depth, dict(cmap="viridis", vmin=0, vmax=z1), "depth (m, 0 = background)")):
    fig, axes = plt.subplots(rows, cols, figsize=(3.8 * cols, 3.3 * rows), squeeze=False,
                             layout="constrained")
    for k, ax in enumerate(axes.ravel()):
      if k >= min(n, 16):
        ax.axis("off")
        continue
      im = ax.imshow(images[k], extent=ext, **kw)
      ax.set_xlabel("x (m)")
      ax.set_ylabel("y (m)")
      ax.set_title(f"{title}: {label}" + (f", frame {k}" if n > 1 else ""), fontsize=8)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.9)
    fig.savefig(out / f"{name}.png", dpi=110)
    plt.close(fig)
  vol = np.maximum(np.asarray(volume[0], np.float32), 0)
  vmax = float(vol.max()) or 1.0
  fig, axes = plt.subplots(1, 3, figsize=(11, 3.6))
  axes[0].imshow(vol.max(axis=0) / vmax, cmap="gray", extent=ext, vmin=0, vmax=1)
  axes[0].set(title="front (max over z)", xlabel="x (m)", ylabel="y (m)")
  axes[1].imshow(vol.max(axis=1) / vmax, cmap="gray", aspect="auto", vmin=0, vmax=1,
                 extent=[ext[0], ext[1], z1, z0])
  axes[1].set(title="top (max over y)", xlabel="x (m)", ylabel="z (m)")
  axes[2].imshow((vol.max(axis=2) / vmax).T, cmap="gray", aspect="auto", vmin=0, vmax=1,
                 extent=[z0, z1, ext[2], ext[3]])
  axes[2].set(title="side (max over x)", xlabel="z (m)", ylabel="y (m)")
  fig.suptitle(title, fontsize=9)
  fig.tight_layout()
  fig.savefig(out / "views.png", dpi=110)
  plt.close(fig)


# --------------------------------------------------------------------- main
def main(argv=None) -> dict:
  args = build_parser().parse_args(argv)
  log = (lambda *a: None) if args.quiet else print
  t_start = time.perf_counter()
  if not args.no_cache:
    enable_compilation_cache()
  from nlosjax import physics  # noqa: F401  (imported here so load_s times the file only)
  from nlosjax.data import io
  out = pathlib.Path(args.out)
  try:
    if args.adapt and args.method not in LEARNED:
      raise ValueError(f"--adapt fits a network; --method {args.method} is a classic method")
    if args.scan_stride is not None and args.scan_stride < 1:
      raise ValueError(f"--scan-stride must be >= 1, got {args.scan_stride}")
    if args.method in VARIANTS:
      if args.variant not in (None, args.method):
        raise ValueError(f"--method {args.method} reconstructs with the {args.method} variant, not"
                         f" --variant {args.variant}")
      args.variant = args.method
    options = {} if args.method in LEARNED else classic_options(args)
    t0 = time.perf_counter()
    transient, setup, single, fmt = load(args)
    t1 = time.perf_counter()
    log(f"{args.file}: format {fmt}, {transient.shape[0]} frame(s) of (T, H, W) ="
        f" {transient.shape[1:]}, wall {setup.wall_size:.4g} m, bins"
        f" {setup.bin_width * 1e12:.4g} ps, depths {setup.depths[0]:.3f}-{setup.depths[-1]:.3f} m")
    info = {}
    if args.method in LEARNED:
      volume, intensity, depth, vsetup, info = reconstruct_model(transient, setup, args, log)
    else:
      volume, intensity, depth = reconstruct_classic(transient, setup, args.method, options,
                                                     args.scan_stride, edge_bins=args.edge_bins)
      vsetup = setup
    t2 = time.perf_counter()
  except (ValueError, OSError) as e:
    from nlosjax.files import describe, one_line
    print(f"error: {one_line(describe(e) if isinstance(e, OSError) else str(e))}", file=sys.stderr)
    raise SystemExit(2) from None
  from experiments.cli import one_line_errors
  with one_line_errors():           # a full disk, a read-only --out: one line, exit status 2
    out.mkdir(parents=True, exist_ok=True)
    timings = {"load_s": t1 - t0, "reconstruct_s": t2 - t1}
    attrs = {"method": args.method, "source": str(pathlib.Path(args.file).absolute()),
             "edge_bins": 0 if args.method in LEARNED else args.edge_bins,
             "source_format": fmt, "options": options, "scan_stride": args.scan_stride or 1,
             "model": info, "command": " ".join(sys.argv if argv is None else ["reconstruct", *argv])}
    io.save_capture(out / "volume.h5", None, vsetup, overwrite=True,
                    attrs={**attrs, "timings": timings},
                    volume=volume[0] if single else volume,
                    intensity=intensity[0] if single else intensity,
                    depth=depth[0] if single else depth)
    title = f"{pathlib.Path(args.file).name}: {args.method}" + (
        f", stride {args.scan_stride}" if args.scan_stride and args.scan_stride > 1 else "")
    views = np.sqrt(np.maximum(volume, 0)) if args.method == "fk" else volume   # f-k: albedo^2
    if args.method not in LEARNED:
      views = edge_masked(views, vsetup, args.edge_bins)
    write_figures(out, views, intensity, depth, vsetup, title)
    t3 = time.perf_counter()
    timings.update(write_s=t3 - t2, total_s=t3 - t_start)
    (out / "timings.json").write_text(json.dumps(timings, indent=2) + "\n")
    fitted = info.get("adapted")
    adapted = (f" (of which adapting {fitted['seconds']:.2f} s: {fitted['steps']} steps, best {fitted['best_step']},"
               f" held-out NLL {fitted['holdout_nll'][0]:.4f} -> {fitted['holdout_nll'][1]:.4f})") if fitted else ""
    print(f"{args.method}: load {timings['load_s']:.2f} s, reconstruct {timings['reconstruct_s']:.2f} s"
          f" (operators, compilation and run){adapted}, write {timings['write_s']:.2f} s; total"
          f" {timings['total_s']:.2f} s -> {out}")
    return {"volume": volume, "intensity": intensity, "depth": depth, "setup": vsetup,
            "timings": timings}


if __name__ == "__main__":
  main()

"""Restore a trained network (ST-Mamba or USM) for inference, and move it to another capture.

:func:`load_trained` reads the parameters of the checkpoint a run chose on validation
(its ``selection.json``; else the latest) written by ``python -m experiments.train``
(``WORKDIR/<variant>/checkpoints``, orbax) and rebuilds the model config from the run's
``config.json``; it needs no optimizer state and no training data. :func:`for_capture`
moves the trained network to a measured capture: the same parameters, the physics layer
rebuilt for the capture's wall, grid and bins (the network's parameter tree
does not depend on the Setup; see :mod:`nlosjax.models.network`), with time
rebinned so the network sees bins of about its training width.

:func:`load_pretrained` reads the weights shipped inside the package
(``nlosjax/weights/<name>-<variant>/``, format in :mod:`nlosjax.pretrained`;
:func:`pretrained_names` lists them) with the same checks, and
:func:`restore_params` is the orbax reader both share with
``python -m experiments.export_weights``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from nlosjax import pretrained
from nlosjax.models.network import triplets  # noqa: F401  (re-exported: part of this module's API)
from nlosjax.physics.setup import Setup
from nlosjax.pretrained import VARIANTS  # the trained models a run folder holds: one source
from nlosjax.variants import OURS


def _holds_checkpoint(ckpt: pathlib.Path) -> bool:
  """Whether an orbax ``checkpoints`` folder holds at least one step."""
  return ckpt.is_dir() and any(c.name.isdigit() for c in ckpt.iterdir())


def find_checkpoints(path, variant: str | None = None) -> tuple[pathlib.Path, str, pathlib.Path]:
  """Locate a trained variant: ``(workdir, variant, checkpoints folder)``.

  Args:
    path: a main-job workdir (``config.json`` plus a folder per trained variant),
      one variant's folder (``WORKDIR/ours``) or its ``checkpoints`` folder.
    variant: a name of :data:`nlosjax.variants.VARIANTS`; required only when ``path``
      is a workdir holding several (default there: the first trained in the registry's
      order, ``"ours"`` first).
  Raises:
    ValueError: naming ``path`` when it is not a trained run or the variant is missing.
  """
  if variant is not None and variant not in VARIANTS:
    raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
  p = pathlib.Path(path).absolute()
  if not p.is_dir():
    raise ValueError(f"{p}: no such checkpoint folder")
  if p.name == "checkpoints":
    p = p.parent
  if p.name in VARIANTS and (p.parent / "config.json").is_file():
    if variant is not None and variant != p.name:
      raise ValueError(f"{p}: is the {p.name!r} folder but variant {variant!r} was asked for")
    workdir, variants = p.parent, [p.name]
  elif (p / "config.json").is_file():
    workdir, variants = p, [variant] if variant else list(VARIANTS)
  else:
    raise ValueError(f"{p}: not a training run: expected a workdir with config.json (written by"
                     f" python -m experiments.train) or one of its folders {VARIANTS}")
  for v in variants:
    ckpt = workdir / v / "checkpoints"
    if _holds_checkpoint(ckpt):
      return workdir, v, ckpt
  raise ValueError(f"{p}: no checkpoint of variant(s) {variants} under {workdir}")


def load_trained(path, variant: str | None = None, *, step: int | None = None,
                 folder: str | None = None):
  """Restore a trained variant's parameters: ``(model_config, params, info)``.

  The model config is rebuilt from the run's ``config.json`` for the
  training Setup (:func:`nlosjax.train.model_config_for`); the checkpoint's
  recorded model config (``repr``) must match it, the restored parameter
  tree must have the shapes that config initialises, and the recorded
  parameter-tree fingerprint (when present) must match, else ValueError.
  Unlike resuming a run (:func:`nlosjax.train.train_model`, which rebuilds and
  compiles the full train state and checks the optimizer and loss settings),
  this reads only the parameters and compiles nothing.

  Args:
    path, variant: see :func:`find_checkpoints`.
    step: checkpoint step (default: the step the run chose on validation,
      ``selection.json`` of the model folder, restored from ``checkpoints`` or,
      when pruned there, ``best_checkpoint``; without a selection the latest).
    folder: the model's folder in the workdir when it is not the variant's own,
      e.g. ``"ours-seed1"`` (another training seed, :func:`seed_folders`).
  Returns:
    ``(ModelConfig, params, info)``; ``info`` holds ``workdir``, ``variant``,
    ``checkpoint`` (folder), ``step``, ``config`` (the run's ``config.json``, a dict:
    :meth:`~nlosjax.train.RunConfig.from_dict` reads it) and
    ``selected_on_validation`` (the step came from ``selection.json``).
  Raises:
    ValueError: naming the folder for a missing, unreadable or mismatched checkpoint.
  """
  from nlosjax import train
  from nlosjax.train.stopping import BEST_FOLDER

  workdir, variant, ckpt = find_checkpoints(path, variant)
  if folder is not None:
    ckpt = workdir / folder / "checkpoints"
    if not _holds_checkpoint(ckpt):
      raise ValueError(f"{ckpt}: no checkpoint there")
  try:
    config = json.loads((workdir / "config.json").read_text())
    typed = train.RunConfig.from_dict(config)
    train_setup = training_setup(typed)
  except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
    raise ValueError(f"{workdir / 'config.json'}: not a usable run config ({e})") from None
  mcfg = train.model_config_for(typed, train_setup, variant)
  selected = None
  if step is None:
    selection = train.read_selection(ckpt.parent)
    if selection and "step" in selection:
      step = selected = int(selection["step"])
      best = ckpt.parent / BEST_FOLDER
      if not (ckpt / str(step)).is_dir() and (best / str(step)).is_dir():
        ckpt = best
  params, restored = restore_params(ckpt, mcfg, step=step, config_file=workdir / "config.json")
  where, step = restored["checkpoint"], restored["step"]
  info = {"workdir": workdir, "variant": variant, "checkpoint": where, "step": int(step),
          "config": config, "selected_on_validation": selected is not None}
  return mcfg, params, info


def training_setup(config) -> Setup:
  """The full-grid Setup a run trained on, from its config's ``data`` section (wall, grid, bins).

  ``config``: a :class:`~nlosjax.train.RunConfig` (a run's ``config.json`` is read by
  :meth:`~nlosjax.train.RunConfig.from_dict`).

  Raises:
    KeyError, ValueError: a config without a usable ``data`` section (callers name the file).
  """
  return config.data.setup()


def restore_params(ckpt, model_config, *, step: int | None = None,
                   config_file=None) -> tuple[dict, dict]:
  """The parameters of one orbax checkpoint, checked against ``model_config``; compiles nothing.

  Reads the ``state`` item (``{"params", "opt_state", "step"}``) and the
  ``meta`` item (the run signature, :func:`nlosjax.train.run_signature`) of a
  :class:`~nlosjax.train.Checkpointer` folder. The recorded model config (a
  field-by-field record, or the ``repr`` older checkpoints hold) must match
  ``model_config`` (:func:`nlosjax.train.compare_model`: equal fields, and a
  field the checkpoint predates at its default); the parameter tree must have the shapes
  ``model_config`` initialises; the recorded parameter fingerprint
  (:func:`nlosjax.train.param_fingerprint`, when recorded) must match.

  Args:
    ckpt: an orbax checkpoint folder (``.../checkpoints`` or ``.../best_checkpoint``).
    model_config: the config the checkpoint must have been written by.
    step: the step to restore (default: the latest).
    config_file: the file ``model_config`` was rebuilt from (named in errors).
  Returns:
    ``(params, info)``: params a nested dict of float32 ``jax.Array``; info
    ``{"checkpoint": step folder, "step", "recorded_model": the recorded record
    or repr, or None, "added_fields": [fields the checkpoint predates]}``.
  Raises:
    ValueError: naming the folder for a missing step, an unreadable checkpoint or a mismatch.
  """
  import orbax.checkpoint as ocp

  from nlosjax import train
  from nlosjax.train.checkpoint import quiet_orbax, short_error, tree_digest
  ckpt = pathlib.Path(ckpt).absolute()            # orbax wants absolute paths
  absl_logger = logging.getLogger("absl")
  level = absl_logger.level
  absl_logger.setLevel(logging.ERROR)      # orbax warns that a read-only manager cannot save
  try:
    options = ocp.CheckpointManagerOptions(read_only=True, create=False,
                                           cleanup_tmp_directories=False)
    manager = ocp.CheckpointManager(ckpt, options=options)
  except BaseException:
    absl_logger.setLevel(level)
    raise
  try:
    step = manager.latest_step() if step is None else int(step)
    if step is None or step not in manager.all_steps():
      raise ValueError(f"{ckpt}: no checkpoint step {step} (steps: {sorted(manager.all_steps())})")
    where = ckpt / str(step)
    try:
      with quiet_orbax():
        meta = manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
        item = manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore()))["state"]
    except Exception as e:  # orbax raises many types for a damaged folder
      raise ValueError(f"checkpoint {where} is unreadable ({short_error(e)}); {DAMAGED_CHECKPOINT}") from None
  finally:
    manager.close()
    absl_logger.setLevel(level)
  recorded_digest = meta.get("params_digest") if isinstance(meta, dict) else None
  if recorded_digest is not None and tree_digest(item["params"]) != recorded_digest:
    raise ValueError(f"checkpoint {where}: its parameters do not match the digest saved with them (the"
                     f" files are damaged); {DAMAGED_CHECKPOINT}")
  signature = _signature(meta.get("model_config") if isinstance(meta, dict) else None)
  recorded = signature.get("model")
  added = []
  if recorded is not None:
    try:
      differ, added = train.compare_model(recorded, model_config)
    except ValueError as e:
      differ = [str(e)]
    if differ:
      source = config_file if config_file is not None else "the run config"
      raise ValueError(f"checkpoint {where} was written by another model config than {source}"
                       " gives:\n  " + "\n  ".join(differ))
  params = jax.tree.map(jnp.asarray, item["params"])
  _check_tree(where, params, _expected_tree(model_config))
  if "params" in signature and signature["params"] != train.param_fingerprint(params):
    raise ValueError(f"checkpoint {where}: its parameter-tree fingerprint {signature['params']}"
                     f" differs from the restored tree's {train.param_fingerprint(params)} (written by"
                     " another version of the model code?)")
  return params, {"checkpoint": where, "step": int(step), "recorded_model": recorded,
                  "added_fields": added}


#: What to do about a checkpoint that does not restore (:func:`restore_params`).
DAMAGED_CHECKPOINT = ("restore the run folder from a copy, or train the model again (move its folder "
                      "away and rerun the training command)")


def _expected_tree(model_config):
  """The parameter tree's shapes ``model_config`` initialises (``jax.eval_shape``: traced, not
  compiled; the trace is kept per config and shared with its physics operators')."""
  return model_config.param_shapes()


def pretrained_names(root=None) -> list[tuple[str, str]]:
  """``(name, variant)`` of every set of weights shipped in ``nlosjax/weights/`` (or ``root``), sorted."""
  return pretrained.shipped(root)


def load_pretrained(name: str = "cpu", variant: str = OURS, *, setup: Setup | None = None,
                    root=None, check_tree: bool = True):
  """Weights shipped inside the package: ``(model_config, params, provenance)``; compiles nothing.

  Reads ``nlosjax/weights/<name>-<variant>/`` (:mod:`nlosjax.pretrained`:
  ``params.npz`` and ``provenance.json``) and rebuilds the model config from
  the provenance's run config as :func:`load_trained` does
  (:func:`nlosjax.train.model_config_for` for the training Setup). Checked,
  each a ValueError naming the file: the sha256 of ``params.npz``, that the
  rebuilt config matches the recorded ``model_config``
  (:func:`nlosjax.train.compare_model`), that the
  parameter tree has the shapes the config initialises (``jax.eval_shape``),
  and the recorded parameter-tree fingerprint.

  Args:
    name: the weights' name, e.g. ``"cpu"`` (trained on the cpu preset's data:
      32 x 32 scans of a 2 m wall, 128 bins of 132 ps, input stride 4);
      :func:`pretrained_names` lists them.
    variant: ``"ours"`` (three frames), ``"ours_s"`` (one frame), ``"usm"``, ``"lfe"`` or ``"ik"``.
    setup: move the model to this full-grid Setup
      (:meth:`~nlosjax.models.network.ModelConfig.with_setup`: the same
      parameters, the physics layer rebuilt); default: the training Setup. Its
      bin width must be the trained one (ValueError otherwise); for a measured
      capture with other bins use :func:`for_capture`, which rebins it.
    root: the folder holding the weights folders (default: the package's; tests).
    check_tree: check the parameter tree against the one the rebuilt config initialises (a
      trace of the network's ``init``). ``False`` leaves that check to the caller, who then
      runs :func:`check_params` on the config it moves the model to (for a model that moves,
      :func:`setup_dependent_params` is empty, so the tree is the same there), sharing that
      trace with the moved config's physics operators; the sha256 and fingerprint checks
      still run.
  Returns:
    ``(ModelConfig, params, provenance)``: params a nested dict of float32
    ``jax.Array`` (the Flax ``params`` collection); provenance the dict of
    ``provenance.json`` (training command, commit, config, validation scores, ...).
  Raises:
    ValueError: unknown ``name``/``variant`` (listing the shipped ones), or a
      file that fails a check above.
  """
  from nlosjax import train
  if variant not in VARIANTS:
    raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
  folder = pretrained.weights_folder(name, variant, root)
  damaged = folder.is_dir() or folder.with_name(f".{folder.name}.old").is_dir()
  if (name, variant) not in pretrained.shipped(root) and not damaged:   # read_weights names a damaged one
    have = ", ".join(f"{n} ({v})" for n, v in pretrained.shipped(root)) or "none"
    raise ValueError(f"no shipped weights {name!r} of variant {variant!r} ({folder}); shipped:"
                     f" {have}")
  params, prov = pretrained.read_weights(folder)
  where = folder / pretrained.PROVENANCE_FILE
  if (prov["name"], prov["variant"]) != (name, variant):
    raise ValueError(f"{where}: records weights {prov['name']!r} of variant {prov['variant']!r}, but"
                     f" lies in the folder of {name!r} ({variant!r})")
  try:
    config = train.RunConfig.from_dict(prov["config"])
    mcfg = train.model_config_for(config, training_setup(config), variant)
  except (KeyError, TypeError, ValueError) as e:
    raise ValueError(f"{where}: its config does not rebuild a model ({type(e).__name__}: {e})") from None
  try:
    differ = train.compare_model(prov["model_config"], mcfg)[0]
  except ValueError as e:
    differ = [str(e)]
  if differ:
    raise ValueError(f"{where}: the model config rebuilt from its config differs from the one"
                     " recorded (another version of nlosjax, or an edited file):\n  "
                     + "\n  ".join(differ))
  params = jax.tree.map(jnp.asarray, params)
  if check_tree:
    _check_tree(folder / pretrained.PARAMS_FILE, params, _expected_tree(mcfg), what="weights")
  fingerprint = train.param_fingerprint(params)
  if prov["param_fingerprint"] != fingerprint:
    raise ValueError(f"{where}: parameter-tree fingerprint {prov['param_fingerprint']} recorded, the"
                     f" tree read has {fingerprint}")
  if setup is not None and setup != mcfg.setup:
    if not isinstance(setup, Setup):
      raise ValueError(f"setup must be a nlosjax.physics.Setup, got {type(setup).__name__}")
    if not np.isclose(setup.bin_width, mcfg.setup.bin_width, rtol=1e-9, atol=0.0):
      raise ValueError(f"{where}: trained on {mcfg.setup.bin_width:g} s bins, the setup has"
                       f" {setup.bin_width:g} s ones; the network reads its trained bin width:"
                       " use nlosjax.inference.for_capture(model_config, capture) to rebin"
                       " a capture to it")
    mcfg = mcfg.with_setup(setup)
  return mcfg, params, prov


def seed_folders(workdir, variant: str) -> list[str]:
  """The folders of ``variant``'s trained models in a main-job workdir: its own, then ``-seed<k>``.

  Only folders holding a checkpoint count; ordered by seed.
  """
  workdir = pathlib.Path(workdir)
  trained = lambda name: _holds_checkpoint(workdir / name / "checkpoints")
  extra = sorted((p.name for p in workdir.glob(f"{variant}-seed*")
                  if p.name[len(variant) + 5:].isdigit() and trained(p.name)),
                 key=lambda n: int(n[len(variant) + 5:]))
  return ([variant] if trained(variant) else []) + extra


def load_run(path, *, setup: Setup | None = None, seeds: bool = False,
             log=print) -> tuple[dict, dict]:
  """Every trained variant of a run, for evaluation: ``(config, variant -> (model_config, params))``;
  ``config`` is the run's ``config.json`` (a dict; :meth:`~nlosjax.train.RunConfig.from_dict` reads it).

  ``path`` as in :func:`find_checkpoints`: a workdir gives each variant that
  has a checkpoint, a variant's folder gives that one. Each variant's
  checkpoint is the one its ``selection.json`` names (chosen on validation by
  the main job), else the latest. With ``setup`` the
  models move to it (:meth:`~nlosjax.models.network.ModelConfig.with_setup`:
  the same parameters, the physics layer rebuilt), e.g. a dataset file's
  Setup; without it they keep the training Setup.

  With ``seeds=True`` (a workdir only) each variant maps to the list of its
  training seeds' ``(model_config, params)`` (:func:`seed_folders`), the form
  :func:`nlosjax.evaluation.protocol.evaluate` scores over seeds.

  Raises:
    ValueError: as :func:`load_trained`.
  """
  p = pathlib.Path(path).absolute()
  workdir, first, _ = find_checkpoints(p)
  wanted = [first] if p.name in VARIANTS or p.name == "checkpoints" else list(VARIANTS)
  trained, config = {}, None
  for variant in wanted:
    folders = seed_folders(workdir, variant)
    if not seeds:
      folders = folders[:1] if folders and folders[0] == variant else []
    models = []
    for folder in folders:
      mcfg, params, info = load_trained(workdir, variant, folder=folder)   # the step chosen on validation
      log(f"[{folder}] restored step {info['step']} from {workdir / folder / 'checkpoints'}")
      config = info["config"]
      models.append((mcfg if setup is None or setup == mcfg.setup else mcfg.with_setup(setup),
                     params))
    if models:
      trained[variant] = models if seeds else models[0]
  return config, trained


def _signature(signature) -> dict:
  """A checkpoint's recorded run signature (JSON: ``model`` repr, ``params`` fingerprint, ...)."""
  if not isinstance(signature, str):
    return {}
  try:
    out = json.loads(signature)
  except json.JSONDecodeError:
    return {}
  return out if isinstance(out, dict) else {}


def check_params(model_config, params, where) -> None:
  """ValueError naming ``where`` unless ``params`` has the paths and shapes ``model_config`` initialises.

  The trace of ``init`` this takes is kept per config and shared with
  ``model_config.physics_operators()``, so checking the config a forward pass then runs costs no
  second trace.
  """
  _check_tree(where, params, _expected_tree(model_config), what="weights")


def _check_tree(where, params, expected, *, what: str = "checkpoint") -> None:
  """ValueError naming ``where`` unless ``params`` has ``expected``'s paths and shapes."""
  got = {jax.tree_util.keystr(k): tuple(v.shape) for k, v in jax.tree_util.tree_leaves_with_path(params)}
  want = {jax.tree_util.keystr(k): tuple(v.shape)
          for k, v in jax.tree_util.tree_leaves_with_path(expected)}
  if got != want:
    missing = sorted(set(want) - set(got))[:3]
    extra = sorted(set(got) - set(want))[:3]
    shapes = [f"{k}: {got[k]} vs {want[k]}" for k in sorted(set(got) & set(want)) if got[k] != want[k]][:3]
    raise ValueError(f"{what} {where}: parameters do not fit the model (missing {missing},"
                     f" unexpected {extra}, shape mismatches {shapes})")


@dataclasses.dataclass(frozen=True)
class CaptureView:
  """How a capture is presented to a trained network (:func:`for_capture`).

  Attributes:
    bin_factor: capture bins summed into one network bin.
    setup: the network's full-grid Setup for the capture (the capture's wall
      and grid; ``bin_factor`` times its bin width; ``T // bin_factor`` bins;
      the capture's depth range, if any).
    model_config: the trained config moved to ``setup``, with the physics
      layer's wavelet rescaled (see :func:`for_capture`).
  """

  bin_factor: int
  setup: Setup
  model_config: object

  def prepare(self, transient) -> np.ndarray:
    """Sum ``bin_factor`` bins: ``[..., T, H, W] -> [..., T // bin_factor, H, W]`` float32."""
    x = np.asarray(transient, np.float32)
    k, n = self.bin_factor, self.setup.num_bins
    x = x[..., :n * k, :, :]
    return x.reshape(x.shape[:-3] + (n, k) + x.shape[-2:]).sum(axis=-3)


def default_bin_factor(trained_bin_width: float, capture_bin_width: float) -> int:
  """Capture bins summed per network bin: ``round(trained / capture)`` bin widths (seconds), >= 1."""
  if not (trained_bin_width > 0 and capture_bin_width > 0):
    raise ValueError(f"bin widths must be > 0 s, got trained {trained_bin_width!r} and capture"
                     f" {capture_bin_width!r}")
  return max(1, int(round(trained_bin_width / capture_bin_width)))


def setup_dependent_params(model_config) -> list[str]:
  """The parameters whose shapes depend on the model's Setup: ``[]`` when the model can move to another.

  Compares the parameter tree ``model_config`` initialises (``jax.eval_shape``: traced, not
  compiled) with the one at twice its grid, wall and bins (the same spacing and bin width, so
  every layer that checks its sampling still holds). Every network here is empty but I-K
  (:mod:`nlosjax.models.ik`), whose learned kernel is a Fourier volume of its coarse grid and
  bins: it runs on its training Setup only.

  The model family declares the answer (``params_depend_on_setup``), so a model that moves
  costs no trace here; only a family that declares a dependence is traced, to name the
  parameters. :func:`traced_setup_dependent_params` is the traced answer for every family,
  which the tests hold each declaration to.

  Returns:
    ``"path: shape -> shape"`` for each parameter that changes, sorted. The answer is kept per
    model config (they are frozen), so a caller checking every scan traces each model once.
  """
  if not type(model_config).params_depend_on_setup:
    return []
  return list(_setup_dependent(model_config))


def traced_setup_dependent_params(model_config) -> list[str]:
  """:func:`setup_dependent_params` traced whatever the family declares (the reference it is tested against)."""
  return list(_setup_dependent(model_config))


@functools.lru_cache(maxsize=32)
def _setup_dependent(model_config) -> tuple[str, ...]:
  s = model_config.setup
  other = Setup(wall_size=2 * s.wall_size, grid=(2 * s.grid[0], 2 * s.grid[1]), bin_width=s.bin_width,
                num_bins=2 * s.num_bins)
  here = _expected_tree(model_config)
  moved_config = dataclasses.replace(model_config, setup=other)     # traced once, not kept
  there = jax.eval_shape(moved_config.module().init, jax.random.key(0),
                         jax.ShapeDtypeStruct(moved_config.input_shape(), jnp.float32))["params"]
  flat = {jax.tree_util.keystr(k): v.shape for k, v in jax.tree_util.tree_flatten_with_path(here)[0]}
  moved = {jax.tree_util.keystr(k): v.shape for k, v in jax.tree_util.tree_flatten_with_path(there)[0]}
  return tuple(sorted(f"{k}: {flat.get(k)} -> {moved.get(k)}" for k in set(flat) | set(moved)
                      if flat.get(k) != moved.get(k)))


def for_capture(model_config, capture: Setup, *, bin_factor: int | None = None) -> CaptureView:
  """Move a trained model to a capture's geometry, keeping what it learned in bin units.

  * Time: ``bin_factor`` (default ``round(trained bin width / capture bin
    width)``, at least 1) capture bins are summed per network bin, so the
    network's convolutions and scans see bins of about the width they were
    trained on; the capture's whole range is kept (``T // bin_factor`` bins).
  * Space: the capture's wall and grid (the output grid; the input is that
    grid under-scanned by the trained ``stride``).
  * Physics layer: rebuilt for this Setup. Its wavelet's virtual wavelength
    is ``2 sampling_coeff Delta``; on a small wall with coarse bins that
    wavelength could fall below two bins (unresolved), and in any case the
    layers around the physics layer learned features whose carrier spans a
    fixed number of bins. So ``wavelet_sampling`` is rescaled to keep the
    wavelength in (coarse) bins what it was in training. A model without a
    phasor physics layer (USM, whose wavelet is only its training loss's)
    keeps its ``wavelet_sampling``.

  Args:
    model_config: the trained :class:`~nlosjax.models.network.ModelConfig`
      (or :class:`~nlosjax.models.usm.USMConfig`).
    capture: the capture's full-grid Setup (its depth range is kept).
    bin_factor: override the time binning.
  Raises:
    ValueError: a bad ``bin_factor``, too few bins, or a model whose parameters depend on
      its Setup (:func:`setup_dependent_params`: I-K), which cannot move.
  """
  from nlosjax.physics.wavelet import illumination_wavelet
  trained = model_config.setup
  tied = setup_dependent_params(model_config)
  if tied:
    raise ValueError(f"{type(model_config).__name__}: its parameters depend on its training Setup"
                     f" ({'; '.join(tied[:2])}), so it runs on that Setup only and cannot move to a"
                     " capture")
  if bin_factor is None:
    bin_factor = default_bin_factor(trained.bin_width, capture.bin_width)
  if not isinstance(bin_factor, int) or bin_factor < 1:
    raise ValueError(f"bin_factor must be a positive integer, got {bin_factor!r}")
  num_bins = capture.num_bins // bin_factor
  if num_bins < 4 * model_config.extract_time_stride * model_config.volume_time_stride:
    raise ValueError(f"the capture's {capture.num_bins} bins of {capture.bin_width:.3g} s give only"
                     f" {num_bins} network bins of {bin_factor * capture.bin_width:.3g} s")
  setup = Setup(wall_size=capture.wall_size, grid=capture.grid,
                bin_width=capture.bin_width * bin_factor, num_bins=num_bins,
                depth_range=capture.depth_range, aperture=capture.aperture)
  if getattr(model_config, "physics", None) != "phasor":
    return CaptureView(bin_factor=bin_factor, setup=setup,
                             model_config=dataclasses.replace(model_config, setup=setup))
  # Wavelength in coarse bins, as trained.
  stride = model_config.volume_time_stride
  trained_coarse = dataclasses.replace(trained.ungated(), bin_width=trained.bin_width * stride)
  wl = illumination_wavelet(trained_coarse, cycles=model_config.wavelet_cycles,
                            sampling_coeff=model_config.wavelet_sampling)
  per_bin = wl.wavelength / trained_coarse.bin_length
  coarse_length = setup.bin_length * stride
  sampling = max(1.0, per_bin * coarse_length / (2.0 * max(setup.spacing)))
  mcfg = dataclasses.replace(model_config, setup=setup, wavelet_sampling=float(sampling))
  return CaptureView(bin_factor=bin_factor, setup=setup, model_config=mcfg)


@functools.lru_cache(maxsize=2)
def _checked_forward(model_config):
  """The jitted, checked forward of ``model_config`` (NaN / negative counts raise), kept per config.

  Kept so that :func:`run_model` called again with the same config (the next
  capture of a setup, the next chunk of a video) reuses the compiled program
  instead of tracing a new closure. The physics operators enter it as an argument
  and stay bound to it (136 MB at the paper preset), so only the last two configs
  are kept.
  """
  from nlosjax.physics.checks import checked
  model = model_config.module()
  return checked(lambda p, b: model.apply({"params": p}, b), operators=model_config.physics_operators())


def run_model(model_config, params, frames, *, batch_size: int = 4):
  """Apply a network to under-scanned frames, one output per frame.

  Args:
    model_config: the (adapted) config.
    params: its parameters.
    frames: ``[F, T, h, w]`` under-scanned counts of consecutive frames.
    batch_size: frames per forward pass.
  Returns:
    dict of NumPy arrays ``intensity [F, H, W]`` in [0, 1], ``depth [F, H, W]``,
    ``volume [F, Z, H, W]``, ``transient [F, T, H, W]`` (counts: the network's
    output times its input scale).
  """
  x = triplets(np.asarray(frames, np.float32), model_config.frames)
  apply = _checked_forward(model_config)
  out = {k: [] for k in ("intensity", "depth", "volume", "transient")}
  for s in range(0, len(x), batch_size):
    o = apply(params, jnp.asarray(x[s:s + batch_size]))
    out["intensity"].append(np.clip(np.asarray(o["intensity"]), 0.0, 1.0))   # USM's is unclamped
    for k in ("depth", "volume"):
      out[k].append(np.asarray(o[k]))
    out["transient"].append(np.asarray(o["transient"] * o["scale"][:, None, None, None]))
  return {k: np.concatenate(v) for k, v in out.items()}

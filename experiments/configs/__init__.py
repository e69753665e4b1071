"""Experiment presets: one ``get_config()`` per module, returning an ``ml_collections.ConfigDict``.

``cpu`` is the default: its whole main job (make data, train a small model, evaluate) fits in
about 20 minutes on 2 CPU cores. ``paper`` reproduces the paper's sizes (128 x 128 full grid,
every 8th point as input, 512 bins of 33 ps, 32 frames, 150 / 16 / 17 sequences for train /
validation / test); ``real`` trains the cpu model on the geometry of the shipped measured scans.
Variants import the default and change a few fields, as flax's example configs do.

Every preset starts from :func:`skeleton`: every key a run's config takes, in sections ``data``
(``scene``, ``physics``, ``loader``, ``num_sequences``), ``model``, ``train`` (``optim``, ``loss``,
``stop``), ``usm``, ``lfe``, ``ik`` (each a ``model`` and an ``optim``) and ``independent``, each
unset (``None``, or :data:`UNSET` where None is a value) until a preset sets it. The keys come
from the library's typed dataclasses, so a locked preset knows exactly the keys the library reads
(``--config.train.stpes=5`` exits naming the key), and an unset key keeps the dataclass's
default. :func:`to_dict` drops the unset keys: the plain dict a run records (``config.json``) and
:meth:`nlosjax.train.RunConfig.from_dict` reads.

The ``data`` section is read by :meth:`nlosjax.data.dataset.DatasetSpec.from_config`
(generation) and by the loaders (``input_stride``, ``input_offset``, ``loader``, ``path``); see
docs/dataset.md (sections "The command", "Loading" and "Presets"). Why the presets' less obvious
values are what they are: docs/decisions.md.
"""

from __future__ import annotations

import dataclasses
import importlib
import pathlib

from ml_collections import ConfigDict, config_dict

#: Preset names (modules of this package).
PRESETS = ("cpu", "paper", "real")
#: The preset used when none is named.
DEFAULT = "cpu"
#: This folder: ``--config NAME`` reads ``FOLDER / f"{NAME}.py"``.
FOLDER = pathlib.Path(__file__).resolve().parent

#: Keys whose values take more than one type (their dataclass field's annotation is a union).
_ANY_TYPE = {"grid", "jitter", "compression", "dt_rank"}
#: The value of an unset key of type ``object``: one where None is a setting of its own
#: (``clip_norm=None``: no clipping; ``eval_batch_size=None``: the training batch; ``jitter=None``).
UNSET = "<unset>"
#: The whole-image recipe: the ``cpu`` preset's model and loss before it trained for the hidden
#: objects (experiments/studies/objects/results/objects.md): width 8, the paper's whole-image losses
#: with the object term, the checkpoint kept on the validation intensity PSNR. Key path -> value
#: (None: the key unset, the library's default). Every real weight and the mechanism study's runs were
#: trained with it: the ``real`` preset writes it out, ``experiments.studies.mechanisms.study_recipe``
#: puts it back over the ``cpu`` preset's new values, and ``experiments.studies.real_preset``'s
#: ``"objects"`` recipe takes the ``cpu`` preset's values at these keys. One description, so the
#: three cannot drift apart.
WHOLE_IMAGE_RECIPE = {("model", "width"): 8, ("train", "loss", "balance"): None,
                      ("train", "loss", "object_intensity"): 3.0, ("train", "stop", "metric"): None}
#: What :func:`get_path` returns where a key of the path is absent (None is a value).
MISSING = object()


def _unset(kind) -> config_dict.FieldReference:
  return config_dict.FieldReference(UNSET, field_type=object) if kind is object else config_dict.placeholder(kind)


def _section(cls, drop=(), rename=None) -> ConfigDict:
  """One unset key per field of dataclass ``cls`` (but ``drop``), typed by the field's default."""
  out = ConfigDict()
  for f in dataclasses.fields(cls):
    if f.name in drop:
      continue
    default = f.default if f.default_factory is dataclasses.MISSING else f.default_factory()
    if f.name in _ANY_TYPE or (default is not None and "None" in str(f.type)):
      kind = object                    # None is a value here, set like any other
    elif default in (None, dataclasses.MISSING):
      kind = int if f.name in ("devices", "scan_chunk", "physics_chunk") else object
    else:
      kind = type(default)
    out[(rename or {}).get(f.name, f.name)] = _unset(kind)
  return out


def skeleton() -> ConfigDict:
  """Every key a run's config takes, each unset (None: the library's default), as a ConfigDict."""
  from nlosjax import losses
  from nlosjax.data.dataset import LoaderOptions, PhysicsMix
  from nlosjax.data.dataset.spec import DatasetSpec
  from nlosjax.data.scenes import SceneParams
  from nlosjax.train import OptimConfig, StopRule, TrainConfig
  from nlosjax.train.config import BASELINES, model_class
  from nlosjax.variants import OURS, USM

  data = _section(DatasetSpec, drop=("setup", "num_train", "num_test", "num_val", "scene", "physics"))
  for key, kind in (("wall_size", float), ("grid", object), ("bin_width", float), ("num_bins", int),
                    ("input_stride", int), ("input_offset", int), ("path", str)):
    data[key] = _unset(kind)
  data.num_sequences = ConfigDict({split: config_dict.placeholder(int) for split in ("train", "val", "test")})
  data.scene = _section(SceneParams, rename={"max_tilt": "max_tilt_deg"})
  data.physics = _section(PhysicsMix)
  data.loader = _section(LoaderOptions)
  train = _section(TrainConfig, drop=("optim", "loss", "stop"))
  train.optim = _section(OptimConfig)
  train.loss = _section(losses.LossWeights)
  train.stop = _section(StopRule)
  config = ConfigDict({"data": data, "model": _section(model_class(OURS), drop=("setup", "stride", "frames")),
                       "train": train})
  for name in BASELINES:
    config[name] = ConfigDict({"model": _section(model_class(name), drop=("setup", "stride")),
                               "optim": _section(OptimConfig)})
  config[USM].recipe = config_dict.placeholder(str)
  # The application's second test set (experiments.train; docs/dataset.md, "The independent test set").
  config.independent = ConfigDict({"path": config_dict.placeholder(str), "sequences": config_dict.placeholder(int),
                                   "frames": config_dict.placeholder(int), "seed": config_dict.placeholder(int)})
  return config


def to_dict(config: ConfigDict) -> dict:
  """``config`` as a plain dict without its unset keys and the sections left with none.

  A section set empty on purpose stays (``'--config.data.physics={}'``: every default), and so
  does a None set where None is a value (``--config.train.optim.clip_norm=None``).
  """
  out = {}
  for key in config:
    value = config[key]
    if isinstance(value, ConfigDict) and len(value):
      value = to_dict(value)
      if not value:
        continue
    elif isinstance(value, ConfigDict):
      value = {}
    elif isinstance(value, str) and value == UNSET:
      continue
    elif value is None and config.get_type(key) is not object:
      continue
    out[key] = value
  return out


def get_path(tree, path: tuple):
  """The value at key path ``path`` (a tuple of keys, outermost first) of nested dicts or
  ConfigDicts ``tree``, or :data:`MISSING` where a key of the path is absent."""
  for key in path:
    if not isinstance(tree, (dict, ConfigDict)) or key not in tree:
      return MISSING
    tree = tree[key]
  return tree


def set_path(tree, path: tuple, value) -> None:
  """Set the value at key path ``path`` of ``tree`` (nested dicts or ConfigDicts) to ``value`` in
  place, adding an empty section for each absent key above it."""
  for key in path[:-1]:
    if key not in tree:
      tree[key] = {}
    tree = tree[key]
  tree[path[-1]] = value


def del_path(tree, path: tuple) -> None:
  """Delete the key at key path ``path`` of ``tree`` (nested dicts or ConfigDicts) in place."""
  node = get_path(tree, path[:-1])
  del node[path[-1]]


def get_config(name: str = DEFAULT) -> dict:
  """Preset ``name`` as a fresh plain dict (:func:`to_dict` of its module's ``get_config()``).

  Raises:
    ValueError: for an unknown preset name.
  """
  if name not in PRESETS:
    raise ValueError(f"config must be one of {PRESETS}, got {name!r}")
  return to_dict(importlib.import_module(f"{__name__}.{name}").get_config())

"""A run's config, typed: frozen dataclasses per section and :meth:`RunConfig.from_dict`, which builds them.

A preset (``experiments/configs``, an ``ml_collections.ConfigDict`` read and locked by
``config_flags`` at the entry point) becomes a nested dict of plain values (``data``,
``model``, ``train``, ``usm``, ``lfe``, ``ik``); :meth:`RunConfig.from_dict` builds the typed
config from it once, at the entry point: :class:`TrainConfig`, :class:`DataConfig`,
:class:`BaselineConfig`. A key the dict leaves out takes its dataclass default; the data
section's Setup keys are needed only by what builds a Setup from them. The library's
functions take the :class:`RunConfig` (their annotations say so) and never re-read the dict.
:meth:`RunConfig.to_dict` is what a run records (``config.json``), and ``from_dict`` reads
that back, also for runs recorded by older versions.
"""

from __future__ import annotations

import copy
import dataclasses
import types
from typing import Any, Mapping

from nlosjax import losses
from nlosjax.train.optimizer import OptimConfig
from nlosjax.train.stopping import StopRule
from nlosjax.variants import FAMILY_LFE, FAMILY_STMAMBA, FAMILY_USM, OURS, OURS_S, USM, VARIANTS
from nlosjax.variants import variant as variant_info

#: USM's training recipes (``usm.recipe``): "ours" trains it with the config's ``train.optim``
#: and ``train.loss`` (Ours' recipe, the like-for-like default); "published" with USM's own
#: (:data:`nlosjax.models.usm.PUBLISHED_OPTIM`, ``PUBLISHED_LOSS``).
USM_RECIPES = (OURS, "published")
#: The variants with a section of their own (``usm``, ``lfe``, ``ik``: every variant not built by
#: ST-Mamba, :data:`nlosjax.variants.VARIANTS`): a ``model`` and an ``optim``.
BASELINES = tuple(name for name, v in VARIANTS.items() if v.family != FAMILY_STMAMBA)


def _frozen(mapping: Mapping | None) -> Mapping:
  return types.MappingProxyType(dict(mapping or {}))


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """A config's ``train`` section: how each variant trains and is chosen.

  Attributes:
    steps: training steps (the ``"steps"`` stopping rule; the plateau rule uses ``stop.max_steps``).
    batch_size: sequences per step; eval_batch_size: per evaluation batch (None: ``batch_size``;
      :attr:`eval_batch` reads it; 8 where a config is silent, as every preset's main job had it).
    seed, seeds: the first training seed and how many (``seed``, ``seed + 1``, ...; tables
      then cover seeds too).
    log_every, checkpoint_every: steps between log rows and between checkpoints.
    keep_checkpoints: checkpoints kept.
    variants: the variants the main job trains (:data:`nlosjax.variants.VARIANTS`).
    data_workers: processes writing the dataset.
    optim: the optimiser (:class:`~nlosjax.train.OptimConfig`); loss: the loss weights.
    select_checkpoint: ``"last"`` or ``"val"`` (the kept checkpoint with the best
      validation intensity PSNR).
    check_memory: before any data or parameters exist, compile each variant's train step
      and refuse when XLA's planned peak exceeds the device's memory
      (:func:`nlosjax.plan.check_fits`).
    devices: train data-parallel on the first ``devices`` devices (None: all of them).
    stop: when training stops (:class:`~nlosjax.train.stopping.StopRule`).
  """

  steps: int = 300
  batch_size: int = 4
  seed: int = 0
  seeds: int = 1
  log_every: int = 10
  checkpoint_every: int = 50
  keep_checkpoints: int = 2
  eval_batch_size: int | None = 8
  variants: tuple[str, ...] = (OURS_S, OURS)
  data_workers: int = 1
  optim: OptimConfig = OptimConfig()
  loss: losses.LossWeights = losses.LossWeights()
  select_checkpoint: str = "last"
  check_memory: bool = False
  devices: int | None = None
  stop: StopRule = StopRule()

  @classmethod
  def from_dict(cls, section: Mapping | None) -> "TrainConfig":
    """The section of a ``train`` mapping (None: the defaults); an unknown key raises ``TypeError``."""
    d = dict(section or {})
    for key, kind in (("optim", OptimConfig), ("loss", losses.LossWeights)):
      value = d.get(key)
      if value is None or isinstance(value, Mapping):
        d[key] = kind(**(value or {}))
    if "stop" in d and not isinstance(d["stop"], StopRule):
      d["stop"] = StopRule.from_config(d["stop"])
    for key in ("steps", "batch_size", "seed", "seeds", "log_every", "checkpoint_every",
                "keep_checkpoints", "eval_batch_size", "data_workers"):
      if d.get(key) is not None:
        d[key] = int(d[key])
    if "variants" in d:
      d["variants"] = tuple(d["variants"])
    return cls(**d)

  @property
  def eval_batch(self) -> int:
    """Sequences per evaluation batch: ``eval_batch_size``, else ``batch_size``."""
    return self.batch_size if self.eval_batch_size is None else self.eval_batch_size

  def __post_init__(self):
    if self.select_checkpoint not in ("last", "val"):
      raise ValueError(f'train.select_checkpoint must be "last" or "val", got {self.select_checkpoint!r}')
    unknown = [v for v in self.variants if v not in VARIANTS]
    if unknown:
      raise ValueError(f"train.variants: unknown variant(s) {unknown}; known: {list(VARIANTS)}")


@dataclasses.dataclass(frozen=True)
class BaselineConfig:
  """A learned baseline's section (``usm``, ``lfe``, ``ik``).

  Attributes:
    model: its model config's fields (those of :class:`~nlosjax.models.usm.USMConfig`,
      ``LFEConfig``, ``IKConfig`` but ``setup`` and ``stride``); where absent, its published widths.
    optim: entries of :class:`~nlosjax.train.OptimConfig` replacing ``train.optim``'s
      (e.g. its own learning rate, chosen on validation).
    recipe: USM only (:data:`USM_RECIPES`): ``"ours"`` or ``"published"``.
  """

  model: Mapping[str, Any] = dataclasses.field(default_factory=_frozen)
  optim: Mapping[str, Any] = dataclasses.field(default_factory=_frozen)
  recipe: str = OURS

  @classmethod
  def from_dict(cls, name: str, section: Mapping | None) -> "BaselineConfig":
    d = dict(section or {})
    recipe = d.get("recipe", OURS)
    if recipe not in USM_RECIPES:
      raise ValueError(f"config usm.recipe must be one of {USM_RECIPES}, got {recipe!r}")
    return cls(model=_frozen(d.get("model")), optim=_frozen(d.get("optim")), recipe=recipe)


def model_class(variant: str) -> type:
  """The model config class of ``variant``, by its family (:class:`nlosjax.variants.Variant`)."""
  family = variant_info(variant).family
  if family == FAMILY_STMAMBA:
    from nlosjax.models.network import ModelConfig
    return ModelConfig
  if family == FAMILY_USM:
    from nlosjax.models.usm import USMConfig
    return USMConfig
  if family == FAMILY_LFE:
    from nlosjax.models.lfe import LFEConfig
    return LFEConfig
  from nlosjax.models.ik import IKConfig
  return IKConfig


@dataclasses.dataclass(frozen=True)
class DataConfig:
  """A config's ``data`` section as the loaders read it; :meth:`spec` reads the rest.

  Attributes:
    section: the whole section (read by :meth:`~nlosjax.data.dataset.DatasetSpec.from_config`).
    input_stride: under-scanning at load time (every ``input_stride``-th scan point per axis).
    input_offset: the first kept scan point; the model reads ``stride // 2 + stride * i``,
      so any other offset is refused.
    path: the dataset file (None where the config names none).
    loader: :class:`~nlosjax.data.dataset.LoaderOptions` (``data.loader``).
  """

  section: Mapping[str, Any]
  input_stride: int | None
  input_offset: int | None
  path: str | None
  loader: Any

  @classmethod
  def from_dict(cls, section: Mapping | None) -> "DataConfig":
    from nlosjax.data.dataset import LoaderOptions
    d = dict(section or {})
    stride = None if d.get("input_stride") is None else int(d["input_stride"])
    offset = d.get("input_offset")
    if stride is not None:
      offset = int(offset if offset is not None else stride // 2)
      if offset != stride // 2:
        raise ValueError(f"config data.input_offset = {offset}, but the model reads scan points "
                         f"stride // 2 + stride * i (offset {stride // 2} for stride {stride})")
    return cls(section=_frozen(d), input_stride=stride, input_offset=offset,
               path=None if d.get("path") is None else str(d["path"]),
               loader=LoaderOptions.from_dict(d.get("loader")))

  def stride(self) -> int:
    """``input_stride``; a ``ValueError`` where the section has none."""
    if self.input_stride is None:
      raise ValueError("config data section lacks 'input_stride'")
    return self.input_stride

  def spec(self):
    """The dataset's :class:`~nlosjax.data.dataset.DatasetSpec` (what :func:`ensure_dataset` writes)."""
    from nlosjax.data.dataset import DatasetSpec
    return DatasetSpec.from_config(self.section)

  def setup(self):
    """The full-grid :class:`~nlosjax.physics.Setup` of the section's wall, grid and bins.

    Raises:
      KeyError, TypeError, ValueError: a section without them.
    """
    from nlosjax.physics import Setup
    s = self.section
    grid = s["grid"]
    return Setup(wall_size=s["wall_size"], grid=grid if isinstance(grid, int) else tuple(grid),
                 bin_width=s["bin_width"], num_bins=s["num_bins"])


@dataclasses.dataclass(frozen=True)
class RunConfig:
  """A run's config, typed (module docstring).

  Attributes:
    data: :class:`DataConfig`.
    model: Ours' and Ours-S's model fields (:class:`~nlosjax.models.ModelConfig`'s but
      ``setup``, ``stride`` and ``frames``, which come from the data and the variant).
    train: :class:`TrainConfig`.
    baselines: ``"usm"``, ``"lfe"``, ``"ik"`` -> :class:`BaselineConfig`.
    extra: top-level sections the library does not read (the application's, e.g. ``independent``).
  """

  data: DataConfig
  model: Mapping[str, Any]
  train: TrainConfig
  baselines: Mapping[str, BaselineConfig]
  extra: Mapping[str, Any] = dataclasses.field(default_factory=_frozen)

  @classmethod
  def from_dict(cls, config: Mapping) -> "RunConfig":
    """Build the typed config from a preset's nested dict or a run's ``config.json`` (once, at the entry point)."""
    model = dict(config.get("model") or {})
    sections = {"data", "model", "train", *BASELINES}
    return cls(data=DataConfig.from_dict(config.get("data")), model=_frozen(model),
               train=TrainConfig.from_dict(config.get("train")),
               baselines=_frozen({b: BaselineConfig.from_dict(b, config.get(b)) for b in BASELINES}),
               extra=_frozen({k: v for k, v in config.items() if k not in sections}))

  def to_dict(self) -> dict:
    """The plain dict this config is read back from (a run's ``config.json``).

    The data and model sections and the application's as given; the ``train`` section with
    every field (its optimiser, loss and stopping rule whole); each baseline's section.
    ``RunConfig.from_dict(c.to_dict()) == c``.
    """
    out = {"data": _thaw(self.data.section), "model": _thaw(self.model), "train": _train_dict(self.train)}
    for name, b in self.baselines.items():
      out[name] = {"model": _thaw(b.model), "optim": _thaw(b.optim), **({"recipe": b.recipe} if name == USM else {})}
    out.update(_thaw(self.extra))
    return out


def _train_dict(t: TrainConfig) -> dict:
  """``t`` as a plain ``train`` section: every field, its optimiser, loss and stopping rule whole."""
  out = {f.name: getattr(t, f.name) for f in dataclasses.fields(TrainConfig)}
  out.update(optim=dataclasses.asdict(t.optim), loss=dataclasses.asdict(t.loss), stop=t.stop.to_dict(),
             variants=list(t.variants))
  return out


def _thaw(value):
  """A plain, mutable deep copy of a (possibly read-only) mapping tree."""
  if isinstance(value, Mapping):
    return {k: _thaw(v) for k, v in value.items()}
  return copy.deepcopy(value)

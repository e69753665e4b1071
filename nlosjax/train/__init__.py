"""Training of ST-Mamba (and USM): optimiser, state, one pure train step, sharding, checkpoints, the loop.

One concern per module, each usable alone; everything is importable from
``nlosjax.train`` as before:

* :mod:`~nlosjax.train.optimizer` -- :class:`OptimConfig`, :func:`make_optimizer`:
  optax AdamW with optional warm-up + cosine and clipping.
* :mod:`~nlosjax.train.state` -- :func:`create_train_state`: parameters from
  ``jax.eval_shape`` first (count, shape errors before any allocation), then
  ``init`` jitted with replicated output sharding; :func:`network`.
* :mod:`~nlosjax.train.step` -- :func:`train_step` ``(state, batch, key) ->
  (state, metrics)``, pure; jitted by :func:`make_train_step` with the state
  donated and the batch sharded over a ``Mesh``.
* :mod:`~nlosjax.train.sharding` -- :func:`make_mesh`, :func:`mesh_for`,
  :func:`shard_batch`, :func:`to_host`, :func:`initialize_distributed`: data
  parallel on 1 CPU, several GPUs, or several processes and hosts.
* :mod:`~nlosjax.train.checkpoint` -- :class:`Checkpointer` (orbax: params,
  optimizer state, step and data position; refuses another run's checkpoint),
  :func:`run_signature`.
* :mod:`~nlosjax.train.config` -- :class:`RunConfig`: a run's config typed, a frozen
  dataclass per section (:class:`TrainConfig`, :class:`DataConfig`, :class:`BaselineConfig`),
  built once by :meth:`RunConfig.from_dict` where the application reads its config; the
  library's functions take the :class:`RunConfig`.
* :mod:`~nlosjax.train.config_record` -- :func:`model_record`: a model config
  field by field as JSON, and :func:`compare_model`: whether a checkpoint's or shipped
  weights' recorded model config is the one a run rebuilds (a field a file predates passes
  at its default; ``repr`` strings of older files are parsed).
* :mod:`~nlosjax.train.stopping` -- :class:`StopRule` (``train.stop``): a fixed
  step count (the default) or the plateau of the validation PSNR
  (:func:`plateau_reached`), the learning-rate horizon it implies, and the
  resumable validation curve (:func:`read_curve`).
* :mod:`~nlosjax.train.run_state` -- :class:`StateExport`: a run's resumable
  state as a small folder to commit, resumed on a fresh clone; pausing at a
  deadline (:class:`TrainingPaused`).
* :mod:`~nlosjax.train.loop` -- :func:`train_model`: one variant, one seed,
  resumable; what it builds from the config (:func:`model_config_for`, :func:`make_loader`,
  :func:`ensure_dataset`, :func:`training_recipe`).

Evaluation (classic baselines, scores, tables, figures) is
:mod:`nlosjax.evaluation`; the main job behind ``python -m experiments.train``
is :func:`experiments.main_job.train_and_evaluate`; the dry run is :mod:`nlosjax.plan`.
"""

from nlosjax.train.checkpoint import Checkpointer, param_fingerprint, run_signature
from nlosjax.train.config import USM_RECIPES, BaselineConfig, DataConfig, RunConfig, TrainConfig
from nlosjax.train.config_record import compare as compare_model
from nlosjax.train.config_record import model_record
from nlosjax.train.loop import (
    VARIANT_FRAMES,
    ensure_dataset,
    make_loader,
    model_config_for,
    read_metrics,
    read_selection,
    select_frames,
    train_model,
    training_recipe,
)
from nlosjax.train.optimizer import OptimConfig, learning_rate_at, make_optimizer
from nlosjax.train.run_state import StateExport, TrainingPaused, export_state, import_state
from nlosjax.train.sharding import initialize_distributed, make_mesh, mesh_for, shard_batch, to_host
from nlosjax.train.state import TrainState, abstract_train_state, create_train_state, network
from nlosjax.train.step import BATCH_KEYS, make_targets, make_train_step, train_step
from nlosjax.train.stopping import StopRule, plateau_reached, read_curve, stop_reason

__all__ = [
    "BATCH_KEYS", "BaselineConfig", "Checkpointer", "DataConfig", "OptimConfig", "RunConfig", "StateExport",
    "StopRule", "TrainConfig", "TrainState",
    "TrainingPaused", "export_state", "import_state",
    "USM_RECIPES", "VARIANT_FRAMES", "abstract_train_state", "compare_model", "create_train_state",
    "ensure_dataset", "initialize_distributed", "learning_rate_at", "make_loader", "make_mesh",
    "make_optimizer", "make_targets", "make_train_step", "mesh_for", "model_config_for", "model_record",
    "network", "param_fingerprint", "plateau_reached", "read_curve", "read_metrics", "read_selection",
    "run_signature", "select_frames", "shard_batch", "stop_reason", "to_host", "train_model",
    "train_step", "training_recipe"
]

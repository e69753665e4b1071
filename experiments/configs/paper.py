"""Paper preset (ST-Mamba, Sec. 3.2 and 5.1): 128 x 128 x 512 at 33 ps, 32 frames, batch 4, AdamW 1e-4.

For reproducing the paper's training run at its sizes: every 8th scan point (16 x 16)
of a 128 x 128 scan of a 2 m wall, 512 bins of 33 ps, 32-frame sequences (150 train,
16 validation, 17 test), 40 epochs of batch 4. Every data and training setting is
written here, so nothing falls back to the cpu preset's values; the model is
``ModelConfig.paper()`` itself.

    python -m experiments.train --config paper --dry-run      # memory and time per device, no data
    python -m experiments.train --config paper --workdir runs/paper

Data generation takes about 75 s per sequence on 2 CPU cores once compiled, hours for
all of them (``train.data_workers`` processes help); the training is accelerator work.
Before those hours, ``--dry-run`` compiles the train and eval steps and predicts memory
and time per device (:mod:`nlosjax.plan`); ``train.check_memory`` makes the run itself
refuse, before any data or parameters exist, when the prediction exceeds the device's
memory.

Why each value: docs/decisions.md, "The paper preset's choices".
"""

import dataclasses

from ml_collections import ConfigDict

from experiments import configs
from experiments.configs import cpu
from nlosjax.models.network import ModelConfig
from nlosjax.variants import OURS, OURS_S, USM

#: Steps of batch 4 per epoch over 150 sequences of 30 training triplets.
STEPS_PER_EPOCH = 150 * 30 // 4
EPOCHS = 40


def model_section(model: ModelConfig) -> dict:
  """A config's ``model`` section that builds ``model`` on its data: the fields that differ from
  :class:`~nlosjax.models.network.ModelConfig`'s defaults, but the Setup, stride and frames (the
  data and the variant set those)."""
  defaults = {f.name: f.default for f in dataclasses.fields(ModelConfig)}
  return {k: getattr(model, k) for k in defaults
          if k not in ("setup", "stride", "frames") and getattr(model, k) != defaults[k]}


def get_config() -> ConfigDict:
  # The cpu preset's detector and scene distributions, at the paper's sizes; its own model,
  # training, USM recipe and (none) independent set.
  config = cpu.get_config()
  unset = configs.skeleton()
  config.model, config.train, config[USM], config.independent = unset.model, unset.train, unset[USM], unset.independent
  config.data.update(
      wall_size=2.0,                 # m
      grid=128,                      # full-resolution scan points per axis
      bin_width=33e-12,              # s
      num_bins=512,                  # Setup.max_depth = 2.53 m
      input_stride=8,                # 128 -> 16
      input_offset=4,                # first kept point (stride // 2, the model's convention)
      frames=32,                     # F per sequence (30 triplets each with ends="valid")
      store_clean=False,             # about 1 GiB per sequence: the target is the full-resolution measurement
      renderer="lct",                # the light-cone renderer: transport would take days at this size
      retroreflective=0.0,           # every object diffuse (r^-4)
      render_batch=4,
      path="runs/data/paper.h5",
  )
  config.data.num_sequences.update(train=150, val=16, test=17)
  config.data.loader.update(ends="valid", target="measurement", in_memory=False, prefetch=4)
  # ModelConfig.paper() itself (its widths: C = 32, N = 16, two ST-Mamba blocks, the physics
  # layer one channel at a time, rematerialisation), with the cpu preset's softplus volume.
  config.model.update(model_section(ModelConfig.paper(volume_activation="softplus")))
  train = config.train
  train.steps = EPOCHS * STEPS_PER_EPOCH     # 45,000
  train.batch_size = 4
  train.seed = 0
  train.seeds = 1                    # training seeds per variant
  train.log_every = 50               # steps
  train.checkpoint_every = STEPS_PER_EPOCH   # one checkpoint per epoch
  train.keep_checkpoints = 5
  train.select_checkpoint = "val"    # the kept checkpoint with the best validation PSNR is evaluated
  train.eval_batch_size = 4
  train.variants = (OURS_S, OURS)
  train.data_workers = 2             # processes generating the data
  train.check_memory = True          # refuse a run whose predicted memory exceeds the device's
  train.optim.update(
      learning_rate=1e-4,            # AdamW, as printed
      weight_decay=0.95,             # as printed
      warmup_steps=0,                # no schedule: the paper names none
      cosine=False,
      clip_norm=1.0,                 # global gradient-norm clipping
  )
  # train.loss unset: the paper's loss weights (Sec. 5.1).
  config[USM].recipe = "published"   # USM's own optimiser, loss and widths
  return config

"""CPU preset, the default: the whole main job (data, training, evaluation) on 2 CPU cores.

For trying the method end to end without an accelerator: it makes the dataset,
trains Ours-S and Ours and evaluates them beside the classic methods, within about
20 minutes on 2 cores. It keeps the paper's ratio structure at a quarter of its size
per axis: a 32 x 32 full-resolution scan (every 4th point -> 8 x 8 input, 4x
upsampling per axis), 128 bins of 132 ps (4 x 33 ps) covering the same 2.53 m of
depth as the paper's 512 x 33 ps, 8 frames per sequence.

    python -m experiments.train            # -> runs/default

Why the less obvious values are what they are: docs/decisions.md, "The cpu preset's
choices" and, for USM, "USM at the cpu preset" and "USM's learning rate".
"""

from ml_collections import ConfigDict

from experiments import configs
from nlosjax.variants import OURS, OURS_S, USM


def get_config() -> ConfigDict:
  config = configs.skeleton()          # every key, unset (None: the library's default)

  data = config.data
  # Capture (full resolution). Setup.max_depth = 128 * c * 132 ps / 2 = 2.53 m.
  data.wall_size = 2.0               # m
  data.grid = 32                     # full-resolution scan points per axis (H = W)
  data.bin_width = 132e-12           # s
  data.num_bins = 128                # T
  data.input_stride = 4              # under-scanning at load time: 32 -> 8
  data.input_offset = 2              # first kept point (stride // 2, the model's convention)
  # Sequences.
  data.frames = 8                    # F per sequence (6 triplets each with ends="valid")
  # val: every choice (classic settings, checkpoint); test: final tables only.
  data.num_sequences.update(train=48, val=8, test=8)
  data.seed = 0
  # Detector (per sequence): efficiency uniform, photons and ambient log-uniform.
  data.efficiency = (0.01, 0.30)
  # Incident signal photons per scan point per frame; docs/decisions.md, "The cpu preset's choices".
  data.photons = (5e1, 2e3)
  data.ambient = (50.0, 500.0)       # incident ambient photons per scan point per histogram
  data.dark_counts = 0.5             # dark counts per scan point per histogram
  data.jitter = "measured"           # the shipped SPAD jitter curve
  # Storage.
  data.store_clean = True
  data.store_albedo = False
  data.compression = "gzip"
  data.compression_level = 4
  data.render_batch = 8
  # Noise-free transients by per-scan-point transport, not the light-cone operator the network inverts.
  data.renderer = "transport"
  data.retroreflective = 0.2         # probability that an object is retroreflective
  # Scenes (nlosjax.data.scenes.SceneParams; lengths in m); the mix: docs/decisions.md,
  # "The cpu preset's choices".
  data.scene.update(
      num_static=(1, 3),
      depth_range=(0.5, 1.5),
      lateral_extent=0.5,
      size_range=(0.25, 0.6),
      helix_radius=(0.05, 0.25),
      helix_pitch=(0.05, 0.3),
      helix_speed=(0.4, 1.6),        # rad/s
      frame_rate=4.0,                # Hz
      texture_probability=0.5,
      max_tilt_deg=35.0,
      supersample=2,
      albedo_range=(0.2, 1.0),       # dim objects beside bright ones
      motions=("helix", "line"),
      spin_speed=(0.0, 0.8),         # rad/s about a random axis
  )
  # Loading.
  data.loader.update(ends="valid", target="clean", in_memory=True, prefetch=2)
  data.path = "runs/data/cpu-v3.h5"  # v3: the photon range above

  # A small ST-Mamba (nlosjax.models.network.ModelConfig), sized for 2 CPU cores; its volume
  # activation and skip were chosen on validation: docs/decisions.md, "The cpu preset's choices".
  model = config.model
  model.width = 16                   # feature channels C (8 before the objects study chose "wide")
  model.d_state = 4                  # Mamba state size N
  model.extract_time_stride = 4      # time bins merged by the extraction
  model.extract_blocks = 1           # interlaced residual blocks in the extraction
  model.st_depth = 1                 # ST-Mamba blocks per frame
  model.cross_depth = 1              # cross ST-Mamba blocks per neighbour
  model.spread_min_width = 1         # smallest channel count of the transposed convs
  model.volume_features = 1          # channels through the physics layer
  model.refine_width = 2             # channels of the refinement
  model.volume_activation = "softplus"   # non-negative volume ("relu" collapses on this data)
  model.skip_frames = "weighted"     # spreading-stage skip: a learned mix of the three frames

  # Steps, learning rate and weight decay chosen on validation:
  # docs/decisions.md, "The cpu preset's choices". The schedule (peak 3e-3, cosine over 400 steps)
  # is the short one of experiments/studies/time_to_plateau/results/time_to_plateau.md; the plateau-trained studies keep
  # the 1e-3 their runs were trained with (experiments.studies.mechanisms.design.STUDY_OPTIM).
  train = config.train
  train.steps = 400                  # the short schedule's horizon
  train.batch_size = 4
  train.seed = 0
  train.log_every = 10               # steps
  train.checkpoint_every = 50        # steps
  train.eval_batch_size = 8
  train.variants = (OURS_S, OURS)    # add "usm" to train the learned baseline too
  # The last five checkpoints (steps 200-400) are kept; the one with the best validation balanced PSNR is evaluated.
  train.keep_checkpoints = 5
  train.select_checkpoint = "val"
  train.optim.update(
      learning_rate=3e-3,            # peak, AdamW
      weight_decay=0.95,             # the paper's value, preferred on validation over 1e-4
      warmup_steps=20,               # linear warm-up
      cosine=True,                   # cosine decay by the last step
      clip_norm=1.0,                 # global gradient-norm clipping
  )
  # Trained, stopped and chosen for the hidden objects (docs/decisions.md, "Scoring what a dark image
  # cannot win"; experiments/studies/objects/results/objects.md): object and background pixels weigh
  # half each in the intensity and depth losses, no extra object term, and the plateau rule and the
  # checkpoint kept read the validation object-balanced PSNR.
  train.loss.balance = 1.0
  train.loss.object_intensity = 0.0  # the paper recipe's row kept 3.0: an intensity term over the object pixels
  train.stop.metric = "psnr_balanced"

  # USM (nlosjax.models.usm), the learned baseline, trained when "usm" is in train.variants;
  # docs/decisions.md, "USM at the cpu preset" and "USM's learning rate".
  usm = config[USM]
  usm.recipe = OURS                  # Ours' data, steps, optimiser and loss ("published": USM's own)
  # Branch kernels for stride 4; branches and fusion cut to 2 channels for 2 CPU cores.
  usm.model.update(trn_kernels=(3, 5, 9), trn_width=2, fusion_widths=(2,))

  # A second test set with its own generator (docs/dataset.md, "The independent test set"), scored
  # beside the test split; nothing is chosen on it. The file is named after the generator's version
  # ("gen3": experiments.independent_set/3); a file of another version is refused.
  config.independent.update(path="runs/data/independent-cpu-v3-gen3.h5", sequences=8, frames=8, seed=2026)
  return config

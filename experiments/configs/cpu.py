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

from nlosjax.variants import OURS, OURS_S, USM


def get_config() -> dict:
  data = {
      # Capture (full resolution). Setup.max_depth = 128 * c * 132 ps / 2 = 2.53 m.
      "wall_size": 2.0,            # m
      "grid": 32,                  # full-resolution scan points per axis (H = W)
      "bin_width": 132e-12,        # s
      "num_bins": 128,             # T
      "input_stride": 4,           # under-scanning at load time: 32 -> 8
      "input_offset": 2,           # first kept point (stride // 2, the model's convention)
      # Sequences.
      "frames": 8,                 # F per sequence (6 triplets each with ends="valid")
      # val: every choice (classic settings, checkpoint); test: final tables only.
      "num_sequences": {"train": 48, "val": 8, "test": 8},
      "seed": 0,
      # Detector (per sequence): efficiency uniform, photons and ambient log-uniform.
      "efficiency": (0.01, 0.30),
      # Incident signal photons per scan point per frame; docs/decisions.md, "The cpu preset's choices".
      "photons": (5e1, 2e3),
      "ambient": (50.0, 500.0),    # incident ambient photons per scan point per histogram
      "dark_counts": 0.5,          # dark counts per scan point per histogram
      "jitter": "measured",        # the shipped SPAD jitter curve
      # Storage.
      "store_clean": True,
      "store_albedo": False,
      "compression": "gzip",
      "compression_level": 4,
      "render_batch": 8,
      # Noise-free transients by per-scan-point transport, not the light-cone operator the network inverts.
      "renderer": "transport",
      "retroreflective": 0.2,      # probability that an object is retroreflective
      # Scenes (nlosjax.data.scenes.SceneParams; lengths in m); the mix: docs/decisions.md,
      # "The cpu preset's choices".
      "scene": {
          "num_static": (1, 3),
          "depth_range": (0.5, 1.5),
          "lateral_extent": 0.5,
          "size_range": (0.25, 0.6),
          "helix_radius": (0.05, 0.25),
          "helix_pitch": (0.05, 0.3),
          "helix_speed": (0.4, 1.6),   # rad/s
          "frame_rate": 4.0,           # Hz
          "texture_probability": 0.5,
          "max_tilt_deg": 35.0,
          "supersample": 2,
          "albedo_range": (0.2, 1.0),  # dim objects beside bright ones
          "motions": ("helix", "line"),
          "spin_speed": (0.0, 0.8),    # rad/s about a random axis
      },
      # Loading.
      "loader": {"ends": "valid", "target": "clean", "in_memory": True, "prefetch": 2},
      "path": "runs/data/cpu-v3.h5",        # v3: the photon range above
  }
  # A small ST-Mamba (nlosjax.models.network.ModelConfig), sized for 2 CPU cores; its volume
  # activation and skip were chosen on validation: docs/decisions.md, "The cpu preset's choices".
  model = {
      "width": 8,                  # feature channels C
      "d_state": 4,                # Mamba state size N
      "extract_time_stride": 4,    # time bins merged by the extraction
      "extract_blocks": 1,         # interlaced residual blocks in the extraction
      "st_depth": 1,               # ST-Mamba blocks per frame
      "cross_depth": 1,            # cross ST-Mamba blocks per neighbour
      "spread_min_width": 1,       # smallest channel count of the transposed convs
      "volume_features": 1,        # channels through the physics layer
      "refine_width": 2,           # channels of the refinement
      "volume_activation": "softplus",   # non-negative volume ("relu" collapses on this data)
      "skip_frames": "weighted",   # spreading-stage skip: a learned mix of the three frames
  }
  # Steps, learning rate, weight decay and the object-intensity term chosen on validation:
  # docs/decisions.md, "The cpu preset's choices". The schedule (peak 3e-3, cosine over 400 steps)
  # is the short one of experiments/studies/time_to_plateau/results/time_to_plateau.md; the plateau-trained studies keep
  # the 1e-3 their runs were trained with (experiments.studies.mechanisms.design.STUDY_OPTIM).
  train = {
      "steps": 400,                # the short schedule's horizon
      "batch_size": 4,
      "seed": 0,
      "log_every": 10,             # steps
      "checkpoint_every": 50,      # steps
      "eval_batch_size": 8,
      "variants": (OURS_S, OURS),   # add "usm" to train the learned baseline too
      # The last five checkpoints (steps 200-400) are kept; the one with the best validation PSNR is evaluated.
      "keep_checkpoints": 5,
      "select_checkpoint": "val",
      "optim": {
          "learning_rate": 3e-3,   # peak, AdamW
          "weight_decay": 0.95,    # the paper's value, preferred on validation over 1e-4
          "warmup_steps": 20,      # linear warm-up
          "cosine": True,          # cosine decay by the last step
          "clip_norm": 1.0,        # global gradient-norm clipping
      },
      "loss": {"object_intensity": 3.0},   # intensity term over the true surface pixels (not in the paper)
  }
  # USM (nlosjax.models.usm), the learned baseline, trained when "usm" is in train.variants;
  # docs/decisions.md, "USM at the cpu preset" and "USM's learning rate".
  usm = {
      "recipe": OURS,            # Ours' data, steps, optimiser and loss ("published": USM's own)
      # Branch kernels for stride 4; branches and fusion cut to 2 channels for 2 CPU cores.
      "model": {"trn_kernels": (3, 5, 9), "trn_width": 2, "fusion_widths": (2,)},
  }
  # A second test set with its own generator (docs/dataset.md, "The independent test set"), scored
  # beside the test split; nothing is chosen on it. The file is named after the generator's version
  # ("gen3": experiments.independent_set/3); a file of another version is refused.
  independent = {"path": "runs/data/independent-cpu-v3-gen3.h5", "sequences": 8, "frames": 8,
                 "seed": 2026}
  return {"data": data, "model": model, "train": train, USM: usm, "independent": independent}

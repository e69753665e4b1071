"""Speed-accuracy trade-offs of every reconstruction knob, on the test split of the CPU-preset data.

    python -m experiments.studies.tradeoff [--quick] [--steps N] [--repeats N] [--batch 8] [--knobs ...]
                                  [--workdir runs/tradeoff] [--out-dir DIR]

For each configuration, on the test split of the CPU preset's dataset
(``runs/data/cpu-v3.h5``, made if absent; 8 sequences x 6 middle frames = 48
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
  ``usm`` section and recipe), Ours-S, Ours; CSA (the iterative method made
  for under-scanned scans, on the sparse scan itself; its l1 weight and falloff
  chosen in the run on validation frames by
  ``nlosjax.evaluation.baselines.tune_csa`` from ``baselines.CSA_GRID``);
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

``--knobs`` runs a subset (``method`` always runs). The quick mode is what
``experiments/studies/tradeoff/results/tradeoff.md`` was produced with (its header gives the seconds).

Every learned configuration is trained by this benchmark with one shared
budget (``--steps``; 150 with ``--quick``) and the CPU preset's optimiser
at peak learning rate 1e-3 (``configs.LEARNING_RATE``) and seed, through the main job's
:func:`nlosjax.train.train_model`, into ``WORKDIR/s<steps>/<name>``; a rerun restores the
checkpoints (an interrupted training resumes). Checkpoints written by the study's own loop
before it trained through ``train_model`` carry another signature and are refused: move them
aside or give another ``--workdir``. Writes ``OUT/tradeoff.md``,
``OUT/tradeoff.json`` and ``OUT/tradeoff.png`` (time per frame against
intensity PSNR, every configuration a point, the Pareto front of the
configurations that read the default capture drawn).

The code, one concern per module; every name is importable from
``experiments.studies.tradeoff`` as before the split:

* :mod:`~experiments.studies.tradeoff.configs` -- the configurations: knobs and their
  settings, the learned configurations (:data:`LEARNED`), the gating depth
  ranges, budgets and default paths.
* :mod:`~experiments.studies.tradeoff.data` -- :class:`TestSplit`, the test split in memory.
* :mod:`~experiments.studies.tradeoff.pipelines` -- the jitted ``input -> (intensity,
  depth)`` pipelines of a classic method and of a network.
* :mod:`~experiments.studies.tradeoff.training` -- :func:`train_learned`: every learned
  configuration trained (or restored) with one budget.
* :mod:`~experiments.studies.tradeoff.runners` -- :func:`evaluate` (compile time, XLA
  memory, outputs) and :func:`interleaved_times` (warm time, round-robin).
* :mod:`~experiments.studies.tradeoff.accuracy` -- :func:`scores` and
  :func:`in_range_accuracy`.
* :mod:`~experiments.studies.tradeoff.stages` -- the LCT stage split and the network's
  volume stage, for the time-gating profile.
* :mod:`~experiments.studies.tradeoff.machine` -- the machine line and load average.
* :mod:`~experiments.studies.tradeoff.study` -- :func:`run`: every measurement in one run.
* :mod:`~experiments.studies.tradeoff.pareto` -- the Pareto front, the recommended
  settings, learned points that beat the classic ones.
* :mod:`~experiments.studies.tradeoff.report` -- :func:`to_markdown`, the report ``tradeoff.md``.
* :mod:`~experiments.studies.tradeoff.figure` -- :func:`plot`, the figure ``tradeoff.png``.
* :mod:`~experiments.studies.tradeoff.__main__` -- ``main``, the command line.
"""

from experiments.studies.tradeoff.accuracy import in_range_accuracy, scores
from experiments.studies.tradeoff.configs import (
  APERTURE,
  CLASSIC,
  DEFAULT_OUT_DIR,
  DEFAULT_WORKDIR,
  DENSITY_STRIDES,
  EXPOSURES,
  FULL_REPEATS,
  FULL_STEPS,
  GOAL_HALVING,
  KNOBS,
  LABELS,
  LEARNED,
  QUICK_REPEATS,
  QUICK_STEPS,
  Learned,
  depth_ranges,
  gated_setup,
  learned_config,
)
from experiments.studies.tradeoff.data import TestSplit
from experiments.studies.tradeoff.figure import plot
from experiments.studies.tradeoff.machine import load_average, machine_line
from experiments.studies.tradeoff.pareto import learned_beats_classic, pareto_front, pareto_points, recommend
from experiments.studies.tradeoff.pipelines import classic_pipeline, csa_pipeline, learned_pipeline
from experiments.studies.tradeoff.report import csa_choice_markdown, gating_markdown, knob_table, to_markdown
from experiments.studies.tradeoff.runners import MIB, evaluate, interleaved_times
from experiments.studies.tradeoff.stages import lct_stage_executables, lct_stages, network_volume_executable
from experiments.studies.tradeoff.study import run
from experiments.studies.tradeoff.training import train_learned

__all__ = [
    "APERTURE", "CLASSIC", "DEFAULT_OUT_DIR",
    "DEFAULT_WORKDIR", "DENSITY_STRIDES", "EXPOSURES", "FULL_REPEATS", "FULL_STEPS",
    "GOAL_HALVING", "KNOBS", "LABELS", "LEARNED", "Learned", "MIB", "QUICK_REPEATS",
    "QUICK_STEPS", "TestSplit", "classic_pipeline", "csa_choice_markdown", "csa_pipeline",
    "depth_ranges", "evaluate", "gated_setup", "gating_markdown", "in_range_accuracy",
    "interleaved_times", "knob_table", "lct_stage_executables", "lct_stages",
    "learned_beats_classic", "learned_config", "learned_pipeline", "load_average", "machine_line",
    "network_volume_executable", "pareto_front", "pareto_points", "plot", "recommend", "run",
    "scores", "to_markdown", "train_learned",
]

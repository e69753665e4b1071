"""Under-scanning on measured scans: every method on 16 x 16 and 8 x 8 subsets of real 64 x 64 scans.

    python -m experiments.studies.real_undersampling                      # -> results/real.md here
    python -m experiments.studies.real_undersampling --data-dir DIR --checkpoint runs/real --out FILE.md
    python -m experiments.studies.real_undersampling --pretrained cpu --no-timing

Protocol (the paper's under-scanning experiment, on measured data):

* each 64 x 64 scan (O'Toole et al. 2018 ``lct_mat`` files: ``--data-dir``,
  default ``../shared/data/real`` next to the repository when it exists, else
  the shipped exit-sign scan) is loaded with the published preparation
  (16 ps, 512 bins);
* the references are the five classic reconstructions of the full 64 x 64
  scan (FBP, LCT, f-k, phasor, RSD with the options below); their intensity
  images (max over depth, normalised) are the targets. A method is scored
  against every reference except its own full-scan image (a phasor-only
  reference favours phasor and RSD by construction), one column each, and
  their mean is its score;
* the scan is interval-sampled with stride 4 (16 x 16) and 8 (8 x 8) at the
  points ``stride // 2 + stride i`` (the network's convention);
* classic methods (FBP, LCT, f-k, phasor, RSD) reconstruct the sparse scan
  linearly interpolated back to 64 x 64 (``nlosjax.evaluation.baselines.upsample_scan``), with
  the options these retroreflective scenes were published with (LCT snr 0.8
  and FBP with the t^2 falloff; f-k, phasor, RSD defaults);
* CSA (``nlosjax.physics.methods.csa``, the iterative method made for
  under-scanned scans) reconstructs the sparse scan itself, as a masked
  64 x 64 grid, with the t^2 falloff and the prior weight ``CSA_TAU_REL``
  chosen per stride on the ``real`` preset's simulated validation split
  (``python -m experiments.studies.csa``, ``experiments/studies/csa/results/csa_choice.md``),
  never on these scans. It is scored, not a reference, and not run on the
  full scan;
* the trained networks (Ours-S, Ours and, where trained, USM of ``--checkpoint``,
  e.g. ``runs/real``: ``python -m experiments.train --config real --workdir
  runs/real``, trained on synthetic 64 x 64 scans of a 0.6 m wall at stride 4
  with 64 ps bins; see ``experiments/configs/real.py``; without
  ``--checkpoint``, the weights shipped inside the package under
  ``--pretrained NAME``, default ``real``, each variant shipped under that
  name; ``--checkpoint none``: classic methods only) read the sparse scan
  with time summed to the trained bin width (4 x 16 ps), the physics layer
  rebuilt for the scan's wall and grid
  (``nlosjax.inference.for_capture``). At their trained stride they
  output the 64 x 64 grid directly. At twice that stride (8) the network keeps
  its trained stride and outputs a 32 x 32 grid of every other scan point
  (full-grid points ``0, 2, ..., 62``, so its inputs ``2 + 4 i`` are the full
  grid's ``4 + 8 i``), which is linearly interpolated to 64 x 64. "Ours" reads
  each static scan as three identical frames;
* scores: intensity PSNR (dB) and SSIM (``nlosjax.metrics``) against each
  reference, per scene and averaged over scenes. Nothing is tuned on these
  scenes;
* to separate what the networks' time bins cost from what the networks do,
  phasor and RSD are also scored on the sparse scans summed to the networks'
  bins (:func:`binned_classic`).

An in-domain check runs the same code on the networks' own data (the synthetic
test split of ``--synthetic``, default the checkpoint's own dataset when present,
scored against its ground truth), to tell a reading or adaptation bug from the
synthetic-to-real gap.

To tell what the networks' learned parts give or take on measured scans, each
ST-Mamba network also runs with its refinement zeroed, and with both its
spreading residual and its refinement zeroed (the interpolated scan through its
physics layer; :func:`ablated_models`; ``--no-ablation`` skips it).

Each method's seconds per scan, as the run above measured them (its first call,
with tracing and compilation, and the median over scenes of a second call on the
same scan), go in a table under the scores. Also times ``python -m
experiments.reconstruct`` against the NumPy/SciPy twins of the public
algorithms (``experiments/numpy_twins.py``) for LCT, f-k and phasor on one
64 x 64 x 512 scan (``--no-timing`` skips it).

Writes the Markdown report (``--out``, say ``real.md``) and, beside it, ``real_<scene>.png``
(one image row per method, columns full scan / 16 x 16 / 8 x 8) and
``real_summary.png`` (mean PSNR and SSIM per method and input), named after the
report's stem (``real_public.md`` writes ``real_public_<scene>.png``).
"""

from experiments.studies.real_undersampling.ablation import ablated_models, adapted_models
from experiments.studies.real_undersampling.figures import write_figures
from experiments.studies.real_undersampling.protocol import (
                                                     CLASSIC,
                                                     ITERATIVE,
                                                     LABELS,
                                                     OPTIONS,
                                                     REFERENCES,
                                                     UNTRAINED,
                                                     binned_classic,
                                                     classic_intensity,
                                                     default_files,
                                                     load_models,
                                                     run,
                                                     scene_name,
)
from experiments.studies.real_undersampling.report import pretrained_data, training_data, write_report

__all__ = ["CLASSIC", "ITERATIVE", "LABELS", "OPTIONS", "REFERENCES", "UNTRAINED", "ablated_models", "adapted_models",
           "binned_classic", "classic_intensity", "default_files", "load_models", "pretrained_data", "run",
           "scene_name", "training_data", "write_figures", "write_report"]

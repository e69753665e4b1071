"""Mechanisms: does Ours use its SSMs and its neighbour frames, every model trained until learning stops?

    python -m experiments.studies.mechanisms [--config cpu] [--budgets full tenth] [--rows full ours_s no_ssm]
                                    [--extra-rows] [--seeds 0 1 2] [--max-runs N] [--time-limit-s S]
                                    [--workdir runs/mechanisms] [--results DIR]
                                    [--report-only] [--untrained] [--probe RUN_DIR] [--tiny]
                                    [--state DIR [--hours H]] [--config.section.key=value ...]

Rows (:data:`ROWS`, built with :func:`experiments.studies.ablations.row_config`):
``full`` (Ours, three frames), ``ours_s`` (Ours-S, the middle frame alone) and
``no_ssm`` (Ours with every SSM replaced by the identity, all else equal);
``--extra-rows`` adds ``bidirectional`` (the temporal SSM runs both ways) and
``no_pf`` (no phasor-field loss); ``--rows usm`` trains the learned baseline USM
(``usm.recipe = "ours"``: Ours' data, stopping rule and loss) for Table 1 at the plateau,
paired with ``full`` and ``ours_s``, and ``--rows lfe`` LFE likewise. Each row is trained from seeds 0, 1 and 2 at
two photon budgets (:data:`BUDGETS`): the preset's (``full``) and one tenth of
its signal and ambient photons (``tenth``: the preset's ``data.photons`` and
``data.ambient`` divided by 10 and its own dataset file,
``<path stem>-exposure-0.1.h5``; for the cpu preset exactly the
``--config.data.photons=(5.0,200.0) --config.data.ambient=(5.0,50.0)
--config.data.path=runs/data/cpu-v3-exposure-0.1.h5`` of the low-photon tables).
A missing dataset is generated (``nlosjax.train.ensure_dataset``).

Every run trains until learning stops: the plateau rule of
:mod:`nlosjax.train.stopping` (:data:`STUDY_STOP`: validate every 50 steps,
stop when the best validation intensity PSNR has not risen by more than 0.05 dB
over the last 4 validations, at most 3000 steps, keep the best model on
validation; the cosine schedule spans the 3000 steps). ``--config.train.stop.KEY=V``
changes it. The model's surface threshold is then chosen on validation as in
the main job, and the test split is scored frame by frame.

Each finished run writes one small JSON file,
``RESULTS/mechanisms/<budget>/<row>-seed<k>.json`` (:func:`run_record`: config
essentials, machine and commit, steps taken and stop reason, the validation
curve, a subsampled training-loss curve, every per-frame test score
``protocol.evaluate`` returns for the model with sequence and frame indices).
A run whose JSON exists is skipped, so the command resumes anywhere (a run
killed mid-training resumes from its checkpoint in ``WORKDIR/<budget>/<row>-seed<k>/``)
and no run is trained twice; ``--budgets/--rows/--seeds``, ``--max-runs`` and
``--time-limit-s`` (no run starts after that many seconds; a started one
finishes) run a subset. Runs go seed by seed, so every row has seed 0 first.
``--state DIR`` also exports each run's resumable state (:mod:`nlosjax.train.run_state`,
with its data's digest and fingerprint) to ``DIR/<budget>/<row>-seed<k>/model`` at every
validation: committed, it lets a fresh clone on another machine resume the run
(``experiments/studies/mechanisms/state/`` holds the study's); ``--hours H`` pauses the run in
progress after H hours, exported, and the same command continues it.

After the full row's seed 0 of a budget, the SSM probe (:func:`probe_model`)
runs on that model and goes into its JSON: the validation PSNR with each SSM's
output replaced by its input at inference (no retraining), with all of them
replaced, and the mean SiLU gate of every block
(:mod:`experiments.studies.mechanisms.probe`). ``--probe RUN_DIR`` probes any finished run
folder (``WORKDIR/<budget>/<row>-seed<k>``) and stores it in that run's JSON.

``--untrained`` scores Table 1's methods without training on each budget's test frames
(:mod:`experiments.studies.mechanisms.untrained`: the classic five tuned on validation as in the main
job, CSA with its l1 weight and falloff chosen on validation frames) into
``RESULTS/mechanisms/untrained-<budget>.json``; the report pairs each with every seed of
``full`` and ``ours_s``.

The report, ``RESULTS/mechanisms.md`` with ``RESULTS/mechanisms_curves.png``, is
rewritten from the JSON files alone after every invocation (``--report-only``:
nothing else): per row and budget the mean test intensity PSNR, SSIM, object
depth RMSE and object recall with 95 % bootstrap intervals over sequences and
seeds, the paired differences full - no_ssm and full - ours_s (same frames,
seeds present in both rows), the steps every run took, the runs still missing,
and the probe. ``--tiny`` runs the tiny config of ``experiments/tiny_run.py`` (two
runs of a few steps, seconds each once compiled) into ``--workdir`` (default
``runs/mechanisms-tiny``) and ``--results`` (default ``runs/mechanisms-tiny/results``).
"""

from experiments.studies.mechanisms.cli import main, tiny_base
from experiments.studies.mechanisms.design import (
    BUDGET_LOSS,
    BUDGETS,
    COLUMNS,
    EXTRA_ROWS,
    FIGURE,
    LOSS_POINTS,
    MAIN_ROWS,
    PAIRS,
    PROBE,
    REPORT,
    ROWS,
    SEEDS,
    STUDY_OPTIM,
    STUDY_STOP,
    TABLE1_ROWS,
    TINY_DESIGN,
    TINY_STOP,
    VERDICTS,
    budget_config,
    check_consistent,
    check_same_data,
    essentials,
    run_config,
    run_dir,
    run_json,
    state_dir,
    study_optim,
    study_recipe,
    study_stop,
)
from experiments.studies.mechanisms.records import code_at_start, load_runs, machine, write_json
from experiments.studies.mechanisms.report import barely_trained, empty_output, plot_curves, summarise, write_report
from experiments.studies.mechanisms.study import (
    probe_model,
    probe_run_dir,
    run_one,
    run_record,
    test_frames,
    train_and_score,
)

__all__ = [
    "BUDGETS", "BUDGET_LOSS", "COLUMNS", "EXTRA_ROWS", "FIGURE", "LOSS_POINTS", "MAIN_ROWS",
    "TABLE1_ROWS", "PAIRS", "PROBE", "REPORT", "ROWS", "SEEDS", "STUDY_OPTIM", "STUDY_STOP", "TINY_DESIGN",
    "TINY_STOP", "VERDICTS", "budget_config", "check_consistent", "check_same_data", "essentials",
    "run_config", "run_dir", "run_json", "state_dir", "study_optim", "study_recipe", "study_stop", "code_at_start",
    "load_runs", "machine",
    "write_json", "probe_model", "probe_run_dir", "run_one", "run_record", "test_frames",
    "train_and_score", "barely_trained", "empty_output", "plot_curves", "summarise", "write_report",
    "main", "tiny_base"
]

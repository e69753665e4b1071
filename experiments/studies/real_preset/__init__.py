"""The real preset's candidates trained to their validation plateau, a working stretch at a time.

    python -m experiments.studies.real_preset --status             # done, left, hours left
    python -m experiments.studies.real_preset --hours 1.5          # train for 1.5 h, then pause
    python -m experiments.studies.real_preset --runs v5-ours_s --hours 1

Each run (:data:`~experiments.studies.real_preset.study.RUNS`) is one candidate data
config and one variant trained by :func:`nlosjax.train.train_model` under the plateau
rule of the preset (validate every 50 steps, patience 4, 0.05 dB, at most 3000 steps),
seed 0. Its dataset is made in the store (``<store>/data/``; :mod:`experiments.store`),
its run folder is ``<store>/runs/real_preset/<run>``, and its resumable state is
mirrored at every checkpoint into ``experiments/studies/real_preset/state/<run>/``:
commit that folder before a working stretch ends, and the next one (on this machine
or a fresh clone) continues from it. On a new machine the dataset is regenerated from
its spec and its content digest checked against the state's before training resumes.

``--hours H`` bounds this invocation: a run still training at the deadline saves,
exports and pauses; data generation is not bounded (its ``.partial`` file resumes).
``--status`` reads only the committed state: per run the steps done, the best
validation PSNR so far, the measured time per step, and the hours left, as a range
from the fewest steps the plateau rule could still stop at to ``max_steps``.
When every run is done, ``--candidates`` makes one workdir per candidate in the store,
linking its runs' folders (:func:`~experiments.studies.real_preset.study.candidate_workdir`),
and prints the ``python -m experiments.studies.preset_choice`` command that compares the shipped
``real`` weights with each candidate on every candidate's validation split, beside the
classic methods (another study's command; run the printed line)::

    python -m experiments.studies.real_preset --candidates

``--align [NAME ...]`` runs the alignment stage (:mod:`experiments.studies.align`, leave one
scan out) from each variant's winner on validation
(:data:`~experiments.studies.real_preset.study.ALIGNMENTS`), fold by fold, into
``<store>/runs/real_preset/align/<variant>-without-<scan>/``; each finished fold's ``params.npz`` and
``align.json`` are copied into ``state/align/`` (commit it) and back into the store on
another machine, so folds accumulate across stretches; ``--hours`` is checked before each
fold starts (a fold is about 15 minutes of 2 cores). ``--status`` shows the folds done and
the hours left::

    python -m experiments.studies.real_preset --align --hours 1.5
    python -m experiments.studies.real_undersampling --adapt --no-timing \
        --out experiments/studies/real_undersampling/results/real_adapt.md \
        --aligned <store>/runs/real_preset/align <store>/runs/real_preset/align-balanced

The ``*-balanced`` alignments (``lam`` set per fold from the training side: the MMD
term's gradient as large as the synthetic loss's; ``experiments.studies.align --lam balanced``)
keep their folds in ``align-balanced/`` (store and ``state/``), one table each. The
``*-layer`` alignments also choose, per fold, the layer they align (``--layer auto``: where the
fold's training scans' features stand furthest from the synthetic ones, a choice recorded in
each fold's ``align.json``); their folds are in ``align-layer/``.
"""

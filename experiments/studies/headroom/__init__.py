"""Headroom: how far can the objects go at the input's scan density, and where does each method fall short?

    python -m experiments.studies.headroom [--model LABEL=RUN ...] [--sets test independent heldout]
        [--conditions base small large far tenth bright] [--methods fbp lct fk phasor rsd]
        [--results DIR] [--report-only] [--tiny]

Scores, on the objects, every method on the ``cpu`` preset's test split, the independent set
(:mod:`experiments.independent_set`) and the held-out renderer's sets
(:mod:`experiments.studies.physics_shift.heldout`, at the preset's capture; ``--conditions``,
by default its base and the conditions that move object size, depth or photons): the five
classic methods (settings and surface thresholds chosen on the validation split as the main
job chooses them), the shipped ``cpu`` networks (``pretrained:cpu/ours``,
``pretrained:cpu/ours_s``; surface thresholds chosen on validation as the protocol does) and any
``--model LABEL=RUN`` (a study run folder or ``pretrained:NAME/VARIANT``, as
:mod:`experiments.studies.generalisation` reads them; a label ``ours`` or ``ours_s`` replaces the
shipped network), beside the all-zero image (the floor) and the truth read through the input's
scan grid, bilinearly as the classic methods read the sparse scan and from the nearest scan
point (:mod:`~experiments.studies.headroom.bounds`).

Per frame it records the object scores (object intensity error, object-balanced PSNR, object
depth RMSE, recall, precision, F1; the whole-image PSNR beside the all-zero image's as the guard;
:mod:`nlosjax.evaluation.scores`) and the frame's attributes (object size, object count, object
depth, photons, efficiency, motion; :mod:`~experiments.studies.headroom.breakdown`). The report,
``RESULTS/headroom.md`` with ``headroom.png`` (object intensity error and F1 against object size)
and ``headroom.json`` (every number of the report), gives each set's objects table with 95 %
bootstrap intervals over sequences, the paired differences of each network to the reference
classic method (per score, the classic method best on validation) and of the bilinear reading to
each network, then every score by tercile of object size, depth, photons and motion, per set.

Records (:mod:`~experiments.studies.headroom.study`) are one JSON file per (set, method) under
``RESULTS/headroom/``; one that exists is not recomputed, so the command resumes anywhere, and
``--report-only`` rebuilds the report from them alone. ``--tiny`` runs the whole path on the tiny
run's data (:mod:`experiments.tiny_run`, files under ``--results``) in seconds, for the tests.

Modules: :mod:`~experiments.studies.headroom.bounds` (the truth through the scan grid),
:mod:`~experiments.studies.headroom.breakdown` (attributes, terciles),
:mod:`~experiments.studies.headroom.study` (sets, choices, records),
:mod:`~experiments.studies.headroom.report` (tables, figure), ``__main__`` (the command line).
"""

import pathlib

#: This study's results folder: its report, figure and records.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"

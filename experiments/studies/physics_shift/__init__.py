"""Physics shift: do learned models keep their lead on forward models they were not trained on?

    python -m experiments.studies.physics_shift [--config cpu] [--designs base mix no_lct ...]
        [--variants ours ours_s] [--conditions base far ...] [--max-runs N] [--time-limit-s S]
        [--workdir runs/physics_shift] [--results DIR] [--report-only]
        [--config.section.key=value ...]

Two protocols, every choice on a validation split (:mod:`experiments.studies.physics_shift.study`):

* **held-out families**: for each renderer family of
  :class:`nlosjax.data.dataset.physics.PhysicsMix` (``lct``, ``transport``,
  ``points``), Ours and Ours-S trained to the validation plateau on the mix
  without it, then tested on sequences drawn from it alone, beside the five
  classic methods;
* **held-out renderer**: the shipped models and those trained on every family,
  tested on the sets of :mod:`experiments.studies.physics_shift.heldout` (a renderer and
  noise code that share nothing with the training generator; object depth,
  photons, ambient light, cosines and falloff varied by condition).

Each run writes ``RESULTS/physics_shift/<design>-<variant>.json`` and each
classic scoring ``RESULTS/physics_shift/classic-<design>-<set>.json``; a file
that exists is not recomputed, so the command resumes anywhere. The report,
``RESULTS/physics_shift.md`` with ``RESULTS/physics_shift.png``, is rebuilt
from those files after every invocation (``--report-only``: nothing else).

Modules: :mod:`~experiments.studies.physics_shift.heldout` (the held-out renderer),
:mod:`~experiments.studies.physics_shift.study` (configs, runs, records),
:mod:`~experiments.studies.physics_shift.report` (tables and figure), ``__main__`` (the CLI).
"""

"""Studies: what trains models to answer one question, one folder a study, apart from the library and the main job.

Each study folder holds its definition and runner, and under ``state/`` the
committed resumable state of each of its long runs (:mod:`nlosjax.train.run_state`),
so a fresh clone continues a run where the last working stretch stopped. Datasets
and full run folders live in the store (:mod:`experiments.store`), outside the work
tree.

* :mod:`experiments.studies.real_preset` -- the ``real`` preset's candidate data
  trained to their validation plateau, across working stretches.
* :mod:`experiments.studies.csa` -- CSA's prior weight chosen on simulated
  validation sequences (``tau-rel-help.patch``: ``--tau-rel``'s help corrected, to be
  applied with the next rerun of the measured protocol, whose results it stales).
"""

"""Studies: what trains models to answer one question, apart from the library and the main job.

Each study is a folder: its definition and runner (``python -m experiments.studies.<name>``), its
results (``results/``: reports, figures, JSON records) and, for its long runs, under ``state/``
the committed resumable state of each run (:mod:`nlosjax.train.run_state`), so a fresh clone
continues a run where the last working stretch stopped. The long-run studies (``real_preset``,
``csa``) keep datasets and full run folders in the store (:mod:`experiments.store`), outside the
work tree; the others write under ``runs/`` in the work tree (``runs/mechanisms``,
``runs/physics_shift``, ...). ``python -m benchmarks.index`` lists every study's results beside the
performance benchmarks'. Files a later study supersedes are kept in ``archive/``, whose README
names what replaces each.

* ``mechanisms`` -- does Ours use its SSMs and its neighbour frames (plateau-trained, with
  intervals over seeds); ``mechanisms.probe`` bypasses SSMs of a trained network.
* ``physics_shift`` -- the learned models on forward models they were not trained on.
* ``generalisation``, ``independent_test`` -- off our own generator: object extent and
  brightness, an independent renderer's test sequences.
* ``real_preset`` -- the ``real`` preset's candidate data trained to their plateau, across
  working stretches; ``preset_choice`` compares candidates on every validation split;
  ``realism`` tells simulated inputs from measured ones.
* ``csa`` -- CSA's prior weight chosen on simulated validation sequences.
* ``real_undersampling`` -- the measured-scan protocol: every method on measured scans
  under-scanned to 16 x 16 and 8 x 8, scored against each classic full-scan reference;
  ``align`` (its command line) and ``alignment`` (the stage) fit a network's features to
  measured inputs, one fold per left-out scan.
* ``ablations`` (the paper's Table 2), ``table1`` (Table 1 over seeds at a fixed step count),
  ``temporal_probe`` (does Ours read its neighbours), ``time_to_plateau`` and
  ``stopping_replay`` (how long to train, when to stop).
* ``tradeoff`` -- speed against accuracy of every reconstruction knob (method, scan density,
  exposure, frames, model size, scan kernel, depth gating); its networks train through
  :func:`nlosjax.train.train_model` with a loader of wider frame windows.
"""

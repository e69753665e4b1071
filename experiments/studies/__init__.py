"""Studies: what trains models to answer one question, apart from the library and the main job.

Each study holds its definition and runner (``python -m experiments.studies.<name>``) and,
for its long runs, under ``state/`` the committed resumable state of each run
(:mod:`nlosjax.train.run_state`), so a fresh clone continues a run where the last working
stretch stopped. The long-run studies (``real_preset``, ``csa``) keep datasets and full run
folders in the store (:mod:`experiments.store`), outside the work tree; the others write under
``runs/`` in the work tree (``runs/mechanisms``, ``runs/physics_shift``, ...). Reports go to
``benchmarks/results/`` beside the performance benchmarks', indexed by ``python -m benchmarks.index``.

* ``mechanisms`` -- does Ours use its SSMs and its neighbour frames (plateau-trained, with
  intervals over seeds); ``mechanisms.probe`` bypasses SSMs of a trained network.
* ``physics_shift`` -- the learned models on forward models they were not trained on.
* ``generalisation``, ``independent_test`` -- off our own generator: object extent and
  brightness, an independent renderer's test sequences.
* ``real_preset`` -- the ``real`` preset's candidate data trained to their plateau, across
  working stretches; ``preset_choice`` compares candidates on every validation split;
  ``realism`` tells simulated inputs from measured ones.
* ``csa`` -- CSA's prior weight chosen on simulated validation sequences
  (``help-fixes.patch``: two command-line help texts corrected, ``--tau-rel``'s default and
  ``--synthetic``'s; to be applied with the next rerun of the measured protocol, whose
  results files their code digests stale).
* ``ablations`` (the paper's Table 2), ``table1`` (Table 1 over seeds at a fixed step count),
  ``temporal_probe`` (does Ours read its neighbours), ``time_to_plateau`` and
  ``stopping_replay`` (how long to train, when to stop).

Still elsewhere: the measured-scan protocol (``experiments.studies.real_undersampling``) and the
alignment stage (``experiments.studies.align``), which move with their next rerun (their code fixes the
scans' folder from the file's own place, and a move stales their results); and in
``benchmarks/`` the trade-off study, which measures speed against accuracy of every
reconstruction knob beside the other performance benchmarks.
"""

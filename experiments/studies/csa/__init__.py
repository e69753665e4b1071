"""CSA's prior weight chosen on simulated validation sequences, never on measured scans.

    python -m experiments.studies.csa                 # -> experiments/studies/csa/results/csa_choice.md
    python -m experiments.studies.csa --sequences 8 --frames 1 4 6 --tau 0.05 0.1 0.2

The ``real`` preset's validation split (the first ``--sequences`` sequences,
simulated into the store by ``python -m experiments.make_dataset`` when absent:
about 15 s a sequence) is under-scanned at the measured protocol's strides (4:
16 x 16, 8: 8 x 8 of 64 x 64) and reconstructed by
:func:`nlosjax.physics.methods.csa.csa` on the masked scan at each ``--tau``
(``tau_rel``), and by the classic methods on the interpolated scan, as
``experiments.studies.real_undersampling`` does. Intensity PSNR against the simulator's
ground truth, mean and 95 % interval over sequences (:mod:`nlosjax.stats`);
the chosen ``tau_rel`` per stride is the best mean, and the measured protocol
(``experiments.studies.real_undersampling.protocol.CSA_TAU_REL``) takes it.
"""

"""nlosjax: confocal non-line-of-sight imaging in JAX.

The library: ``physics`` (Setup, forward model, SPAD noise, classic reconstructions),
``ssm`` (selective-scan kernels, the Mamba mixer), ``models`` (ST-Mamba and the learned
baselines), ``losses``, ``metrics``, ``stats`` (intervals), ``data`` (measured formats,
the simulator and datasets), ``train`` (typed run config, resumable training), ``plan``
(the dry run), ``evaluation`` (the protocol), ``inference`` / ``pretrained`` (trained and
shipped weights on any capture), ``adaptation`` (fit a network to one capture) and
``variants`` (the learned models by name). The application that trains and evaluates is
``experiments``; it takes typed arguments from here, never the other way round.
"""

__version__ = "0.1.0"

"""The classic reconstructions, one module per method (dispatch: :mod:`nlosjax.physics.reconstruct`).

    lct      light-cone transform; ``_lct_problem``, the cached LCT operators
    fbp      filtered backprojection (LCT backprojection, ``-LoG``)
    fk       f-k (Stolt) migration
    phasor   phasor-field virtual wave (wavelet folded into the LCT operators)
    rsd      Rayleigh-Sommerfeld diffraction of the phasor field (NUFFT depth sum)
    csa      compressed sensing of a masked scan: FISTA on the LCT model (iterative)

Imports among them run one way: ``fbp`` and ``phasor`` import ``lct``; ``fk``,
``rsd`` and ``csa`` import no other method. What each method does differently from
the public reference code is in the docstring of
:mod:`nlosjax.physics.reconstruct`, which re-exports the six functions.
"""

"""nlosjax: confocal non-line-of-sight imaging in JAX.

Subpackages: ``nlosjax.physics`` (Setup, forward model, SPAD noise, classic
reconstructions), ``nlosjax.metrics`` (PSNR, SSIM, RMSE, MAD), ``nlosjax.data``
(measured formats and datasets).
"""

__version__ = "0.1.0"

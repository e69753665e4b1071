"""Confocal NLOS physics: capture geometry, forward model, SPAD noise, classic reconstructions.

Public API::

    Setup                      frozen capture geometry (metres, seconds, bins)
    render, render_points      albedo volume -> noise-free transient (fast LCT form; brute force)
    add_spad_noise             SPAD detector model (paper Eq. 2)
    reconstruct                transient -> volume with "fbp" | "lct" | "fk" | "phasor" | "rsd" | "csa"
    fbp, lct, fk, phasor, rsd, csa   the same methods as plain functions (csa: iterative)
    illumination_wavelet       the phasor-field wavelet P(t) for a Setup
    intensity_depth            volume -> intensity image [0, 1] and depth map (metres)
    checked                    jit a function with its input checks compiled in (``checks``)
    estimate_depth_range       (z_min, z_max) of a capture's scene; auto_depth_range: gated Setup
"""

from nlosjax.physics.checks import checked
from nlosjax.physics.depth_range import auto_depth_range, estimate_depth_range
from nlosjax.physics.forward import render, render_points
from nlosjax.physics.noise import add_spad_noise, expected_counts, jitter_kernel
from nlosjax.physics.project import intensity_depth
from nlosjax.physics.reconstruct import ITERATIVE_METHODS, METHODS, csa, fbp, fk, lct, phasor, reconstruct, rsd
from nlosjax.physics.setup import SPEED_OF_LIGHT, Setup
from nlosjax.physics.wavelet import Wavelet, convolve_time, illumination_wavelet

__all__ = [
    "Setup", "SPEED_OF_LIGHT", "render", "render_points", "add_spad_noise", "expected_counts",
    "jitter_kernel", "reconstruct", "METHODS", "ITERATIVE_METHODS", "csa", "fbp", "lct", "fk", "phasor", "rsd",
    "illumination_wavelet", "Wavelet", "convolve_time", "intensity_depth", "checked",
    "estimate_depth_range", "auto_depth_range",
]

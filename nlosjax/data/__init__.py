"""Measured NLOS data: format readers and the shipped scan.

``load_measurement(path, ...) -> (transient [T, H, W] float32, Setup)`` reads a
measured confocal scan (now: the O'Toole et al. 2018 ``lct_mat`` MATLAB v5
files); ``shipped_scan_path()`` locates the exit-sign scan shipped in
``experiments/data/``.
"""

from nlosjax.data.io import detect_format, load_measurement, shipped_scan_path

__all__ = ["detect_format", "load_measurement", "shipped_scan_path"]

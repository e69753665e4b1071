"""Measured NLOS data: format readers and the shipped scan.

``load_measurement(path, ...) -> (transient [T, H, W] float32, Setup)`` reads a
measured confocal scan (O'Toole LCT, Stanford f-k, NLOST, nlosjax HDF5; see
:mod:`nlosjax.data.io`); ``save_capture`` writes the nlosjax single-capture
layout; ``shipped_scan_path()`` locates the exit-sign scan shipped in
the package (``nlosjax/data/scans/``).
"""

from nlosjax.data.io import detect_format, load_measurement, save_capture, shipped_scan_path

__all__ = ["detect_format", "load_measurement", "save_capture", "shipped_scan_path"]

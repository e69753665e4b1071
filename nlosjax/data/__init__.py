"""NLOS data: measured formats and the shipped scans, and the simulator of dynamic scenes and its datasets.

``load_measurement(path, ...) -> (transient [T, H, W] float32, Setup)`` reads a
measured confocal scan (O'Toole LCT, Stanford f-k, NLOST, nlosjax HDF5; see
:mod:`nlosjax.data.io`); ``save_capture`` writes the nlosjax single-capture
layout; ``shipped_scan_path(name)`` locates a scan shipped in the package
(``nlosjax/data/scans/``: the exit sign, the default, and ``s_u``). ``scenes``
(procedural dynamic scenes), ``surfaces`` (their surfaces as patches) and ``dataset``
(the simulator, its HDF5 files and the training loader) make the synthetic data.
"""

from nlosjax.data.io import detect_format, load_measurement, save_capture, shipped_scan_path

__all__ = ["detect_format", "load_measurement", "save_capture", "shipped_scan_path"]

"""Benchmarks of nlosjax against NumPy/SciPy twins of the public reference code."""

"""Performance benchmarks: kernels, physics, compilation, memory, the main job's time, the device run,
beside NumPy/SciPy twins of the public reference code; and the index of every results file
(``benchmarks/results/`` for performance, each study's own ``results/`` folder for its findings;
``python -m benchmarks.index``). The studies are in ``experiments/studies``."""

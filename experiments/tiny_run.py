"""A tiny training run: the cpu preset shrunk to seconds, for the tests and smoke runs (``--tiny``)."""

from experiments import configs
from nlosjax.data.scenes import params as scene_params
from nlosjax.variants import OURS, USM

# 16 x 16 capture, every 4th point in (4 x 4), 64 bins of 264 ps; a model a few thousand parameters big.
# The cpu preset's first data recipe: the light-cone renderer, 1e3-1e4 photons, and the
# scene options added since at their defaults (helix motion, no spin, albedo 0.5-1). The
# training and dataset tests' margins were measured there; the transport renderer the preset
# uses is tested against its own brute-force loop in tests/test_transport.py.
LCT_DATA = dict(renderer="lct", retroreflective=0.0, photons=(1e3, 1e4))
LCT_SCENE = dict(scene_params._LATER_FIELDS)
TINY_DATA = dict(grid=16, num_bins=64, bin_width=264e-12, frames=4, input_stride=4, input_offset=2,
                 num_sequences={"train": 2, "val": 1, "test": 1}, render_batch=4, **LCT_DATA)
# conv_impl="fold": at these widths "auto" would pick the unrolled "direct" sums for every
# convolution (the cpu preset: only the refinement's), and the train step would compile 1.3-1.6x
# slower; tests/test_conv_impl.py checks "direct" against "fold", values and gradients.
TINY_MODEL = dict(width=4, d_state=2, extract_time_stride=2, extract_blocks=1, st_depth=1,
                  cross_depth=1, spread_min_width=1, volume_features=1, refine_width=2,
                  conv_impl="fold")
#: USM (the "usm" variant) at the same scale.
TINY_USM = dict(trn_width=2, trn_kernels=(3, 9), fusion_widths=(), extract_width=1,
                refine=((2, 3), (2, 3)), render_widths=(2, 2))


def tiny_config(data_path, **train):
  """The CPU preset shrunk to TINY_DATA / TINY_MODEL, 4 steps of batch 2 unless ``train`` overrides."""
  cfg = configs.get_config("cpu")
  cfg["data"].update(TINY_DATA, path=str(data_path))
  cfg["data"]["scene"] = {**cfg["data"]["scene"], **LCT_SCENE}
  cfg["model"] = dict(TINY_MODEL)
  cfg[USM] = {"recipe": OURS, "model": dict(TINY_USM)}
  cfg["train"] = {"steps": 4, "batch_size": 2, "log_every": 1, "checkpoint_every": 2,
                  "eval_batch_size": 2, **train}
  return cfg

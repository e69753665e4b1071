"""The tiny training run of :mod:`experiments.tiny_run`, and its dataset made once per test session."""

from experiments.tiny_run import LCT_DATA, LCT_SCENE, TINY_DATA, TINY_MODEL, TINY_USM, tiny_config
from nlosjax import train as T
from nlosjax.train import RunConfig

__all__ = ["LCT_DATA", "LCT_SCENE", "TINY_DATA", "TINY_MODEL", "TINY_USM", "make_tiny_dataset", "tiny_config"]


def make_tiny_dataset(tmp_path_factory):
  """Generate the tiny dataset in a fresh temporary folder; returns its path."""
  path = tmp_path_factory.mktemp("data") / "tiny.h5"
  T.ensure_dataset(RunConfig.from_dict(tiny_config(path)), path, log=lambda s: None)
  return path

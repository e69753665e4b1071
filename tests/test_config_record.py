"""A model config recorded field by field (``nlosjax.train.config_record``) and the one rule matching it.

Checked against Python's own ``repr`` of the dataclasses (an independent writer of
the same fields), against hand-made records, and through a checkpoint written
with the ``repr`` signature older runs recorded.
"""

import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import optax
import pytest

from nlosjax import losses, train
from nlosjax.models.network import ModelConfig
from nlosjax.models.usm import USMConfig
from nlosjax.physics.setup import Setup
from nlosjax.train import config_record as R

SETUP = Setup(wall_size=2.0, grid=(32, 32), bin_width=132e-12, num_bins=128)
CONFIGS = {
    "cpu": ModelConfig.cpu(SETUP, stride=4, width=8),
    "usm": USMConfig(setup=SETUP, stride=4, trn_kernels=(3, 5, 9), trn_width=2, fusion_widths=(2,)),
    "gated": ModelConfig.cpu(SETUP.with_depth_range(0.2, 1.5), stride=4, physics_variant="public",
                             physics="lct"),
}


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_a_record_is_the_repr_read_field_by_field_and_survives_json(name):
  cfg = CONFIGS[name]
  rec = R.model_record(cfg)
  # Setup's repr leaves out an unset aperture (a field added later), the record does not.
  assert rec["setup"]["aperture"] is None and "aperture" not in repr(cfg)
  assert R.parse_repr(repr(cfg)) == {**rec, "setup": {k: v for k, v in rec["setup"].items() if k != "aperture"}}
  assert json.loads(json.dumps(rec)) == rec
  assert rec["type"] == type(cfg).__name__ and rec["setup"]["type"] == "Setup"
  assert set(rec) - {"type"} == {f.name for f in dataclasses.fields(cfg)}
  assert R.compare(rec, cfg) == ([], []) and R.compare(repr(cfg), cfg) == ([], ["setup.aperture"])


def test_the_rule_names_each_difference_and_passes_fields_a_file_predates_at_their_default():
  cfg = CONFIGS["cpu"]
  rec = R.model_record(cfg)
  older = {k: v for k, v in rec.items() if k not in ("conv_impl", "physics_variant")}
  assert R.compare(older, cfg) == ([], ["conv_impl", "physics_variant"])
  public = dataclasses.replace(cfg, physics_variant="public")
  differ, added = R.compare(older, public)
  assert added == ["conv_impl"] and len(differ) == 1 and differ[0].startswith("physics_variant: not recorded")
  differ, _ = R.compare({**rec, "width": 16}, cfg)
  assert differ == ["width: 16 recorded, 8 now"]
  differ, _ = R.compare({**rec, "setup": {**rec["setup"], "wall_size": 1.0}}, cfg)
  assert differ == ["setup.wall_size: 1.0 recorded, 2.0 now"]
  differ, _ = R.compare({**rec, "removed_field": 3}, cfg)
  assert differ == ["removed_field: recorded (3) but not a field of ModelConfig"]
  differ, _ = R.compare(R.model_record(CONFIGS["usm"]), cfg)
  assert differ == ["type: 'USMConfig' recorded, 'ModelConfig' now"]
  # JSON's numbers: 2 and 2.0 are one value, True is not 1.
  assert R.compare({**rec, "wavelet_cycles": int(cfg.wavelet_cycles)}, cfg)[0] == []
  assert R.compare({**rec, "remat": 0}, cfg)[0] == ["remat: 0 recorded, False now"]


def test_parse_repr_reads_literals_only():
  for text in ("ModelConfig(stride=__import__('os').getpid())", "ModelConfig(4)", "not a repr (",
               "[1, 2]", "ModelConfig(setup=Setup(grid=np.array([1])))"):
    with pytest.raises(ValueError, match="repr"):
      R.parse_repr(text)
  with pytest.raises(ValueError, match="record or a repr"):
    R.as_record(3)
  with pytest.raises(TypeError, match="dataclass"):
    R.model_record({"width": 8})


def test_a_checkpoint_with_the_older_repr_signature_resumes_and_another_config_is_refused(tmp_path):
  """A checkpoint whose signature holds the ``repr`` (less a field added since) resumes under
  the record signature of the same config; another width is refused with the field named."""
  cfg = CONFIGS["cpu"]
  params = {"w": jnp.arange(3.0)}
  state = train.TrainState.create(apply_fn=None, params=params, tx=optax.sgd(0.1))
  mine = train.run_signature(cfg, params, train.OptimConfig(), losses.LossWeights(), 4, 0)
  old = json.loads(mine)
  old["model"] = repr(cfg).replace(", physics_variant='refined'", "")
  writer = train.Checkpointer(tmp_path / "ckpt", json.dumps(old, sort_keys=True), every=1)
  writer.save(state.replace(step=5, params={"w": jnp.arange(3.0) + 1}), 11, force=True)
  writer.close()
  reader = train.Checkpointer(tmp_path / "ckpt", mine, every=1, model=cfg)
  restored, position = reader.restore_latest(state)
  assert int(restored.step) == 5 and position == 11
  np.testing.assert_array_equal(restored.params["w"], [1.0, 2.0, 3.0])
  reader.close()
  wider = dataclasses.replace(cfg, width=16)
  other = train.Checkpointer(tmp_path / "ckpt", train.run_signature(wider, params, train.OptimConfig(),
                                                                    losses.LossWeights(), 4, 0),
                             every=1, model=wider)
  with pytest.raises(ValueError, match=r"model\.width: 8 recorded, 16 now"):
    other.restore_latest(state)
  other.close()
  # Without the model the whole signature must be equal, as before.
  strict = train.Checkpointer(tmp_path / "ckpt", mine, every=1)
  with pytest.raises(ValueError, match="another model config"):
    strict.restore_latest(state)
  strict.close()

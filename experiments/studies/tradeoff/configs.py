"""The study's configurations: what is varied, the learned configurations, the depth ranges.

The knobs (:data:`KNOBS`) and their settings (classic methods, scan-density strides,
exposures), the networks the study trains (:class:`Learned`, :data:`LEARNED`,
:func:`learned_config`), the depth ranges of the time-gating rows (:func:`depth_ranges`,
:func:`gated_setup`), the budgets of ``--quick`` and the full run, and the default paths.
"""

from __future__ import annotations

import dataclasses
import pathlib

from nlosjax.evaluation.baselines import CLASSIC_METHODS
from nlosjax.evaluation.report import METHOD_LABELS
from nlosjax.variants import OURS, OURS_S, USM

DEFAULT_OUT_DIR = pathlib.Path(__file__).resolve().parent / "results"
DEFAULT_WORKDIR = pathlib.Path("runs/tradeoff")
QUICK_STEPS, FULL_STEPS = 150, 300
QUICK_REPEATS, FULL_REPEATS = 9, 15
#: The peak learning rate of every learned configuration (the CPU preset's optimiser otherwise):
#: the preset's when the checkpoints were trained, kept when its main job took the short schedule.
LEARNING_RATE = 1e-3

CLASSIC = CLASSIC_METHODS
LABELS = {m: METHOD_LABELS[m] for m in CLASSIC}
DENSITY_STRIDES = (8, 4, 2, 1)
EXPOSURES = (0.1, 0.3, 1.0, 3.0)
KNOBS = ("method", "density", "exposure", "frames", "model", "kernel", "gating")
GOAL_HALVING = 1.6     # the goal: halving the depth range cuts the time by this much
APERTURE = 0.7         # m: lateral reach of the aperture gating rows (35 degrees off axis at 1 m)


@dataclasses.dataclass(frozen=True)
class Learned:
  """A network configuration trained by this benchmark.

  Attributes:
    name: folder name under ``WORKDIR/s<steps>``.
    label: table label.
    frames: input frames (odd).
    model: ``ModelConfig`` overrides on top of the preset's ``model`` section.
    variant: the main job's variant it is built as (``"usm"``: the preset's
      ``usm`` section and recipe, :func:`nlosjax.train.model_config_for`).
  """

  name: str
  label: str
  frames: int
  model: tuple = ()
  variant: str = OURS


LEARNED = (
    Learned(USM, "USM", 1, variant=USM),
    Learned(OURS_S, "Ours-S", 1),
    Learned(OURS, "Ours", 3),
    Learned("ours_f5", "Ours, 5 frames", 5),
    Learned("ours_w4", "Ours, width 4", 3, (("width", 4),)),
    Learned("ours_w16", "Ours, width 16", 3, (("width", 16),)),
    Learned("ours_d2", "Ours, 2 ST-Mamba blocks", 3, (("st_depth", 2),)),
    Learned("ours_n1", "Ours, N = 1", 3, (("d_state", 1),)),
    Learned("ours_n16", "Ours, N = 16", 3, (("d_state", 16),)),
)
#: The learned methods scored as the classic ones are (at the default capture and at each
#: exposure); the other entries of :data:`LEARNED` vary one knob of Ours.
METHODS_LEARNED = (USM, OURS_S, OURS)


def learned_config(config, setup, spec: Learned):
  """The model config of ``spec`` on ``setup`` (the preset's model section + overrides; USM's own).

  ``config``: a :class:`~nlosjax.train.RunConfig`.
  """
  from nlosjax.models.network import ModelConfig
  if spec.variant == USM:
    from nlosjax.train import model_config_for
    return model_config_for(config, setup, USM)
  kw = {**config.model, **dict(spec.model), "frames": spec.frames}
  return ModelConfig(setup=setup, stride=config.data.stride(), **kw)


def depth_ranges(scene_range: tuple[float, float], max_depth: float,
                 aperture: float | None = None) -> list[tuple[str, tuple | None, float | None]]:
  """``[(label, range, aperture)]``: no range (``full``), its first half (``full/2``), the
  scenes' range ``R``, and the middle half and quarter of ``R``; with ``aperture``, also
  ``R|a`` and ``R/2|a`` (the same ranges with ``Setup.aperture``)."""
  z0, z1 = scene_range
  mid, half = 0.5 * (z0 + z1), 0.5 * (z1 - z0)
  out = [("full", None, None), ("full/2", (0.0, 0.5 * max_depth), None), ("R", (z0, z1), None),
         ("R/2", (mid - half / 2, mid + half / 2), None),
         ("R/4", (mid - half / 4, mid + half / 4), None)]
  if aperture is not None:
    out += [("R|a", (z0, z1), aperture), ("R/2|a", (mid - half / 2, mid + half / 2), aperture)]
  return out


def gated_setup(setup, rng, aperture=None):
  """``setup`` with a depth range (``None``: ungated) and an aperture."""
  su = setup if rng is None else setup.with_depth_range(*rng)
  return su if aperture is None else su.with_aperture(aperture)

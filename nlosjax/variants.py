"""The learned models by name: the one registry of variants that configs, weights and tables use.

Imports nothing (the weights reader, which never imports JAX, reads it). A variant's name is
what ``train.variants`` lists, what a weights folder and a run's model folder are called, and
the row a results table prints under its label.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Variant:
  """One learned model.

  Attributes:
    name: its name in configs, folders and tables (``"ours"``).
    label: its name in tables and figures (``"Ours"``).
    frames: under-scanned frames it reads per output frame (3: the frame and its two neighbours).
    family: the module that builds it: ``"stmamba"`` (:class:`nlosjax.models.STMambaNet`),
      ``"usm"`` (:mod:`nlosjax.models.usm`), ``"lfe"`` (:mod:`nlosjax.models.lfe`) or ``"ik"``
      (:mod:`nlosjax.models.ik`, an approximation of I-K).
  """
  name: str
  label: str
  frames: int
  family: str


#: The variants' names, spelled here only: code that selects a variant names it by these.
OURS, OURS_S, USM, LFE, IK = "ours", "ours_s", "usm", "lfe", "ik"

#: The families (:attr:`Variant.family`), spelled here only: the module that builds a variant.
#: A baseline's family shares its variant's name; both Ours variants are STMamba networks.
FAMILY_STMAMBA, FAMILY_USM, FAMILY_LFE, FAMILY_IK = "stmamba", "usm", "lfe", "ik"

#: Every variant, in order of preference: a run or weights folder read without naming a
#: variant gives the first it holds. Tables print them in the reverse order (baselines first).
VARIANTS = {v.name: v for v in (
    Variant(OURS, "Ours", 3, FAMILY_STMAMBA),        # the paper's method
    Variant(OURS_S, "Ours-S", 1, FAMILY_STMAMBA),   # the paper's single-frame ablation
    Variant(USM, "USM", 1, FAMILY_USM),
    Variant(LFE, "LFE", 1, FAMILY_LFE),
    Variant(IK, "I-K", 1, FAMILY_IK),
)}

#: The paired differences every results table reports, ``(a, b)`` for ``a - b``, where both ran
#: (each variant also against the best classic method).
COMPARISONS = ((OURS, OURS_S), (OURS, USM), (OURS_S, USM), (OURS, LFE), (OURS, IK))


def variant(name: str) -> Variant:
  """The :class:`Variant` called ``name``; ValueError naming the known ones otherwise."""
  if name not in VARIANTS:
    raise ValueError(f"variant must be one of {tuple(VARIANTS)}, got {name!r}")
  return VARIANTS[name]

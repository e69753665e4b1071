"""Deprecated: the old name of :mod:`nlosjax.inference` (restore a trained model for inference).

Importing it warns and gives the same functions; it will be removed.
"""

import warnings

from nlosjax.inference import *  # noqa: F403
from nlosjax.inference import VARIANTS, adapt_to_capture, find_checkpoints, load_run, load_trained  # noqa: F401

warnings.warn("nlosjax.checkpoints_io is now nlosjax.inference", DeprecationWarning, stacklevel=2)

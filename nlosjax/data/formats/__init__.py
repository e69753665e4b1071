"""The measurement formats :func:`nlosjax.data.io.load_measurement` reads, one module per format.

:mod:`~nlosjax.data.formats.registry` holds the registry (``FORMATS``,
``register_format``) and content-based detection;
:mod:`~nlosjax.data.formats._common` the reading helpers every reader shares.
Each format module registers its format when imported:

* :mod:`~nlosjax.data.formats.lct_mat`: ``"lct_mat"`` (O'Toole et al. 2018).
* :mod:`~nlosjax.data.formats.stanford_fk`: ``"stanford_fk"`` (Lindell et al. 2019).
* :mod:`~nlosjax.data.formats.nlost_mat`: ``"nlost_mat"`` (Li et al. 2023, aligned f-k).
* :mod:`~nlosjax.data.formats.capture`: ``"nlosjax_capture"`` and its writer ``save_capture``.
* :mod:`~nlosjax.data.formats.dataset_file`: ``"nlosjax_dataset"`` (nlosjax dynamic dataset).
* :mod:`~nlosjax.data.formats.tal`: ``"tal"`` (y-tal's HDF5 captures, confocal) and its writer ``save_tal``.

Importing this package registers all six. Registration order is detection
order (the first format whose check passes wins), so the imports below keep
it; a new format module is added to them.
"""

# isort: off
from nlosjax.data.formats import lct_mat
from nlosjax.data.formats import stanford_fk
from nlosjax.data.formats import nlost_mat
from nlosjax.data.formats import capture
from nlosjax.data.formats import dataset_file
from nlosjax.data.formats import tal
# isort: on

__all__ = ["capture", "dataset_file", "lct_mat", "nlost_mat", "stanford_fk", "tal"]

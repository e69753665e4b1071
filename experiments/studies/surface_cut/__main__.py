"""``python -m experiments.studies.surface_cut``: runs :func:`experiments.studies.surface_cut.main`."""

import sys

from experiments.studies.surface_cut import main

sys.exit(main())

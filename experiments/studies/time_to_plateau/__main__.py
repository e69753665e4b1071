"""``python -m experiments.studies.time_to_plateau``: runs :func:`experiments.studies.time_to_plateau.main`."""

import sys

from experiments.studies.time_to_plateau import main

sys.exit(main())

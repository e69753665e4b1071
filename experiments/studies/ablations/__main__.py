"""``python -m experiments.studies.ablations``: runs :func:`experiments.studies.ablations.main`."""

import sys

from experiments.studies.ablations import main

sys.exit(main())

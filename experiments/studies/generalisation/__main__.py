"""``python -m experiments.studies.generalisation``: runs :func:`experiments.studies.generalisation.main`."""

import sys

from experiments.studies.generalisation import main

sys.exit(main())

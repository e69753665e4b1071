"""``python -m experiments.studies.mitransient``: runs :func:`experiments.studies.mitransient.main`."""

import sys

from experiments.studies.mitransient import main

sys.exit(main())

"""``python -m experiments.studies.independent_test``: runs :func:`experiments.studies.independent_test.main`."""

import sys

from experiments.studies.independent_test import main

sys.exit(main())

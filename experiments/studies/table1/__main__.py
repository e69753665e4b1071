"""``python -m experiments.studies.table1``: runs :func:`experiments.studies.table1.main`."""

import sys

from experiments.studies.table1 import main

sys.exit(main())

"""``python -m experiments.studies.realism``: runs :func:`experiments.studies.realism.main`."""

import sys

from experiments.studies.realism import main

sys.exit(main())

"""``python -m experiments.studies.temporal_probe``: runs :func:`experiments.studies.temporal_probe.main`."""

import sys

from experiments.studies.temporal_probe import main

sys.exit(main())

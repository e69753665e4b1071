"""``python -m experiments.studies.stopping_replay``: runs :func:`experiments.studies.stopping_replay.main`."""

import sys

from experiments.studies.stopping_replay import main

sys.exit(main())

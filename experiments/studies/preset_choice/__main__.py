"""``python -m experiments.studies.preset_choice``: runs :func:`experiments.studies.preset_choice.main`."""

import sys

from experiments.studies.preset_choice import main

sys.exit(main())

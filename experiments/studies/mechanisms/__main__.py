"""``python -m experiments.studies.mechanisms``."""

import sys

from experiments.studies.mechanisms.cli import main

if __name__ == "__main__":
  sys.exit(main())

"""``python -m benchmarks.physics``."""

import sys

from benchmarks.physics.cli import main

if __name__ == "__main__":
  sys.exit(main())

"""``python -m benchmarks.mechanisms``."""

import sys

from benchmarks.mechanisms.cli import main

if __name__ == "__main__":
  sys.exit(main())

"""``python -m train.pipeline``: `train.pipeline.command.main`."""

import sys

from train.pipeline.command import main

if __name__ == "__main__":
    sys.exit(main())

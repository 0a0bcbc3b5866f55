"""``python -m deepcharuco.calibrate``: the documented entry point of ``deepcharuco calibrate`` (`deepcharuco.cli.calibrate`)."""

import sys

from deepcharuco.cli.calibrate import main

if __name__ == "__main__":
    sys.exit(main())

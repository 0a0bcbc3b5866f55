"""``python -m deepcharuco.detect``: the documented entry point of ``deepcharuco detect`` (`deepcharuco.cli.detect`)."""

import sys

from deepcharuco.cli.detect import main

if __name__ == "__main__":
    sys.exit(main())

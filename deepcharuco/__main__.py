"""``python -m deepcharuco``: the ``deepcharuco`` command (`deepcharuco.cli.main`)."""

import sys

from deepcharuco.cli.main import main

sys.exit(main())

"""``python -m deepcharuco``: the ``deepcharuco`` command (`deepcharuco.command`)."""

import sys

from deepcharuco.command import main

sys.exit(main())

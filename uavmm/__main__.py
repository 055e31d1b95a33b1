"""`python -m uavmm` runs the command line."""

import sys

from uavmm.cli import main

sys.exit(main())

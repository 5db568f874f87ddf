"""`python -m adseismic.cli`: the adseismic command line."""

import sys

from adseismic.cli import main

sys.exit(main())

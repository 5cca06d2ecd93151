"""`python -m ddvs` runs the `ddvs` command."""

import sys

from ddvs.cli import main

sys.exit(main())

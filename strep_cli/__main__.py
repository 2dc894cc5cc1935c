"""``python -m strep_cli ARGS``: the same as ``strep ARGS``."""

import sys

from strep_cli.main import main

sys.exit(main())

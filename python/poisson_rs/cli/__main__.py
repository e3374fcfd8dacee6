"""``python -m poisson_rs.cli``: the ``poisson-rs`` command."""

import sys

from . import main

sys.exit(main())

"""``python -m stage.cli``: the same as the ``stage`` command."""

import sys

from .main import main

sys.exit(main())

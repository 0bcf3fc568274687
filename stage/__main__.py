"""``python -m stage``: the same as the ``stage`` command."""

import sys

from .cli.main import main

sys.exit(main())

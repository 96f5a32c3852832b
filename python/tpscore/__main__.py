"""``python -m tpscore``: the same as the ``tpscore`` command."""
import sys

from .cli import main

sys.exit(main())

"""``python -m tpscore.cli``: the same as the ``tpscore`` command."""
import sys

from .main import main

sys.exit(main())

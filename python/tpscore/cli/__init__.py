"""The ``tpscore`` command line: one module per subcommand family, each a thin layer
over the library's API."""
from __future__ import annotations

from .main import main

__all__ = ["main"]

"""The installed package's version, in one place for the package and its pages."""
from importlib import metadata as _metadata

try:
    __version__ = _metadata.version("tpscore")
except _metadata.PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"

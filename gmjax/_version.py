"""The installed distribution's version (``gmjax.__version__``), read once, below every module that
records it (checkpoints, saved results)."""

from importlib import metadata as _metadata

try:
    __version__ = _metadata.version("gmjax")
except _metadata.PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

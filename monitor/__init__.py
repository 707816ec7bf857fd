"""The feedmon service: CLI, identification workflow, live monitor and sinks."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("feedmon")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+unknown"
